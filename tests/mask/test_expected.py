"""The scene's expected residual (willags_ns/mask/expected.py): the rule thresholds the residual beyond it, the two
channels fit each Gaussian's level to the median residual without touching the rest of the model, and a run with it
densifies, saves and reloads the levels."""

import math

import pytest
import torch

from tests._configs import mask as mask_config
from tests.test_mask_eval import _camera
from tests.test_model import _tiny_model
from willags_ns.eval.mask_eval import expected_render
from willags_ns.mask.expected import LEVEL, excess_residual, level_loss
from willags_ns.mask.residual import ResidualConfig, colour_residual
from willags_ns.mask.rule import compare_to_teacher
from willags_ns.splats.gaussians import rasterize_gaussians

H, W = 64, 96
OCCLUDER = (slice(8, 32), slice(8, 40))
HARD = (slice(32, 56), slice(56, 88))


def test_the_rule_keeps_what_every_photo_gets_wrong_and_still_finds_the_occluder():
    g = torch.Generator().manual_seed(0)
    render = 0.3 + 0.4 * torch.rand(H, W, 3, generator=g)
    photo = (render + 0.02 * torch.randn(H, W, 3, generator=g)).clamp(0, 1)
    photo[OCCLUDER] = torch.tensor([0.95, 0.1, 0.9])  # a passer-by in this photo only
    photo[HARD] = (render[HARD] + 0.3).clamp(0, 1)  # static scene the model misses in every photo
    cfg = mask_config(distance="residual")
    plain, _, d_plain = compare_to_teacher(cfg, 10_000, photo, render, None)
    assert plain[OCCLUDER].float().mean() > 0.9 and plain[HARD].float().mean() > 0.9  # both taken out
    expected = torch.zeros(H, W)
    expected[HARD] = colour_residual(photo, render)[HARD].mean()  # what the other photos taught its Gaussians
    beyond, _, d = compare_to_teacher(cfg, 10_000, photo, render, None, expected=expected)
    assert beyond[OCCLUDER].float().mean() > 0.9, "the occluder is no static scene's usual residual"
    assert beyond[HARD].float().mean() < 0.05, "the hard static region is masked although every photo shows it so"
    torch.testing.assert_close(d, excess_residual(d_plain, expected))
    assert (d >= 0).all() and torch.equal(d[OCCLUDER], d_plain[OCCLUDER])
    assert not (beyond & ~plain).any(), "beyond the expected residual masks a subset of the plain rule's pixels"


def test_level_loss_is_zero_in_value_and_the_absolute_deviations_gradient_in_the_probe():
    e, r = torch.rand(5, 7), torch.rand(5, 7)
    probe = torch.zeros(5, 7, requires_grad=True)
    loss = level_loss(e, probe, r)
    assert loss.item() == 0.0
    (grad,) = torch.autograd.grad(loss, probe)
    torch.testing.assert_close(grad, torch.sign(e - r) / e.numel())


def _expected_model(fused: bool):
    fields = {"distance": "residual", "residual": ResidualConfig(expected=True)}
    model = _tiny_model("modulated", mask_fields=fields)
    model.config.mask.teacher.fused = fused
    g = torch.Generator().manual_seed(5)
    with torch.no_grad():
        model.gauss_params[LEVEL].copy_(0.2 * torch.rand(model.num_points, 1, generator=g))
        model.gauss_params["opacities"].fill_(-1.0)  # half-transparent: every Gaussian's weight counts
    model.train()
    return model


@pytest.mark.parametrize("fused", [True, False])
def test_the_channels_fit_the_levels_and_leave_every_other_gradient_as_it_was(fused):
    model = _expected_model(fused)
    assert model.gauss_params[LEVEL].shape == (model.num_points, 1)
    cam = _camera(48, 32)
    h, w = int(cam.height), int(cam.width)
    image = (torch.rand(h, w, 3, generator=torch.Generator().manual_seed(1)) * 255).to(torch.uint8)
    model.set_train_batch({"image": image, "image_idx": 0})
    out = model.get_outputs(cam)
    assert "teacher_rgb" in out and "expected_probe" in out, "a mask step carries the level channels"
    assert torch.equal(out["expected_probe"], torch.zeros(h, w))
    gt = model.get_gt_img(image).to(out["rgb"])  # background black: no compositing to redo
    losses = model.get_loss_dict(out, {"image": image, "image_idx": 0})
    assert losses[LEVEL].item() == 0.0
    names = ["means", "scales", "quats", "opacities", "features", "features_dc", "features_rest", LEVEL]
    params = [model.gauss_params[k] for k in names]
    with_level = torch.autograd.grad(sum(losses.values()), params, retain_graph=True, allow_unused=True)
    without = torch.autograd.grad(losses["main_loss"], params[:-1], retain_graph=True)
    for name, a, b in zip(names, with_level, without, strict=False):
        torch.testing.assert_close(a, b, msg=lambda m, n=name: f"{n}: {m}")

    # the level's gradient is that of mean |E - r| with E rendered from the levels on fixed geometry
    gp = {k: v.detach() for k, v in model.gauss_params.items()}
    view = model._view(cam)
    level = model.gauss_params[LEVEL].detach().clone().requires_grad_(True)
    args = (gp["means"], gp["quats"], gp["scales"], gp["opacities"], level, view.viewmat, view.K, w, h)
    e, _, _ = rasterize_gaussians(model.config, *args, "RGB", None, False)
    torch.testing.assert_close(e[0, ..., 0], out["expected_residual"], atol=1e-5, rtol=1e-4)
    model.eval()  # what the mask's evaluation and the viewer subtract: the same map
    torch.testing.assert_close(expected_render(model, cam, 0), out["expected_residual"], atol=1e-5, rtol=1e-4)
    assert expected_render(_tiny_model("modulated"), cam, 0) is None  # no levels, nothing to subtract
    r = colour_residual(gt, out["teacher_rgb"])
    (want,) = torch.autograd.grad((e[0, ..., 0] - r).abs().mean(), level)
    assert want.abs().sum() > 0
    torch.testing.assert_close(with_level[-1], want, atol=1e-7, rtol=1e-4)


@pytest.mark.slow
def test_a_run_with_the_expected_residual_densifies_saves_and_reloads_the_levels(tmp_path):
    from nerfstudio.utils.eval_utils import eval_setup

    from tests.test_train import _check_finite, _train

    overrides = {"mask.enabled": True, "mask.distance": "residual", "mask.residual.expected": True}
    config, trainer, losses = _train(
        tmp_path, "willags", steps=20, densification="mcmc", auto_config=False, **overrides
    )
    _check_finite(losses)
    model = trainer.pipeline.model
    level = model.gauss_params[LEVEL]
    assert level.shape == (model.num_points, 1) and model.num_points > 0
    assert level.abs().max() > 0, "no mask step fitted the levels"
    assert math.isfinite(level.sum().item())
    _, pipeline, _, _ = eval_setup(config.get_base_dir() / "config.yml", test_mode="test")
    torch.testing.assert_close(pipeline.model.gauss_params[LEVEL].cpu(), level.detach().cpu())


def test_a_negative_level_expects_nothing_rather_than_less():
    r = torch.tensor([[0.2, 0.05, 0.3]])
    e = torch.tensor([[-0.5, 0.1, 0.1]])
    torch.testing.assert_close(excess_residual(r, e), torch.tensor([[0.2, 0.0, 0.2]]))
