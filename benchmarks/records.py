"""The records file: a record's key, merging new records into old ones, reading ``<out>.json`` and writing
``<out>.json`` with ``<out>.md`` regenerated from it."""

import json
from pathlib import Path
from typing import Any

from benchmarks.tables import render_markdown


def record_key(rec: dict[str, Any]) -> tuple:
    return (rec["scene"], rec["method"], rec["device"], int(rec["steps"]), rec.get("tag") or "")


def merge_records(existing: list[dict[str, Any]], new: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """Records of `existing` whose key no new record has, then the new ones (a later duplicate in `new` wins)."""
    fresh: dict[tuple, dict[str, Any]] = {}
    for r in new:
        fresh[record_key(r)] = r
    kept = [r for r in existing if record_key(r) not in fresh]
    return kept + list(fresh.values())


def load_records(path: Path) -> list[dict[str, Any]]:
    if not path.is_file():
        return []
    data = json.loads(path.read_text())
    return data["records"] if isinstance(data, dict) else data


def write_outputs(records: list[dict[str, Any]], out_prefix: Path) -> tuple[Path, Path]:
    """Write `<out>.json` (sorted records) and `<out>.md` (regenerated from them)."""
    out_prefix = Path(out_prefix)
    out_prefix.parent.mkdir(parents=True, exist_ok=True)
    records = sorted(records, key=lambda r: (r["device"], r["scene"], r["method"], int(r["steps"]), r.get("tag") or ""))
    jpath, mpath = out_prefix.with_suffix(".json"), out_prefix.with_suffix(".md")
    jpath.write_text(json.dumps(records, indent=1, sort_keys=True, default=_json_default) + "\n")
    mpath.write_text(render_markdown(records))
    return jpath, mpath


def _json_default(o):
    if isinstance(o, Path):
        return str(o)
    if hasattr(o, "item"):
        return o.item()
    raise TypeError(f"not JSON serialisable: {type(o).__name__}")
