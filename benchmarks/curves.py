"""Speed vs accuracy per scene: right-half PSNR against training wall time, from the run records; docs/curves.md and
its PNGs:

    python -m benchmarks curves          # benchmarks/records/benchmarks.json -> docs/curves.md + PNGs
    python -m benchmarks curves --records benchmarks/records/benchmarks.json $OUT/long-*.json \
        --scenes reichstag south-building

Points (one per run and step count) come from long runs (benchmarks/long_run.py), one per scored milestone, and from
grid runs (benchmarks/grid.py), one per record. A milestone's time is its own ``train_s``, or the summed segments
where a segment ended there; a milestone inside a segment of a record without its own time is listed with "time not
recorded" and left out of the plot and the Pareto marks.

Each point says whether its time was measured alone on the GPU or shared with other runs (:func:`gpu_sharing`);
shared-GPU times are longer than the method's own cost, so they are drawn hollow and labelled. Records with a
``tree_note`` (not a clean record of their method) and failed runs are left out (and counted). Runs trained under
willags' time budget (``time_budget_minutes``: the knob chose the preset and the last step and compressed the
learning-rate schedules to it) are no point of their method's curve (docs/benchmarks.md lists them with the long runs),
nor are runs on several devices (``num_devices`` > 1: a step there trains one image per device under schedules divided
by the devices; docs/distributed.md and the several-GPU table of docs/benchmarks.md hold them).

Writes a plot per scene with a curve (a method timed at two step counts or more; :func:`plot_scene`) and docs/curves.md:
what the records hold and every run per scene. PSNR at each step count and at equal training time: docs/results.md.
"""

import argparse
import statistics
from collections.abc import Sequence
from dataclasses import dataclass
from functools import partial
from pathlib import Path
from typing import Any

from benchmarks.methods import configuration
from benchmarks.records import RECORDS, REPO, merged_records
from benchmarks.tables import gpu, md_table

CURVE_METHODS = (
    "willags-lite", "willags", "willags-noprior", "willags-full", "willags-paper", "peer-full", "peer", "splatfacto"
)  # fmt: skip
"""The methods of the curves (benchmarks/methods.py METHODS names; a record's configuration,
benchmarks.methods.configuration: `willags` records from before the default inspected the scene are `willags-full`,
from before its latent prior `willags-noprior`)."""
REAL_SCENES = ("reichstag", "sacre-coeur-mini", "south-building")
SCENES = (*REAL_SCENES, "fox-wild")
"""The curves' scenes: the real photo collections and fox-wild, in this order."""
COLORS = {"willags": "C0", "willags-noprior": "C5", "willags-full": "C9", "willags-lite": "C2", "willags-paper": "C4"}
COLORS.update({"peer": "C1", "splatfacto": "C7"})  # any other method (peer-full) in black


# ---------------------------------------------------------------------------------------------- GPU sharing


@dataclass(frozen=True)
class Sharing:
    """Whether a run's train time was measured alone on its GPU."""

    state: str
    """"alone", "shared" or "unknown"."""
    runs: int | None
    """Most runs on the GPU at once while it trained (itself included), when recorded."""
    why: str
    """Where that comes from (field or note)."""

    def label(self) -> str:
        if self.state == "alone":
            return "alone"
        if self.state == "shared":
            return f"shared, up to {self.runs} runs" if self.runs else "shared, count not recorded"
        return "not recorded"


def gpu_sharing(rec: dict[str, Any]) -> Sharing:
    """How many runs shared the GPU while ``rec`` trained: the most of its ``concurrent_runs`` and its segments'
    (benchmarks/long_run.py and benchmarks/grid.py ``--concurrent``), or the ``gpu_sharing`` it carries (records
    without those fields: what their notes and grid files said)."""
    if rec.get("gpu_sharing"):
        return Sharing(**rec["gpu_sharing"])
    given = {"concurrent_runs": [rec.get("concurrent_runs")]}
    given["segments"] = [seg.get("concurrent_runs") for seg in rec.get("segments") or []]
    counts = {k: [n for n in ns if isinstance(n, int)] for k, ns in given.items()}
    runs = max((n for ns in counts.values() for n in ns), default=None)
    if runs is None:
        return Sharing("unknown", None, "")
    return Sharing("alone" if runs == 1 else "shared", runs, ", ".join(k for k, ns in counts.items() if ns))


# ---------------------------------------------------------------------------------------------- points


@dataclass(frozen=True)
class Point:
    """One run's PSNR at one step count, with the training time it took (None: not recorded)."""

    scene: str
    method: str
    steps: int
    psnr: float
    train_s: float | None
    source: str
    """"grid" or "long run"."""
    tag: str
    gpu: str
    sharing: Sharing
    seed: int = 42
    """The run's seed (records without one ran with the harness's default, 42)."""


def _usable(rec: dict[str, Any]) -> bool:
    return rec.get("status", "ok") == "ok" and not rec.get("tree_note") and int(rec.get("num_devices") or 1) == 1


def milestone_train_s(rec: dict[str, Any], milestone: str) -> float | None:
    """Training seconds to a long run's milestone: its own ``train_s``, else the summed segments that end exactly
    there; None when the milestone lies inside an older record's segment (never interpolated)."""
    own = (rec.get("milestones") or {}).get(milestone, {}).get("train_s")
    if own is not None:
        return float(own)
    total = 0.0
    for seg in rec.get("segments") or []:
        total += float(seg["train_s"])
        if int(seg["end_step"]) + 1 == int(milestone):
            return total
    return None


def scene_points(records: Sequence[dict[str, Any]], scene: str, methods: Sequence[str] = CURVE_METHODS) -> list[Point]:
    """Every measured (method, steps, train time, PSNR) of ``scene`` on the GPU, one per run and step count. Runs
    under the time budget are left out (:func:`is_knob_run`)."""
    out = []
    for r in records:
        method = configuration(r)
        if r.get("scene") != scene or method not in methods or r.get("device") != "cuda" or not _usable(r):
            continue
        if is_knob_run(r):  # a compressed schedule: not its method's curve
            continue
        tag, seed = str(r.get("tag") or ""), int(r.get("seed") or 42)
        point = partial(Point, scene, method, tag=tag, gpu=gpu(r), sharing=gpu_sharing(r), seed=seed)
        if r.get("kind") == "long_run":
            for k, ms in (r.get("milestones") or {}).items():
                if ms.get("psnr") is None:
                    continue
                out.append(point(int(k), float(ms["psnr"]), milestone_train_s(r, k), "long run"))
        elif r.get("psnr") is not None and int(r.get("steps") or 0) > 0:
            t = r.get("train_s")
            out.append(point(int(r["steps"]), float(r["psnr"]), None if t is None else float(t), "grid"))
    return sorted(out, key=lambda p: (methods.index(p.method), p.steps, p.train_s or 0.0))


def pareto_optimal(points: Sequence[tuple[float, float]]) -> list[bool]:
    """For each (seconds, psnr), whether no other point is at least as fast and at least as good, and strictly
    better in one of the two: the one dominance rule of the curves."""
    return [
        not any(j != i and t2 <= t and q2 >= q and (t2 < t or q2 > q) for j, (t2, q2) in enumerate(points))
        for i, (t, q) in enumerate(points)
    ]


def pareto_flags(points: Sequence[Point]) -> list[bool]:
    """For each point, whether it is Pareto-optimal among the timed ones (`pareto_optimal`). Untimed points are never
    optimal."""
    timed = [i for i, p in enumerate(points) if p.train_s is not None]
    flags = pareto_optimal([(points[i].train_s, points[i].psnr) for i in timed])  # type: ignore[misc]
    optimal = dict(zip(timed, flags, strict=True))
    return [optimal.get(i, False) for i in range(len(points))]


@dataclass(frozen=True)
class StepPoint:
    """A method at one step count on a scene: the mean PSNR of its runs and their times."""

    method: str
    steps: int
    psnr: float
    n: int
    times: tuple[float, ...]
    """Measured train seconds of the runs (untimed runs left out)."""
    alone: tuple[float, ...] = ()
    """Train seconds of the runs timed alone on their GPU."""


def step_curve(points: Sequence[Point], method: str) -> list[StepPoint]:
    """``method``'s points grouped by step count, in step order."""
    out = []
    for steps in sorted({p.steps for p in points if p.method == method}):
        ps = [p for p in points if p.method == method and p.steps == steps]
        times = tuple(sorted(p.train_s for p in ps if p.train_s is not None))
        alone = tuple(sorted(p.train_s for p in ps if p.train_s is not None and p.sharing.state == "alone"))
        out.append(StepPoint(method, steps, statistics.mean(p.psnr for p in ps), len(ps), times, alone))
    return out


@dataclass(frozen=True)
class StepTime:
    """The time a step count took: the median of its runs timed alone on the GPU when there are such runs, else of
    all its timed runs (shared-GPU or unrecorded sharing: ``alone`` False)."""

    seconds: float
    alone: bool


def step_time(s: StepPoint) -> StepTime | None:
    """``s``'s time (:class:`StepTime`); None: no run of it was timed."""
    return StepTime(statistics.median(s.alone or s.times), bool(s.alone)) if s.times else None


def has_curve(points: Sequence[Point]) -> bool:
    """A method timed at two step counts or more: something to draw as a curve."""
    by: dict[str, set[int]] = {}
    for p in points:
        if p.train_s is not None:
            by.setdefault(p.method, set()).add(p.steps)
    return any(len(s) >= 2 for s in by.values())


def is_knob_run(rec: dict[str, Any]) -> bool:
    """Whether ``rec`` was trained under the time budget (benchmarks/long_run.py ``--budget-minutes``)."""
    return rec.get("time_budget_minutes") is not None or rec.get("time_budget") is not None


# ---------------------------------------------------------------------------------------------- outputs


def plot_scene(points: Sequence[Point], path: Path) -> Path:
    """PSNR vs minutes (log axis) for one scene: a line per method through its mean PSNR at each step count (at the
    median time of its runs timed alone; dashed through shared-GPU times where fewer than two step counts were timed
    alone), every run a marker (hollow: shared-GPU time), Pareto-optimal runs ringed."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.ticker import FuncFormatter

    fig, ax = plt.subplots(figsize=(9.0, 4.8), dpi=120)
    flags = pareto_flags(points)
    gpus = sorted({p.gpu for p in points if p.train_s is not None})
    shapes = dict(zip(gpus, "os^Dv", strict=False))
    methods = [m for m in CURVE_METHODS if any(p.method == m and p.train_s is not None for p in points)]
    for m in methods:
        color = COLORS.get(m, "k")
        curve = [s for s in step_curve(points, m) if s.times]
        # the line goes through the step counts timed alone (a shared-GPU time is no method's own cost): dashed
        # through every timed one only where fewer than two were timed alone
        alone = [s for s in curve if s.alone]
        curve, style = (alone, "-") if len(alone) >= 2 else (curve, "--")
        xs = [step_time(s).seconds / 60 for s in curve]  # type: ignore[union-attr]
        ax.plot(xs, [s.psnr for s in curve], style, color=color, label=m, lw=1.5)
        for s, x in zip(curve, xs, strict=True):
            label = f"{s.steps // 1000}k" if s.steps >= 1000 else str(s.steps)
            ax.annotate(label, (x, s.psnr), textcoords="offset points", xytext=(4, 4), fontsize=7, color=color)
        for p, pareto in zip(points, flags, strict=True):
            if p.method != m or p.train_s is None:
                continue
            alone = p.sharing.state == "alone"
            ax.plot(p.train_s / 60, p.psnr, shapes.get(p.gpu, "o"), ms=5, color=color, mfc=color if alone else "none")
            if pareto:
                ax.plot(p.train_s / 60, p.psnr, "o", ms=12, mfc="none", mec="k", mew=1.0)
    for g in gpus:
        ax.plot([], [], shapes[g], color="0.4", label=f"run on {g} (filled: alone)")
    ax.plot([], [], "o", color="0.4", mfc="none", label="hollow: shared-GPU time")
    ax.plot([], [], "o", ms=12, mfc="none", mec="k", label="Pareto-optimal run")
    ax.set_xscale("log")
    plain = FuncFormatter(lambda v, _: f"{v:g}")
    ax.xaxis.set_major_formatter(plain)
    ax.xaxis.set_minor_formatter(plain)
    ax.tick_params(axis="x", which="minor", labelsize=7)
    ax.set_xlabel("training wall time (minutes, log scale)")
    ax.set_ylabel("right-half PSNR (dB), NeRF-W protocol")
    scene = points[0].scene if points else "?"
    ax.set_title(
        f"{scene}: PSNR vs training time\n(lines: mean PSNR at each step count, at the median time of its runs timed "
        "alone; dashed: shared-GPU times)",
        fontsize=8,
    )
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.01, 1.0), borderaxespad=0.0)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path)
    plt.close(fig)
    return path


# ---------------------------------------------------------------------------------------------- docs/curves.md


MEASURE = (
    "How the points alone on the GPU are measured (`benchmarks/remote/solo.sh`): a queue of runs trained one after "
    "another on one GPU, each scored at its milestones (1k, 2k, 5k, 10k, 15k, 30k up to its steps) right after it "
    "trained, detached, so `wait` can be called again until it is done: `export WILLAGS_COMMIT=<sha>; source benchmarks/remote/env.sh; "
    'SOLO_DATA=.gpu-data bash benchmarks/remote/solo.sh start "reichstag:peer:15000 reichstag:willags:30000 '
    'reichstag:willags:30000:42:5"` then `bash benchmarks/remote/solo.sh wait $OUT 570` in that call and each next '
    "one (`scene:method:steps[:seed[:budget minutes]]`; the last form trains under the time budget: no point of a "
    "curve, docs/benchmarks.md lists it with the long runs), then "
    "`python -m benchmarks merge <the long-*.json, as one list>` and "
    "`python -m benchmarks curves`."
)
"""How the missing points get measured (printed in the markdown)."""


def scene_table(points: Sequence[Point]) -> list[str]:
    """Markdown rows: every run, its time, GPU, sharing and Pareto mark."""
    rows = []
    for p, pareto in zip(points, pareto_flags(points), strict=True):
        t = "not recorded" if p.train_s is None else f"{p.train_s:.0f}"
        share = p.sharing.label() + (f" ({p.sharing.why})" if p.sharing.why else "")
        rows.append([p.method, str(p.steps), t, f"{p.psnr:.2f}", p.gpu, share, p.source, p.tag or "–", "*" * pareto])
    return md_table(["method", "steps", "train s", "PSNR", "GPU", "GPU shared", "from", "tag", "Pareto"], rows)


def render_markdown(
    by_scene: dict[str, list[Point]], pngs: dict[str, Path], skipped: dict[str, int], sources: Sequence[str]
) -> str:
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
        "times are compared as recorded. Each method's PSNR at each step count and at equal training time: "
        "[results.md](results.md).",
        "",
        "## What the records hold",
        "",
    ]
    rows = []
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
        rows.append([scene, f"{len(points)} ({timed})", methods or "–", plot])
    out += md_table(["scene", "runs × step counts (timed)", "methods: step counts", "plot"], rows)
    missing = [m for m in CURVE_METHODS if not any(p.method == m for ps in by_scene.values() for p in ps)]
    if missing:
        out += ["", f"No records of {', '.join(missing)} on these scenes."]
    out += ["", MEASURE]
    if any(skipped.values()):
        out += ["", "Left out: " + ", ".join(f"{n} {why}" for why, n in skipped.items() if n) + "."]
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
    records = merged_records(args.records)
    asked = [r for r in records if r.get("scene") in args.scenes]
    skipped = {
        "failed runs": sum(r.get("status", "ok") != "ok" for r in asked),
        "records with a tree_note (not a clean record of their method)": sum(bool(r.get("tree_note")) for r in asked),
    }
    by_scene = {s: scene_points(records, s) for s in args.scenes}
    out_dir = Path(args.out_dir)
    pngs = {s: plot_scene(pts, out_dir / f"curves_{s}.png") for s, pts in by_scene.items() if has_curve(pts)}
    md = Path(args.md) if args.md else out_dir / "curves.md"
    sources = [
        str(Path(p).resolve().relative_to(REPO)) if Path(p).resolve().is_relative_to(REPO) else p for p in args.records
    ]
    md.write_text(render_markdown(by_scene, pngs, skipped, sources) + "\n")
    for s, pts in by_scene.items():
        print(
            f"curves: {s}: {len(pts)} points ({sum(p.train_s is not None for p in pts)} timed)"
            + (f" -> {pngs[s]}" if s in pngs else " (no plot)")
        )
    print(f"curves: {md}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
