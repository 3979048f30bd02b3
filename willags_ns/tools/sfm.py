"""`willags-process`: a folder of photos -> a COLMAP scene that nerfstudio (and `willags-data`) reads directly.

Structure-from-motion with pycolmap on CPU (a pip wheel: no COLMAP binary, no GPU), in four resumable stages:

1. features: SIFT per image into `colmap/database.db`, one camera per EXIF camera (the photos of one phone or lens at
   one zoom share intrinsics) and one per photo without an EXIF focal length (tourist photos come from many
   cameras), camera model SIMPLE_RADIAL (focal length, principal point, one radial term) or SIMPLE_PINHOLE;
2. matching: exhaustive up to `exhaustive_max_images` images (all n(n-1)/2 pairs); above that, image retrieval with
   a vocabulary tree built from the collection's own SIFT descriptors (no download) and each image matched with its
   `retrieval_neighbors` best-scoring images; every pair is verified geometrically;
3. mapping: COLMAP's incremental mapper or GLOMAP (`--mapper`; auto: global from `global_min_images` images), fixed
   seed; the largest model is kept. When the incremental mapper leaves out photos that match others, it is
   retried with relaxed thresholds (RETRY_STEPS), then (auto) the global mapper is tried and used only if it agrees
   with the incremental model; the summary lists every attempt;
4. writing: SIMPLE_RADIAL models are undistorted to PINHOLE (images re-sampled, so the training images match a
   pinhole camera); SIMPLE_PINHOLE models are written as they are with the registered photos copied.

Output (nerfstudio's colmap dataparser defaults, so `ns-train willags --data OUT colmap` works as is)::

    OUT/images/                 registered images (undistorted for SIMPLE_RADIAL)
    OUT/images_2/, images_4/    with --num-downscales: 1/2, 1/4, ... size (floor), what --downscale-factor reads
    OUT/colmap/sparse/0/        the model (cameras.bin, images.bin, points3D.bin)
    OUT/colmap/distorted/0/     SIMPLE_RADIAL only: the SfM model before undistortion
    OUT/colmap/database.db      features and matches: kept, so an interrupted run resumes where it stopped
    OUT/<name>.tsv              NeRF-W split (filename, id, split, dataset): every test_every-th registered image
                                (COLMAP id order, nerfstudio's interval rule) is "test"
    OUT/process_summary.json    the summary printed at the end, plus options and timings

Interrupting (Ctrl-C) stops the current stage at the next image or block of pairs: the database keeps every image
already extracted and every pair already matched, and the same command resumes from there. The model and images are
written last, each into a temporary directory renamed into place, so they are either the previous run's or complete.
"""

import dataclasses
import json
import os
import shutil
import signal
import threading
import time
from collections.abc import Callable, Collection, Iterator, Sequence
from contextlib import closing, contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import numpy as np
from PIL import Image

from willags_ns.data.images import save_downscaled
from willags_ns.files import write_text_atomic

IMAGE_SUFFIXES = (".jpg", ".jpeg", ".png", ".bmp", ".tif", ".tiff")
"""Files (case-insensitive suffix) taken as photos; everything else in the folder is ignored."""

DATABASE = Path("colmap/database.db")
MODEL_DIR = Path("colmap/sparse/0")
DISTORTED_DIR = Path("colmap/distorted/0")
VOCAB_TREE = Path("colmap/vocab_tree.bin")
OPTIONS_STAMP = Path("colmap/database_options.json")
SUMMARY = Path("process_summary.json")


class ProcessError(RuntimeError):
    """The input or the SfM result cannot give a usable scene; the message says why and what to do."""


@dataclass
class ProcessConfig:
    """willags-process: structure-from-motion on a folder of photos with pycolmap (CPU), written for nerfstudio.

    Resumable: features and matches are kept in OUTPUT/colmap/database.db, so after Ctrl-C the same command goes on
    where it stopped (only mapping restarts). The model and images are replaced only when a run completes.
    """

    images: Path
    """Folder of photos (.jpg, .jpeg, .png, .bmp, .tif; subfolders are ignored). Never written."""
    output: Path
    """Scene folder to write (images/, colmap/sparse/0, <name>.tsv); created if missing."""
    camera_model: Literal["SIMPLE_RADIAL", "SIMPLE_PINHOLE"] = "SIMPLE_RADIAL"
    """SIMPLE_RADIAL: f, cx, cy and one radial distortion term per camera, then undistortion to PINHOLE for training.
    SIMPLE_PINHOLE: no distortion; the photos are copied as they are."""
    single_camera: bool = False
    """Share one camera (intrinsics) between all images, for photos taken with one camera and zoom. Default: one
    camera per image (tourist photos come from many cameras), or per EXIF camera with exif_cameras."""
    exif_cameras: bool = True
    """Photos whose EXIF gives the same camera make, model and focal length, at the same pixel size, share one camera
    (intrinsics): one phone's photos at one zoom are one camera, photos without an EXIF focal length a camera each.
    Why: with a camera per photo, each photo's focal length is free, and on a forward-moving walk (lund) focal length
    and depth trade off, bending the model (docs/process.md)."""
    max_num_features: int = 8192
    """SIFT features kept per image."""
    max_feature_image_size: int = 1600
    """Photos are resized to at most this long side for SIFT (features are scaled back to full resolution)."""
    matching: Literal["auto", "exhaustive", "vocab-tree"] = "auto"
    """Pair selection. auto: exhaustive up to exhaustive_max_images images, else vocab-tree (retrieval with a
    vocabulary tree built from the collection's own SIFT descriptors)."""
    exhaustive_max_images: int = 150
    """auto matching: the largest collection matched exhaustively (n(n-1)/2 pairs; 150 images = 11,175 pairs)."""
    retrieval_neighbors: int = 40
    """vocab-tree matching: each image is matched with its this many most similar images."""
    mapper: Literal["auto", "incremental", "global"] = "auto"
    """incremental: COLMAP's incremental mapper (registers images one by one; robust, slow on large collections).
    global: GLOMAP through pycolmap (rotation averaging and global positioning of all images at once; much faster on
    large collections). auto: incremental up to global_min_images images, global above."""
    global_min_images: int = 500
    """auto mapper: the smallest collection mapped with the global mapper."""
    retry_below: float = 1.0
    """Incremental mapper: when its model holds fewer than this share of the photos that could be placed (those
    with a verified pair of 15 inlier matches or more), mapping is retried with relaxed thresholds (a photo placed
    from 15 inliers, not 30; then also a first pair at 4 deg, not 16) and, with --mapper auto, the global mapper, whose model is used only if it agrees with the
    incremental one on the photos both placed; the model with the most photos is kept, and the summary lists every
    attempt. 1: retry while any such photo is left out; 0: no retries. Each retry costs about one mapping stage."""
    seed: int = 0
    """Random seed of the mapper (RANSAC, image selection)."""
    num_threads: int = -1
    """CPU threads for extraction, matching and mapping; -1: all cores."""
    min_registered: int = 3
    """Fail unless at least this many images are registered (fewer cannot define a scene)."""
    max_image_size: int = 3200
    """Photos whose long side is larger are resized to this many px (PIL's area filter) for SfM and training, so that
    one huge photo does not make every training step need tens of GB; the summary names them. 0 keeps every photo at
    full size."""
    num_downscales: int = 0
    """Also write images_2, images_4, ... images_(2**num_downscales) (floor size), for nerfstudio's
    --downscale-factor."""
    test_every: int = 8
    """Split: every test_every-th registered image (COLMAP id order) is a test image, as nerfstudio's
    eval_interval rule; 0 puts every image in train."""
    scene_name: str | None = None
    """Name of the split file (<scene_name>.tsv) and its dataset column; default: the output folder's name."""
    verbose: bool = False
    """Show COLMAP's own log (otherwise only its errors)."""


# --------------------------------------------------------------------------------------------------------------------
# inputs


def list_images(images_dir: Path) -> list[str]:
    """Sorted file names of the photos in `images_dir` (top level only)."""
    if not images_dir.is_dir():
        raise ProcessError(f"--images {images_dir} is not a folder")
    names = sorted(p.name for p in images_dir.iterdir() if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES)
    if not names:
        raise ProcessError(f"--images {images_dir} holds no photos ({', '.join(IMAGE_SUFFIXES)})")
    return names


def find_unreadable(images_dir: Path, names: Sequence[str]) -> dict[str, str]:
    """{name: reason} for every photo that PIL cannot decode completely (empty, corrupt or truncated files)."""
    bad = {}
    for name in names:
        try:
            with Image.open(images_dir / name) as im:
                im.load()  # decodes every pixel: catches truncated files that open() alone accepts
                if im.width < 16 or im.height < 16:
                    bad[name] = f"too small ({im.width}x{im.height})"
        except Exception as e:  # PIL raises OSError, SyntaxError, ValueError... depending on the codec
            bad[name] = f"{type(e).__name__}: {e}"
    return bad


CAPPED_DIR = Path("colmap") / "inputs"
"""Under the output: the photos SfM reads when some are larger than --max-image-size (the others linked)."""


def cap_photos(cfg: ProcessConfig, names: Sequence[str]) -> tuple[Path, dict[str, tuple[int, int, int, int]]]:
    """(folder SfM reads, {name: (w, h, new w, new h)} of the photos resized). Photos with a long side above
    ``cfg.max_image_size`` are resized (area filter, EXIF kept for COLMAP's focal-length prior) into
    OUTPUT/colmap/inputs/, the others symbolically linked there; without such photos (or with max_image_size 0),
    ``cfg.images`` itself. A rerun reuses resized copies of the right size."""
    cap = cfg.max_image_size
    if cap <= 0:
        return cfg.images, {}
    resized: dict[str, tuple[int, int, int, int]] = {}
    for name in names:
        with Image.open(cfg.images / name) as im:
            w, h = im.size
        if max(w, h) > cap:
            scale = cap / max(w, h)
            resized[name] = (w, h, max(1, round(w * scale)), max(1, round(h * scale)))
    if not resized:
        return cfg.images, {}
    out = cfg.output / CAPPED_DIR
    out.mkdir(parents=True, exist_ok=True)
    for name in names:
        src, dst = (cfg.images / name).resolve(), out / name
        if name not in resized:
            if not dst.is_symlink() or dst.resolve() != src:
                dst.unlink(missing_ok=True)
                os.symlink(src, dst)
            continue
        size = resized[name][2:]
        if dst.is_file() and not dst.is_symlink():
            with Image.open(dst) as im:
                if im.size == size:
                    continue
        dst.unlink(missing_ok=True)
        tmp = out / f".{name}.partial{src.suffix}"
        with Image.open(src) as im:
            small = im.resize(size, resample=Image.Resampling.BOX)
            kwargs: dict[str, Any] = {"exif": im.info["exif"]} if "exif" in im.info else {}
            if src.suffix.lower() in (".jpg", ".jpeg"):
                small.convert("RGB").save(tmp, quality=95, subsampling=0, format="JPEG", **kwargs)
            else:
                small.save(tmp, format=im.format, **kwargs)
        os.replace(tmp, dst)
    return out, resized


def split_table(image_ids: dict[int, str], test_every: int) -> list[tuple[str, int, str]]:
    """(filename, id, split) per registered image, in COLMAP id order: index % test_every == 0 -> "test".

    The same images nerfstudio's colmap parser holds out with eval_mode=interval, eval_interval=test_every (it also
    sorts by id), so a tsv-aware parser and the stock one agree."""
    rows = []
    for k, image_id in enumerate(sorted(image_ids)):
        test = test_every > 0 and k % test_every == 0
        rows.append((image_ids[image_id], image_id, "test" if test else "train"))
    return rows


def write_split_tsv(path: Path, rows: Sequence[tuple[str, int, str]], dataset: str) -> None:
    """NeRF-W / PhotoTourism split file: tab-separated `filename id split dataset` with a header."""
    lines = ["filename\tid\tsplit\tdataset"] + [f"{name}\t{i}\t{split}\t{dataset}" for name, i, split in rows]
    write_text_atomic(path, "\n".join(lines) + "\n")


def exhaustive_pair_blocks(names: Sequence[str], block: int = 12) -> list[list[tuple[str, str]]]:
    """All n(n-1)/2 pairs, grouped by blocks of `block` images (pairs between block a and block b >= a), so that one
    matching call reads the descriptors of at most 2 * block images."""
    starts = range(0, len(names), block)
    out = []
    for a in starts:
        for b in starts:
            if b < a:
                continue
            pairs = [
                (names[i], names[j])
                for i in range(a, min(a + block, len(names)))
                for j in range(max(b, i + 1), min(b + block, len(names)))
            ]
            if pairs:
                out.append(pairs)
    return out


# --------------------------------------------------------------------------------------------------------------------
# pose comparison (tests, docs/process.md)


def umeyama(src: np.ndarray, dst: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    """Least-squares similarity dst ~ s * R @ src + t (Umeyama 1991). src, dst [N, 3], N >= 3. Returns s, R, t."""
    mu_s, mu_d = src.mean(0), dst.mean(0)
    xs, xd = src - mu_s, dst - mu_d
    cov = xd.T @ xs / len(src)
    u, d, vt = np.linalg.svd(cov)
    sign = np.eye(3)
    if np.linalg.det(u) * np.linalg.det(vt) < 0:  # a reflection fits better: take the best rotation instead
        sign[2, 2] = -1
    rot = u @ sign @ vt
    var_s = (xs**2).sum() / len(src)
    scale = float(np.trace(np.diag(d) @ sign) / var_s)
    return scale, rot, mu_d - scale * rot @ mu_s


def rotation_mean(rotations: np.ndarray) -> np.ndarray:
    """Chordal L2 mean of rotations [N, 3, 3]: the rotation nearest (Frobenius) to their average."""
    u, _, vt = np.linalg.svd(rotations.sum(0))
    sign = np.diag([1.0, 1.0, np.sign(np.linalg.det(u @ vt))])
    return u @ sign @ vt


def rotation_errors_deg(ref_rot: np.ndarray, est_rot: np.ndarray) -> np.ndarray:
    """[N] angles in degrees of R_ref_i^T R_est_i for camera-to-world rotations [N, 3, 3] already in one frame."""
    rel = np.einsum("nji,njk->nik", ref_rot, est_rot)
    # angle from both the trace (cos) and the skew part (sin): arccos alone loses precision near 0
    skew = np.stack([rel[:, 2, 1] - rel[:, 1, 2], rel[:, 0, 2] - rel[:, 2, 0], rel[:, 1, 0] - rel[:, 0, 1]], -1)
    return np.degrees(np.arctan2(np.linalg.norm(skew, axis=-1) / 2, (np.trace(rel, axis1=1, axis2=2) - 1) / 2))


def compare_poses(
    est_w2c: dict[str, np.ndarray],
    ref_w2c: dict[str, np.ndarray],
    align: str = "poses",
    trim: float = 3.0,
) -> dict[str, Any]:
    """Errors of estimated camera poses against reference poses after a similarity alignment.

    Poses are world-to-camera [4, 4] (COLMAP convention; any convention works if both sides use it) keyed by image
    name. The similarity ref ~ s * R @ est + t:

    - align="centres": Umeyama on the camera centres, refitted on those within `trim` x the median residual (a few
      badly placed cameras do not drag the others). Ill-conditioned in rotation when the centres are nearly
      collinear or clustered (tourists on one square): an error of the alignment, not of the poses;
    - align="poses" (default): R = the chordal mean of R_ref_i R_est_i^T (camera-to-world rotations), which every
      camera constrains fully; s and t are then the least-squares fit of the centres (with the same trimming).

    Rotation error: angle of R_ref^T R R_est (camera-to-world rotations). Centre errors are also given relative to
    the reference extent: the largest distance between two reference camera centres.
    """
    if align not in ("poses", "centres"):
        raise ValueError(f"align must be 'poses' or 'centres', got {align!r}")
    common = sorted(set(est_w2c) & set(ref_w2c))
    if len(common) < 3:
        raise ValueError(f"need >= 3 images in both models to align them, got {len(common)}")
    est_c2w = np.stack([np.linalg.inv(est_w2c[n]) for n in common])
    ref_c2w = np.stack([np.linalg.inv(ref_w2c[n]) for n in common])
    src, dst = est_c2w[:, :3, 3], ref_c2w[:, :3, 3]
    fixed_rot = None
    if align == "poses":
        fixed_rot = rotation_mean(np.einsum("nij,nkj->nik", ref_c2w[:, :3, :3], est_c2w[:, :3, :3]))

    def fit(sel: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
        if fixed_rot is None:
            return umeyama(src[sel], dst[sel])
        xs, xd = src[sel] - src[sel].mean(0), dst[sel] - dst[sel].mean(0)
        scale = float((xd * (xs @ fixed_rot.T)).sum() / (xs**2).sum())
        return scale, fixed_rot, dst[sel].mean(0) - scale * fixed_rot @ src[sel].mean(0)

    s, rot, t = fit(np.ones(len(common), dtype=bool))
    res = np.linalg.norm(s * src @ rot.T + t - dst, axis=1)
    keep = res <= trim * max(np.median(res), 1e-12)
    if keep.sum() >= 3:
        s, rot, t = fit(keep)
    centre_err = np.linalg.norm(s * src @ rot.T + t - dst, axis=1)
    rot_err = rotation_errors_deg(ref_c2w[:, :3, :3], rot @ est_c2w[:, :3, :3])
    extent = float(np.max(np.linalg.norm(dst[:, None] - dst[None], axis=-1)))
    return {
        "align": align,
        "num_common": len(common),
        "scale": s,
        "rotation_error_deg": dict(zip(common, rot_err.tolist(), strict=True)),
        "centre_error": dict(zip(common, centre_err.tolist(), strict=True)),
        "median_rotation_error_deg": float(np.median(rot_err)),
        "max_rotation_error_deg": float(rot_err.max()),
        "median_centre_error": float(np.median(centre_err)),
        "reference_extent": extent,
        "median_centre_error_pct": float(100 * np.median(centre_err) / extent),
        "max_centre_error_pct": float(100 * centre_err.max() / extent),
    }


def model_w2c(model_dir: Path) -> dict[str, np.ndarray]:
    """{image name: world-to-camera [4, 4]} of the registered images of a COLMAP model."""
    import pycolmap

    return rec_w2c(pycolmap.Reconstruction(str(model_dir)))


def rec_w2c(rec) -> dict[str, np.ndarray]:
    """{image name: world-to-camera [4, 4]} of the registered images of a pycolmap Reconstruction."""
    out = {}
    for image_id in rec.reg_image_ids():
        im = rec.images[image_id]
        w2c = np.eye(4)
        w2c[:3, :4] = im.cam_from_world().matrix()
        out[im.name] = w2c
    return out


# --------------------------------------------------------------------------------------------------------------------
# interruption


@contextmanager
def cancellable() -> Iterator[Any]:
    """A pycolmap CancellationToken cancelled by Ctrl-C; KeyboardInterrupt is raised once the C++ call returns
    (also where the call reports the cancellation as InterruptedError, as vocabulary-tree matching does).

    Why: while pycolmap runs C++ code, Python's own SIGINT handler only runs when the call returns (minutes for
    matching or mapping). The token makes COLMAP stop at its next check (next image, pair block or registration),
    with every database write before it committed. A second Ctrl-C falls back to the default handler.
    """
    import pycolmap

    token = pycolmap.CancellationToken()
    if threading.current_thread() is not threading.main_thread():
        yield token
        return
    previous = signal.getsignal(signal.SIGINT)

    def handler(signum, frame):
        token.cancel()
        signal.signal(signal.SIGINT, signal.default_int_handler)

    signal.signal(signal.SIGINT, handler)
    try:
        yield token
    except InterruptedError:  # pycolmap's "Operation cancelled": ours when the token was cancelled
        if not token.is_cancelled:
            raise
    finally:
        signal.signal(signal.SIGINT, previous)
    if token.is_cancelled:
        raise KeyboardInterrupt


# --------------------------------------------------------------------------------------------------------------------
# the stages


def _progress():
    """A bar per stage on a terminal; in a log, a line per stage every half minute (willags_ns.tools.progress)."""
    from nerfstudio.utils.rich_utils import CONSOLE
    from rich.progress import BarColumn, MofNCompleteColumn, TextColumn, TimeElapsedColumn

    from willags_ns.tools.progress import Progress

    return Progress(
        TextColumn("[bold blue]{task.description:<22}"),
        BarColumn(),
        MofNCompleteColumn(),
        TimeElapsedColumn(),
        console=CONSOLE,
        transient=False,
        label="willags-process",
    )


def _options_stamp(cfg: ProcessConfig, capped: bool = False, exif_grouped: bool = False) -> dict[str, Any]:
    """The options that decide what the database holds: a rerun with other values cannot reuse it. The size cap
    only where it resized a photo, EXIF camera sharing only where photos share an EXIF camera (the database of a
    collection they leave alone is the same either way)."""
    stamp = {
        "camera_model": cfg.camera_model,
        "single_camera": cfg.single_camera,
        "max_num_features": cfg.max_num_features,
        "max_feature_image_size": cfg.max_feature_image_size,
        "images": str(cfg.images.resolve()),
    }
    if capped:
        stamp["max_image_size"] = cfg.max_image_size
    if exif_grouped:
        stamp["exif_cameras"] = True
    return stamp


def _database_names(db: Path) -> set[str]:
    """The image names the database holds."""
    import sqlite3

    with closing(sqlite3.connect(f"file:{db}?mode=ro", uri=True)) as con:
        return {row[0] for row in con.execute("SELECT name FROM images")}


def _check_database_options(cfg: ProcessConfig, resized: Collection[str] = (), exif_grouped: bool = False) -> None:
    """Refuse a database made with options that change what it holds (_options_stamp), naming them. The size cap
    counts only for the photos it resizes: a database made when no photo was resized holds every photo at full size,
    so a photo added since and resized now (one big photo added to the folder) extends it; a resized photo the
    database already holds at full size does not."""
    stamp = cfg.output / OPTIONS_STAMP
    db = cfg.output / DATABASE
    want = _options_stamp(cfg, capped=bool(resized), exif_grouped=exif_grouped)
    if db.exists() and stamp.is_file():
        try:
            have = json.loads(stamp.read_text(encoding="utf-8"))
            if not isinstance(have, dict):
                raise ValueError(f"a JSON {type(have).__name__}, not an object")
        except (OSError, ValueError) as e:  # JSONDecodeError and UnicodeDecodeError are ValueErrors
            raise ProcessError(
                f"{stamp} cannot be read ({e}): it records the options {db} was made with; delete both (or use "
                "another --output) to start over"
            ) from None
        diff = {k: (have.get(k), v) for k, v in want.items() if have.get(k) != v}
        if "max_image_size" in diff and "max_image_size" not in have and not set(resized) & _database_names(db):
            del diff["max_image_size"]
        if diff:
            raise ProcessError(
                f"{db} was made with other options {diff} (old, new): delete it (or use another --output) to start over"
            )
    stamp.parent.mkdir(parents=True, exist_ok=True)
    write_text_atomic(stamp, json.dumps(want, indent=1) + "\n")


EXIF_MAKE, EXIF_MODEL, EXIF_IFD, EXIF_FOCAL_LENGTH = 0x010F, 0x0110, 0x8769, 0x920A


def exif_camera_key(path: Path) -> tuple[str, str, float, int, int] | None:
    """(make, model, focal length in mm, width, height) from a photo's EXIF and size, or None without an EXIF focal
    length: photos with the same key come from one camera and lens at one zoom."""
    try:
        with Image.open(path) as im:
            exif = im.getexif()
            focal = exif.get_ifd(EXIF_IFD).get(EXIF_FOCAL_LENGTH)
            if focal is None or float(focal) <= 0:
                return None
            make, model = (str(exif.get(tag, "")).strip("\x00 ") for tag in (EXIF_MAKE, EXIF_MODEL))
            return make, model, round(float(focal), 3), im.width, im.height
    except (OSError, ValueError, ZeroDivisionError, TypeError):  # unreadable EXIF: a camera of its own
        return None


def camera_groups(cfg: ProcessConfig, names: Sequence[str]) -> list[list[str]]:
    """The photos that share one camera (intrinsics), each group sorted: every photo in one group with
    --single-camera; with exif_cameras, the photos of one EXIF camera key (exif_camera_key) of two photos or more;
    the photos in no group get a camera each."""
    if cfg.single_camera:
        return [sorted(names)]
    if not cfg.exif_cameras:
        return []
    by_key: dict[tuple, list[str]] = {}
    for name in names:
        key = exif_camera_key(cfg.images / name)
        if key is not None:
            by_key.setdefault(key, []).append(name)
    return sorted((sorted(g) for g in by_key.values() if len(g) > 1), key=lambda g: g[0])


def camera_sharing_words(cfg: ProcessConfig, groups: Sequence[Sequence[str]], num_photos: int) -> str:
    """How the photos share cameras, for the summary: ", one shared camera", ", 2 EXIF cameras for 40 photos, one
    camera per other photo" or ", one camera per image"."""
    if cfg.single_camera:
        return ", one shared camera"
    if not groups:
        return ", one camera per image"
    shared = sum(len(g) for g in groups)
    rest = num_photos - shared
    return f", {len(groups)} EXIF camera(s) for {shared} photos" + (
        f", one camera per other photo ({rest})" if rest else ""
    )


def extract_features(
    cfg: ProcessConfig, names: Sequence[str], progress, groups: Sequence[Sequence[str]] | None = None, chunk: int = 8
) -> list[str]:
    """SIFT for every image of `names` not yet in the database, `chunk` images per call (progress and Ctrl-C between
    calls; one image per call would cost ~0.4 s of set-up each). The photos of a camera group (camera_groups) share
    the camera the group's first extracted photo got, across calls and reruns. Returns the names with features in
    the database. ``groups``: camera_groups(cfg, names) when not given."""
    import pycolmap

    db_path = cfg.output / DATABASE
    groups = camera_groups(cfg, names) if groups is None else groups
    camera_of: dict[int, int] = {}  # group index -> camera id already in the database
    with pycolmap.Database.open(str(db_path)) as db:
        done = set()
        for name in names:
            im = db.read_image_with_name(name)
            if im is not None and db.exists_keypoints(im.image_id) and db.exists_descriptors(im.image_id):
                done.add(name)
        for g, members in enumerate(groups):
            for name in members:
                im = db.read_image_with_name(name)
                if im is not None:
                    camera_of[g] = im.camera_id
                    break
    extraction = pycolmap.FeatureExtractionOptions()
    extraction.num_threads = cfg.num_threads
    extraction.max_image_size = cfg.max_feature_image_size
    extraction.sift.max_num_features = cfg.max_num_features
    task = progress.add_task("feature extraction", total=len(names), completed=len(done))
    grouped = {n for members in groups for n in members}
    calls: list[tuple[int | None, list[str]]] = []  # (group index or None: a camera per photo, names)
    for g, members in enumerate(groups):
        todo = [n for n in members if n not in done]
        calls += [(g, todo[k : k + chunk]) for k in range(0, len(todo), chunk)]
    todo = [n for n in names if n not in done and n not in grouped]
    calls += [(None, todo[k : k + chunk]) for k in range(0, len(todo), chunk)]
    order = {n: i for i, n in enumerate(names)}
    calls.sort(key=lambda c: order[c[1][0]])  # the folder's order, as before groups existed
    for g, batch in calls:
        reader = pycolmap.ImageReaderOptions()
        reader.camera_model = cfg.camera_model
        mode = pycolmap.CameraMode.PER_IMAGE
        if g is not None:
            mode = pycolmap.CameraMode.SINGLE
            if g in camera_of:
                reader.existing_camera_id = camera_of[g]
        with cancellable() as token:
            pycolmap.extract_features(
                str(db_path),
                str(cfg.images),
                image_names=batch,
                camera_mode=mode,
                reader_options=reader,
                extraction_options=extraction,
                device=pycolmap.Device.cpu,
                cancellation_token=token,
            )
        if g is not None and g not in camera_of:
            with pycolmap.Database.open(str(db_path)) as db:
                im = db.read_image_with_name(batch[0])
                if im is not None:
                    camera_of[g] = im.camera_id
        progress.advance(task, len(batch))
    with pycolmap.Database.open(str(db_path)) as db:
        ok = []
        for name in names:
            im = db.read_image_with_name(name)
            if im is not None and db.exists_keypoints(im.image_id) and db.num_keypoints_for_image(im.image_id) > 0:
                ok.append(name)
    return ok


def _matched_pairs(db_path: Path) -> set[tuple[str, str]]:
    """Name pairs (sorted) that already have matches in the database (matched in an earlier, interrupted run)."""
    import pycolmap

    with pycolmap.Database.open(str(db_path)) as db:
        id_to_name = {im.image_id: im.name for im in db.read_all_images()}
        pair_ids, _ = db.read_num_matches()
    out = set()
    for pid in pair_ids:
        a, b = pycolmap.pair_id_to_image_pair(pid)
        if a in id_to_name and b in id_to_name:
            out.add(tuple(sorted((id_to_name[a], id_to_name[b]))))
    return out


def _matching_options(cfg: ProcessConfig):
    import pycolmap

    matching = pycolmap.FeatureMatchingOptions()
    matching.num_threads = cfg.num_threads
    return matching


def match_exhaustive(cfg: ProcessConfig, names: Sequence[str], progress) -> int:
    """Match and verify all pairs, a block of pairs per call (progress, Ctrl-C between blocks). Returns #pairs."""
    import pycolmap

    db_path = cfg.output / DATABASE
    blocks = exhaustive_pair_blocks(names)
    total = sum(len(b) for b in blocks)
    if any(any(c.isspace() for c in n) for n in names):
        # COLMAP's pair lists are space-separated: names with spaces can only go through its own exhaustive matcher
        task = progress.add_task("matching (exhaustive)", total=None)
        with cancellable() as token:
            pycolmap.match_exhaustive(
                str(db_path),
                matching_options=_matching_options(cfg),
                device=pycolmap.Device.cpu,
                cancellation_token=token,
            )
        progress.update(task, total=total, completed=total)
        return total
    done = _matched_pairs(db_path)
    task = progress.add_task("matching (exhaustive)", total=total)
    pairs_file = cfg.output / "colmap" / "pairs_block.txt"
    for block in blocks:
        todo = [p for p in block if tuple(sorted(p)) not in done]
        if todo:
            pairs_file.write_text("".join(f"{a} {b}\n" for a, b in todo))
            with cancellable() as token:
                pycolmap.match_image_pairs(
                    str(db_path),
                    matching_options=_matching_options(cfg),
                    pairing_options=pycolmap.ImportedPairingOptions(match_list_path=str(pairs_file)),
                    device=pycolmap.Device.cpu,
                    cancellation_token=token,
                )
        progress.advance(task, len(block))
    pairs_file.unlink(missing_ok=True)
    return total


def build_vocab_tree(db_path: Path, out: Path, per_image: int = 500, seed: int = 0) -> int:
    """A vocabulary tree (pycolmap VisualIndex) trained on up to `per_image` SIFT descriptors of each image of the
    database, written to `out`. Returns its number of visual words (about 40 training descriptors per word, 256 to
    65,536). Why our own: COLMAP's published trees are a download, and this machine may have no internet."""
    import pycolmap

    rng = np.random.default_rng(seed)
    samples = []
    with pycolmap.Database.open(str(db_path)) as db:
        for im in db.read_all_images():
            if not db.exists_descriptors(im.image_id):
                continue
            d = db.read_descriptors(im.image_id).to_float().data
            if len(d) > per_image:
                d = d[rng.choice(len(d), per_image, replace=False)]
            samples.append(d)
    train = np.ascontiguousarray(np.concatenate(samples).astype(np.float32))
    words = int(2 ** np.clip(np.floor(np.log2(max(len(train) // 40, 1))), 8, 16))
    options = pycolmap.VisualIndex.BuildOptions()
    options.num_visual_words = words
    # k-means: COLMAP's 100 iterations x 3 rounds take minutes on 2 cores for a large collection; retrieval only
    # needs a rough quantiser (the pairs it proposes are verified geometrically anyway)
    options.num_iterations = 25
    options.num_rounds = 1
    index = pycolmap.VisualIndex.create(128, 64)  # SIFT descriptors, the only embedding size pycolmap implements
    index.build(options, pycolmap.FeatureDescriptorsFloat(data=train, type=pycolmap.FeatureExtractorType.SIFT))
    out.parent.mkdir(parents=True, exist_ok=True)
    index.write(str(out))
    return words


def match_vocab_tree(cfg: ProcessConfig, names: Sequence[str], progress, chunk: int = 8) -> int:
    """Retrieval matching: each image with its `retrieval_neighbors` most similar images by vocabulary tree, a chunk of
    query images per call (progress, Ctrl-C between chunks). Returns the number of pairs in the database."""
    import pycolmap

    db_path = cfg.output / DATABASE
    tree = cfg.output / VOCAB_TREE
    if not tree.is_file():
        build_vocab_tree(db_path, tree, seed=cfg.seed)
    queried_file = cfg.output / "colmap" / "vocab_tree_queried.txt"  # resume: query images already done
    queried = set(queried_file.read_text().splitlines()) if queried_file.is_file() else set()
    if not _matched_pairs(db_path):
        queried = set()  # a new database (the old one deleted): the list belongs to the old one
    task = progress.add_task("matching (vocab tree)", total=len(names))
    list_file = cfg.output / "colmap" / "vocab_tree_queries.txt"
    for k in range(0, len(names), chunk):
        todo = [n for n in names[k : k + chunk] if n not in queried]
        if todo:
            list_file.write_text("".join(n + "\n" for n in todo))
            pairing = pycolmap.VocabTreePairingOptions()
            pairing.vocab_tree_path = str(tree)
            pairing.num_images = cfg.retrieval_neighbors + 1  # the query itself is its own best match
            pairing.match_list_path = str(list_file)
            pairing.num_threads = cfg.num_threads
            with cancellable() as token:
                pycolmap.match_vocabtree(
                    str(db_path),
                    matching_options=_matching_options(cfg),
                    pairing_options=pairing,
                    device=pycolmap.Device.cpu,
                    cancellation_token=token,
                )
            with queried_file.open("a") as f:
                f.write("".join(n + "\n" for n in todo))
        progress.advance(task, len(names[k : k + chunk]))
    list_file.unlink(missing_ok=True)
    return len(_matched_pairs(db_path))


def incremental_mapping(
    cfg: ProcessConfig, num_images: int, progress, work: Path, relax: dict[str, float] | None = None, label: str = ""
):
    """COLMAP's incremental mapper (fixed seed); returns the reconstruction with the most registered images, or
    None when no model could be made. ``relax``: IncrementalMapperOptions fields set instead of COLMAP's defaults
    (RETRY_STEPS); ``label`` names the attempt on its progress bar."""
    import pycolmap

    options = pycolmap.IncrementalPipelineOptions()
    options.num_threads = cfg.num_threads
    options.random_seed = cfg.seed
    options.mapper.random_seed = cfg.seed
    options.triangulation.random_seed = cfg.seed
    # COLMAP drops models under 10 images; a small collection's only model may be smaller and still usable
    options.min_model_size = max(3, min(10, cfg.min_registered))
    for name, value in (relax or {}).items():
        setattr(options.mapper, name, value)
    pycolmap.set_random_seed(cfg.seed)
    task = progress.add_task(f"incremental mapping{f' ({label})' if label else ''}", total=num_images)
    registered = [0]

    def on_init_pair() -> None:
        registered[0] = 2
        progress.update(task, completed=min(registered[0], num_images))

    def on_next_image() -> None:
        registered[0] += 1
        progress.update(task, completed=min(registered[0], num_images))

    shutil.rmtree(work, ignore_errors=True)
    work.mkdir(parents=True)
    with cancellable() as token:
        models = pycolmap.incremental_mapping(
            str(cfg.output / DATABASE),
            str(cfg.images),
            str(work),
            options,
            initial_image_pair_callback=on_init_pair,
            next_image_callback=on_next_image,
            cancellation_token=token,
        )
    if not models:
        return None
    best = max(models.values(), key=lambda r: r.num_reg_images())
    progress.update(task, completed=best.num_reg_images())
    return best


def global_mapping(cfg: ProcessConfig, num_images: int, progress, work: Path):
    """GLOMAP (pycolmap.global_mapping, fixed seed): all images positioned at once; returns the reconstruction with
    the most registered images, or None. Ctrl-C takes effect when it returns (pycolmap offers no cancellation)."""
    import pycolmap

    options = pycolmap.GlobalPipelineOptions()
    options.num_threads = cfg.num_threads
    options.random_seed = cfg.seed
    options.min_model_size = max(3, min(10, cfg.min_registered))
    pycolmap.set_random_seed(cfg.seed)
    task = progress.add_task("global mapping", total=num_images)
    shutil.rmtree(work, ignore_errors=True)
    work.mkdir(parents=True)
    models = pycolmap.global_mapping(str(cfg.output / DATABASE), str(cfg.images), str(work), options)
    if not models:
        return None
    best = max(models.values(), key=lambda r: r.num_reg_images())
    progress.update(task, completed=best.num_reg_images())
    return best


def chosen_mapper(cfg: ProcessConfig, num_images: int) -> str:
    """The mapper that runs: cfg.mapper, or for "auto" incremental below global_min_images images and global from
    there."""
    if cfg.mapper != "auto":
        return cfg.mapper
    return "global" if num_images >= cfg.global_min_images else "incremental"


@dataclass(frozen=True)
class RetryStep:
    """One retry of the incremental mapper with relaxed thresholds (IncrementalMapperOptions fields)."""

    name: str
    """Short name, in the summary and the progress bar."""
    what: str
    """What it changes, in words (the summary prints it)."""
    relax: dict[str, float]
    """IncrementalMapperOptions field -> value, instead of COLMAP's default."""


RETRY_STEPS = (
    RetryStep(
        "relaxed registration",
        "a photo is placed from 15 inlier matches with the model's points (COLMAP: 30)",
        {"abs_pose_min_num_inliers": 15},
    ),
    RetryStep(
        "relaxed initialisation",
        "as relaxed registration, and the first pair may have a 4 deg triangulation angle (COLMAP: 16) and move "
        "straight forward (COLMAP: forward motion at most 0.95)",
        {"abs_pose_min_num_inliers": 15, "init_min_tri_angle": 4.0, "init_max_forward_motion": 1.0},
    ),
)
"""The incremental mapper's retries, in order, while a model holds fewer than retry_below of the photos. Why these
(docs/process.md): tourist photos (liberty: 47-53 of 90 with COLMAP's defaults) fall apart into partial models that
15 inliers join (75-86 of 90); a forward-moving street walk (lund) has no first pair with a 16 deg angle (2 of 29
with COLMAP's defaults, 3-21 with relaxed registration, 21-26 with relaxed initialisation)."""

MAX_RETRY_REPROJECTION_PX = 1.5
"""A retry's model (or the global mapper's) is kept only if its mean reprojection error is at most this many px; the
measured models had 0.3-0.8 px."""

GLOBAL_CHECK_MIN_COMMON = 5
"""The global mapper's model is checked against the incremental one on the photos both placed: at least this many."""
GLOBAL_CHECK_MAX_ROTATION_DEG = 2.0
"""... the median rotation error after a similarity alignment (compare_poses) must be at most this,"""
GLOBAL_CHECK_MAX_CENTRE_PCT = 5.0
"""... and the median centre error at most this % of the incremental model's extent. On liberty the global model
places all 90 photos at 0.58 px yet is 41 deg off; on lund it agrees to 0.2 deg and 0.7 %."""


def _registered_names(rec) -> set[str]:
    return {rec.images[i].name for i in rec.reg_image_ids()}


def models_agreement(a, b) -> dict[str, Any]:
    """compare_poses of two reconstructions over the photos both placed, ``b`` as the reference."""
    return compare_poses(rec_w2c(a), rec_w2c(b))


def map_with_retries(
    cfg: ProcessConfig,
    num_images: int,
    mapper: str,
    run_incremental: Callable[[RetryStep | None], Any],
    run_global: Callable[[], Any],
    agreement: Callable[[Any, Any], dict[str, Any]] = models_agreement,
) -> tuple[Any, list[dict[str, Any]]]:
    """Mapping with the retry ladder: (the kept reconstruction or None, one entry per attempt).

    ``mapper`` "global" (chosen or --mapper global): the global mapper once. Otherwise the incremental mapper with
    COLMAP's defaults (``run_incremental(None)``), then, while the best model holds fewer than ``cfg.retry_below`` of
    the ``num_images`` photos (those that could be placed), each of RETRY_STEPS (kept when it places more photos at a mean reprojection error of
    at most MAX_RETRY_REPROJECTION_PX), then with --mapper auto the global mapper (``run_global()``), kept only if it
    places more photos and agrees with the best incremental model on the photos both placed (GLOBAL_CHECK_*).
    Each entry: step, what, registered, mean_reprojection_error_px, seconds, kept, note (why not kept, or the check).
    """
    attempts: list[dict[str, Any]] = []

    def attempt(step: str, what: str, fn: Callable[[], Any]) -> tuple[Any, dict[str, Any]]:
        t = time.time()
        rec = fn()
        entry = {
            "step": step,
            "what": what,
            "registered": 0 if rec is None else int(rec.num_reg_images()),
            "mean_reprojection_error_px": None if rec is None else float(rec.compute_mean_reprojection_error()),
            "seconds": time.time() - t,
            "kept": False,
            "note": "no model" if rec is None else "",
        }
        attempts.append(entry)
        return rec, entry

    if mapper == "global":
        rec, entry = attempt("global mapper", "GLOMAP: every photo positioned at once", run_global)
        entry["kept"] = rec is not None
        return rec, attempts
    best, best_entry = attempt(
        "default", "COLMAP's incremental mapper with its default thresholds", lambda: run_incremental(None)
    )
    retry = cfg.retry_below > 0

    def enough() -> bool:
        return best is not None and best.num_reg_images() >= cfg.retry_below * num_images

    for step in RETRY_STEPS if retry else ():
        if enough():
            break
        rec, entry = attempt(step.name, step.what, lambda step=step: run_incremental(step))
        if rec is None:
            continue
        if entry["mean_reprojection_error_px"] > MAX_RETRY_REPROJECTION_PX:
            entry["note"] = f"mean reprojection error above {MAX_RETRY_REPROJECTION_PX} px"
        elif best is None or rec.num_reg_images() > best.num_reg_images():
            best, best_entry = rec, entry
        else:
            entry["note"] = f"placed no more photos than {best_entry['step']}"
    if retry and cfg.mapper == "auto" and not enough():
        rec, entry = attempt("global mapper", "GLOMAP, checked against the incremental model", run_global)
        if rec is not None:
            ok, entry["note"] = _global_check(rec, best, agreement)
            if ok:
                best, best_entry = rec, entry
    if best is not None:
        best_entry["kept"] = True
    return best, attempts


def kept_mapper(attempts: Sequence[dict[str, Any]], mapper: str) -> str:
    """The mapper whose model was kept, in words: "incremental", "incremental, relaxed registration", "global"."""
    kept = next((a["step"] for a in attempts if a["kept"]), None)
    if kept is None or kept == "default":
        return mapper
    if kept == "global mapper":
        return "global" if mapper == "global" else "global (checked against the incremental model)"
    return f"incremental, {kept}"


def _global_check(rec, best, agreement: Callable[[Any, Any], dict[str, Any]]) -> tuple[bool, str]:
    """(whether the global mapper's model ``rec`` replaces the incremental model ``best``, why in words)."""
    placed = best.num_reg_images() if best is not None else 0
    if rec.num_reg_images() <= placed:
        return False, "placed no more photos than the incremental mapper"
    if rec.compute_mean_reprojection_error() > MAX_RETRY_REPROJECTION_PX:
        return False, f"mean reprojection error above {MAX_RETRY_REPROJECTION_PX} px"
    common = len(_registered_names(rec) & _registered_names(best)) if best is not None else 0
    if common < GLOBAL_CHECK_MIN_COMMON:
        return False, (
            f"not used: it shares {common} photo(s) with the incremental model and the check needs "
            f"{GLOBAL_CHECK_MIN_COMMON}; --mapper global uses it unchecked"
        )
    cmp_ = agreement(rec, best)
    rot, ctr = cmp_["median_rotation_error_deg"], cmp_["median_centre_error_pct"]
    words = f"on the {cmp_['num_common']} photos both placed (median {rot:.1f} deg, {ctr:.1f} % of the extent)"
    if rot > GLOBAL_CHECK_MAX_ROTATION_DEG or ctr > GLOBAL_CHECK_MAX_CENTRE_PCT:
        return False, f"not used: it disagrees with the incremental model {words}"
    return True, f"agrees with the incremental model {words}"


# --------------------------------------------------------------------------------------------------------------------
# writing


def _replace_dir(tmp: Path, dst: Path) -> None:
    """Move the complete directory `tmp` onto `dst` (the old `dst`, if any, is removed first)."""
    dst.parent.mkdir(parents=True, exist_ok=True)
    if dst.exists():
        shutil.rmtree(dst)
    os.rename(tmp, dst)


def write_downscaled(images: Path, factor: int, dst: Path) -> None:
    """Every image of `images` resized to floor(w / factor) x floor(h / factor) (nerfstudio's 'floor' rounding of the
    camera) with PIL's box (area) filter, into `dst` (written to a temporary sibling, then renamed)."""
    tmp = dst.parent / f".{dst.name}.tmp"
    shutil.rmtree(tmp, ignore_errors=True)
    tmp.mkdir(parents=True)
    for f in sorted(images.iterdir()):
        save_downscaled(f, factor, tmp / f.name)
    _replace_dir(tmp, dst)


def write_scene(cfg: ProcessConfig, rec, work: Path) -> None:
    """The registered images and the model where nerfstudio reads them (undistorted for SIMPLE_RADIAL)."""
    import pycolmap

    out = cfg.output
    raw = work / "chosen"
    raw.mkdir(parents=True)
    rec.write(str(raw))
    names = [rec.images[i].name for i in rec.reg_image_ids()]
    if cfg.camera_model == "SIMPLE_PINHOLE":
        images_tmp = work / "images"
        images_tmp.mkdir()
        for name in names:
            shutil.copy2(cfg.images / name, images_tmp / name)
        model_tmp = raw
    else:
        und = work / "undistorted"
        with cancellable() as token:
            pycolmap.undistort_images(
                str(und),
                str(raw),
                str(cfg.images),
                output_type="COLMAP",
                num_threads=cfg.num_threads,
                cancellation_token=token,
            )
        images_tmp, model_tmp = und / "images", und / "sparse"
        distorted_tmp = work / "distorted"
        shutil.copytree(raw, distorted_tmp)
        _replace_dir(distorted_tmp, out / DISTORTED_DIR)
    _replace_dir(images_tmp, out / "images")
    _replace_dir(model_tmp, out / MODEL_DIR)
    for k in range(1, cfg.num_downscales + 1):
        write_downscaled(out / "images", 2**k, out / f"images_{2**k}")


MIN_LINK_INLIERS = 15
"""A verified pair with at least this many inlier matches links two photos (COLMAP's mapper needs 15 by default)."""


def verified_links(db_path: Path) -> dict[str, dict[str, int]]:
    """{photo: {other photo: inlier matches}} of every geometrically verified pair in the database."""
    import pycolmap

    with pycolmap.Database.open(str(db_path)) as db:
        id_to_name = {im.image_id: im.name for im in db.read_all_images()}
        pair_ids, inliers = db.read_two_view_geometry_num_inliers()
    links: dict[str, dict[str, int]] = {}
    for pid, n in zip(pair_ids, inliers, strict=True):
        a, b = (id_to_name.get(i) for i in pycolmap.pair_id_to_image_pair(pid))
        if a is not None and b is not None and n > 0:
            links.setdefault(a, {})[b] = int(n)
            links.setdefault(b, {})[a] = int(n)
    return links


def unregistered_reasons(
    links: dict[str, dict[str, int]],
    registered: set[str],
    unregistered: Sequence[str],
    tried: Sequence[str] = ("default",),
) -> dict[str, dict[str, str]]:
    """Why each photo of ``unregistered`` is not in the model, and what to try, from the verified pairs ``links``
    ({photo: {other: inliers}}; pairs under MIN_LINK_INLIERS do not link). ``tried``: the mapping attempts that ran
    (map_with_retries' steps), named in the ``weak`` text. ``reason`` is one of:

    - ``no-matches``: no verified pair with any photo (too little overlap, or another place);
    - ``other-component``: linked only to other unregistered photos: a separate group the model does not reach;
    - ``weak``: linked to registered photos, yet no mapping attempt could place it (too few or badly spread matches).
    """
    tried_words = "tried: " + ", ".join(tried)
    strong = {a: {b for b, n in others.items() if n >= MIN_LINK_INLIERS} for a, others in links.items()}
    todo = set(unregistered)
    group: dict[str, list[str]] = {}
    for start in unregistered:  # connected groups of unregistered photos
        if start in group:
            continue
        members, stack = [], [start]
        seen = {start}
        while stack:
            a = stack.pop()
            members.append(a)
            for b in strong.get(a, ()):
                if b in todo and b not in seen:
                    seen.add(b)
                    stack.append(b)
        for m in members:
            group[m] = sorted(members)
    out = {}
    for name in unregistered:
        partners = strong.get(name, set())
        placed = sorted(partners & registered)
        best = max((links[name][b] for b in placed), default=0)
        if not partners:
            most = max(links.get(name, {}).values(), default=0)
            out[name] = {
                "reason": "no-matches",
                "text": f"no photo shares enough verified matches with it (best {most}, need {MIN_LINK_INLIERS}): "
                "too little overlap, a very different view, or another place; add photos taken between it and "
                "the others",
            }
        elif not placed:
            others = [g for g in group[name] if g != name]
            out[name] = {
                "reason": "other-component",
                "text": f"it matches only {len(others)} other unregistered photo(s) ({', '.join(others[:4])}"
                f"{', ...' if len(others) > 4 else ''}): a separate part of the scene the model does not reach; add "
                "photos that link the two parts, or process that group on its own",
            }
        else:
            out[name] = {
                "reason": "weak",
                "text": f"it matches {len(placed)} registered photo(s) (at most {best} inlier matches) but could not be "
                f"placed ({tried_words}): add photos from nearby viewpoints",
            }
    return out


def reconstruction_stats(rec, all_names: Sequence[str]) -> dict[str, Any]:
    """Summary of a model: registered / total, 3D points, mean reprojection error, mean track length, unregistered."""
    reg = {rec.images[i].name for i in rec.reg_image_ids()}
    return {
        "registered": len(reg),
        "total": len(all_names),
        "points3D": int(rec.num_points3D()),
        "mean_reprojection_error_px": float(rec.compute_mean_reprojection_error()),
        "mean_track_length": float(rec.compute_mean_track_length()),
        "unregistered": [n for n in all_names if n not in reg],
    }


def attempt_words(a: dict[str, Any], total: int) -> str:
    """One mapping attempt in words: "relaxed registration 86 / 90 at 0.56 px (111 s): kept"."""
    err = a["mean_reprojection_error_px"]
    words = f"{a['step']} {a['registered']} / {total}" + (f" at {err:.2f} px" if err is not None else "")
    words += f" ({a['seconds']:.0f} s)"
    if a["kept"]:
        return words + ": kept" + (f", {a['note']}" if a["note"] else "")
    return words + (f": {a['note']}" if a["note"] else "")


MAX_REASONS_SHOWN = 12
"""Unregistered photos explained one per line after the summary table; the rest only in process_summary.json."""


def print_summary(summary: dict[str, Any]) -> None:
    from nerfstudio.utils.rich_utils import CONSOLE
    from rich.table import Table

    table = Table(title="willags-process", show_header=False)
    table.add_row("images registered / total", f"{summary['registered']} / {summary['total']}")
    table.add_row("3D points", f"{summary['points3D']:,}")
    table.add_row("mean reprojection error", f"{summary['mean_reprojection_error_px']:.3f} px")
    table.add_row("mean track length", f"{summary['mean_track_length']:.2f}")
    table.add_row("camera model", summary["camera_model"])
    table.add_row("matching", f"{summary['matching']} ({summary['num_pairs']:,} pairs)")
    if "mapper" in summary:
        table.add_row("mapper", summary["mapper"])
    attempts = summary.get("mapping_attempts") or []
    if len(attempts) > 1:
        table.add_row("mapping attempts", "; ".join(attempt_words(a, summary["total"]) for a in attempts))
    table.add_row("split", f"{summary['num_train']} train / {summary['num_test']} test ({summary['split_file']})")
    stages = ", ".join(f"{k} {v:.0f} s" for k, v in summary["stage_s"].items())
    table.add_row("wall time", f"{summary['wall_s']:.0f} s ({stages})")
    resized = summary.get("resized") or {}
    if resized:
        table.add_row("resized", ", ".join(f"{k} ({v})" for k, v in resized.items()))
    unreadable = summary.get("unreadable") or []
    if unreadable:
        table.add_row("unreadable (skipped)", ", ".join(unreadable))
    unreg = [n for n in summary["unregistered"] if n not in set(unreadable)]
    table.add_row("unregistered", ", ".join(unreg) if unreg else "none")
    CONSOLE.print(table)
    kept = next((a for a in attempts if a["kept"]), None)
    if kept is not None and kept is not attempts[0]:
        more = kept["registered"] - attempts[0]["registered"]
        CONSOLE.print(
            f"  {kept['step']} placed {more} more photo(s) than {attempts[0]['step']}: {kept['what']}",
            soft_wrap=True,
            markup=False,
            highlight=False,
        )
    why = summary.get("unregistered_why") or {}
    shown = list(why.items())[:MAX_REASONS_SHOWN]
    for name, entry in shown:
        CONSOLE.print(f"  {name} not registered: {entry['text']}", soft_wrap=True, markup=False, highlight=False)
    if len(why) > len(shown):
        CONSOLE.print(f"  ... and {len(why) - len(shown)} more: see {SUMMARY} (unregistered_why)")
    CONSOLE.print(f"Scene written to {summary['output']}: ns-train willags --data {summary['output']}")


def run(cfg: ProcessConfig, log: Callable[[str], None] | None = None) -> dict[str, Any]:
    """The whole pipeline (see the module docstring). Returns the summary (also written to process_summary.json).
    Raises ProcessError on unusable input or too few registered images, KeyboardInterrupt on Ctrl-C."""
    import pycolmap
    from nerfstudio.utils.rich_utils import CONSOLE

    log = log or (lambda msg: CONSOLE.print(msg))
    t0 = time.time()
    cfg = dataclasses.replace(cfg, images=Path(cfg.images).expanduser(), output=Path(cfg.output).expanduser())
    if cfg.min_registered < 3:
        raise ProcessError(f"--min-registered must be >= 3, got {cfg.min_registered}")
    if not 0 <= cfg.retry_below <= 1:
        raise ProcessError(f"--retry-below must be a share between 0 (no retries) and 1, got {cfg.retry_below}")
    if cfg.test_every == 1 or cfg.test_every < 0:
        raise ProcessError(f"--test-every must be 0 (no test images) or >= 2, got {cfg.test_every}")
    names = list_images(cfg.images)
    if cfg.images.resolve() == (cfg.output / "images").resolve():
        raise ProcessError(f"--images {cfg.images} is the output's images/ folder, which this command replaces")
    bad = find_unreadable(cfg.images, names)
    for name, why in bad.items():
        log(f"[yellow]warning: skipping unreadable image {cfg.images / name}: {why}")
    readable = [n for n in names if n not in bad]
    if len(readable) < cfg.min_registered:
        raise ProcessError(
            f"{len(readable)} readable photo(s) in {cfg.images} ({len(bad)} unreadable: {', '.join(bad) or '-'}); "
            f"SfM needs at least {cfg.min_registered}"
        )
    cfg.output.mkdir(parents=True, exist_ok=True)
    photos, resized = cap_photos(cfg, readable)
    groups = camera_groups(dataclasses.replace(cfg, images=photos), readable)
    _check_database_options(cfg, resized=list(resized), exif_grouped=bool(groups) and not cfg.single_camera)
    for name, (w, h, w2, h2) in resized.items():
        log(f"{name}: {w}x{h} resized to {w2}x{h2} (--max-image-size {cfg.max_image_size}; 0 keeps full size)")
    given = cfg.images
    cfg = dataclasses.replace(cfg, images=photos)
    if not cfg.verbose:
        pycolmap.logging.minloglevel = 2  # errors only: COLMAP's INFO/WARNING lines would break the progress bars
    stage_s: dict[str, float] = {}
    work = cfg.output / "colmap" / ".work"
    with _progress() as progress:
        t = time.time()
        extracted = extract_features(cfg, readable, progress, groups)
        stage_s["extraction"] = time.time() - t
        for name in readable:
            if name not in extracted:
                log(f"[yellow]warning: no SIFT features in {given / name} (COLMAP could not read it or it is blank)")
        if len(extracted) < cfg.min_registered:
            raise ProcessError(f"only {len(extracted)} photo(s) gave SIFT features; SfM needs {cfg.min_registered}")
        t = time.time()
        method = cfg.matching
        if method == "auto":
            method = "exhaustive" if len(extracted) <= cfg.exhaustive_max_images else "vocab-tree"
        if method == "exhaustive":
            num_pairs = match_exhaustive(cfg, extracted, progress)
        else:
            num_pairs = match_vocab_tree(cfg, extracted, progress)
        stage_s["matching"] = time.time() - t
        t = time.time()
        mapper = chosen_mapper(cfg, len(extracted))
        n = len(extracted)
        links = verified_links(cfg.output / DATABASE)
        placeable = sum(any(k >= MIN_LINK_INLIERS for k in links.get(name, {}).values()) for name in extracted)
        rec, attempts = map_with_retries(
            cfg,
            placeable,
            mapper,
            run_incremental=lambda step: incremental_mapping(
                cfg, n, progress, work / "mapping", relax=step and step.relax, label=step.name if step else ""
            ),
            run_global=lambda: global_mapping(cfg, n, progress, work / "mapping"),
        )
        stage_s["mapping"] = time.time() - t
    registered = 0 if rec is None else rec.num_reg_images()
    if rec is None or registered < cfg.min_registered:
        shutil.rmtree(work, ignore_errors=True)
        tried = "; ".join(
            f"{a['step']}: {a['registered']}" + (f" ({a['note']})" if a["note"] else "") for a in attempts
        )
        raise ProcessError(
            f"SfM registered {registered} of {len(names)} images, fewer than {cfg.min_registered} (tried {tried}): "
            "the photos share too few matching features (too little overlap or texture). Add overlapping photos of "
            "the same scene."
        )
    t = time.time()
    stats = reconstruction_stats(rec, names)
    reg_names = {rec.images[i].name for i in rec.reg_image_ids()}
    not_placed = [n for n in stats["unregistered"] if n not in bad]
    tried = [a["step"] for a in attempts]
    why = unregistered_reasons(links, reg_names, not_placed, tried=tried) if not_placed else {}
    write_scene(cfg, rec, work)
    final = pycolmap.Reconstruction(str(cfg.output / MODEL_DIR))
    ids = {i: final.images[i].name for i in final.reg_image_ids()}
    rows = split_table(ids, cfg.test_every)
    scene_name = cfg.scene_name or cfg.output.resolve().name
    tsv = cfg.output / f"{scene_name}.tsv"
    write_split_tsv(tsv, rows, scene_name)
    stage_s["writing"] = time.time() - t
    shutil.rmtree(work, ignore_errors=True)
    summary = {
        **stats,
        "unreadable": sorted(bad),
        "unregistered_why": why,
        "camera_model": cfg.camera_model
        + (" -> undistorted to PINHOLE" if cfg.camera_model == "SIMPLE_RADIAL" else "")
        + camera_sharing_words(cfg, groups, len(readable)),
        "matching": method,
        "mapper": kept_mapper(attempts, mapper),
        "mapping_attempts": attempts,
        "num_pairs": num_pairs,
        "num_train": sum(r[2] == "train" for r in rows),
        "num_test": sum(r[2] == "test" for r in rows),
        "split_file": tsv.name,
        "output": str(cfg.output),
        "wall_s": time.time() - t0,
        "stage_s": stage_s,
        "pycolmap": pycolmap.__version__,
        "resized": {name: f"{w}x{h} -> {w2}x{h2}" for name, (w, h, w2, h2) in resized.items()},
        "options": {
            k: str(v) if isinstance(v, Path) else v
            for k, v in dataclasses.asdict(dataclasses.replace(cfg, images=given)).items()
        },
    }
    write_text_atomic(cfg.output / SUMMARY, json.dumps(summary, indent=1) + "\n")
    return summary
