"""The full-image datamanager every willags method uses: nerfstudio's, with an image cache that works on a CPU.

nerfstudio 1.1.5's FullImageDatamanager caches the images on the training device ("gpu"), except past 500 training
images, where it moves the cache to "cpu" and pins it (page-locked memory, for fast copies to a GPU). Pinning needs
CUDA: on a machine without a GPU that collection would crash at its first step ("Cannot access accelerator device
when none is available"), and on a CPU device pinned pages buy nothing. Here a cache that nerfstudio would pin for a
device other than CUDA stays in ordinary memory on that device: the same tensors, not page-locked. On CUDA nothing
changes.

The images are cached as uint8 (`cache_images_type`, set by the method configs): a quarter of float32's memory, and
the model turns each into floats in [0, 1] when it reads it (`appearance.latents.image_as_float`).
"""

from dataclasses import dataclass, field
from typing import Literal

import torch
from nerfstudio.data.datamanagers.full_images_datamanager import FullImageDatamanager, FullImageDatamanagerConfig
from nerfstudio.data.datasets.base_dataset import InputDataset


def pins_memory(device) -> bool:
    """Whether an image cache kept on the host for ``device`` should be pinned: only for copies to a CUDA device
    (pinning needs CUDA, and speeds nothing else)."""
    return torch.device(str(device)).type == "cuda" and torch.cuda.is_available()


@dataclass
class WillagsDatamanagerConfig(FullImageDatamanagerConfig):
    """nerfstudio's full-image datamanager (every option as there), whose host image cache is pinned only for a
    CUDA device, so that collections of over 500 training images train on a CPU."""

    _target: type = field(default_factory=lambda: WillagsDatamanager)


class WillagsDatamanager(FullImageDatamanager[InputDataset]):
    """FullImageDatamanager whose "cpu" cache is pinned only for a CUDA device (see the module docstring)."""

    def _load_images(self, split: Literal["train", "eval"], cache_images_device: Literal["cpu", "gpu"]):
        if cache_images_device == "cpu" and not pins_memory(self.device):
            # nerfstudio's "gpu" is "on the training device": here the host, in ordinary memory
            cache_images_device = "gpu"
        return super()._load_images(split, cache_images_device)


def use_willags_datamanager(datamanager_config) -> None:
    """Build nerfstudio's own full-image datamanager config (a config.yml written before the method configs named
    WillagsDatamanagerConfig, or one a script made) as WillagsDatamanager, so that a run trained on a GPU loads on a
    CPU whatever its image count. Any other datamanager is left as it is."""
    if type(datamanager_config) is FullImageDatamanagerConfig:
        datamanager_config._target = WillagsDatamanager
