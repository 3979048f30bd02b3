"""Does each training photo show what the SfM model says it sees? A pre-training check for photo collections.

A photo of another place filed under a registered frame (a mix-up in a collection, a re-used file name) trains
without any error and pulls the scene apart. The SfM points give a cheap test before training: project a seeded
subset of them into every training image (its own camera, the image read at <= ``max_side`` px), and fit one affine
colour transform per image from the points' median colours (over the images that see them) to the colours the
image has there. A real photo of the scene, whatever its exposure, white balance or time of day, is explained by
such a transform to a fair degree, crowds and night shots included; a photo of another place is not: its pixels at
the projections are unrelated to the points' colours (the fits measured: docs/design.md). No depth test is possible
before training, so points hidden behind static geometry add noise to every image alike: the bound is low.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from willags_ns.data.dataparser import InputWarning

MIN_R2 = 0.05
"""Images whose affine colour fit explains less than this share of the colour variance are reported."""
FOREIGN_PHOTO = "photos whose colours do not follow the SfM points they should show (photos of another place?)"
"""The kind of :func:`foreign_photo_warnings`' warnings."""


def _load(path: Path, max_side: int) -> np.ndarray:
    from PIL import Image

    with Image.open(path) as im:
        im = im.convert("RGB")
        w, h = im.size
        s = min(1.0, max_side / max(w, h))
        if s < 1.0:
            im = im.resize((max(1, round(w * s)), max(1, round(h * s))), Image.Resampling.BILINEAR)
        return np.asarray(im, dtype=np.float32) / 255.0


def point_colours(outputs, max_points: int = 4000, max_side: int = 128, seed: int = 0) -> np.ndarray | None:
    """Colours [I, P, 3] of up to `max_points` SfM points in each training image (NaN where a point projects
    behind the camera or outside the image); None without SfM points."""
    xyz = outputs.metadata.get("points3D_xyz")
    if xyz is None or len(xyz) == 0:
        return None
    xyz = xyz.float()
    if len(xyz) > max_points:
        idx = np.sort(np.random.default_rng(seed).choice(len(xyz), max_points, replace=False))
        xyz = xyz[torch.from_numpy(idx)]
    cams = outputs.cameras
    obs = np.full((len(outputs.image_filenames), len(xyz), 3), np.nan, dtype=np.float32)
    for i, path in enumerate(outputs.image_filenames):
        img = _load(Path(path), max_side)
        h, w = img.shape[:2]
        sx, sy = w / float(cams.width[i]), h / float(cams.height[i])
        c2w = cams.camera_to_worlds[i].float()
        pc = (xyz - c2w[:3, 3]) @ c2w[:3, :3]  # camera frame, OpenGL: -z forward, +y up
        z = -pc[:, 2]
        u = float(cams.cx[i]) * sx + float(cams.fx[i]) * sx * pc[:, 0] / z.clamp_min(1e-6)
        v = float(cams.cy[i]) * sy - float(cams.fy[i]) * sy * pc[:, 1] / z.clamp_min(1e-6)
        ok = ((z > 1e-3) & (u >= 0) & (u <= w - 1) & (v >= 0) & (v <= h - 1)).numpy()
        obs[i, ok] = img[v.numpy()[ok].round().astype(int), u.numpy()[ok].round().astype(int)]
    return obs


def colour_fit_r2(obs: np.ndarray, min_views: int = 3, min_points: int = 30) -> np.ndarray:
    """Per image, R^2 of the affine colour fit (3x3 + offset, least squares) from the points' median colours to the
    image's colours at them; NaN where too few points are seen or the image has no colour variance there."""
    seen = ~np.isnan(obs[..., 0])
    keep = seen.sum(0) >= min_views
    obs, seen = obs[:, keep], seen[:, keep]
    r2 = np.full(obs.shape[0], np.nan)
    if obs.shape[1] == 0:
        return r2
    ref = np.nanmedian(obs, axis=0)
    for i in range(obs.shape[0]):
        m = seen[i]
        if m.sum() < min_points:
            continue
        X = np.concatenate([ref[m], np.ones((int(m.sum()), 1), np.float32)], 1)
        Y = obs[i, m]
        total = float(((Y - Y.mean(0)) ** 2).sum())
        if total < 1e-6 * m.sum():  # a flat image (all black / white): nothing to judge
            continue
        coef, *_ = np.linalg.lstsq(X, Y, rcond=None)
        r2[i] = 1.0 - float(((Y - X @ coef) ** 2).sum()) / total
    return r2


def foreign_photo_warnings(outputs, min_r2: float = MIN_R2, max_images: int = 2000) -> list[InputWarning]:
    """One warning per training image that does not look like what the SfM points say it sees (see the module
    docstring). Skipped (no warnings) without SfM points, with fewer than 4 images or more than `max_images`."""
    n = len(outputs.image_filenames)
    if n < 4 or n > max_images:
        return []
    obs = point_colours(outputs)
    if obs is None:
        return []
    r2 = colour_fit_r2(obs)
    return [
        InputWarning(
            f"{outputs.image_filenames[i]}: its colours do not follow the SfM points it should show (colour-fit R^2 "
            f"{r2[i]:.3f} < {min_r2}); is it a photo of another place under this frame? If so, remove it",
            FOREIGN_PHOTO,
            Path(outputs.image_filenames[i]).name,
        )
        for i in range(n)
        if np.isfinite(r2[i]) and r2[i] < min_r2
    ]
