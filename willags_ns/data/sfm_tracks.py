"""SfM observations of the training images: where, in each training photo, COLMAP found a keypoint of a 3D point,
and how many training photos see that point (its track length over the training split).

A 3D point that several photos matched and triangulated consistently is static by construction: a person, a car or a
cloud moves between photos and does not give the same feature at one 3D position in five images. Its observations
are therefore ground truth for "this pixel of this photo shows the static scene", available for every COLMAP scene
without any labelling. The transient mask's safeguard (willags_ns/mask/static_support.py) and the "static observations
masked" measurement (benchmarks) read them.

Only the training split counts: a test photo's keypoints never reach training (not even through a track length).
Coordinates are normalised to [0, 1] by the COLMAP camera's size, so they hold at any image resolution (the
resolution schedule, a downscale factor). Lens distortion is ignored: the parsers undistort the images, which moves a
keypoint by a few pixels at most, below the coarse grid the safeguard works on.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from jaxtyping import Bool, Float
from torch import Tensor

from willags_ns.data.colmap import read_colmap_model
from willags_ns.tensor_constants import as_dtype

SFM_OBSERVATIONS_KEY = "sfm_observations"
"""DataparserOutputs.metadata key: a list (one entry per training image, in image order) of float32 arrays [n, 3]
holding (u, v, track length over the training images), u and v in [0, 1] (x right, y down)."""


SFM_DEPTHS_KEY = "sfm_depths"
"""DataparserOutputs.metadata key: a callable without arguments returning a list (one entry per training image,
aligned with SFM_OBSERVATIONS_KEY's rows) of float32 arrays [n]: each observation's 3D point's depth along that
photo's optical axis, in the dataparser's scaled units (NaN where the point is missing from the model or lies behind
the camera). A callable, so that the points file is read only by the one that uses the depths (the SfM depth loss,
objective/sfm_depth.py), not at every start of a run without it."""


def read_observations(model: Path) -> dict[str, tuple[np.ndarray, np.ndarray, tuple[int, int]]]:
    """{image name: (xy [n, 2] pixels, point3D ids [n], (width, height) of its camera)} for every registered image of
    the COLMAP model in `model` (.bin or .txt), keypoints without a 3D point left out."""
    colmap = read_colmap_model(model)
    cams, ims = colmap.cameras, colmap.images
    out = {}
    for im in ims.values():
        ids = np.asarray(im.point3D_ids, dtype=np.int64).reshape(-1)
        xy = np.asarray(im.xys, dtype=np.float64).reshape(-1, 2)
        keep = ids >= 0
        cam = cams[im.camera_id]
        out[im.name] = (xy[keep], ids[keep], (int(cam.width), int(cam.height)))
    return out


def train_observations(
    observations: dict[str, tuple[np.ndarray, np.ndarray, tuple[int, int]]], train_names: list[str]
) -> list[np.ndarray]:
    """One float32 array [n, 3] (u, v, track length over `train_names`) per name of `train_names`, in that order.

    The track length counts the training images whose keypoints see the point (a name missing from the model
    contributes nothing and gets an empty array)."""
    present = [observations.get(n) for n in train_names]
    # distinct images per point: a point can hold two keypoints of one photo (a merged track)
    all_ids = [np.unique(o[1]) for o in present if o is not None and len(o[1])]
    if all_ids:
        ids = np.concatenate(all_ids)
        uniq, counts = np.unique(ids, return_counts=True)
    else:
        uniq, counts = np.zeros(0, np.int64), np.zeros(0, np.int64)
    out = []
    for o in present:
        if o is None or not len(o[1]):
            out.append(np.zeros((0, 3), np.float32))
            continue
        xy, ids, (w, h) = o
        track = counts[np.searchsorted(uniq, ids)]
        uv = xy / np.asarray([w, h], dtype=np.float64)
        out.append(np.concatenate([uv, track[:, None]], axis=1).astype(np.float32))
    return out


def train_observation_depths(model: Path, train_names: list[str], scale: float) -> list[np.ndarray]:
    """One float32 array [n] per name of `train_names`, aligned with `train_observations`' rows for that name (the
    keypoints with a 3D point, in the model's order): the point's depth along the photo's optical axis (COLMAP's
    camera z of R X + t), times `scale` (the dataparser's scale of the scene: rotations and translations of the
    scene leave a depth unchanged, its scale multiplies it). NaN for a point missing from the model's points3D file
    or not in front of the camera; a name missing from the model gets an empty array."""
    from nerfstudio.data.utils import colmap_parsing_utils as cpu

    colmap = read_colmap_model(model, points=True)
    pts = colmap.points or {}
    by_name = {im.name: im for im in colmap.images.values()}
    out = []
    for name in train_names:
        im = by_name.get(name)
        if im is None:
            out.append(np.zeros(0, np.float32))
            continue
        ids = np.asarray(im.point3D_ids, dtype=np.int64).reshape(-1)
        ids = ids[ids >= 0]
        xyz = np.full((len(ids), 3), np.nan)
        for j, i in enumerate(ids):
            p = pts.get(int(i))
            if p is not None:
                xyz[j] = p.xyz
        rot = cpu.qvec2rotmat(im.qvec)  # world to camera, as nerfstudio's COLMAP parser reads it
        z = xyz @ rot[2] + float(np.asarray(im.tvec, dtype=np.float64)[2])
        z = np.where(z > 0, z * float(scale), np.nan)
        out.append(z.astype(np.float32))
    return out


# the observations on a coarse grid of each image: the mask's safeguard (mask/static_support.py) and the sky's
# open background (appearance/sky.py)


def grid_shape(width: int, height: int, grid: int) -> tuple[int, int]:
    """(rows, cols) of the support grid of a width x height image: `grid` cells along the longer side."""
    if width >= height:
        return max(1, round(grid * height / width)), grid
    return grid, max(1, round(grid * width / height))


def cell_counts(obs: np.ndarray, rows: int, cols: int, min_track: float = 0) -> Tensor:
    """[rows, cols] counts of the observations `obs` [n, 3] = (u, v, track length) with track >= `min_track` that
    fall inside the image, on a rows x cols grid."""
    counts = torch.zeros(rows, cols)
    if not len(obs):
        return counts
    o = torch.as_tensor(obs, dtype=torch.float32)
    o = o[(o[:, 2] >= min_track) & (o[:, 0] >= 0) & (o[:, 0] < 1) & (o[:, 1] >= 0) & (o[:, 1] < 1)]
    r = (o[:, 1] * rows).long().clamp_(0, rows - 1)
    c = (o[:, 0] * cols).long().clamp_(0, cols - 1)
    return counts.view(-1).index_add_(0, r * cols + c, torch.ones(len(o))).view(rows, cols)


def support_at(
    support: Bool[Tensor, "rows cols"] | Float[Tensor, "rows cols"], height: int, width: int
) -> Bool[Tensor, "H W"]:
    """The support map (bool, or float with 1 = supported) at an image resolution (nearest cell)."""
    return F.interpolate(as_dtype(support, torch.float32)[None, None], size=(height, width), mode="nearest")[0, 0] > 0.5


def open_background_map(obs: np.ndarray, width: int, height: int, grid: int = 32) -> Bool[Tensor, "rows cols"]:
    """Cells [rows, cols] of one image above the scene's skyline: in each column, the cells above the first cell
    that an SfM observation covers (any track length; covered cells dilated by one). A column without any covered
    cell takes the median skyline of the others; an image without observations has no open cells.

    What hangs above everything SfM reconstructed is open sky or far background. A textureless plaza, a lawn or a
    crowd below the horizon has no points either, but it lies under the scene's covered cells in its column and is
    not open. The sky's region option (appearance/sky.py) composites the learnt sky only here while training,
    keeping splatfacto's random background (which forces the Gaussians to be opaque) everywhere else."""
    rows, cols = grid_shape(width, height, grid)
    covered = (cell_counts(obs, rows, cols) > 0).float()
    covered = F.max_pool2d(covered[None, None], 3, stride=1, padding=1)[0, 0] > 0
    has = covered.any(dim=0)  # [cols]
    if not bool(has.any()):
        return torch.zeros(rows, cols, dtype=torch.bool)
    top = covered.float().argmax(dim=0)  # first covered row of each column
    top = torch.where(has, top, top[has].median())
    return torch.arange(rows)[:, None] < top[None, :]
