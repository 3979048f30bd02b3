"""Loss terms of WilLaGS as pure functions.

    L = (1 - lambda_ssim) * L1_masked + lambda_ssim * DSSIM_masked + lambda_vae * L_VAE,
        lambda_ssim = 0.2, lambda_vae = 0.01

where "masked" means restricted to the static pixels of the perceptual transient mask (``willags_ns.mask.transient``).
The regularisers that join it during training are weighted in ``willags_ns/objective/regularizers.py``.

Layout: every image here is ``[B, 3, H, W]`` in [0, 1] (torch / torchmetrics convention) and every mask is
``[B, H, W]`` (``[B, 1, H, W]`` accepted), bool or float in [0, 1], with True / 1 = static = kept in the loss.
The model converts nerfstudio's ``[H, W, 3]`` renders once, before calling these.

Normalisation: masked terms are averaged over the kept pixels (x channels), so the loss scale does not depend on
how much of the image a transient covers. With nothing kept the terms are exactly 0, finite, and still attached
to the graph (zero gradients), so a fully masked step is a no-op rather than a NaN.
"""

import torch
import torch.nn.functional as F
from jaxtyping import Float
from torch import Tensor

from willags_ns.tensor_constants import as_dtype, constant, made_once


def _check(pred: Tensor, gt: Tensor, mask: Tensor | None) -> Tensor | None:
    """Validate shapes; return the mask as float [B, 1, H, W] (None when ``mask`` is None: every pixel kept)."""
    if pred.dim() != 4 or pred.shape[1] != 3 or pred.shape != gt.shape:
        raise ValueError(
            f"expected pred and gt [B, 3, H, W] of equal shape, got {tuple(pred.shape)}, {tuple(gt.shape)}"
        )
    if mask is None:
        return None
    if mask.dim() == 3:
        mask = mask.unsqueeze(1)
    if mask.shape != (pred.shape[0], 1, *pred.shape[2:]):
        raise ValueError(f"expected mask [B, H, W] matching {tuple(pred.shape)}, got {tuple(mask.shape)}")
    return mask.to(pred.dtype).detach()


def _masked_mean(per_pixel: Tensor, m: Tensor | None) -> Tensor:
    """Mean of ``per_pixel`` [B, C, H, W] over the pixels where ``m`` [B, 1, H, W] > 0, weighted by ``m``; the plain
    mean without a mask (no [B, 1, H, W] of ones to multiply and sum)."""
    if m is None:
        return per_pixel.mean()
    denom = m.sum() * per_pixel.shape[1]
    return (per_pixel * m).sum() / denom.clamp_min(torch.finfo(per_pixel.dtype).eps)


def masked_l1(pred: Float[Tensor, "B 3 H W"], gt: Float[Tensor, "B 3 H W"], mask: Tensor | None = None) -> Tensor:
    """Mean ``|pred - gt|`` over kept pixels and channels; 0 when nothing is kept. Example: one kept pixel with
    errors (0.3, 0, 0) gives 0.1 whatever the rest of the image holds."""
    m = _check(pred, gt, mask)
    return _masked_mean((pred - gt).abs(), m)


def masked_dssim(pred: Float[Tensor, "B 3 H W"], gt: Float[Tensor, "B 3 H W"], mask: Tensor | None = None) -> Tensor:
    """``1 - SSIM`` averaged over kept pixels and channels (the per-pixel SSIM map of :func:`ssim_map`: Gaussian
    window 11, sigma 1.5, reflect padding, data range 1; smaller images use a smaller window, see
    :func:`ssim_window`).

    Excluded pixels are zeroed in *both* images before SSIM, so a transient neither enters the window statistics
    of nearby kept pixels nor receives gradient through them. With an all-true mask this equals ``1 - SSIM``.
    """
    m = _check(pred, gt, mask)
    _, sigma = ssim_window(*pred.shape[-2:])
    gt = as_dtype(gt, pred.dtype)
    if m is not None:
        pred, gt = pred * m, gt * m
    return _masked_mean(constant(1.0, pred) - ssim_map(pred, gt, sigma), m)


@made_once
def _gaussian_1d(sigma: float, dtype: torch.dtype, device: torch.device) -> Tensor:
    """torchmetrics' SSIM window: int(3.5 sigma + 0.5) * 2 + 1 taps of a normalised Gaussian. Made once per (sigma,
    dtype, device): every training step's SSIM uses it (and the convolutions' backward saves it)."""
    size = int(3.5 * sigma + 0.5) * 2 + 1
    d = torch.arange((1 - size) / 2, (1 + size) / 2, 1.0, dtype=dtype, device=device)
    g = torch.exp(-((d / sigma) ** 2) / 2)
    return g / g.sum()


@made_once
def _separable_filters(sigma: float, planes: int, dtype: torch.dtype, device: torch.device) -> tuple[Tensor, Tensor]:
    """The depthwise weights of SSIM's row pass [planes, 1, 1, n] and column pass [planes, 1, n, 1]: views of
    :func:`_gaussian_1d`, made once per (sigma, planes, dtype, device) instead of two views each per pass per step."""
    g = _gaussian_1d(sigma, dtype, device)
    return g.view(1, 1, 1, -1).expand(planes, 1, 1, -1), g.view(1, 1, -1, 1).expand(planes, 1, -1, 1)


def ssim_map(
    x: Float[Tensor, "B C H W"], y: Float[Tensor, "B C H W"], sigma: float = 1.5, data_range: float = 1.0
) -> Float[Tensor, "B C H W"]:
    """Per-pixel SSIM of x and y: torchmetrics' ``structural_similarity_index_measure(..., return_full_image=True)``
    (Gaussian window, reflect padding, k1 0.01, k2 0.03) with its 2D window applied as two 1D passes.

    Why not torchmetrics itself: its window is one depthwise 11x11 convolution (121 taps per pixel, forward and
    backward, over 5 x C planes); a Gaussian is separable, so a row pass and a column pass give the same sums with
    22 taps (float rounding apart: ``tests/objective/test_losses.py`` compares maps and gradients)."""
    g = _gaussian_1d(sigma, x.dtype, x.device)
    pad = (g.numel() - 1) // 2
    c = x.shape[1]
    x = F.pad(x, (pad, pad, pad, pad), mode="reflect")
    y = F.pad(y, (pad, pad, pad, pad), mode="reflect")
    planes = torch.cat((x, y, x * x, y * y, x * y), dim=1)  # [B, 5C, H + 2p, W + 2p]
    k = planes.shape[1]
    along_rows, along_columns = _separable_filters(sigma, k, x.dtype, x.device)
    blurred = F.conv2d(F.conv2d(planes, along_rows, groups=k), along_columns, groups=k)
    mu_x, mu_y, e_xx, e_yy, e_xy = blurred.split(c, dim=1)
    mu_xx, mu_yy, mu_xy = mu_x * mu_x, mu_y * mu_y, mu_x * mu_y
    var_x = (e_xx - mu_xx).clamp_min(0.0)
    var_y = (e_yy - mu_yy).clamp_min(0.0)
    cov = e_xy - mu_xy
    c1, c2 = constant((0.01 * data_range) ** 2, x), constant((0.03 * data_range) ** 2, x)
    # c + 2 t as one add (alpha 2: doubling is exact, so the same value however the kernel fuses it)
    return (torch.add(c1, mu_xy, alpha=2.0) * torch.add(c2, cov, alpha=2.0)) / (
        (mu_xx + mu_yy + c1) * (var_x + var_y + c2)
    )


SSIM_WINDOW = 11
SSIM_SIGMA = 1.5


def ssim_window(height: int, width: int) -> tuple[int, float]:
    """SSIM's Gaussian window (size, sigma) for an image: 11 and 1.5 (3DGS's) whenever the image has at least 6 rows
    and columns; below that the largest odd window whose reflect padding fits, ``2 * min(H, W) - 1``, with sigma
    scaled alike. Why: splatfacto's resolution schedule trains an 8x8 image at 2x2 for the first steps, where an
    11-px window cannot be padded (torch raises deep inside torchmetrics). Example: 2x2 -> (3, 0.41); 1x1 -> (1,
    0.14)."""
    k = min(SSIM_WINDOW, 2 * min(int(height), int(width)) - 1)
    k = max(1, k if k % 2 == 1 else k - 1)
    return k, SSIM_SIGMA * k / SSIM_WINDOW


def reconstruction_loss(
    pred: Float[Tensor, "B 3 H W"],
    gt: Float[Tensor, "B 3 H W"],
    mask: Tensor | None = None,
    ssim_lambda: float = 0.2,
) -> Tensor:
    """``(1 - ssim_lambda) * masked_l1 + ssim_lambda * masked_dssim`` (3DGS's 0.8 / 0.2 by default)."""
    loss = constant(1.0 - ssim_lambda, pred) * masked_l1(pred, gt, mask)
    if ssim_lambda > 0.0:
        loss = loss + constant(ssim_lambda, pred) * masked_dssim(pred, gt, mask)
    return loss


def total_loss(
    pred: Float[Tensor, "B 3 H W"],
    gt: Float[Tensor, "B 3 H W"],
    mask: Tensor | None = None,
    l_vae: Tensor | None = None,
    ssim_lambda: float = 0.2,
    lambda_vae: float = 0.01,
) -> tuple[Tensor, dict[str, Tensor]]:
    """``reconstruction_loss + lambda_vae * l_vae``; returns ``(total, terms)``.

    ``terms`` holds the *weighted* parts (``"rgb_loss"``, and ``"vae_loss"`` when ``l_vae`` is given) whose sum
    is ``total``, the form nerfstudio's ``get_loss_dict`` expects (the trainer sums the dict).
    """
    terms = {"rgb_loss": reconstruction_loss(pred, gt, mask, ssim_lambda=ssim_lambda)}
    if l_vae is not None:
        terms["vae_loss"] = lambda_vae * l_vae
    total = sum(terms.values())
    assert isinstance(total, Tensor)
    return total, terms


def scale_regularization(log_scales: Float[Tensor, "N 3"], max_ratio: float) -> Tensor:
    """Splatfacto's penalty on needle-like Gaussians: 0.1 * mean(max(s_max / s_min, r) - r) over the Gaussians,
    scales s = exp(log_scales); 0 when no Gaussian is longer than r times its width."""
    s = torch.exp(log_scales)
    ratio = s.amax(dim=-1) / s.amin(dim=-1)
    return 0.1 * (torch.clamp_min(ratio, max_ratio) - max_ratio).mean()
