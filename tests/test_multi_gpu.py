"""benchmarks/multi_gpu.py's pure parts: the runs it understands, the schedules it divides, and how it reads the
ranks' step profiles into a breakdown (transfer, wait) and the goals."""

import pytest

from benchmarks.multi_gpu import Run, breakdown, eval_gpus, parse_runs, scale_schedules, startup, steps_of, tables


def test_runs_name_devices_machines_reduction_and_images():
    runs = parse_runs("4, 1,2x2@2000,4:reference")
    assert runs == [Run(4), Run(1), Run(2, 2, "buffer", 2000), Run(4, 1, "reference")]
    assert [r.name for r in runs] == ["gpus4", "gpus1", "gpus2x2-2000", "gpus4-reference"]
    assert runs[2].total == 4 and steps_of(2000, 4) == 500
    with pytest.raises(ValueError, match="not a multiple"):
        steps_of(8000, 3)
    with pytest.raises(ValueError, match="unknown reduction"):
        parse_runs("2:ddp")


def test_schedules_are_divided_by_the_devices():
    import willags_ns.method_configs  # noqa: F401
    from willags_ns.engine.trainer import PRESET_CONFIGS

    one, four = PRESET_CONFIGS["willags"](), PRESET_CONFIGS["willags"]()
    assert scale_schedules(one, 1)["refine_every"] == one.pipeline.model.refine_every == 100
    done = scale_schedules(four, 4)
    m = four.pipeline.model
    assert (m.refine_every, m.warmup_length, m.resolution_schedule, m.stop_split_at) == (25, 125, 750, 3750)
    assert m.mask.teacher.tau == pytest.approx(0.99**4) and done["means.max_steps"] == 7500
    assert four.optimizers["camera_opt"]["scheduler"].warmup_steps == 250


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


def test_summary_compares_with_the_one_gpu_run_and_states_the_goals():
    def result(name, n, step_ms, wall):
        return {
            "name": name, "num_devices": n, "machines": 1, "reduction": "buffer", "images": 8000,
            "steps": 8000 // n, "status": "ok", "train_wall_s": wall, "breakdown": {"iteration": step_ms},
        }  # fmt: skip

    text = tables([result("gpus1", 1, 11.0, 160.0), result("gpus4", 4, 13.0, 60.0), result("gpus2", 2, 12.5, 95.0)])
    assert "4 GPUs: throughput 3.38x (goal >= 3.2x: met), wall 2.67x at 8000 images" in text
    assert "2 GPUs: throughput 1.76x (goal >= 1.8x: NOT met)" in text


def test_records_of_several_gpus_have_their_own_section():
    from benchmarks.multi_gpu import record
    from benchmarks.tables import devices_section

    class Args:
        data, method, device_type, tag, images, runs, seed = "/x/reichstag", "willags", "cuda", "t", 8000, "4,1", 42

    base = {"machines": 1, "reduction": "buffer", "images": 8000, "status": "ok", "psnr": 19.4}
    one = record({**base, "name": "gpus1", "num_devices": 1, "steps": 8000, "breakdown": {"iteration": 11.0}}, Args)
    four = record({**base, "name": "gpus4", "num_devices": 4, "steps": 2000, "breakdown": {"iteration": 13.75}}, Args)
    assert (four["num_devices"], four["steps"], four["tag"], four["images_per_s"]) == (4, 2000, "t-gpus4", 4000 / 13.75)
    text = "\n".join(devices_section([four, one]))
    assert "### reichstag (t)" in text
    assert "| 4 | 1 | buffer | 2000 | 8000 | ok | n/a | 13.75 | 3.20 | 19.40 | n/a |" in text


def test_evaluations_stay_on_the_gpus_the_script_was_given():
    assert eval_gpus(None, 4) == ["0", "1", "2", "3"]
    assert eval_gpus("", 2) == ["0", "1"]
    assert eval_gpus("2,3", 4) == ["2", "3"]  # another job trains on GPUs 0-1 of the host
    assert eval_gpus("1", 4) == ["1"]
    assert eval_gpus("0, 1,2,3", 2) == ["0", "1"]
