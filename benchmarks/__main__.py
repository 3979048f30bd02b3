"""The benchmarks as one tool: ``python -m benchmarks <verb> [its options]`` (``<verb> --help`` for each).

    python -m benchmarks run --grid configs/benchmark_cpu.json     # train and score a grid; records + benchmarks.md
    python -m benchmarks merge gpu_out/records.json                # merge fetched records, regenerate benchmarks.md
    python -m benchmarks report                                    # every generated page from the records
    python -m benchmarks speed --out speed.json                    # the speed suite (GPU)
    python -m benchmarks profile --method willags --data ../shared/data/reichstag --out p.json
    python -m benchmarks multi-gpu run --data .gpu-cv1/reichstag --out $OUT --runs 4,1,2,4:budget1 --gpus 0,1,2,3
    python -m benchmarks collections build lund --out /scenes/lund   # a real photo collection -> a scene
    python -m benchmarks scale run --source ../shared/data/reichstag --photos 100 300 1000 --work /tmp/scale
    python -m benchmarks placement --truth SRC/colmap/sparse/0 --model SCENE/colmap/sparse/0

Each verb runs one module's ``main`` with the rest of the command line; the GPU machine's side is
benchmarks/remote/ (its README).
"""

import importlib
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]

VERBS: dict[str, tuple[str, str]] = {
    "run": ("grid", "train and score a grid of methods x scenes x steps; merge its records"),
    "merge": ("grid", "merge record files into benchmarks/records/benchmarks.json (= run --merge FILES)"),
    "report": (
        "",
        "regenerate every generated page: docs/benchmarks.md, docs/results.md + README, docs/curves.md, docs/scale.md",
    ),
    "tables": ("grid", "regenerate docs/benchmarks.md from the records (= run --render-only)"),
    "results": ("results", "regenerate docs/results.md and README.md's results table"),
    "curves": ("curves", "regenerate docs/curves.md and its plots"),
    "regions": ("regions", "PSNR per region of the test views (the region maps of runs; the region table)"),
    "long-run": ("long_run", "one long run: train (in segments, or under the time budget), score milestones, record"),
    "speed": ("speed", "the speed suite: train step, memory and render timings per variant (GPU)"),
    "profile": ("profile_step", "a window of training steps under torch's profiler"),
    "multi-gpu": ("multi_gpu", "runs on 1-4 GPUs, or under a budget: step breakdown, wall, PSNR, records"),
    "cv": ("cv", "cross-validation: every photo a test photo once (fold folders, GPU queues, tables with intervals)"),
    "scale": ("scale", "Photo-Tourism scale: start-up, memory, steps, ns-eval, a rank's image cache; docs/scale.md"),
    "fingerprint": ("behaviour_fingerprint", "20 CPU training steps: numbers that show a refactor kept behaviour"),
    "placement": ("placement", "an SfM model's cameras against the true poses: registered, placed, errors"),
    "collections": ("collections", "real photo collections: list them, or rebuild one from its public source"),
}
"""verb -> (module under benchmarks/ whose ``main`` it runs, what it does)."""

_FIXED_ARGS = {"merge": ["--merge"], "tables": ["--render-only"]}
"""Options a verb puts in front of the user's."""


def usage() -> str:
    width = max(map(len, VERBS))
    lines = [__doc__.strip(), "", "verbs:"] + [f"  {v:<{width}}  {what}" for v, (_, what) in VERBS.items()]
    return "\n".join(lines)


def _call(verb: str, args: list[str]) -> int:
    """Run the verb's module's main with ``args`` as its command line (argparse reads sys.argv)."""
    sys.argv = [f"benchmarks {verb}", *_FIXED_ARGS.get(verb, []), *args]
    return int(importlib.import_module(f"benchmarks.{VERBS[verb][0]}").main() or 0)


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    if not argv or argv[0] in ("-h", "--help", "help"):
        print(usage())
        return 0 if argv else 2
    verb, rest = argv[0], argv[1:]
    if verb not in VERBS:
        print(f"benchmarks: unknown verb {verb!r}; verbs: {', '.join(VERBS)}", file=sys.stderr)
        return 2
    if str(REPO) not in sys.path:
        sys.path.insert(0, str(REPO))
    if verb != "report":
        return _call(verb, rest)
    if rest:
        print(f"benchmarks report: takes no options, got {' '.join(rest)}", file=sys.stderr)
        return 2
    # in the order each reads the last: benchmarks.md, results.md (+ README), curves.md; scale.md reads its own records
    pages = (("tables", []), ("results", []), ("curves", []), ("scale", ["report"]))
    return next((rc for rc in (_call(v, a) for v, a in pages) if rc), 0)


if __name__ == "__main__":
    sys.exit(main())
