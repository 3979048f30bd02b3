"""The training-image cache of one rank, whole and sharded: what each rank of a data-parallel run holds in memory.

    python -m benchmarks scale cache --source ../shared/data/reichstag --photos 1000 2000 --ranks 1 2 4 --work /tmp/scale

nerfstudio caches every training image in every process; with several devices willags' ranks decode only their
own share (``--pipeline.data-parallel.shard-image-cache``, willags_ns/engine/distributed.py) and hold a placeholder
of one broadcast value for the others'. For each scale collection (benchmarks/scale.py's :func:`make_collection`)
and each rank count R, a fresh process builds the datamanager of ``willags`` on the CPU exactly as training does
(uint8 images), shards it as rank 0 of R (R = 1: the whole cache, what every rank holds with the sharding off) and
reads the cache: the images it decoded, their bytes (exact), the growth of the process's resident memory while
caching, its peak and the time the caching took. The bytes are the same pinned on a GPU machine's host, where a
collection of over 500 training images keeps its cache. The record goes to
``benchmarks/records/cpu_runs/rank_cache_<source>.json``; docs/scale.md shows it (``python -m benchmarks scale
report``).
"""

from __future__ import annotations

import json
import resource
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

from benchmarks.records import RECORDS_DIR, REPO, json_default, shown_path

RECORD_GLOB = "rank_cache_*.json"
"""The records docs/scale.md reads for its section on the image cache."""


def _resident_bytes() -> int:
    return int(Path("/proc/self/statm").read_text().split()[1]) * resource.getpagesize()


def probe(collection: Path, ranks: int, rank: int = 0) -> dict[str, Any]:
    """Rank `rank` of `ranks`: build willags' datamanager on the CPU, shard its cache (ranks > 1), read the cache."""
    from benchmarks.methods import build_config
    from willags_ns.engine.distributed import is_placeholder, shard_image_cache

    config = build_config("willags", 20, "cpu", Path(collection), None, "default", Path("/tmp/willags-image-cache"))
    dm = config.pipeline.datamanager.setup(device="cpu", test_mode="val", world_size=1, local_rank=0)
    shard_image_cache(dm, rank, ranks)
    before, t0 = _resident_bytes(), time.perf_counter()
    cache = dm.cached_train
    seconds, after = time.perf_counter() - t0, _resident_bytes()
    own = [c["image"] for c in cache if not is_placeholder(c["image"])]
    return {
        "ranks": ranks,
        "train_images": len(cache),
        "decoded": len(own),
        "cache_bytes": sum(im.numel() * im.element_size() for im in own),
        "resident_growth_bytes": after - before,
        "peak_host_bytes": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024,
        "cache_s": round(seconds, 3),
    }


def measure(collection: Path, ranks: int) -> dict[str, Any]:  # (benchmarks/scale.py's `cache` runs it)
    """:func:`probe` in a fresh process (its memory its own)."""
    cmd = [sys.executable, "-m", "benchmarks.rank_cache", "probe", str(collection), str(ranks)]
    done = subprocess.run(cmd, cwd=REPO, capture_output=True, text=True)
    if done.returncode != 0:
        tail = (done.stderr or done.stdout).strip().splitlines()[-1:] or ["(no output)"]
        raise SystemExit(f"benchmarks scale cache: the probe of {collection} with {ranks} ranks failed: {tail[0]}")
    return json.loads(done.stdout.strip().splitlines()[-1])


def write_record(record: dict[str, Any], out: Path | None) -> Path:
    path = Path(out) if out else RECORDS_DIR / "cpu_runs" / f"rank_cache_{record['source']}.json"
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(record, indent=1, default=json_default) + "\n")
    return path


def section(path: Path, record: dict[str, Any]) -> list[str]:
    """docs/scale.md's lines for one record: a row per collection and rank count, each rank count against the whole
    cache of the same collection."""
    gb = 1e9
    lines = [
        "",
        f"## The training-image cache per rank ({record['source']}, CPU)",
        "",
        "What one rank of a data-parallel run holds: the whole cache (1 rank, or any rank with "
        "`--pipeline.data-parallel.shard-image-cache False`) against a rank's share when the cache is sharded "
        "(the default on several devices). Each row a fresh process building `willags`' datamanager and reading "
        "its cache as rank 0 (uint8 images, "
        f"{record['long_side']} px on the long side); the same bytes are pinned on a GPU machine's host past 500 "
        f"training images. Record: `{shown_path(path)}` "
        f"(`{record['command']}`).",
        "",
        "| photos (training) | ranks | images decoded | cache GB | x whole | resident growth GB | process peak GB | "
        "caching s |",
        "|---|---|---|---|---|---|---|---|",
    ]
    whole = {r["photos"]: r for r in record["runs"] if r["ranks"] == 1}
    for r in record["runs"]:
        base = whole.get(r["photos"])
        ratio = f"{r['cache_bytes'] / base['cache_bytes']:.2f}" if base and base["cache_bytes"] else "–"
        lines.append(
            f"| {r['photos']:,} ({r['train_images']}) | {r['ranks']} | {r['decoded']} | {r['cache_bytes'] / gb:.2f} | "
            f"{ratio} | {r['resident_growth_bytes'] / gb:.2f} | {r['peak_host_bytes'] / gb:.2f} | {r['cache_s']:.1f} |"
        )
    return lines


def records() -> list[tuple[Path, dict[str, Any]]]:
    """Every image-cache record, by path."""
    return [(p, json.loads(p.read_text())) for p in sorted(RECORDS_DIR.glob(f"*/{RECORD_GLOB}"))]


if __name__ == "__main__":  # the probe's own process: python -m benchmarks.rank_cache probe COLLECTION RANKS
    if len(sys.argv) != 4 or sys.argv[1] != "probe":
        raise SystemExit("usage: python -m benchmarks.rank_cache probe COLLECTION RANKS")
    print(json.dumps(probe(Path(sys.argv[2]), int(sys.argv[3]))))
