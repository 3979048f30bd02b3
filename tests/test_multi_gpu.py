"""benchmarks/multi_gpu.py's parts that need no GPU: the runs it understands, the GPUs each run takes, the schedules
it divides (on the configs it builds today), how it reads the ranks' step profiles into a breakdown, a budget run's
stop and the wall time to the last checkpoint, and its records."""

import json
import os
from types import SimpleNamespace

import pytest

from benchmarks.multi_gpu import (
    WALL_MEANS,
    Run,
    breakdown,
    build_config,
    collect,
    eval_gpus,
    gpu_list,
    gpus_of_run,
    main,
    parse_runs,
    record,
    startup,
    steps_of,
    tables,
)


def _args(runs: str, seed: int, commit: str | None) -> SimpleNamespace:
    """The command line `record` reads: reichstag, willags on CUDA, tag "t", 8000 images."""
    return SimpleNamespace(
        data="/x/reichstag", method="willags", device_type="cuda", tag="t", images=8000, runs=runs, seed=seed,
        commit=commit,
    )  # fmt: skip


def test_runs_name_devices_machines_reduction_budget_and_images():
    runs = parse_runs("4, 1,2x2@2000,4:reference,4:budget1,2x2:budget1.5")
    assert runs == [
        Run(4),
        Run(1),
        Run(2, 2, "buffer", 2000),
        Run(4, 1, "reference"),
        Run(4, budget_minutes=1.0),
        Run(2, 2, budget_minutes=1.5),
    ]
    names = [r.name for r in runs]
    assert names == ["gpus4", "gpus1", "gpus2x2-2000", "gpus4-reference", "gpus4-budget1", "gpus2x2-budget1.5"]
    assert runs[2].total == 4 and steps_of(2000, 4) == 500
    with pytest.raises(ValueError, match="not a multiple"):
        steps_of(8000, 3)
    for bad, why in (("2:ddp", "unknown modifier"), ("4:budget", "budget<minutes>"), ("4:budget0", "> 0")):
        with pytest.raises(ValueError, match=why):
            parse_runs(bad)
    with pytest.raises(ValueError, match="no run"):
        parse_runs(" , ")


def test_a_noshard_run_caches_every_image_on_every_rank_and_says_so_in_its_name():
    runs = parse_runs("2,2:noshard,2:reference:noshard@400")
    assert [r.shard for r in runs] == [True, False, False]
    assert [r.name for r in runs] == ["gpus2", "gpus2-noshard", "gpus2-reference-noshard-400"]
    assert build_config(_spec(2)).pipeline.data_parallel.shard_image_cache is True
    config = build_config(_spec(2) | {"shard_image_cache": False, "eval_max_images": 32})
    assert config.pipeline.data_parallel.shard_image_cache is False
    assert config.pipeline.eval_protocol.max_images == 32  # what ns-eval scores, read from the run's config.yml


def test_a_run_takes_the_first_gpus_of_the_list_and_each_machine_its_group():
    assert gpu_list("2,3", "0,1,2,3", 4) == ["2", "3"]  # --gpus wins
    assert gpu_list(None, "1, 3", 4) == ["1", "3"]  # else what the environment gives
    assert gpu_list(None, "", 2) == ["0", "1"]
    assert gpus_of_run(["2", "3"], Run(1)) == [["2"]]
    assert gpus_of_run(["0", "1", "2", "3"], Run(2, 2)) == [["0", "1"], ["2", "3"]]
    with pytest.raises(ValueError, match="needs 4 GPUs"):
        gpus_of_run(["2", "3"], Run(4))
    assert eval_gpus(["2", "3"], 4) == ["2", "3"]
    assert eval_gpus(["0", "1", "2", "3"], 2) == ["0", "1"]


def _spec(devices: int, machines: int = 1, budget=None, method="willags") -> dict:
    n = devices * machines
    return {
        "name": "x", "method": method, "data": "/nowhere/reichstag", "devices": devices, "machines": machines,
        "device_type": "cuda", "seed": 7, "steps": 30000 // n, "reduction": "buffer", "budget_minutes": budget,
        "output_dir": "/tmp/mg", "dist_url": "auto",
    }  # fmt: skip


def _steps(config) -> dict:
    """Every step-counted setting scale_schedules divides (by their names today), read from a built config."""
    m = config.pipeline.model
    out = {k: getattr(m, k) for k in ("warmup_length", "refine_every", "stop_split_at", "stop_screen_size_at")}
    out |= {"resolution_schedule": m.resolution_schedule, "sh_degree_interval": m.sh_degree_interval}
    out |= {"mask.warmup_steps": m.mask.warmup_steps, "mask.health.window": m.mask.health.window}
    for group, settings in config.optimizers.items():
        if settings.get("scheduler") is not None:
            out[f"{group}.max_steps"] = settings["scheduler"].max_steps
            out[f"{group}.warmup_steps"] = getattr(settings["scheduler"], "warmup_steps", 0)
    return out


def test_configs_on_several_devices_divide_every_step_counted_setting():
    one = build_config(_spec(1))
    base = _steps(one)
    assert base["refine_every"] == 100 and base["means.max_steps"] == 30000 and base["camera_opt.warmup_steps"] == 1000
    assert one.machine.num_devices == 1 and one.machine.seed == 7 and one.max_num_iterations == 30000
    assert one.pipeline.data_parallel.step_profile and one.pipeline.time_budget_minutes is None
    tau = one.pipeline.model.mask.teacher.tau
    for devices, machines in ((2, 1), (4, 1), (2, 2)):
        config = build_config(_spec(devices, machines))
        n = devices * machines
        assert (config.machine.num_devices, config.machine.num_machines) == (devices, machines)
        assert config.max_num_iterations == 30000 // n
        for field, value in _steps(config).items():
            assert value == (max(1, round(base[field] / n)) if base[field] else 0), field
        assert config.pipeline.model.mask.teacher.tau == pytest.approx(tau**n)
        assert config.pipeline.model.reset_alpha_every == one.pipeline.model.reset_alpha_every  # counts refinements
    assert (base["warmup_length"], base["stop_split_at"]) == (500, 15000)
    # MCMC's refinement window and period are these fields (splats/mcmc.py)
    from willags_ns.splats.mcmc import mcmc_strategy

    strategy = mcmc_strategy(build_config(_spec(4)).pipeline.model)
    assert (strategy.refine_start_iter, strategy.refine_every, strategy.refine_stop_iter) == (125, 25, 3750)


def test_a_budget_run_keeps_the_schedules_and_caps_the_steps():
    config = build_config(_spec(2, 2, budget=1.5))
    assert config.pipeline.time_budget_minutes == 1.5 and config.max_num_iterations == 7500
    assert _steps(config) == _steps(build_config(_spec(1)))
    with pytest.raises(ValueError, match="no data-parallel pipeline"):
        build_config(_spec(1, method="splatfacto"))


def _rows(rank: int, n: int = 8) -> list[dict]:
    """Device spans of 8 steps on a rank: rank 1 reaches the all-reduce 2 ms later, so rank 0 waits there."""
    late = 2.0 * rank
    rows = []
    for step in range(n):
        spans = {"forward": 4.0 + late, "backward": 3.0, "pack": 0.5, "collective": 2.5 - late, "unpack": 0.1}
        spans.update({"optimizer": 0.9, "callbacks": 1.0})
        row = {f"d_{k}": v for k, v in spans.items()} | {f"h_{k}": v for k, v in spans.items()}
        row.update({"step": step, "d_iteration": 13.0, "h_iteration": 13.2, "bytes": 4e6, "host_reads": 0})
        row.update({"gaussians": 1000 + step, "pixels": 640})
        rows.append(row)
    return rows


def test_breakdown_splits_the_all_reduce_into_transfer_and_wait():
    meta = {"phases": {"pipeline_init": 105.0, "first_step": 130.0}}
    profile = {0: (meta, _rows(0)), 1: ({"phases": {"first_step": 131.0}}, _rows(1))}
    b = breakdown(profile)
    assert b["clock"] == "device" and b["steps"] == 2  # the last quarter of 8 steps
    assert b["transfer"] == 0.5 and b["wait"] == 1.0 and b["wait_spread"] == 2.0  # rank 0 waits 2 ms, rank 1 none
    assert b["forward"] == 5.0 and b["iteration"] == 13.0
    assert b["rest"] == pytest.approx(13.0 - (5.0 + 3.0 + 0.5 + 1.5 + 0.1 + 0.9 + 1.0))
    assert b["gaussians_end"] == 1007 and b["bytes"] == 4e6
    assert startup(profile, 100.0) == {"pipeline_init": 5.0, "first_step": 30.0, "first_step_last_rank": 31.0}


def _write_run(run_dir, steps_per_rank: list[int], t_launch: float) -> None:
    """A run folder as a finished budget run leaves it: each rank's step profile, time_budget.json, checkpoints."""
    prof = run_dir / "step_profile"
    prof.mkdir(parents=True)
    for rank, n in enumerate(steps_per_rank):
        meta = {"rank": rank, "device": "NVIDIA H200", "host": "h", "cpu_count": 64}
        meta["phases"] = {"first_step": t_launch + 40.0 + rank, "train_end": t_launch + 100.0 + rank}
        if rank == 0:
            meta |= {"peak_host_bytes": 2.5e9, "peak_device_bytes": 7.5e8}
        (prof / f"rank{rank}.json").write_text(json.dumps(meta))
        (prof / f"rank{rank}.jsonl").write_text("".join(json.dumps(r) + "\n" for r in _rows(rank, n)))
    run = {"budget_s": 60.0, "elapsed_s": 59.2, "stopped_after_step": steps_per_rank[0] - 1, "stop_reason": "budget"}
    (run_dir / "time_budget.json").write_text(json.dumps({"preset": "willags", "run": run}))
    models = run_dir / "nerfstudio_models"
    models.mkdir()
    for step, mtime in ((100, t_launch + 50.0), (7, t_launch + 104.5)):  # the last written counts, not the highest
        path = models / f"step-{step:09d}.ckpt"
        path.write_bytes(b"x")
        os.utime(path, (mtime, mtime))


@pytest.mark.parametrize("steps, same", [([8, 8], True), ([8, 6], False)])
def test_a_budget_run_records_each_ranks_last_step_and_its_time(tmp_path, steps, same):
    t_launch = 1_000_000.0
    _write_run(tmp_path, steps, t_launch)
    res = {"name": "gpus2-budget1", "num_devices": 2, "machines": 1, "reduction": "buffer", "images": 8000}
    res |= {"steps": 4000, "status": "ok", "budget_minutes": 1.0}
    collect(res, tmp_path, t_launch)
    assert res["last_steps"] == [steps[0] - 1, steps[1] - 1] and res["same_last_step"] is same
    assert res["steps_trained"] == min(steps)
    assert res["wall_s"] == 104.5 and res["checkpoint"] == "step-000000007.ckpt"
    assert (res["budget_s"], res["budget_elapsed_s"], res["budget_used"]) == (60.0, 59.2, round(59.2 / 60, 4))
    assert res["train_span_s"] == [60.0, 60.0] and res["startup"]["first_step"] == 40.0
    assert res["machine"] == "2x NVIDIA H200 (h, 64 CPUs)"

    rec = record(res, _args(runs="2", seed=5, commit="abc"))
    assert (rec["num_devices"], rec["num_machines"], rec["seed"], rec["commit"]) == (2, 1, 5, "abc")
    assert rec["tag"] == "t-gpus2-budget1" and rec["wall_s"] == 104.5 and rec["wall_s_means"] == WALL_MEANS
    assert rec["same_last_step"] is same and rec["images_cap"] == 8000 and rec["time_budget_minutes"] == 1.0
    assert rec["images"] == 2 * min(steps)  # seen: the budget, not the cap, ended the run
    assert rec["images_per_s"] == pytest.approx(2000 / 13.0) and rec["steps"] == min(steps)
    summary = tables([res])
    assert f"same {same}" in summary and "elapsed 59.2 s of 60 s" in summary
    # each rank's peak memory, from its step profile (rank 1 wrote none of it)
    assert res["peak_host_gb"] == [2.5, None] and res["peak_device_gb"] == [0.75, None]
    assert rec["peak_host_gb_per_rank"] == [2.5, None] and rec["shard_image_cache"] is True
    assert "2.50 / 0.75, - / -  (host, all ranks: 2.50)" in summary


def test_summary_compares_with_the_one_gpu_run_and_states_the_goals():
    def result(name, n, step_ms, wall):
        return {
            "name": name, "num_devices": n, "machines": 1, "reduction": "buffer", "images": 8000,
            "steps": 8000 // n, "status": "ok", "wall_s": wall, "breakdown": {"iteration": step_ms},
        }  # fmt: skip

    text = tables([result("gpus1", 1, 11.0, 160.0), result("gpus4", 4, 13.0, 60.0), result("gpus2", 2, 12.5, 95.0)])
    assert "4 GPUs: throughput 3.38x (goal >= 3.2x: met), wall 2.67x at 8000 images" in text
    assert "2 GPUs: throughput 1.76x (goal >= 1.8x: NOT met)" in text


def test_records_of_several_gpus_have_their_own_table():
    from benchmarks.tables import devices_table, kind

    args = _args(runs="4,1", seed=42, commit=None)
    base = {"machines": 1, "reduction": "buffer", "images": 8000, "status": "ok", "psnr": 19.4}
    one = record({**base, "name": "gpus1", "num_devices": 1, "steps": 8000, "breakdown": {"iteration": 11.0}}, args)
    four = record({**base, "name": "gpus4", "num_devices": 4, "steps": 2000, "breakdown": {"iteration": 13.75}}, args)
    assert (four["num_devices"], four["steps"], four["tag"], four["images_per_s"]) == (4, 2000, "t-gpus4", 4000 / 13.75)
    assert kind(four) == "devices" and four["seed"] == 42
    text = "\n".join(devices_table([four, one]))
    assert "| reichstag | t-gpus4 | 4 | 1 | 2000 | 8000 | – | 13.75 | 3.20 | 19.40 | – |" in text


def test_the_command_line_checks_the_runs_and_gpus_before_training(tmp_path, capsys):
    args = ["run", "--data", str(tmp_path), "--out", str(tmp_path / "out"), "--work", str(tmp_path / "w")]
    assert main([*args, "--runs", "4", "--gpus", "2,3"]) == 2
    assert "needs 4 GPUs, --gpus gives 2" in capsys.readouterr().err
    assert main([*args, "--runs", "2:ddp"]) == 2
    assert main([*args, "--runs", "1", "--method", "nope"]) == 2
    assert "unknown --method 'nope'" in capsys.readouterr().err
    # a budget run without @N is capped at the method's own 30000 steps per device, not at --images
    assert main([*args, "--runs", "1,2:budget1", "--gpus", "2,3", "--dry-run", "--commit", "abc"]) == 0
    out = capsys.readouterr().out
    assert "gpus1: 1 GPUs (['2'])" in out and "gpus2-budget1: 2 GPUs (['2,3']), 30000 steps at most" in out
    records = json.loads((tmp_path / "out" / "multi_gpu_records.json").read_text())
    assert [(r["status"], r["commit"], r["seed"]) for r in records] == [("dry-run", "abc", 42)] * 2
