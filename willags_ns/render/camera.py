"""Camera conventions between nerfstudio and the rasteriser: the view matrix, the intrinsics at a render scale, and
the two together as the `View` a forward pass renders."""

import functools
from typing import NamedTuple

import torch
from torch import Tensor

from willags_ns.tensor_constants import made_once


def viewmat_from_c2w(c2w: Tensor) -> Tensor:
    """nerfstudio camera-to-world [C, 3, 4] (OpenGL: -z forward, +y up) -> gsplat world-to-camera [C, 4, 4].

    Same maths as splatfacto's `get_viewmat`, without its torch.compile (15-20 s on the first CPU call).
    """
    flip, last_row = _viewmat_constants(c2w.device, c2w.dtype)
    R_inv = (c2w[:, :3, :3] * flip).transpose(1, 2)  # the y and z axes (columns 1, 2) flipped, transposed
    t = -torch.bmm(R_inv, c2w[:, :3, 3:4])
    return torch.cat((torch.cat((R_inv, t), dim=2), last_row.expand(c2w.shape[0], 1, 4)), dim=1)


@made_once
def _viewmat_constants(device: torch.device, dtype: torch.dtype) -> tuple[Tensor, Tensor]:
    """(the axis flip [1, -1, -1], the view matrix's last row [0, 0, 0, 1]) on `device`, made once: a constant
    copied from the host in every step would be a blocking copy that drains the GPU's queue."""
    return (
        torch.tensor([1.0, -1.0, -1.0], device=device, dtype=dtype),
        torch.tensor([[0.0, 0.0, 0.0, 1.0]], device=device, dtype=dtype),
    )


def scaled_size(width: int, height: int, factor: float) -> tuple[int, int]:
    """(width, height) of an image `width` x `height` at `factor` of its resolution, rounded as nerfstudio's
    `Cameras.rescale_output_resolution` does by default (floor mode: size times the factor as a tensor of the default
    dtype, cast to int64), computed on the host."""
    return _scaled_size(int(width), int(height), float(factor), torch.get_default_dtype())


@functools.lru_cache(maxsize=4096)
def _scaled_size(width: int, height: int, factor: float, dtype: torch.dtype) -> tuple[int, int]:
    w, h = (torch.tensor([width, height]) * torch.tensor([factor], dtype=dtype)).to(torch.int64).tolist()
    return w, h


def intrinsics_at(camera, scale_factor: float, device, size: tuple[int, int] | None = None) -> tuple[Tensor, int, int]:
    """(K [*C, 3, 3] float32 on `device`, width, height) of a nerfstudio `Cameras` rendered at 1 / scale_factor of its
    resolution (splatfacto's resolution schedule), bit for bit what nerfstudio's `rescale_output_resolution(1 /
    scale_factor)` then `get_intrinsics_matrices()` give, without changing the camera.

    K is made on the camera's device from its fx, fy, cx, cy by device operations only: on a GPU, nerfstudio's path
    copies the factor from the host and builds K on the host from the camera's values (each copy and each read a
    wait for the GPU). `size`: the camera's (width, height) at its own resolution when the caller knows it on the host (the
    training images' sizes); otherwise the camera's width and height are read (one read, a wait on a GPU)."""
    factor = 1 / scale_factor
    fx, fy, cx, cy = camera.fx, camera.fy, camera.cx, camera.cy  # [*C, 1] each
    zero, one = torch.zeros_like(fx), torch.ones_like(fx)
    K = torch.cat((fx, zero, cx, zero, fy, cy, zero, zero, one), dim=-1)  # K's rows, flattened
    if factor != 1:  # x * 1.0 is x: nothing to launch at full resolution
        # nerfstudio multiplies fx, fy, cx, cy by torch.tensor([factor]) (the default dtype); made here on the device,
        # no copy, and applied to K's first two rows in one product (their zeros stay zero)
        K = K.to(torch.promote_types(K.dtype, torch.get_default_dtype()))
        K[..., :6] *= torch.full((1,), factor, dtype=torch.get_default_dtype(), device=K.device)
    K = K.to(torch.float32).reshape(*K.shape[:-1], 3, 3).to(device)
    if size is None:  # one camera: its width and height in one read
        if camera.width.numel() != 1:
            raise ValueError(f"willags renders one camera at a time without a given size; got {camera.width.numel()}")
        size = tuple(torch.stack((camera.width.reshape(()), camera.height.reshape(()))).tolist())
    W, H = scaled_size(size[0], size[1], factor)
    return K, W, H


class View(NamedTuple):
    """A camera at the render's scale in the rasteriser's terms: what every stage of a forward pass reads of it."""

    c2w: Tensor
    """[C, 3, 4] nerfstudio camera-to-world (OpenGL axes), after the camera optimiser while training."""
    viewmat: Tensor
    """[C, 4, 4] the rasteriser's world-to-camera (viewmat_from_c2w)."""
    K: Tensor
    """[C, 3, 3] intrinsics at the render's scale."""
    width: int
    height: int

    @property
    def center(self) -> Tensor:
        """[3] the first camera's centre in world space (where the Gaussians' view directions start)."""
        return self.c2w[0, :3, 3]


def camera_view(camera, c2w: Tensor, scale_factor: float, device, size: tuple[int, int] | None = None) -> View:
    """The `View` of a nerfstudio `Cameras` posed at `c2w` [C, 3, 4], rendered at 1 / scale_factor of its
    resolution (intrinsics_at; `size`: its (width, height) at its own resolution when known on the host)."""
    K, W, H = intrinsics_at(camera, scale_factor, device, size)
    return View(c2w, viewmat_from_c2w(c2w), K, W, H)
