"""benchmarks/curves.py and benchmarks/curves_report.py on synthetic records: GPU-sharing labels, milestone times,
points, Pareto marks, time to the peer's 15k PSNR (alone-timed ratio, goal), the time-budget knob against the curves,
the markdown and the PNG; and benchmarks/long_run.py recording what the curves need."""

import json

import pytest

from benchmarks import curves, curves_report
from benchmarks.curves import (
    KnobRun,
    Point,
    Sharing,
    best_within,
    first_reaching,
    gpu_sharing,
    has_curve,
    knob_runs,
    milestone_train_s,
    pareto_flags,
    scene_points,
    step_curve,
    step_time,
    time_ratio,
)

GRIDS = {
    "configs/concurrent.json": "benchmarks/remote/grid.sh runs the pairs concurrently on one GPU",
    "configs/seq.json": "runs one after another (true times)",
}
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


@pytest.mark.parametrize(
    "rec, state, runs",
    [
        ({"concurrent_runs": 3, "note": "three segments, 12, 9 and 3 runs concurrent on the GPU"}, "shared", 12),
        ({"run_note": "4-5 runs at once on one H100 (train times are shared-GPU times)"}, "shared", 5),
        ({"note": "segments 1-2 shared the GPU with 6 other runs; segments 3-4 ran alone"}, "shared", 7),
        ({"concurrent_runs": 1, "segments": [{"shared_with": 1}]}, "shared", 2),
        ({"concurrent_runs": 1, "segments": [{"concurrent_runs": 4}]}, "shared", 4),
        ({"note": "willags and splatfacto concurrently on one H100"}, "shared", None),
        ({"concurrent_runs": 1, "note": "trained alone on one H100"}, "alone", 1),
        ({"run_note": "runs one after another on one H100 (true train times)"}, "alone", 1),
        ({"command": "python benchmarks/run_benchmark.py --grid configs/concurrent.json --scenes x"}, "shared", None),
        ({"command": "python benchmarks/run_benchmark.py --grid configs/seq.json"}, "alone", 1),
        ({"command": "python benchmarks/run_benchmark.py --grid configs/other.json"}, "unknown", None),
        ({}, "unknown", None),
    ],
)
def test_gpu_sharing_reads_what_the_record_says(rec, state, runs):
    s = gpu_sharing(rec, GRIDS)
    assert (s.state, s.runs) == (state, runs)


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
        _grid("willags", 5000, 19.0, 200.0, tag="a", command="x --grid configs/concurrent.json"),
        _grid("peer", 5000, 19.5, 300.0, tag="a", seed=43),
        _grid("willags", 5000, 30.0, 10.0, tag="dirty", tree_note="not a clean record"),
        _grid("willags", 5000, 30.0, 10.0, tag="failed", status="failed"),
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
    pts = scene_points(records, "reichstag", grids=GRIDS)
    got = [(p.method, p.steps, p.train_s, p.source, p.gpu, p.sharing.state) for p in pts]
    assert got == [
        ("willags", 5000, 200.0, "grid", "H100", "shared"),
        ("willags", 7000, None, "long run", "H200", "alone"),
        ("willags", 30000, 420.0, "long run", "H200", "alone"),
        ("peer", 5000, 300.0, "grid", "H100", "unknown"),
    ]
    assert [p.seed for p in pts] == [42, 42, 42, 43]  # a record without a seed ran with the default, 42


def _p(method, steps, psnr, t, sharing=ALONE, gpu="H100", seed=42):
    return Point("s", method, steps, psnr, t, "grid", "", gpu, sharing, seed)


def test_crossings_are_changes_of_order_between_shared_step_counts_with_their_seeds():
    pts = [
        _p("willags", 1000, 19.0, 18.0),
        _p("willags", 5000, 19.4, 80.0),
        _p("willags", 15000, 19.3, 250.0),
        _p("peer", 1000, 18.3, 15.0),
        _p("peer", 1000, 18.2, 16.0, seed=43),
        _p("peer", 2000, 19.9, 30.0),  # willags has no 2000: no comparison there
        _p("peer", 5000, 19.2, 80.0),
        _p("peer", 5000, 19.3, 75.0, seed=43),
        _p("peer", 15000, 19.5, 260.0),
        _p("peer", 15000, 19.4, 250.0, seed=43),
        _p("splatfacto", 1000, 16.0, 10.0),
        _p("splatfacto", 15000, 14.8, 140.0),
    ]
    (c,) = curves.crossings(pts)  # splatfacto stays below both; willags leads the peer at 1k and 5k, not at 15k
    assert (c.first, c.second, c.steps, c.leader) == ("willags", "peer", (5000, 15000), ("willags", "peer"))
    assert c.seeds == {"willags": 1, "peer": 2} and c.needs_seed
    rows = curves_report.crossing_rows({"s": pts})
    assert (
        rows[2]
        == "| s | willags / peer | 5000 and 15000 steps | willags -> peer | willags 1, peer 2 | missing: willags |"
    )
    # a second seed of willags at both step counts: the crossing has its seeds
    more = pts + [_p("willags", 5000, 19.3, 82.0, seed=43), _p("willags", 15000, 19.2, 251.0, seed=43)]
    (c2,) = curves.crossings(more)
    assert not c2.needs_seed and curves_report.crossing_rows({"s": more})[2].endswith("| have |")
    # willags-full (drawn, but not one of the methods) crossing the peer is not listed
    assert curves.crossings([_p("willags-full", 1000, 20.0, 1.0), _p("willags-full", 5000, 18.0, 5.0)] + pts[3:8]) == []
    assert curves_report.crossing_rows({"s": pts[:3]}) == ["No two methods' curves cross in these records."]


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


def test_time_to_the_peers_psnr():
    pts = [
        _p("peer", 15000, 19.2, 480.0),
        _p("peer", 15000, 19.4, 1000.0),  # target: mean 19.3
        _p("willags", 5000, 19.35, 160.0),  # one lucky seed reaches it, the step count's mean does not
        _p("willags", 5000, 19.05, 200.0),
        _p("willags", 15000, 19.3, 360.0),
        _p("splatfacto", 30000, 14.2, 365.0),
    ]
    target = step_curve(pts, "peer")[0]
    assert target.psnr == pytest.approx(19.3) and target.n == 2 and target.times == (480.0, 1000.0)
    hit = first_reaching(step_curve(pts, "willags"), target.psnr)
    assert hit is not None and hit.steps == 15000 and hit.times == (360.0,)
    assert first_reaching(step_curve(pts, "splatfacto"), target.psnr) is None
    rows = curves_report.time_to_target_rows({"s": pts})
    assert "| s | 19.30 (n=2), 740 s [alone, H100; median of 2 runs] |" in rows[2]
    assert "15000 steps, 19.30 (n=1), 360 s [alone, H100] | 0.49x | met |" in rows[2]  # 360 / 740
    assert "not reached (best 14.20 at 30000 steps)" in rows[2] and "not measured" in rows[2]  # lite: no records


def test_a_bar_reached_and_lost_again_says_so():
    """A method that reaches the peer at one milestone and falls below it later (one run's noise around the bar):
    the cell says where, beside the time it first reached it."""
    pts = [
        _p("peer", 15000, 19.29, 259.0),
        _p("willags", 5000, 19.37, 82.0),
        _p("willags", 10000, 19.18, 170.0),
        _p("willags", 15000, 19.27, 251.0),
    ]
    row = curves_report.time_to_target_rows({"s": pts})[2]
    assert "5000 steps, 19.37 (n=1), 82 s [alone, H100]; below it again at 10000 steps (19.18, n=1), " in row
    assert "15000 steps (19.27, n=1) | 0.32x | met where first reached, not held |" in row
    held = [_p("peer", 15000, 19.29, 259.0), _p("willags", 5000, 19.37, 82.0), _p("willags", 15000, 19.4, 251.0)]
    assert "below it again" not in curves_report.time_to_target_rows({"s": held})[2]


def _ratio_row(pts):
    """willags' cells of the time-to-target row: (its time / the peer's, goal)."""
    cells = [c.strip() for c in curves_report.time_to_target_rows({"s": pts})[2].strip("|").split("|")]
    return cells[3], cells[4]


def test_the_time_ratio_uses_the_runs_timed_alone():
    peer = [_p("peer", 15000, 19.0, 600.0, gpu="H200"), _p("peer", 15000, 19.4, 1000.0, SHARED, gpu="H200")]
    fast = [
        _p("willags", 5000, 19.2, 100.0, gpu="H200"),
        _p("willags", 5000, 19.4, 140.0, gpu="H200"),
        _p("willags", 5000, 19.3, 30.0, SHARED, gpu="H200"),  # shared: its time is left out of the median
    ]
    target = step_curve(peer, "peer")[0]
    hit = step_curve(fast, "willags")[0]
    assert target.psnr == pytest.approx(19.2)  # the shared run's PSNR counts in the bar
    assert step_time(target).seconds == 600.0 and step_time(hit).seconds == 120.0 and step_time(hit).n == 2
    assert time_ratio(hit, target) == pytest.approx(0.2)
    assert _ratio_row(peer + fast) == ("0.20x", "met")
    row = curves_report.time_to_target_rows({"s": peer + fast})[2]
    assert "| 19.20 (n=2), 600 s [alone, H200] |" in row
    assert "5000 steps, 19.30 (n=3), 120 s [alone, H200; median of 2 runs]" in row
    slow = [_p("willags", 5000, 19.3, 400.0, gpu="H200")]
    assert _ratio_row(peer + slow) == ("0.67x", "missed (0.67x)")
    other_gpu = [_p("willags", 5000, 19.3, 100.0, gpu="H100")]
    assert _ratio_row(peer + other_gpu) == ("0.17x (H100 vs H200)", "– (timed on different GPUs)")


def test_only_shared_times_are_not_comparable():
    peer = [_p("peer", 15000, 19.0, 1000.0, SHARED)]
    fast = [_p("willags", 5000, 19.3, 100.0)]  # alone, but the peer's time is shared
    assert time_ratio(step_curve(fast, "willags")[0], step_curve(peer, "peer")[0]) is None
    assert _ratio_row(peer + fast) == ("not comparable (shared-GPU time)", "–")
    assert "| 19.00 (n=1), 1000 s [shared, up to 4 runs] |" in curves_report.time_to_target_rows({"s": peer})[2]
    alone_peer = [_p("peer", 15000, 19.0, 600.0)]
    assert _ratio_row(alone_peer + [_p("willags", 5000, 19.3, 100.0, SHARED)])[0] == "not comparable (shared-GPU time)"


def test_not_reaching_the_bar_misses_the_goal_only_after_as_many_steps():
    peer = [_p("peer", 15000, 19.0, 600.0)]
    assert _ratio_row(peer + [_p("willags", 5000, 18.0, 60.0), _p("willags", 30000, 18.9, 500.0)]) == (
        "–",
        "missed (not reached)",
    )
    assert _ratio_row(peer + [_p("willags", 5000, 18.0, 60.0)]) == ("–", "– (not reached by 5000 steps)")


def _knob(minutes, end, psnr, train_s, preset="willags", **extra):
    """A long_run record of a run under the time budget (benchmarks/long_run.py --budget-minutes)."""
    return _long(
        "willags",
        {str(end): {"psnr": psnr, "train_s": train_s}},
        [{"start_step": 0, "end_step": end - 1, "train_s": train_s}],
        tag=f"h200-curve-knob{minutes:g}",
        time_budget_minutes=minutes,
        end_step=end,
        time_budget={
            "budget_minutes": minutes,
            "device_class": "cuda",
            "choice": {"preset": preset, "steps": end, "reason": "measured"},
            "run": {"budget_s": minutes * 60, "elapsed_s": train_s, "steps_trained": end, "stop_reason": "budget"},
        },
        **extra,
    )


KNOB_RECORDS = [
    _long(
        "willags",
        {"1000": {"psnr": 19.0, "train_s": 20.0}, "5000": {"psnr": 19.4, "train_s": 80.0}},
        [{"end_step": 4999, "train_s": 80.0}],
        concurrent_runs=1,
    ),
    _grid("peer", 5000, 19.5, 290.0, tag="seq", run_note="runs one after another"),  # alone: the best within 5 min
    _grid("peer", 5000, 19.9, 250.0, tag="conc", run_note="5 runs at once"),  # better and faster, but shared
    _grid("peer", 15000, 19.8, 600.0, tag="seq", run_note="runs one after another"),  # alone, past 5 min
    _knob(5.0, 17213, 19.2, 298.7, concurrent_runs=1),
    _knob(2.0, 6100, 18.8, 119.0, preset="willags-lite", concurrent_runs=1),
    _knob(10.0, 30000, 19.9, 590.0, concurrent_runs=3),  # shared the GPU: not judged
]


def test_knob_runs_stay_off_the_curves():
    pts = scene_points(KNOB_RECORDS, "reichstag", grids=GRIDS)
    assert [(p.method, p.steps, p.tag) for p in pts if p.method == "willags"] == [
        ("willags", 1000, "long"),
        ("willags", 5000, "long"),
    ]
    assert [s.steps for s in step_curve(pts, "willags")] == [1000, 5000]
    knobs = knob_runs(KNOB_RECORDS, "reichstag", grids=GRIDS)
    assert [(k.budget_minutes, k.preset, k.steps, k.psnr, k.train_s, k.gpu, k.sharing.state) for k in knobs] == [
        (2.0, "willags-lite", 6100, 18.8, 119.0, "H200", "alone"),
        (5.0, "willags", 17213, 19.2, 298.7, "H200", "alone"),
        (10.0, "willags", 30000, 19.9, 590.0, "H200", "shared"),
    ]
    assert isinstance(knobs[0], KnobRun) and knobs[1].tag == "h200-curve-knob5"
    assert knob_runs(KNOB_RECORDS, "fox-wild", grids=GRIDS) == []


def test_the_knob_against_the_best_alone_run_within_its_budget():
    pts = scene_points(KNOB_RECORDS, "reichstag", grids=GRIDS)
    best = best_within(pts, 300.0)
    assert (best.method, best.steps, best.psnr, best.train_s) == ("peer", 5000, 19.5, 290.0)  # not the shared 19.9
    assert best_within(pts, 120.0).psnr == 19.4 and best_within(pts, 10.0) is None
    knobs = {"reichstag": knob_runs(KNOB_RECORDS, "reichstag", grids=GRIDS)}
    rows = curves_report.knob_rows({"reichstag": pts}, knobs)
    assert rows[2] == (
        "| reichstag | 2 min | H200 (alone) | willags-lite, 6100 steps, 119 s | 18.80 "
        "| willags, 5000 steps, 19.40, 80 s (H200) | -0.60 dB | missed by 0.10 dB |"
    )
    assert rows[3] == (
        "| reichstag | 5 min | H200 (alone) | willags, 17213 steps, 299 s | 19.20 "
        "| peer, 5000 steps, 19.50, 290 s (H100) | -0.30 dB | met |"
    )
    assert rows[4].endswith(
        "| peer, 15000 steps, 19.80, 600 s (H100) | +0.10 dB | not judged (the knob's run did not have the GPU alone) |"
    )
    curve_side = curves_report.best_within_rows({"reichstag": pts, "fox-wild": []}, [0.1, 1.0, 5.0])
    assert curve_side[2] == (
        "| reichstag | no run timed alone within 0.1 min | willags, 1000 steps, 19.00, 20 s (H200) "
        "| peer, 5000 steps, 19.50, 290 s (H100) |"
    )
    assert curve_side[3] == (
        "| fox-wild | no run timed alone within 0.1 min | no run timed alone within 1 min "
        "| no run timed alone within 5 min |"
    )


def test_has_curve_needs_a_method_timed_at_two_step_counts():
    assert not has_curve([_p("a", 5000, 1, 10.0), _p("b", 5000, 1, 10.0), _p("a", 15000, 1, None)])
    assert has_curve([_p("a", 5000, 1, 10.0), _p("a", 15000, 1, 30.0)])


# ---------------------------------------------------------------------------------------------- outputs


def test_main_writes_the_png_and_labels_shared_times(tmp_path):
    records = [
        _grid("willags", 5000, 19.0, 200.0, tag="a", run_note="5 runs at once on one H100"),
        _grid("peer", 5000, 19.4, 210.0, tag="a", run_note="runs one after another"),
        _long("peer", {"15000": {"psnr": 19.3}}, [{"end_step": 14999, "train_s": 500.0}], concurrent_runs=1),
        _long(
            "willags",
            {"15000": {"psnr": 19.35, "train_s": 380.0}, "30000": {"psnr": 19.2}},
            [{"end_step": 29999, "train_s": 760.0, "concurrent_runs": 3}],
        ),
        _grid("peer", 5000, 22.0, 300.0, scene="south-building"),  # one step count: no plot
        _knob(5.0, 17213, 19.2, 298.7, concurrent_runs=1),
    ]
    src = tmp_path / "records.json"
    src.write_text(json.dumps(records))
    out = tmp_path / "docs"
    assert (
        curves_report.main(["--records", str(src), "--out-dir", str(out), "--scenes", "reichstag", "south-building"])
        == 0
    )
    png = out / "curves_reichstag.png"
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and png.stat().st_size > 10_000
    assert not (out / "curves_south-building.png").exists()
    md = (out / "curves.md").read_text()
    assert "| willags | 5000 | 200 | 19.00 | H100 | shared, up to 5 runs (note) |" in md
    assert "| willags | 15000 | 380 | 19.35 | H200 | shared, up to 3 runs (segments) |" in md
    assert "| peer | 5000 | 210 | 19.40 | H100 | alone (note) |" in md
    assert "none (no method timed at 2 step counts)" in md  # south-building
    assert "15000 steps, 19.35 (n=1), 380 s [shared, up to 3 runs]" in md  # willags reaches the peer's 19.30
    assert "| not comparable (shared-GPU time) | – |" in md
    assert "## The time-budget knob against the curves" in md and "17213" not in md.split("## reichstag")[1]
    assert (
        "| reichstag | 5 min | H200 (alone) | willags, 17213 steps, 299 s | 19.20 | peer, 5000 steps, 19.40, 210 s"
        in md
    )


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
    assert milestone_train_s(rec, "1000") == 13.0 and gpu_sharing(rec, {}).label() == "shared, up to 3 runs"
