"""WillagsModel wiring that unit tests of the components do not see: the fused teacher render."""

import math

import torch

from tests.test_mask_eval import _camera
from tests.test_mask_eval import _tiny_model as _mask_eval_tiny_model


def _tiny_model():
    """test_mask_eval's tiny model, in training shape: the mask from step 0, a teacher that differs from the student
    (as it does during training), half-transparent Gaussians."""
    model = _mask_eval_tiny_model(use_vae=True)
    model.config.mask.warmup_steps = 0
    g = torch.Generator().manual_seed(0)
    with torch.no_grad():
        model.gauss_params["opacities"].fill_(1.0)
        model.gauss_params["scales"].fill_(math.log(0.05))
        for p in model.teacher.parameters():
            p.add_(0.3 * torch.randn(p.shape, generator=g))
    model.optimizers = {}  # only read by densification, which a single forward does not reach
    return model


def test_fused_teacher_render_equals_a_second_rasterisation_and_leaves_student_gradients_unchanged():
    model = _tiny_model()
    model.train()
    cam = _camera(48, 32)
    h, w = int(cam.height), int(cam.width)
    image = (torch.rand(h, w, 3, generator=torch.Generator().manual_seed(1)) * 255).to(torch.uint8)
    names = ["means", "scales", "quats", "opacities", "features"]
    results = {}
    for fused in (True, False):
        model.config.fuse_teacher_render = fused
        model._mask_cache.clear()
        model._mask_visits.clear()
        torch.manual_seed(3)  # same reparameterisation noise in both runs
        model.set_train_batch({"image": image, "image_idx": 0})
        out = model.get_outputs(cam)
        assert "teacher_rgb" in out, "the teacher must render on a mask step"
        loss = (out["rgb"] - 0.5).square().mean()
        grads = torch.autograd.grad(loss, [model.gauss_params[k] for k in names])
        results[fused] = (out["teacher_rgb"], out["rgb"].detach(), grads)
        model._end_step(0)
    (t_f, rgb_f, g_f), (t_s, rgb_s, g_s) = results[True], results[False]
    assert t_f.shape == (h, w, 3) and not torch.allclose(t_f, rgb_f, atol=1e-3)  # really the teacher's colours
    torch.testing.assert_close(t_f, t_s, atol=1e-5, rtol=1e-5)
    torch.testing.assert_close(rgb_f, rgb_s, atol=1e-5, rtol=1e-5)
    for name, a, b in zip(names, g_f, g_s, strict=True):
        assert a.abs().sum() > 0, name
        torch.testing.assert_close(a, b, atol=1e-6, rtol=1e-4, msg=lambda m, n=name: f"{n}: {m}")


def test_appearance_path_is_finite_at_the_extremes():
    """Huge latents, Gaussians far outside the scene bounds, a Gaussian exactly at the camera centre (zero-length
    view direction): colours stay finite in [0, 1] and every gradient stays finite."""
    model = _tiny_model()
    n = model.num_points
    means = model.means.detach().clone()
    means[0] = torch.tensor([1e6, -1e6, 1e6])  # far outside the bounds: clamped, not extrapolated
    means[1] = torch.tensor([0.0, 0.0, 2.5])  # at the camera centre below
    means.requires_grad_(True)
    f_s = model.intrinsic_features.detach().clone().requires_grad_(True)
    cam_center = torch.tensor([0.0, 0.0, 2.5])
    for scale in (0.0, 1.0, 1e4, -1e4):
        z = torch.full((model.train_latents.shape[1],), scale, requires_grad=True)
        rgb = model.appearance_colors(z, means, f_s, cam_center)
        assert rgb.shape == (n, 3) and torch.isfinite(rgb).all() and rgb.min() >= 0 and rgb.max() <= 1
        gz, gm, gf = torch.autograd.grad(rgb.sum(), [z, means, f_s])
        assert torch.isfinite(gz).all() and torch.isfinite(gm).all() and torch.isfinite(gf).all(), scale


def test_fixed_appearance_renders_through_baked_sh_close_to_the_decoder_and_runs_it_once():
    model = _tiny_model()
    with torch.no_grad():
        g = torch.Generator().manual_seed(6)
        for p in model.appearance_nets.parameters():  # a decoder with real latent and view dependence
            p.add_(0.3 * torch.randn(p.shape, generator=g))
    model.eval()
    model.render_latent = torch.randn(model.train_latents.shape[1], generator=g)
    cam = _camera(48, 32)
    calls = []
    model.appearance_nets.color.register_forward_hook(lambda *a: calls.append(1))
    with torch.no_grad():
        model.config.render_sh_degree = -1
        exact = model.get_outputs(cam)["rgb"]
        n_exact = len(calls)
        model.config.render_sh_degree = 3
        first = model.get_outputs(cam)["rgb"]  # a first frame with this appearance: still the exact decoder
        n_first = len(calls) - n_exact
        baked = model.get_outputs(cam)["rgb"]  # the same appearance again: bake once
        n_second = len(calls) - n_exact - n_first
        cam.camera_to_worlds[0, 0, 3] += 0.2  # the viewer moves the camera; the appearance stays
        model.get_outputs(cam)
        n_third = len(calls) - n_exact - n_first - n_second
        model.step += 1  # training moved the Gaussians: exact again for one frame, no bake per frame
        model.get_outputs(cam)
        n_fourth = len(calls) - n_exact - n_first - n_second - n_third
    torch.testing.assert_close(first, exact)
    assert (n_exact, n_first, n_third, n_fourth) == (1, 1, 0, 1) and n_second >= 32  # baked once, never per frame
    psnr = -10 * torch.log10(((baked - exact) ** 2).mean())
    assert psnr > 35, f"baked SH render differs from the decoder's: {psnr:.1f} dB"
    assert (baked - exact).abs().max() < 0.1
    # a camera-supplied latent (the NeRF-W protocol, the demo) always takes the exact decoder path
    cam.metadata = {"appearance_latent": model.render_latent}
    with torch.no_grad():
        before = len(calls)
        model.get_outputs(cam)
    assert len(calls) - before == 1
