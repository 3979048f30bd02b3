"""Rotations of Gaussians: a quaternion (w, x, y, z; any non-zero norm, normalised here as gsplat does) to its
rotation matrix. The torch rasteriser (a Gaussian's covariance) and MCMC's position noise (its covariance) share it."""

import torch
import torch.nn.functional as F
from torch import Tensor


def quaternion_to_matrix(quats: Tensor) -> Tensor:
    """Rotation matrices [..., 3, 3] of quaternions [..., 4] in (w, x, y, z) order, normalised first."""
    w, x, y, z = F.normalize(quats, p=2, dim=-1).unbind(-1)
    rows = (
        1 - 2 * (y * y + z * z),
        2 * (x * y - w * z),
        2 * (x * z + w * y),
        2 * (x * y + w * z),
        1 - 2 * (x * x + z * z),
        2 * (y * z - w * x),
        2 * (x * z - w * y),
        2 * (y * z + w * x),
        1 - 2 * (x * x + y * y),
    )
    return torch.stack(rows, dim=-1).reshape(quats.shape[:-1] + (3, 3))
