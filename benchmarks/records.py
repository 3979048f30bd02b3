"""The records: where they are, a record's key, merging new records into old ones, reading and writing the JSON.

``benchmarks/records/benchmarks.json`` holds the merged records every generated page comes from (docs/benchmarks.md,
docs/curves.md, docs/results.md), ``cv.json`` those of the cross-validation's folds (docs/results.md); ``gpu_runs/`` and ``cpu_runs/`` the files runs brought back, as they wrote them;
``regions/`` the region scores (:mod:`benchmarks.regions`)."""

import functools
import json
import tarfile
from collections.abc import Sequence
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parents[1]
RECORDS_DIR = REPO / "benchmarks" / "records"
"""The one place for run records (outside the package and outside docs/)."""
RECORDS = RECORDS_DIR / "benchmarks.json"
"""The merged records."""
CV_RECORDS = RECORDS_DIR / "cv.json"
"""The merged records of the cross-validation's fold runs (benchmarks/cv.py), apart: each keeps every test photo's
scores."""


def shown_path(path: Path) -> Path:
    """`path` as a page names it: relative to the repository when inside it, else as given."""
    return path.relative_to(REPO) if path.is_relative_to(REPO) else path


def tree_bytes(path: Path) -> int:
    """Bytes of the files under `path`, links not followed (a link costs nothing to carry or store)."""
    return sum(f.stat().st_size for f in Path(path).rglob("*") if f.is_file() and not f.is_symlink())


def record_key(rec: dict[str, Any]) -> tuple:
    return (rec["scene"], rec["method"], rec["device"], int(rec["steps"]), rec.get("tag") or "")


def merge_records(existing: list[dict[str, Any]], new: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """Records of `existing` whose key no new record has, then the new ones (a later duplicate in `new` wins)."""
    fresh: dict[tuple, dict[str, Any]] = {}
    for r in new:
        fresh[record_key(r)] = r
    kept = [r for r in existing if record_key(r) not in fresh]
    return kept + list(fresh.values())


def replaced_across_commits(existing: list[dict[str, Any]], new: list[dict[str, Any]]) -> list[tuple[dict, dict]]:
    """The (old, new) pairs where merging `new` into `existing` replaces a record of another commit: the key holds no
    commit, so the same run at two commits needs two tags to keep both."""
    fresh = {record_key(r): r for r in new}
    return [
        (r, fresh[k])
        for r in existing
        if (k := record_key(r)) in fresh
        and r.get("commit")
        and fresh[k].get("commit")
        and r["commit"] != fresh[k]["commit"]
    ]


def queue_records(archive: Path) -> list[dict[str, Any]]:
    """The records in a queues archive (`benchmarks/remote/solo.sh queues wait` packs every queue's
    `rec/long-<run>.json`, each a list of records, into queues.tgz), in the members' name order."""
    try:
        tf = tarfile.open(archive, "r:gz")
    except (OSError, tarfile.TarError) as e:
        raise SystemExit(f"benchmarks: {archive}: not a queues archive ({e})") from None
    out: list[dict[str, Any]] = []
    with tf:
        for m in sorted(tf.getmembers(), key=lambda m: m.name):
            name = Path(m.name)
            if m.isfile() and name.parent.name == "rec" and name.name.startswith("long-") and name.suffix == ".json":
                data = json.load(tf.extractfile(m))  # type: ignore[arg-type]
                out += data if isinstance(data, list) else [data]
    if not out:
        raise SystemExit(f"benchmarks: {archive} holds no rec/long-*.json records")
    return out


def load_records(path: Path) -> list[dict[str, Any]]:
    if not path.is_file():
        return []
    data = json.loads(path.read_text())
    return data["records"] if isinstance(data, dict) else data


def merged_records(paths: Sequence[Path | str]) -> list[dict[str, Any]]:
    """The records of several files, merged in their order (:func:`merge_records`: a later record wins)."""
    return functools.reduce(lambda records, path: merge_records(records, load_records(Path(path))), paths, [])


def sort_records(records: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """The records in file order: by (device, scene, method, steps, tag)."""
    return sorted(records, key=lambda r: (r["device"], r["scene"], r["method"], int(r["steps"]), r.get("tag") or ""))


def write_records(records: list[dict[str, Any]], path: Path) -> Path:
    """Write the records to `path` in file order (:func:`sort_records`)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(sort_records(records), indent=1, sort_keys=True, default=json_default) + "\n")
    return path


def json_default(o):
    if isinstance(o, Path):
        return str(o)
    if hasattr(o, "item"):
        return o.item()
    raise TypeError(f"not JSON serialisable: {type(o).__name__}")
