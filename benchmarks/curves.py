"""Speed vs accuracy per scene: right-half PSNR against training wall time, from the run records. The command that
writes docs/curves.md and the PNGs is benchmarks/curves_report.py:

    python -m benchmarks curves          # benchmarks/records/benchmarks.json -> docs/curves.md + PNGs
    python -m benchmarks curves --records benchmarks/records/benchmarks.json $OUT/long-*.json \
        --scenes reichstag south-building

Points (one per run and step count) come from two kinds of record:

- long runs (``kind: long_run``, benchmarks/long_run.py): one point per scored milestone. Its time is the
  milestone's own ``train_s`` (recorded since long_run measures it) or, in older records, the summed segments when
  the milestone is where a segment ended; a milestone inside an older segment has no measured time: it is listed
  with "time not recorded" and left out of the plot, the Pareto marks and the time-to-quality table;
- grid runs (benchmarks/run_benchmark.py): one point per record (5000 or 15000 steps, a few 1000/2000).

Each point says whether its time was measured alone on the GPU or shared with other runs (:func:`gpu_sharing`,
from the record's ``concurrent_runs``, its segments' ``shared_with`` / ``concurrent_runs``, its notes, and the grid
file's description); shared-GPU times are longer than the method's own cost, so they are drawn hollow and labelled.
Records with a ``tree_note`` (not a clean record of their method) and failed runs are left out (and counted).
Runs trained under willags' time budget (``time_budget_minutes``: the knob chose the preset and the last step and
compressed the learning-rate schedules to it) are no point of their method's curve: they are :class:`KnobRun` s, a star
on the plot and a row of the knob's table (benchmarks/curves_report.py), against the best run timed alone within the
budget (:func:`best_within`).

Writes, per scene with a curve (a method timed at two step counts or more), ``<out-dir>/curves_<scene>.png`` (PSNR vs
minutes, log time axis, a line per method through the mean PSNR at each step count, every run a marker, Pareto-optimal
runs ringed; matplotlib, Agg backend) and one markdown file with a table per scene and the time each method needs to
reach the peer's 15000-step PSNR (the markdown: benchmarks/curves_report.py).
"""

import json
import re
import statistics
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from benchmarks.methods import configuration
from benchmarks.records import merge_records

REPO = Path(__file__).resolve().parents[1]
CURVE_METHODS = ("willags-lite", "willags", "willags-full", "willags-paper", "peer-full", "peer", "splatfacto")
"""The methods of the curves (benchmarks/methods.py METHODS names; a record's configuration,
benchmarks.methods.configuration: `willags` records from before the default inspected the scene are `willags-full`)."""
CROSSING_METHODS = ("willags-lite", "willags", "willags-paper", "peer", "splatfacto")
"""The methods compared by the curves (willags-full, every component without inspection, is drawn but not one of
them): where two of these cross, a second seed is wanted."""
REAL_SCENES = ("reichstag", "sacre-coeur-mini", "south-building")
SCENES = (*REAL_SCENES, "fox-wild")
"""The curves' scenes: the real ones and fox-wild, in this order."""
"""Scenes of real photo collections (the fox scenes are rendered); the default scenes of the curves."""
TARGET_METHOD, TARGET_STEPS = "peer", 15000
"""The quality bar of the time-to-quality table: the peer's mean right-half PSNR at 15000 steps."""
REACHING = ("willags", "willags-full", "willags-lite", "splatfacto", "willags-paper")
"""Methods whose time to that bar the table reports (willags first: the question the table answers)."""
COLORS = {
    "willags": "C0",
    "willags-full": "C9",
    "willags-lite": "C2",
    "willags-paper": "C4",
    "peer": "C1",
    "splatfacto": "C7",
}


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


_COUNT = re.compile(r"((?:\d+(?:-\d+)?(?:, | and ))*\d+(?:-\d+)?) (?:scene )?runs (?:at once|concurrent)")
_OTHERS = re.compile(r"with (\d+) other runs?")
_SHARED_WORDS = ("shared-gpu", "shared the gpu", "concurrent", "at once")
_ALONE_WORDS = ("one after another", "alone")


def grid_descriptions(repo: Path = REPO) -> dict[str, str]:
    """configs/<grid>.json -> its description (which says whether its runs shared the GPU)."""
    out = {}
    for p in sorted((repo / "configs").glob("*.json")):
        try:
            out[f"configs/{p.name}"] = str(json.loads(p.read_text()).get("description", ""))
        except (OSError, ValueError):
            continue
    return out


def gpu_sharing(rec: dict[str, Any], grids: dict[str, str] | None = None) -> Sharing:
    """How many runs shared the GPU while ``rec`` trained, from what the record says.

    Counts: ``concurrent_runs`` (long runs: runs on the GPU while its segment trained), each segment's
    ``concurrent_runs`` or ``shared_with`` + 1, and numbers in its notes ("12, 9 and 3 runs concurrent", "4-5 runs at
    once", "with 6 other runs"); the largest wins. Without a count above 1: words in the notes ("shared-GPU",
    "concurrently" -> shared; "alone", "one after another" -> alone), then the grid file named in ``command``
    (remote/grid.sh grids say their runs are concurrent; the Pareto grid ran one after another).
    """
    counts: list[int] = []
    why: list[str] = []
    if isinstance(rec.get("concurrent_runs"), int):
        counts.append(rec["concurrent_runs"])
        why.append("concurrent_runs")
    for seg in rec.get("segments") or []:
        if isinstance(seg.get("concurrent_runs"), int):
            counts.append(seg["concurrent_runs"])
            why.append("segments")
        elif isinstance(seg.get("shared_with"), int):
            counts.append(seg["shared_with"] + 1)
            why.append("segments")
    text = " ".join(str(rec.get(k) or "") for k in ("note", "run_note"))
    for m in _COUNT.finditer(text):
        counts += [int(n) for n in re.findall(r"\d+", m.group(1))]
        why.append("note")
    for m in _OTHERS.finditer(text):
        counts.append(int(m.group(1)) + 1)
        why.append("note")
    low = text.lower()
    src = ", ".join(dict.fromkeys(why))
    if counts and max(counts) > 1:
        return Sharing("shared", max(counts), src)
    if any(w in low for w in _SHARED_WORDS):
        return Sharing("shared", None, "note")
    if (counts and max(counts) == 1) or any(w in low for w in _ALONE_WORDS):
        return Sharing("alone", 1, src or "note")
    grid = re.search(r"--grid (\S+\.json)", str(rec.get("command") or ""))
    if grid is not None:
        desc = (grids if grids is not None else grid_descriptions()).get(grid.group(1), "").lower()
        if "concurrent" in desc:
            return Sharing("shared", None, f"{grid.group(1)} runs its pairs concurrently")
        if "one after another" in desc:
            return Sharing("alone", 1, f"{grid.group(1)} runs one after another")
    return Sharing("unknown", None, "")


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


def _gpu(rec: dict[str, Any]) -> str:
    machine = str(rec.get("machine") or "")
    name = machine.split("(")[0].replace("NVIDIA", "").split()
    return name[0] if name else "?"


def _seed(rec: dict[str, Any]) -> int:
    seed = rec.get("seed")
    return 42 if seed is None else int(seed)


def _usable(rec: dict[str, Any]) -> bool:
    return rec.get("status", "ok") == "ok" and not rec.get("tree_note")


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


def scene_points(
    records: Sequence[dict[str, Any]],
    scene: str,
    methods: Sequence[str] = CURVE_METHODS,
    grids: dict[str, str] | None = None,
) -> list[Point]:
    """Every measured (method, steps, train time, PSNR) of ``scene`` on the GPU, one per run and step count. Runs
    under the time budget are left out (:func:`knob_runs`)."""
    grids = grid_descriptions() if grids is None else grids
    out, seen = [], set()
    for r in records:
        method = configuration(r)
        if r.get("scene") != scene or method not in methods or r.get("device") != "cuda" or not _usable(r):
            continue
        if is_knob_run(r):  # a compressed schedule: not its method's curve (knob_runs)
            continue
        share, gpu, tag = gpu_sharing(r, grids), _gpu(r), str(r.get("tag") or "")
        if r.get("kind") == "long_run":
            for k, ms in (r.get("milestones") or {}).items():
                if ms.get("psnr") is None:
                    continue
                key = (method, int(k), tag)
                seen.add(key)
                out.append(
                    Point(
                        scene,
                        method,
                        int(k),
                        float(ms["psnr"]),
                        milestone_train_s(r, k),
                        "long run",
                        tag,
                        gpu,
                        share,
                        _seed(r),
                    )
                )
        elif r.get("psnr") is not None and int(r.get("steps") or 0) > 0:
            key = (method, int(r["steps"]), tag)
            if key in seen:  # the same run merged twice (a long run's final milestone and its grid copy)
                continue
            seen.add(key)
            t = r.get("train_s")
            out.append(
                Point(
                    scene,
                    method,
                    int(r["steps"]),
                    float(r["psnr"]),
                    None if t is None else float(t),
                    "grid",
                    tag,
                    gpu,
                    share,
                    _seed(r),
                )
            )
    return sorted(out, key=lambda p: (methods.index(p.method), p.steps, p.train_s or 0.0))


def pareto_optimal(points: Sequence[tuple[float, float]]) -> list[bool]:
    """For each (seconds, psnr), whether no other point is at least as fast and at least as good, and strictly
    better in one of the two. The one dominance rule of the curves and of docs/benchmarks.md's Pareto table."""
    return [
        not any(j != i and t2 <= t and q2 >= q and (t2 < t or q2 > q) for j, (t2, q2) in enumerate(points))
        for i, (t, q) in enumerate(points)
    ]


def pareto_flags(points: Sequence[Point]) -> list[bool]:
    """For each point, whether it is Pareto-optimal among the timed ones (`pareto_optimal`). Untimed points are never
    optimal."""
    timed = [i for i, p in enumerate(points) if p.train_s is not None]
    flags = pareto_optimal([(points[i].train_s, points[i].psnr) for i in timed])  # type: ignore[misc]
    out = [False] * len(points)
    for i, f in zip(timed, flags, strict=True):
        out[i] = f
    return out


@dataclass(frozen=True)
class StepPoint:
    """A method at one step count on a scene: the mean PSNR of its runs and their times."""

    method: str
    steps: int
    psnr: float
    n: int
    times: tuple[float, ...]
    """Measured train seconds of the runs (untimed runs left out)."""
    sharing: str
    """The runs' sharing labels, joined."""
    alone: tuple[tuple[float, str], ...] = ()
    """(train seconds, GPU) of the runs timed alone on their GPU."""


def step_curve(points: Sequence[Point], method: str) -> list[StepPoint]:
    """``method``'s points grouped by step count, in step order."""
    out = []
    for steps in sorted({p.steps for p in points if p.method == method}):
        ps = [p for p in points if p.method == method and p.steps == steps]
        times = tuple(sorted(p.train_s for p in ps if p.train_s is not None))
        labels = " / ".join(dict.fromkeys(p.sharing.label() for p in ps if p.train_s is not None)) or "–"
        alone = tuple(sorted((p.train_s, p.gpu) for p in ps if p.train_s is not None and p.sharing.state == "alone"))
        out.append(StepPoint(method, steps, statistics.mean(p.psnr for p in ps), len(ps), times, labels, alone))
    return out


@dataclass(frozen=True)
class StepTime:
    """The time a step count took: the median of its runs timed alone on the GPU when there are such runs, else of
    all its timed runs (shared-GPU or unrecorded sharing: ``alone`` False)."""

    seconds: float
    alone: bool
    n: int
    """Runs the median is over."""
    gpus: tuple[str, ...]
    """GPU models of the alone runs (empty for a shared time)."""


def step_time(s: StepPoint) -> StepTime | None:
    """``s``'s time (:class:`StepTime`); None: no run of it was timed."""
    if s.alone:
        gpus = tuple(sorted({g for _, g in s.alone}))
        return StepTime(statistics.median(t for t, _ in s.alone), True, len(s.alone), gpus)
    if s.times:
        return StepTime(statistics.median(s.times), False, len(s.times), ())
    return None


def time_ratio(hit: StepPoint, ref: StepPoint) -> float | None:
    """``hit``'s time over ``ref``'s when both were timed alone on the GPU (medians, :func:`step_time`); None:
    one of them has no alone time (a shared-GPU time is no method's own cost)."""
    a, b = step_time(hit), step_time(ref)
    if a is None or b is None or not (a.alone and b.alone):
        return None
    return a.seconds / b.seconds


def first_reaching(curve: Sequence[StepPoint], target: float) -> StepPoint | None:
    """The first step count (in steps) whose mean PSNR reaches ``target``; None: not reached."""
    return next((s for s in curve if s.psnr >= target), None)


@dataclass(frozen=True)
class Crossing:
    """Two methods' mean curves changing order between two step counts both were scored at."""

    first: str
    second: str
    steps: tuple[int, int]
    """The step counts between which the order changes."""
    leader: tuple[str, str]
    """The method ahead at each of the two step counts."""
    seeds: dict[str, int]
    """Per method, the fewest distinct seeds it has at either of the two step counts."""

    @property
    def needs_seed(self) -> bool:
        """Two seeds are wanted where curves cross: True while a side has one."""
        return min(self.seeds.values()) < 2


def crossings(points: Sequence[Point], methods: Sequence[str] = CROSSING_METHODS) -> list[Crossing]:
    """Where two methods' curves (mean PSNR per step count, :func:`step_curve`) cross: consecutive step counts that
    both methods were scored at, with the other method ahead at each. Ties (equal means) are no order."""
    out = []
    curve = {m: {s.steps: s.psnr for s in step_curve(points, m)} for m in methods}  # each method's, once
    for i, a in enumerate(methods):
        for b in methods[i + 1 :]:
            ca, cb = curve[a], curve[b]
            common = [k for k in sorted(ca) if k in cb and ca[k] != cb[k]]
            for lo, hi in zip(common, common[1:], strict=False):
                if (ca[lo] > cb[lo]) == (ca[hi] > cb[hi]):
                    continue
                seeds = {
                    m: min(len({p.seed for p in points if p.method == m and p.steps == k}) for k in (lo, hi))
                    for m in (a, b)
                }
                leader = (a if ca[lo] > cb[lo] else b, a if ca[hi] > cb[hi] else b)
                out.append(Crossing(a, b, (lo, hi), leader, seeds))
    return out


def has_curve(points: Sequence[Point]) -> bool:
    """A method timed at two step counts or more: something to draw as a curve."""
    by: dict[str, set[int]] = {}
    for p in points:
        if p.train_s is not None:
            by.setdefault(p.method, set()).add(p.steps)
    return any(len(s) >= 2 for s in by.values())


# ---------------------------------------------------------------------------------------------- the time-budget knob


@dataclass(frozen=True)
class KnobRun:
    """A run under willags' time budget (``--pipeline.time-budget-minutes``): the knob chose the preset and the last
    step and compressed the learning-rate schedules to it, so it is no point of its method's curve."""

    scene: str
    budget_minutes: float
    preset: str
    """The preset the knob chose."""
    steps: int | None
    """Steps trained (where the knob stopped: the record's ``end_step``)."""
    psnr: float | None
    """Right-half PSNR where it stopped (None: not scored)."""
    train_s: float | None
    gpu: str
    sharing: Sharing
    tag: str


def is_knob_run(rec: dict[str, Any]) -> bool:
    """Whether ``rec`` was trained under the time budget (benchmarks/long_run.py ``--budget-minutes``)."""
    return rec.get("time_budget_minutes") is not None or rec.get("time_budget") is not None


def knob_runs(records: Sequence[dict[str, Any]], scene: str, grids: dict[str, str] | None = None) -> list[KnobRun]:
    """The time-budget runs of ``scene`` on the GPU, by budget: PSNR and train time where the knob stopped."""
    grids = grid_descriptions() if grids is None else grids
    out = []
    for r in records:
        if r.get("scene") != scene or r.get("device") != "cuda" or not _usable(r) or not is_knob_run(r):
            continue
        tb = r.get("time_budget") or {}
        minutes = r.get("time_budget_minutes", tb.get("budget_minutes"))
        end = r.get("end_step") or (tb.get("run") or {}).get("steps_trained")
        at_end = (r.get("milestones") or {}).get(str(end), {}) if end else {}
        psnr = at_end.get("psnr", r.get("psnr"))
        t = milestone_train_s(r, str(end)) if end else None
        if t is None and r.get("train_s") is not None:
            t = float(r["train_s"])
        out.append(
            KnobRun(
                scene,
                float("nan") if minutes is None else float(minutes),
                configuration({**r, "method": (tb.get("choice") or {}).get("preset") or r.get("method")}),
                None if end is None else int(end),
                None if psnr is None else float(psnr),
                t,
                _gpu(r),
                gpu_sharing(r, grids),
                str(r.get("tag") or ""),
            )
        )
    return sorted(out, key=lambda k: (k.budget_minutes, k.tag))


def best_within(points: Sequence[Point], seconds: float) -> Point | None:
    """The best run (highest PSNR, then the faster) of the curves' methods timed alone on the GPU in at most
    ``seconds`` of training; None: no such run."""
    fit = [
        p
        for p in points
        if p.method in CURVE_METHODS and p.sharing.state == "alone" and p.train_s is not None and p.train_s <= seconds
    ]
    return max(fit, key=lambda p: (p.psnr, -(p.train_s or 0.0)), default=None)


# ---------------------------------------------------------------------------------------------- outputs


def plot_scene(points: Sequence[Point], path: Path, knobs: Sequence[KnobRun] = ()) -> Path:
    """PSNR vs minutes (log axis) for one scene: a line per method through its mean PSNR at each step count (at the
    median time of its runs timed alone; dashed through shared-GPU times where fewer than two step counts were timed
    alone), every run a marker (hollow: shared-GPU time), Pareto-optimal runs ringed; each timed
    and scored time-budget run a star in the colour of the preset it chose."""
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
    knob_labels: set[str] = set()
    for k in knobs:
        if k.train_s is None or k.psnr is None:
            continue
        label = f"willags knob, {k.budget_minutes:g} min" + (f" ({k.preset})" if k.preset != "willags" else "")
        color = COLORS.get(k.preset, "k")
        alone = k.sharing.state == "alone"
        ax.plot(
            k.train_s / 60,
            k.psnr,
            "*",
            ms=14,
            color=color,
            mfc=color if alone else "none",
            mec="k" if alone else color,
            mew=0.7,
            label=None if label in knob_labels else label,
        )
        knob_labels.add(label)
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


def load_records(paths: Sequence[Path]) -> list[dict[str, Any]]:
    """Records of several files (each a JSON list); a later record with the same (scene, method, device, steps, tag)
    replaces an earlier one, as benchmarks/harness.py merges them."""
    records: list[dict[str, Any]] = []
    for p in paths:
        data = json.loads(Path(p).read_text())
        records = merge_records(records, data if isinstance(data, list) else [data])
    return records
