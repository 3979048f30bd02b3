"""Colour decoder T_color: (dynamic feature f_d, intrinsic feature f_s, view direction) -> RGB per Gaussian.

``rgb = sigmoid(MLP([f_d, f_s, SH_l(d / |d|)]))``, a 3-layer ReLU MLP (hidden 64). ``f_d`` comes from the
tri-plane field (image-dependent appearance), ``f_s`` is a learnable per-Gaussian feature stored by the model
(the Gaussian's intrinsic colour/material), ``d`` the direction from the camera centre to the Gaussian.

View-direction encoding: the real spherical-harmonics basis of the unit direction up to degree 2 (9 values;
degree 3 gives 16). Why SH: it is the basis 3DGS already uses for view dependence, so degree 2-3 covers the same
low-frequency effects (soft specular, sheen); it is a fixed polynomial of (x, y, z), cheap for millions of
Gaussians per step and smooth, so the decoder cannot overfit a per-view colour from a high-frequency encoding of
the sparse training directions. The basis: willags_ns/render/sh.py's `sh_basis` (3DGS' constants and order).
"""

from dataclasses import dataclass
from typing import Any

import torch
from jaxtyping import Float
from torch import Tensor, nn

from willags_ns.appearance.color_model import ColorModel, GaussianLayout
from willags_ns.render.sh import sh_basis


@dataclass
class ColorDecoderConfig:
    """Hyper-parameters of the colour decoder (its input sizes follow the model: triplane.feature_dim for f_d,
    intrinsic_dim for f_s, plus latent.dim without the field)."""

    hidden: int = 64
    """Width of the two hidden layers."""
    dir_sh_degree: int = 2
    """Degree of the real SH encoding of the view direction (0..3; (degree + 1)**2 values)."""


class ColorDecoder(ColorModel):
    """T_color: ``[f_d, f_s, SH(view dir)] -> Linear-ReLU-Linear-ReLU-Linear -> sigmoid -> rgb`` in (0, 1): the colour
    model of color_mode 'decoder' (appearance/color_model.py). Without the field (dynamic_dim 0) z joins f_s."""

    @classmethod
    def build(cls, cfg: Any, latent_dim: int, field_dim: int) -> "ColorDecoder":
        """From the model config: f_d of the field (field_dim, 0 without it), f_s (intrinsic_dim) and, without the
        field, z beside it."""
        return cls(
            dynamic_dim=field_dim,
            intrinsic_dim=cfg.intrinsic_dim + (0 if field_dim > 0 else latent_dim),
            hidden=cfg.decoder.hidden,
            dir_sh_degree=cfg.decoder.dir_sh_degree,
        )

    @classmethod
    def layout(cls, cfg: Any) -> GaussianLayout:
        """f_s only (no SH: the colour is regressed), its first entries starting at the seed colour."""
        return GaussianLayout(sh=False, intrinsic_dim=cfg.intrinsic_dim, seed_color_in_features=True)

    def rgb(self, z, base, f_s, f_d, dirs, prepared) -> Tensor:
        """:meth:`forward` of (f_d, f_s, dirs); without the field, f_s with z beside it (the "w/o field" ablation)."""
        if f_s is None:
            raise ValueError("color_mode='decoder' needs the Gaussians' intrinsic features f_s")
        if self.dynamic_dim == 0:
            f_s = torch.cat([f_s, z.expand(f_s.shape[0], -1)], dim=-1)
        return self(f_d, f_s, dirs)

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
