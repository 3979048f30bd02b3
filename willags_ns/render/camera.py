"""Camera conventions between nerfstudio and the rasteriser: the view matrix, the intrinsics at a render scale."""

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
