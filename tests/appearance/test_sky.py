"""The appearance-conditioned background (willags_ns/appearance/sky.py) and its wiring in the model."""

import math

import pytest
import torch

from tests.test_mask_eval import _camera
from tests.test_model import _tiny_model
from willags_ns.appearance.sky import SkyConfig, SkyModel, background_alpha_penalty, pixel_directions


def test_pixel_directions_match_nerfstudio_rays():
    cam = _camera(12, 8)
    c2w = cam.camera_to_worlds.clone()
    # a rotated, translated camera: the directions must follow the rotation and ignore the translation
    ang = 0.7
    R = torch.tensor([[math.cos(ang), 0.0, math.sin(ang)], [0.0, 1.0, 0.0], [-math.sin(ang), 0.0, math.cos(ang)]])
    c2w[0, :3, :3] = R
    c2w[0, :3, 3] = torch.tensor([3.0, -1.0, 2.0])
    cam.camera_to_worlds = c2w
    want = cam.generate_rays(camera_indices=0, keep_shape=True).directions  # [H, W, 3]
    got = pixel_directions(c2w[0], cam.get_intrinsics_matrices()[0], 12, 8)
    assert got.shape == (8, 12, 3)
    torch.testing.assert_close(got, want, atol=1e-5, rtol=1e-5)
    torch.testing.assert_close(got.norm(dim=-1), torch.ones(8, 12))


def test_sky_starts_grey_and_learns_a_latent_dependent_gradient():
    torch.manual_seed(0)
    sky = SkyModel(4, SkyConfig(enabled=True, sh_degree=2, hidden=16))
    dirs = torch.nn.functional.normalize(torch.randn(64, 3), dim=-1)
    z_a, z_b = torch.zeros(4), torch.ones(4)
    torch.testing.assert_close(sky(z_a, dirs), torch.full((64, 3), 0.5))  # grey, direction-independent
    # target: photo A has a blue sky brightening upwards, photo B an orange one
    up = dirs[:, 1:2].clamp(-1, 1)
    tgt_a = torch.cat([0.3 + 0.2 * up, 0.5 + 0.2 * up, 0.8 + 0.1 * up], -1)
    tgt_b = torch.tensor([0.9, 0.6, 0.3]).expand(64, 3)
    opt = torch.optim.Adam(sky.parameters(), lr=1e-2)
    for _ in range(400):
        loss = (sky(z_a, dirs) - tgt_a).square().mean() + (sky(z_b, dirs) - tgt_b).square().mean()
        opt.zero_grad()
        loss.backward()
        opt.step()
    assert (sky(z_a, dirs) - tgt_a).abs().max() < 0.03
    assert (sky(z_b, dirs) - tgt_b).abs().max() < 0.03


def test_sky_is_bounded_for_huge_latents_and_rejects_bad_degrees():
    sky = SkyModel(4, SkyConfig(enabled=True))
    with torch.no_grad():
        for p in sky.parameters():
            p.normal_()
    out = sky(torch.full((4,), 1e6), torch.nn.functional.normalize(torch.randn(10, 3), dim=-1))
    assert torch.isfinite(out).all() and out.min() >= 0 and out.max() <= 1
    with pytest.raises(ValueError, match="sky.sh_degree"):
        SkyModel(4, SkyConfig(enabled=True, sh_degree=5))


def test_background_alpha_penalty_only_where_the_background_explains_the_photo():
    h, w = 20, 20
    bg = torch.full((h, w, 3), 0.6)
    gt = bg.clone()
    gt[10:] = 0.1  # the lower half is a building the sky does not explain
    alpha = torch.zeros(h, w, 1)
    alpha[:, :] = 0.25
    alpha[10:] = 1.0
    pen = background_alpha_penalty(alpha, gt, bg, tol=0.03)
    # rows well inside the sky (the 5x5 window keeps the two rows next to the edge out) carry alpha 0.25
    assert pen is not None and abs(float(pen) - 0.25) < 1e-6
    assert background_alpha_penalty(alpha, torch.zeros(h, w, 3), bg, tol=0.03) is None  # nothing explained: no 0/0
    mask = torch.zeros(h, w)
    assert background_alpha_penalty(alpha, gt, bg, tol=0.03, mask=mask) is None  # all transient: nothing
    # the gradient reaches alpha, not the background
    a = alpha.clone().requires_grad_(True)
    b = bg.clone().requires_grad_(True)
    background_alpha_penalty(a, gt, b, tol=0.03).backward()
    assert a.grad.abs().sum() > 0 and b.grad is None


def _sky_model():
    model = _tiny_model("modulated")
    from willags_ns.appearance.sky import SkyModel as _Sky

    model.config.sky = SkyConfig(enabled=True, sh_degree=2, alpha_penalty=0.1, region="everywhere")
    d = model.appearance_nets.latent_dim
    torch.manual_seed(5)
    for nets in (model.appearance_nets, model.teacher):
        nets.sky = _Sky(d, model.config.sky)
        with torch.no_grad():
            for p in nets.sky.parameters():
                p.normal_(0.0, 0.2)
    return model


def test_model_composites_over_the_sky_of_the_latent_and_the_teacher_uses_its_own():
    model = _sky_model()
    model.eval()
    cam = _camera(24, 16)
    with torch.no_grad():
        model.gauss_params["opacities"].fill_(-20.0)  # no Gaussian visible: the render is the sky alone
        z1, z2 = torch.zeros(model.appearance_nets.latent_dim), torch.ones(model.appearance_nets.latent_dim)
        outs = []
        for z in (z1, z2):
            cam.metadata = {"appearance_latent": z}
            outs.append(model.get_outputs(cam))
    dirs = pixel_directions(cam.camera_to_worlds[0], cam.get_intrinsics_matrices()[0], 24, 16)
    torch.testing.assert_close(outs[0]["rgb"], model.appearance_nets.sky(z1, dirs), atol=1e-5, rtol=1e-5)
    assert not torch.allclose(outs[0]["rgb"], outs[1]["rgb"], atol=1e-3)  # the latent chooses the sky
    assert outs[0]["background"].shape == (16, 24, 3)

    # training: the fused teacher channels sit over the teacher's sky, the student's over its own
    model.train()
    model.config.mask.teacher.fused = True
    image = (torch.rand(16, 24, 3, generator=torch.Generator().manual_seed(1)) * 255).to(torch.uint8)
    model.set_train_batch({"image": image, "image_idx": 0})
    out = model.get_outputs(_camera(24, 16))
    z_s = model.appearance_nets.latent_stats(model._image_chw(image), 0)[0]
    z_t = out["teacher_latent"]
    with torch.no_grad():
        torch.testing.assert_close(out["teacher_rgb"], model.teacher.sky(z_t, dirs), atol=1e-5, rtol=1e-5)
    assert not torch.allclose(out["rgb"].detach(), out["teacher_rgb"], atol=1e-3)
    assert z_s.shape == z_t.shape
    # the loss has the alpha term (the photo equals the sky somewhere once the sky matches it) and backpropagates
    batch = {"image": (out["rgb"].detach() * 255).to(torch.uint8), "image_idx": 0}
    losses = model.get_loss_dict(out, batch, {})
    assert "sky_alpha" in losses and torch.isfinite(losses["sky_alpha"])
    total = sum(losses.values())
    total.backward()
    grads = [p.grad for p in model.appearance_nets.sky.parameters()]
    assert all(g is not None and torch.isfinite(g).all() for g in grads)
    assert any(g.abs().sum() > 0 for g in grads)
    model.end_step(0)


def test_open_region_sky_shows_above_the_skyline_and_the_random_colour_below():
    import numpy as np

    from willags_ns.appearance.sky import OpenRegions

    model = _sky_model()
    model.config.sky.region = "open"
    rng = np.random.default_rng(0)
    uv = np.stack([rng.uniform(0, 1, 2000), rng.uniform(0.5, 1.0, 2000)], 1)  # keypoints in the lower half only
    model.open_regions = OpenRegions([np.concatenate([uv, np.full((2000, 1), 6.0)], 1).astype(np.float32), None])
    model.open_regions.observations[1] = np.zeros((0, 3), np.float32)
    model.train()
    with torch.no_grad():
        model.gauss_params["opacities"].fill_(-20.0)  # nothing in front: the render is the background
    W, H = 32, 32
    image = (torch.rand(H, W, 3, generator=torch.Generator().manual_seed(1)) * 255).to(torch.uint8)
    model.set_train_batch({"image": image, "image_idx": 0})
    out = model.get_outputs(_camera(W, H))
    bg, rgb = out["background"], out["rgb"].detach()
    z = out["latent"]
    dirs = pixel_directions(_camera(W, H).camera_to_worlds[0], _camera(W, H).get_intrinsics_matrices()[0], W, H)
    sky = model.appearance_nets.sky(z, dirs).detach()
    top, bottom = slice(0, 12), slice(18, 32)  # skyline at 0.5 less the one-cell dilation: rows < 15 are open
    torch.testing.assert_close(rgb[top], sky[top], atol=1e-5, rtol=1e-5)
    flat = rgb[bottom].reshape(-1, 3)
    assert torch.allclose(flat, flat[:1].expand_as(flat))  # one (random) colour under the skyline
    assert not torch.allclose(rgb[bottom], sky[bottom], atol=1e-3)
    assert bg.shape == (H, W, 3)
    model.end_step(0)
    # an image without keypoints: no open cells, the random colour everywhere; evaluation: the sky everywhere
    model.set_train_batch({"image": image, "image_idx": 1})
    flat = model.get_outputs(_camera(W, H))["rgb"].detach().reshape(-1, 3)
    assert torch.allclose(flat, flat[:1].expand_as(flat))
    model.end_step(1)
    model.eval()
    cam = _camera(W, H)
    cam.metadata = {"appearance_latent": z.detach()}
    with torch.no_grad():
        ev = model.get_outputs(cam)["rgb"]
    torch.testing.assert_close(ev, model.appearance_nets.sky(z.detach(), dirs), atol=1e-5, rtol=1e-5)


def test_open_region_sky_without_keypoints_is_off():
    from tests.test_mask_eval import _tiny_model as _bare_model

    model = _bare_model(use_vae=True, sky=SkyConfig(enabled=True, region="open"))
    assert model.appearance_nets.sky is None and model.open_regions is None
    assert model.config.sky.enabled and model.config.sky.region == "open"  # the config is read, never written


@pytest.mark.parametrize("degree", [0, 1, 2, 3, 4])
def test_sky_equals_the_sh_expansion_it_stands_for(degree):
    """The sky's colour, evaluated through the monomials, is sum_k c_k(z) Y_k(d) + 0.5 clamped, with the SH basis of
    render/sh.py (gsplat's constants), in float32 rounding; and the gradient reaches the latent network."""
    from willags_ns.render.sh import eval_sh_bases

    torch.manual_seed(degree)
    sky = SkyModel(8, SkyConfig(enabled=True, sh_degree=degree, hidden=16))
    torch.nn.init.normal_(sky.mlp[-1].weight, std=0.3)  # away from the grey start
    z = torch.randn(8)
    dirs = torch.nn.functional.normalize(torch.randn(4000, 3), dim=-1)
    ref = (eval_sh_bases(degree, dirs) @ sky.coefficients(z) + 0.5).clamp(0.0, 1.0)
    out = sky(z, dirs)
    torch.testing.assert_close(out, ref, atol=2e-6, rtol=0)
    out.sum().backward()
    assert sky.mlp[-1].weight.grad.abs().sum() > 0
    assert "monomial_to_sh" not in sky.state_dict()  # a constant of the degree, not a parameter of checkpoints
