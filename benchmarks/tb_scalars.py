"""Windowed means of a training run's logged scalars (nerfstudio's tensorboard events), one line per tag.

    python -m benchmarks tb-scalars RUN_DIR [--tags psnr,masked_fraction,gaussian_count] [--window 250]

Why: the training PSNR and the mask's share are logged every few steps and are noisy (each step is one photo);
means over windows of steps show a trend, e.g. whether a run keeps fitting its own training views or loses them
(the paper preset on south-building: docs/design.md, the mask's feedback loop). Reads every events file under RUN_DIR, in step order.
"""

import argparse
from collections import defaultdict
from pathlib import Path


def windowed_means(points: list[tuple[int, float]], window: int) -> list[tuple[int, float, int]]:
    """(window start, mean, count) of (step, value) points grouped by step // window, in step order."""
    if window <= 0:
        raise ValueError(f"window must be > 0, got {window}")
    groups: dict[int, list[float]] = defaultdict(list)
    for step, value in points:
        groups[step // window].append(value)
    return [(k * window, sum(v) / len(v), len(v)) for k, v in sorted(groups.items())]


def read_scalars(run_dir: Path) -> dict[str, list[tuple[int, float]]]:
    """Every scalar tag of the events files under `run_dir` -> its (step, value) points, in step order."""
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    files = sorted(run_dir.rglob("events.out.tfevents.*"))
    if not files:
        raise SystemExit(f"tb_scalars: no events file under {run_dir}")
    out: dict[str, list[tuple[int, float]]] = defaultdict(list)
    for f in files:
        acc = EventAccumulator(str(f))
        acc.Reload()
        for tag in acc.Tags().get("scalars", []):
            out[tag].extend((e.step, e.value) for e in acc.Scalars(tag))
    return {tag: sorted(points) for tag, points in out.items()}


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("run_dir", type=Path)
    ap.add_argument("--tags", default="psnr,masked_fraction,gaussian_count", help="substrings of the tags shown")
    ap.add_argument("--window", type=int, default=250, help="steps per window")
    args = ap.parse_args(argv)
    wanted = [t for t in args.tags.split(",") if t]
    for tag, points in read_scalars(args.run_dir).items():
        if not any(w in tag for w in wanted):
            continue
        cells = " ".join(f"{start}:{mean:.3g}" for start, mean, _ in windowed_means(points, args.window))
        print(f"{args.run_dir.name} {tag}: {cells}")


if __name__ == "__main__":
    main()
