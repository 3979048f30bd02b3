"""Held-out halves (willags_ns/eval/holdout.py): which photos lend their right half, the loss that never sees it, the
scorings and the copy a run ends with."""

import pytest
import torch

from willags_ns.eval.holdout import (
    BestStep,
    HoldoutConfig,
    copy_state,
    holdout_indices,
    is_scoring_step,
    left_half_weight,
)
from willags_ns.eval.protocol import split_halves


@pytest.mark.parametrize(
    "n, k, want",
    [(47, 8, 8), (12, 8, 3), (16, 4, 4), (3, 8, 0), (100, 0, 0), (8, 1, 1)],
)
def test_held_out_photos_are_evenly_spaced_and_at_most_a_quarter(n, k, want):
    idx = holdout_indices(n, k)
    assert len(idx) == want and len(set(idx)) == want and all(0 <= i < n for i in idx)
    if want > 1:  # evenly spaced: neighbours n / k apart, give or take one
        gaps = [b - a for a, b in zip(idx[:-1], idx[1:], strict=True)]
        assert max(gaps) - min(gaps) <= 1 and abs(gaps[0] - n / want) < 1


@pytest.mark.parametrize("w", [2, 7, 48, 49])
def test_a_held_out_photo_trains_on_exactly_the_protocols_left_half(w):
    weight = left_half_weight(5, w)
    left, right = split_halves(w)
    assert weight.shape == (5, w)
    assert torch.all(weight[:, left] == 1) and torch.all(weight[:, right] == 0)


def test_scoring_steps_start_late_and_follow_the_cadence():
    cfg = HoldoutConfig(photos=4, every=1000, start=3000)
    steps = [s for s in range(0, 15000) if is_scoring_step(s, cfg, last_step=14999)]
    assert steps == [3000, 4000, 5000, 6000, 7000, 8000, 9000, 10000, 11000, 12000, 13000, 14000, 14999]
    assert not is_scoring_step(2999, cfg, last_step=2999)  # a run that ends before start is never scored


def test_the_best_step_is_copied_once_and_restored_only_beyond_the_margin():
    copies = []

    def take(step):
        return lambda: copies.append(step) or {"x": torch.tensor(float(step))}

    best = BestStep(margin=0.1)
    assert best.to_restore() is None
    for step, score in ((3000, 20.0), (4000, 20.5), (5000, 20.45)):
        best.observe(step, score, take(step))
    assert copies == [3000, 4000] and best.best_step == 4000
    assert best.to_restore() is None  # 0.05 below the best: inside the margin, the last step stays
    best.observe(6000, 20.3, take(6000))
    assert float(best.to_restore()["x"]) == 4000.0  # 0.2 below: the run ends with step 4000's copy
    best.observe(7000, 21.0, take(7000))
    assert best.to_restore() is None and copies == [3000, 4000, 7000]  # the last is the best
    assert best.summary() == {
        "history": [(3000, 20.0), (4000, 20.5), (5000, 20.45), (6000, 20.3), (7000, 21.0)],
        "best_step": 7000,
        "best_psnr": 21.0,
    }


def _tiny_training_model():
    from tests.test_mask_eval import _tiny_model

    model = _tiny_model(use_vae=False, mask_fields={"enabled": False})
    model.optimizers = {}
    model.train()
    return model


def test_the_loss_of_a_held_out_photo_never_sees_its_right_half():
    from tests.test_mask_eval import _camera

    model = _tiny_training_model()
    model.holdout = (0,)
    cam = _camera(48, 32)
    g = torch.Generator().manual_seed(3)
    image = (torch.rand(32, 48, 3, generator=g) * 255).to(torch.uint8)
    other = image.clone()
    other[:, 24:] = (torch.rand(32, 24, 3, generator=g) * 255).to(torch.uint8)  # another right half

    def loss_and_grad(photo, idx):
        model.zero_grad(set_to_none=True)
        batch = {"image": photo, "image_idx": idx}
        model.set_train_batch(batch)
        out = model.get_outputs(cam)
        loss = model.get_loss_dict(out, batch, {})["main_loss"]
        loss.backward()
        grad = model.gauss_params["features_dc"].grad.clone()
        model.end_step(0)
        return loss.detach(), grad

    held, held_grad = loss_and_grad(image, 0)
    held2, held2_grad = loss_and_grad(other, 0)
    assert torch.equal(held, held2) and torch.equal(held_grad, held2_grad)
    seen, _ = loss_and_grad(image, 1)
    seen2, _ = loss_and_grad(other, 1)
    assert not torch.equal(seen, seen2)  # a photo that lends nothing trains on all of itself


def test_restoring_a_copy_puts_back_every_tensor_and_drops_the_gaussians_optimiser_moments():
    model = _tiny_training_model()
    copy = copy_state(model)
    assert not any(k.startswith("perceptual.") for k in copy)
    means = model.gauss_params["means"]
    opt = torch.optim.Adam([means], lr=1e-3)
    model.optimizers = {"means": opt}
    with torch.no_grad():  # the run goes on: more Gaussians, other values, Adam's moments for them
        for p in model.gauss_params.values():
            p.data = torch.cat([p.data, p.data[:5]]) * 1.5
        for p in model.appearance_nets.parameters():
            p.add_(1.0)
    means.grad = torch.ones_like(means)
    opt.step()
    assert opt.state[means]
    model._restore(copy)
    after = model.state_dict()
    for k, v in copy.items():
        assert torch.equal(after[k], v), k
    assert model.gauss_params["means"] is means and opt.state[means] == {}


def _scripted_scorings(monkeypatch, scores: list[float]) -> dict[int, dict]:
    """The model's held-out scorings return `scores` in turn; returns {step: the copy taken at that step}, filled as
    the run takes them."""
    import willags_ns.model as model_module

    it = iter(scores)
    monkeypatch.setattr(model_module, "holdout_psnr", lambda *a, **k: next(it))
    copies: dict[int, dict] = {}

    def spy_copy(model):
        copies[model.step] = c = copy_state(model)
        return c

    monkeypatch.setattr(model_module, "copy_state", spy_copy)
    return copies


def test_a_run_ends_with_its_best_scoring_step_and_its_checkpoint_says_so(tmp_path, monkeypatch, capsys):
    """30 CPU steps, four photos lending their right half, scored at steps 10 and 20 and after the last (29); the
    scores are scripted so that step 10 is best by more than the margin: the last checkpoint holds step 10's
    Gaussians."""
    from tests.test_train import _train

    copies = _scripted_scorings(monkeypatch, [20.0, 18.0, 17.0])
    overrides = {"holdout.photos": 4, "holdout.start": 10, "holdout.every": 10}
    _, trainer, _ = _train(tmp_path, "willags", steps=30, device="cpu", **overrides)
    model = trainer.pipeline.model
    assert len(model.holdout) == 4
    assert [s for s, _ in model.holdout_best.history] == [10, 20, 29] and list(copies) == [10]
    assert "best 20.00 at step 10; the run ends with step 10's model" in capsys.readouterr().out
    ckpt = torch.load(sorted(trainer.checkpoint_dir.glob("step-*.ckpt"))[-1], map_location="cpu", weights_only=False)
    saved = ckpt["pipeline"]
    assert torch.equal(saved["_model.gauss_params.means"], copies[10]["gauss_params.means"])
    assert saved["_model._extra_state"]["holdout"]["best_step"] == 10


def test_a_run_scores_its_held_out_halves_as_the_protocol_would(tmp_path):
    """Unscripted: 12 CPU steps, scored at 5, 10 and 11, each a finite PSNR of the held-out right halves."""
    from tests.test_train import _train

    overrides = {"holdout.photos": 2, "holdout.start": 5, "holdout.every": 5}
    _, trainer, _ = _train(tmp_path, "willags", steps=12, device="cpu", **overrides)
    model = trainer.pipeline.model
    assert [s for s, _ in model.holdout_best.history] == [5, 10, 11]
    assert all(0.0 < p < 100.0 for _, p in model.holdout_best.history)
    assert model.training  # scoring renders in eval mode and gives training mode back


@pytest.mark.parametrize("field, value", [("photos", -1), ("every", 0), ("start", -5), ("margin", -0.1)])
def test_a_bad_holdout_setting_is_refused_naming_it(field, value):
    from willags_ns.config import WillagsModelConfig

    with pytest.raises(ValueError, match=rf"holdout\.\*.*{field} {value}"):
        WillagsModelConfig(holdout=HoldoutConfig(**{field: value}))


def test_the_benchmark_harness_ends_a_run_as_ns_train_does(tmp_path, monkeypatch):
    """`python -m benchmarks long-run train` stops its loop itself; its last checkpoint still holds the model the run
    ends with (the best-scoring step's, scores scripted), as `ns-train`'s does."""
    import benchmarks.methods as methods
    from benchmarks import long_run
    from tests._scenes import small_scene

    spec = methods.MethodSpec("willags", (("holdout.photos", 2), ("holdout.start", 2), ("holdout.every", 2)))
    monkeypatch.setitem(methods.METHODS, "willags-holdout-test", spec)
    copies = _scripted_scorings(monkeypatch, [20.0, 18.0, 17.0])
    data = small_scene(tmp_path / "scene", appearance=1.0, transients=0.0)
    run = tmp_path / "run"
    argv = ["train", "--method", "willags-holdout-test", "--data", str(data), "--run-dir", str(run), "--steps", "6"]
    assert long_run.main([*argv, "--milestones", "6", "--budget-s", "1e9"]) == 0
    assert list(copies) == [2]
    ckpt = torch.load(sorted(run.rglob("step-000000005.ckpt"))[0], map_location="cpu", weights_only=False)
    assert torch.equal(ckpt["pipeline"]["_model.gauss_params.means"], copies[2]["gauss_params.means"].cpu())
    assert [s for s, _ in ckpt["pipeline"]["_model._extra_state"]["holdout"]["history"]] == [2, 4, 5]
