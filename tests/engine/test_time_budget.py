"""The time budget (willags_ns/engine/time_budget.py, willags_ns/engine/trainer.py): the choice before training (pure, fake step
times), the adaptation while training (fake clock), bad values, the table against its records, one real CPU run."""

import dataclasses
import json
import math
import statistics
import subprocess
from pathlib import Path

import pytest
import torch

from benchmarks.scale import console_script
from willags_ns.engine import time_budget as tb
from willags_ns.engine.time_budget import (
    OPTION,
    STEP_TIMES,
    TABLE,
    TimeBudget,
    TimeBudgetError,
    choose,
    plan_steps,
    validate_minutes,
)

REPO = Path(__file__).resolve().parents[2]
CAPS = {"willags": 30000, "willags-lite": 7000}


# ---------------------------------------------------------------------------------------------- the choice (pure)


CURRENT = tuple(dataclasses.replace(p, measured_as=p.preset) for p in TABLE)
"""The table as if today's presets had measured its points (the decision logic, away from the records' gaps)."""
FAKE = {"willags-lite": 0.1, "willags": 0.3}
"""Fake CPU step times (seconds)."""


def test_tiny_cpu_budget_picks_lite_and_few_steps():
    c = choose(30.0, "cpu", CAPS, step_s=FAKE, table=CURRENT)
    assert c.preset == "willags-lite"
    assert c.steps == 300  # 30 s / 0.1 s
    assert c.point is not None and c.point.steps == 300  # lite's 300-step point takes 30 s: it fits, willags' do not
    assert not c.keep_resolution_schedule  # the CPU points were measured at full resolution from the first step
    assert "willags-lite" in c.reason


def test_budget_below_every_point_takes_the_quickest_preset():
    c = choose(5.0, "cpu", CAPS, step_s=FAKE, table=CURRENT)
    assert c.preset == "willags-lite" and c.steps == 50 and c.point is None
    assert "no measured point fits" in c.reason


def test_large_cpu_budget_picks_the_default_with_its_full_step_count():
    c = choose(600 * 60.0, "cpu", CAPS, step_s=FAKE, table=CURRENT)
    assert c.preset == "willags"
    assert c.steps == 30000  # 36000 s / 0.3 s = 120000 steps, capped at the preset's default
    assert c.point is not None and c.point.steps == max(p.steps for p in TABLE if p.device == "cpu")


def test_gpu_measured_points_pick_willags_over_lite_at_every_budget():
    """Today's GPU points (one run of each preset alone on an H200, fox-wild): willags scores higher at every step
    count and costs less per step, so every budget gets willags, and the reason names the lite point it beat."""
    assert STEP_TIMES[("willags", "cuda")].seconds < STEP_TIMES[("willags-lite", "cuda")].seconds
    for budget in (15.0, 30.0, 60.0, 300.0, 3600.0):
        c = choose(budget, "cuda", CAPS)
        assert c.preset == "willags" and c.keep_resolution_schedule, budget
        assert c.point is not None and c.point.measured_as == "willags"
    c = choose(60.0, "cuda", CAPS)  # fits: willags 1000/2000/5000 (54 s), lite 1000/2000 (29 s)
    assert c.point.steps == 5000 and "vs willags-lite: 20.58 dB at 2000 steps" in c.reason


def test_gpu_switches_preset_where_the_default_first_fits():
    """The switch itself, on the GPU table's shape with a cheaper lite: willags' first point is its 1000-step one;
    below its cost only lite's points fit, from it on willags' point beats every lite point that fits."""
    step_s = {"willags": 0.02, "willags-lite": 0.005}
    t = 1000 * step_s["willags"]
    below = choose(t - 1, "cuda", CAPS, step_s=step_s)
    above = choose(t + 1, "cuda", CAPS, step_s=step_s)
    assert below.preset == "willags-lite" and above.preset == "willags"
    assert below.keep_resolution_schedule and above.keep_resolution_schedule  # GPU points: the stock schedule
    assert below.steps <= CAPS["willags-lite"]


def test_points_of_earlier_configurations_do_not_decide():
    """The real table: willags-lite-v0's points and the paper configuration's CPU points are cited but do not count
    (the choice names them as unused); today's points decide, on both device classes."""
    for budget in (30.0, 60.0, 600.0, 36000.0):
        gpu = choose(budget, "cuda", CAPS)
        assert gpu.preset == "willags" and "willags-lite-v0" in gpu.reason
        assert gpu.steps == plan_steps(budget, 0, 0, STEP_TIMES[("willags", "cuda")].seconds, CAPS["willags"])
    # CPU: lite is cheaper per step, willags better at equal steps; lite's 600 steps (78 s) beat willags' 300 (51 s)
    # until willags' 600 steps fit (103 s)
    for budget, preset in ((60.0, "willags"), (90.0, "willags-lite"), (600.0, "willags"), (36000.0, "willags")):
        cpu = choose(budget, "cpu", CAPS)
        assert cpu.preset == preset and cpu.point is not None and cpu.point.measured_as == preset, budget
        assert "willags-paper" in cpu.reason and "willags-lite-v0" in cpu.reason
        assert cpu.steps == plan_steps(budget, 0, 0, STEP_TIMES[(preset, "cpu")].seconds, CAPS[preset])
        assert not cpu.keep_resolution_schedule  # the CPU points: full resolution from the first step
    text = tb.format_choice(choose(60.0, "cpu", CAPS), 1.0, "cpu")
    assert "re-planned from this run's own step time over steps 20-70" in text and "cpu-knob" in text


def test_caps_limit_the_steps():
    c = choose(1e6, "cuda", {"willags": 1234, "willags-lite": 7000})
    assert c.preset == "willags" and c.steps == 1234 and c.max_steps == 1234


@pytest.mark.parametrize(
    "budget, elapsed, done, step_s, cap, want",
    [
        (600, 100, 1000, 0.05, 30000, 11000),  # the docstring's example
        (600, 100, 1000, 0.01, 30000, 30000),  # capped
        (600, 700, 1000, 0.05, 30000, 1000),  # over budget: stop now
        (10, 0, 0, 0.1, 30000, 100),  # exact division is not lost to rounding
    ],
)
def test_plan_steps(budget, elapsed, done, step_s, cap, want):
    assert plan_steps(budget, elapsed, done, step_s, cap) == want


def test_plan_steps_rejects_a_zero_step_time():
    with pytest.raises(ValueError):
        plan_steps(10, 0, 0, 0.0, 100)


# ---------------------------------------------------------------------------------------------- bad values


@pytest.mark.parametrize("bad", [-1, -0.5, float("nan"), float("inf"), "ten", True])
def test_bad_budget_names_the_option(bad):
    with pytest.raises(TimeBudgetError, match=OPTION.replace(".", r"\.")):
        validate_minutes(bad)


@pytest.mark.parametrize("off", [None, 0, 0.0])
def test_zero_or_none_turns_it_off(off):
    assert validate_minutes(off) is None


def test_bad_budget_stops_the_trainer_before_training(tmp_path):
    from willags_ns import method_configs

    config = method_configs.willags_config()
    config.output_dir = tmp_path
    config.machine.device_type = "cpu"
    config.pipeline.time_budget_minutes = float("nan")
    trainer = config.setup(local_rank=0, world_size=1)
    with pytest.raises(TimeBudgetError, match="time-budget-minutes"):
        trainer.setup()


# ---------------------------------------------------------------------------------------------- the short-run rates


def test_cooldown_factor_falls_linearly_over_the_last_share():
    f = [tb.cooldown_factor(s, 0, 1000, 0.3) for s in range(1000)]
    assert f[:701] == [1.0] * 701
    assert tb.cooldown_factor(850, 0, 1000, 0.3) == pytest.approx(0.5)
    assert all(a >= b for a, b in zip(f, f[1:], strict=False))
    assert 0 < f[-1] < 0.01  # the last step still trains
    assert tb.cooldown_factor(999, 0, 1000, 0.3, floor=0.2) == pytest.approx(0.2 + 0.8 / 300)
    # a resumed run counts its own steps
    assert tb.cooldown_factor(1500, 1000, 2000, 0.5) == 1.0
    assert tb.cooldown_factor(1750, 1000, 2000, 0.5) == pytest.approx(0.5)
    assert {tb.cooldown_factor(s, 0, 1000, 0.0) for s in (0, 500, 999)} == {1.0}


def test_only_a_short_plan_changes_the_rates():
    assert tb.short_run_rates(tb.SHORT_RUN_STEPS - 1) == (tb.SHORT_RUN_LR_SCALE, tb.SHORT_RUN_COOLDOWN)
    assert tb.short_run_rates(tb.SHORT_RUN_STEPS) == (1.0, 0.0)
    assert tb.SHORT_RUN_LR_SCALE > 1 and 0 < tb.SHORT_RUN_COOLDOWN <= 1


@pytest.mark.parametrize(
    ("option", "bad"),
    [
        ("--lr-scale", {"scale": 0}),
        ("--lr-scale", {"scale": -1.0}),
        ("--lr-scale", {"scale": float("nan")}),
        ("--lr-scale", {"scale": float("inf")}),
        ("--lr-scale", {"scale": "4"}),
        ("--lr-cooldown", {"cooldown": 1.5}),
        ("--lr-cooldown", {"cooldown": -0.1}),
        ("--lr-cooldown-floor", {"floor": 2.0}),
        ("--lr-cooldown-floor", {"floor": None}),
    ],
)
def test_bad_rates_name_their_option(option, bad):
    values = {"scale": None, "cooldown": None, "floor": 0.0, **bad}
    with pytest.raises(TimeBudgetError, match=f"^{option} must"):
        tb.validate_rates(**values)


def test_rates_in_range_pass():
    for scale, cooldown, floor in [(None, None, 0.0), (4, 0.5, 0.1), (1, 1, 1), (0.5, 0, 0)]:
        tb.validate_rates(scale, cooldown, floor)


def test_a_bad_rate_stops_the_trainer_before_training(tmp_path):
    from willags_ns import method_configs

    config = method_configs.willags_config()
    config.output_dir = tmp_path
    config.machine.device_type = "cpu"
    config.lr_cooldown = 2.0
    trainer = config.setup(local_rank=0, world_size=1)
    with pytest.raises(TimeBudgetError, match="--lr-cooldown"):
        trainer.setup()
    assert not list(tmp_path.rglob("config.yml"))


def _record_rates(monkeypatch) -> list[list[float]]:
    """Wrap the trainer's step: before each, every group's learning rate over its scheduled (or configured) one."""
    from willags_ns.engine.trainer import WillagsTrainer

    factors: list[list[float]] = []
    train_iteration = WillagsTrainer.train_iteration

    def recording(self, step):
        opt = self.optimizers
        row = []
        for name, o in opt.optimizers.items():
            scheduled = opt.schedulers[name].get_last_lr() if name in opt.schedulers else None
            for i, group in enumerate(o.param_groups):
                want = scheduled[i] if scheduled is not None else opt.config[name]["optimizer"].lr
                row.append(group["lr"] / want)
        factors.append(row)
        return train_iteration(self, step)

    monkeypatch.setattr(WillagsTrainer, "train_iteration", recording)
    return factors


@pytest.mark.slow
def test_rate_switches_scale_and_cool_down_a_run_without_budget(tmp_path, monkeypatch):
    """--lr-scale 2 --lr-cooldown 0.5 on an 8-step run: every group at twice its rate, then falling over steps 4-7."""
    from tests.test_train import _train
    from willags_ns import method_configs

    factors = _record_rates(monkeypatch)
    real = method_configs.willags_config

    def switched():
        config = real()
        config.lr_scale, config.lr_cooldown = 2.0, 0.5
        return config

    monkeypatch.setattr(method_configs, "willags_config", switched)
    _train(tmp_path, "willags", steps=8)
    want = [2.0 * tb.cooldown_factor(s, 0, 8, 0.5) for s in range(8)]
    assert want[:5] == [2.0] * 5 and want[-1] < 1.0
    assert len(factors) == 8
    for row, w in zip(factors, want, strict=True):
        assert row == pytest.approx([w] * len(row))


# ---------------------------------------------------------------------------------------------- while training


class FakeClock:
    """A clock the test advances by hand (`_run` adds each step's seconds)."""

    def __init__(self):
        self.t = 1000.0

    def __call__(self) -> float:
        return self.t


def _trainer_on_a_fake_clock(monkeypatch, step_seconds) -> FakeClock:
    """WillagsTrainer's clock made a FakeClock that advances `step_seconds(step)` after each training step, whatever
    the machine's speed."""
    from willags_ns.engine.trainer import WillagsTrainer

    clock = FakeClock()
    train_iteration = WillagsTrainer.train_iteration

    def timed_steps(self, step):
        out = train_iteration(self, step)
        clock.t += step_seconds(step)
        return out

    monkeypatch.setattr(WillagsTrainer, "clock", staticmethod(clock))
    monkeypatch.setattr(WillagsTrainer, "train_iteration", timed_steps)
    return clock


def _run(budget: TimeBudget, clock: FakeClock, step_s, start: int = 0, limit: int = 100000) -> int:
    """Drive the budget as nerfstudio's loop does; returns the last step trained."""
    for step in range(start, start + limit):
        budget.before_step(step)
        clock.t += step_s(step)
        if budget.after_step(step):
            return step
    return start + limit - 1


def _budget_on_two_ranks(rank: int) -> None:
    """Each rank times its own step (rank 1 is slower; in the second run it also pauses for 10 s at step 100): both
    plan from the slower rank's step time and stop after the same step, the clock's stop being read where the ranks
    exchange it (every AGREE_EVERY steps)."""
    import torch.distributed as dist

    step_s = 0.125 if rank == 0 else 0.25
    for pause in (0.0, 10.0):
        clock = FakeClock()
        budget = TimeBudget(60.0, max_steps=30000, clock=clock, log=lambda m: None)

        def step_time(s: int, pause: float = pause) -> float:
            return step_s + (pause if (rank == 1 and s == 100) else 0.0)

        last = _run(budget, clock, step_time)
        assert budget.agree is tb.agreed_max
        everyone: list = [None, None]
        dist.all_gather_object(everyone, (last, budget.end_step, budget.stop_reason, budget.history))
        assert everyone[0] == everyone[1], everyone
        if pause == 0.0:  # 70 steps of 0.25 s in 17.5 s, 42.5 s left = 170 steps
            assert budget.history[0]["step_s"] == 0.25 and budget.end_step == 240 and last == 239
        else:  # the pause makes the clock run out before the plan's end: read at step 199 (200 steps done)
            assert budget.stop_reason.startswith("the clock") and last == 199


def test_ranks_plan_from_the_slowest_and_stop_together():
    from tests.engine.test_distributed import _run_gloo

    _run_gloo(_budget_on_two_ranks)


def test_one_process_reads_the_clock_at_every_step():
    clock = FakeClock()
    # measured at the step counts only (early_share and replan_share 0), so that the clock, not a plan, ends it
    budget = TimeBudget(60.0, max_steps=30000, clock=clock, log=lambda m: None, early_share=0, replan_share=0)
    last = _run(budget, clock, lambda s: 0.25 + (3.0 if s == 100 else 0.0))
    assert budget.agree is None
    assert last == 227 and budget.stop_reason.startswith("the clock")  # 228 * 0.25 + 3 = 60 s


def test_the_choice_says_what_a_step_is_on_several_devices():
    text = tb.format_choice(choose(600.0, "cuda", CAPS), 10.0, "cuda", num_devices=4)
    assert "devices:  4, one image each per step" in text
    assert "devices:" not in tb.format_choice(choose(600.0, "cuda", CAPS), 10.0, "cuda")


def test_measures_steps_20_to_70_and_stops_within_the_budget():
    # early_share 0 here and below: the step-count windows alone (slow steps: test_slow_steps_are_measured_...)
    clock, ends, logs = FakeClock(), [], []
    budget = TimeBudget(12.5, max_steps=30000, on_plan=ends.append, clock=clock, log=logs.append, early_share=0)
    last = _run(budget, clock, lambda s: 0.125)  # binary-exact seconds: no rounding at the boundaries
    assert budget.history[0]["step"] == 69 and budget.history[0]["step_s"] == 0.125
    assert ends[0] == 100  # 70 steps in 8.75 s, 3.75 s left = 30 steps
    assert last == 99 and budget.elapsed() <= 12.5
    assert "measured 125.0 ms/step (steps 20-70)" in logs[0]


def test_replans_when_steps_slow_down():
    """Densification and the resolution schedule make later steps slower: re-plans move the end earlier and the run
    still ends within the budget (at most one step late, when the clock stops it)."""
    clock, ends = FakeClock(), []
    budget = TimeBudget(60.0, max_steps=30000, on_plan=ends.append, clock=clock, log=lambda m: None, early_share=0)
    last = _run(budget, clock, lambda s: 0.01 if s < 500 else 0.05)
    assert len(ends) > 2 and ends[-1] < ends[0]
    assert budget.elapsed() <= 60.0 + 0.05
    assert last + 1 == ends[-1] or budget.stop_reason.startswith("the clock")


def test_a_run_slowed_by_densification_ends_at_its_plan_not_by_the_clock():
    """Densification adds Gaussians and later steps cost more: here steps of 0.17 s, 0.23 s after step 70 and 0.7 s
    after step 270 (the shape of a 3-minute CPU run on sacre-coeur-mini, docs/design.md). Re-planned every tenth of
    the budget, the run ends at its planned step within the budget, its schedules ended there; re-planned only every
    200 steps, the clock stops it long before the plan its progress and schedules count against."""

    def densifying(s: int) -> float:
        return 0.17 if s < 70 else 0.23 if s < 270 else 0.7

    def last_plan_and_steps(replan_share: float) -> tuple[int, int, str]:
        clock, ends = FakeClock(), []
        budget = TimeBudget(180.0, max_steps=30000, on_plan=ends.append, clock=clock, log=lambda m: None)
        budget.replan_share = replan_share
        last = _run(budget, clock, densifying)
        assert budget.elapsed() <= 180.0 + densifying(last)  # at most one step past the budget
        return ends[-1], last + 1, budget.stop_reason

    end, trained, why = last_plan_and_steps(tb.REPLAN_SHARE)
    assert trained == end and why.startswith("reached the planned last step")
    end, trained, why = last_plan_and_steps(0.0)
    assert why.startswith("the clock") and trained < 0.7 * end


def test_never_past_the_cap():
    clock = FakeClock()
    budget = TimeBudget(1e6, max_steps=300, clock=clock, log=lambda m: None)
    assert _run(budget, clock, lambda s: 0.01) == 299


def test_clock_stops_a_budget_shorter_than_the_measurement():
    clock = FakeClock()
    budget = TimeBudget(1.0, max_steps=30000, clock=clock, log=lambda m: None, early_share=0)
    assert _run(budget, clock, lambda s: 0.125) == 7 and budget.end_step is None
    assert budget.stop_reason.startswith("the clock")


def test_resumed_run_counts_its_own_steps():
    clock, ends = FakeClock(), []
    budget = TimeBudget(
        12.5, max_steps=1000, start_step=5000, on_plan=ends.append, clock=clock, log=lambda m: None, early_share=0
    )
    last = _run(budget, clock, lambda s: 0.125, start=5000)
    assert budget.history[0]["step"] == 5069 and ends[0] == 5100 and last == 5099


# ---------------------------------------------------------------------------------------------- the table


def _records():
    """benchmarks/records/benchmarks.json, with each long run's scored milestones as records of their own (benchmarks/long_run.py
    writes one record per run: its last step, and every milestone's PSNR and train seconds inside it)."""
    out = []
    for r in json.loads((REPO / "benchmarks" / "records" / "benchmarks.json").read_text()):
        out.append(r)
        for step, m in (r.get("milestones") or {}).items():
            if int(step) != r["steps"] and m.get("psnr") is not None:
                out.append({**r, "steps": int(step), "psnr": m["psnr"], "train_s": m.get("train_s"), "milestones": {}})
    return out


def _find(records, scene, method, device, steps, tag):
    return [
        r
        for r in records
        if (r["scene"], r["method"], r["device"], r["steps"], r.get("tag", "")) == (scene, method, device, steps, tag)
        and r.get("status", "ok") == "ok"
    ]


def test_every_table_point_is_its_records_mean():
    records = _records()
    for p in TABLE:
        runs = [r for tag in p.records for r in _find(records, p.scene, p.measured_as, p.device, p.steps, tag)]
        assert len(runs) == len(p.records), (p, len(runs))
        assert math.isclose(statistics.mean(r["psnr"] for r in runs), p.psnr, abs_tol=5e-4), p
        assert {r["schedule"] for r in runs} == {"default" if p.schedule == "stock" else "short"}, p
        scenes = {
            r["scene"]
            for r in records
            if (r["method"], r["device"], r["steps"]) == (p.measured_as, p.device, p.steps) and r.get("psnr")
        }
        assert p.one_scene == (len(scenes) == 1), (p, scenes)


@pytest.mark.parametrize(
    "key, runs",
    [
        (("willags-lite", "cuda"), [("fox-wild", "willags-lite", "cuda", 5000, "h200-solo")]),
        (("willags", "cuda"), [("fox-wild", "willags", "cuda", 5000, "h200-solo")]),
        (("willags-lite", "cpu"), [("default", "willags-lite", "cpu", 600, "cpu-knob")]),
        (("willags", "cpu"), [("default", "willags", "cpu", 600, "cpu-knob")]),
    ],
)
def test_step_times_are_their_records(key, runs):
    records = _records()
    found = [r for k in runs for r in _find(records, *k)]
    assert len(found) == len(runs)
    per_step = statistics.mean(r["train_s"] / r["steps"] for r in found)
    assert math.isclose(per_step, STEP_TIMES[key].seconds, rel_tol=2e-3)
    notes = " ".join(str(r.get(k, "")) for r in found for k in ("note", "run_note"))
    assert "shared" not in notes and "at once" not in notes  # alone on the device


def test_preset_defaults_are_the_method_configs():
    import willags_ns.method_configs  # noqa: F401  (registers the presets)
    from willags_ns.engine.time_budget import preset_defaults

    assert (
        preset_defaults("willags")[1] == CAPS["willags"] and preset_defaults("willags-lite")[1] == CAPS["willags-lite"]
    )


def test_presets_differ_only_in_model_steps_and_schedules():
    """apply_budget switches a preset by swapping the model config and the step cap: nothing else may differ."""
    from willags_ns import method_configs

    a, b = method_configs.willags_config(), method_configs.willags_lite_config()
    differ = {f.name for f in dataclasses.fields(a) if getattr(a, f.name) != getattr(b, f.name)}
    assert differ <= {"method_name", "max_num_iterations", "pipeline", "optimizers"}
    assert {
        f.name for f in dataclasses.fields(a.pipeline) if getattr(a.pipeline, f.name) != getattr(b.pipeline, f.name)
    } == {"model"}
    for name, group in a.optimizers.items():
        other = b.optimizers[name]
        assert group["optimizer"] == other["optimizer"], name
        if group["scheduler"] is not None:
            assert dataclasses.replace(group["scheduler"], max_steps=0) == dataclasses.replace(
                other["scheduler"], max_steps=0
            ), name


def test_apply_budget_switches_the_preset_in_the_config():
    """With the current CPU points, a 90 s budget picks lite (its 600 steps fit, willags' do not): the model config is
    swapped for the lite preset's, the user's settings kept, the steps capped at lite's default, full resolution."""
    from willags_ns import method_configs
    from willags_ns.engine.time_budget import apply_budget, preset_defaults

    config = method_configs.willags_config()
    config.machine.device_type = "cpu"
    config.pipeline.model.backend = "torch"
    choice, notes, replaced = apply_budget(config, 90.0)
    model = config.pipeline.model
    assert choice.preset == "willags-lite" and model.latent.kind == "vae" and model.backend == "torch"
    assert model.num_downscales == 0 and config.max_num_iterations == CAPS["willags-lite"]
    assert replaced == preset_defaults("willags-lite")[0].num_downscales > 0
    lite_step = STEP_TIMES[("willags-lite", "cpu")].seconds
    assert choice.steps == plan_steps(90.0, 0, 0, lite_step, 7000)
    # the learning-rate schedules stay the preset's: a short run is not decayed within its few hundred steps
    own = method_configs.willags_config().optimizers  # the invoked config's (a switch swaps only the model)
    assert {k: g["scheduler"] for k, g in config.optimizers.items()} == {k: g["scheduler"] for k, g in own.items()}
    assert config.method_name == "willags" and "your settings kept: backend" in notes[0]


def test_switching_preset_keeps_the_users_settings():
    import willags_ns.method_configs  # noqa: F401  (registers the presets)
    from willags_ns.engine.time_budget import carry_overrides, preset_defaults

    willags, _ = preset_defaults("willags")
    lite, _ = preset_defaults("willags-lite")
    user = preset_defaults("willags")[0]
    user.backend = "torch"
    user.mask.threshold = 0.9
    copied = carry_overrides(user, willags, lite)
    assert sorted(copied) == ["backend", "mask.threshold"]
    assert lite.backend == "torch" and lite.mask.threshold == 0.9
    assert lite.latent.kind == "vae"  # the lite preset's own switches are untouched


# ---------------------------------------------------------------------------------------------- a real run


@pytest.mark.timing
@pytest.mark.slow
@pytest.mark.parametrize(
    "minutes, step_s, preset",
    [(0.2, 1.0, "willags-lite"), (1.0, 5.0, "willags")],
    ids=["lite-splatfacto-densification", "willags-mcmc"],
)
def test_budget_stops_a_real_cpu_run_and_prints_its_choice(tmp_path, monkeypatch, capsys, minutes, step_s, preset):
    """`ns-train willags` under a budget on the CPU, in either preset the table picks there: willags-lite (12 s,
    splatfacto's densification) and willags (60 s, asked for MCMC's densification)."""
    from tests.test_train import _train
    from willags_ns import method_configs
    from willags_ns.splats.mcmc import McmcDensification

    monkeypatch.setattr(tb, "WARMUP_STEPS", 3)
    monkeypatch.setattr(tb, "WINDOW_STEPS", 5)
    # the trainer's clock advances step_s seconds per training step, whatever the machine's speed: the budget
    # measures step_s and plans about 12 steps
    factors = _record_rates(monkeypatch)
    _trainer_on_a_fake_clock(monkeypatch, lambda step: step_s)
    real_config = method_configs.willags_config

    def budgeted():
        config = real_config()
        config.pipeline.time_budget_minutes = minutes
        if preset == "willags":  # 'auto' densifies by splatfacto's on the CPU: ask for MCMC's to cover its schedule
            config.pipeline.model.densification = "mcmc"
        return config

    monkeypatch.setattr(method_configs, "willags_config", budgeted)
    config, trainer, losses = _train(tmp_path, "willags", steps=5000)
    out = capsys.readouterr().out
    assert f"willags time budget: {minutes:g} min" in out and "preset:" in out and "schedule:" in out
    assert "stopped after step" in out
    record = json.loads((config.get_base_dir() / "time_budget.json").read_text())
    steps = record["run"]["steps_trained"]
    assert 8 < steps <= 13 and len(losses) == steps  # past the measurement window, within the budget
    assert record["run"]["elapsed_s"] <= minutes * 60 + step_s  # at most one step past the budget
    assert record["choice"]["preset"] == preset
    # the record says whether the run densified: the Gaussians it started from and ended with, and the window
    assert record["gaussians_at_start"] > 0
    assert record["gaussians_at_end"] == trainer.pipeline.model.means.shape[0]
    strategy = trainer.pipeline.model.strategy
    assert record["densification"]["refine_every"] == strategy.refine_every
    assert record["densification"]["refine_stop_iter"] == strategy.refine_stop_iter
    saved = (config.get_base_dir() / "config.yml").read_text()
    assert f"max_num_iterations: {steps}" in saved  # config.yml says what was trained
    assert list((config.get_base_dir() / "nerfstudio_models").glob(f"step-{steps - 1:09d}.ckpt"))
    # the progress counted against the planned end, and the schedules fitted inside it
    from nerfstudio.utils import writer

    last_plan = record["run"]["plans"][-1]["end_step"] if record["run"]["plans"] else None
    if last_plan is not None:
        assert writer.GLOBAL_BUFFER["max_iter"] == last_plan
        strategy = trainer.pipeline.model.strategy
        assert isinstance(strategy, McmcDensification) == (preset == "willags")
        assert strategy.refine_start_iter + strategy.refine_every < last_plan  # it densifies within the run
        assert strategy.refine_start_iter < strategy.refine_stop_iter <= last_plan
        window = range(strategy.refine_start_iter + 1, strategy.refine_stop_iter)
        if isinstance(strategy, McmcDensification):  # MCMC never resets opacities: every refinement step counts
            assert strategy.reset_every == 0
            refines = [s for s in window if s % strategy.refine_every == 0]
        else:  # a densification step that is not in the pause after an opacity reset, before the splits stop
            refines = [
                s
                for s in window
                if s % strategy.refine_every == 0 and s % strategy.reset_every >= strategy.pause_refine_after_reset
            ]
        assert refines, (strategy.refine_every, strategy.reset_every, getattr(strategy, "pause_refine_after_reset", 0))
        assert trainer.pipeline.model.config.mask.warmup_steps < last_plan
    # a short plan: every rate at SHORT_RUN_LR_SCALE times the preset's, falling over the plan's second half
    assert record["learning_rates"] == {"scale": tb.SHORT_RUN_LR_SCALE, "cooldown": tb.SHORT_RUN_COOLDOWN, "floor": 0.0}
    assert factors[0] == pytest.approx([tb.SHORT_RUN_LR_SCALE] * len(factors[0]))
    assert max(factors[-1]) < tb.SHORT_RUN_LR_SCALE * (1 - tb.SHORT_RUN_COOLDOWN + 0.1)
    # the learning-rate schedules are the preset's, not ended at the plan
    preset_opt = real_config().optimizers  # the invoked config's (a switch swaps only the model)
    assert all(
        trainer.config.optimizers[k]["scheduler"] == g["scheduler"]
        for k, g in preset_opt.items()
        if k in trainer.config.optimizers
    )


def test_budget_progress_is_a_range_until_measured_and_counts_time():
    """The step table's numbers under a budget (time_budget.budget_progress): the plans at the table's and the run's
    own step time while unsure, the budget's time left, the share of time done; at the cap, the steps left."""
    p = tb.budget_progress(480.0, 60.0, 9, 0, None, 30000, (0.1, 0.5))
    assert (p.end_low, p.end_high, p.time_left_s, p.share) == (850, 4210, 420.0, 0.125)
    p = tb.budget_progress(480.0, 120.0, 99, 0, 700, 30000, (0.1, 0.5))  # measured: one end
    assert (p.end_low, p.end_high, p.time_left_s, p.share) == (700, 700, 360.0, 0.25)
    p = tb.budget_progress(480.0, 60.0, 49, 0, None, 100, (0.1, 0.5))  # every plan at the cap: 50 steps left
    assert (p.end_low, p.end_high, p.time_left_s) == (100, 100, 25.0)
    p = tb.budget_progress(480.0, 60.0, 109, 100, None, 30000, (0.5, float("nan")))  # resumed; no table time
    assert (p.end_low, p.end_high) == (100 + 850, 100 + 30000)
    assert tb.budget_progress(60.0, 90.0, 9, 0, 20, 30000, (1.0,)).share == 1.0  # past the budget


@pytest.mark.timing
@pytest.mark.slow
def test_the_step_table_of_a_budget_shows_time_left_and_a_share_that_only_grows(tmp_path, monkeypatch, capsys):
    """A 12-second budget whose steps take 1 s, then 0.5 s (the plan grows when re-measured: nerfstudio's step / end
    went backwards there): from the first row the table shows the planned end (a range until the run has measured
    its own steps, then one number), the share of the budget's time done, which never decreases, and, as its ETA,
    the time left of the budget."""
    import re

    from tests.test_train import _train
    from willags_ns import method_configs
    from willags_ns.engine.time_budget import table_time

    monkeypatch.setattr(tb, "WARMUP_STEPS", 3)
    monkeypatch.setattr(tb, "WINDOW_STEPS", 5)
    _trainer_on_a_fake_clock(monkeypatch, lambda step: 1.0 if step < 8 else 0.5)
    real_config = method_configs.willags_config

    def budgeted():
        config = real_config()
        config.pipeline.time_budget_minutes = 0.2
        config.logging.steps_per_log = 1
        return config

    monkeypatch.setattr(method_configs, "willags_config", budgeted)
    from willags_ns.data.synthetic import SyntheticSceneConfig, make_scene, write_scene

    tiny = SyntheticSceneConfig(num_train=8, num_test=2, width=32, height=24, num_points=400, supersample=1)
    scene = write_scene(make_scene(tiny), tmp_path / "scene")
    config, _, losses = _train(tmp_path, "willags", steps=5000, data=scene)
    out = capsys.readouterr().out
    (header,) = [ln for ln in out.splitlines() if ln.startswith("Step of plan (% time)")]
    eta_at = header.index("ETA (time)")
    rows = []
    for line in out.splitlines():
        m = re.match(r"^(\d+) of (\d+)(?:-(\d+))? \(([\d.]+)%\)", line)
        if m:
            rows.append((int(m[1]), int(m[2]), int(m[3] or m[2]), float(m[4]), line[eta_at:].split("  ")[0].strip()))
    steps = [r[0] for r in rows]
    assert steps[0] == 0 and len(set(steps)) == len(losses), out[-3000:]
    step0, low, high, share0, eta0 = rows[0]
    assert low < high  # unsure: the plans at the table's step time and at the run's own first step
    assert eta0 == table_time(12.0 - 1.0)  # the budget's time left after the first step: no estimate from the table
    shares = [r[3] for r in rows]
    assert shares == sorted(shares) and shares[-1] <= 100.0
    record = json.loads((config.get_base_dir() / "time_budget.json").read_text())
    plans = [p["end_step"] for p in record["run"]["plans"]]
    assert len(plans) >= 2 and plans[-1] > plans[0]  # the plan grew when re-measured
    measured_at = record["run"]["plans"][0]["step"]
    for step, low, high, _, _ in rows:
        if step >= measured_at:
            assert low == high and low in plans, (step, low, high, plans)


def test_slow_steps_are_measured_within_the_first_sixth_of_the_budget():
    """4.5 s steps in a 180 s budget (a loaded 2-core CPU, 800 px photos): 70 steps would outlast the budget; the plan
    comes from the run's own steps within its first sixth (2 x EARLY_SHARE and a few steps), and the run ends at its
    plan, not at the table's."""
    clock = FakeClock()
    plans: list[int] = []
    budget = TimeBudget(180.0, max_steps=30000, clock=clock, log=lambda m: None, on_plan=plans.append)
    last = _run(budget, clock, lambda s: 4.5)
    first = budget.history[0]
    assert first["elapsed_s"] <= 180 / 6 and first["step_s"] == pytest.approx(4.5)
    assert plans and plans[0] == 40  # 180 s / 4.5 s
    assert last + 1 == 40 and budget.stop_reason.startswith("reached the planned last step")


def test_fit_schedules_keeps_each_schedules_share_of_a_shorter_run():
    own = {
        "warmup_length": 500,
        "refine_every": 100,
        "stop_split_at": 15000,
        "stop_screen_size_at": 4000,
        "reset_alpha_every": 30,
        "sh_degree_interval": 1000,
        "mask.warmup_steps": 500,
        "mask.ramp_steps": 0,
    }
    long = tb.fit_schedules(own, 6000, 30000)  # the docstring's worked example: each keeps its share of the run
    assert long["warmup_length"] == 100 and long["refine_every"] == 20 and long["stop_split_at"] == 3000
    assert long["reset_alpha_every"] * long["refine_every"] == 600 and long["mask.ramp_steps"] == 0
    assert long["mask.warmup_steps"] == 100 and long["sh_degree_interval"] == 200
    # a short run densifies by the short-run schedule: from a sixth of the run, every 50 steps, until 0.8 of it,
    # and never resets opacities within it; the mask keeps its share
    short = tb.fit_schedules(own, 600, 30000)
    assert (short["warmup_length"], short["refine_every"], short["stop_split_at"]) == (100, 50, 480)
    assert short["reset_alpha_every"] * short["refine_every"] > 600 and short["mask.warmup_steps"] == 10
    assert tb.fit_schedules(own, 30000, 30000) == own and tb.fit_schedules(own, 90000, 30000) == own
    half = tb.fit_schedules(own, 15000, 30000)
    assert half["warmup_length"] == 250 and half["refine_every"] == 50 and half["reset_alpha_every"] == 30
    assert half["mask.warmup_steps"] == 250
    tiny = tb.fit_schedules(own, 12, 30000)  # never 0 (0 would switch a schedule off); still a few refinements
    assert all(v >= 1 for k, v in tiny.items() if own[k] > 0)
    assert tiny["warmup_length"] + 2 * tiny["refine_every"] < tiny["stop_split_at"] <= 12
    assert tiny["reset_alpha_every"] * tiny["refine_every"] > 12
    at = tb.fit_schedules(own, tb.SHORT_RUN_STEPS, 30000)  # from SHORT_RUN_STEPS on, the preset's shares
    assert at["refine_every"] == tb.MIN_REFINE_EVERY and at["reset_alpha_every"] * at["refine_every"] == 200
    assert tb.fit_schedules({**own, "refine_every": 4}, 6000, 30000)["refine_every"] == 4  # below the floor: kept
    assert tb.fit_schedules({**own, "refine_every": 4}, 600, 30000)["refine_every"] == 4


@pytest.mark.parametrize("mcmc", [True, False], ids=["mcmc", "splatfacto"])
def test_the_schedules_are_fitted_into_either_densification(mcmc):
    """A budget fits the refinement window and period into the strategy of either densification: MCMC's (the
    default `willags`), which has no screen-size splits and never resets opacities, and splatfacto's (gsplat's
    DefaultStrategy: willags-lite, willags-paper, willags-3dgs), whose resets keep their period in steps."""
    from types import SimpleNamespace

    from willags_ns.config import WillagsModelConfig
    from willags_ns.engine.time_budget import schedule_fitter
    from willags_ns.splats.gaussians import densification_strategy
    from willags_ns.splats.mcmc import McmcDensification

    cfg = WillagsModelConfig(densification="mcmc" if mcmc else "splatfacto")  # 30000 steps: warm-up 500, every 100
    strategy = densification_strategy(cfg, num_train=12, mcmc=mcmc)
    fit = schedule_fitter(SimpleNamespace(config=cfg, strategy=strategy), 30000)
    fit(6000)  # the fit_schedules docstring's example
    assert isinstance(strategy, McmcDensification) == mcmc
    assert (strategy.refine_start_iter, strategy.refine_every, strategy.refine_stop_iter) == (100, 20, 3000)
    assert (cfg.warmup_length, cfg.refine_every, cfg.stop_split_at) == (100, 20, 3000)
    assert cfg.sh_degree_interval == 1000  # the SH degree keeps its steps: a short run stays at degree 0
    assert cfg.mask.warmup_steps == 1000  # the mask keeps its share of the run (5000 of 30000)
    if mcmc:
        assert strategy.reset_every == 0  # never resets opacities, however short the run
    else:
        assert strategy.reset_every == 600 and strategy.refine_scale2d_stop_iter == 800
        assert strategy.pause_refine_after_reset == 20
    fit(600)  # a short run: the short-run densification, no opacity reset within it
    assert (strategy.refine_start_iter, strategy.refine_every, strategy.refine_stop_iter) == (100, 50, 480)
    assert strategy.reset_every == 0 if mcmc else strategy.reset_every > 600
    fit(30000)  # a plan of the preset's own length gives the schedules back
    assert (strategy.refine_start_iter, strategy.refine_every, strategy.refine_stop_iter) == (500, 100, 15000)
    assert strategy.reset_every == (0 if mcmc else 3000) and cfg.mask.warmup_steps == 5000


@pytest.mark.slow
def test_ns_train_prints_one_line_for_a_bad_budget(tmp_path):
    exe = console_script("ns-train")
    cmd = [str(exe), "willags", "--pipeline.time-budget-minutes", "-5", "--vis", "tensorboard"]
    out = subprocess.run(cmd + ["--output-dir", str(tmp_path)], capture_output=True, text=True, timeout=600)
    assert out.returncode == 1
    assert "willags: --pipeline.time-budget-minutes must be a finite number of minutes" in out.stderr
    assert "Traceback" not in out.stderr


@pytest.mark.parametrize(("side", "want_downscales"), [(128, 0), (256, 0), (800, "preset")])
def test_a_cpu_choice_keeps_the_resolution_schedule_for_images_larger_than_the_measured_ones(side, want_downscales):
    """The CPU points were measured at full resolution on 128 px images; on 800 px photos a full-resolution CPU step
    took 12.9 s (19 steps in 4 minutes), so larger images keep the preset's resolution schedule."""
    from types import SimpleNamespace

    import torch

    from willags_ns import method_configs
    from willags_ns.engine.time_budget import apply_budget, preset_defaults, resolution_for_images
    from willags_ns.engine.trainer import WillagsTrainer

    config = method_configs.willags_config()
    config.machine.device_type = "cpu"
    choice, notes, replaced = apply_budget(config, 600.0)
    assert not choice.keep_resolution_schedule and config.pipeline.model.num_downscales == 0
    trainer = WillagsTrainer.__new__(WillagsTrainer)
    cams = SimpleNamespace(width=torch.tensor([[side], [side // 2]]), height=torch.tensor([[side * 3 // 4], [side]]))
    trainer.config = config
    trainer.pipeline = SimpleNamespace(
        datamanager=SimpleNamespace(train_dataset=SimpleNamespace(cameras=cams)),
        model=SimpleNamespace(config=config.pipeline.model),
    )
    trainer.budget_record = {"notes": list(notes)}
    trainer.local_rank = 1  # no config.yml written here
    resolution_for_images(trainer, replaced)
    preset = preset_defaults(choice.preset)[0].num_downscales
    assert preset > 0 and replaced == preset
    want = preset if want_downscales == "preset" else want_downscales
    assert config.pipeline.model.num_downscales == want
    kept = [n for n in trainer.budget_record["notes"] if "resolution schedule kept" in n]
    assert (f"up to {side} px" in kept[0]) if want else not kept
    assert tb.full_resolution_suits(side) == (want == 0)


def test_the_users_own_resolution_schedule_is_kept_and_not_restored():
    """--pipeline.model.num-downscales set by the user: the budget leaves it (and says so), and reports nothing for the
    trainer to put back for large images."""
    from willags_ns import method_configs
    from willags_ns.engine.time_budget import apply_budget

    config = method_configs.willags_config()
    config.machine.device_type = "cpu"
    config.pipeline.model.num_downscales = 1
    choice, notes, replaced = apply_budget(config, 600.0)
    assert not choice.keep_resolution_schedule and config.pipeline.model.num_downscales == 1
    assert replaced is None and "your --pipeline.model.num-downscales 1 kept" in notes


def test_trainer_takes_a_budget_on_several_devices(tmp_path: Path):
    """With a budget and world_size 2 willags' trainer goes on to build the pipeline (it then stops there: no process
    group in this test) rather than refusing the budget first."""
    from willags_ns import method_configs
    from willags_ns.engine.distributed import DataParallelError

    config = method_configs.willags_config()
    config.output_dir, config.machine.device_type = tmp_path, "cpu"
    config.pipeline.time_budget_minutes = 1.0
    with pytest.raises(DataParallelError):
        config.setup(local_rank=0, world_size=2).setup()


@pytest.mark.slow
def test_budget_on_two_ranks_stops_both_after_the_same_step(tmp_path, monkeypatch):
    """Two CPU ranks through nerfstudio's launcher under a budget of a few seconds: the ranks measure their steps,
    agree on the plan and on the clock, and stop after the same step with the same parameters."""
    from nerfstudio.scripts.train import launch

    from tests._distributed_launch import record_path, train_and_record
    from tests.engine.test_distributed import _tiny_config
    from willags_ns.data.synthetic import SyntheticSceneConfig, ensure_default_scene

    scene_cfg = SyntheticSceneConfig(num_train=6, num_test=1, width=32, height=24, num_points=400, supersample=1)
    config = _tiny_config(tmp_path, ensure_default_scene(scene_cfg, root=tmp_path / "scenes"))
    config.method_name = "willags-3dgs"  # a method named explicitly keeps its model: only the steps follow the budget
    config.max_num_iterations = 400
    config.pipeline.time_budget_minutes = 0.05  # 3 s
    config.pipeline.data_parallel.step_profile = False
    config.set_timestamp()
    config.save_config()
    monkeypatch.setenv("WILLAGS_TEST_BUDGET_STEPS", "2,3,5")
    launch(main_func=train_and_record, num_devices_per_machine=2, device_type="cpu", config=config)
    r0, r1 = (torch.load(record_path(config, r), weights_only=False) for r in range(2))
    assert len(r0["images"]) == len(r1["images"]) < 400
    for k in r0["final"]:
        assert torch.equal(r0["final"][k], r1["final"][k]), k
    record = json.loads((Path(config.get_base_dir()) / "time_budget.json").read_text())
    assert record["run"]["steps_trained"] == len(r0["images"]) and record["run"]["plans"]
