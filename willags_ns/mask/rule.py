"""The transient mask's rule: its settings, its thresholds and the one comparison of a photo with the teacher's render.

    D = VGG16 perceptual distance (mask/transient.py) or colour residual (mask/residual.py)   compare_to_teacher
    transient = D >= bar(step)   the bar: inf while warming up, then the threshold (ramped down from
                                 RAMP_START_FACTOR x), per image raised by the robust rule; the residual's own bar
    rejected when the mask would drop more than max_masked_fraction of the image (then nothing is transient)

Training (mask/step.MaskStep), the mask evaluation (eval/mask_eval.py) and the viewer's mask picture call
:func:`compare_to_teacher`, and nothing else decides what is transient. Pure functions and the config.
"""

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

from jaxtyping import Bool, Float
from torch import Tensor

from willags_ns.mask.expected import excess_residual
from willags_ns.mask.health import MaskHealthConfig
from willags_ns.mask.residual import ResidualConfig, colour_residual, residual_transient
from willags_ns.mask.static_support import StaticSupportConfig
from willags_ns.mask.teacher import TeacherConfig
from willags_ns.mask.transient import PerceptualFeatures, VggWeights, image_distance


@dataclass
class MaskConfig:
    """The transient mask: the EMA teacher's render compared with the photo in VGG16 features, thresholded, with its
    cadence, its safeguard and its health watch (the step: willags_ns/mask/step.py; the rule: this module)."""

    enabled: bool = True
    """Mask transients with the perceptual mask of the EMA teacher. Off: every pixel is supervised, and neither the
    teacher nor VGG16 is built."""
    distance: Literal["vgg", "residual"] = "vgg"
    """How the photo is compared with the EMA teacher's render (after the appearance transform of the image's
    latent). "vgg": the perceptual distance D of VGG16 features (the paper's; threshold, threshold_rule, robust_k,
    vgg_weights, max_resolution). "residual": the per-pixel colour residual with a per-image robust bar and
    spatial coherence, no network and no weights (mask.residual; willags_ns/mask/residual.py). Both share the
    teacher, warmup_steps, ramp_steps, max_masked_fraction, every, the safeguard and the health watch."""
    residual: ResidualConfig = field(default_factory=ResidualConfig)
    """The colour-residual comparison's bar and coherence filters (distance "residual")."""
    threshold: float = 0.85
    """Pixels with perceptual error D >= threshold are transient (excluded from the loss; distance "vgg")."""
    threshold_rule: Literal["fixed", "robust"] = "robust"
    """"fixed": the paper's rule, transient iff D >= threshold. "robust": per image, transient iff
    D >= max(threshold, median(D) + robust_k * 1.4826 * MAD(D)) (see :func:`robust_threshold`). Equal to "fixed"
    whenever the teacher explains the image (most pixels have a small D); it raises the bar only in images whose
    typical pixel already differs (a teacher that cannot yet render fine texture, the seeded VGG fallback's
    uncalibrated scale), which otherwise lose their textured static regions to the mask."""
    robust_k: float = 2.0
    """Robust rule: how many robust standard deviations (1.4826 MAD) above the median D a pixel must be."""
    vgg_weights: VggWeights = "auto"
    """Where the VGG16 weights come from: "auto" (vgg_weights_path if set, else the torch hub cache file, else
    the seeded fallback), "torchvision" (torchvision's loader; downloads when online), "path" (a state-dict file
    at vgg_weights_path), "seeded" (the calibrated random fallback, see willags_ns.mask.transient)."""
    vgg_weights_path: Path | None = None
    """A state-dict file in torchvision's vgg16 layout (keys features.N.weight / features.N.bias, or N.weight)."""
    warmup_steps: int = 5000
    """No masking before this step: until then the teacher render is not yet a meaningful reference and D would
    flag most of the image, and the latent has not yet learned a large appearance change, so what the mask would
    drop is scene the photos show in another light (docs/design.md, "The mask from step 5000"). The paper's preset
    starts it at step 500."""
    start_rule: Literal["always", "transients"] = "transients"
    """Whether the mask starts at warmup_steps. "always": it does. "transients" (:func:`mask_start`): at
    warmup_steps training measures the share of its own photos' pixels that their renders, each with its own latent,
    leave as residual blobs (eval/protocol.training_outlier_share, the measure of MCMC's "transients" cap rule), and
    the mask starts only at or above start_share; below it the mask stays off for the rest of the run. Why: where
    the renders leave few blobs the mask has few passers-by to drop, and what it dropped there was scene the test
    photos show (docs/design.md, "The mask from step 5000")."""
    start_share: float = 0.10
    """The "transients" start rule's bar: the share of the training photos' pixels left as residual blobs at
    warmup_steps at or above which the mask starts."""
    ramp_steps: int = 0
    """After warmup, lower the threshold linearly from RAMP_START_FACTOR * threshold to threshold over this many
    steps (0: the full threshold at once). Eases the switch from no mask to the full mask."""
    max_masked_fraction: float = 0.5
    """If the mask would drop more than this fraction of an image, the teacher is not trustworthy there (still
    training, or an appearance it cannot explain): that image is supervised everywhere instead (logged as
    mask_rejected). Occluders in photo collections cover far less than half an image."""
    every: int = 4
    """Recompute an image's mask on every k-th visit of that image (teacher render + VGG); the visits between reuse
    its last mask. 1 = the paper (every step); 4 costs a fraction of the step time (docs/design.md)."""
    max_resolution: int = 256
    """Longest image side at which VGG features are computed; larger images are downsampled (antialiased) first
    and D is upsampled back. The mask is coarse by nature (relu3_3 is at 1/4 resolution), so this mostly buys
    speed (the paper: 512)."""
    teacher: TeacherConfig = field(default_factory=TeacherConfig)
    """The EMA teacher that renders the pseudo ground truth (decay tau; fused into the student's rasterisation)."""
    safeguard: StaticSupportConfig = field(default_factory=StaticSupportConfig)
    """Pixels around observations of SfM points seen by many training images are static and never masked
    (willags_ns/mask/static_support.py; COLMAP scenes, where the tracks exist)."""
    health: MaskHealthConfig = field(default_factory=MaskHealthConfig)
    """Warn once while training when the mask feeds on itself (its masked share rising while the training PSNR
    falls; willags_ns/mask/health.py)."""


RAMP_START_FACTOR = 4.0
"""Threshold multiplier at the start of the ramp (see :func:`mask_threshold`)."""


def static_mask(D: Float[Tensor, "B H W"], threshold: float | Tensor) -> Bool[Tensor, "B H W"]:
    """True where the pixel is static (kept in the loss): ``D < threshold`` (a float, or [B, 1, 1] per image)."""
    return D < threshold


MAD_TO_STD = 1.4826
"""MAD of a normal distribution times this is its standard deviation."""


def _lower_median(x: Tensor) -> Tensor:
    """``x.median(dim=1).values`` (the lower median of each row) through a sort: the same value, but CUDA's median
    kernel selects within one block per row, several times slower than the sort (docs/design.md)."""
    return x.sort(dim=1).values[:, (x.shape[1] - 1) // 2]


def robust_threshold(D: Float[Tensor, "B H W"], threshold: float, k: float) -> Float[Tensor, "B 1 1"]:
    """Per-image threshold ``max(threshold, median(D) + k * 1.4826 * MAD(D))``, medians over each image's pixels.

    Transients cover a minority of an image, so the median and MAD describe its static pixels: a pixel must stand
    out from them by ``k`` robust standard deviations *and* exceed the absolute threshold. Example: D of a clean
    image ~ 0.1 +- 0.05 -> bar max(0.85, 0.1 + 2 * 0.07) = 0.85 (the paper's rule); D of a textured image the
    teacher renders blurred ~ 0.7 +- 0.3 -> bar 0.7 + 2 * 0.44 = 1.58, so texture stays and an occluder (D ~ 2)
    is still flagged. ``threshold = inf`` (mask warming up) stays inf.
    """
    flat = D.flatten(1)
    med = _lower_median(flat)  # [B]
    mad = _lower_median((flat - med[:, None]).abs())
    bar = (med + k * MAD_TO_STD * mad).clamp_min(threshold)
    return bar[:, None, None]


def transient_threshold(D: Float[Tensor, "B H W"], threshold: float, rule: str = "fixed", k: float = 2.0):
    """The threshold of ``rule`` ("fixed" -> ``threshold``; "robust" -> :func:`robust_threshold`)."""
    if rule == "fixed" or math.isinf(threshold):
        return threshold
    if rule == "robust":
        return robust_threshold(D, threshold, k)
    raise ValueError(f"unknown mask threshold rule {rule!r} (fixed | robust)")


def transient_mask(
    D: Float[Tensor, "H W"], threshold: float, rule: str = "fixed", k: float = 2.0, max_masked_fraction: float = 1.0
) -> tuple[Bool[Tensor, "H W"], Bool[Tensor, ""]]:
    """``(transient [H, W], rejected)`` of one image: ``D >= `` the threshold of ``rule`` (see
    :func:`transient_threshold`). When more than ``max_masked_fraction`` of the image would be transient the mask is
    rejected (all False): a teacher that disagrees with most of an image is not yet trained, or cannot explain that
    appearance; it is not looking at an occluder. The one rule of training and of the mask evaluation.

    ``rejected`` is a 0-d bool tensor on D's device, not a Python bool: reading it on the host would make the
    training step wait there until the GPU has run the teacher and VGG, with the loss and the backward not yet
    queued (``bool(rejected)`` where a caller needs it on the host)."""
    thr = transient_threshold(D[None], threshold, rule, k)
    transient = ~static_mask(D[None], thr)[0]
    rejected = transient.float().mean() > max_masked_fraction
    return transient & ~rejected, rejected


def mask_start(share: float, cfg: MaskConfig) -> tuple[bool, str]:
    """(start, reason) of the "transients" start rule (MaskConfig.start_rule) for a measured `share` of the training
    photos' pixels left as residual blobs: the mask starts at or above `cfg.start_share`, else stays off."""
    if not 0.0 <= share <= 1.0:
        raise ValueError(f"willags: a residual-blob share is within [0, 1], got {share}")
    start = share >= cfg.start_share
    side = "at or above" if start else "below"
    verdict = "the transient mask starts" if start else "the transient mask stays off for the rest of the run"
    return start, (
        f"the training photos leave {share:.1%} of their pixels as residual blobs, {side} the mask's bar of "
        f"{cfg.start_share:.1%}: {verdict}"
    )


def mask_active(step: int, warmup_steps: int) -> bool:
    """Whether the transient mask is applied at ``step``: from ``warmup_steps`` on (step 0-based)."""
    return step >= warmup_steps


def mask_threshold(step: int, threshold: float, warmup_steps: int, ramp_steps: int = 0) -> float:
    """The threshold in effect at ``step``: ``inf`` before warmup (nothing masked), then linear from
    ``RAMP_START_FACTOR * threshold`` at ``warmup_steps`` to ``threshold`` at ``warmup_steps + ramp_steps``.

    Example: threshold 0.85, warmup 500, ramp 100: step 499 -> inf, 500 -> 3.4, 550 -> 2.125, >= 600 -> 0.85.
    """
    if not mask_active(step, warmup_steps):
        return math.inf
    if ramp_steps <= 0:
        return threshold
    t = min(1.0, (step - warmup_steps) / ramp_steps)
    return threshold * (RAMP_START_FACTOR + (1.0 - RAMP_START_FACTOR) * t)


def step_threshold(mask_cfg: MaskConfig, step: int) -> float:
    """The bar in effect at `step` (:func:`mask_threshold` of the comparison's own: mask.threshold for "vgg", the
    residual bar's floor for "residual")."""
    base = mask_cfg.residual.floor if mask_cfg.distance == "residual" else mask_cfg.threshold
    return mask_threshold(step, base, mask_cfg.warmup_steps, mask_cfg.ramp_steps)


def compare_to_teacher(
    mask_cfg: MaskConfig,
    step: int,
    photo: Tensor,
    render: Tensor,
    perceptual: PerceptualFeatures | None,
    threshold: float | None = None,
    expected: Tensor | None = None,
) -> tuple[Tensor, Tensor, Tensor]:
    """``(transient [H, W] bool, rejected 0-d bool, D [H, W])`` of a photo [H, W, 3] against the teacher's render
    of it at `step`, by the comparison mask_cfg.distance names: "vgg" (perceptual D, its threshold rule;
    willags_ns/mask/transient.py for D) or "residual" (colour residual, robust bar, coherence;
    willags_ns/mask/residual.py). The one rule of training, the mask evaluation and the viewer. `threshold`: the bar
    instead of the step's (:func:`step_threshold`), for an evaluation at another one. `expected` [H, W]: the scene's
    expected residual at each pixel (willags_ns/mask/expected.py); with "residual", D is the residual beyond it,
    held to the bar of the plain residual."""
    thr = step_threshold(mask_cfg, step) if threshold is None else threshold
    if mask_cfg.distance == "residual":
        d = colour_residual(photo, render)
        excess = None if expected is None else excess_residual(d, expected)
        transient, rejected = residual_transient(d, thr, mask_cfg.residual, mask_cfg.max_masked_fraction, excess)
        return transient, rejected, d if excess is None else excess
    if mask_cfg.distance != "vgg":
        raise ValueError(f"mask.distance {mask_cfg.distance!r}: expected vgg | residual")
    assert perceptual is not None
    d = image_distance(perceptual, photo, render)  # [H, W]
    transient, rejected = transient_mask(
        d, thr, mask_cfg.threshold_rule, mask_cfg.robust_k, mask_cfg.max_masked_fraction
    )
    return transient, rejected, d
