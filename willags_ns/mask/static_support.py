"""The transient mask's safeguard: what SfM tracks vouch for is static and is never masked.

The perceptual mask (willags_ns/mask/transient.py) flags pixels where the photo and the EMA teacher's render differ in
VGG features. That is right for an occluder, and wrong wherever the model has not (yet) reconstructed the static
scene: a subject seen against the sky that the Gaussians lose, a tree whose fine texture the teacher blurs, window
panes that reflect a different sky in every photo. Masked, such a region is never supervised and never gets better:
the mask confirms its own error.

The principle: a 3D point that at least ``min_track`` training photos matched and triangulated at one position is
static (a transient does not produce one consistent feature in five photos), so the pixels around its observations
in each of those photos show static scene. Per training image the observations of such points
(willags_ns/data/sfm_tracks.py) are counted on a coarse grid; a cell is *supported* when the cells within
``radius_cells`` of it hold at least ``min_observations`` such observations, and a supported pixel stays in the loss
whatever the perceptual mask says. Requiring several observations keeps an isolated keypoint (a point that happens to
lie on a person's edge, a mismatched track) from unmasking an occluder; the window keeps the support region coherent
at the scale of the mask itself (relu3_3's receptive field is ~40 px).

Where there are no tracks (a transforms.json scene, the synthetic scene) there is no support and the mask is the
perceptual mask alone. Pure functions and one config; MaskStep holds the maps (willags_ns/mask/step.py).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch.nn.functional as F
from jaxtyping import Bool
from torch import Tensor

from willags_ns.data.sfm_tracks import cell_counts, grid_shape, support_at


@dataclass
class StaticSupportConfig:
    """SfM-track support that overrides the perceptual mask."""

    enabled: bool = True
    """Keep pixels supported by long SfM tracks in the loss whatever the perceptual mask says (COLMAP scenes; no
    effect without tracks). Off in the paper's configuration."""
    min_track: int = 5
    """A 3D point vouches for static scene when at least this many training images observe it."""
    grid: int = 64
    """Cells along the image's longer side (800 px photos: 12.5 px cells)."""
    radius_cells: int = 1
    """A cell is supported by the observations in the (2r+1)^2 cells around it."""
    min_observations: int = 3
    """... when those cells hold at least this many observations of long-track points."""


def support_map(obs: np.ndarray, width: int, height: int, cfg: StaticSupportConfig) -> Bool[Tensor, "rows cols"]:
    """Supported cells [rows, cols] of one image from its observations `obs` [n, 3] = (u, v, track length)."""
    counts = cell_counts(obs, *grid_shape(width, height, cfg.grid), cfg.min_track)
    k = 2 * cfg.radius_cells + 1
    window = F.avg_pool2d(counts[None, None], k, stride=1, padding=cfg.radius_cells, count_include_pad=True)
    return (window[0, 0] * k * k + 0.5).floor() >= cfg.min_observations


def apply_support(static: Bool[Tensor, "H W"], support: Bool[Tensor, "rows cols"] | None) -> Bool[Tensor, "H W"]:
    """The static mask (True = supervised) with every supported pixel kept."""
    if support is None:
        return static
    return static | support_at(support.to(static.device), *static.shape)


def observations_masked(static: Bool[Tensor, "H W"], obs: np.ndarray, min_track: int) -> tuple[int, int]:
    """(observations of points with track >= min_track that the mask flags as transient, all such observations) in
    one image: the "static observations masked" measurement (0 is right: each of them shows static scene)."""
    o = obs[obs[:, 2] >= min_track] if len(obs) else obs
    if not len(o):
        return 0, 0
    H, W = static.shape
    y = np.clip((o[:, 1] * H).astype(np.int64), 0, H - 1)
    x = np.clip((o[:, 0] * W).astype(np.int64), 0, W - 1)
    flagged = ~static.cpu().numpy()[y, x]
    return int(flagged.sum()), len(o)


def masked_share(pairs: list[tuple[int, int]]) -> float | None:
    """Share of observations flagged over (flagged, total) pairs, or None when there are none."""
    total = sum(t for _, t in pairs)
    return None if total == 0 else sum(f for f, _ in pairs) / total
