"""docs/curves.md and its PNGs from the records (the curves themselves: benchmarks/curves.py): what the records
hold, the time to the peer's 15000-step PSNR, the time-budget knob against the curves, and a table of runs per scene.

    python -m benchmarks curves          # benchmarks/records/benchmarks.json -> docs/curves.md + PNGs
    python -m benchmarks curves --records benchmarks/records/benchmarks.json $OUT/long-*.json \
        --scenes reichstag south-building
"""

import argparse
from collections.abc import Sequence
from pathlib import Path

from benchmarks.curves import (
    CROSSING_METHODS,
    CURVE_METHODS,
    REACHING,
    REAL_SCENES,
    REPO,
    SCENES,
    TARGET_METHOD,
    TARGET_STEPS,
    KnobRun,
    Point,
    StepPoint,
    best_within,
    crossings,
    first_reaching,
    grid_descriptions,
    has_curve,
    knob_runs,
    load_records,
    pareto_flags,
    plot_scene,
    scene_points,
    step_curve,
    step_time,
    time_ratio,
)
from benchmarks.records import RECORDS

MEASURE = (
    "How the points alone on the GPU are measured (`benchmarks/remote/solo.sh`): a queue of runs trained one after "
    "another on one GPU, each scored at its milestones (1k, 2k, 5k, 10k, 15k, 30k up to its steps) right after it "
    "trained, detached, so `wait` can be called again until it is done: `export WILLAGS_COMMIT=<sha>; source benchmarks/remote/env.sh; "
    'SOLO_DATA=.gpu-data bash benchmarks/remote/solo.sh start "reichstag:peer:15000 reichstag:willags:30000 '
    'reichstag:willags:30000:42:5"` then `bash benchmarks/remote/solo.sh wait $OUT 570` in that call and each next '
    "one (`scene:method:steps[:seed[:budget minutes]]`; the last form is a run of the time-budget knob), then "
    "`python -m benchmarks merge <the long-*.json, as one list>` and "
    "`python -m benchmarks curves`."
)
"""How the missing points get measured (printed in the markdown)."""
SPEED_GOAL = 0.5
"""The goal: willags reaches the peer's 15000-step PSNR in at most this fraction of the peer's time."""
KNOB_GOAL_DB = 0.5
"""The knob's goal: its PSNR within this many dB of the best run timed alone within its budget."""
BUDGETS_MIN = (2.0, 5.0, 10.0, 20.0)
"""Budgets (minutes) whose best alone-timed run the markdown lists per scene, with those of the knob's runs."""


def _times(s: StepPoint) -> str:
    if not s.times:
        return "time not recorded"
    lo, hi = s.times[0], s.times[-1]
    return f"{lo:.0f} s" if len(s.times) == 1 else f"{lo:.0f}-{hi:.0f} s ({len(s.times)} runs)"


def _time_cell(s: StepPoint) -> str:
    """The median alone time with its GPU(s), else every timed run's time with its sharing label."""
    t = step_time(s)
    if t is None or not t.alone:
        return f"{_times(s)} [{s.sharing}]"
    median = f"; median of {t.n} runs" if t.n > 1 else ""
    return f"{t.seconds:.0f} s [alone, {', '.join(t.gpus)}{median}]"


def _ratio_and_goal(hit: StepPoint | None, curve: Sequence[StepPoint], target: StepPoint) -> tuple[str, str]:
    """willags' cells: its time over the peer's, and the goal (at most SPEED_GOAL of it)."""
    if not curve:
        return "–", "–"
    if hit is None:
        most = max(s.steps for s in curve)
        if most >= TARGET_STEPS:  # trained at least as long as the peer and still below it
            return "–", "missed (not reached)"
        return "–", f"– (not reached by {most} steps)"
    ratio = time_ratio(hit, target)
    if ratio is None:
        if step_time(hit) is None or step_time(target) is None:
            return "not comparable (time not recorded)", "–"
        return "not comparable (shared-GPU time)", "–"
    gh, gt = step_time(hit).gpus, step_time(target).gpus  # type: ignore[union-attr]
    if gh != gt:
        return f"{ratio:.2f}x ({'/'.join(gh)} vs {'/'.join(gt)})", "– (timed on different GPUs)"
    return f"{ratio:.2f}x", "met" if ratio <= SPEED_GOAL else f"missed ({ratio:.2f}x)"


def _not_held(curve: Sequence[StepPoint], hit: StepPoint, target: StepPoint) -> str:
    """Where a later step count's mean falls below the bar again: the first reaching milestone may be one run's
    noise around it (said in the cell, so that "met" is not read as the method staying above the peer)."""
    below = [s for s in curve if s.steps > hit.steps and s.psnr < target.psnr]
    if not below:
        return ""
    return "; below it again at " + ", ".join(f"{s.steps} steps ({s.psnr:.2f}, n={s.n})" for s in below)


def time_to_target_rows(by_scene: dict[str, list[Point]]) -> list[str]:
    """Markdown: per scene, the peer's 15000-step PSNR and time, where each method first reaches it, and willags' time
    over the peer's (alone-timed runs only) against the goal."""
    first, *others = REACHING
    out = [
        f"| scene | {TARGET_METHOD} at {TARGET_STEPS} steps: PSNR (runs), time | {first}: first reaching it | "
        f"{first} time / {TARGET_METHOD} time | goal (<= {SPEED_GOAL}x) | "
        + " | ".join(f"{m}: first reaching it" for m in others)
        + " |",
        "|---|---|---|---|---|" + "---|" * len(others),
    ]
    for scene, points in by_scene.items():
        ref = [s for s in step_curve(points, TARGET_METHOD) if s.steps == TARGET_STEPS]
        if not ref:
            out.append(f"| {scene} | not measured |" + " – |" * (len(REACHING) + 2))
            continue
        target = ref[0]
        cells = []
        for m in REACHING:
            curve = step_curve(points, m)
            hit = first_reaching(curve, target.psnr)
            not_held = "" if hit is None else _not_held(curve, hit, target)
            if not curve:
                cells.append("not measured")
            elif hit is None:
                best = max(curve, key=lambda s: s.psnr)
                cells.append(f"not reached (best {best.psnr:.2f} at {best.steps} steps)")
            else:
                cells.append(f"{hit.steps} steps, {hit.psnr:.2f} (n={hit.n}), {_time_cell(hit)}{not_held}")
            if m == first:
                ratio, goal = _ratio_and_goal(hit, curve, target)
                if goal == "met" and not_held:
                    goal = "met where first reached, not held"  # it falls below the bar again later
                cells += [ratio, goal]
        out.append(f"| {scene} | {target.psnr:.2f} (n={target.n}), {_time_cell(target)} | " + " | ".join(cells) + " |")
    return out


def crossing_rows(by_scene: dict[str, list[Point]]) -> list[str]:
    """Markdown: every place two methods' mean curves change order, with the seeds each side has there (two seeds
    are wanted where curves cross: a crossing on one seed may be one run's noise)."""
    rows = [
        "| scene | methods | between | ahead before -> after | seeds there | a second seed |",
        "|---|---|---|---|---|---|",
    ]
    for scene, points in by_scene.items():
        for c in crossings(points):
            seeds = ", ".join(f"{m} {n}" for m, n in c.seeds.items())
            todo = "missing: " + ", ".join(m for m, n in c.seeds.items() if n < 2) if c.needs_seed else "have"
            rows.append(
                f"| {scene} | {c.first} / {c.second} | {c.steps[0]} and {c.steps[1]} steps | "
                f"{c.leader[0]} -> {c.leader[1]} | {seeds} | {todo} |"
            )
    if len(rows) == 2:
        return ["No two methods' curves cross in these records."]
    return rows


def _point_cell(p: Point | None, minutes: float) -> str:
    if p is None:
        return f"no run timed alone within {minutes:g} min"
    return f"{p.method}, {p.steps} steps, {p.psnr:.2f}, {p.train_s:.0f} s ({p.gpu})"


def knob_rows(by_scene: dict[str, list[Point]], knobs: dict[str, list[KnobRun]]) -> list[str]:
    """Markdown: each time-budget run against the best run of the curves timed alone within its budget."""
    out = [
        "| scene | budget | GPU (sharing) | the knob's choice: preset, steps trained, train s | its PSNR "
        f"| best run within the budget (timed alone) | knob − best | goal: knob ≥ best − {KNOB_GOAL_DB} dB |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for scene, runs in knobs.items():
        for k in runs:
            best = best_within(by_scene.get(scene, []), k.budget_minutes * 60)
            t = "time not recorded" if k.train_s is None else f"{k.train_s:.0f} s"
            steps = "?" if k.steps is None else str(k.steps)
            diff, goal = "–", "–"
            if k.psnr is not None and best is not None:
                d = k.psnr - best.psnr
                diff = f"{d:+.2f} dB"
                if k.sharing.state != "alone":
                    goal = "not judged (the knob's run did not have the GPU alone)"
                else:
                    goal = "met" if d >= -KNOB_GOAL_DB else f"missed by {-KNOB_GOAL_DB - d:.2f} dB"
            elif best is None:
                goal = "– (no run to compare)"
            out.append(
                f"| {scene} | {k.budget_minutes:g} min | {k.gpu} ({k.sharing.label()}) | {k.preset}, {steps} steps, "
                f"{t} | {'not scored' if k.psnr is None else f'{k.psnr:.2f}'} | "
                f"{_point_cell(best, k.budget_minutes)} | {diff} | {goal} |"
            )
    return out


def best_within_rows(by_scene: dict[str, list[Point]], budgets: Sequence[float]) -> list[str]:
    """Markdown: per scene, the best run timed alone within each budget (minutes)."""
    out = [
        "| scene | " + " | ".join(f"within {b:g} min" for b in budgets) + " |",
        "|---|" + "---|" * len(budgets),
    ]
    for scene, points in by_scene.items():
        out.append(f"| {scene} | " + " | ".join(_point_cell(best_within(points, b * 60), b) for b in budgets) + " |")
    return out


def knob_section(by_scene: dict[str, list[Point]], knobs: dict[str, list[KnobRun]]) -> list[str]:
    budgets = sorted({*BUDGETS_MIN, *(k.budget_minutes for ks in knobs.values() for k in ks)})
    n = sum(len(ks) for ks in knobs.values())
    out = [
        "## The time-budget knob against the curves",
        "",
        "Runs trained under `--pipeline.time-budget-minutes` (the knob chooses the preset and the last step and "
        "compresses the learning-rate schedules to it, so they are no point of their method's curve; a star on the "
        "plot). Each is compared with the best single run of the curves' methods "
        f"({', '.join(CURVE_METHODS)}) timed alone on the GPU within the budget (its train s ≤ budget × 60; runs "
        "timed on a shared GPU, or not timed, are left out; the GPU model may differ from the knob's). The goal: the "
        f"knob within {KNOB_GOAL_DB} dB of that run.",
        "",
    ]
    out += knob_rows(by_scene, knobs) if n else ["No time-budget runs in these records."]
    out += [
        "",
        "The curve side: the best run timed alone within each budget.",
        "",
        *best_within_rows(by_scene, budgets),
    ]
    return out


def scene_table(points: Sequence[Point]) -> list[str]:
    """Markdown rows: every run, its time, GPU, sharing and Pareto mark."""
    flags = pareto_flags(points)
    out = [
        "| method | steps | train s | PSNR | GPU | GPU shared | from | tag | Pareto |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for p, pareto in zip(points, flags, strict=True):
        t = "not recorded" if p.train_s is None else f"{p.train_s:.0f}"
        share = p.sharing.label() + (f" ({p.sharing.why})" if p.sharing.why else "")
        out.append(
            f"| {p.method} | {p.steps} | {t} | {p.psnr:.2f} | {p.gpu} | {share} | {p.source} | {p.tag or '–'} "
            f"| {'*' if pareto else ''} |"
        )
    return out


def render_markdown(
    by_scene: dict[str, list[Point]],
    pngs: dict[str, Path],
    skipped: dict[str, int],
    sources: Sequence[str],
    knobs: dict[str, list[KnobRun]] | None = None,
) -> str:
    knobs = knobs or {}
    out = [
        "# Speed vs accuracy: PSNR against training time",
        "",
        f"Generated by `python -m benchmarks curves` from {', '.join(f'`{s}`' for s in sources)}; do not edit by hand. "
        "Right-half PSNR under the NeRF-W protocol (latent fitted on the left half of each test image). **train s**: "
        "training wall time (set-up and evaluation excluded). **GPU shared**: runs on the GPU at once while this one "
        "trained (`alone`: measured alone; `shared`: a shared-GPU time, longer than the method's own cost; the source "
        "in brackets). Long runs contribute one point per scored milestone; a milestone inside a segment of an older "
        "record has no measured time (`not recorded`) and stays out of the plot and the Pareto marks. `*`: "
        "Pareto-optimal among the timed runs of the scene (no run is both faster and better); shared and alone "
        "times are compared as recorded.",
        "",
        "## What the records hold",
        "",
        "| scene | runs × step counts (timed) | methods: step counts | plot |",
        "|---|---|---|---|",
    ]
    for scene, points in by_scene.items():
        timed = sum(p.train_s is not None for p in points)
        methods = "; ".join(
            f"{m}: {', '.join(str(s) for s in sorted({p.steps for p in points if p.method == m}))}"
            for m in CURVE_METHODS
            if any(p.method == m for p in points)
        )
        plot = (
            f"[curves_{scene}.png]({pngs[scene].name})" if scene in pngs else "none (no method timed at 2 step counts)"
        )
        out.append(f"| {scene} | {len(points)} ({timed}) | {methods or '–'} | {plot} |")
    missing = [m for m in CURVE_METHODS if not any(p.method == m for ps in by_scene.values() for p in ps)]
    if missing:
        out += ["", f"No records of {', '.join(missing)} on these scenes."]
    out += ["", MEASURE]
    if any(skipped.values()):
        out += [
            "",
            "Left out: " + ", ".join(f"{n} {why}" for why, n in skipped.items() if n) + ".",
        ]
    real = ", ".join(s for s in REAL_SCENES if s in by_scene)
    out += [
        "",
        f"## Time to the {TARGET_METHOD}'s {TARGET_STEPS}-step PSNR",
        "",
        "The first step count (in order of steps) whose mean PSNR over its runs reaches the peer's mean at "
        f"{TARGET_STEPS} steps. That mean is over all the peer's {TARGET_STEPS}-step runs: a shared-GPU run's PSNR "
        "counts, only its time does not. PSNR is only measured at milestones (1k, 2k, 5k, 10k, 15k, 30k steps), so "
        "the first reaching milestone's time is an upper bound on the time to the bar. **Times**: the median of the "
        "runs timed alone on the GPU at that step count (`[alone, GPU]`), both for the peer's and for the reaching "
        "point; where no run of it was timed alone, every timed run's time with its sharing (a shared-GPU time, not "
        f"the method's own cost). **{REACHING[0]} time / {TARGET_METHOD} time**: the two alone medians' ratio "
        f"(`not comparable` with a shared-GPU time on either side). **goal**: {REACHING[0]} reaches the bar in at "
        f"most {SPEED_GOAL}x the peer's time on every real scene ({real}); `met` / `missed (ratio)`, `missed (not "
        f"reached)` where it stays below the bar though trained at least {TARGET_STEPS} steps, `–` where it cannot be "
        "judged (no alone time on a side, the two on different GPU models, or not reached in fewer steps).",
        "",
        *time_to_target_rows(by_scene),
        "",
        "## Where the curves cross",
        "",
        f"Consecutive step counts at which two of the compared methods ({', '.join(CROSSING_METHODS)}) were both "
        "scored, with the other one ahead (mean PSNR of the runs at each step count). Two seeds are wanted "
        "there; `seeds there`: the fewest distinct seeds the method has at either of the two step counts.",
        "",
        *crossing_rows(by_scene),
        "",
        *knob_section(by_scene, knobs),
        "",
    ]
    for scene, points in by_scene.items():
        out += [f"## {scene}", ""]
        if scene in pngs:
            out += [f"![{scene}: PSNR vs training time]({pngs[scene].name})", ""]
        out += scene_table(points) + [""] if points else ["No records.", ""]
    return "\n".join(out)


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--records", nargs="+", default=[str(RECORDS)])
    ap.add_argument("--scenes", nargs="+", default=list(SCENES))
    ap.add_argument("--out-dir", default=str(REPO / "docs"), help="where curves_<scene>.png go")
    ap.add_argument("--md", default=None, help="markdown output (default: <out-dir>/curves.md)")
    args = ap.parse_args(argv)
    records = load_records([Path(p) for p in args.records])
    grids = grid_descriptions()
    skipped = {
        "failed runs": sum(r.get("status", "ok") != "ok" for r in records if r.get("scene") in args.scenes),
        "records with a tree_note (not a clean record of their method)": sum(
            bool(r.get("tree_note")) for r in records if r.get("scene") in args.scenes
        ),
    }
    by_scene = {s: scene_points(records, s, grids=grids) for s in args.scenes}
    knobs = {s: knob_runs(records, s, grids=grids) for s in args.scenes}
    out_dir = Path(args.out_dir)
    pngs = {s: plot_scene(pts, out_dir / f"curves_{s}.png", knobs[s]) for s, pts in by_scene.items() if has_curve(pts)}
    md = Path(args.md) if args.md else out_dir / "curves.md"
    sources = [
        str(Path(p).resolve().relative_to(REPO)) if Path(p).resolve().is_relative_to(REPO) else p for p in args.records
    ]
    md.write_text(render_markdown(by_scene, pngs, skipped, sources, knobs) + "\n")
    for s, pts in by_scene.items():
        print(
            f"curves: {s}: {len(pts)} points ({sum(p.train_s is not None for p in pts)} timed)"
            + (f", {len(knobs[s])} time-budget runs" if knobs[s] else "")
            + (f" -> {pngs[s]}" if s in pngs else " (no plot)")
        )
    print(f"curves: {md}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
