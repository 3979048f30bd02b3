"""Numbers that a training step uses in tensor operations, as tensors made once per dtype and device."""

import functools

import torch
from torch import Tensor


@functools.lru_cache(maxsize=256)
def _constant(value: float, dtype: torch.dtype, device: torch.device) -> Tensor:
    with torch.inference_mode(False):
        return torch.tensor(value, dtype=dtype, device=device)


def constant(value: float, like: Tensor) -> Tensor:
    """`value` as a 0-dim tensor of `like`'s dtype on its device, made once. A Python number in a tensor operation is
    wrapped into a tensor and converted to the other operand's dtype at every call, host work and operators of their
    own in every step; the cached tensor holds the number that conversion gives, so the results are the same. A
    normal tensor even when first made under inference mode (autograd may save it); read-only for its callers."""
    return _constant(float(value), like.dtype, like.device)
