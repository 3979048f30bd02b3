"""Camera conventions between nerfstudio and the rasteriser: the view matrix, the intrinsics at a render scale, and
the two together as the `View` a forward pass renders."""

from typing import NamedTuple

import torch
from torch import Tensor


def viewmat_from_c2w(c2w: Tensor) -> Tensor:
    """nerfstudio camera-to-world [C, 3, 4] (OpenGL: -z forward, +y up) -> gsplat world-to-camera [C, 4, 4].

    Same maths as splatfacto's `get_viewmat`, without its torch.compile (15-20 s on the first CPU call).
    """
    # flip the y and z axes (columns 1, 2); negation on the device, not a constant copied from the host (a blocking
    # copy that drains the GPU's queue once per step)
    R = torch.cat((c2w[:, :3, :1], -c2w[:, :3, 1:3]), dim=-1)
    T = c2w[:, :3, 3:4]
    R_inv = R.transpose(1, 2)
    viewmat = torch.zeros(c2w.shape[0], 4, 4, device=c2w.device, dtype=c2w.dtype)
    viewmat[:, 3, 3] = 1.0
    viewmat[:, :3, :3] = R_inv
    viewmat[:, :3, 3:4] = -torch.bmm(R_inv, T)
    return viewmat


def intrinsics_at(camera, scale_factor: float, device) -> tuple[Tensor, int, int]:
    """(K [C, 3, 3] on `device`, width, height) of a nerfstudio `Cameras` rendered at 1 / scale_factor of its
    resolution (splatfacto's resolution schedule); the camera is left at its own resolution."""
    camera.rescale_output_resolution(1 / scale_factor)
    K = camera.get_intrinsics_matrices().to(device)
    W, H = int(camera.width.item()), int(camera.height.item())
    camera.rescale_output_resolution(scale_factor)
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


def camera_view(camera, c2w: Tensor, scale_factor: float, device) -> View:
    """The `View` of a nerfstudio `Cameras` posed at `c2w` [C, 3, 4], rendered at 1 / scale_factor of its
    resolution (intrinsics_at)."""
    K, W, H = intrinsics_at(camera, scale_factor, device)
    return View(c2w, viewmat_from_c2w(c2w), K, W, H)
