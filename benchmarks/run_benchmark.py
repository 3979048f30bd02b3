"""Train and evaluate a grid of methods x scenes x step budgets; merge the records into
benchmarks/records/benchmarks.json and regenerate docs/benchmarks.md.

    python -m benchmarks run --grid configs/benchmark_cpu.json
    python -m benchmarks run --grid configs/benchmark_gpu.json                  # adds GPU records
    python -m benchmarks tables                                      # markdown from the JSON
    python -m benchmarks run --grid configs/benchmark_cpu.json --dry-run        # list the runs
    python -m benchmarks merge gpu_out/benchmarks.json                    # fetched records
    python -m benchmarks run --grid configs/benchmark_cpu.json --out /tmp/b     # /tmp/b.json, /tmp/b.md

Each run trains in its own subprocess (see benchmarks/runner.py); records merge into the existing JSON
(same (scene, method, device, steps, tag) replaced, others kept) and the markdown is regenerated after every run.
"""

import argparse
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
if str(REPO) not in sys.path:  # `python benchmarks/run_benchmark.py` from anywhere
    sys.path.insert(0, str(REPO))

from benchmarks.records import RECORDS, load_records, merge_records  # noqa: E402
from benchmarks.runner import run_grid  # noqa: E402
from benchmarks.tables import write_outputs  # noqa: E402


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--grid", type=Path, help="grid JSON (configs/benchmark_cpu.json, configs/benchmark_gpu.json)")
    ap.add_argument(
        "--out",
        type=Path,
        default=RECORDS.with_suffix(""),
        help="output prefix: writes <out>.json and <out>.md (default: benchmarks/records/benchmarks.json, whose "
        "markdown is docs/benchmarks.md)",
    )
    ap.add_argument(
        "--work-dir",
        type=Path,
        default=Path("/tmp/willags-bench"),
        help="per-run folders (spec, log, result; checkpoints with --keep-runs)",
    )
    ap.add_argument("--methods", nargs="*", help="only these methods of the grid")
    ap.add_argument("--scenes", nargs="*", help="only these scenes of the grid (short names: default, fox-wild, ...)")
    ap.add_argument("--dry-run", action="store_true", help="list the runs and exit")
    ap.add_argument("--keep-runs", action="store_true", help="keep each run's checkpoint and config.yml")
    ap.add_argument("--steps", nargs="*", type=int, help="only these step budgets of the grid")
    ap.add_argument(
        "--stop-after-s",
        type=float,
        default=0.0,
        help="start no new run after this many seconds (time-limited machines); 0 = no limit",
    )
    ap.add_argument("--tag", help="override every run's tag (repeats: r1, r2, ...)")
    ap.add_argument("--seed", type=int, help="override every run's seed")
    ap.add_argument("--oracle", action="store_true", help="also score latents fitted on the whole test image")
    ap.add_argument("--render-only", action="store_true", help="regenerate <out>.md from <out>.json and exit")
    ap.add_argument(
        "--merge",
        nargs="*",
        type=Path,
        default=[],
        help="merge the records of these JSON files (e.g. fetched from a GPU run) into <out>.json, "
        "regenerate <out>.md and exit",
    )
    args = ap.parse_args(argv)
    out = args.out if args.out.is_absolute() else Path.cwd() / args.out
    if args.merge:
        recs = load_records(out.with_suffix(".json"))
        for f in args.merge:
            recs = merge_records(recs, load_records(f))
        _, m = write_outputs(recs, out)
        print(f"{len(recs)} records -> {out.with_suffix('.json')}, {m}")
        return 0
    if args.render_only:
        recs = load_records(out.with_suffix(".json"))
        j, m = write_outputs(recs, out)
        print(f"{len(recs)} records -> {m}")
        return 0
    if args.grid is None:
        ap.error("--grid is required (unless --render-only)")
    command = "python -m benchmarks run " + " ".join(sys.argv[1:] if argv is None else argv)
    run_grid(
        args.grid,
        out,
        args.work_dir,
        args.methods,
        args.scenes,
        args.dry_run,
        args.keep_runs,
        command,
        stop_after_s=args.stop_after_s,
        only_steps=args.steps,
        overrides={
            k: v for k, v in (("tag", args.tag), ("seed", args.seed), ("oracle", args.oracle or None)) if v is not None
        },
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
