"""benchmarks/curves.py on synthetic records: GPU-sharing labels, milestone times, points, Pareto marks, the times of
a step count, the markdown and the PNG; and benchmarks/long_run.py recording what the curves need."""

import json

import pytest

from benchmarks import curves
from benchmarks.curves import (
    Point,
    Sharing,
    gpu_sharing,
    has_curve,
    milestone_train_s,
    pareto_flags,
    scene_points,
    step_curve,
    step_time,
)

ALONE = Sharing("alone", 1, "test")
SHARED = Sharing("shared", 4, "test")


def _grid(method, steps, psnr, train_s, tag="t", scene="reichstag", **extra):
    return {
        "scene": scene,
        "method": method,
        "device": "cuda",
        "steps": steps,
        "tag": tag,
        "psnr": psnr,
        "train_s": train_s,
        "status": "ok",
        "machine": "NVIDIA H100 80GB HBM3 (16 CPU cores)",
        **extra,
    }


def _long(method, milestones, segments, tag="long", scene="reichstag", **extra):
    return {
        "scene": scene,
        "method": method,
        "device": "cuda",
        "kind": "long_run",
        "steps": 30000,
        "tag": tag,
        "status": "ok",
        "milestones": milestones,
        "segments": segments,
        "machine": "NVIDIA H200 (16 CPU cores)",
        **extra,
    }


# ---------------------------------------------------------------------------------------------- sharing labels


NOTE_SHARING = {"state": "shared", "runs": 12, "why": "concurrent_runs, note"}


@pytest.mark.parametrize(
    "rec, state, runs, why",
    [
        ({"concurrent_runs": 3}, "shared", 3, "concurrent_runs"),
        ({"concurrent_runs": 1, "segments": [{"concurrent_runs": 4}]}, "shared", 4, "concurrent_runs, segments"),
        ({"concurrent_runs": 1, "segments": [{"train_s": 1.0}]}, "alone", 1, "concurrent_runs"),
        ({"concurrent_runs": None}, "unknown", None, ""),  # a grid run not told
        ({"concurrent_runs": 9, "gpu_sharing": NOTE_SHARING}, "shared", 12, "concurrent_runs, note"),  # carried
        ({}, "unknown", None, ""),
    ],
)
def test_gpu_sharing_reads_what_the_record_says(rec, state, runs, why):
    assert gpu_sharing(rec) == Sharing(state, runs, why)


def test_sharing_labels_say_shared_gpu_times():
    assert Sharing("shared", 12, "note").label() == "shared, up to 12 runs"
    assert Sharing("shared", None, "grid").label() == "shared, count not recorded"
    assert Sharing("alone", 1, "x").label() == "alone" and Sharing("unknown", None, "").label() == "not recorded"


# ---------------------------------------------------------------------------------------------- points


def test_milestone_times_are_measured_never_interpolated():
    rec = _long(
        "willags",
        {"7000": {"psnr": 1}, "15000": {"psnr": 2, "train_s": 150.0}, "24227": {"psnr": 3}, "30000": {"psnr": 4}},
        [{"end_step": 24226, "train_s": 240.0}, {"end_step": 29999, "train_s": 60.0}],
    )
    assert milestone_train_s(rec, "15000") == 150.0  # its own (benchmarks/long_run.py records it now)
    assert milestone_train_s(rec, "24227") == 240.0 and milestone_train_s(rec, "30000") == 300.0  # segment ends
    assert milestone_train_s(rec, "7000") is None  # inside an older segment


def test_scene_points_from_milestones_and_grid_runs():
    records = [
        _grid("willags", 5000, 19.0, 200.0, tag="a", concurrent_runs=2),
        _grid("peer", 5000, 19.5, 300.0, tag="a", seed=43),
        _grid("willags", 5000, 30.0, 10.0, tag="dirty", tree_note="not a clean record"),
        _grid("willags", 5000, 30.0, 10.0, tag="failed", status="failed"),
        _grid("willags", 5000, 30.0, 10.0, tag="gpus2", num_devices=2),  # one image per device a step
        _grid("willags", 5000, 30.0, 10.0, tag="gpus1", num_devices=1),
        _grid("willags", 5000, 30.0, 10.0, tag="other", scene="fox-wild"),
        {**_grid("willags", 5000, 30.0, 10.0, tag="cpu"), "device": "cpu"},
        _grid("willags-3dgs", 5000, 30.0, 10.0),  # not a method of the curves
        _long(
            "willags",
            {"7000": {"psnr": 19.2}, "30000": {"psnr": 19.3}},
            [{"end_step": 29999, "train_s": 420.0}],
            concurrent_runs=1,
        ),
    ]
    pts = scene_points(records, "reichstag")
    got = [(p.method, p.steps, p.train_s, p.source, p.gpu, p.sharing.state) for p in pts]
    assert got == [
        ("willags", 5000, 10.0, "grid", "H100", "unknown"),
        ("willags", 5000, 200.0, "grid", "H100", "shared"),
        ("willags", 7000, None, "long run", "H200", "alone"),
        ("willags", 30000, 420.0, "long run", "H200", "alone"),
        ("peer", 5000, 300.0, "grid", "H100", "unknown"),
    ]
    assert [p.seed for p in pts] == [42, 42, 42, 42, 43]  # a record without a seed ran with the default, 42


def _p(method, steps, psnr, t, sharing=ALONE, gpu="H100", seed=42):
    return Point("s", method, steps, psnr, t, "grid", "", gpu, sharing, seed)


def test_pareto_marks_the_runs_nothing_beats_on_both():
    pts = [
        _p("a", 1000, 18.0, 10.0),  # fastest: optimal
        _p("a", 5000, 19.0, 50.0),  # optimal
        _p("b", 5000, 18.5, 60.0),  # slower and worse than a@5000
        _p("b", 15000, 19.0, 50.0),  # ties a@5000 on both: neither dominates the other
        _p("c", 30000, 20.0, None),  # untimed: never marked
        _p("c", 30000, 19.5, 100.0),  # best: optimal
    ]
    assert pareto_flags(pts) == [True, True, False, True, False, True]


def test_a_step_counts_time_is_the_median_of_its_runs_timed_alone():
    pts = [
        _p("willags", 5000, 19.2, 100.0, gpu="H200"),
        _p("willags", 5000, 19.4, 140.0, gpu="H200"),
        _p("willags", 5000, 19.3, 30.0, SHARED, gpu="H200"),  # shared: its PSNR counts, its time does not
        _p("peer", 15000, 19.0, 1000.0, SHARED),
        _p("peer", 15000, 19.4, None),
    ]
    (hit,) = step_curve(pts, "willags")
    assert hit.psnr == pytest.approx(19.3) and hit.n == 3 and hit.times == (30.0, 100.0, 140.0)
    t = step_time(hit)
    assert (t.seconds, t.alone) == (120.0, True) and hit.alone == (100.0, 140.0)
    (peer,) = step_curve(pts, "peer")
    assert (step_time(peer).seconds, step_time(peer).alone) == (1000.0, False)  # only a shared-GPU time
    assert step_time(step_curve([_p("peer", 15000, 19.4, None)], "peer")[0]) is None


def test_time_budget_runs_stay_off_the_curves():
    knob = _long(
        "willags",
        {"15004": {"psnr": 19.2, "train_s": 298.7}},
        [{"start_step": 0, "end_step": 15003, "train_s": 298.7}],
        tag="h200-curve-knob5",
        time_budget_minutes=5.0,
        concurrent_runs=1,
    )
    plain = _long("willags", {"5000": {"psnr": 19.4, "train_s": 80.0}}, [{"end_step": 4999, "train_s": 80.0}])
    assert [(p.steps, p.tag) for p in scene_points([knob, plain], "reichstag")] == [(5000, "long")]


def test_has_curve_needs_a_method_timed_at_two_step_counts():
    assert not has_curve([_p("a", 5000, 1, 10.0), _p("b", 5000, 1, 10.0), _p("a", 15000, 1, None)])
    assert has_curve([_p("a", 5000, 1, 10.0), _p("a", 15000, 1, 30.0)])


# ---------------------------------------------------------------------------------------------- outputs


def test_main_writes_the_png_and_labels_shared_times(tmp_path):
    records = [
        _grid("willags", 5000, 19.0, 200.0, tag="a", concurrent_runs=5),
        _grid("peer", 5000, 19.4, 210.0, tag="a", gpu_sharing={"state": "alone", "runs": 1, "why": "note"}),
        _long("peer", {"15000": {"psnr": 19.3}}, [{"end_step": 14999, "train_s": 500.0}], concurrent_runs=1),
        _long(
            "willags",
            {"15000": {"psnr": 19.35, "train_s": 380.0}, "30000": {"psnr": 19.2}},
            [{"end_step": 29999, "train_s": 760.0, "concurrent_runs": 3}],
        ),
        _grid("peer", 5000, 22.0, 300.0, scene="south-building"),  # one step count: no plot
        _long(
            "willags",
            {"17213": {"psnr": 19.2}},
            [{"end_step": 17212, "train_s": 298.7}],
            tag="knob5",
            time_budget_minutes=5.0,
        ),
    ]
    src = tmp_path / "records.json"
    src.write_text(json.dumps(records))
    out = tmp_path / "docs"
    assert curves.main(["--records", str(src), "--out-dir", str(out), "--scenes", "reichstag", "south-building"]) == 0
    png = out / "curves_reichstag.png"
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and png.stat().st_size > 10_000
    assert not (out / "curves_south-building.png").exists()
    md = (out / "curves.md").read_text()
    assert "| willags | 5000 | 200 | 19.00 | H100 | shared, up to 5 runs (concurrent_runs) |" in md
    assert "| willags | 15000 | 380 | 19.35 | H200 | shared, up to 3 runs (segments) |" in md
    assert "| peer | 5000 | 210 | 19.40 | H100 | alone (note) |" in md
    assert "none (no method timed at 2 step counts)" in md  # south-building
    assert "17213" not in md  # the time-budget run is no point of a curve


def test_long_run_record_keeps_milestone_times_and_the_most_runs_sharing(tmp_path):
    from benchmarks import long_run

    run = tmp_path / "reichstag-willags-s42"
    run.mkdir()
    state = {
        "method": "willags",
        "data": "/x/reichstag",
        "steps": 3000,
        "seed": 42,
        "segments": [
            {"start_step": 0, "end_step": 1499, "train_s": 20.0, "concurrent_runs": 3},
            {"start_step": 1500, "end_step": 2999, "train_s": 25.0, "concurrent_runs": 1},
        ],
        "milestone_train_s": {"1000": 13.0, "3000": 45.0},
        "scores": {"1000": {"psnr": 18.0}, "3000": {"psnr": 19.0}},
    }
    (run / long_run.STATE).write_text(json.dumps(state))
    out = tmp_path / "rec.json"
    long_run.main(["record", "--run-dir", str(run), "--tag", "t", "--out", str(out), "--milestones", "1000,3000"])
    (rec,) = json.loads(out.read_text())
    assert rec["milestones"]["1000"] == {"psnr": 18.0, "train_s": 13.0} and rec["concurrent_runs"] == 3
    assert milestone_train_s(rec, "1000") == 13.0 and gpu_sharing(rec).label() == "shared, up to 3 runs"
