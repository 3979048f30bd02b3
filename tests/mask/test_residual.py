"""The weight-free transient mask (willags_ns/mask/residual.py) and its switch in MaskStep (mask.distance)."""

import math
import warnings

import pytest
import torch

from tests._configs import mask as mask_config
from willags_ns.mask.residual import (
    ResidualConfig,
    blob_patches,
    colour_residual,
    majority,
    outlier_share,
    residual_threshold,
    residual_transient,
)
from willags_ns.mask.rule import mask_threshold
from willags_ns.mask.step import MaskStep, compare_to_teacher

H, W = 96, 128
BLOB = (slice(30, 62), slice(40, 80))  # 32 x 40 px opaque occluder
EDGE_ROW = 80  # a one-pixel misaligned edge across the image


def _teacher_render(seed: int = 0) -> torch.Tensor:
    """A textured stand-in for the teacher's render [H, W, 3]: smooth colour gradients plus fine texture."""
    g = torch.Generator().manual_seed(seed)
    y = torch.linspace(0, 1, H)[:, None, None]
    x = torch.linspace(0, 1, W)[None, :, None]
    base = 0.3 + 0.3 * y * torch.tensor([1.0, 0.5, 0.2]) + 0.3 * x * torch.tensor([0.2, 0.6, 1.0])
    return (base + 0.05 * torch.rand(H, W, 3, generator=g)).clamp(0, 1)


def _photo(render: torch.Tensor, noise: float = 0.03, blob: bool = True, edge: bool = True, seed: int = 1):
    """The render + photometric noise (+ an opaque magenta blob, + a one-pixel bright edge the render misses)."""
    g = torch.Generator().manual_seed(seed)
    photo = render + noise * torch.randn(render.shape, generator=g)
    if blob:
        photo[BLOB] = torch.tensor([0.95, 0.1, 0.9])
    if edge:
        photo[EDGE_ROW, :] = 1.0
    return photo.clamp(0, 1)


def _blob_mask() -> torch.Tensor:
    m = torch.zeros(H, W, dtype=torch.bool)
    m[BLOB] = True
    return m


def test_blob_masked_noise_and_thin_edge_not():
    render = _teacher_render()
    photo = _photo(render)
    r = colour_residual(photo, render)
    transient, rejected = residual_transient(r, 0.1, ResidualConfig())
    assert not bool(rejected)
    blob = _blob_mask()
    assert transient[blob].float().mean() > 0.97  # the occluder is masked
    assert not transient[EDGE_ROW].any()  # the one-pixel edge is an outlier row, but not a blob
    static = ~blob
    static[EDGE_ROW] = False
    assert transient[static].float().mean() < 0.002  # photometric noise stays supervised
    # the bare bar alone would flag the edge: the coherence filters are what keep it
    assert (r > residual_threshold(r, 0.1, 3.0))[EDGE_ROW].float().mean() > 0.9


def test_outlier_share_is_the_blobs_share_of_the_photo():
    render = _teacher_render()
    share = float(outlier_share(_photo(render), render, ResidualConfig()))
    blob = _blob_mask().float().mean().item()
    assert blob * 0.97 <= share <= blob + 0.01  # the occluder, not the edge or the noise
    assert float(outlier_share(_photo(render, blob=False), render, ResidualConfig())) < 0.002


def test_strong_noise_raises_the_bar_not_the_masked_share():
    """Photometric noise well above the floor: the image's own median + k MAD bar keeps it supervised."""
    render = _teacher_render()
    photo = _photo(render, noise=0.15, blob=False, edge=False)
    r = colour_residual(photo, render)
    assert float((r > 0.1).float().mean()) > 0.3  # a fixed bar at the floor would drop a third of the image
    transient, _ = residual_transient(r, 0.1, ResidualConfig())
    assert float(transient.float().mean()) < 0.01


def test_cap_rejects_a_mask_over_max_masked_fraction():
    render = _teacher_render()
    photo = render.clone()
    photo[:, : int(0.3 * W)] = torch.tensor([0.95, 0.1, 0.9])  # an "occluder" over 30 % of the image
    r = colour_residual(photo, render)
    ok, rej_ok = residual_transient(r, 0.1, ResidualConfig(), max_masked_fraction=0.5)
    assert not bool(rej_ok) and float(ok.float().mean()) > 0.25
    capped, rejected = residual_transient(r, 0.1, ResidualConfig(), max_masked_fraction=0.2)
    assert bool(rejected) and not capped.any()  # over the cap: nothing masked, every pixel supervised


def test_isolated_pixels_fail_the_pixel_majority_and_scattered_ones_the_patch_test():
    m = torch.zeros(40, 40, dtype=torch.bool)
    m[5, 5] = m[20, 30] = True
    assert not majority(m, 3).any()
    solid = torch.zeros(40, 40, dtype=torch.bool)
    solid[8:24, 8:24] = True
    assert majority(solid, 3)[9:23, 9:23].all()
    checker = torch.zeros(40, 40, dtype=torch.bool)
    checker[::4, ::4] = True  # 1/16 of each patch: texture, not a blob
    assert not blob_patches(checker, 8, 0.5).any()
    assert blob_patches(solid, 8, 0.5)[8:24, 8:24].all()


def test_warmup_floor_is_inf_and_masks_nothing():
    render = _teacher_render()
    photo = _photo(render)
    floor = mask_threshold(10, 0.1, warmup_steps=500)
    assert math.isinf(floor)
    transient, rejected = residual_transient(colour_residual(photo, render), floor, ResidualConfig())
    assert not transient.any() and not bool(rejected)


class _Cfg:
    """What MaskStep reads of the model's config."""

    def __init__(self, distance: str, warmup: int = 100):
        self.appearance = "willags"
        self.mask = mask_config(distance=distance, warmup_steps=warmup, max_masked_fraction=0.5)


def test_mask_step_residual_mode_masks_the_blob_after_warmup_only():
    render = _teacher_render()
    photo = _photo(render)
    ms = MaskStep(_Cfg("residual", warmup=100), observations=None)
    before = ms.static_mask(99, 0, photo, render, None, "cpu")
    assert before.mask is None  # warming up: no mask, no teacher comparison
    assert not ms.teacher_needed(99, 0)
    after = ms.static_mask(100, 0, photo, render, None, "cpu")  # no VGG needed: perceptual None
    assert after.mask is not None and after.distance is not None and float(after.rejected) == 0.0
    static = after.mask.bool()
    assert static[_blob_mask()].float().mean() < 0.03  # the blob is dropped from the loss
    assert static[EDGE_ROW].all()
    torch.testing.assert_close(after.distance, colour_residual(photo, render))
    # a later step without a teacher render reuses the image's mask
    again = ms.static_mask(101, 0, photo, None, None, "cpu")
    assert torch.equal(again.mask, after.mask) and again.distance is None


def test_compare_to_teacher_vgg_mode_is_the_perceptual_rule():
    from willags_ns.mask.rule import transient_mask
    from willags_ns.mask.transient import PerceptualFeatures, image_distance

    render = _teacher_render()
    photo = _photo(render)
    cfg = mask_config(vgg_weights="seeded", warmup_steps=0)
    perceptual = PerceptualFeatures(weights="seeded", max_resolution=128)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the seeded fallback's one-time warning
        transient, rejected, d = compare_to_teacher(cfg, 5, photo, render, perceptual)
    ref_d = image_distance(perceptual, photo, render)
    ref, ref_rej = transient_mask(ref_d, cfg.threshold, cfg.threshold_rule, cfg.robust_k, cfg.max_masked_fraction)
    assert torch.equal(d, ref_d) and torch.equal(transient, ref) and bool(rejected) == bool(ref_rej)


def test_unknown_distance_is_refused_with_its_name():
    cfg = mask_config(distance="lpips", warmup_steps=0)
    render = _teacher_render()
    with pytest.raises(ValueError, match="mask.distance 'lpips'"):
        compare_to_teacher(cfg, 5, render, render, None)
