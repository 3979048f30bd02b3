"""Colour decoder T_color: (dynamic feature f_d, intrinsic feature f_s, view direction) -> RGB per Gaussian.

``rgb = sigmoid(MLP([f_d, f_s, SH_l(d / |d|)]))``, a 3-layer ReLU MLP (hidden 64). ``f_d`` comes from the
tri-plane field (image-dependent appearance), ``f_s`` is a learnable per-Gaussian feature stored by the model
(the Gaussian's intrinsic colour/material), ``d`` the direction from the camera centre to the Gaussian.

View-direction encoding: the real spherical-harmonics basis of the unit direction up to degree 2 (9 values;
degree 3 gives 16). Why SH: it is the basis 3DGS already uses for view dependence, so degree 2-3 covers the same
low-frequency effects (soft specular, sheen); it is a fixed polynomial of (x, y, z), cheap for millions of
Gaussians per step and smooth, so the decoder cannot overfit a per-view colour from a high-frequency encoding of
the sparse training directions. Constants are the ones of gsplat / 3DGS (``SH_C*`` below).
"""

from dataclasses import dataclass

import torch
from jaxtyping import Float
from torch import Tensor, nn

SH_C0 = 0.28209479177387814
SH_C1 = 0.4886025119029199
SH_C2 = (1.0925484305920792, -1.0925484305920792, 0.31539156525252005, -1.0925484305920792, 0.5462742152960396)
SH_C3 = (
    -0.5900435899266435,
    2.890611442640554,
    -0.4570457994644658,
    0.3731763325901154,
    -0.4570457994644658,
    1.445305721320277,
    -0.5900435899266435,
)


@dataclass
class ColorDecoderConfig:
    """Hyper-parameters of the colour decoder (its input sizes follow the model: triplane.feature_dim for f_d,
    intrinsic_dim for f_s, plus latent.dim without the field)."""

    hidden: int = 64
    """Width of the two hidden layers."""
    dir_sh_degree: int = 2
    """Degree of the real SH encoding of the view direction (0..3; (degree + 1)**2 values)."""


def sh_basis(dirs: Float[Tensor, "N 3"], degree: int) -> Float[Tensor, "N K"]:
    """Real spherical-harmonics basis of unit directions up to ``degree`` (0..3): ``K = (degree + 1)**2``.

    Same ordering and signs as 3DGS / gsplat's ``spherical_harmonics``. ``dirs`` must be unit length.
    At d = (0, 0, 1), degree 1: [C0, 0, C1, 0] (the basis is -C1*y, C1*z, -C1*x after the constant).
    """
    if not 0 <= degree <= 3:
        raise ValueError(f"sh degree must be in 0..3, got {degree}")
    x, y, z = dirs.unbind(-1)
    xx, yy, zz, xy, yz, xz = x * x, y * y, z * z, x * y, y * z, x * z  # [N] each (unused for degree < 2)
    out = [torch.full_like(x, SH_C0)]
    if degree >= 1:
        out += [-SH_C1 * y, SH_C1 * z, -SH_C1 * x]
    if degree >= 2:
        out += [
            SH_C2[0] * xy,
            SH_C2[1] * yz,
            SH_C2[2] * (2.0 * zz - xx - yy),
            SH_C2[3] * xz,
            SH_C2[4] * (xx - yy),
        ]
    if degree >= 3:
        out += [
            SH_C3[0] * y * (3.0 * xx - yy),
            SH_C3[1] * xy * z,
            SH_C3[2] * y * (4.0 * zz - xx - yy),
            SH_C3[3] * z * (2.0 * zz - 3.0 * xx - 3.0 * yy),
            SH_C3[4] * x * (4.0 * zz - xx - yy),
            SH_C3[5] * z * (xx - yy),
            SH_C3[6] * x * (xx - 3.0 * yy),
        ]
    return torch.stack(out, dim=-1)


class ColorDecoder(nn.Module):
    """T_color: ``[f_d, f_s, SH(view dir)] -> Linear-ReLU-Linear-ReLU-Linear -> sigmoid -> rgb`` in (0, 1)."""

    def __init__(self, dynamic_dim: int = 32, intrinsic_dim: int = 32, hidden: int = 64, dir_sh_degree: int = 2):
        super().__init__()
        if dynamic_dim < 0 or intrinsic_dim <= 0:
            raise ValueError(f"need dynamic_dim >= 0 and intrinsic_dim > 0, got {dynamic_dim}, {intrinsic_dim}")
        if not 0 <= dir_sh_degree <= 3:
            raise ValueError(f"dir_sh_degree must be in 0..3, got {dir_sh_degree}")
        self.dynamic_dim = dynamic_dim
        self.intrinsic_dim = intrinsic_dim
        self.dir_sh_degree = dir_sh_degree
        d_in = dynamic_dim + intrinsic_dim + (dir_sh_degree + 1) ** 2
        self.mlp = nn.Sequential(
            nn.Linear(d_in, hidden), nn.ReLU(), nn.Linear(hidden, hidden), nn.ReLU(), nn.Linear(hidden, 3)
        )

    def forward(
        self,
        f_d: Float[Tensor, "N Fd"] | None,
        f_s: Float[Tensor, "N Fs"],
        view_dirs: Float[Tensor, "N 3"],
    ) -> Float[Tensor, "N 3"]:
        """RGB in (0, 1) per Gaussian. ``view_dirs`` need not be normalised; ``f_d`` is ignored (may be None)
        when ``dynamic_dim == 0``. Works for N = 0."""
        if f_s.shape[-1] != self.intrinsic_dim:
            raise ValueError(f"f_s has {f_s.shape[-1]} channels, expected {self.intrinsic_dim}")
        dirs = view_dirs / view_dirs.norm(dim=-1, keepdim=True).clamp_min(1e-8)
        parts = [f_s, sh_basis(dirs, self.dir_sh_degree).to(f_s.dtype)]
        if self.dynamic_dim > 0:
            if f_d is None or f_d.shape[-1] != self.dynamic_dim:
                got = None if f_d is None else tuple(f_d.shape)
                raise ValueError(f"f_d must be [N, {self.dynamic_dim}], got {got}")
            parts.insert(0, f_d)
        return torch.sigmoid(self.mlp(torch.cat(parts, dim=-1)))
