"""WillagsModel wiring that unit tests of the components do not see: the fused teacher render, the appearance
path at the extremes, rendering a fixed appearance through baked SH; for both colour modes."""

import math

import pytest
import torch

from tests.test_mask_eval import _camera
from tests.test_mask_eval import _tiny_model as _mask_eval_tiny_model

MODES = ("modulated", "decoder")


def _tiny_model(color_mode: str = "modulated", **overrides):
    """test_mask_eval's tiny model, in training shape: the mask from step 0, a teacher that differs from the student
    (as it does during training), half-transparent Gaussians. Modulated: the zero-initialised colour transform is
    perturbed (a trained one is not the identity) and the SH has view dependence (degree 3 active)."""
    model = _mask_eval_tiny_model(use_vae=True, color_mode=color_mode, **overrides)
    model.config.mask.warmup_steps = 0
    g = torch.Generator().manual_seed(0)
    with torch.no_grad():
        model.gauss_params["opacities"].fill_(1.0)
        model.gauss_params["scales"].fill_(math.log(0.05))
        for p in model.teacher.parameters():
            p.add_(0.3 * torch.randn(p.shape, generator=g))
        if color_mode == "modulated":
            for p in model.appearance_nets.modulation.parameters():
                p.add_(0.1 * torch.randn(p.shape, generator=g))
            model.gauss_params["features_rest"].normal_(0.0, 0.03, generator=g)
            # colours away from 0, where 3DGS' clamp (and so the bake's one approximation) does not bite
            rgb = 0.25 + 0.5 * torch.rand(model.num_points, 3, generator=g)
            model.gauss_params["features_dc"].copy_((rgb - 0.5) / 0.28209479177387814)
            model.step = 10_000  # SH degree 3 active
    model.optimizers = {}  # only read by densification, which a single forward does not reach
    return model


@pytest.mark.parametrize("color_mode", MODES)
def test_fused_teacher_render_equals_a_second_rasterisation_and_leaves_student_gradients_unchanged(color_mode):
    model = _tiny_model(color_mode)
    model.train()
    cam = _camera(48, 32)
    h, w = int(cam.height), int(cam.width)
    image = (torch.rand(h, w, 3, generator=torch.Generator().manual_seed(1)) * 255).to(torch.uint8)
    names = ["means", "scales", "quats", "opacities", "features"]
    if color_mode == "modulated":
        names += ["features_dc", "features_rest"]
    results = {}
    for fused in (True, False):
        model.config.mask.teacher.fused = fused
        model.last_masks.clear()
        model.mask_step.visits.clear()
        torch.manual_seed(3)  # same reparameterisation noise in both runs
        model.set_train_batch({"image": image, "image_idx": 0})
        out = model.get_outputs(cam)
        assert "teacher_rgb" in out, "the teacher must render on a mask step"
        loss = (out["rgb"] - 0.5).square().mean()
        grads = torch.autograd.grad(loss, [model.gauss_params[k] for k in names])
        results[fused] = (out["teacher_rgb"], out["rgb"].detach(), grads)
        model.end_step(0)
    (t_f, rgb_f, g_f), (t_s, rgb_s, g_s) = results[True], results[False]
    assert t_f.shape == (h, w, 3) and not torch.allclose(t_f, rgb_f, atol=1e-3)  # really the teacher's colours
    torch.testing.assert_close(t_f, t_s, atol=1e-5, rtol=1e-5)
    torch.testing.assert_close(rgb_f, rgb_s, atol=1e-5, rtol=1e-5)
    for name, a, b in zip(names, g_f, g_s, strict=True):
        assert a.abs().sum() > 0, name
        torch.testing.assert_close(a, b, atol=1e-6, rtol=1e-4, msg=lambda m, n=name: f"{n}: {m}")


@pytest.mark.parametrize("color_mode", MODES)
def test_appearance_path_is_finite_at_the_extremes(color_mode):
    """Huge latents, Gaussians far outside the scene bounds, a Gaussian exactly at the camera centre (zero-length
    view direction): colours stay finite (in [0, 1] for the decoder's sigmoid, >= 0 for the modulated SH colour,
    which the compositing clamps) and every gradient stays finite."""
    model = _tiny_model(color_mode)
    n = model.num_points
    means = model.means.detach().clone()
    means[0] = torch.tensor([1e6, -1e6, 1e6])  # far outside the bounds: clamped, not extrapolated
    means[1] = torch.tensor([0.0, 0.0, 2.5])  # at the camera centre below
    means.requires_grad_(True)
    f_s = model.intrinsic_features.detach().clone().requires_grad_(True)
    cam_center = torch.tensor([0.0, 0.0, 2.5])
    for scale in (0.0, 1.0, 1e4, -1e4):
        z = torch.full((model.train_latents.shape[1],), scale, requires_grad=True)
        rgb = model.appearance_colors(z, means, f_s, cam_center).rgb
        assert rgb.shape == (n, 3) and torch.isfinite(rgb).all() and rgb.min() >= 0
        assert color_mode == "modulated" or rgb.max() <= 1
        gz, gm, gf = torch.autograd.grad(rgb.sum(), [z, means, f_s])
        assert torch.isfinite(gz).all() and torch.isfinite(gm).all() and torch.isfinite(gf).all(), scale


def test_fixed_appearance_renders_through_baked_sh_close_to_the_decoder_and_runs_it_once():
    model = _tiny_model("decoder")
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


def test_modulated_appearance_bakes_to_sh_exactly_once_per_appearance():
    """color_mode='modulated' is affine in the SH coefficients: the baked SH render equals the exact render (no
    least-squares fit), and the bake runs the colour transform once per appearance, never per frame."""
    model = _tiny_model("modulated")
    model.eval()
    g = torch.Generator().manual_seed(6)
    model.render_latent = torch.randn(model.train_latents.shape[1], generator=g)
    cam = _camera(48, 32)
    calls = []
    mod = model.appearance_nets.modulation
    global_params = mod.global_params  # the colour transform of a latent (its MLP runs as addmv, past module hooks)
    mod.global_params = lambda z: calls.append(1) or global_params(z)
    with torch.no_grad():
        model.config.render_sh_degree = -1
        exact = model.get_outputs(cam)["rgb"]
        model.config.render_sh_degree = 3
        model.get_outputs(cam)  # first frame of this appearance: exact path
        before = len(calls)
        baked = model.get_outputs(cam)["rgb"]  # second: bake
        cam.camera_to_worlds[0, 0, 3] += 0.2
        moved_baked = model.get_outputs(cam)["rgb"]
        n_bake = len(calls) - before
        model.config.render_sh_degree = -1
        moved_exact = model.get_outputs(cam)["rgb"]
    assert n_bake == 1
    assert not torch.allclose(exact, moved_exact, atol=1e-3)  # really view-dependent
    torch.testing.assert_close(baked, exact, atol=2e-5, rtol=1e-4)
    torch.testing.assert_close(moved_baked, moved_exact, atol=2e-5, rtol=1e-4)
    # the exported SH (ns-export) is the same bake of the chosen appearance
    model.config.render_sh_degree = 3
    sh = model.export_sh()
    assert sh.shape == (model.num_points, 16, 3) and torch.isfinite(sh).all()
    torch.testing.assert_close(model.shs_0, sh[:, 0, :])


def test_residual_latent_mean_renders_the_mean_latents_residual_and_still_bakes_exactly():
    """modulation.residual_latent "mean": rendering a chosen latent (the viewer, export, the NeRF-W protocol) gives
    the Gaussians the global transform of that latent and the local residual of the training latents' mean; the
    baked SH still equals the exact render; training steps read the photo's own latent."""
    from willags_ns.appearance.modulation import ColorModulationConfig

    model = _tiny_model("modulated", modulation=ColorModulationConfig(residual_latent="mean"))
    mod = model.appearance_nets.modulation
    g = torch.Generator().manual_seed(7)
    with torch.no_grad():
        model.train_latents.normal_(0.0, 1.0, generator=g)  # two training photos with distinct latents
        model.train_latent_seen.fill_(True)
    mean = model.default_latent()
    z = torch.randn(model.train_latents.shape[1], generator=g)
    means, f_s, center = model.means, model.intrinsic_features, torch.tensor([0.0, 0.0, 3.0])
    model.eval()
    with torch.no_grad():
        got = model.appearance_colors(z, means, f_s, center).prepared
        # the tri-plane field's feature (on in this model) still follows the chosen latent
        f_d = model.color_path.dynamic_features(model.appearance_nets, z, means, model.color_context(), False)
        mod.set_render_anchor(None)
        want = mod.local_residual(mean, f_s, f_d, model.num_points)
        own = mod.local_residual(z, f_s, f_d, model.num_points)
    torch.testing.assert_close(got, want)
    assert not torch.allclose(got, own)
    model.render_latent = z
    cam = _camera(48, 32)
    with torch.no_grad():
        model.config.render_sh_degree = -1
        exact = model.get_outputs(cam)["rgb"]
        model.config.render_sh_degree = 3
        model.get_outputs(cam)  # first frame of this appearance: exact path
        baked = model.get_outputs(cam)["rgb"]  # second: the bake
    torch.testing.assert_close(baked, exact, atol=2e-5, rtol=1e-4)
    mod.residual_latent = "own"  # read at the own latent again (long_run's --residual-latent sets it): no anchor left
    with torch.no_grad():
        torch.testing.assert_close(model.appearance_colors(z, means, f_s, center).prepared, own)
    mod.residual_latent = "mean"
    model.train()
    with torch.no_grad():
        trained = model.appearance_colors(z, means, f_s, center).prepared
    torch.testing.assert_close(trained, own)


def test_modulated_starts_as_plain_3dgs_and_the_latent_transforms_colour_globally():
    """At initialisation the colour transform is the identity (the model starts as 3DGS: colour = SH + 0.5); a
    trained global transform A(z) b(z) changes every Gaussian's colour the same way, and the local residual is
    the only per-Gaussian deviation (its penalty is zero at init)."""
    from willags_ns.appearance.modulation import local_penalty
    from willags_ns.render.sh import spherical_harmonics

    model = _mask_eval_tiny_model(use_vae=True, color_mode="modulated")
    means, f_s, sh = model.means, model.intrinsic_features, model.sh_coeffs()
    cam_center = torch.tensor([0.0, 0.0, 2.5])
    with torch.no_grad():
        for z in (torch.zeros(8), torch.randn(8) * 3):
            rgb = model.appearance_colors(z, means, f_s, cam_center).rgb
            ref = (spherical_harmonics(0, means - cam_center, sh) + 0.5).clamp_min(0)
            torch.testing.assert_close(rgb, ref)
        mod = model.appearance_nets.modulation
        f_d = model.color_path.dynamic_features(model.appearance_nets, z, means, model.color_context(), False)
        assert local_penalty(mod.local_residual(z, f_s, f_d, means.shape[0])) == 0
        mod.global_mlp[-1].bias.copy_(torch.tensor([1.0, 0, 0, 0, 1.0, 0, 0, 0, 1.0, 0.1, 0.0, -0.1]))  # 2x + b
        rgb = model.appearance_colors(z, means, f_s, cam_center).rgb
        torch.testing.assert_close(rgb, (2 * ref + torch.tensor([0.1, 0.0, -0.1])).clamp_min(0))


def test_render_latent_is_reused_across_frames_and_follows_every_change(monkeypatch):
    """A fixed appearance renders frame after frame without recomputing (or re-checking) its latent, so the baked
    SH's cache key costs no copy to the host; an in-place edit, a new tensor or a training update of the
    latents is seen at the next frame, and a NaN written into the chosen latent is still refused."""
    from willags_ns.appearance_spec import AppearanceSpecError

    model = _tiny_model("modulated")
    model.eval()
    cam = _camera(48, 32)
    d = model.train_latents.shape[1]
    with torch.no_grad():
        model.train_latents.normal_()  # the VAE path's recorded latents: their mean is the default appearance
        model.train_latent_seen.fill_(True)
        z0 = model.default_latent()
        assert model.default_latent() is z0  # memoised: same tensor, nothing recomputed
        torch.testing.assert_close(z0, model.train_latents.mean(0))
        model.train_latents[0] += 1.0  # a training visit records a new latent in place
        z1 = model.default_latent()
        assert z1 is not z0
        torch.testing.assert_close(z1, model.train_latents.mean(0))

        model.render_latent = torch.randn(d, generator=torch.Generator().manual_seed(2))
        chosen = model.current_latent()
        assert model.current_latent() is chosen
        key = model.latents.key_of(chosen)
        assert key[0] == "render"  # from the memo: no device -> host copy
        frames = [model.get_outputs(cam)["rgb"] for _ in range(3)]  # exact, bake, cached bake
        torch.testing.assert_close(frames[1], frames[2])
        seen = []
        orig_cpu = torch.Tensor.cpu
        monkeypatch.setattr(torch.Tensor, "cpu", lambda t, *a, **k: seen.append(t.shape) or orig_cpu(t, *a, **k))
        model.get_outputs(cam)
        assert (d,) not in seen, "a cached frame copied its latent to the host"
        monkeypatch.undo()

        model.render_latent.mul_(-1.0)  # edited in place: a different appearance from the next frame on
        flipped = model.get_outputs(cam)["rgb"]
        assert not torch.allclose(flipped, frames[2], atol=1e-4)
        model.render_latent[0] = float("nan")
        with pytest.raises(AppearanceSpecError, match="NaN"):
            model.get_outputs(cam)
        model.render_latent = None
        torch.testing.assert_close(model.current_latent(), z1)
    # a value the memo never handed out is keyed by its bytes
    assert model.latents.key_of(torch.zeros(d))[0] == "value"


def test_embedding_row_lookup_matches_the_table_and_names_a_bad_index():
    """The per-image latent is the table's row (and its gradient reaches only that row); an index outside the table
    is refused with the index and the table size, not read from the end as a negative Python index would be."""
    from willags_ns.appearance.networks import AppearanceNetworks
    from willags_ns.config import WillagsModelConfig

    nets = AppearanceNetworks(WillagsModelConfig(use_field=False), num_train=5)  # the embedding table
    mu, logvar = nets.latent_stats(None, 3)
    assert logvar is None
    torch.testing.assert_close(mu, nets.embeddings(torch.tensor([3]))[0])
    mu.sum().backward()
    grad = nets.embeddings.weight.grad
    assert grad[3].abs().sum() > 0 and grad[[0, 1, 2, 4]].abs().sum() == 0
    for bad in (5, -1):
        with pytest.raises(IndexError, match=rf"index {bad} outside the appearance table's 5 rows"):
            nets.latent_stats(None, bad)


def test_viewmat_is_the_inverse_of_the_opencv_camera_pose():
    """viewmat_from_c2w: nerfstudio's OpenGL camera-to-world (y up, -z forward) -> world-to-camera in OpenCV axes,
    i.e. the inverse of c2w with its y and z axes flipped (splatfacto's get_viewmat), for a batch of poses."""
    from willags_ns.render.camera import viewmat_from_c2w

    g = torch.Generator().manual_seed(9)
    q, _ = torch.linalg.qr(torch.randn(3, 3, 3, generator=g))
    c2w = torch.cat((q, torch.randn(3, 3, 1, generator=g)), dim=-1)  # [3, 3, 4]
    vm = viewmat_from_c2w(c2w)
    pose = torch.eye(4).repeat(3, 1, 1)
    pose[:, :3, :4] = c2w
    pose[:, :3, 1:3] *= -1.0  # OpenGL -> OpenCV camera axes
    torch.testing.assert_close(vm, torch.linalg.inv(pose), atol=1e-5, rtol=1e-5)


def test_training_metrics_match_splatfactos_and_the_photo_is_converted_once_per_step(monkeypatch):
    model = _tiny_model()
    model.train()
    cam = _camera(48, 32)
    image = (torch.rand(32, 48, 3, generator=torch.Generator().manual_seed(2)) * 255).to(torch.uint8)
    batch = {"image": image, "image_idx": 0}
    calls = []
    orig = type(model).get_gt_img
    monkeypatch.setattr(type(model), "get_gt_img", lambda self, img: calls.append(1) or orig(self, img))
    model.set_train_batch(batch)
    out = model.get_outputs(cam)
    metrics = model.get_metrics_dict(out, batch)
    losses = model.get_loss_dict(out, batch, metrics)
    assert len(calls) == 1 and torch.isfinite(losses["main_loss"])
    gt = model.composite_with_background(orig(model, image), out["background"])
    torch.testing.assert_close(metrics["psnr"], model.psnr(out["rgb"].detach(), gt), rtol=1e-5, atol=1e-5)
    assert metrics["gaussian_count"] == model.num_points
    model.end_step(0)
    # the next step converts afresh, also for the same photo object (the resolution schedule may have moved on)
    for n_calls, photo in ((2, image), (3, torch.zeros_like(image))):
        batch2 = {"image": photo, "image_idx": 1}
        model.set_train_batch(batch2)
        out2 = model.get_outputs(cam)
        model.get_metrics_dict(out2, batch2)
        assert len(calls) == n_calls
        want = model.composite_with_background(orig(model, photo), out2["background"])
        torch.testing.assert_close(model._gt_image(out2, batch2), want)
        model.end_step(0)
    model.eval()  # outside training nothing is kept
    with torch.no_grad():
        out3 = model.get_outputs(cam)
    model._gt_image(out3, batch2)
    assert "gt_rgb" not in out3


def test_modulated_with_gamma_bakes_by_least_squares_close_to_the_exact_render():
    """The gamma makes the colour non-affine in the SH: a fixed appearance then bakes like the decoder (a
    least-squares fit over directions), close to the exact render, and exports finite SH."""
    from willags_ns.appearance.modulation import ColorModulationConfig

    model = _tiny_model("modulated", modulation=ColorModulationConfig(gamma=True))
    mod = model.appearance_nets.modulation
    assert mod.gamma
    g = torch.Generator().manual_seed(7)
    with torch.no_grad():
        mod.global_mlp[-1].bias[12:].copy_(torch.tensor([0.5, -0.4, 0.2]))  # a gamma far from 1
    model.eval()
    model.render_latent = torch.randn(model.train_latents.shape[1], generator=g)
    assert not torch.allclose(mod.gamma_of(model.render_latent), torch.ones(3), atol=0.1)
    cam = _camera(48, 32)
    with torch.no_grad():
        model.config.render_sh_degree = -1
        exact = model.get_outputs(cam)["rgb"]
        model.config.render_sh_degree = 3
        model.get_outputs(cam)
        baked = model.get_outputs(cam)["rgb"]  # the second frame of this appearance renders the bake
    psnr = -10 * torch.log10(((baked - exact) ** 2).mean())
    assert psnr > 40, f"baked SH render differs from the exact one: {psnr:.1f} dB"
    assert not torch.equal(baked, exact)  # it is the fit, not the exact path
    sh = model.export_sh()
    assert sh.shape == (model.num_points, 16, 3) and torch.isfinite(sh).all()


def test_a_training_forward_takes_its_cameras_size_from_the_training_sizes_and_nothing_else_does():
    """While training, the camera's size comes from the training images' sizes by its cam_idx (no read of the
    camera's width: a wait for the GPU there); at downscale 2 an odd size floors (49 x 33 -> 24 x 16) as nerfstudio's
    rescale does. Outside training (a viewer or evaluation camera, whose cam_idx is no training index) and for a
    camera whose cam_idx the sizes do not cover, the camera's own size is read."""
    from tests.render.test_camera import unreadable_size

    model = _tiny_model()
    model.config.num_downscales, model.config.resolution_schedule = 1, 10**9  # downscale 2 at every step
    model.set_train_image_sizes([(49, 33), (40, 30)])
    model.train()
    cam = unreadable_size(_camera(49, 33))
    cam.metadata = {"cam_idx": 0}
    image = (torch.rand(33, 49, 3, generator=torch.Generator().manual_seed(2)) * 255).to(torch.uint8)
    batch = {"image": image, "image_idx": 0}
    model.set_train_batch(batch)
    out = model.get_outputs(cam)
    assert out["rgb"].shape == (16, 24, 3) and model.last_size == (16, 24)
    assert torch.isfinite(model.get_loss_dict(out, batch, {})["main_loss"])  # the photo downscales to the same size
    model.end_step(0)
    # a cam_idx the sizes do not cover, or none: the camera's size is read
    for metadata in ({"cam_idx": 2}, {}):
        model.set_train_batch({"image": image[:30, :40], "image_idx": 1})
        unread, other = unreadable_size(_camera(40, 30)), _camera(40, 30)
        unread.metadata, other.metadata = dict(metadata), dict(metadata)
        with pytest.raises(AssertionError, match="size was read"):
            model.get_outputs(unread)
        assert model.get_outputs(other)["rgb"].shape == (15, 20, 3)
        model.end_step(0)
    # outside training the sizes are not used: an evaluation camera with cam_idx 0 renders at its own size
    model.eval()
    viewer = _camera(24, 16)
    viewer.metadata = {"cam_idx": 0}
    with torch.no_grad():
        assert model.get_outputs(viewer)["rgb"].shape == (16, 24, 3)
