"""Loss terms of WilLaGS as pure functions.

    L = (1 - lambda_ssim) * L1_masked + lambda_ssim * DSSIM_masked + lambda_vae * L_VAE,
        lambda_ssim = 0.2, lambda_vae = 0.01

where "masked" means restricted to the static pixels of the perceptual transient mask (``willags_ns.transient``).

Layout: every image here is ``[B, 3, H, W]`` in [0, 1] (torch / torchmetrics convention) and every mask is
``[B, H, W]`` (``[B, 1, H, W]`` accepted), bool or float in [0, 1], with True / 1 = static = kept in the loss.
The model converts nerfstudio's ``[H, W, 3]`` renders once, before calling these.

Normalisation: masked terms are averaged over the kept pixels (x channels), so the loss scale does not depend on
how much of the image a transient covers. With nothing kept the terms are exactly 0, finite, and still attached
to the graph (zero gradients), so a fully masked step is a no-op rather than a NaN.
"""

import torch
from jaxtyping import Float
from torch import Tensor


def _check(pred: Tensor, gt: Tensor, mask: Tensor | None) -> Tensor:
    """Validate shapes; return the mask as float [B, 1, H, W] (all ones when ``mask`` is None)."""
    if pred.dim() != 4 or pred.shape[1] != 3 or pred.shape != gt.shape:
        raise ValueError(
            f"expected pred and gt [B, 3, H, W] of equal shape, got {tuple(pred.shape)}, {tuple(gt.shape)}"
        )
    if mask is None:
        return pred.new_ones(pred.shape[0], 1, *pred.shape[2:])
    if mask.dim() == 3:
        mask = mask.unsqueeze(1)
    if mask.shape != (pred.shape[0], 1, *pred.shape[2:]):
        raise ValueError(f"expected mask [B, H, W] matching {tuple(pred.shape)}, got {tuple(mask.shape)}")
    return mask.to(pred.dtype).detach()


def _masked_mean(per_pixel: Tensor, m: Tensor) -> Tensor:
    """Mean of ``per_pixel`` [B, C, H, W] over the pixels where ``m`` [B, 1, H, W] > 0, weighted by ``m``."""
    denom = m.sum() * per_pixel.shape[1]
    return (per_pixel * m).sum() / denom.clamp_min(torch.finfo(per_pixel.dtype).eps)


def masked_l1(pred: Float[Tensor, "B 3 H W"], gt: Float[Tensor, "B 3 H W"], mask: Tensor | None = None) -> Tensor:
    """Mean ``|pred - gt|`` over kept pixels and channels; 0 when nothing is kept. Example: one kept pixel with
    errors (0.3, 0, 0) gives 0.1 whatever the rest of the image holds."""
    m = _check(pred, gt, mask)
    return _masked_mean((pred - gt).abs(), m)


def masked_dssim(pred: Float[Tensor, "B 3 H W"], gt: Float[Tensor, "B 3 H W"], mask: Tensor | None = None) -> Tensor:
    """``1 - SSIM`` averaged over kept pixels and channels (torchmetrics' per-pixel SSIM map: Gaussian window
    11, sigma 1.5, reflect padding, data range 1; smaller images use a smaller window, see :func:`ssim_window`).

    Excluded pixels are zeroed in *both* images before SSIM, so a transient neither enters the window statistics
    of nearby kept pixels nor receives gradient through them. With an all-true mask this equals ``1 - SSIM``.
    """
    # Lazy: importing torchmetrics imports torchvision (~6 s on a CPU box, and it needs the CPU shim).
    from torchmetrics.functional.image import structural_similarity_index_measure

    m = _check(pred, gt, mask)
    k, sigma = ssim_window(*pred.shape[-2:])
    _, ssim_map = structural_similarity_index_measure(
        pred * m,
        gt.to(pred.dtype) * m,
        data_range=1.0,
        return_full_image=True,
        reduction="none",
        kernel_size=k,
        sigma=sigma,
    )  # [B, 3, H, W]
    return _masked_mean(1.0 - ssim_map, m)


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
    loss = (1.0 - ssim_lambda) * masked_l1(pred, gt, mask)
    if ssim_lambda > 0.0:
        loss = loss + ssim_lambda * masked_dssim(pred, gt, mask)
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
