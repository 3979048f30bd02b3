"""Tensors a training step uses but need not make again, and conversions that run only where they change something.

A step runs hundreds of small tensor operations, and on a GPU the host that issues them sets its time
(docs/design.md, "Speed"): a constant built or a number wrapped every step, or a conversion to the dtype a tensor
already has, is host work (an operator each) for nothing."""

import functools
from collections.abc import Callable
from typing import TypeVar

import torch
from torch import Tensor

T = TypeVar("T")


def made_once(fn: Callable[..., T]) -> Callable[..., T]:
    """Cache `fn`'s tensors per argument tuple (its arguments name what they depend on: a device, a dtype, a size),
    built outside inference mode, so that they are normal tensors (autograd may save them) even when first asked for
    under it. Read-only for their callers."""

    @functools.lru_cache(maxsize=256)
    @functools.wraps(fn)
    def made(*args, **kwargs):
        with torch.inference_mode(False):
            return fn(*args, **kwargs)

    return made


@made_once
def _constant(value: float, dtype: torch.dtype, device: torch.device) -> Tensor:
    return torch.tensor(value, dtype=dtype, device=device)


def constant(value: float, like: Tensor) -> Tensor:
    """`value` as a 0-dim tensor of `like`'s dtype on its device, made once. A Python number in a tensor operation is
    wrapped into a tensor and converted to the other operand's dtype at every call, host work and operators of their
    own in every step; the cached tensor holds the number that conversion gives, so the results are the same."""
    return _constant(float(value), like.dtype, like.device)


def as_dtype(t: Tensor, dtype: torch.dtype) -> Tensor:
    """`t` in `dtype`: `t` itself when it already is (Tensor.to would still run an operator for nothing)."""
    return t if t.dtype == dtype else t.to(dtype)
