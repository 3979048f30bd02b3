"""Weight-free transient mask: the colour residual between the photo and the EMA teacher's render, RobustFilter style.

The reference is the same as the perceptual mask's: the EMA teacher's render of the view under that image's
latent, i.e. after the appearance transform (willags_ns/mask/step.py). Instead of VGG16 features the comparison is
the per-pixel colour residual, as in RobustNeRF's robust filter (Sabour et al. 2023), so no downloaded weights
are needed and nothing random decides what is static:

    r[y, x]  = mean_c |photo - teacher render|                                   (colour_residual)
    bar      = max(floor(step), median(r) + k * 1.4826 * MAD(r))   per image    (residual_threshold)
    outlier  = r > bar
    pixel    = box_k(outlier) >= 1/2      majority over a small window: isolated pixels and thin edges drop out
    patch    = mean of outlier over P x P patches >= patch_fraction, grown by one patch: a blob, not texture
    transient = pixel & patch             (rejected, i.e. none, when more than max_masked_fraction)

A transient the 3D model cannot explain leaves a large, spatially coherent residual; a static pixel's residual is
photometric noise, or a thin misalignment at an edge, which the two majority filters remove. ``floor(step)`` is
:func:`willags_ns.mask.rule.mask_threshold` of ``floor``: inf before the warm-up (nothing masked), then the
optional ramp. Measured numbers: docs/design.md, "A weight-free transient mask".
"""

from dataclasses import dataclass

import torch.nn.functional as F
from jaxtyping import Bool, Float
from torch import Tensor

MAD_SCALE = 1.4826
"""MAD of a normal distribution times this is its standard deviation."""


@dataclass
class ResidualConfig:
    """The colour-residual comparison (mask.distance "residual"): its threshold and its spatial coherence."""

    floor: float = 0.1
    """Absolute floor of the residual bar (mean absolute colour difference, colours in [0, 1]): a pixel closer to
    the teacher's render than this is static whatever the image's statistics say."""
    k: float = 3.0
    """The bar is median(r) + k robust standard deviations (1.4826 MAD) of the image's residuals: a transient must
    stand out from the image's own photometric noise, which the median and MAD describe (transients cover a
    minority of the image)."""
    pixel_window: int = 3
    """Side of the pixel-scale majority window (odd): an outlier pixel stays only when at least half of this
    window is outlier too, so isolated pixels and one-pixel edges are not masked."""
    patch_size: int = 8
    """Side of the patch-scale test in pixels at the training resolution: a pixel is masked only within one patch
    of a patch whose outlier share reaches patch_fraction (a blob, not scattered texture)."""
    patch_fraction: float = 0.5
    """Share of outlier pixels that makes a patch a transient patch."""
    expected: bool = False
    """Threshold the residual beyond the scene's expected residual at each pixel (willags_ns/mask/expected.py: a
    level per Gaussian, the median of the residuals it is rendered over in the photos that see it) instead of the
    residual itself, so that static scene the model fits badly in every photo is not taken for a transient."""


def colour_residual(photo: Float[Tensor, "H W 3"], render: Float[Tensor, "H W 3"]) -> Float[Tensor, "H W"]:
    """r = mean over the colour channels of |photo - render|, both in [0, 1]."""
    if photo.shape != render.shape or photo.shape[-1] != 3:
        raise ValueError(
            f"expected photo and render [H, W, 3] of one shape, got {tuple(photo.shape)}, {tuple(render.shape)}"
        )
    return (photo - render.to(photo.dtype)).abs().mean(dim=-1)


def residual_threshold(r: Float[Tensor, "H W"], floor: float, k: float) -> Tensor:
    """0-d bar ``max(floor, median(r) + k * 1.4826 * MAD(r))``; ``floor = inf`` (warming up) stays inf.

    Example: residuals of a well-fitted image ~ 0.02 +- 0.01 -> bar max(0.1, 0.02 + 3 * 0.015) = 0.1; an image
    whose appearance the teacher only half explains ~ 0.15 +- 0.05 -> bar 0.15 + 3 * 0.074 = 0.37."""
    flat = r.flatten()
    med = flat.median()
    mad = (flat - med).abs().median()
    return (med + k * MAD_SCALE * mad).clamp_min(floor)


def majority(mask: Bool[Tensor, "H W"], window: int) -> Bool[Tensor, "H W"]:
    """True where at least half of the ``window`` x ``window`` box around the pixel is True (zero padding: the
    image border counts as False). ``window <= 1`` returns the mask."""
    if window <= 1:
        return mask
    x = mask[None, None].float()
    share = F.avg_pool2d(x, window, stride=1, padding=window // 2, count_include_pad=True)
    return share[0, 0, : mask.shape[0], : mask.shape[1]] >= 0.5


def blob_patches(mask: Bool[Tensor, "H W"], patch: int, fraction: float) -> Bool[Tensor, "H W"]:
    """True within one patch of a ``patch`` x ``patch`` patch whose True share reaches ``fraction`` (patches of the
    image's grid; the last row and column of patches may be partial and count their real pixels)."""
    H, W = mask.shape
    if patch <= 1:
        return mask
    x = mask[None, None].float()
    share = F.avg_pool2d(x, patch, stride=patch, ceil_mode=True, padding=0)  # partial patches: mean of real pixels
    hit = (share >= fraction).float()
    grown = F.max_pool2d(hit, 3, stride=1, padding=1)
    up = grown.repeat_interleave(patch, dim=2).repeat_interleave(patch, dim=3)
    return up[0, 0, :H, :W] > 0.5


def residual_transient(
    r: Float[Tensor, "H W"],
    floor: float,
    cfg: ResidualConfig,
    max_masked_fraction: float = 1.0,
    excess: Float[Tensor, "H W"] | None = None,
) -> tuple[Bool[Tensor, "H W"], Bool[Tensor, ""]]:
    """``(transient [H, W], rejected)`` of one image's residual ``r`` (see the module docstring). ``floor``: the
    bar's floor at this step (inf before the warm-up: nothing is transient). More than ``max_masked_fraction``
    transient: rejected (all False), as the perceptual mask. ``rejected`` is a 0-d bool tensor on r's device.
    ``excess``: the residual beyond the scene's expected residual (willags_ns/mask/expected.py), held to the bar of
    ``r`` in place of ``r``: a subset of the plain rule's outliers, those the scene does not usually show there."""
    bar = residual_threshold(r, floor, cfg.k)
    outlier = (r if excess is None else excess) > bar
    transient = majority(outlier, cfg.pixel_window) & blob_patches(outlier, cfg.patch_size, cfg.patch_fraction)
    rejected = transient.float().mean() > max_masked_fraction
    return transient & ~rejected, rejected


def outlier_share(photo: Float[Tensor, "H W 3"], render: Float[Tensor, "H W 3"], cfg: ResidualConfig) -> Tensor:
    """The share (0-d tensor) of a photo's pixels that the rule (`residual_transient` at `cfg.floor`) marks transient
    against `render`: the blobs a model leaves unfit in a photo, a measure of how crowded the photo is to that
    model (eval/protocol.train_view_scores; the "transients" cap rule, splats/mcmc.py)."""
    return residual_transient(colour_residual(photo, render), cfg.floor, cfg)[0].float().mean()
