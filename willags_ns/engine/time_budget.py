"""Training under a time budget: which preset, how many steps, and when to stop (`--pipeline.time-budget-minutes`).

Two decisions, both from measurements:

1. **Before training** (:func:`choose`; for ``ns-train willags``: a method named explicitly, willags-lite included,
   keeps its model), from the measured points (``TABLE``, loaded from willags_ns/data/time_budget_points.json): for
   each preset, the steps that fit in the budget at its step time; among the measured points that fit, the one with
   the highest right-half PSNR decides the preset. The run then reproduces that point's resolution schedule
   (splatfacto's stock one on the GPU points, full resolution from the first step on the CPU ones, measured on 128 px
   images: larger training images keep the stock schedule, :func:`full_resolution_suits`). The preset cannot change
   later: willags-lite and willags build different appearance networks.
2. **While training** (:class:`TimeBudget`), from the run's own clock: the wall time of steps 20-70 (after the first
   steps' warm-up: allocations, kernel caches) gives the step time on this machine and scene; the last step is set so
   that the run ends within the budget (never after the preset's own default, nor after ``--max-num-iterations``),
   re-planned every 200 steps and, on one device, every tenth of the budget (steps get slower as densification adds
   Gaussians and the resolution schedule doubles the image size); the step schedules (densification, the mask's
   warm-up) fit into the planned steps, and a plan shorter than SHORT_RUN_STEPS trains at higher learning rates that
   fall to zero over its second half (:func:`short_run_rates`). Should the clock run out first, training stops
   there.

The budget is wall-clock time of the trainer's loop (its periodic evaluation and checkpoints, and any pause in the
viewer, included) from the first step; not the set-up before it (loading and caching images, gsplat's first JIT
compile) nor the final checkpoint.

**Several devices** (``--machine.num-devices N``, several machines too): a step trains N images, one per device, and
every schedule stays counted in steps (docs/distributed.md), so the budget plans steps, as on one device. A measured
point of S steps on one device is reached by S steps on N devices (the same schedules, N times the images), so the
points keep their steps; what differs is the step's cost. Before the run has measured its own, the plan uses the
single-device step time (a data-parallel step costs more: the first plan is optimistic and the measurement at step 70
corrects it). While training, each rank times the distributed step (the wait for the others in the gradient
all-reduce included), and every decision is taken on values the ranks agree on (the largest elapsed time and step
time over the ranks, :func:`agreed_max`), so that every rank stops after the same step: a rank that stopped alone
would leave the others waiting in their next all-reduce. The clock is therefore read against the budget only where
the ranks exchange it: at the plans and every ``AGREE_EVERY`` steps.

**The table** holds what has been measured, nothing else (the data file names every record and says where the runs
come from). Its limits, stated where the choice is printed:

- the PSNR of a point is the NeRF-W protocol's right-half PSNR on one reference scene per device class;
- points of an earlier configuration are in the table (cited) but do not decide (``choose(current_only=True)``):
  their configuration says nothing about the current preset, neither its PSNR nor its step cost;
- GPU step times are of runs alone on one GPU (runs sharing a GPU measure the sharing, not the step);
- ``one_scene``: only one scene has a record of this (configuration, steps, device); the others were measured on
  several (PSNR still from the reference scene).

The records are in benchmarks/records/benchmarks.json (keys: scene, method, device, steps, tag); tests/engine/test_time_budget.py checks
every number of the data file against them.

**In the trainer** (this module's last section; engine/trainer.py calls it from its set-up): the preset switch in
the config before the pipeline is built (:func:`apply_budget`), the TimeBudget's callbacks and plans with the step
schedules fitted into them (:func:`attach_budget`, :func:`schedule_fitter`), the learning rates
(:func:`attach_rates`), the step table of a budgeted run (:class:`BudgetStepTable`) and the record written beside
config.yml (:func:`write_budget_record`).
"""

import copy
import dataclasses
import json
import math
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import torch
from nerfstudio.engine.callbacks import TrainingCallback, TrainingCallbackLocation
from nerfstudio.utils import writer
from nerfstudio.utils.printing import human_format
from nerfstudio.utils.rich_utils import CONSOLE

from willags_ns.engine.checks import WillagsTrainingError

OPTION = "--pipeline.time-budget-minutes"
PRESETS = ("willags-lite", "willags")
"""The presets the budget chooses between, for `ns-train willags`; every other method (willags-lite named explicitly
too) keeps its model and only its step count follows the budget."""
DEFAULT_PRESET = "willags"
"""The method whose preset the budget chooses, and the preset when no point of the current presets was measured on
the device (the best measured configuration)."""

WARMUP_STEPS = 20
"""Steps before the step time is measured (the first steps allocate memory and fill kernel caches)."""
WINDOW_STEPS = 50
"""Steps whose wall time gives the first step-time measurement (steps 20-70 with the warm-up above)."""
REPLAN_EVERY = 200
"""After the first plan, the step time is measured again over each span of this many steps and the plan redone."""
REPRINT_CHANGE = 0.05
"""A re-plan is printed when it moves the last step by more than this fraction (the schedules follow every re-plan)."""
EARLY_SHARE = 0.05
"""Slow steps (one device): the measurement starts once this share of the budget has passed, even before
WARMUP_STEPS, and the first plan comes after another such share (and at least EARLY_MIN_STEPS steps), even before
WINDOW_STEPS: a run whose 70 steps would take half its budget replaces the table's step time by its own after about
two such shares (a 180 s budget of 4.5 s steps: at 27 s, after 6 steps)."""
EARLY_MIN_STEPS = 3
REPLAN_SHARE = 0.1
"""One device: after the first plan, the plan is also redone once this share of the budget has passed since the last
measurement (and at least EARLY_MIN_STEPS steps), even before REPLAN_EVERY steps. Densification makes steps slower
as it goes: planned from an earlier, cheaper span only every REPLAN_EVERY steps, a short budget is stopped by the
clock far before its planned end, its learning rates never decayed and its progress showing half of the run done."""
"""Fewest steps a measurement spans (and fewest steps before it starts)."""
AGREE_EVERY = 50
"""Several devices: steps between two readings of the clock against the budget (each one an exchange of the elapsed
time between the ranks, so that they stop after the same step), besides the readings of the plans."""


class TimeBudgetError(WillagsTrainingError, ValueError):
    """A bad time budget (negative, NaN, infinite, not a number); the message names the option. A WillagsTrainingError, so
    ns-train prints one line instead of a traceback."""


# --------------------------------------------------------------------------------------------------------------------
# the measured table


@dataclass(frozen=True)
class MeasuredPoint:
    """One measured (preset, steps) on a device class: the mean right-half PSNR of its runs on the reference scene."""

    preset: str
    """The preset whose slot this point fills (willags-lite or willags)."""
    device: str
    """Device class: "cuda" or "cpu"."""
    steps: int
    """Training steps of the runs."""
    psnr: float
    """Mean right-half PSNR (NeRF-W protocol) of the runs, in dB."""
    scene: str
    """The reference scene the runs trained on."""
    records: tuple[str, ...]
    """The runs: tags in benchmarks/records/benchmarks.json (scene, measured_as, device, steps, tag)."""
    measured_as: str
    """The method name of the records: the configuration that actually ran."""
    schedule: str
    """"stock": splatfacto's resolution schedule (1/4 resolution to step 3000, 1/2 to 6000, then full); "full": full
    resolution from the first step (the CPU grid's short schedule, images downscaled by the harness)."""
    one_scene: bool
    """Only one scene has a record of (measured_as, steps, device)."""


@dataclass(frozen=True)
class StepTime:
    """Seconds per training step of a preset on a device class, from runs alone on the device."""

    seconds: float
    """train_s / steps of the run(s) below."""
    source: str
    """Where it comes from (scene, method, steps, tag, machine)."""
    measured_as: str
    """The method name of the records (as MeasuredPoint.measured_as)."""


POINTS_FILE = Path(__file__).parents[1] / "data" / "time_budget_points.json"
"""The measured points and step times, with the records that measured them and where those runs come from."""


def load_points(path: Path = POINTS_FILE) -> tuple[tuple[MeasuredPoint, ...], dict[tuple[str, str], StepTime]]:
    """(TABLE, STEP_TIMES) from the data file `path` (its "what", "fields" and "provenance" say what each column means
    and where each number was measured)."""
    data = json.loads(Path(path).read_text())
    points = tuple(MeasuredPoint(**{**p, "records": tuple(p["records"])}) for p in data["points"])
    times = {
        (t["preset"], t["device"]): StepTime(t["seconds"], t["source"], t["measured_as"]) for t in data["step_times"]
    }
    return points, times


TABLE, STEP_TIMES = load_points()
"""TABLE: every measured point the choice uses; STEP_TIMES: seconds per step of each preset on each device class on
one device, before this run has measured its own."""


CPU_SCENE_SIDE = 128
"""Longest image side (px) of the scene the CPU points were measured on (the embedded default scene, 128x96)."""
FULL_RESOLUTION_MAX_SIDE = 2 * CPU_SCENE_SIDE
"""Largest image side (px) for which a CPU choice trains at full resolution from the first step, as its points were
measured; larger images keep splatfacto's resolution schedule (:func:`full_resolution_suits`)."""


def full_resolution_suits(image_side: int) -> bool:
    """Whether full resolution from the first step (how the CPU points were measured, on 128 px images) suits training
    images whose longest side is ``image_side`` px: up to twice the measured scene's side. Larger images keep
    splatfacto's resolution schedule, whose first steps at a quarter of the resolution train far more steps in the
    same minutes (the measurement: docs/design.md, "Measured numbers behind the code")."""
    return image_side <= FULL_RESOLUTION_MAX_SIDE


def device_class(device_type: str) -> str:
    """The table's device class of a torch device type: "cuda", else "cpu" (mps and others: the CPU's table)."""
    return "cuda" if str(device_type).startswith("cuda") else "cpu"


# --------------------------------------------------------------------------------------------------------------------
# the choice before training


def validate_minutes(value: Any) -> float | None:
    """The budget in minutes, or None when it is off (None or 0). Negative, NaN, infinite or non-numbers raise a
    TimeBudgetError naming the option."""
    if value is None:
        return None
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise TimeBudgetError(f"{OPTION} must be a number of minutes (got {value!r})")
    v = float(value)
    if math.isnan(v) or math.isinf(v) or v < 0:
        raise TimeBudgetError(
            f"{OPTION} must be a finite number of minutes >= 0 (got {value!r}; 0 turns the budget off)"
        )
    return v if v > 0 else None


def plan_steps(budget_s: float, elapsed_s: float, steps_done: int, step_s: float, max_steps: int) -> int:
    """How many steps the run should have trained when it stops: those done plus what the rest of the budget affords
    at ``step_s`` seconds per step, at most ``max_steps`` and at least ``steps_done``.

    600 s budget, 100 s elapsed after 1000 steps at 0.05 s/step: 1000 + floor(500 / 0.05) = 11000 (30000 allowed).
    """
    if not step_s > 0:
        raise ValueError(f"step time must be > 0 s (got {step_s})")
    left = max(0.0, budget_s - elapsed_s)
    return int(min(max_steps, max(steps_done, steps_done + math.floor(left / step_s + 1e-9))))


@dataclass(frozen=True)
class BudgetProgress:
    """What the step table shows of a run under a time budget (:func:`budget_progress`)."""

    end_low: int
    """The planned end (exclusive step index), the lower bound while the plan is unsure."""
    end_high: int
    """The upper bound (end_low once the run has measured its own step time)."""
    time_left_s: float
    """Seconds until the run stops: the budget's time left, or less when the plan ends at the step cap first."""
    share: float
    """Share of the run done in time (elapsed / (elapsed + time left)), 0 to 1."""


def budget_progress(
    budget_s: float,
    elapsed_s: float,
    step: int,
    start_step: int,
    end_step: int | None,
    max_steps: int,
    step_times: tuple[float, ...],
) -> BudgetProgress:
    """The progress of a budgeted run after ``step`` (its first step ``start_step``), in time, whose plan ends at
    ``end_step`` (exclusive; None before the run has measured its own step time, when the plan is unsure).

    While unsure, the planned end is a range: the plans at each of ``step_times`` (seconds per step: the table's and
    the run's own so far; one that is unknown, not > 0, stands for the cap). The time left is the budget's (the clock stops the run at the
    latest), unless every plan ends at the step cap before the budget does: then the steps left at the slowest of
    ``step_times``. The share done is the time spent over the time the run takes, so it grows with the clock however
    the plan moves (a share of steps would go backwards when a re-plan moves the end further).

    A 480 s budget after 60 s and 10 steps (table 0.1 s, the run's own 0.5 s, cap 30000): the plans 850 and 4210,
    420 s left, 12.5 % done."""
    done = step - start_step + 1
    left = max(0.0, budget_s - elapsed_s)
    times = [t for t in step_times if t > 0 and math.isfinite(t)]
    if end_step is not None:
        ends = [end_step]
    else:
        ends = [start_step + plan_steps(budget_s, elapsed_s, done, t, max_steps) for t in times]
        if len(times) < len(step_times) or not times:  # a step time not known: the plan may reach the cap
            ends.append(start_step + max_steps)
    low, high = min(ends), max(ends)
    if times and low >= start_step + max_steps:  # every plan stops at the cap, before the clock
        left = min(left, (low - step - 1) * max(times))
    total = elapsed_s + left
    return BudgetProgress(low, high, left, elapsed_s / total if total > 0 else 1.0)


@dataclass(frozen=True)
class BudgetChoice:
    """What the budget decided before training."""

    preset: str
    """willags-lite or willags (or the run's own method when it is not one of the presets)."""
    steps: int
    """Steps planned from the table's step time (replaced once the run has measured its own)."""
    step_s: float
    """The step time the plan used (seconds)."""
    keep_resolution_schedule: bool
    """Keep splatfacto's resolution schedule (else: full resolution from the first step)."""
    point: MeasuredPoint | None
    """The measured point that decided, or None when none fits in the budget."""
    reason: str
    """One line: why this preset and these steps."""
    max_steps: int
    """The cap: the preset's own default step count (or --max-num-iterations when lower)."""


def choose(
    budget_s: float,
    device: str,
    max_steps: Mapping[str, int],
    step_s: Mapping[str, float] | None = None,
    table: tuple[MeasuredPoint, ...] | None = None,
    presets: tuple[str, ...] = PRESETS,
    current_only: bool = True,
) -> BudgetChoice:
    """The preset and the step count for a budget of ``budget_s`` seconds on ``device`` ("cuda" | "cpu").

    A point of the table fits when its steps at its preset's step time (``step_s``: seconds per step by preset;
    default the table's STEP_TIMES) take no longer than the budget (``table``: default TABLE). The fitting point with the highest PSNR picks the
    preset; without one (a budget below every measured point), the preset with the cheapest measured point. Steps: as
    many as the budget affords at that preset's step time, at most ``max_steps[preset]``.

    ``current_only``: only points (and step times) measured with the current configuration of their preset take
    part; those of an earlier configuration (``measured_as`` another method: willags-lite-v0, the paper
    configuration) say nothing about the current preset, neither its PSNR nor its step cost. With no point left, the
    default preset, its own resolution schedule, and no step plan before the run has measured its own step time
    (``step_s`` NaN).
    """
    if not budget_s > 0:
        raise ValueError(f"budget must be > 0 s (got {budget_s})")
    candidates = [p for p in (TABLE if table is None else table) if p.device == device and p.preset in presets]
    stale = sorted({p.measured_as for p in candidates if p.measured_as != p.preset})
    if current_only:
        candidates = [p for p in candidates if p.measured_as == p.preset]
    if step_s is None:
        known = {p: STEP_TIMES[(p, device)] for p in presets if (p, device) in STEP_TIMES}
        step_s = {p: t.seconds for p, t in known.items() if t.measured_as == p or not current_only}
    not_used = f"; points of earlier configurations not used: {', '.join(stale)}" if stale and current_only else ""
    points = [p for p in candidates if p.preset in step_s]
    if not points:
        preset = DEFAULT_PRESET
        own = step_s.get(preset, math.nan)
        steps = max_steps[preset] if math.isnan(own) else plan_steps(budget_s, 0.0, 0, own, max_steps[preset])
        why = (
            f"no point of the current presets measured on {device}{not_used}: the default, its own resolution schedule"
        )
        return BudgetChoice(preset, steps, own, True, None, why, max_steps[preset])

    def cost(p: MeasuredPoint) -> float:
        return p.steps * step_s[p.preset]

    fits = [p for p in points if cost(p) <= budget_s]
    if fits:
        best = max(fits, key=lambda p: (p.psnr, -cost(p)))
        others = [p for p in fits if p.preset != best.preset]
        why = f"best measured PSNR within {budget_s:.0f} s: {_describe(best)} in ~{cost(best):.0f} s"
        if others:
            rival = max(others, key=lambda p: p.psnr)
            why += f" (vs {rival.preset}: {rival.psnr:.2f} dB at {rival.steps} steps)"
        elif len({p.preset for p in points}) > 1:
            why += f" (no other preset has a measured point within {budget_s:.0f} s)"
    else:
        best = min(points, key=cost)
        why = (
            f"no measured point fits in {budget_s:.0f} s (the quickest: {_describe(best)} in ~{cost(best):.0f} s): "
            f"the preset of the quickest, as many steps as fit"
        )
    preset = best.preset
    steps = plan_steps(budget_s, 0.0, 0, step_s[preset], max_steps[preset])
    return BudgetChoice(
        preset=preset,
        steps=steps,
        step_s=step_s[preset],
        keep_resolution_schedule=best.schedule == "stock",
        point=best if fits else None,
        reason=why + not_used,
        max_steps=max_steps[preset],
    )


def fixed_choice(method: str, max_steps: int) -> BudgetChoice:
    """The budget of a method named explicitly (willags-lite, willags-paper, willags-3dgs, ...): its own model and
    resolution schedule; only the step count follows the budget, from the run's own step time."""
    return BudgetChoice(
        preset=method,
        steps=max_steps,
        step_s=math.nan,
        keep_resolution_schedule=True,
        point=None,
        reason=f"kept (the preset is chosen for `ns-train {DEFAULT_PRESET}` only); the steps follow the measured step time",
        max_steps=max_steps,
    )


def _describe(p: MeasuredPoint) -> str:
    as_ = "" if p.measured_as == p.preset else f" (measured as {p.measured_as})"
    return f"{p.preset}{as_}, {p.steps} steps, {p.psnr:.2f} dB on {p.scene}"


def format_choice(
    choice: BudgetChoice, budget_min: float, device: str, notes: list[str] | None = None, num_devices: int = 1
) -> str:
    """The block printed before training: budget, preset and why, the table point, the steps and the schedules (and,
    with several devices, what a step is)."""
    p = choice.point
    src = STEP_TIMES.get((choice.preset, device))
    lines = [
        f"willags time budget: {budget_min:g} min ({budget_min * 60:.0f} s of training steps; set-up not counted)",
        f"  preset:   {choice.preset}: {choice.reason}",
    ]
    if p is not None:
        caveats = [f"runs {', '.join(t or '(untagged)' for t in p.records)}"]
        if p.measured_as != p.preset:
            caveats.append(f"measured as {p.measured_as}, not the current {p.preset}")
        if p.one_scene:
            caveats.append("only one scene measured")
        lines.append(f"  entry:    {p.device} table, {p.scene}: {'; '.join(caveats)}")
    measured = f"this run's own step time over steps {WARMUP_STEPS}-{WARMUP_STEPS + WINDOW_STEPS}"
    if math.isnan(choice.step_s):
        lines.append(f"  steps:    at most {choice.max_steps}, set from {measured}")
    else:
        from_table = f" ({src.source})" if src is not None and math.isclose(src.seconds, choice.step_s) else ""
        lines.append(
            f"  steps:    {choice.steps} planned at {choice.step_s * 1000:.1f} ms/step{from_table}"
            + f"; at most {choice.max_steps}; re-planned from {measured}"
        )
    if choice.point is None and math.isnan(choice.step_s):
        sched = f"{choice.preset}'s own resolution schedule (no measured point to change it)"
    elif choice.keep_resolution_schedule:
        sched = f"splatfacto's resolution schedule kept (the {device} points were measured with it)"
    else:
        sched = f"full resolution from the first step (the {device} points were measured so, on small images)"
    lines.append(f"  schedule: {sched}; the step schedules (densification, mask) fitted into the planned steps")
    lines.append(
        f"  rates:    a plan under {SHORT_RUN_STEPS} steps: {SHORT_RUN_LR_SCALE:g} x the preset's learning rates, "
        f"falling to {COOLDOWN_FLOOR:g} over its last {SHORT_RUN_COOLDOWN:.0%}; a longer one: the preset's"
    )
    if num_devices > 1:
        lines.append(
            f"  devices:  {num_devices}, one image each per step: the steps and every schedule as on one device, with "
            f"{num_devices} times the images; planned first at the one-device step time, then at the measured "
            "data-parallel step (the slowest rank's)"
        )
    lines += [f"  note:     {n}" for n in notes or []]
    return "\n".join(lines)


# --------------------------------------------------------------------------------------------------------------------
# while training


STEP_SCHEDULES = (
    "warmup_length",
    "refine_every",
    "stop_split_at",
    "stop_screen_size_at",
    "reset_alpha_every",
    "mask.warmup_steps",
    "mask.ramp_steps",
)
"""The model's schedules counted in steps (dotted: under pipeline.model) that :func:`fit_schedules` fits into a run
shorter than its preset's. reset_alpha_every counts refinements, the others steps. Two step schedules are not among
them: the resolution schedule (each doubling makes a step four times dearer, and the plan is re-measured at the
resolution trained) and the SH degree's (``sh_degree_interval``): the higher bands are view-dependent colour that a
few hundred steps cannot constrain, and raised within a short run they fit the training views and lose on new ones.
Nor are the learning-rate schedules: a budget keeps the preset's (decayed within a few hundred steps they cost a
short run more than a decibel); a short plan scales them instead and cools them down at its end
(:func:`short_run_rates`; docs/design.md, the time budget)."""
MIN_REFINE_EVERY = 10
"""Fewest steps between two densifications in a fitted schedule (each one judges the gradients gathered since the
last)."""
MIN_RESET_REFINES = 3
"""Fewest densifications between two opacity resets in a fitted schedule: a reset at every densification would
leave none outside the pause that follows each reset."""
SHORT_RUN_STEPS = 2000
"""A run planned shorter than this densifies by the short-run schedule (:func:`short_densification`) instead of the
preset's scaled: scaled, a few hundred steps would split from their tenth step on, on gradients of a scene not yet
fitted, and reset opacities every few dozen steps (docs/design.md, the time budget)."""
SHORT_REFINE_EVERY = 50
"""Steps between two densifications in the short-run schedule (at most; fewer where a run has room for few)."""


def fit_schedules(own: Mapping[str, int], run_steps: int, preset_steps: int) -> dict[str, int]:
    """The step schedules ``own`` (STEP_SCHEDULES -> value, for a run of ``preset_steps``) fitted into a run of
    ``run_steps``: each keeps its share of the run (scaled by r = run_steps / preset_steps, never above 1), so that a
    short budget still densifies, resets opacities and warms up the mask within it.
    refine_every is at least MIN_REFINE_EVERY (or its own value when smaller); the opacity reset keeps its period in
    steps (reset_alpha_every x refine_every x r), counted in the fitted refinements and at least MIN_RESET_REFINES of
    them; a schedule at 0 (off) stays 0. A run shorter than SHORT_RUN_STEPS densifies by :func:`short_densification`.

    willags (30000 steps: warm-up 500, refine every 100, split until 15000, reset every 30 refinements) in 6000
    steps: warm-up 100, refine every 20, split until 3000, reset every 30 refinements (600 steps)."""
    r = min(1.0, max(0, int(run_steps)) / max(1, int(preset_steps)))
    if r >= 1.0:
        return dict(own)
    out = {k: (max(1, round(v * r)) if v > 0 else int(v)) for k, v in own.items()}
    refine = own.get("refine_every", 0)
    if refine > 0 and run_steps < SHORT_RUN_STEPS:
        out.update(short_densification(own, int(run_steps)))
    elif refine > 0:
        out["refine_every"] = max(min(refine, MIN_REFINE_EVERY), round(refine * r))
        if own.get("reset_alpha_every", 0) > 0:
            scaled = round(own["reset_alpha_every"] * refine * r / out["refine_every"])
            out["reset_alpha_every"] = max(min(own["reset_alpha_every"], MIN_RESET_REFINES), scaled)
    return out


def short_densification(own: Mapping[str, int], run_steps: int) -> dict[str, int]:
    """The densification schedule of a run of ``run_steps`` < SHORT_RUN_STEPS (the schedule the CPU points were
    measured with, benchmarks/methods.py ``apply_schedule``): the first split after a sixth of the run, one every
    SHORT_REFINE_EVERY steps (at most ``own``'s period, and at least four within the window), the last at 0.8 of
    the run, and no opacity reset within it. Only the keys ``own`` has.

    600 steps: warm-up 100, refine every 50, split until 480, a reset every 13 refinements (650 steps: never)."""
    run = max(1, int(run_steps))
    warm, stop = max(1, run // 6), max(1, int(0.8 * run))
    every = max(1, min(own["refine_every"], SHORT_REFINE_EVERY, (stop - warm) // 4))
    out = {"warmup_length": warm, "refine_every": every, "stop_split_at": stop}
    if own.get("reset_alpha_every", 0) > 0:
        out["reset_alpha_every"] = run // every + 1
    return {k: v for k, v in out.items() if k in own}


SHORT_RUN_LR_SCALE = 4.0
"""A plan shorter than SHORT_RUN_STEPS trains at this multiple of the preset's learning rates (:func:`short_run_rates`).
The preset's rates are a 30000-step run's: a run of a few hundred steps ends while they are at their first values,
far from what the scene needs (docs/design.md, the time budget)."""
SHORT_RUN_COOLDOWN = 0.5
"""Share of such a plan's last steps over which its learning rates fall linearly to COOLDOWN_FLOOR of their value
(:func:`cooldown_factor`): the run ends settled rather than wherever its last few images pulled it."""
COOLDOWN_FLOOR = 0.0
"""The learning rates' factor at the last step of a cooldown."""


def short_run_rates(run_steps: int) -> tuple[float, float]:
    """(learning-rate scale, cooldown share) of a budgeted run planned for ``run_steps``: SHORT_RUN_LR_SCALE and
    SHORT_RUN_COOLDOWN below SHORT_RUN_STEPS, the preset's own rates (1.0, 0.0) from there on."""
    if run_steps < SHORT_RUN_STEPS:
        return SHORT_RUN_LR_SCALE, SHORT_RUN_COOLDOWN
    return 1.0, 0.0


def validate_rates(scale: Any, cooldown: Any, floor: Any) -> None:
    """The learning-rate switches (``--lr-scale``, ``--lr-cooldown``, ``--lr-cooldown-floor``): a scale > 0 (or None),
    a cooldown share and a floor from 0 to 1 (the share may be None). A bad value raises a TimeBudgetError naming its
    option."""
    for option, value, lo_open, hi, optional in (
        ("--lr-scale", scale, True, math.inf, True),
        ("--lr-cooldown", cooldown, False, 1.0, True),
        ("--lr-cooldown-floor", floor, False, 1.0, False),
    ):
        if value is None and optional:
            continue
        number = isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)
        if not number or value < 0 or value > hi or (lo_open and value == 0):
            bound = "a finite number > 0" if lo_open else f"a number from 0 to {hi:g}"
            raise TimeBudgetError(f"{option} must be {bound} (got {value!r})")


def cooldown_factor(step: int, start_step: int, end_step: int, share: float, floor: float = COOLDOWN_FLOOR) -> float:
    """The factor on every learning rate at ``step`` of a run training steps ``start_step`` to ``end_step - 1``: 1
    until the last ``share`` of the run, then falling linearly to reach ``floor`` at ``end_step`` (so its last step
    still trains). ``share`` 0: always 1.

    Steps 0-999, share 0.3, floor 0: 1 up to step 700, 0.5 at step 850, 0.01 at step 997, 1/300 at step 999."""
    run = end_step - start_step
    if share <= 0 or run <= 0:
        return 1.0
    length = max(1.0, share * run)
    t = (step - (end_step - length)) / length
    if t <= 0:
        return 1.0
    return 1.0 - (1.0 - floor) * min(1.0, t)


def agreed_max(values: list[float]) -> list[float]:
    """The element-wise maximum of `values` over the ranks of the initialised process group (every rank calls it at
    the same step with as many values); the values themselves without a group of several ranks."""
    import torch
    import torch.distributed as dist

    if not (dist.is_available() and dist.is_initialized()) or dist.get_world_size() <= 1:
        return [float(v) for v in values]
    from willags_ns.engine.distributed import comm_device

    t = torch.tensor([float(v) for v in values], dtype=torch.float64, device=comm_device())
    dist.all_reduce(t, op=dist.ReduceOp.MAX)
    return t.tolist()


def several_ranks() -> bool:
    """Whether this process is one rank of an initialised process group of several."""
    import torch.distributed as dist

    return dist.is_available() and dist.is_initialized() and dist.get_world_size() > 1


@dataclass
class TimeBudget:
    """The budget during training: call :meth:`before_step` and :meth:`after_step` around every step (the trainer's
    callbacks do); ``after_step`` says when to stop. ``clock`` and ``sync`` are injectable (tests use a fake clock;
    on CUDA, ``sync`` waits for the device so the clock measures finished work). With several ranks every decision
    is taken on values the ranks agree on (``agree``), read at the same steps on every rank, so that they all stop
    after the same step."""

    budget_s: float
    """The budget in seconds, from the first step on."""
    max_steps: int
    """Never train more steps than this (the preset's default or --max-num-iterations)."""
    start_step: int = 0
    """The first step of this run (> 0 when resumed)."""
    on_plan: Callable[[int], None] | None = None
    """Called with the new end step (exclusive) at every plan: the trainer fits its step schedules into it."""
    log: Callable[[str], None] = print
    clock: Callable[[], float] = time.perf_counter
    sync: Callable[[], None] | None = None
    agree: Callable[[list[float]], list[float]] | None = None
    """Values -> the same values on every rank (their maximum over the ranks: :func:`agreed_max`). None: agreed_max
    when this process is one rank of several (:func:`several_ranks`, read at the first step), else no exchange."""
    warmup_steps: int = WARMUP_STEPS
    window_steps: int = WINDOW_STEPS
    replan_every: int = REPLAN_EVERY
    agree_every: int = AGREE_EVERY
    early_share: float = EARLY_SHARE
    """See EARLY_SHARE; 0 measures only at the step counts."""
    replan_share: float = REPLAN_SHARE
    """See REPLAN_SHARE; 0 re-plans only every replan_every steps."""
    t0: float | None = None
    end_step: int | None = None
    """Planned end (exclusive step index): training stops after step end_step - 1. None until measured."""
    stopped_after: int | None = None
    """The last step trained when the budget stopped training."""
    stop_reason: str = ""
    history: list[dict[str, float]] = field(default_factory=list)
    """Every plan: step, elapsed, measured step time, end step."""
    _mark: tuple[int, float] | None = None

    def before_step(self, step: int) -> None:
        if self.t0 is None:
            self.t0 = self._now()
            if self.agree is None and several_ranks():
                self.agree = agreed_max

    def _now(self) -> float:
        if self.sync is not None:
            self.sync()
        return self.clock()

    def elapsed(self) -> float:
        return 0.0 if self.t0 is None else self.clock() - self.t0

    def after_step(self, step: int) -> bool:
        """Record step ``step`` as done; True when training must stop after it (on every rank at the same step)."""
        if self.t0 is None:
            self.before_step(step)
        t0 = self.t0
        assert t0 is not None
        done = step - self.start_step + 1  # steps trained in this run
        due = (
            (self._mark is None and done == self.warmup_steps)
            or (self.end_step is None and done == self.warmup_steps + self.window_steps)
            or (self.end_step is not None and self._mark is not None and done - self._mark[0] >= self.replan_every)
        )
        if not due and self.agree is None and self.end_step is None and self.early_share > 0:  # slow steps
            early = self.early_share * self.budget_s
            if self._mark is None:
                due = done >= EARLY_MIN_STEPS and self.clock() - t0 >= early
            else:
                due = done - self._mark[0] >= EARLY_MIN_STEPS and self.clock() - self._mark[1] >= early
        if not due and self.agree is None and self.end_step is not None and self._mark is not None:  # steps slow down
            since = self.clock() - self._mark[1]
            due = (
                self.replan_share > 0
                and done - self._mark[0] >= EARLY_MIN_STEPS
                and since >= self.replan_share * self.budget_s
            )
        # with several ranks the clock is held against the budget only where the ranks exchange it
        read = self.agree is None or due or done % self.agree_every == 0
        now = self._now() if due else self.clock()
        elapsed = now - t0
        if due:
            if self._mark is not None and done > self._mark[0]:
                step_s = (now - self._mark[1]) / (done - self._mark[0])
                elapsed, step_s = self._agreed([elapsed, step_s])
                self._plan(step, done, step_s, elapsed)
            else:
                elapsed = self._agreed([elapsed])[0]
            self._mark = (done, now)
        elif read:
            elapsed = self._agreed([elapsed])[0]
        if self.end_step is not None and step + 1 >= self.end_step:
            return self._stop(step, f"reached the planned last step {step}")
        if read and elapsed >= self.budget_s:
            return self._stop(step, f"the clock: {elapsed:.0f} s of {self.budget_s:.0f} s used")
        return False

    def _agreed(self, values: list[float]) -> list[float]:
        return self.agree(values) if self.agree is not None else values

    def _plan(self, step: int, done: int, step_s: float, elapsed: float) -> None:
        total = plan_steps(self.budget_s, elapsed, done, step_s, self.max_steps)
        end = self.start_step + total
        before = self.end_step
        first = before is None
        moved = before is None or abs(end - before) > REPRINT_CHANGE * max(1, before - self.start_step)
        self.end_step = end
        self.history.append({"step": step, "elapsed_s": elapsed, "step_s": step_s, "end_step": end})
        if self.on_plan is not None:
            self.on_plan(end)
        if not moved:
            return
        span = f"steps {self._mark[0] if self._mark else 0}-{done}"
        cap = " (the cap)" if total >= self.max_steps else ""
        verb = "measured" if first else "re-planned: step time now"
        self.log(
            f"willags time budget: {verb} {step_s * 1000:.1f} ms/step ({span}), {elapsed:.0f} s of "
            f"{self.budget_s:.0f} s used -> training stops after step {end - 1}{cap}"
        )

    def _stop(self, step: int, why: str) -> bool:
        self.stopped_after = step
        self.stop_reason = why
        return True

    def summary(self) -> dict[str, Any]:
        """What happened, for time_budget.json."""
        trained = (self.stopped_after + 1 - self.start_step) if self.stopped_after is not None else None
        return {
            "budget_s": self.budget_s,
            "elapsed_s": self.elapsed(),
            "max_steps": self.max_steps,
            "stopped_after_step": self.stopped_after,
            "steps_trained": trained,
            "stop_reason": self.stop_reason,
            "plans": self.history,
        }


# --------------------------------------------------------------------------------------------------------------------
# the budget in nerfstudio's trainer: engine/trainer.py calls these around its set-up and its loop


BUDGET_FILE = "time_budget.json"
"""Written next to config.yml: the choice, the table point, every plan and where training stopped."""


PRESET_CONFIGS: dict[str, Any] = {}
"""method name -> factory of its TrainerConfig, registered by willags_ns/method_configs.py (which builds its methods
on this module's WillagsTrainerConfig, so the trainer must not import it back): the time budget's presets
(PRESETS) and every method's own defaults (a user's auto_config switches are those that differ)."""


def preset_defaults(preset: str) -> tuple[Any, int]:
    """(model config, default step count) of a preset, fresh from its registered factory."""
    if preset not in PRESET_CONFIGS:
        raise KeyError(f"time budget: preset {preset!r} is not registered (import willags_ns.method_configs first)")
    config = PRESET_CONFIGS[preset]()
    return config.pipeline.model, config.max_num_iterations


def carry_overrides(current: Any, base: Any, target: Any) -> list[str]:
    """Copy onto ``target`` every field where ``current`` differs from ``base`` (what the user changed in the preset
    he ran: ``--pipeline.model.backend torch`` survives a switch to the other preset), recursing into nested config
    dataclasses. Returns the dotted names copied."""
    copied = []
    for f in dataclasses.fields(current):
        if f.name == "_target" or not hasattr(target, f.name):
            continue
        a, b = getattr(current, f.name), getattr(base, f.name, None)
        if a == b:
            continue
        sub = getattr(target, f.name)
        if dataclasses.is_dataclass(a) and type(a) is type(b) and type(sub) is type(a):
            copied += [f"{f.name}.{n}" for n in carry_overrides(a, b, sub)]
        else:
            setattr(target, f.name, copy.deepcopy(a))
            copied.append(f.name)
    return copied


def apply_budget(config: Any, budget_s: float) -> tuple[BudgetChoice, list[str], int | None]:
    """Choose the preset and the steps for ``budget_s`` and write them into ``config`` (model, max_num_iterations,
    resolution schedule; the learning-rate schedules stay the preset's). Returns the choice, notes for the
    printed block, and the preset's num_downscales when this set full resolution from the first step in its place
    (None otherwise: kept schedule, or the user's own num_downscales), which the trainer restores for large images."""
    device = device_class(config.machine.device_type)
    method = str(config.method_name)
    notes: list[str] = []
    replaced: int | None = None
    if method != DEFAULT_PRESET:  # a method named explicitly (willags-lite too) keeps its model
        choice = fixed_choice(method, config.max_num_iterations)
    else:
        defaults = {p: preset_defaults(p) for p in PRESETS}
        caps = {p: min(steps, config.max_num_iterations) for p, (_, steps) in defaults.items()}
        choice = choose(budget_s, device, caps)
        base_model = defaults[method][0]
        model: Any = config.pipeline.model  # a WillagsModelConfig (both presets' model)
        if choice.preset != method:
            target = copy.deepcopy(defaults[choice.preset][0])
            kept = carry_overrides(model, base_model, target)
            config.pipeline.model = model = target
            base_model = defaults[choice.preset][0]
            notes.append(
                f"model switched from {method} to {choice.preset}"
                + (f"; your settings kept: {', '.join(kept)}" if kept else "")
            )
        if not choice.keep_resolution_schedule:
            if model.num_downscales == base_model.num_downscales:
                replaced, model.num_downscales = model.num_downscales, 0
            else:
                notes.append(f"your --pipeline.model.num-downscales {model.num_downscales} kept")
    config.max_num_iterations = choice.max_steps
    return choice, notes, replaced


def table_time(seconds: float) -> str:
    """A duration as nerfstudio's step table writes it: ``350.123 ms``, ``2 s, 149.675 ms``, ``7 m, 58 s``,
    ``1 h, 2 m, 3 s``."""
    seconds = max(0.0, float(seconds))
    whole = int(seconds)
    ms = (seconds - whole) * 1e3
    hours, rest = divmod(whole, 3600)
    minutes, secs = divmod(rest, 60)
    if hours:
        return f"{hours} h, {minutes} m, {secs} s"
    if minutes:
        return f"{minutes} m, {secs} s"
    if secs:
        return f"{secs} s, {ms:0.3f} ms"
    return f"{ms:0.3f} ms"


class BudgetStepTable(writer.LocalWriter):
    """nerfstudio's step table (its LocalWriter, whose class this becomes: :meth:`attach`) for a run under a time
    budget. nerfstudio counts the step against the planned end and the ETA as the steps left times the step time;
    the budget re-plans the end as the run measures itself, so its percentage went backwards when a plan grew
    (88 % then 87 %), and its first ETA multiplied the table's step count by this machine's slower steps (31 minutes
    for an 8-minute budget). Here every row says, from the first one: the step, the planned end (a range while the
    run has not measured its own step time: the plans at the table's step time and at the run's own so far), the
    share of the run's time done (which only grows), and in the ETA column the time left of the budget
    (budget_progress). The other columns are nerfstudio's."""

    budget: TimeBudget
    table_step_s: float
    shown_share: float
    HEADER = "Step of plan (% time)"
    WIDTH = 30

    @classmethod
    def attach(cls, writers: list, budget: TimeBudget, table_step_s: float) -> None:
        """Make nerfstudio's LocalWriter in ``writers`` this table for ``budget`` (the table's step time:
        ``table_step_s``)."""
        for w in writers:
            if type(w) is writer.LocalWriter:
                w.__class__ = cls
                w.budget, w.table_step_s, w.shown_share = budget, table_step_s, 0.0

    def row(self, step: int, latest_map: dict) -> str:
        """The table's row after ``step`` (see the class docstring)."""
        b = self.budget
        elapsed = b.elapsed()
        done = step - b.start_step + 1
        own = elapsed / done if done > 0 and elapsed > 0 else math.nan
        progress = budget_progress(
            b.budget_s, elapsed, step, b.start_step, b.end_step, b.max_steps, (self.table_step_s, own)
        )
        self.shown_share = max(self.shown_share, progress.share)
        low, high = progress.end_low, progress.end_high
        plan = f"{low}" if low == high else f"{low}-{high}"
        first = f"{step} of {plan} ({100 * self.shown_share:.2f}%)"
        cells = [f"{first:<{self.WIDTH}}"]
        for name, v in latest_map.items():
            if name not in self.stats_to_track:
                continue
            if name == writer.EventName.ETA.value:
                v = table_time(progress.time_left_s)
            elif "(time)" in name:
                v = table_time(v)
            elif "Rays" in name:
                v = human_format(v)
            else:
                v = f"{v:0.4f}"
            cells.append(f"{v:<20} ")
        return "".join(cells)

    def _update_header(self, latest_map, new_key):
        names = "".join(f"{name:<20} " for name in latest_map if name in self.stats_to_track)
        header = f"{self.HEADER:<{self.WIDTH}}{names}"
        if not self.config.max_log_size:  # a log: the header once, before the first row (a resumed run's too)
            if not getattr(self, "said_header", False):
                self.said_header = True
                print(header)
                print("-" * len(header))
            return
        if len(self.past_mssgs) - self.banner_len <= 2 or new_key:
            self.past_mssgs[0], self.past_mssgs[1] = header, "-" * len(header)
            if not self.has_printed:
                print(header)
                print("-" * len(header))

    def _print_stats(self, latest_map, padding=" "):
        curr = self.row(writer.GLOBAL_BUFFER["step"], latest_map)
        if not self.config.max_log_size:
            print(curr)
            return
        # nerfstudio's redrawn table: the last max_log_size rows above the banner
        if not self.has_printed:
            cursor_idx = len(self.past_mssgs) - self.banner_len
            self.has_printed = True
        else:
            cursor_idx = len(self.past_mssgs)
        if len(self.past_mssgs[2:]) - self.banner_len >= self.config.max_log_size:
            self.past_mssgs.pop(2)
        self.past_mssgs.insert(len(self.past_mssgs) - self.banner_len, curr)
        print(f"\r\033[{cursor_idx}A", end="\x1b[1K\r")
        pad_len = len(max(self.past_mssgs, key=len))
        for i, mssg in enumerate(self.past_mssgs):
            style = "\x1b[30;42m" if self.banner_len and i >= len(self.past_mssgs) - self.banner_len + 1 else ""
            print(f"{style}{mssg:{padding}<{pad_len}} \x1b[0m")


def resolution_for_images(trainer, downscales: int) -> None:
    """The budget set full resolution from the first step in place of the preset's ``downscales`` (the CPU points
    were measured so, on 128 px images); with larger training images (known only now, the data loaded) put the
    preset's resolution schedule back (full_resolution_suits): a full-resolution step costs too much.
    The model reads num_downscales at every step, so the change counts from the first one."""
    cams = getattr(getattr(trainer.pipeline.datamanager, "train_dataset", None), "cameras", None)
    if cams is None:
        return
    side = int(max(cams.width.max().item(), cams.height.max().item()))
    if full_resolution_suits(side):
        return
    trainer.pipeline.model.config.num_downscales = downscales  # what the model reads
    trainer.config.pipeline.model.num_downscales = downscales  # what config.yml says (the same object in nerfstudio)
    note = (
        f"training images up to {side} px (the {device_class(trainer.config.machine.device_type)} points: "
        f"{CPU_SCENE_SIDE} px): splatfacto's resolution schedule kept (num_downscales {downscales}) instead of "
        "full resolution from the first step"
    )
    CONSOLE.print(f"  note:     {note}")
    trainer.budget_record["notes"].append(note)
    if trainer.local_rank == 0:
        trainer.config.save_config()


def attach_budget(trainer, start_step: int, budget_s: float, choice: BudgetChoice) -> None:
    """The budget's TimeBudget in `trainer` (nerfstudio's, set up): its plans fit the model's step schedules and
    move the step table's end, its callbacks run first in every step and stop the loop, and the step table becomes
    BudgetStepTable. `start_step` > 0 when resumed with --load-dir: the budget is this run's."""
    start = start_step

    # the step schedules are the preset's, for its own run: their shares are of that run, not of a lower cap
    # (--max-num-iterations 5000 would keep a 30000-step run's last split at 3 times the planned run)
    own_steps = preset_defaults(choice.preset)[1] if choice.preset in PRESET_CONFIGS else choice.max_steps
    fit = schedule_fitter(trainer.pipeline.model, own_steps)

    def on_plan(end_step: int) -> None:
        fit(end_step - start)
        # progress and ETA count against the planned end, not the cap (nerfstudio's step table reads max_iter)
        writer.GLOBAL_BUFFER["max_iter"] = end_step

    on_plan(start + choice.steps)
    cuda = str(trainer.device).startswith("cuda") and torch.cuda.is_available()
    budget = TimeBudget(
        budget_s,
        max_steps=choice.max_steps,
        start_step=start,
        on_plan=on_plan,
        log=CONSOLE.print,
        sync=torch.cuda.synchronize if cuda else None,
        clock=trainer.clock,
        warmup_steps=WARMUP_STEPS,  # read now, so a test can shorten them
        window_steps=WINDOW_STEPS,
        replan_every=REPLAN_EVERY,
    )

    def after_step(step: int) -> None:
        if budget.after_step(step):
            trainer.stop_training = True  # nerfstudio's loop breaks before the next step

    # first, so that the interrupt checkpoint (the pipeline's last AFTER_TRAIN_ITERATION callback) stays last
    trainer.callbacks[:0] = [
        TrainingCallback([TrainingCallbackLocation.BEFORE_TRAIN_ITERATION], budget.before_step),
        TrainingCallback([TrainingCallbackLocation.AFTER_TRAIN_ITERATION], after_step),
        TrainingCallback([TrainingCallbackLocation.AFTER_TRAIN], lambda step: budget_done(trainer, step)),
    ]
    trainer.time_budget = budget
    BudgetStepTable.attach(writer.EVENT_WRITERS, budget, choice.step_s)
    trainer.budget_record["gaussians_at_start"] = num_gaussians(trainer.pipeline.model)
    write_budget_record(trainer)


def attach_rates(trainer, start_step: int, budget_steps: int | None) -> None:
    """Before every step, each learning rate = its scheduled value x ``lr_scale`` x cooldown_factor
    (``lr_cooldown``). The run's end: the budget's latest plan (``budget_steps`` from the first step until the run
    has measured its own), else max_num_iterations from the first step; under a budget, unset switches follow
    short_run_rates of that plan. The schedulers set their groups' rates from their own base every
    step; a group without one is at its configured rate (not the rate a resumed checkpoint saved: that one was
    already scaled). Nothing is attached when neither a budget nor a switch asks for it."""
    cfg = trainer.config
    budget = trainer.time_budget
    if budget is None and cfg.lr_scale in (None, 1) and not cfg.lr_cooldown:
        return
    optimizers = trainer.optimizers
    start = start_step
    fixed_end = start + (cfg.max_num_iterations if budget_steps is None else budget_steps)
    used: dict[str, float] = {}

    def before_step(step: int) -> None:
        end = budget.end_step if budget is not None and budget.end_step is not None else fixed_end
        scale, share = short_run_rates(end - start) if budget is not None else (1.0, 0.0)
        scale = scale if cfg.lr_scale is None else cfg.lr_scale
        share = share if cfg.lr_cooldown is None else cfg.lr_cooldown
        factor = scale * cooldown_factor(step, start, end, share, cfg.lr_cooldown_floor)
        for name, opt in optimizers.optimizers.items():
            scheduler = optimizers.schedulers.get(name)
            own = optimizers.config[name]["optimizer"].lr
            rates = scheduler.get_last_lr() if scheduler is not None else [own] * len(opt.param_groups)
            for group, lr in zip(opt.param_groups, rates, strict=True):
                group["lr"] = lr * factor
        if used.get("scale") != scale or used.get("cooldown") != share:
            used.update(scale=scale, cooldown=share, floor=cfg.lr_cooldown_floor)
            if budget is not None:
                trainer.budget_record["learning_rates"] = dict(used)

    trainer.callbacks.append(TrainingCallback([TrainingCallbackLocation.BEFORE_TRAIN_ITERATION], before_step))


def num_gaussians(model) -> int | None:
    """The model's Gaussian count (None for a model without Gaussians)."""
    means = getattr(model, "means", None)
    return None if means is None else int(means.shape[0])


def densification_window(model) -> dict[str, int] | None:
    """The densification steps as the strategy runs them now (after the budget fitted them): refinements every
    ``refine_every`` steps after ``refine_start_iter`` until ``refine_stop_iter``."""
    strategy = getattr(model, "strategy", None)
    if strategy is None or not hasattr(strategy, "refine_start_iter"):
        return None
    keys = ("refine_start_iter", "refine_every", "refine_stop_iter", "reset_every")
    return {k: int(getattr(strategy, k)) for k in keys if isinstance(getattr(strategy, k, None), int)}


def schedule_fitter(model, preset_steps: int) -> Callable[[int], None]:
    """A function of the run's planned steps that fits the model's step schedules into them
    (fit_schedules, from the values the run started with): the config (what config.yml says and
    what the model reads at each step) and the densification strategy, which copied them when it was built.
    Both strategies have the refinement window and period; splatfacto's (gsplat's DefaultStrategy) also stops
    its screen-size splits and resets opacities (its period and the pause after each reset), which MCMC's never
    does (its reset_every stays 0)."""
    cfg = model.config

    def get(name: str) -> Any:
        target = cfg
        for part in name.split("."):
            target = getattr(target, part, None)
        return target

    own = {k: int(v) for k in STEP_SCHEDULES if isinstance(v := get(k), int) and not isinstance(v, bool)}
    strategy = getattr(model, "strategy", None)
    base_pause = getattr(strategy, "pause_refine_after_reset", None)

    def fit(run_steps: int) -> None:
        values = fit_schedules(own, run_steps, preset_steps)
        for name, value in values.items():
            *parents, last = name.split(".")
            target = cfg
            for part in parents:
                target = getattr(target, part)
            setattr(target, last, value)
        if strategy is None or not hasattr(strategy, "refine_start_iter"):
            return
        strategy.refine_start_iter = values.get("warmup_length", strategy.refine_start_iter)
        strategy.refine_stop_iter = values.get("stop_split_at", strategy.refine_stop_iter)
        if "refine_every" in values:
            strategy.refine_every = values["refine_every"]
        if base_pause is None:  # MCMC's densification: no screen-size splits, no opacity resets
            return
        strategy.refine_scale2d_stop_iter = values.get("stop_screen_size_at", strategy.refine_scale2d_stop_iter)
        if "refine_every" in values:
            strategy.reset_every = values.get("reset_alpha_every", 0) * values["refine_every"]
            # an epoch after each reset; in a shorter run, one refinement
            pause = base_pause - own["refine_every"] + values["refine_every"]
            if values != own:
                pause = min(pause, values["refine_every"])
            strategy.pause_refine_after_reset = pause

    return fit


def budget_done(trainer, step: int) -> None:
    """After the last step: say where the budget stopped, config.yml says the steps trained, and the record says
    how the run densified."""
    budget = trainer.time_budget
    assert budget is not None
    trained = step - budget.start_step + 1
    how = budget.stop_reason or "trained every step allowed"
    CONSOLE.print(
        f"willags time budget: stopped after step {step} ({trained} steps; {how}) at {budget.elapsed():.0f} s of "
        f"{budget.budget_s:.0f} s"
    )
    if trainer.local_rank == 0:
        trainer.config.max_num_iterations = trained
        trainer.config.save_config()  # config.yml says what was trained
    # whether the run densified: Gaussians at the end against those it started from (the SfM points)
    trainer.budget_record["gaussians_at_end"] = num_gaussians(trainer.pipeline.model)
    trainer.budget_record["densification"] = densification_window(trainer.pipeline.model)
    write_budget_record(trainer)


def write_budget_record(trainer) -> None:
    """BUDGET_FILE beside config.yml (rank 0): the choice, the notes, the learning rates, the Gaussians, the run."""
    if trainer.local_rank != 0:
        return
    record = {**trainer.budget_record}
    if trainer.time_budget is not None:
        record["run"] = trainer.time_budget.summary()
    path = Path(trainer.base_dir) / BUDGET_FILE
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(record, indent=1, default=str))
