"""LPIPS for the eval images, only when it needs no download: torchmetrics' LPIPS builds torchvision's AlexNet with
ImageNet weights."""

from pathlib import Path

import torch
from nerfstudio.utils.rich_utils import CONSOLE


def lpips_weights_cached() -> bool:
    """Whether AlexNet's ImageNet weights are in torch hub's checkpoint folder."""
    hub = Path(torch.hub.get_dir()) / "checkpoints"
    return any(hub.glob("alexnet-owt-*.pth"))


def make_lpips(device) -> tuple[torch.nn.Module | None, str]:
    """(torchmetrics LPIPS on `device`, "torchmetrics alexnet") when the weights are on disk; else (None,
    "unavailable") with a one-line notice."""
    if lpips_weights_cached():
        from torchmetrics.image.lpip import LearnedPerceptualImagePatchSimilarity

        return LearnedPerceptualImagePatchSimilarity(normalize=True).to(device), "torchmetrics alexnet"
    CONSOLE.log(
        f"willags: reporting PSNR and SSIM only: LPIPS needs AlexNet's ImageNet weights in "
        f"{torch.hub.get_dir()}/checkpoints, which willags never downloads itself; to add LPIPS, run once with "
        "internet: python -c \"import torchvision; torchvision.models.alexnet(weights='DEFAULT')\""
    )
    return None, "unavailable"
