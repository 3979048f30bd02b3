"""Training under a time budget: which preset, how many steps, and when to stop (`--pipeline.time-budget-minutes`).

Two decisions, both from measurements:

1. **Before training** (:func:`choose`; for ``ns-train willags``: a method named explicitly, willags-lite included,
   keeps its model), from the table of measured points below: for each preset, the steps that fit
   in the budget at its step time; among the measured points that fit, the one with the highest right-half PSNR
   decides the preset. The run then reproduces that point's resolution schedule (splatfacto's stock one on the GPU
   points, full resolution from the first step on the CPU ones, measured on 128 px images: larger training
   images keep the stock schedule, :func:`full_resolution_suits`). The preset cannot change later: willags-lite and
   willags build different appearance networks.
2. **While training** (:class:`TimeBudget`), from the run's own clock: the wall time of steps 20-70 (after the first
   steps' warm-up: allocations, kernel caches) gives the step time on this machine and scene; the last step is set so
   that the run ends within the budget (never after the preset's own default, nor after ``--max-num-iterations``),
   re-planned every 200 steps (steps get slower as densification adds Gaussians and the resolution schedule doubles
   the image size), and every learning-rate schedule ends at that step. Should the clock run out first, training
   stops there.

The budget is wall-clock time of the trainer's loop (its periodic evaluation and checkpoints, and any pause in the
viewer, included) from the first step; not the set-up before it (loading and caching images, gsplat's first JIT
compile) nor the final checkpoint.

**The table** holds what has been measured, nothing else. Its limits, stated where the choice is printed:

- the PSNR of a point is the NeRF-W protocol's right-half PSNR on one reference scene per device class (the GPU:
  fox-wild, the only scene where both presets were measured; the CPU: the embedded default scene);
- points of an earlier configuration are in the table (cited) but do not decide (``choose(current_only=True)``):
  willags-lite-v0 (the fast preset before the modulated colour path) and the CPU's willags points, measured as the
  default of that time, the paper's configuration (records relabelled ``willags-paper``). The GPU points of today's
  presets come from one run each alone on an H200 on fox-wild (the default there is the same model before and after
  issue 26's sky and safeguard, which need COLMAP keypoints): willags beats willags-lite at every step count and costs
  less per step (10.8 vs 14.5 ms: lite keeps the beta-VAE encoder, run on every step's photo, and computes the mask's
  VGG at 512 px where willags uses 256), so on the GPU the measured choice is willags for every budget. The real
  scenes agree (one run of willags-lite alone on an H200 to 15k, tag h200-curve13, not in the table: reichstag
  18.36 -> 18.00 dB, south-building 18.92 -> 20.32, below willags at every milestone, 328 s for 15k vs 308 s). On the CPU
  (one run of each alone on the 2-core machine, the embedded scene, the CPU grid's short schedule) willags-lite is
  cheaper per step (0.130 vs 0.171 s) and willags better at equal steps (23.01 vs 22.25 dB at 600 steps): the best
  point that fits decides (lite's 300 steps below 51 s, willags' 300 to 78 s, lite's 600 to 103 s, then willags'
  600: the points are few, so the choice alternates between them);
- the points of ``willags`` were measured with the full model (``willags-full`` since the default inspects the scene
  first): on the GPU's reference scene the inspection keeps the same components (fox-wild's transients keep the mask;
  it has no keypoints for the sky), and the CPU's embedded scene (no ``--data``) is not inspected;
- GPU step times are of runs alone on one GPU (the fidelity grid's runs share it with 4-12 others, so their times
  are not step costs);
- ``one_scene``: only one scene has a record of this (configuration, steps, device); the others were measured on
  several (PSNR still from the reference scene).

The records are in docs/benchmarks.json (keys: scene, method, device, steps, tag); tests/test_time_budget.py checks
every number below against them.
"""

import math
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any

from willags_ns.checks import WillagsTrainingError

OPTION = "--pipeline.time-budget-minutes"
PRESETS = ("willags-lite", "willags")
"""The presets the budget chooses between, for `ns-train willags`; every other method (willags-lite named explicitly
too) keeps its model and only its step count follows the budget."""
DEFAULT_PRESET = "willags"
"""The method whose preset the budget chooses, and the preset when no point of today's presets was measured on the
device (the best measured configuration)."""

WARMUP_STEPS = 20
"""Steps before the step time is measured (the first steps allocate memory and fill kernel caches)."""
WINDOW_STEPS = 50
"""Steps whose wall time gives the first step-time measurement (steps 20-70 with the warm-up above)."""
REPLAN_EVERY = 200
"""After the first plan, the step time is measured again over each span of this many steps and the plan redone."""
REPRINT_CHANGE = 0.05
"""A re-plan is printed when it moves the last step by more than this fraction (the schedules follow every re-plan)."""


class TimeBudgetError(WillagsTrainingError, ValueError):
    """A bad time budget (negative, NaN, several devices); the message names the option. A WillagsTrainingError, so
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
    """The runs: tags in docs/benchmarks.json (scene, measured_as, device, steps, tag)."""
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


_LITE_V0 = "willags-lite-v0"
TABLE: tuple[MeasuredPoint, ...] = (
    # GPU, fox-wild, splatfacto's stock schedule, NeRF-W protocol with 128 steps. Today's presets: one run each alone
    # on an H200 scored at milestones (tag h200-solo, benchmarks/long_run.py); willags' 5000-step point adds the eight
    # H100 grid runs (shared GPU: their PSNR counts, not their times). willags-lite-v0: the earlier fast preset.
    MeasuredPoint("willags-lite", "cuda", 1000, 19.631, "fox-wild", ("h100-seq",), _LITE_V0, "stock", True),
    MeasuredPoint("willags-lite", "cuda", 2000, 19.184, "fox-wild", ("h100-seq", "h100-seq2"), _LITE_V0, "stock", True),
    MeasuredPoint("willags-lite", "cuda", 5000, 20.615, "fox-wild", ("h100",), _LITE_V0, "stock", True),
    MeasuredPoint("willags-lite", "cuda", 1000, 20.155, "fox-wild", ("h200-solo",), "willags-lite", "stock", False),
    MeasuredPoint("willags-lite", "cuda", 2000, 20.580, "fox-wild", ("h200-solo",), "willags-lite", "stock", False),
    MeasuredPoint("willags-lite", "cuda", 5000, 21.003, "fox-wild", ("h200-solo",), "willags-lite", "stock", False),
    MeasuredPoint("willags", "cuda", 1000, 21.134, "fox-wild", ("h200-solo",), "willags", "stock", False),
    MeasuredPoint("willags", "cuda", 2000, 21.172, "fox-wild", ("h200-solo",), "willags", "stock", False),
    MeasuredPoint(
        "willags",
        "cuda",
        5000,
        22.243,
        "fox-wild",
        ("h100-r1", "h100-r2", "h100-r7", "h100-r7b", "h100-r7c", "h100-r7d", "h100-r7e", "h100-r7f", "h200-solo"),
        "willags",
        "stock",
        False,
    ),
    MeasuredPoint("willags", "cuda", 15000, 22.391, "fox-wild", ("h100-15k",), "willags", "stock", False),
    # CPU (2 cores), the embedded default scene (128x96), the CPU grid's short schedule, protocol with 32 steps
    MeasuredPoint("willags-lite", "cpu", 300, 17.733, "default", ("",), _LITE_V0, "full", False),
    # today's presets, one run each alone on the 2-core machine (tag cpu-knob, docs/gpu_runs/cpu_knob_session11.json)
    MeasuredPoint("willags-lite", "cpu", 300, 20.140, "default", ("cpu-knob",), "willags-lite", "full", True),
    MeasuredPoint("willags-lite", "cpu", 600, 22.246, "default", ("cpu-knob",), "willags-lite", "full", True),
    MeasuredPoint("willags", "cpu", 300, 21.379, "default", ("cpu-knob",), "willags", "full", True),
    MeasuredPoint("willags", "cpu", 600, 23.015, "default", ("cpu-knob",), "willags", "full", True),
    MeasuredPoint("willags", "cpu", 200, 17.516, "default", ("",), "willags-paper", "full", False),
    MeasuredPoint("willags", "cpu", 300, 18.840, "default", ("",), "willags-paper", "full", False),
    MeasuredPoint("willags", "cpu", 600, 20.533, "default", ("",), "willags-paper", "full", True),
)
"""Every measured point the choice uses (docs/benchmarks.json; see the module docstring for what each column means)."""

STEP_TIMES: dict[tuple[str, str], StepTime] = {
    ("willags-lite", "cuda"): StepTime(
        0.014502, "fox-wild, willags-lite, 5000 steps, tag h200-solo (72.5 s), alone on an H200", "willags-lite"
    ),
    ("willags", "cuda"): StepTime(
        0.010795,
        "fox-wild, willags, 5000 steps, tag h200-solo (54.0 s), alone on an H200 (reichstag alone: 78.7 s)",
        "willags",
    ),
    ("willags-lite", "cpu"): StepTime(
        0.13004,
        "default scene, willags-lite, 600 steps (78.0 s), tag cpu-knob, 2-core CPU, load 1.9-2.0",
        "willags-lite",
    ),
    ("willags", "cpu"): StepTime(
        0.17102, "default scene, willags, 600 steps (102.6 s), tag cpu-knob, 2-core CPU, load 1.6-1.9", "willags"
    ),
}
"""Seconds per step of each preset on each device class, before this run has measured its own."""


CPU_SCENE_SIDE = 128
"""Longest image side (px) of the scene the CPU points were measured on (the embedded default scene, 128x96)."""
FULL_RESOLUTION_MAX_SIDE = 2 * CPU_SCENE_SIDE
"""Largest image side (px) for which a CPU choice trains at full resolution from the first step, as its points were
measured; larger images keep splatfacto's resolution schedule (:func:`full_resolution_suits`)."""


def full_resolution_suits(image_side: int) -> bool:
    """Whether full resolution from the first step (how the CPU points were measured, on 128 px images) suits training
    images whose longest side is ``image_side`` px: up to twice the measured scene's side. Measured on the 2-core CPU,
    sacre-coeur-mini (800 px), a 4-minute budget: at full resolution a step took 12.9 s (19 steps trained); with
    splatfacto's resolution schedule (a quarter of the resolution for the first 3000 steps) 0.20 s (1180 steps)."""
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

    ``current_only``: only points (and step times) measured with today's configuration of their preset take part;
    those of an earlier configuration (``measured_as`` another method: willags-lite-v0, the paper configuration) say
    nothing about today's preset, neither its PSNR nor its step cost. With no point left, the default preset, its own
    resolution schedule, and no step plan before the run has measured its own step time (``step_s`` NaN).
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
        why = f"no point of today's presets measured on {device}{not_used}: the default, its own resolution schedule"
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


def format_choice(choice: BudgetChoice, budget_min: float, device: str, notes: list[str] | None = None) -> str:
    """The block printed before training: budget, preset and why, the table point, the steps and the schedules."""
    p = choice.point
    src = STEP_TIMES.get((choice.preset, device))
    lines = [
        f"willags time budget: {budget_min:g} min ({budget_min * 60:.0f} s of training steps; set-up not counted)",
        f"  preset:   {choice.preset}: {choice.reason}",
    ]
    if p is not None:
        caveats = [f"runs {', '.join(t or '(untagged)' for t in p.records)}"]
        if p.measured_as != p.preset:
            caveats.append(f"measured as {p.measured_as}, not today's {p.preset}")
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
    lines.append(f"  schedule: {sched}; learning-rate schedules end at the last step")
    lines += [f"  note:     {n}" for n in notes or []]
    return "\n".join(lines)


# --------------------------------------------------------------------------------------------------------------------
# while training


def schedule_warmups(optimizers: Mapping[str, Mapping[str, Any]]) -> dict[str, int]:
    """Each learning-rate schedule's own warm-up (steps), kept so that re-plans start from it, not from a shortened one."""
    return {
        name: int(group["scheduler"].warmup_steps)
        for name, group in optimizers.items()
        if group.get("scheduler") is not None and hasattr(group["scheduler"], "warmup_steps")
    }


def end_schedules_at(
    optimizers: Mapping[str, Mapping[str, Any]], end_step: int, warmups: Mapping[str, int] | None = None
) -> None:
    """Make every learning-rate schedule with a ``max_steps`` end at ``end_step`` (what benchmarks/harness.py's short
    schedule does, here also during the run: nerfstudio's schedulers read their config at every step). A warm-up
    (``warmups``: the schedules' own, default their current one) that would not end before ``end_step`` is shortened
    to a tenth of the run.

    camera_opt (warm-up 1000, exponential decay to 5e-7) with end_step 500: max_steps 500, warm-up 50."""
    for name, group in optimizers.items():
        sched = group.get("scheduler")
        if sched is None or not hasattr(sched, "max_steps"):
            continue
        sched.max_steps = int(end_step)
        if hasattr(sched, "warmup_steps"):
            own = int((warmups or {}).get(name, sched.warmup_steps) or 0)
            sched.warmup_steps = own if own < end_step else int(end_step) // 10


@dataclass
class TimeBudget:
    """The budget during training: call :meth:`before_step` and :meth:`after_step` around every step (the trainer's
    callbacks do); ``after_step`` says when to stop. ``clock`` and ``sync`` are injectable (tests use a fake clock;
    on CUDA, ``sync`` waits for the device so the clock measures finished work)."""

    budget_s: float
    """The budget in seconds, from the first step on."""
    max_steps: int
    """Never train more steps than this (the preset's default or --max-num-iterations)."""
    start_step: int = 0
    """The first step of this run (> 0 when resumed)."""
    on_plan: Callable[[int], None] | None = None
    """Called with the new end step (exclusive) at every plan: the trainer ends its learning-rate schedules there."""
    log: Callable[[str], None] = print
    clock: Callable[[], float] = time.perf_counter
    sync: Callable[[], None] | None = None
    warmup_steps: int = WARMUP_STEPS
    window_steps: int = WINDOW_STEPS
    replan_every: int = REPLAN_EVERY
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

    def _now(self) -> float:
        if self.sync is not None:
            self.sync()
        return self.clock()

    def elapsed(self) -> float:
        return 0.0 if self.t0 is None else self.clock() - self.t0

    def after_step(self, step: int) -> bool:
        """Record step ``step`` as done; True when training must stop after it."""
        if self.t0 is None:
            self.before_step(step)
        t0 = self.t0
        assert t0 is not None
        done = step - self.start_step + 1  # steps trained in this run
        due = (
            done == self.warmup_steps
            or (self.end_step is None and done == self.warmup_steps + self.window_steps)
            or (self.end_step is not None and self._mark is not None and done - self._mark[0] >= self.replan_every)
        )
        now = self._now() if due else self.clock()
        if due:
            if self._mark is not None and done > self._mark[0]:
                self._plan(step, done, (now - self._mark[1]) / (done - self._mark[0]), now - t0)
            self._mark = (done, now)
        if self.end_step is not None and step + 1 >= self.end_step:
            return self._stop(step, f"reached the planned last step {step}")
        if now - t0 >= self.budget_s:
            return self._stop(step, f"the clock: {now - t0:.0f} s of {self.budget_s:.0f} s used")
        return False

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
            f"{self.budget_s:.0f} s used -> training stops after step {end - 1}{cap}; learning-rate schedules end there"
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
