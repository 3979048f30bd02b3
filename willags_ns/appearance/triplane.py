"""Tri-plane hypernetwork field: appearance latent z -> three feature planes -> per-Gaussian dynamic feature f_d.

A hypernetwork (3-layer MLP) maps z to three axis-aligned planes (XY, XZ, YZ), each ``Cp x R x R``
(Cp = 32 channels, R = 64). Each Gaussian's mean, normalised to [-1, 1]^3 by scene bounds fixed at
initialisation, is sampled bilinearly on the three planes; the concatenated ``3 * Cp`` features go through a
2-layer MLP to the dynamic feature ``f_d`` (32-d), which the colour decoder combines with the Gaussian's own
intrinsic feature. The planes make appearance spatially varying (a shadow over one part of the scene) while z
makes it image-dependent.

Parameter budget: the planes hold ``3 * 32 * 64 * 64 = 393,216`` values. A dense last layer from a 256-wide
hidden layer would be 100M parameters, so the hypernetwork is ``z -> 128 -> 32 -> planes``: the planes are a
learned linear basis of 32 plane-sets mixed by coefficients the MLP computes from z, plus a learned bias (the
mean planes, shared by all images). The last layer then has 32 * 393,216 = 12.6M weights. It is still the
paper's 3-layer MLP.

Initialisation (for stable early training): the bias planes are N(0, 1) (unit-variance features, so the
sampling MLP sees well-scaled inputs from step 0), the basis (last hypernetwork layer) is small (weights
N(0, 0.01^2 / width): the z-dependent part is ~0.2% of the planes' std at init), so z modulates the planes only
slightly at first, and the sampling MLP's last layer is small with
zero bias, so f_d starts near a constant (0) and the colour decoder first relies on the intrinsic feature.

Bounds rule (:func:`robust_bounds`): per axis the [q, 1 - q] quantiles (q = 0.02) of the initial points, widened
by a 10% margin of the extent on each side. Quantiles ignore the far-away SfM outliers (sky points, stray
matches) that would otherwise squeeze the whole scene into a few texels; the margin leaves room for Gaussians
that densify slightly outside the initial cloud. Points outside the box are clamped to its faces: they share the
boundary texels instead of producing NaN or zero padding. A degenerate axis (flat point cloud) is widened,
around its centre, to 1% of the largest axis' extent (and at least 1e-5 x the coordinates' magnitude), so the normalisation never divides by
zero and Gaussians that leave the plane still map to distinct texels.
"""

from collections.abc import Sequence
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from jaxtyping import Float
from torch import Tensor, nn

MIN_EXTENT = 1e-5
"""Smallest extent of the bounds, relative to max(1, |box centre|) so that it survives float32 rounding, and
(absolute) of ``normalize_points``' divisor: no division by zero."""
MIN_REL_EXTENT = 0.01
"""Smallest per-axis extent of :func:`robust_bounds` relative to its largest axis: a flat (planar) point cloud
still gets a usable box along its thin axis."""

# (u, v) axes of the three planes: grid_sample's x indexes the plane's width, y its height.
PLANE_AXES = ((0, 1), (0, 2), (1, 2))  # XY, XZ, YZ


@dataclass
class TriplaneConfig:
    """Hyper-parameters of the tri-plane hypernetwork field (its input is the latent z of size latent.dim)."""

    resolution: int = 64
    """Side R of each feature plane (texels)."""
    channels: int = 32
    """Channels Cp of each plane."""
    hyper_hidden: tuple[int, ...] = (128, 32)
    """Hidden widths of the hypernetwork z -> planes. The last one is the size of the learned plane basis;
    keep it small, the last layer has ``hyper_hidden[-1] * 3 * channels * resolution**2`` weights."""
    feature_dim: int = 32
    """Size of the dynamic feature f_d produced per Gaussian."""
    mlp_hidden: int = 64
    """Hidden width of the 2-layer MLP from the sampled plane features to f_d."""


def _quantile(x: Tensor, q: float) -> Tensor:
    """Linear-interpolated quantile along dim 0 of ``x`` [N, K] via sort (torch.quantile caps N at 2**24)."""
    xs, _ = torch.sort(x, dim=0)
    pos = q * (x.shape[0] - 1)
    i0 = int(pos)
    i1 = min(i0 + 1, x.shape[0] - 1)
    w = pos - i0
    return xs[i0] * (1.0 - w) + xs[i1] * w


@torch.no_grad()
def robust_bounds(
    points: Float[Tensor, "N 3"], quantile: float = 0.02, margin: float = 0.1
) -> tuple[Float[Tensor, " 3"], Float[Tensor, " 3"]]:
    """Per-axis scene box ``(lo, hi)``: the [quantile, 1 - quantile] range widened by ``margin * extent`` per side.

    Non-finite points are ignored; with no finite point the box is [-1, 1]^3. Each axis is at least
    ``max(MIN_EXTENT * max(1, |centre|), MIN_REL_EXTENT * largest extent)`` wide (widened about its centre). Example: x uniform on [0, 10], q = 0.02, margin = 0.1 gives
    [0.2, 9.8] -> extent 9.6 -> [-0.76, 10.76].
    """
    if points.dim() != 2 or points.shape[-1] != 3:
        raise ValueError(f"expected points [N, 3], got {tuple(points.shape)}")
    if not 0.0 <= quantile < 0.5:
        raise ValueError(f"quantile must be in [0, 0.5), got {quantile}")
    pts = points.detach().float()
    pts = pts[torch.isfinite(pts).all(dim=-1)]
    if pts.shape[0] == 0:
        return -torch.ones(3, device=points.device), torch.ones(3, device=points.device)
    lo = _quantile(pts, quantile)
    hi = _quantile(pts, 1.0 - quantile)
    extent = hi - lo
    lo = lo - margin * extent
    hi = hi + margin * extent
    centre = 0.5 * (lo + hi)
    floor = MIN_EXTENT * max(1.0, float(centre.abs().max()))
    min_extent = max(floor, MIN_REL_EXTENT * float((hi - lo).max()))
    half = 0.5 * (hi - lo).clamp_min(min_extent)
    return centre - half, centre + half


def normalize_points(
    points: Float[Tensor, "N 3"], lo: Float[Tensor, " 3"], hi: Float[Tensor, " 3"]
) -> Float[Tensor, "N 3"]:
    """Map ``points`` to [-1, 1]^3 with ``lo -> -1`` and ``hi -> +1``, clamping points outside the box.

    Differentiable in ``points`` (inside the box). The extent is floored at ``MIN_EXTENT``.
    """
    lo = lo.to(points)
    hi = hi.to(points)
    x = (points - lo) / (hi - lo).clamp_min(MIN_EXTENT) * 2.0 - 1.0
    return x.clamp(-1.0, 1.0)


class TriplaneHyperField(nn.Module):
    """z -> three ``Cp x R x R`` planes (hypernetwork); normalised means -> f_d (bilinear sampling + MLP)."""

    def __init__(
        self,
        latent_dim: int = 64,
        resolution: int = 64,
        channels: int = 32,
        hyper_hidden: Sequence[int] = (128, 32),
        feature_dim: int = 32,
        mlp_hidden: int = 64,
    ):
        super().__init__()
        self.latent_dim = latent_dim
        self.resolution = resolution
        self.channels = channels
        self.feature_dim = feature_dim
        n_out = 3 * channels * resolution * resolution

        layers = []
        d_in = latent_dim
        for h in hyper_hidden:
            layers += [nn.Linear(d_in, h), nn.ReLU()]
            d_in = h
        self.hyper = nn.Sequential(*layers)
        # Last layer without bias: the bias is the explicit `mean_planes` parameter below.
        self.basis = nn.Linear(d_in, n_out, bias=False)
        nn.init.normal_(self.basis.weight, std=0.01 / d_in**0.5)
        self.mean_planes = nn.Parameter(torch.randn(3, channels, resolution, resolution))  # [3, Cp, R, R]

        last = nn.Linear(mlp_hidden, feature_dim)
        nn.init.normal_(last.weight, std=1e-2 / mlp_hidden**0.5)
        nn.init.zeros_(last.bias)
        self.mlp = nn.Sequential(nn.Linear(3 * channels, mlp_hidden), nn.ReLU(), last)

    def planes(self, z: Float[Tensor, " D"]) -> Float[Tensor, "3 Cp R R"]:
        """The three planes (XY, XZ, YZ) for one latent ``z`` [D] (a [1, D] batch of one is accepted)."""
        if z.dim() == 2 and z.shape[0] == 1:
            z = z[0]
        if z.dim() != 1 or z.shape[0] != self.latent_dim:
            raise ValueError(f"expected z [{self.latent_dim}], got {tuple(z.shape)}")
        delta = self.basis(self.hyper(z))  # [3 * Cp * R * R]
        return self.mean_planes + delta.view_as(self.mean_planes)

    def query(self, planes: Float[Tensor, "3 Cp R R"], xyz_norm: Float[Tensor, "N 3"]) -> Float[Tensor, "N F"]:
        """Bilinear samples of ``planes`` at points in [-1, 1]^3 -> MLP -> f_d [N, feature_dim].

        ``grid_sample(align_corners=True)``: -1 and +1 are the centres of the border texels, so the clamped
        box faces sample exactly the border. Differentiable in the planes and in the points.
        """
        n = xyz_norm.shape[0]
        if n == 0:
            return xyz_norm.new_zeros(0, self.feature_dim)
        uv = torch.stack([xyz_norm[:, list(ax)] for ax in PLANE_AXES], dim=0)  # [3, N, 2]
        feats = F.grid_sample(
            planes, uv.unsqueeze(2).to(planes.dtype), mode="bilinear", padding_mode="border", align_corners=True
        )  # [3, Cp, N, 1]
        feats = feats.squeeze(-1).permute(2, 0, 1).reshape(n, 3 * self.channels)  # [N, 3 * Cp]
        return self.mlp(feats)

    def forward(self, z: Float[Tensor, " D"], xyz_norm: Float[Tensor, "N 3"]) -> Float[Tensor, "N F"]:
        """``query(planes(z), xyz_norm)``."""
        return self.query(self.planes(z), xyz_norm)
