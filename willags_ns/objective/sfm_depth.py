"""The SfM depth loss: the render's expected depth held to the depths of the photo's own SfM points.

A COLMAP scene comes with, in every training photo, the pixels where a triangulated 3D point was matched
(data/sfm_tracks.py). Such a point is static and its depth in that photo is known: the distance along the optical
axis that the photos agreeing on it fixed. The photometric loss alone lets a novel view's geometry drift wherever the
training photos do not constrain it (few photos, or a crowd in front of the facade in most of them): Gaussians that
fit one photo's colours at the wrong depth show as floaters from another viewpoint, which is what the NeRF-W protocol's
held-out photos look from. The loss samples the rendered expected depth at those pixels and pays the absolute
difference of log depths (scale-free: a near and a far point weigh alike), where the render is opaque enough for its
expected depth to mean a surface.

Pure functions: :func:`sample_at` (a map at normalised pixel positions), :func:`select_observations` (once per
photo), :func:`sfm_depth_loss`.
"""

from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import Tensor


@dataclass
class SfmDepthConfig:
    """The SfM depth loss (COLMAP scenes; nothing on a scene without SfM keypoints)."""

    weight: float = 0.0
    """Weight of the mean |log rendered depth - log SfM depth| over the training photo's observations in the loss
    (0 = off: the render's depth is then not even computed while training)."""
    min_track: int = 3
    """Only points that at least this many training photos matched: a point of two photos can be a chance match, one
    of three or more is the static scene."""
    min_alpha: float = 0.5
    """Only pixels whose accumulated opacity reaches this: below it the expected depth is an average over too little
    to be a surface (the sky, a gap)."""


def sample_at(image: Tensor, uv: Tensor) -> Tensor:
    """Bilinear samples [n, C] of `image` [H, W, C] at `uv` [n, 2] (x right, y down, in [0, 1] of the image's width
    and height; pixel centres at (i + 0.5) / size, as COLMAP's keypoints are)."""
    grid = (uv * 2.0 - 1.0).to(image.dtype)[None, None]  # [1, 1, n, 2]
    out = F.grid_sample(image.permute(2, 0, 1)[None], grid, mode="bilinear", align_corners=False)
    return out[0, :, 0].transpose(0, 1)


def select_observations(obs: Tensor, target: Tensor, cfg: SfmDepthConfig) -> tuple[Tensor, Tensor]:
    """(uv [m, 2], depth [m]) of the observations a photo's loss uses, from its `obs` [n, 3] = (u, v, track length)
    and their depths `target` [n] (NaN: unknown): inside the image, track >= cfg.min_track, a finite positive depth.
    Done once per photo; the loss itself reads nothing back from the device."""
    uv, track = obs[:, :2], obs[:, 2]
    inside = (uv >= 0).all(1) & (uv < 1).all(1)
    ok = inside & (track >= cfg.min_track) & torch.isfinite(target) & (target > 0)
    return uv[ok], target[ok]


def sfm_depth_loss(
    depth: Tensor, alpha: Tensor, uv: Tensor, target: Tensor, cfg: SfmDepthConfig
) -> tuple[Tensor, Tensor]:
    """(loss, observations used) of one training render: the mean of |log d - log target| over the observations at
    `uv` [m, 2] (select_observations) whose pixel reaches alpha >= cfg.min_alpha, 0 when none does (unweighted:
    cfg.weight is the caller's). `depth` [H, W, 1]: the expected depth (accumulated z / alpha); `alpha` [H, W, 1];
    `target` [m]: the observations' depths in the render's units."""
    a = sample_at(alpha.detach(), uv)[:, 0]
    d = sample_at(depth, uv)[:, 0]
    use = (a >= cfg.min_alpha) & (d > 0)
    err = (torch.log(torch.where(use, d, torch.ones_like(d))) - torch.log(target.to(d.dtype))).abs()
    n = use.sum()
    return (err * use).sum() / n.clamp_min(1), n
