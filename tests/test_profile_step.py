"""benchmarks/profile_step.py: a window of training steps under the profiler, on the CPU (the GPU run is a benchmark)."""

import json
import traceback

import pytest

from benchmarks import profile_step
from tests._scenes import small_scene


def test_a_sync_is_attributed_to_the_innermost_project_line():
    fs = traceback.FrameSummary
    stack = [
        fs("/x/site-packages/nerfstudio/engine/trainer.py", 500, "train_iteration"),
        fs("/x/willags_ns/model.py", 369, "_image_idx"),
        fs("/x/site-packages/torch/_tensor.py", 10, "__int__"),
    ]
    assert profile_step.sync_site(stack) == "willags_ns/model.py:369"
    assert profile_step.sync_site([fs("/x/torch/foo.py", 1, "f")]) == "?"


def test_profiling_a_window_of_willags_steps_on_the_cpu(tmp_path):
    data = small_scene(
        tmp_path / "scene", appearance=1.0, transients=0.3, num_train=12, width=64, height=48, num_points=1500
    )
    out = tmp_path / "prof.json"
    args = ["--method", "willags", "--data", str(data), "--warmup", "6", "--steps", "3", "--out", str(out)]
    assert profile_step.main([*args, "--lap-every", "2", "--run-dir", str(tmp_path / "run")]) == 0
    rec = json.loads(out.read_text())
    # the warm-up in laps of 2 steps; steps 2 and 4 are clocked alone (step 0 has no lap before it)
    assert [lap["steps"] for lap in rec["laps"]] == [2, 4, 6]
    assert rec["laps"][0]["event_ms"] is None and rec["laps"][0]["ordinary_ms"] is None
    assert all(lap["event_ms"] > 0 and lap["ordinary_ms"] is not None for lap in rec["laps"][1:])
    assert all(lap["step_ms"] > 0 and lap["gaussians"] > 0 for lap in rec["laps"])
    assert (rec["method"], rec["scene"], rec["device"], rec["steps"]) == ("willags", "scene", "cpu", 3)
    assert rec["wall_ms"] > 0 and rec["num_gaussians"] > 0
    assert rec["device_ms"] == 0 and rec["syncs"] == 0  # nothing waits on a CPU
    assert rec["launches"] == rec["aten_ops"] > 50  # a step is hundreds of operators
    assert rec["top_host"] and all(r["self_ms"] >= 0 and r["calls"] > 0 for r in rec["top_host"])
    # the backward pass's nodes: counted a step, the commonest first, every count within the total
    nodes = rec["top_backward_nodes"]
    assert rec["backward_nodes"] > 10 and any(n["node"].startswith("MulBackward") for n in nodes)
    assert [n["calls"] for n in nodes] == sorted((n["calls"] for n in nodes), reverse=True)
    assert sum(n["calls"] for n in nodes) <= rec["backward_nodes"] + 1e-9
    assert not any(n["node"].startswith("autograd::") for n in nodes)
    parts = rec["components"]
    # the model's forward, its colours inside it, the loss and the optimisers: once per step each, with operators
    for name in (
        "model.get_outputs",
        "model.appearance_colors",
        "model.get_loss_dict",
        "optimizers.optimizer_scaler_step_some",
    ):
        assert parts[name]["calls"] == pytest.approx(1.0), name
        assert parts[name]["launches"] > 0 and parts[name]["host_ms"] > 0, name
    # nested: the colours are part of the forward
    assert parts["model.appearance_colors"]["launches"] < parts["model.get_outputs"]["launches"]
    assert parts["model.appearance_colors"]["host_ms"] < parts["model.get_outputs"]["host_ms"]


def test_a_window_of_no_steps_is_refused(tmp_path):
    with pytest.raises(SystemExit, match="--warmup and --steps must be >= 1"):
        profile_step.main(["--method", "willags", "--data", "x", "--steps", "0", "--out", str(tmp_path / "o")])


def test_a_components_device_time_and_launches_are_what_ran_inside_its_label():
    from types import SimpleNamespace as Event

    launch = Event(name="cudaLaunchKernel", cpu_children=[])
    op = Event(name="aten::mul", cpu_children=[launch, Event(name="cudaLaunchKernel", cpu_children=[])])
    forward = Event(name="step/model.get_outputs", cpu_children=[op], cpu_time_total=2000.0, device_time_total=500.0)
    other = Event(name="aten::add", cpu_children=[launch], cpu_time_total=1.0, device_time_total=9.0)
    out = profile_step.component_summary([forward, other, forward], steps=2, on_cuda=True)
    assert out == {
        "model.get_outputs": {
            "host_ms": 2.0,
            "device_ms": 0.5,
            "launches": 2.0,
            "calls": 1.0,
            "ops": {"aten::mul": 1.0},
        }
    }


def test_a_components_own_calls_are_its_outermost_operators_outside_nested_labels():
    from types import SimpleNamespace as Event

    def ev(name, *children):
        return Event(name=name, cpu_children=list(children))

    linear = ev("aten::linear", ev("aten::t"), ev("aten::addmm", ev("cudaLaunchKernel")))
    nested = ev("step/model._rasterize", ev("aten::add"), ev("aten::add"))
    wrapper = ev("some python function", ev("aten::mul"), ev("aten::mul"))  # not an operator: looked through
    forward = ev("step/model.get_outputs", linear, nested, wrapper, ev("aten::mul"))
    assert sorted(profile_step.own_ops(forward)) == ["aten::linear", "aten::mul", "aten::mul", "aten::mul"]
    assert list(profile_step.own_ops(nested)) == ["aten::add", "aten::add"]


def test_a_lap_splits_into_its_refining_step_and_the_others():
    # laps of 100 steps: the first (steps 0..99) holds no clocked step, the second's step 100 took 300 ms
    laps = [[100, 1.0, 1000], [200, 2.5, 1500]]
    rows = profile_step.lap_rows(laps, {100: 300.0})
    assert rows[0] == {"steps": 100, "gaussians": 1000, "step_ms": 10.0, "event_ms": None, "ordinary_ms": None}
    assert rows[1]["step_ms"] == pytest.approx(15.0) and rows[1]["event_ms"] == 300.0
    assert rows[1]["ordinary_ms"] == pytest.approx((1500.0 - 300.0) / 99)


def test_a_lap_of_one_step_is_refused(tmp_path):
    with pytest.raises(SystemExit, match="--lap-every must be 0 or >= 2"):
        profile_step.main(["--method", "willags", "--data", "x", "--lap-every", "1", "--out", str(tmp_path / "o")])
