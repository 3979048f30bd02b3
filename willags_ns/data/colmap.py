"""Reading a COLMAP scene: where its model and its images are, and the model itself, in one place.

The data parser (its checks), the SfM observations of the mask's safeguard and the sky (sfm_tracks.py),
willags-inspect and the benchmarks' folds all read COLMAP scenes through these functions: the same folders are
looked in, binary or text models are read alike, and a model that cannot be read raises one error naming it.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

COLMAP_MODEL_DIRS = ("colmap/sparse/0", "sparse/0", "sparse", "dense/sparse")
"""Where a COLMAP model is looked for, in this order (relative to the scene's folder)."""


class ColmapModelError(ValueError):
    """A COLMAP model that cannot be read; the message names its folder and why."""


@dataclass(frozen=True)
class ColmapModel:
    """A COLMAP model as nerfstudio's readers return it (colmap_parsing_utils' records, by id)."""

    path: Path
    """The model's folder."""
    cameras: dict[int, Any]
    images: dict[int, Any]
    points: dict[int, Any] | None
    """The 3D points, None when they were not asked for or the model has none."""


def find_colmap_model(root: Path, colmap_path: Path | None = None) -> Path | None:
    """The COLMAP model directory under `root` (`colmap_path` if given, else the first of `COLMAP_MODEL_DIRS` holding
    cameras and images files), or None."""
    candidates = [colmap_path] if colmap_path is not None else [Path(c) for c in COLMAP_MODEL_DIRS]
    for rel in candidates:
        d = root / rel
        has_cams = (d / "cameras.bin").is_file() or (d / "cameras.txt").is_file()
        has_imgs = (d / "images.bin").is_file() or (d / "images.txt").is_file()
        if has_cams and has_imgs:
            return d
    return None


def colmap_images_path(root: Path, images_path: Path = Path("images")) -> Path:
    """The scene's image folder relative to `root`: `images_path`, or `dense/images` (COLMAP's undistorted output)
    when only that exists."""
    if not (root / images_path).is_dir() and (root / "dense" / "images").is_dir():
        return Path("dense/images")
    return Path(images_path)


def read_colmap_model(model: Path, points: bool = False) -> ColmapModel:
    """The cameras and images (and with `points` the 3D points, where the file exists) of the COLMAP model in
    `model`, binary or text. ColmapModelError names the folder when a file cannot be read."""
    from nerfstudio.data.utils import colmap_parsing_utils as cpu

    model = Path(model)
    ext = ".bin" if (model / "images.bin").is_file() else ".txt"
    binary = ext == ".bin"
    try:
        cameras = (cpu.read_cameras_binary if binary else cpu.read_cameras_text)(model / f"cameras{ext}")
        images = (cpu.read_images_binary if binary else cpu.read_images_text)(model / f"images{ext}")
        pts = None
        if points and (model / f"points3D{ext}").is_file():
            pts = (cpu.read_points3D_binary if binary else cpu.read_points3D_text)(model / f"points3D{ext}")
    except Exception as e:  # the readers raise assorted errors (struct, KeyError, ValueError) on bad files
        raise ColmapModelError(f"cannot read the COLMAP model in {model}: {type(e).__name__}: {e}") from None
    return ColmapModel(model, cameras, images, pts)
