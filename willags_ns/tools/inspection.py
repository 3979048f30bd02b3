"""`willags-inspect`: look at a scene BEFORE training and say which parts of WilLaGS it needs.

It reads the scenes `willags-data` reads (a nerfstudio `transforms.json` scene with an optional `ply_file_path`, or a
COLMAP scene under `colmap/sparse/0`, `sparse/0`, `sparse` or `dense/sparse`, optionally with a NeRF-W `*.tsv`
split), measures four things on CPU in seconds, and turns them into a recommendation with its reasons.

Evidence 1, appearance variation (`appearance_score`, 8-bit colour levels). The SfM points are the scene's shared
ground truth: a static point has one colour, so what differs between the images that see it is the photograph, not
the scene. Every point is projected into every image that sees it (in the frustum, in front of the camera, not behind a nearer point
in a coarse point z-buffer of `zbuffer_cell` px cells; for COLMAP scenes also only from a direction within
`max_view_angle_deg` of a camera of its track), and the image's colour is sampled there (3x3 box filter, images downscaled to `max_side`). Each
point gets a reference colour m_p (the median over the images that see it) and each image i a per-channel affine
transform c_ip ~= a_i m_p + b_i, fitted robustly (start from the pure gain, then rounds of least squares without the residuals beyond 2.5 MADs);
then the references are recomputed from the images' colours with their transforms undone, and the transforms
re-fitted (`iterations` rounds). An image's appearance change is the mean, over its points and channels, of
|a_i m_p + b_i - m_p| (how far its global transform moves the scene's colours), in 8-bit levels; the scene's score is
the median over images. Why a per-image affine transform: exposure, white balance and most of a camera's tone curve
are (nearly) per-image global colour transforms, which is what the latent of WilLaGS models first; content (people,
cars, view-dependent highlights) is not, and robust fitting keeps it out of the transform.

Evidence 2, transients (`transient_score`, a share of images). With every image's transform undone, the colour of
a point should agree across the images that see it. An observation is an outlier when its RMS colour distance to the
point's median colour exceeds `outlier_floor` (0.2, ~51 levels; optionally also `outlier_k` MADs of the point). An
outlier is a *transient* observation only when it also disagrees (same limit) with each of the `neighbours` nearest
cameras (by centre) that see the point: parallax, visibility errors the z-buffer misses and view-dependent colour are
shared by nearby views, an occluder in one photo is not (without this test fox-clean's top-down views, where the
wall hides behind the fox, scored like the occluded scenes). Nor does it count an outlier whose raw colour
another analysed photo repeats (`twin_tolerance`): light that no per-image transform undoes (a statue's sunlit and
shaded sides, an evening's golden face) recurs in the photos taken under it, an occluder differs from photo to
photo. An image is occluded when at least
`image_transient_level` (5%) of its observations are transient; the score is the share of occluded images. It cannot
see occluders that sit where there are no SfM points (people in front of a facade's base, sky) nor occluders that
recur at the same place in nearby views.

Without SfM points (a transforms.json scene without a ply), the fallback is honest but weaker: per-image global
colour statistics of images downscaled to 64 px (the spread across images of each image's mean colour, 8-bit
levels, median over channels): it mixes appearance with content (different views show different things), so its
threshold is separate, and transients are not measured (`transient_score` is None).

Evidence 3, scene facts: image count (and how many the analysis used), resolutions, scene extent (the diagonal of the
5-95 percentile box of the points and of the camera centres, in the scene's units) and a rough resource estimate
(`resource_estimate`): Gaussians ~ `gaussians_per_point` x points (clipped), GPU memory = a fixed part (CUDA
context, VGG for the mask) + images cached as uint8 + a share per Gaussian (59 parameters with Adam's two moments,
gradients and the rasteriser's buffers), the GPU and CPU step times of a measured scene scaled by pixels per image
(`GPU_STEP_S`, `CPU_STEP_S`; their measurements: docs/design.md). Rough estimates: step time also grows with the
Gaussian count, not modelled.

Evidence 4, open background (`background_score`, a share of the image area). Tourist photos are largely sky, and
the sky's colour changes with the photo (sun, overcast, dusk); SfM finds no points in the sky (no texture, nothing
static to match), so the part of a photo that no SfM point covers is sky or far / textureless background, which the
Gaussians would otherwise have to paint, one photo's sky at a time. Every SfM point of the scene (all of them, no
visibility test: a hidden point still shows there is geometry along its ray) is projected into each analysed image
with its camera (points whose pinhole projection lies more than half the image size outside it are dropped: a
distortion polynomial can fold them back in); the cells of a coarse grid (`background_grid` cells along the long
side) that hold a point are marked and dilated by one cell, so the gaps between the points of a textured surface do
not count; the uncovered share of the cells is the image's `background_fraction`, and the scene's score is the median
over the analysed images (the mean and the per-image values are reported too). It also counts what SfM misses below
the horizon: a textureless plaza, crowds (on reichstag about half of the uncovered area lies in the lower half of the
image, docs/inspect.md). Where the subject stands against the sky matters too (`surround_score`): per image,
the share of its covered cells that have open background connected to the image's top on both sides in their row
(`surround_fraction`), median over the images: a statue or a tower seen against the sky scores high, a building under
the sky (open background above its roofline only) low. What is uncovered but not reached from the top (`ground_score`:
per image the share of cells uncovered and enclosed by covered ones from above, `enclosed_fraction`, median over the
images) is ground SfM did not reconstruct under the subject: a plaza where crowds stand (docs/inspect.md gives each
shared scene's). It is measured and printed, and it does not switch anything: the transient
score does not see crowds where SfM has no points, and whether this does is for collections it was not found on to
say. At or above `ground_hint_threshold`, with the mask off, the mask's reason suggests trying it. Without SfM points
none of these is measured (None).

The recommendation (see `recommend`): appearance latent on when appearance_score >= `appearance_threshold`; mask (with
its EMA teacher) on when transient_score >= `transient_threshold`; tri-plane field always off (measured: it did not
help, docs/benchmarks.md); the appearance-conditioned sky (appearance/sky.py) on when background_score >=
`sky_threshold`, in one of two modes (`SKY_MODES`): above each photo's skyline, or behind every pixel with the alpha
penalty where surround_score >= `surround_threshold` (kept as the method's own setting when not measured; never with
plain 3DGS, which has no latent to condition it on); the latent size; and the preset, each with a sentence quoting
the number and threshold.
The thresholds come from the measurements on the shared scenes and synthetic scenes in docs/inspect.md.
"""

from __future__ import annotations

import json
import math
import warnings
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from PIL import Image

IMAGE_EXTS = (".jpg", ".jpeg", ".png", ".JPG", ".JPEG", ".PNG")


class InspectError(ValueError):
    """Unusable input; the message names the path at fault (the CLI prints it on one line)."""


@dataclass
class InspectConfig:
    """Options of `willags-inspect` (defaults: about a minute or less on 2 CPU cores for the shared scenes)."""

    data: Path = Path(".")
    """Scene directory: a transforms.json scene (or the json file) or a COLMAP scene (colmap/sparse/0, sparse/0,
    sparse or dense/sparse; a NeRF-W *.tsv split is honoured)."""
    output: Path | None = None
    """Write the evidence and the recommendation to this JSON file."""
    split: str = "train"
    """Which images to analyse: 'train' (the images training sees, when the scene names a split) or 'all'."""
    max_images: int = 120
    """Analyse at most this many images (evenly spaced), to bound the time."""
    downscale_factor: int | None = None
    """The factor training reads the photos at (1/N of their sides) for the time and memory estimate: ns-train's
    `--pipeline.datamanager.dataparser.downscale-factor`. None: the factor training resolves by itself (the largest
    side brought to at most 1600 px, as willags' data parser does)."""
    max_points: int = 20000
    """Use at most this many SfM points (a seeded random subset)."""
    max_side: int = 400
    """Images are downscaled so that their longest side is at most this many pixels before sampling."""
    max_view_angle_deg: float = 30.0
    """COLMAP scenes: an image sees a point only from within this angle of one of the point's track cameras."""
    zbuffer_cell: int = 8
    """Visibility: cell size (pixels of the downscaled image) of the coarse point z-buffer."""
    zbuffer_tolerance: float = 0.1
    """Visibility: a point is hidden when it is more than this fraction deeper than its cell's nearest point."""
    neighbours: int = 3
    """Transients: an outlier observation counts only when it also disagrees with each of this many nearest cameras
    that see the point."""
    min_views: int = 3
    """A point is used only when at least this many analysed images see it."""
    iterations: int = 2
    """Rounds of (reference colours, per-image transforms)."""
    outlier_k: float = 0.0
    """An observation is an outlier beyond this many robust standard deviations (1.4826 MAD) of its point's
    observations (0: the fixed limit below alone, the default: per-point MADs grow with residual appearance change
    and hid the occluders of fox-wild)."""
    outlier_floor: float = 0.2
    """... and beyond this colour distance (RMS over channels, colours in [0, 1]; 0.2 ~ 51 levels)."""
    twin_tolerance: float = 0.1
    """Transients: an outlier observation whose raw colour (no transform undone) another analysed photo of the same
    point repeats within this RMS distance is not counted (0: off). Light that a per-image colour transform cannot
    undo (the sunlit and the shaded side of a statue, a golden evening on one face) recurs in other photos taken
    under similar light; an occluder in front of a point differs from photo to photo. Without this test a
    collection photographed under directional light reads as occluded where none of its photos shows an occluder
    (docs/inspect.md)."""
    image_transient_level: float = 0.05
    """An image counts as occluded when at least this fraction of its observations are transient."""
    appearance_threshold: float = 4.0
    """appearance_score (8-bit levels) at or above which the appearance latent is recommended (SfM evidence). Low on
    purpose: the per-image latent costs little, and it helps even on a phone video's exposure drift (fox-clean);
    scenes rendered without any appearance change score well below it (docs/inspect.md)."""
    fallback_appearance_threshold: float = 12.0
    """The same threshold for the no-points fallback evidence (spread of per-image mean colours, 8-bit levels)."""
    transient_threshold: float = 0.12
    """transient_score (share of occluded images) at or above which the transient mask (and its teacher) is
    recommended. Decided on the shared scenes at once, 2 seeds each (docs/inspect.md gives each scene's score and
    what the mask costs or wins there): it lies between the highest score of a scene where the mask was level or
    cost, and the lowest where it helped."""
    background_grid: int = 32
    """Open background: cells of the coverage grid along the image's long side (32: cells of 1/32 of it, 25 px at
    800 px; one cell of dilation then bridges gaps of up to ~50 px between neighbouring points)."""
    sky_threshold: float = 0.15
    """background_score (median share of an image that no SfM point covers) at or above which the
    appearance-conditioned sky is recommended: between the scenes without sky (a close-up of an object, a facade
    filling the frame) and the Internet photo collections (docs/inspect.md gives each scene's score); it separates
    the two groups with a grid of 16 or 64 cells too."""
    surround_threshold: float = 0.6
    """surround_score (median share of the covered cells of an image with open background on both sides in their
    row) at or above which the sky is composited behind every pixel with the alpha penalty (sky mode "surround")
    instead of only above the skyline: the subject stands against the sky (a statue, a tower), so the sky shows
    beside it as well as above it, where the skyline region never reaches, and Gaussians floating in that sky show
    in every new view. A building seen against the sky only above its roofline measures far less (docs/inspect.md
    gives every shared scene's value)."""
    ground_hint_threshold: float = 0.1
    """ground_score (median share of an image uncovered by SfM and enclosed from above: ground under the subject) at
    or above which the mask's reason, when the mask stays off, adds a hint to try it. Crowds stand where SfM has no
    points, so the transient score cannot see them; on the one shared collection above this (reichstag) the mask won,
    while the collections below it scored level or lost with it (docs/inspect.md, "Ground under the subject"). A hint,
    not a switch: one collection is too few to set a default by."""
    gaussians_per_point: float = 10.0
    """Resource estimate: expected final Gaussians per SfM point (clipped to [1e5, 1.5e6])."""
    max_gaussians: int = 300_000
    """Resource estimate: the most Gaussians the default grows (its MCMC densification's mcmc.cap_max; kept here so
    that the inspector starts without importing torch, and checked against it by the tests)."""
    steps: int = 30000
    """Resource estimate: training steps (the willags preset's 30k)."""
    seed: int = 0
    """Seed of the point subset."""


@dataclass
class SceneViews:
    """What the analysis reads from a scene. N images, P points; cameras in OpenCV convention (x right, y down, z in)."""

    kind: str
    """'transforms' or 'colmap'."""
    root: Path
    """The scene directory."""
    image_paths: list[Path]
    """[N] image files."""
    w2c: np.ndarray | None
    """[N, 3, 4] world-to-camera (OpenCV), or None when the scene has no poses."""
    K: np.ndarray | None
    """[N, 3, 3] intrinsics in the pixel units of `cam_size`."""
    dist: np.ndarray | None
    """[N, 4] OpenCV distortion k1, k2, p1, p2 (zeros when none)."""
    cam_size: np.ndarray | None
    """[N, 2] (width, height) the intrinsics refer to."""
    points: np.ndarray | None
    """[P, 3] SfM points, or None."""
    tracks: list[np.ndarray] | None = None
    """COLMAP: [P] indices (into image_paths) of the images in each point's track."""
    split: list[str] = field(default_factory=list)
    """[N] 'train' / 'test' / '' (unknown)."""
    total_images: int = 0
    """Images in the scene before the split / max_images selection."""


# --------------------------------------------------------------------------------------------------------------------
# reading scenes


def _posed_views(
    kind: str,
    root: Path,
    paths: list[Path],
    cameras: tuple[list, list, list, list],
    points: np.ndarray | None,
    split: list[str],
    tracks: list[np.ndarray] | None = None,
) -> SceneViews:
    """SceneViews of every image in `paths`, from per-image lists `cameras` = (w2c [3, 4], K [3, 3], distortion [4],
    (width, height))."""
    w2c, Ks, dists, sizes = cameras
    return SceneViews(
        kind=kind,
        root=root,
        image_paths=paths,
        w2c=np.asarray(w2c),
        K=np.asarray(Ks, dtype=np.float64),
        dist=np.asarray(dists, dtype=np.float64),
        cam_size=np.asarray(sizes, dtype=np.float64),
        points=points,
        tracks=tracks,
        split=split,
        total_images=len(paths),
    )


def _tsv_split(root: Path, names: list[str]) -> list[str]:
    from willags_ns.data.dataparser import WillagsDataError, read_split_tsv

    tsvs = sorted(root.glob("*.tsv"))
    if len(tsvs) != 1:
        return [""] * len(names)
    try:
        table = read_split_tsv(tsvs[0])
    except WillagsDataError as e:
        raise InspectError(str(e)) from None
    return [table.get(n, table.get(Path(n).name, "")) for n in names]


def read_transforms_scene(root: Path, tf_path: Path) -> SceneViews:
    """A nerfstudio transforms.json scene: OpenGL camera-to-world poses, shared or per-frame intrinsics, an optional
    ply (in the poses' coordinates, as nerfstudio reads it) and an optional explicit split."""
    from willags_ns.data.dataparser import WillagsDataError, read_ply_points

    try:
        meta = json.loads(tf_path.read_text())
        frames = meta["frames"]
    except (OSError, ValueError, KeyError, TypeError) as e:
        raise InspectError(f"cannot read {tf_path}: {e!r}") from None
    if not frames:
        raise InspectError(f"{tf_path} lists no frames")
    paths, w2c, Ks, dists, sizes = [], [], [], [], []
    for k, fr in enumerate(frames):
        get = lambda key, fr=fr: fr.get(key, meta.get(key))  # noqa: E731
        try:
            c2w = np.asarray(fr["transform_matrix"], dtype=np.float64)[:4, :4]
            fx, fy, cx, cy = (float(get(x)) for x in ("fl_x", "fl_y", "cx", "cy"))
            w, h = int(get("w")), int(get("h"))
        except (KeyError, TypeError, ValueError) as e:
            raise InspectError(f"{tf_path}: frame {k} lacks a pose or intrinsics ({e!r})") from None
        c2w = c2w.copy()
        c2w[:3, 1:3] *= -1  # OpenGL -> OpenCV
        inv = np.linalg.inv(c2w)
        paths.append(root / fr["file_path"])
        w2c.append(inv[:3])
        Ks.append([[fx, 0, cx], [0, fy, cy], [0, 0, 1]])
        dists.append([float(get(x) or 0.0) for x in ("k1", "k2", "p1", "p2")])
        sizes.append([w, h])
    names = [str(Path(fr["file_path"])) for fr in frames]
    split = [""] * len(frames)
    if "train_filenames" in meta:
        train = {str(Path(n)) for n in meta["train_filenames"]}
        split = ["train" if n in train else "test" for n in names]
    elif any(root.glob("*.tsv")):
        split = _tsv_split(root, [Path(n).name for n in names])
    missing = [p for p in paths if not p.is_file()]
    if missing:
        raise InspectError(f"{len(missing)} image(s) of {tf_path} are missing, e.g. {missing[0]}")
    points = None
    if meta.get("ply_file_path"):
        try:
            points = read_ply_points(root / meta["ply_file_path"])[0].astype(np.float64)
        except WillagsDataError as e:
            raise InspectError(str(e)) from None
    return _posed_views("transforms", root, paths, (w2c, Ks, dists, sizes), points, split)


def read_colmap_scene(root: Path, model: Path) -> SceneViews:
    """A COLMAP scene: registered images with their poses, the 3D points with their tracks, the tsv split if any."""
    from nerfstudio.data.utils import colmap_parsing_utils as cpu
    from nerfstudio.process_data.colmap_utils import parse_colmap_camera_params

    from willags_ns.data.colmap import ColmapModelError, colmap_images_path, read_colmap_model

    try:
        colmap = read_colmap_model(model, points=True)
    except ColmapModelError as e:
        raise InspectError(str(e)) from None
    cams, ims, pts = colmap.cameras, colmap.images, colmap.points or {}
    if not ims:
        raise InspectError(f"the COLMAP model in {model} has no registered images")
    images_dir = root / colmap_images_path(root)
    ids = sorted(ims, key=lambda i: ims[i].name)
    index = {im_id: k for k, im_id in enumerate(ids)}
    paths, w2c, Ks, dists, sizes = [], [], [], [], []
    for im_id in ids:
        im = ims[im_id]
        try:
            p = parse_colmap_camera_params(cams[im.camera_id])
        except Exception as e:
            raise InspectError(f"{model}: unsupported camera of image {im.name} ({e!r})") from None
        R = cpu.qvec2rotmat(im.qvec)
        paths.append(images_dir / im.name)
        w2c.append(np.concatenate([R, np.asarray(im.tvec)[:, None]], axis=1))
        Ks.append([[p["fl_x"], 0, p["cx"]], [0, p["fl_y"], p["cy"]], [0, 0, 1]])
        dists.append([float(p.get(x, 0.0)) for x in ("k1", "k2", "p1", "p2")])
        sizes.append([p["w"], p["h"]])
    points, tracks = None, None
    if pts:
        keys = list(pts)
        points = np.asarray([pts[k].xyz for k in keys], dtype=np.float64)
        tracks = [np.asarray([index[i] for i in pts[k].image_ids if i in index], dtype=np.int64) for k in keys]
    names = [ims[i].name for i in ids]
    return _posed_views("colmap", root, paths, (w2c, Ks, dists, sizes), points, _tsv_split(root, names), tracks)


def read_scene(data: Path) -> SceneViews:
    """Resolve `data` like `willags-data` does and read it; InspectError (naming the path) when unusable."""
    from willags_ns.data.colmap import find_colmap_model

    data = Path(data).expanduser()
    if not data.exists():
        raise InspectError(f"data path {data} does not exist")
    if data.is_file():
        if data.suffix != ".json":
            raise InspectError(f"{data} is neither a scene directory nor a transforms json file")
        scene = read_transforms_scene(data.parent, data)
    elif (data / "transforms.json").is_file():
        scene = read_transforms_scene(data, data / "transforms.json")
    elif (model := find_colmap_model(data)) is not None:
        scene = read_colmap_scene(data, model)
    else:
        raise InspectError(
            f"{data} has neither transforms.json nor a COLMAP model (colmap/sparse/0, sparse/0, sparse, dense/sparse); "
            "run willags-process on a folder of photos first"
        )
    missing = [p for p in scene.image_paths if not p.is_file()]
    if missing:
        raise InspectError(f"{len(missing)} image(s) of {data} are missing, e.g. {missing[0]}")
    return scene


def select_images(scene: SceneViews, split: str, max_images: int) -> np.ndarray:
    """Indices of the images to analyse: the train split when known (split='train'), at most max_images, evenly."""
    idx = np.arange(len(scene.image_paths))
    if split == "train" and any(s == "train" for s in scene.split):
        idx = idx[[s == "train" for s in scene.split]]
    if len(idx) > max_images:
        idx = idx[np.linspace(0, len(idx) - 1, max_images).round().astype(int)]
    return idx


# --------------------------------------------------------------------------------------------------------------------
# the evidence (pure functions on arrays)


def load_image(path: Path, max_side: int) -> np.ndarray:
    """[H, W, 3] float32 in [0, 1], downscaled so that max(H, W) <= max_side."""
    try:
        with Image.open(path) as im:
            im = im.convert("RGB")
            s = min(1.0, max_side / max(im.size))
            if s < 1.0:
                im = im.resize((max(1, round(im.width * s)), max(1, round(im.height * s))), Image.Resampling.BOX)
            return np.asarray(im, dtype=np.float32) / 255.0
    except OSError as e:
        raise InspectError(f"cannot read image {path}: {e}") from None


def box3(img: np.ndarray) -> np.ndarray:
    """3x3 box filter (edge-replicated): sampling is robust to a pixel of misregistration."""
    p = np.pad(img, ((1, 1), (1, 1), (0, 0)), mode="edge")
    h, w = img.shape[:2]
    return sum(p[dy : dy + h, dx : dx + w] for dy in range(3) for dx in range(3)) / 9.0


def project_points(
    points: np.ndarray, w2c: np.ndarray, K: np.ndarray, dist: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Project [P, 3] world points with a [3, 4] OpenCV world-to-camera and [3, 3] K (optional OpenCV k1, k2, p1,
    p2). Returns pixel coordinates [P, 2] (pixel centres at +0.5) and depth [P]."""
    pc = points @ w2c[:, :3].T + w2c[:, 3]
    z = pc[:, 2]
    safe = np.where(np.abs(z) < 1e-9, 1e-9, z)
    x, y = pc[:, 0] / safe, pc[:, 1] / safe
    if dist is not None and np.any(dist):
        k1, k2, p1, p2 = dist
        r2 = x * x + y * y
        radial = 1 + k1 * r2 + k2 * r2 * r2
        x, y = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x), y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
    return np.stack([K[0, 0] * x + K[0, 2], K[1, 1] * y + K[1, 2]], axis=-1), z


def sample_colors(scene: SceneViews, images: np.ndarray, cfg: InspectConfig) -> tuple[np.ndarray, np.ndarray]:
    """Colours of the (subsampled) points in the selected images: [P, M, 3] float (NaN where unseen) and the [P]
    indices of the points used. Needs poses and points."""
    assert scene.points is not None and scene.w2c is not None and scene.K is not None and scene.cam_size is not None
    rng = np.random.default_rng(cfg.seed)
    pidx = np.arange(len(scene.points))
    if len(pidx) > cfg.max_points:
        pidx = np.sort(rng.choice(pidx, cfg.max_points, replace=False))
    pts = scene.points[pidx]
    centres = np.stack([-w2c[:, :3].T @ w2c[:, 3] for w2c in scene.w2c])  # [N, 3]
    near = None
    if scene.tracks is not None:
        # unit directions point -> camera of every image, for the track-direction visibility stand-in
        near = np.zeros((len(pidx), len(images)), dtype=bool)
        cos_max = math.cos(math.radians(cfg.max_view_angle_deg))
        dirs = centres[None, :, :] - pts[:, None, :]  # [P, N, 3]
        dirs /= np.linalg.norm(dirs, axis=-1, keepdims=True) + 1e-12
        for r, p in enumerate(pidx):
            tr = scene.tracks[p]
            if len(tr) == 0:
                continue
            cos = dirs[r, images] @ dirs[r, tr].T  # [M, T]
            near[r] = cos.max(axis=1) >= cos_max
    colors = np.full((len(pidx), len(images), 3), np.nan, dtype=np.float32)
    for m, i in enumerate(images):
        img = box3(load_image(scene.image_paths[i], cfg.max_side))
        h, w = img.shape[:2]
        uv, z = project_points(pts, scene.w2c[i], scene.K[i], None if scene.dist is None else scene.dist[i])
        uv = uv * np.array([w, h]) / scene.cam_size[i]  # camera pixels -> pixels of the downscaled image
        ok = (z > 1e-6) & (uv[:, 0] >= 0) & (uv[:, 0] < w) & (uv[:, 1] >= 0) & (uv[:, 1] < h)
        if near is not None:
            ok &= near[:, m]
        px = np.clip(uv[ok].astype(np.int64), 0, [w - 1, h - 1])
        vis = zbuffer_visible(px, z[ok], w, h, cfg.zbuffer_cell, cfg.zbuffer_tolerance)
        rows = np.flatnonzero(ok)[vis]
        colors[rows, m] = img[px[vis, 1], px[vis, 0]]
    return colors, pidx


def zbuffer_visible(px: np.ndarray, z: np.ndarray, w: int, h: int, cell: int, tolerance: float) -> np.ndarray:
    """[K] bool: a projected point is visible when its depth is within `tolerance` (relative) of the nearest point
    projected into its `cell` x `cell` pixel cell: a coarse point z-buffer (sparse points cannot cover each other
    pixel by pixel), so a wall behind an object is not sampled on the object."""
    if len(z) == 0:
        return np.zeros(0, dtype=bool)
    cw = (w + cell - 1) // cell
    key = (px[:, 1] // cell) * cw + px[:, 0] // cell
    zmin = np.full(cw * ((h + cell - 1) // cell), np.inf)
    np.minimum.at(zmin, key, z)
    return z <= zmin[key] * (1.0 + tolerance)


def _fit_affine(ref: np.ndarray, obs: np.ndarray, rounds: int = 6) -> tuple[float, float]:
    """Robust a, b with obs ~= a ref + b (1-D arrays): start from the pure gain median(obs) / median(ref), then
    alternate dropping residuals beyond 2.5 robust standard deviations and least squares on the rest."""
    if len(ref) < 3 or np.ptp(ref) < 1e-6:
        return 1.0, float(np.median(obs - ref)) if len(ref) else 0.0
    a, b = float(np.median(obs) / max(float(np.median(ref)), 1e-3)), 0.0
    for _ in range(rounds):
        res = obs - (a * ref + b)
        dev = np.abs(res - np.median(res))
        keep = dev <= max(2.5 * 1.4826 * float(np.median(dev)), 2.0 / 255.0)
        if keep.sum() < 3:
            break
        A = np.stack([ref[keep], np.ones(int(keep.sum()))], axis=1)
        a, b = (float(v) for v in np.linalg.lstsq(A, obs[keep], rcond=None)[0])
    return a, b


def nearest_cameras(centres: np.ndarray, k: int) -> np.ndarray:
    """[M, k] indices of each camera's k nearest other cameras (by centre distance)."""
    d = np.linalg.norm(centres[:, None] - centres[None], axis=-1)
    np.fill_diagonal(d, np.inf)
    return np.argsort(d, axis=1)[:, : min(k, len(centres) - 1)]


def raw_colour_twins(colors: np.ndarray, seen: np.ndarray, candidates: np.ndarray, tolerance: float) -> np.ndarray:
    """[P, M] bool: the `candidates` observations (of colours [P, M, 3], `seen` [P, M]) whose raw colour another
    photo of the same point repeats within `tolerance` (RMS over channels): the point under a light that recurs,
    not an occluder (InspectConfig.twin_tolerance)."""
    twins = np.zeros_like(candidates)
    for p in np.flatnonzero(candidates.any(axis=1)):
        ms = np.flatnonzero(seen[p])
        cand = np.flatnonzero(candidates[p, ms])
        x = colors[p, ms]  # [k, 3]
        d = np.sqrt(np.mean((x[cand, None] - x[None]) ** 2, axis=-1))  # [c, k]
        d[np.arange(len(cand)), cand] = np.inf  # not its own twin
        twins[p, ms[cand]] = d.min(axis=1) <= tolerance
    return twins


def appearance_and_transients(colors: np.ndarray, cfg: InspectConfig, neighbours: np.ndarray) -> dict[str, Any]:
    """The SfM-point evidence (module docstring) from colours [P, M, 3] (NaN where unseen) and each image's nearest
    cameras [M, k] (indices into M)."""
    seen = ~np.isnan(colors[..., 0])
    use = seen.sum(axis=1) >= cfg.min_views
    colors, seen = colors[use], seen[use]
    P, M = seen.shape
    if P < 20:
        raise InspectError(f"only {P} SfM points are seen by >= {cfg.min_views} of the analysed images: too few")
    a = np.ones((M, 3))
    b = np.zeros((M, 3))
    norm = colors.copy()
    for _ in range(max(1, cfg.iterations)):
        ref = np.nanmedian(norm, axis=1)  # [P, 3]
        for m in range(M):
            s = seen[:, m]
            for c in range(3):
                a[m, c], b[m, c] = _fit_affine(ref[s, c], colors[s, m, c])
        a = np.where(np.abs(a) < 0.05, 0.05, a)
        norm = (colors - b[None]) / a[None]
    ref = np.nanmedian(norm, axis=1)
    per_image_change = np.array(
        [
            np.mean(np.abs(a[m] * ref[seen[:, m]] + b[m] - ref[seen[:, m]])) * 255.0 if seen[:, m].any() else np.nan
            for m in range(M)
        ]
    )
    with warnings.catch_warnings():  # unseen observations are all-NaN rows
        warnings.simplefilter("ignore", RuntimeWarning)
        dist = np.sqrt(np.nanmean((norm - ref[:, None]) ** 2, axis=-1))  # [P, M] RMS over channels
    mad = np.nanmedian(dist, axis=1) * 1.4826
    limit = np.maximum(cfg.outlier_k * mad, cfg.outlier_floor)
    outlier = (dist > limit[:, None]) & seen
    frac = outlier.sum(axis=0) / np.maximum(seen.sum(axis=0), 1)
    # transient observations: outliers that also disagree with every nearby camera seeing the point (geometry and
    # visibility errors, view-dependent colour are shared by nearby views; an occluder in one photo is not)
    isolated = outlier.copy()
    checked = np.zeros_like(outlier)
    for j in range(neighbours.shape[1]):
        nb = neighbours[:, j]
        other = norm[:, nb]  # [P, M, 3]: the j-th neighbour's colour of each point
        both = seen & seen[:, nb]
        d = np.sqrt(np.mean((norm - other) ** 2, axis=-1))
        agree = both & (d <= limit[:, None])
        isolated &= ~agree
        checked |= both
    isolated &= checked
    if cfg.twin_tolerance > 0:
        isolated &= ~raw_colour_twins(colors, seen, isolated, cfg.twin_tolerance)
    tfrac = isolated.sum(axis=0) / np.maximum(seen.sum(axis=0), 1)
    return {
        "appearance_score": float(np.nanmedian(per_image_change)),
        "transient_score": float(np.mean(tfrac >= cfg.image_transient_level)),
        "transient_fraction_mean": float(np.mean(tfrac)),
        "per_image_transient_fraction": tfrac.tolist(),
        "per_image_color_change": per_image_change.tolist(),
        "per_image_outlier_fraction": frac.tolist(),
        "outlier_fraction_median": float(np.median(frac)),
        "outlier_fraction_p90": float(np.quantile(frac, 0.9)),
        "gain_log2_std": float(np.std(np.log2(np.clip(a.mean(axis=1), 1e-3, None)))),
        "offset_std": float(np.std(b.mean(axis=1)) * 255.0),
        "points_used": int(P),
        "observations_per_point": float(seen.sum() / P),
    }


def global_color_evidence(paths: list[Path]) -> dict[str, Any]:
    """Fallback without SfM points: the spread across images of each image's mean colour (64 px images), 8-bit
    levels, median over channels. Mixes appearance with content; transients are not measured."""
    means = np.stack([load_image(p, 64).reshape(-1, 3).mean(axis=0) for p in paths])
    spread = np.median(np.abs(means - np.median(means, axis=0)), axis=0) * 1.4826 * 255.0
    return {
        "appearance_score": float(np.median(spread)),
        "transient_score": None,
        "per_image_mean_color": means.tolist(),
    }


def covered_cells(uv: np.ndarray, width: float, height: float, grid: int) -> np.ndarray:
    """[ny, nx] bool: the cells of a coarse grid over a `width` x `height` image (`grid` cells along the long side,
    the short side's count in proportion, so cells are near-square and of equal area) that hold at least one of the
    points uv [K, 2] (pixels; outside the image ignored), dilated by one cell (8-neighbourhood): SfM points are
    sparse even on a textured wall, and the gap between two neighbouring points is not open background."""
    nx = grid if width >= height else max(1, round(grid * width / height))
    ny = grid if height > width else max(1, round(grid * height / width))
    inside = (uv[:, 0] >= 0) & (uv[:, 0] < width) & (uv[:, 1] >= 0) & (uv[:, 1] < height)
    cx = np.minimum((uv[inside, 0] * nx / width).astype(np.int64), nx - 1)
    cy = np.minimum((uv[inside, 1] * ny / height).astype(np.int64), ny - 1)
    hit = np.zeros((ny, nx), dtype=bool)
    hit[cy, cx] = True
    p = np.pad(hit, 1)
    return np.logical_or.reduce([p[dy : dy + ny, dx : dx + nx] for dy in range(3) for dx in range(3)])


def coverage_maps(scene: SceneViews, images: np.ndarray, grid: int) -> list[np.ndarray]:
    """Per selected image, the cells [ny, nx] that an SfM point covers (`covered_cells`): all the scene's points
    projected with the image's camera (no visibility test: a hidden point still proves there is geometry along that
    ray, and open sky has none). Needs poses and points."""
    assert scene.points is not None and scene.w2c is not None and scene.K is not None and scene.cam_size is not None
    out = []
    for i in images:
        w, h = scene.cam_size[i]
        dist = None if scene.dist is None else scene.dist[i]
        uv, z = project_points(scene.points, scene.w2c[i], scene.K[i], dist)
        # the distortion polynomial folds points far outside the field of view back into the image (a negative k1
        # maps a large radius to a small one), which would cover sky with points from behind the camera's edge:
        # keep only points whose pinhole projection lies within the image plus a margin of half its size
        pin, _ = project_points(scene.points, scene.w2c[i], scene.K[i], None) if dist is not None else (uv, z)
        near = (np.abs(pin[:, 0] / w - 0.5) <= 1.0) & (np.abs(pin[:, 1] / h - 0.5) <= 1.0)
        out.append(covered_cells(uv[(z > 1e-6) & near], w, h, grid))
    return out


def background_fractions(scene: SceneViews, images: np.ndarray, grid: int) -> np.ndarray:
    """[M] share of each selected image's area that no SfM point covers (evidence 4, module docstring)."""
    return np.array([1.0 - float(c.mean()) for c in coverage_maps(scene, images, grid)])


def open_from_top(covered: np.ndarray) -> np.ndarray:
    """[ny, nx] bool: the uncovered cells connected (4-neighbourhood) to the image's top row through uncovered
    cells: the sky, and what reaches into it (not a plaza or a crowd under a covered facade)."""
    free = ~covered
    reach = np.zeros_like(free)
    reach[0] = free[0]
    while True:
        grown = reach.copy()
        grown[1:] |= reach[:-1]
        grown[:-1] |= reach[1:]
        grown[:, 1:] |= reach[:, :-1]
        grown[:, :-1] |= reach[:, 1:]
        grown &= free
        if (grown == reach).all():
            return reach
        reach = grown


def surround_fraction(covered: np.ndarray, sky: np.ndarray | None = None) -> float:
    """Share of an image's covered cells with open background (`open_from_top`, or `sky` when the caller has it)
    both to their left and to their right in the same row: how much of what SfM reconstructed stands against the sky
    (a statue: most of it; a building under the sky: only its roofline). 0 for an image without covered cells."""
    sky = open_from_top(covered) if sky is None else sky
    left = np.maximum.accumulate(sky, axis=1)
    right = np.maximum.accumulate(sky[:, ::-1], axis=1)[:, ::-1]
    n = int(covered.sum())
    return float((covered & left & right).sum()) / n if n else 0.0


def enclosed_fraction(covered: np.ndarray, sky: np.ndarray | None = None) -> float:
    """Share of an image's cells that no SfM point covers and that are not reached from the image's top through
    uncovered cells (`open_from_top`, or `sky` when the caller has it): open background under covered scene, not
    sky."""
    sky = open_from_top(covered) if sky is None else sky
    return float((~covered & ~sky).mean())


def open_background_evidence(scene: SceneViews, images: np.ndarray, cfg: InspectConfig) -> dict[str, Any]:
    """Evidence 4 (module docstring): the median over the selected images of the uncovered share, of the surround
    share (`surround_fraction`) and of the enclosed uncovered share (`enclosed_fraction`), and the per-image values."""
    maps = coverage_maps(scene, images, cfg.background_grid)
    frac = np.array([1.0 - float(c.mean()) for c in maps])
    skies = [open_from_top(c) for c in maps]  # each map's flood fill once, for both shares
    surround = np.array([surround_fraction(c, sky) for c, sky in zip(maps, skies, strict=True)])
    ground = np.array([enclosed_fraction(c, sky) for c, sky in zip(maps, skies, strict=True)])
    return {
        "background_score": float(np.median(frac)),
        "background_fraction_mean": float(np.mean(frac)),
        "surround_score": float(np.median(surround)),
        "surround_fraction_mean": float(np.mean(surround)),
        "per_image_background_fraction": frac.tolist(),
        "per_image_surround_fraction": surround.tolist(),
        "ground_score": float(np.median(ground)),
        "per_image_ground_fraction": ground.tolist(),
    }


def image_sizes(paths: list[Path]) -> np.ndarray:
    """[N, 2] (width, height) from the image headers (no decoding)."""
    out = []
    for p in paths:
        try:
            with Image.open(p) as im:
                out.append(im.size)
        except OSError as e:
            raise InspectError(f"cannot read image {p}: {e}") from None
    return np.asarray(out, dtype=np.int64)


def _extent(x: np.ndarray | None) -> float | None:
    if x is None or len(x) < 2:
        return None
    lo, hi = np.quantile(x, 0.05, axis=0), np.quantile(x, 0.95, axis=0)
    return float(np.linalg.norm(hi - lo))


GPU_FIXED_GB = 1.5
"""GPU memory of a run before its images and Gaussians: the CUDA context and the mask's VGG."""
BYTES_PER_GAUSSIAN = 1e3
"""GPU memory per Gaussian: its parameters, Adam's two moments, gradients and the rasteriser's buffers."""
GPU_STEP_S, GPU_STEP_MPX = 0.024, 0.35
"""A measured GPU step (seconds) and the megapixels per image it was measured at (reichstag on an H100)."""
CPU_STEP_S, CPU_STEP_MPX = 0.8, 0.13
"""A measured CPU step (seconds, 2 cores) and the megapixels per image it was measured at (fox)."""


def train_megapixels(sizes: np.ndarray, trains: list[bool] | None, factor: int) -> float:
    """Megapixels of the training photos (`trains`: which of `sizes` [N, 2] train; None: all) at the size training
    reads them (1/`factor` of each side): what MCMC's "pixels" cap rule scales with."""
    use = sizes if trains is None else sizes[np.asarray(trains, dtype=bool)]
    return round(float(np.sum(use[:, 0].astype(np.float64) * use[:, 1])) / (factor * factor) / 1e6, 2)


def resource_estimate(n_images: int, sizes: np.ndarray, n_points: int, cfg: InspectConfig) -> dict[str, Any]:
    """Rough memory and time (module docstring, evidence 3)."""
    mpx = float(np.mean(sizes[:, 0] * sizes[:, 1])) / 1e6
    cap = cfg.max_gaussians
    gaussians = int(min(np.clip(cfg.gaussians_per_point * n_points, 1e5, 1.5e6), cap))
    images_gb = n_images * mpx * 1e6 * 3 / 1e9
    gpu_gb = GPU_FIXED_GB + images_gb + gaussians * BYTES_PER_GAUSSIAN / 1e9

    def step_s(at: float, mpx_measured: float, scale: float) -> float:  # pixels of the image trained at 1/scale
        return at * max(mpx / (scale * scale) / mpx_measured, 0.25)

    def run_s(at: float, mpx_measured: float) -> float:  # the resolution schedule: 1/2**k size until its steps
        return sum(step_s(at, mpx_measured, 2.0**k) * n for k, n in resolution_spans(cfg.steps).items())

    first = max(resolution_spans(cfg.steps))
    return {
        "rough": True,
        "how": f"Gaussians ~ gaussians_per_point x points (clipped to [1e5, 1.5e6], at most the default's "
        f"mcmc.cap_max {cap:,}); GPU memory = {GPU_FIXED_GB} GB + "
        f"images as uint8 + {BYTES_PER_GAUSSIAN / 1e3:g} KB per Gaussian; step time scaled by pixels per image from "
        f"{GPU_STEP_S * 1e3:g} ms at {GPU_STEP_MPX} Mpx (H100) and {CPU_STEP_S:g} s at {CPU_STEP_MPX} Mpx (2 CPU "
        "cores), both measured in docs/benchmarks.md, at the size each step trains (splatfacto's resolution schedule: "
        "1/4 size, then 1/2, then full); the Gaussian count's effect is not modelled",
        "expected_gaussians": gaussians,
        "gpu_memory_gb": round(gpu_gb, 2),
        "cpu_memory_gb": round(gpu_gb + 2.0, 2),
        "gpu_hours": round(run_s(GPU_STEP_S, GPU_STEP_MPX) / 3600, 2),
        "cpu_hours": round(run_s(CPU_STEP_S, CPU_STEP_MPX) / 3600, 1),
        "cpu_first_step_s": round(step_s(CPU_STEP_S, CPU_STEP_MPX, 2.0**first), 2),
        "cpu_full_step_s": round(step_s(CPU_STEP_S, CPU_STEP_MPX, 1.0), 2),
        "steps": cfg.steps,
    }


RESOLUTION_SCHEDULE = 3000
"""Steps per resolution level of the willags presets (splatfacto's resolution_schedule)."""
NUM_DOWNSCALES = 2
"""Resolution levels below full size the willags presets start at (splatfacto's num_downscales: 1/4 size)."""


def resolution_spans(steps: int) -> dict[int, int]:
    """{k: steps trained at 1/2**k size} of a run of ``steps`` under the presets' resolution schedule (the model's
    rule: k = max(0, NUM_DOWNSCALES - step // RESOLUTION_SCHEDULE)). 30000 steps: {2: 3000, 1: 3000, 0: 24000}."""
    spans: dict[int, int] = {}
    for k in range(NUM_DOWNSCALES, -1, -1):
        start = (NUM_DOWNSCALES - k) * RESOLUTION_SCHEDULE
        end = steps if k == 0 else min(steps, start + RESOLUTION_SCHEDULE)
        if end > start:
            spans[k] = end - start
    return spans


# --------------------------------------------------------------------------------------------------------------------
# the recommendation


SKY_MODES: dict[str, dict[str, Any]] = {
    "off": {"sky.enabled": False, "sky.region": "open", "sky.alpha_penalty": 0.0},
    "skyline": {"sky.enabled": True, "sky.region": "open", "sky.alpha_penalty": 0.0},
    "surround": {"sky.enabled": True, "sky.region": "everywhere", "sky.alpha_penalty": 0.1},
}
"""The sky switch's settings (model fields under pipeline.model), one per mode: "off", no learnt sky (splatfacto's
background); "skyline", the appearance-conditioned sky trained only above each photo's SfM skyline, so the scene's
Gaussians stay opaque (a building under the sky); "surround", the sky behind every pixel and the alpha penalty
where the sky alone explains the photo, so no Gaussian floats in the sky around a subject that stands against it
(appearance/sky.py). What each costs and wins, per scene: docs/inspect.md."""

WILLAGS_SKY: dict[str, Any] = SKY_MODES["skyline"]
"""The sky of the default `willags` preset: the command line names only what differs from it. Kept in step with
method_configs.willags_model_config (tests/tools/test_autoconfig.py checks)."""


def sky_settings(mode: str) -> dict[str, Any]:
    """Model fields of a sky mode ("off", "skyline" or "surround"): the one place the switch maps to settings;
    `sky_flags` and autoconfig.overrides_from_recommendation read it."""
    if mode not in SKY_MODES:
        raise ValueError(f"unknown sky mode {mode!r} (one of {', '.join(SKY_MODES)})")
    return dict(SKY_MODES[mode])


def sky_flags(mode: str) -> list[str]:
    """ns-train flags that give the willags preset `sky_settings(mode)`: the fields that differ from WILLAGS_SKY
    (the region and the penalty are read only with the sky enabled, so switching it off needs the one flag)."""
    return [
        f"--pipeline.model.{key.replace('_', '-')} {value}"
        for key, value in sky_settings(mode).items()
        if value != WILLAGS_SKY[key] and (mode != "off" or key == "sky.enabled")
    ]


def against(value: float, threshold: float, digits: int = 2) -> str:
    """`value` with `digits` decimals, or more (up to 6) where fewer would print it on the other side of the threshold
    it is compared with: 0.1496 against 0.15 reads 0.1496, not 0.15 < threshold 0.15."""
    for d in range(digits, 7):
        text = f"{value:.{d}f}"
        if (float(text) >= threshold) == (value >= threshold):
            return text
    return text


def _sky(evidence: dict[str, Any], preset: str, cfg: InspectConfig) -> dict[str, Any]:
    """The sky entry of the recommendation (evidence 4), for the willags presets: "off" below `sky_threshold` of
    open background, "surround" where the subject stands against it (surround_score >= `surround_threshold`),
    "skyline" otherwise; not measured without SfM points (the method's own setting stays)."""
    bg = evidence.get("background_score")
    if bg is None:
        return {
            "on": bool(WILLAGS_SKY["sky.enabled"]),
            "mode": "skyline",
            "measured": False,
            "reason": "open background not measured (no SfM points): the sky is kept as the method's own setting",
        }
    need = bg >= cfg.sky_threshold
    reason = (
        f"median share of an image that no SfM point covers {against(bg, cfg.sky_threshold)} "
        f"(mean {evidence['background_fraction_mean']:.2f}) "
        f"{'>=' if need else '<'} threshold {cfg.sky_threshold:g}"
    )
    if need and preset == "willags-3dgs":
        # the sky's colour is a function of the appearance latent, which plain 3DGS does not have
        return {
            "on": False,
            "mode": "off",
            "measured": True,
            "reason": reason + "; plain 3DGS has no latent to condition a sky on",
        }
    if not need:
        return {"on": False, "mode": "off", "measured": True, "reason": reason}
    sur = evidence.get("surround_score")
    surround = sur is not None and sur >= cfg.surround_threshold
    if sur is not None:
        reason += (
            f"; the subject stands against it in a median {against(sur, cfg.surround_threshold)} of its rows "
            f"{'>=' if surround else '<'} threshold {cfg.surround_threshold:g}: "
            + (
                "surround (the sky behind every pixel, the alpha penalty where it alone explains the photo)"
                if surround
                else "skyline (the sky above each photo's skyline only)"
            )
        )
    return {"on": True, "mode": "surround" if surround else "skyline", "measured": True, "reason": reason}


def recommend(evidence: dict[str, Any], n_train: int, cfg: InspectConfig) -> dict[str, Any]:
    """Switches and preset from the evidence, each with a reason quoting the number and the threshold."""
    app = evidence["appearance_score"]
    fallback = evidence["method"] != "sfm-points"
    thr = cfg.fallback_appearance_threshold if fallback else cfg.appearance_threshold
    appearance = app >= thr
    what = "spread of per-image mean colours (no SfM points)" if fallback else "median per-image colour change"
    app_reason = f"{what} {against(app, thr, 1)} levels {'>=' if appearance else '<'} threshold {thr:g}"
    tr = evidence["transient_score"]
    if tr is None:
        mask = True
        mask_reason = "transients not measured (no SfM points): the mask is kept on, as in the default willags"
    else:
        mask = tr >= cfg.transient_threshold
        mask_reason = (
            f"{against(tr, cfg.transient_threshold)} of the images have >= {cfg.image_transient_level:g} of their "
            "observations transient "
            f"{'>=' if mask else '<'} threshold {cfg.transient_threshold:g} (mean transient fraction "
            f"{evidence['transient_fraction_mean']:.3f})"
        )
        ground = evidence.get("ground_score")
        if not mask and ground is not None and ground >= cfg.ground_hint_threshold:
            mask_reason += (
                f"; but ground under the subject {against(ground, cfg.ground_hint_threshold)} >= "
                f"{cfg.ground_hint_threshold:g}: people may stand where SfM has no points, which that count cannot see; "
                "try --pipeline.model.mask.enabled True (docs/inspect.md)"
            )
    if appearance:
        latent = 64 if n_train >= 30 else 32
        latent_reason = f"{n_train} training images: {latent}-d ({'the default' if latent == 64 else 'fewer images'})"
    elif mask:
        latent = 8
        latent_reason = "no appearance change, but the mask needs the willags model: a small 8-d latent (a heuristic)"
    else:
        latent = 0
        latent_reason = "no latent (plain 3DGS)"
    if mask:
        preset = "willags"
        flags = [] if latent == 64 else [f"--pipeline.model.latent.dim {latent}"]
        preset_reason = "the mask (with its EMA teacher) is part of the willags model"
        if not appearance:
            preset_reason += "; willags cannot switch the latent off while keeping the mask, so the latent stays small"
    elif appearance:
        preset = "willags"
        flags = ["--pipeline.model.mask.enabled False"] + (
            [] if latent == 64 else [f"--pipeline.model.latent.dim {latent}"]
        )
        preset_reason = "appearance latent without the mask (and so without the teacher's renders)"
    else:
        preset, flags = "willags-3dgs", []
        preset_reason = "neither an appearance change nor transients: plain 3DGS through willags' rasteriser"
    sky = _sky(evidence, preset, cfg)
    if preset == "willags" and sky["measured"]:
        flags = flags + sky_flags(sky["mode"])
    return {
        "appearance_latent": {"on": appearance, "reason": app_reason},
        "mask": {"on": mask, "reason": mask_reason},
        "teacher": {"on": mask, "reason": "the EMA teacher only renders the mask's pseudo ground truth"},
        "triplane_field": {
            "on": False,
            "reason": "measured, it did not help (docs/benchmarks.md: willags-vae-field vs willags-vae on reichstag, "
            "willags-paper vs willags on fox-wild)",
        },
        "sky": sky,
        "latent_dim": {"value": latent, "reason": latent_reason},
        "preset": {"value": preset, "flags": flags, "reason": preset_reason},
        "command": " ".join(["ns-train", preset, *flags, "--data", str(evidence["data"])]),
    }


def inspect_scene(cfg: InspectConfig) -> dict[str, Any]:
    """Read the scene, compute the evidence and the recommendation. Raises InspectError on unusable input."""
    import time

    t0 = time.perf_counter()
    scene = read_scene(cfg.data)
    sel = select_images(scene, cfg.split, cfg.max_images)
    sizes = image_sizes(scene.image_paths)
    from willags_ns.data.dataparser import auto_downscale_factor

    # the factor training reads the photos at: the data parser's rule on the photos' folder
    factor = cfg.downscale_factor or (
        auto_downscale_factor(Path(scene.image_paths[0]).parent) if scene.image_paths else 1
    )
    n_train = sum(s == "train" for s in scene.split) or len(scene.image_paths)
    trains = [s == "train" for s in scene.split] if any(s == "train" for s in scene.split) else None
    evidence: dict[str, Any] = {"data": str(cfg.data)}
    if scene.points is not None and len(scene.points) >= 20 and scene.w2c is not None:
        colors, _ = sample_colors(scene, sel, cfg)
        centres = np.stack([-w[:, :3].T @ w[:, 3] for w in scene.w2c[sel]])
        nbrs = nearest_cameras(centres, cfg.neighbours)
        evidence.update(method="sfm-points", **appearance_and_transients(colors, cfg, nbrs))
        evidence.update(open_background_evidence(scene, sel, cfg))
    else:
        evidence.update(method="global-color-stats", **global_color_evidence([scene.image_paths[i] for i in sel]))
        evidence.update(background_score=None, background_fraction_mean=None)
    cams = None if scene.w2c is None else np.stack([-w[:, :3].T @ w[:, 3] for w in scene.w2c])
    facts = {
        "kind": scene.kind,
        "images": len(scene.image_paths),
        "train_images": n_train,
        "analysed_images": len(sel),
        "analysed_split": cfg.split if any(s == "train" for s in scene.split) else "all (no split in the scene)",
        "resolution_min": sizes.min(axis=0).tolist(),
        "resolution_median": np.median(sizes, axis=0).astype(int).tolist(),
        "resolution_max": sizes.max(axis=0).tolist(),
        "train_megapixels": train_megapixels(sizes, trains, factor),
        "points": 0 if scene.points is None else len(scene.points),
        "points_extent": _extent(scene.points),
        "cameras_extent": _extent(cams),
        "estimate": {
            **resource_estimate(n_train, sizes / factor, 0 if scene.points is None else len(scene.points), cfg),
            "downscale_factor": factor,
        },
    }
    rec = recommend(evidence, n_train, cfg)
    short = {k: v for k, v in evidence.items() if not k.startswith("per_image")}
    report = {
        "data": str(cfg.data),
        "facts": facts,
        "evidence": short,
        "recommendation": rec,
        "per_image": {
            "names": [scene.image_paths[i].name for i in sel],
            **{k: v for k, v in evidence.items() if k.startswith("per_image")},
        },
        "config": {k: (str(v) if isinstance(v, Path) else v) for k, v in asdict(cfg).items()},
        "wall_s": round(time.perf_counter() - t0, 2),
    }
    return report


def capacity_line(train_megapixels: float | None) -> str:
    """How many Gaussians the willags method trains for these photos, and why: MCMC's cap on a GPU
    (splats/mcmc.cap_and_reason, the method's own McmcConfig), splatfacto's densification on a CPU."""
    from willags_ns.splats.mcmc import McmcConfig, cap_and_reason

    _, reason = cap_and_reason(McmcConfig(), train_megapixels)
    return (
        f"on a GPU MCMC grows to {reason}; on a CPU splatfacto's densification grows by the gradients "
        "(short runs: MCMC's growth of 5 % a refinement leaves them too few, docs/design.md)"
    )


def format_report(report: dict[str, Any]) -> str:
    """The human-readable summary the CLI prints."""
    f, e, r = report["facts"], report["evidence"], report["recommendation"]
    est = f["estimate"]
    ts, bg = e["transient_score"], e.get("background_score")
    lines = [
        f"willags-inspect {report['data']}  ({report['wall_s']:.1f} s)",
        f"  scene: {f['kind']}, {f['images']} images ({f['train_images']} train, {f['analysed_images']} analysed), "
        f"resolution {f['resolution_min']}..{f['resolution_max']} (median {f['resolution_median']}), "
        f"{f['points']} SfM points, {f.get('train_megapixels', 0):.1f} Mpx of training photos",
        f"  extent: points {f['points_extent'] if f['points_extent'] is None else round(f['points_extent'], 2)}, "
        f"cameras {f['cameras_extent'] if f['cameras_extent'] is None else round(f['cameras_extent'], 2)} (scene units)",
        f"  rough estimate: ~{est['expected_gaussians']:,} Gaussians, GPU ~{est['gpu_memory_gb']} GB / "
        f"~{est['gpu_hours']} h, CPU ~{est['cpu_memory_gb']} GB / ~{est['cpu_hours']} h for {est['steps']} steps "
        f"(a CPU step ~{est['cpu_first_step_s']} s at the first 1/4 size, ~{est['cpu_full_step_s']} s at full size: an "
        "ETA taken early in a run counts the first"
        + (f"; photos read at 1/{est['downscale_factor']} of their size" if est.get("downscale_factor", 1) > 1 else "")
        + ")",
        f"  evidence ({e['method']}): appearance {e['appearance_score']:.2f} levels, transients "
        + ("not measured" if ts is None else f"{ts:.2f} of the images occluded")
        + ", open background "
        + ("not measured" if bg is None else f"{bg:.2f} of the image (median)")
        + ("" if e.get("surround_score") is None else f", subject against it {e['surround_score']:.2f} (median)")
        + ("" if e.get("ground_score") is None else f", ground under it {e['ground_score']:.2f} (median)"),
    ]
    for key in ("appearance_latent", "mask", "teacher", "triplane_field", "sky"):
        mode = f" {r[key]['mode']}" if key == "sky" and r[key]["on"] else ""
        lines.append(f"  {key}: {'ON ' if r[key]['on'] else 'off'}{mode}  ({r[key]['reason']})")
    lines.append(f"  latent_dim: {r['latent_dim']['value']}  ({r['latent_dim']['reason']})")
    lines.append(f"  capacity: {capacity_line(f.get('train_megapixels'))}")
    lines.append(f"  preset: {r['preset']['value']}  ({r['preset']['reason']})")
    lines.append(f"  command: {r['command']}")
    return "\n".join(lines)
