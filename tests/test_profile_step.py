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
    args = ["--method", "willags", "--data", str(data), "--warmup", "2", "--steps", "3", "--out", str(out)]
    assert profile_step.main([*args, "--run-dir", str(tmp_path / "run")]) == 0
    rec = json.loads(out.read_text())
    assert (rec["method"], rec["scene"], rec["device"], rec["steps"]) == ("willags", "scene", "cpu", 3)
    assert rec["wall_ms"] > 0 and rec["num_gaussians"] > 0
    assert rec["device_ms"] == 0 and rec["syncs"] == 0  # nothing waits on a CPU
    assert rec["launches"] == rec["aten_ops"] > 50  # a step is hundreds of operators
    assert rec["top_host"] and all(r["self_ms"] >= 0 and r["calls"] > 0 for r in rec["top_host"])


def test_a_window_of_no_steps_is_refused(tmp_path):
    with pytest.raises(SystemExit, match="--warmup and --steps must be >= 1"):
        profile_step.main(["--method", "willags", "--data", "x", "--steps", "0", "--out", str(tmp_path / "o")])
