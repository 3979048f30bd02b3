"""The metrics nerfstudio's eval writes per image (`Model.get_image_metrics_and_images`): PSNR, SSIM and, when its
weights are on disk, LPIPS of a render against its photo, with the model's own metric modules (splatfacto's:
torchmetrics' PSNR, pytorch_msssim's SSIM; LPIPS from eval/lpips.py). The NeRF-W protocol scores its half images
with its own functions (eval/protocol.py)."""

from collections.abc import Callable

from jaxtyping import Float
from torch import Tensor


def image_metrics(
    gt: Float[Tensor, "H W 3"], pred: Float[Tensor, "H W 3"], psnr: Callable, ssim: Callable, lpips: Callable | None
) -> dict[str, float]:
    """{"psnr", "ssim"(, "lpips" when `lpips` is given)} of `pred` against `gt`, both in [0, 1], as floats; the
    metric modules take [1, 3, H, W] images."""
    gt_b, pred_b = gt.permute(2, 0, 1)[None], pred.permute(2, 0, 1)[None]
    metrics = {"psnr": float(psnr(gt_b, pred_b).item()), "ssim": float(ssim(gt_b, pred_b))}
    if lpips is not None:
        metrics["lpips"] = float(lpips(gt_b, pred_b))
    return metrics
