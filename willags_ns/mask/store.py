"""Each training image's last mask, kept at one bit a pixel.

The transient mask is recomputed on every `mask.every`-th visit of an image and reused between, so each training
image's last mask stays in memory for the whole run, on the training device. As bool tensors that is one byte a pixel:
0.45 MB a photo of 800 x 560 px, 0.9 GB at 2,000 training photos. Packed eight pixels to a byte it is 1/8 of that
(0.11 GB), and unpacking gives back the same mask bit for bit.

    pack_bits(mask) -> uint8 [ceil(H*W / 8)]      unpack_bits(packed, (H, W)) -> bool [H, W]
    PackedMasks: {image index: bool [H, W]}, stored packed
"""

import math
from collections.abc import Iterator, MutableMapping

import torch
from torch import Tensor

_BITS = 8


def _shifts(device) -> Tensor:
    return torch.arange(_BITS, dtype=torch.uint8, device=device)


def pack_bits(mask: Tensor) -> Tensor:
    """A bool tensor of any shape as uint8 [ceil(numel / 8)]: pixel i in bit i % 8 of byte i // 8 (row-major)."""
    flat = mask.reshape(-1).to(torch.uint8)
    pad = (-flat.numel()) % _BITS
    if pad:
        flat = torch.cat([flat, flat.new_zeros(pad)])
    return (flat.view(-1, _BITS) << _shifts(flat.device)).sum(dim=1, dtype=torch.uint8)


def unpack_bits(packed: Tensor, shape: tuple[int, ...]) -> Tensor:
    """The bool tensor of `shape` that `pack_bits` packed into `packed`."""
    numel = math.prod(int(s) for s in shape)
    if packed.numel() * _BITS < numel:
        raise ValueError(f"unpack_bits: {packed.numel()} bytes hold fewer than the {numel} pixels of shape {shape}")
    bits = (packed[:, None] >> _shifts(packed.device)) & 1
    return bits.reshape(-1)[:numel].reshape(shape).bool()


class PackedMasks(MutableMapping):
    """{image index: bool mask [H, W]}, each kept packed (`pack_bits`); reading one unpacks it into a new tensor on
    the device it was stored from."""

    def __init__(self) -> None:
        self._packed: dict[int, tuple[Tensor, tuple[int, ...]]] = {}

    def __setitem__(self, idx: int, mask: Tensor) -> None:
        if mask.dtype != torch.bool:
            raise TypeError(f"PackedMasks: image {idx}'s mask is {mask.dtype}, not bool")
        self._packed[idx] = (pack_bits(mask), tuple(mask.shape))

    def __getitem__(self, idx: int) -> Tensor:
        packed, shape = self._packed[idx]
        return unpack_bits(packed, shape)

    def __delitem__(self, idx: int) -> None:
        del self._packed[idx]

    def __contains__(self, idx: object) -> bool:
        return idx in self._packed

    def __iter__(self) -> Iterator[int]:
        return iter(self._packed)

    def __len__(self) -> int:
        return len(self._packed)

    def nbytes(self) -> int:
        """The bytes the packed masks hold."""
        return sum(p.numel() * p.element_size() for p, _ in self._packed.values())
