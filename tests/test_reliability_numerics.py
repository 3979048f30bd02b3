"""Numerical stability at the extremes (docs/reliability.md rows 6-13, 18): one tiny WillagsModel (tests/test_model's,
mask active from step 0, a teacher that differs from the student) driven through full training steps (encode,
render, fused teacher render, VGG mask, losses, backward) on extreme inputs. Every loss term, metric and gradient
must be finite."""

import math
import re
import warnings

import pytest
import torch

from tests.test_mask_eval import _camera
from tests.test_model import _tiny_model
from willags_ns.engine.checks import (
    WillagsInputError,
    WillagsTrainingError,
    check_gaussians_alive,
    check_scene_scale,
    check_train_memory,
    estimate_train_step_bytes,
)
from willags_ns.mask.rule import transient_mask
from willags_ns.objective.losses import masked_dssim, masked_l1, reconstruction_loss

H, W = 24, 32


@pytest.fixture(scope="module")
def model():
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        m = _tiny_model()
    m.train()
    return m


def train_step(model, image_u8: torch.Tensor, cam=None, idx: int = 0):
    """One training step's forward + backward; returns (loss_dict, metrics) as floats, asserting finiteness of every
    loss, metric, output and gradient."""
    cam = cam if cam is not None else _camera(image_u8.shape[1], image_u8.shape[0])
    batch = {"image": image_u8, "image_idx": idx}
    model.zero_grad(set_to_none=True)
    model.set_train_batch(batch)
    out = model.get_outputs(cam)
    metrics = model.get_metrics_dict(out, batch)
    losses = model.get_loss_dict(out, batch, metrics)
    total = sum(losses.values())
    total.backward()
    assert torch.isfinite(out["rgb"]).all()
    for k, v in {**losses, **metrics}.items():
        if torch.is_tensor(v):
            assert torch.isfinite(v).all(), f"{k} = {v}"
    for name, p in model.named_parameters():
        if p.grad is not None:
            assert torch.isfinite(p.grad).all(), f"gradient of {name}"
    model.end_step(0)
    return {k: float(v) for k, v in losses.items()}, {k: float(v) for k, v in metrics.items() if torch.is_tensor(v)}


def _image(fill=None, seed=0, h=H, w=W):
    if fill is not None:
        return torch.full((h, w, 3), fill, dtype=torch.uint8)
    return (torch.rand(h, w, 3, generator=torch.Generator().manual_seed(seed)) * 255).to(torch.uint8)


# ---- row 6: all-black and all-white images


@pytest.mark.parametrize("fill", [0, 255])
def test_row6_black_and_white_images_train_finite_with_kl_mask_and_ssim(model, fill):
    losses, metrics = train_step(model, _image(fill))
    assert {"main_loss", "vae_loss"} <= set(losses)
    assert "vae_kl" in metrics and "masked_fraction" in metrics  # the KL and the mask really ran
    # SSIM of constant images (zero variance: the 0/0 SSIM is guarded by its C1, C2 constants)
    flat = torch.full((1, 3, H, W), fill / 255.0, requires_grad=True)
    d = masked_dssim(flat, flat.detach())
    assert torch.isfinite(d) and abs(float(d)) < 1e-4
    (g,) = torch.autograd.grad(d, flat)
    assert torch.isfinite(g).all()


# ---- row 7: extreme exposures


@pytest.mark.parametrize("gain", [0.05, 20.0])
def test_row7_extreme_exposures_train_finite_and_the_latent_stays_bounded(model, gain):
    base = _image(seed=1).float()
    img = (base * gain).clamp(0, 255).to(torch.uint8)  # x20 clips most of the image to white
    norms = []
    opt = torch.optim.Adam(model.appearance_nets.parameters(), lr=1e-2)  # an aggressive optimiser on the encoder
    for _ in range(15):
        _, metrics = train_step(model, img)
        opt.step()
        norms.append(metrics["latent_norm"])
    # a sampled latent is mu + sigma * eps with |logvar| <= 10: bounded by |mu| + 148 |eps|; in practice it
    # stays at the prior's scale (sqrt(D) ~ 2.8 for D = 8)
    assert all(math.isfinite(n) for n in norms) and max(norms) < 50, norms
    mu = model.encode_image(img)
    assert torch.isfinite(mu).all() and mu.norm() < 50


# ---- row 8: a rendering latent of norm 1e3 (the latent-file / spec clamping belongs to the viewer's parser)


@pytest.mark.parametrize("norm", [1e3, 1e6])
def test_row8_huge_render_latent_gives_finite_pixels(model, norm):
    model.eval()
    try:
        z = torch.randn(model.train_latents.shape[1], generator=torch.Generator().manual_seed(0))
        model.render_latent = z / z.norm() * norm
        with torch.no_grad():
            out = model.get_outputs(_camera(W, H))
        assert torch.isfinite(out["rgb"]).all() and out["rgb"].min() >= 0 and out["rgb"].max() <= 1
    finally:
        model.render_latent = None
        model.train()


# ---- row 9: scene scale 1e-3 and 1e4


@pytest.mark.parametrize("scale", [1e-3, 1e4])
def test_row9_scaled_scene_trains_finite_after_autoscale_or_stops_with_a_clear_error(scale):
    """Model level, poses and points scaled by `scale` with no dataparser auto-scaling (the dataparser level,
    where nerfstudio's auto_scale_poses undoes the scale, is in test_reliability.py)."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        m = _tiny_model()
    m.train()
    with torch.no_grad():
        m.gauss_params["means"].mul_(scale)
        m.gauss_params["scales"].add_(math.log(scale))
        m.bounds_lo.mul_(scale)  # what robust_bounds gives on the scaled seed points
        m.bounds_hi.mul_(scale)
    cam = _camera(W, H)
    cam.camera_to_worlds[..., 3] *= scale
    centres = cam.camera_to_worlds[:, :3, 3]
    if scale < 1:
        # the camera sits 2.5e-3 units from the scene: inside the rasteriser's near plane (0.01) -> a clear error
        with pytest.raises(WillagsInputError, match="auto_scale_poses"):
            check_scene_scale(centres, m.means.detach())
        return
    check_scene_scale(centres, m.means.detach())
    losses, _ = train_step(m, _image(seed=2), cam)
    # the scene is seen (not culled, not collapsed to a point): the render is not the flat background
    m.eval()
    with torch.no_grad():
        rgb = m.get_outputs(cam)["rgb"]
    assert torch.isfinite(rgb).all() and rgb.std() > 0.01


# ---- row 10: Gaussians drifting outside the tri-plane bounds


def test_row10_gaussians_far_outside_the_bounds_are_clamped_and_finite(model):
    from willags_ns.appearance.triplane import normalize_points

    with torch.no_grad():
        saved = model.gauss_params["means"].detach().clone()
        model.gauss_params["means"][:50] *= 1e6  # 50 Gaussians flung far away
    try:
        x = normalize_points(model.means.detach(), model.bounds_lo, model.bounds_hi)
        assert x.min() >= -1 and x.max() <= 1
        train_step(model, _image(seed=3))
    finally:
        with torch.no_grad():
            model.gauss_params["means"].copy_(saved)


# ---- row 11: every pixel flagged transient


def test_row11_every_pixel_transient_is_capped_and_the_loss_stays_finite():
    D = torch.full((H, W), 10.0)  # the teacher disagrees everywhere
    transient, rejected = transient_mask(D, 0.85, "fixed", max_masked_fraction=0.5)
    assert rejected and not transient.any()  # capped: the image is supervised everywhere instead
    some = D.clone()
    some[:, : W // 4] = 0.0
    transient, rejected = transient_mask(some, 0.85, "fixed", max_masked_fraction=0.8)
    assert not rejected and transient.float().mean() == pytest.approx(0.75)
    # and if a caller does pass an all-transient mask: 0, not 0/0, with zero (finite) gradients
    pred = torch.rand(1, 3, H, W, requires_grad=True)
    gt = torch.rand(1, 3, H, W)
    none_kept = torch.zeros(1, H, W)
    for fn in (masked_l1, masked_dssim, reconstruction_loss):
        v = fn(pred, gt, none_kept)
        (g,) = torch.autograd.grad(v, pred)
        assert float(v) == 0.0 and torch.isfinite(g).all() and not g.any()


def test_row11_a_rejected_mask_is_reported_in_training(model):
    mask_cfg = model.config.mask
    old = (mask_cfg.threshold, mask_cfg.threshold_rule)
    mask_cfg.threshold, mask_cfg.threshold_rule = 0.0, "fixed"  # D >= 0 everywhere: every pixel flagged
    try:
        model.last_masks.clear()
        model.mask_step.visits.clear()
        losses, metrics = train_step(model, _image(seed=4))
        assert metrics.get("mask_rejected") == 1.0 and metrics["masked_fraction"] == 0.0
        assert losses["main_loss"] > 0  # supervised everywhere, not a 0/0
    finally:
        mask_cfg.threshold, mask_cfg.threshold_rule = old
        model.last_masks.clear()


def test_row11_pipeline_warns_when_the_mask_is_rejected():
    from types import SimpleNamespace

    from nerfstudio.utils.rich_utils import CONSOLE

    from willags_ns.engine.pipeline import WillagsPipeline
    from willags_ns.mask.health import MaskHealth, MaskHealthConfig

    fake = SimpleNamespace(
        datamanager=SimpleNamespace(train_dataparser_outputs=SimpleNamespace(image_filenames=["a/x.png", "a/y.png"])),
        model=SimpleNamespace(
            config=SimpleNamespace(mask=SimpleNamespace(max_masked_fraction=0.5)),
            mask_health=MaskHealth(MaskHealthConfig()),
        ),
    )
    with CONSOLE.capture() as cap:
        WillagsPipeline._warn_mask_rejected(fake, 7, {"image_idx": torch.tensor(1)})  # type: ignore[arg-type]
        WillagsPipeline._warn_mask_rejected(fake, 8, {"image_idx": torch.tensor(1)})  # rate-limited: silent
    text = cap.get()
    assert text.count("transient mask flagged more than 0.5 of y.png") == 1, text


def test_row11_the_rejected_flag_is_read_one_step_late_and_only_when_set():
    from types import SimpleNamespace

    from nerfstudio.utils.rich_utils import CONSOLE

    from willags_ns.engine.pipeline import WillagsPipeline
    from willags_ns.mask.health import MaskHealth, MaskHealthConfig

    fake = SimpleNamespace(
        _pending_rejected=(3, {"image_idx": torch.tensor(0)}, torch.tensor(False)),
        datamanager=SimpleNamespace(train_dataparser_outputs=SimpleNamespace(image_filenames=["a/x.png", "a/y.png"])),
        model=SimpleNamespace(
            config=SimpleNamespace(mask=SimpleNamespace(max_masked_fraction=0.5)),
            mask_health=MaskHealth(MaskHealthConfig()),
        ),
    )
    fake._warn_mask_rejected = lambda step, batch: WillagsPipeline._warn_mask_rejected(fake, step, batch)
    with CONSOLE.capture() as cap:
        WillagsPipeline._report_rejected_mask(fake)  # type: ignore[arg-type]  # not rejected: silent
        assert fake._pending_rejected is None
        fake._pending_rejected = (9, {"image_idx": torch.tensor(1)}, torch.tensor(True))
        WillagsPipeline._report_rejected_mask(fake)  # type: ignore[arg-type]
        WillagsPipeline._report_rejected_mask(fake)  # type: ignore[arg-type]  # consumed: nothing twice
    text = cap.get()
    assert "x.png" not in text and text.count("step 9: the transient mask flagged more than 0.5 of y.png") == 1


# ---- row 12: all Gaussians pruned


def test_row12_all_gaussians_pruned_is_a_clear_error_and_renders_stay_finite():
    with pytest.raises(WillagsTrainingError, match="every Gaussian was pruned by step 123.*cull-alpha-thresh"):
        check_gaussians_alive(0, 123)
    check_gaussians_alive(1, 123)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        m = _tiny_model()
    for k in list(m.gauss_params.keys()):
        m.gauss_params[k] = torch.nn.Parameter(m.gauss_params[k].detach()[:0])
    m.eval()
    with torch.no_grad():
        out = m.get_outputs(_camera(W, H))  # the viewer / eval still render the background
    assert torch.isfinite(out["rgb"]).all() and out["accumulation"].abs().max() == 0


# ---- row 13: 8x8 images; a 4k image on the CPU


def test_row13_8x8_image_trains_finite(model):
    losses, _ = train_step(model, _image(seed=5, h=8, w=8))
    assert losses["main_loss"] > 0


def test_row13_a_4k_image_on_the_cpu_is_a_clear_memory_error_when_it_does_not_fit():
    need = estimate_train_step_bytes(100_000, 3840, 2160)
    assert 20 * 2**30 < need < 40 * 2**30  # ~24 GB by the measured 2.9 kB / pixel
    with pytest.raises(WillagsInputError, match=r"3840x2160 image needs about .* GiB.*downscale-factor"):
        check_train_memory(100_000, 3840, 2160, available=16 * 2**30)
    check_train_memory(100_000, 3840, 2160, available=64 * 2**30)  # fits: no error
    check_train_memory(100_000, 960, 540, available=16 * 2**30)


# ---- row 18: bf16 autocast on the MLPs


@pytest.mark.parametrize("scale", [0.0, 1.0, 1e3, -1e3])
def test_row18_bf16_autocast_keeps_the_appearance_mlps_finite_at_the_extremes(model, scale):
    n = model.num_points
    means = model.means.detach().clone()
    means[0] = torch.tensor([1e6, -1e6, 1e6])  # far outside the bounds
    means[1] = torch.tensor([0.0, 0.0, 2.5])  # at the camera centre (zero view direction)
    means.requires_grad_(True)
    f_s = model.intrinsic_features.detach().clone().requires_grad_(True)
    z = torch.full((model.train_latents.shape[1],), scale, requires_grad=True)
    with torch.autocast("cpu", dtype=torch.bfloat16):
        rgb = model.appearance_colors(z, means, f_s, torch.tensor([0.0, 0.0, 2.5])).rgb
        images = torch.stack([torch.zeros(3, H, W), torch.ones(3, H, W), torch.rand(3, H, W) * 20])
        mu, logvar = model.appearance_nets.vae.encode(images.clamp(0, 1))
    assert rgb.shape == (n, 3) and torch.isfinite(rgb).all()
    assert torch.isfinite(mu).all() and torch.isfinite(logvar).all()
    grads = torch.autograd.grad(rgb.float().sum() + mu.float().sum(), [z, means, f_s], allow_unused=True)
    assert all(g is None or torch.isfinite(g).all() for g in grads)


@pytest.mark.parametrize("hw", [(1, 1), (2, 2), (2, 7), (5, 5), (6, 6), (8, 8)])
def test_row13_ssim_works_down_to_1x1_images(hw):
    from willags_ns.objective.losses import ssim_window

    h, w = hw
    k, _ = ssim_window(h, w)
    assert k % 2 == 1 and (k - 1) // 2 < min(h, w) and (k == 11) == (min(h, w) >= 6)
    pred = torch.rand(1, 3, h, w, requires_grad=True)
    v = masked_dssim(pred, torch.rand(1, 3, h, w))
    (g,) = torch.autograd.grad(v, pred)
    assert torch.isfinite(v) and torch.isfinite(g).all()
    same = masked_dssim(pred.detach(), pred.detach())
    assert abs(float(same)) < 1e-4  # identical images: no dissimilarity


def test_row13_vgg_mask_features_of_a_2x2_image():
    from willags_ns.mask.transient import PerceptualFeatures, perceptual_error

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        feats = PerceptualFeatures(weights="seeded")
        a, b = torch.rand(1, 3, 2, 2), torch.rand(1, 3, 2, 2)
        d = perceptual_error(feats(a), feats(b), (2, 2))
    assert d.shape == (1, 2, 2) and torch.isfinite(d).all() and d.min() >= 0


def test_row8_latent_clamping_of_the_appearance_spec_parser():
    """Chosen latents pass through the SPEC parser's check: huge ones are scaled down with a warning, NaN is named."""
    from willags_ns import appearance_spec as spec

    z = torch.ones(8) * 1e3 / math.sqrt(8)  # norm 1e3
    with pytest.warns(UserWarning, match="scaled down"):
        out = spec.checked_latent(z, "latent file z.pt")
    assert torch.isfinite(out).all() and float(out.norm()) <= spec.MAX_LATENT_NORM + 1e-3
    with pytest.raises(ValueError, match="z.pt.*NaN"):
        spec.checked_latent(torch.tensor([0.0, float("nan")]), "latent file z.pt")


def test_row13_the_memory_error_names_the_photo_and_its_command_parses():
    """The command in the message parses as ns-train and reads the images at the suggested factor."""
    import shlex

    import tyro
    from nerfstudio.configs.method_configs import AnnotatedBaseConfigUnion

    argv = ["/venv/bin/ns-train", "willags", "--data", "scenes/church", "--max-num-iterations", "100"]
    with pytest.raises(WillagsInputError) as info:
        check_train_memory(100_000, 8000, 6000, available=16 * 2**30, names=["IMG_9.jpg"], argv=argv)
    text = str(info.value)
    assert "IMG_9.jpg" in text and "\n" not in text
    command = re.search(r"(ns-train .*?); or ", text).group(1)
    words = shlex.split(command)
    config = tyro.cli(AnnotatedBaseConfigUnion, args=words[1:])
    factor = config.pipeline.datamanager.dataparser.downscale_factor
    assert config.max_num_iterations == 100 and factor >= 2
    assert estimate_train_step_bytes(100_000, 8000 // factor, 6000 // factor) <= 16 * 2**30
    # a line that already names the dataparser: the factor replaced there, still one that parses
    again = argv + ["willags-data", "--downscale-factor", "2"]
    with pytest.raises(WillagsInputError) as info:
        check_train_memory(100_000, 8000, 6000, available=16 * 2**30, argv=again)
    words = shlex.split(re.search(r"(ns-train .*?); or ", str(info.value)).group(1))
    assert tyro.cli(AnnotatedBaseConfigUnion, args=words[1:]).pipeline.datamanager.dataparser.downscale_factor == factor
