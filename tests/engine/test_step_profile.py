"""willags_ns/engine/step_profile.py on the CPU (host clock): the spans between marks, a step's row written when the next
one starts, the files and the start-up phases."""

import json

import torch

from willags_ns.engine.step_profile import SPANS, StepProfile, spans_ms


def test_spans_are_differences_of_their_marks():
    times = {"start": 1.0, "forward_end": 1.004, "reduce_start": 1.010, "reduce_end": 1.011}
    got = spans_ms(times)
    assert set(got) == {"forward", "backward", "reduce"}  # spans whose two marks were set
    assert abs(got["forward"] - 4.0) < 1e-9 and abs(got["backward"] - 6.0) < 1e-9 and abs(got["reduce"] - 1.0) < 1e-9
    assert SPANS["collective"] == ("collective_start", "collective_end")


def test_rows_phases_and_files(tmp_path):
    profile = StepProfile(tmp_path, rank=1, world_size=2, device=torch.device("cpu"), meta={"reduction": "buffer"})
    profile.phase("pipeline_init", 10.0)
    profile.mark("reduce_start")  # before the first step: ignored
    for step in range(3):
        profile.mark("start")
        profile.note(step=step, image=2 * step + 1)
        for mark in ("forward_end", "reduce_start", "collective_start", "collective_end", "reduce_end"):
            profile.mark(mark)
        profile.note(bytes=400)
        profile.mark("optimizer_end")
        profile.mark("callbacks_end")
    profile.flush(final=True)
    rows = [json.loads(x) for x in (tmp_path / "rank1.jsonl").read_text().splitlines()]
    assert [(r["step"], r["image"], r["bytes"]) for r in rows] == [(0, 1, 400), (1, 3, 400), (2, 5, 400)]
    for r in rows:
        spans = [r[f"h_{k}"] for k in ("forward", "backward", "pack", "collective", "unpack", "optimizer", "callbacks")]
        assert all(v >= 0 for v in spans) and r["h_iteration"] >= sum(spans) - 1e-6
        assert "d_iteration" not in r  # no CUDA events on the CPU
    meta = json.loads((tmp_path / "rank1.json").read_text())
    assert meta["rank"] == 1 and meta["world_size"] == 2 and meta["reduction"] == "buffer"
    assert meta["steps_written"] == 3 and meta["phases"]["pipeline_init"] == 10.0
    assert meta["phases"]["first_step"] <= meta["phases"]["train_end"]
