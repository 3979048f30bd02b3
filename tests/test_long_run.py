"""benchmarks/long_run.py: a run under the time-budget knob, and milestones scored by several processes at once."""

import json
import multiprocessing as mp
import re

import pytest

from benchmarks import long_run


def _write_state(run, state):
    run.mkdir(parents=True, exist_ok=True)
    (run / long_run.STATE).write_text(json.dumps(state))


def test_all_milestones_are_those_with_a_recorded_train_time():
    state = {"milestone_train_s": {"1000": 20.0, "15004": 300.0}}
    assert long_run._milestones("all", state) == [1000, 15004]
    assert long_run._milestones("2000,5000", state) == [2000, 5000]
    assert long_run._milestones("all", {}) == []


def test_milestones_given_with_spaces_or_commas_are_read_alike_and_a_bad_one_is_named(tmp_path, capsys):
    assert long_run.milestone_spec("5000 15000") == long_run.milestone_spec("5000,15000") == "5000,15000"
    assert long_run.milestone_spec(" all ") == "all"
    for bad, argv in (
        ("5k", ["eval", "--run-dir", str(tmp_path), "--milestones", "5k"]),
        (
            "all",
            ["train", "--run-dir", str(tmp_path), "--method", "willags", "--data", ".", "--budget-s", "1"]
            + ["--milestones", "all"],
        ),
    ):
        with pytest.raises(SystemExit) as exc:
            long_run.main(argv)
        err = capsys.readouterr().err.strip().splitlines()
        assert exc.value.code == 2 and "--milestones" in err[-1] and bad in err[-1]
        assert "Traceback" not in "\n".join(err)
    assert not list(tmp_path.iterdir())  # nothing started


def test_a_knob_run_is_scored_with_the_preset_the_knob_chose():
    # on a CPU the knob may swap willags for willags-lite: the checkpoints then hold willags-lite's networks
    state = {"method": "willags", "time_budget": {"choice": {"preset": "willags-lite"}}}
    assert long_run._eval_method(state) == "willags-lite"
    assert long_run._eval_method({"method": "peer"}) == "peer"
    # a preset the benchmarks do not know is no method to build: the run's own
    assert long_run._eval_method({"method": "willags", "time_budget": {"choice": {"preset": "nope"}}}) == "willags"


def _score(run_dir, milestone):
    long_run._save_score(run_dir, milestone, {"psnr": float(milestone) / 1000})


def test_milestones_scored_at_once_by_several_processes_all_land_in_the_state(tmp_path):
    run = tmp_path / "run"
    _write_state(run, {"method": "willags", "segments": [], "scores": {}, "milestone_train_s": {"1": 1.0}})
    ctx = mp.get_context("fork")
    procs = [ctx.Process(target=_score, args=(run, str(m))) for m in (1000, 2000, 5000, 10000, 15000, 30000)]
    for p in procs:
        p.start()
    for p in procs:
        p.join()
    state = json.loads((run / long_run.STATE).read_text())
    assert sorted(state["scores"], key=int) == ["1000", "2000", "5000", "10000", "15000", "30000"]
    assert state["scores"]["15000"] == {"psnr": 15.0}
    assert state["milestone_train_s"] == {"1": 1.0}  # the rest of the state survives


def test_a_knob_runs_record_carries_the_budget_and_the_score_where_it_stopped(tmp_path):
    run = tmp_path / "reichstag-willags-30000-s42-knob5"
    budget = {"budget_minutes": 5.0, "choice": {"preset": "willags"}, "run": {"steps_trained": 15004}}
    _write_state(
        run,
        {
            "method": "willags",
            "data": "/x/reichstag",
            "steps": 30000,
            "seed": 42,
            "segments": [{"start_step": 0, "end_step": 15003, "train_s": 301.0, "concurrent_runs": 1}],
            "milestone_train_s": {"15004": 300.0},
            "scores": {"15004": {"psnr": 19.43, "ssim": 0.7}},
            "time_budget_minutes": 5.0,
            "time_budget": budget,
            "end_step": 15004,
        },
    )
    out = tmp_path / "rec.json"
    assert long_run.main(["record", "--run-dir", str(run), "--tag", "h200-curve-knob5", "--out", str(out)]) == 0
    (rec,) = json.loads(out.read_text())
    assert (rec["time_budget_minutes"], rec["end_step"], rec["time_budget"]) == (5.0, 15004, budget)
    assert rec["psnr"] == 19.43  # the score where the knob stopped, not at the cap (30000)
    assert rec["milestones"]["15004"] == {"psnr": 19.43, "ssim": 0.7, "train_s": 300.0}
    assert (rec["steps_done"], rec["concurrent_runs"]) == (15004, 1)


def test_a_record_carries_the_share_the_transients_cap_rule_measured(tmp_path):
    """The "transients" cap rule's share (model.cap_decision, scored into the state) reaches the record's milestone,
    where `cv bar` reads it; a run without the rule claims none."""
    base = {"method": "willags-prior-low-captransients", "data": "/x/south-building-cv1of4", "steps": 10, "seed": 42,
            "segments": [{"start_step": 0, "end_step": 9, "train_s": 1.0}]}  # fmt: skip
    recs = []
    for case, score in (("rule", {"psnr": 15.0, "cap_rule_share": 0.021}), ("plain", {"psnr": 15.0})):
        _write_state(tmp_path / case, {**base, "scores": {"10": score}})
        out = tmp_path / f"{case}.json"
        assert long_run.main(["record", "--run-dir", str(tmp_path / case), "--tag", "t", "--out", str(out)]) == 0
        recs.append(json.loads(out.read_text())[0]["milestones"]["10"])
    assert recs[0]["cap_rule_share"] == 0.021
    assert "cap_rule_share" not in recs[1]


def test_a_record_carries_the_share_and_verdict_of_the_masks_start_rule(tmp_path):
    """The mask's start rule's share and verdict (model.mask_decision, scored into the state) reach the record's
    milestone; a run without the rule claims none."""
    base = {"method": "willags-prior-low-mask5k-gate", "data": "/x/fox-wild", "steps": 10, "seed": 42,
            "segments": [{"start_step": 0, "end_step": 9, "train_s": 1.0}]}  # fmt: skip
    recs = []
    for case, score in (
        ("rule", {"psnr": 15.0, "mask_start_share": 0.062, "mask_started": False}),
        ("plain", {"psnr": 15.0}),
    ):
        _write_state(tmp_path / case, {**base, "scores": {"10": score}})
        out = tmp_path / f"{case}.json"
        assert long_run.main(["record", "--run-dir", str(tmp_path / case), "--tag", "t", "--out", str(out)]) == 0
        recs.append(json.loads(out.read_text())[0]["milestones"]["10"])
    assert (recs[0]["mask_start_share"], recs[0]["mask_started"]) == (0.062, False)
    assert "mask_start_share" not in recs[1] and "mask_started" not in recs[1]


def test_a_record_names_the_sfm_model_its_scene_held(tmp_path):
    """Two builds of one collection can hold different SfM models (benchmarks/collections.py): each record says
    which one its run started from, so the cross-validation can tell runs on different builds apart."""
    from benchmarks.collections import model_digest
    from tests._scenes import sfm_model_stub

    scene = sfm_model_stub(tmp_path / "lund-cv1of4")
    state = {"method": "willags", "data": str(scene), "steps": 10, "seed": 42, "scores": {"10": {"psnr": 15.0}},
             "segments": [{"start_step": 0, "end_step": 9, "train_s": 1.0}]}  # fmt: skip
    recs = {}
    for case, data in (("with", scene), ("without", tmp_path / "moved")):
        _write_state(tmp_path / case, {**state, "data": str(data)})
        out = tmp_path / f"{case}.json"
        assert long_run.main(["record", "--run-dir", str(tmp_path / case), "--tag", "t", "--out", str(out)]) == 0
        (recs[case],) = json.loads(out.read_text())
    assert recs["with"]["scene_model_sha256"] == model_digest(scene)
    assert "scene_model_sha256" not in recs["without"]  # no model where the run's data was: nothing claimed


def test_a_resumed_or_scored_willags_run_rebuilds_the_model_it_trained_without_inspecting_again(tmp_path, monkeypatch):
    """The default inspects the scene before it builds the model; a later segment and every scoring process build
    the run's model from its config.yml (the resolved switches), not from the method name: no second inspection, and
    a run trained under another meaning of `willags` still loads."""
    import pytest
    import torch

    import willags_ns.tools.autoconfig as ac
    from tests._scenes import small_scene

    data = small_scene(tmp_path / "appearance", appearance=1.0, transients=0.0)
    run = tmp_path / "run"
    args = ["train", "--method", "willags", "--data", str(data), "--run-dir", str(run), "--steps", "4"]
    assert long_run.main([*args, "--milestones", "2,4", "--budget-s", "1000", "--check-finite"]) == 0
    state = json.loads((run / long_run.STATE).read_text())
    assert sorted(state["milestone_train_s"], key=int) == ["2", "4"]

    monkeypatch.setattr(ac, "inspect_scene", lambda *a, **k: pytest.fail("a trained run must not be inspected again"))
    trainer = long_run._setup("willags", data, run, 4, 42, 1, "test")
    model = trainer.pipeline.model
    assert not model.config.mask.enabled and model.teacher is None  # the inspector's choice (no transients here)
    assert trainer._start_step == 2  # resumed from the checkpoint of step index 1 (the milestone "2")
    model.eval()
    with torch.no_grad():
        assert torch.isfinite(
            model.get_outputs_for_camera(trainer.pipeline.datamanager.eval_dataset.cameras[0:1])["rgb"]
        ).all()

    saved = trainer.config.get_base_dir() / "config.yml"
    saved.write_text("")  # a config.yml emptied outside the run: said in one line naming it, not an AttributeError
    with pytest.raises(
        SystemExit, match=rf"^long_run: {re.escape(str(saved))} holds no run configuration \(it reads as NoneType\)"
    ):
        long_run._setup("willags", data, run, 4, 42, 1, "test")


def test_a_run_killed_after_a_milestone_keeps_its_time_and_is_scored_there(tmp_path, monkeypatch):
    """A training process that dies after its first milestone (killed, out of time) leaves a state that says where
    it got: the milestone's train time (what gpu_solo scores) and a segment ending at its checkpoint."""
    import pytest

    from willags_ns.data.synthetic import SyntheticSceneConfig, make_scene, write_scene
    from willags_ns.engine.trainer import WillagsTrainer

    cfg = SyntheticSceneConfig(num_train=8, num_test=2, width=32, height=24, num_points=400, supersample=1)
    scene = write_scene(make_scene(cfg), tmp_path / "scene")
    train_iteration = WillagsTrainer.train_iteration

    def dies_at_step_4(self, step):
        if step == 4:
            raise RuntimeError("killed")
        return train_iteration(self, step)

    monkeypatch.setattr(WillagsTrainer, "train_iteration", dies_at_step_4)
    run = tmp_path / "run"
    argv = ["train", "--run-dir", str(run), "--method", "willags-3dgs", "--data", str(scene), "--steps", "8"]
    with pytest.raises(RuntimeError, match="killed"):
        long_run.main([*argv, "--milestones", "3,8", "--budget-s", "1e9"])
    state = json.loads((run / long_run.STATE).read_text())
    assert list(state["milestone_train_s"]) == ["3"] and state["data"] == str(scene)
    (seg,) = state["segments"]
    assert seg["end_step"] == 2 and seg["train_s"] == state["milestone_train_s"]["3"]
    assert long_run._ckpt_steps(run) == [2]


def test_check_finite_stops_at_the_first_non_finite_parameter(tmp_path, monkeypatch):
    """docs/reliability.md, row 19: with --check-finite a run stops at the step after which a parameter is not finite,
    naming it."""
    import pytest
    import torch

    from willags_ns.data.synthetic import SyntheticSceneConfig, make_scene, write_scene
    from willags_ns.engine.trainer import WillagsTrainer

    cfg = SyntheticSceneConfig(num_train=8, num_test=2, width=32, height=24, num_points=400, supersample=1)
    scene = write_scene(make_scene(cfg), tmp_path / "scene")
    train_iteration = WillagsTrainer.train_iteration

    def poisoned_at_step_2(self, step):
        out = train_iteration(self, step)
        if step == 2:
            with torch.no_grad():
                self.pipeline.model.gauss_params["opacities"][0] = float("nan")
        return out

    monkeypatch.setattr(WillagsTrainer, "train_iteration", poisoned_at_step_2)
    argv = ["train", "--run-dir", str(tmp_path / "run"), "--method", "willags-3dgs", "--data", str(scene)]
    with pytest.raises(RuntimeError, match=r"non-finite at step 2: \['gauss_params.opacities'\]"):
        long_run.main([*argv, "--steps", "8", "--milestones", "8", "--budget-s", "1e9", "--check-finite"])


def test_a_protocol_variant_is_scored_apart_from_the_protocols_own_scores(tmp_path, capsys):
    """`eval --variant` scores a milestone under other fit settings (steps, the oracle) into state.json's variants:
    the protocol's own scores (what the record's tables are made of) are neither skipped nor replaced, and the record
    carries the variant beside them with each photo's fit. An eval whose milestones the run has no checkpoint for
    says so in one line, naming the steps it kept, and fails instead of scoring nothing in silence."""
    from tests._scenes import small_scene

    data = small_scene(tmp_path / "appearance", appearance=1.0, transients=0.0)
    run = tmp_path / "run"
    argv = ["--run-dir", str(run), "--milestones", "4"]
    assert (
        long_run.main(["train", *argv, "--method", "willags", "--data", str(data), "--steps", "4", "--budget-s", "1e9"])
        == 0
    )
    capsys.readouterr()
    assert long_run.main(["eval", "--run-dir", str(run), "--milestones", "7000,15000"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "7000, 15000" in err[0] and "kept at: 4" in err[0]
    assert json.loads((run / long_run.STATE).read_text())["scores"] == {}
    variant = ["--variant", "oracle2", "--protocol-steps", "2", "--oracle", "--protocol-start-candidates", "3"]
    variant += ["--train-views", "0"]
    assert long_run.main(["eval", *argv, *variant]) == 0
    state = json.loads((run / long_run.STATE).read_text())
    assert state["scores"] == {} and list(state["variants"]) == ["oracle2"]
    assert long_run.main(["eval", *argv, "--protocol-steps", "2", "--train-views", "0"]) == 0
    state = json.loads((run / long_run.STATE).read_text())
    own, other = state["scores"]["4"], state["variants"]["oracle2"]["4"]
    assert "oracle_psnr" in other and "oracle_psnr" not in own
    assert other["protocol"] == {"steps": 2, "lr": 0.01, "oracle": True, "start_candidates": 3}
    assert all(0 <= r["start_pick"] <= 3 for r in other["per_image"]) and "start_pick" not in own
    assert own["latent_spread"] >= 0.0 and all(r["fit_shift"] > 0.0 for r in own["per_image"])
    out = tmp_path / "rec.json"
    assert long_run.main(["record", *argv, "--tag", "t", "--out", str(out)]) == 0
    (rec,) = json.loads(out.read_text())
    assert rec["psnr"] == own["psnr"] and rec["milestones"]["4"]["latent_spread"] == own["latent_spread"]
    kept = rec["protocol_variants"]["oracle2"]["4"]
    assert kept["oracle_psnr"] == other["oracle_psnr"] and len(kept["per_image"]) == len(other["per_image"])
    assert set(kept["per_image"][0]) == {
        "image",
        "psnr",
        "oracle_psnr",
        "encoder_psnr",
        "left_loss_after",
        "fit_shift",
        "start_pick",
    }
    # the residual's readout as a variant: the same run scored with the local residual at the mean latent
    with pytest.raises(SystemExit):  # never the protocol's own scores
        long_run.main(["eval", *argv, "--residual-latent", "mean"])
    resmean = ["--variant", "resmean", "--protocol-steps", "2", "--train-views", "0", "--residual-latent", "mean"]
    assert long_run.main(["eval", *argv, *resmean]) == 0
    state = json.loads((run / long_run.STATE).read_text())
    assert state["variants"]["resmean"]["4"]["protocol"]["residual_latent"] == "mean"
    assert state["scores"]["4"] == own and "residual_latent" not in state["variants"]["oracle2"]["4"]["protocol"]


def test_a_residual_readout_needs_the_modulation():
    """`eval --residual-latent` on a run whose model has no modulation (splatfacto, the peer, the decoder) stops in
    one line naming the method instead of scoring the run unchanged."""
    import torch

    class Nets:
        color_model = torch.nn.Linear(1, 1)  # no residual_latent: not the modulation

    class Model:
        appearance_nets = Nets()

    with pytest.raises(SystemExit, match="modulation.*willags-paper"):
        long_run.read_residual(Model(), "mean", "willags-paper")
    with pytest.raises(SystemExit, match="splatfacto"):
        long_run.read_residual(object(), "mean", "splatfacto")


def test_a_downscaled_run_trains_and_is_scored_on_the_smaller_photos(tmp_path, monkeypatch):
    """--downscale k: the run's photos k times smaller (a resampled mirror of the scene), kept in the state so that
    every later segment and every scoring process sees the same photos."""
    from tests._scenes import small_scene

    monkeypatch.setenv("WILLAGS_CACHE", str(tmp_path / "cache"))
    data = small_scene(tmp_path / "appearance", appearance=1.0, transients=0.0)
    run = tmp_path / "run"
    argv = ["train", "--run-dir", str(run), "--method", "willags-3dgs", "--data", str(data), "--steps", "2"]
    assert long_run.main([*argv, "--milestones", "2", "--budget-s", "1e9", "--downscale", "2"]) == 0
    state = json.loads((run / long_run.STATE).read_text())
    assert state["downscale"] == 2 and state["data"] == str(data)
    full = long_run._setup("willags-3dgs", data, tmp_path / "full", 2, 42, None, "test")
    small = long_run._setup("willags-3dgs", data, run, 2, 42, 1, "test", downscale=state["downscale"])
    w, h = (
        int(full.pipeline.datamanager.eval_dataset.cameras.width[0]),
        int(full.pipeline.datamanager.eval_dataset.cameras.height[0]),
    )
    cams = small.pipeline.datamanager.eval_dataset.cameras
    assert (int(cams.width[0]), int(cams.height[0])) == (w // 2, h // 2)


def test_a_run_records_its_laps_so_a_speed_pair_shows_where_its_time_went(tmp_path, monkeypatch):
    """--lap-every k: every k steps the segment records the steps done, the train time so far and the Gaussians; the
    laps rise with the steps and end within the segment's train time."""
    from tests._scenes import small_scene

    monkeypatch.setenv("WILLAGS_CACHE", str(tmp_path / "cache"))
    data = small_scene(tmp_path / "scene", appearance=1.0, transients=0.0)
    run = tmp_path / "run"
    argv = ["train", "--run-dir", str(run), "--method", "willags-3dgs", "--data", str(data), "--steps", "5"]
    assert long_run.main([*argv, "--milestones", "5", "--budget-s", "1e9", "--lap-every", "2"]) == 0
    (seg,) = json.loads((run / long_run.STATE).read_text())["segments"]
    assert [lap[0] for lap in seg["laps"]] == [2, 4]
    times = [lap[1] for lap in seg["laps"]]
    assert 0 < times[0] < times[1] <= seg["train_s"] and all(lap[2] > 0 for lap in seg["laps"])
    run0 = tmp_path / "run0"
    argv0 = [*argv[:2], str(run0), *argv[3:]]
    assert long_run.main([*argv0, "--milestones", "5", "--budget-s", "1e9", "--lap-every", "0"]) == 0
    assert json.loads((run0 / long_run.STATE).read_text())["segments"][0]["laps"] == []
