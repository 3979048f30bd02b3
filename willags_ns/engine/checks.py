"""Input and state checks that turn bad data into one clear message before (or instead of) a deep torch traceback.

Every check is a pure function over plain inputs (file names, a nerfstudio ``Cameras``, tensors) that raises
:class:`WillagsInputError` (a ``WillagsDataError``) whose message names the file, frame or field at fault and says what
to do, or returns warnings (strings) for inputs that train but deserve a look. :func:`validate_dataparser_outputs`
runs them all over a dataparser's outputs; ``WillagsPipeline`` calls it for every willags method whatever the
dataparser (``willags-data``, ``nerfstudio-data``, ``colmap``, ...), after parsing and before any image is cached
or any step runs.

From the command line these errors print as one line (``willags: <message>``) instead of a traceback: see
:func:`install_cli_excepthook`.

Behaviour chosen for the edge cases (docs/reliability.md has the whole table):

- image size differs from the camera's width/height: an error, also when the image is exactly k times the camera
  size (a full-resolution image next to a downscaled camera). No silent rescale: nerfstudio would pass the image on
  as it is and the loss would fail on mismatched shapes deep inside torch;
- a single training image: trains (the appearance latent and the mask work per image), with a warning that novel
  views will not be constrained;
- byte-identical image files under two frames: a warning naming both.
"""

import hashlib
import os
import sys
import warnings
from collections.abc import Sequence
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import torch
from torch import Tensor

from willags_ns.data.dataparser import ROTATION_TOL, InputWarning, WillagsDataError


class WillagsInputError(WillagsDataError):
    """Bad training input found before training; the message names the file / frame / field and what to do."""


class WillagsTrainingError(RuntimeError):
    """Training reached a state it cannot continue from (e.g. every Gaussian pruned); the message says what to do."""


class WillagsWarning(UserWarning):
    """A warning of willags' own that :func:`warn_all` has printed on the console already. Python does not print it
    a second time (``file:line: UserWarning: ...`` and the source line): the filter below ignores it, while code that
    records warnings (``pytest.warns``, ``warnings.catch_warnings(record=True)``) still sees it."""


warnings.filterwarnings("ignore", category=WillagsWarning)


class WillagsIOError(RuntimeError):
    """A file cannot be written or read (a full disk, a damaged checkpoint); the message names it and what to do."""


# --------------------------------------------------------------------------------------------------------------------
# images


def check_image_file(path: Path, expected_wh: tuple[int, int] | None = None) -> tuple[int, int]:
    """Open and fully decode one image; return its (width, height).

    Raises WillagsInputError when the file is missing, is not an image, is truncated or corrupt, or (with
    ``expected_wh``) has another size than its camera. JPEGs are decoded in draft mode (DCT scaling, about 8x
    cheaper), which still reads every byte of the entropy-coded data, so a truncated file is still caught.
    """
    from PIL import Image, UnidentifiedImageError

    path = Path(path)
    if not path.is_file():
        raise WillagsInputError(f"image {path} does not exist: restore it, or remove its frame from the dataset")
    try:
        with Image.open(path) as im:
            size = im.size
            im.verify()  # structure / checksums (PNG CRCs)
        with Image.open(path) as im:
            if im.format == "JPEG":
                im.draft("RGB", (max(1, size[0] // 8), max(1, size[1] // 8)))
            im.load()  # full decode: a truncated file fails here ("image file is truncated")
    except (UnidentifiedImageError, OSError, SyntaxError, ValueError, Image.DecompressionBombError) as e:
        raise WillagsInputError(
            f"image {path} cannot be decoded ({type(e).__name__}: {e}); it is truncated or corrupt: "
            "re-export or re-download it, or remove its frame from the dataset"
        ) from None
    if expected_wh is not None and tuple(size) != tuple(expected_wh):
        raise WillagsInputError(
            f"image {path} is {size[0]}x{size[1]} but its camera says {expected_wh[0]}x{expected_wh[1]} (w x h): "
            "resize the image to the camera's size, or fix the camera's w/h (and fx, fy, cx, cy with it)"
        )
    return int(size[0]), int(size[1])


def _file_digest(path: Path) -> str:
    h = hashlib.blake2b(digest_size=16)
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


DUPLICATE_PHOTO = "photos byte-identical to another photo under another frame (duplicates: remove one of each)"
"""The kind of :func:`check_images`' warnings."""


def check_images(
    filenames: Sequence[Path], sizes_wh: Sequence[tuple[int, int]] | None = None, workers: int = 4
) -> list[InputWarning]:
    """:func:`check_image_file` for every file (in a small thread pool: decoding releases the GIL); the first bad
    file in dataset order raises. Returns warnings: byte-identical files listed under different frames."""
    files = [Path(f) for f in filenames]
    sizes = list(sizes_wh) if sizes_wh is not None else [None] * len(files)
    if len(sizes) != len(files):
        raise ValueError(f"{len(files)} files but {len(sizes)} sizes")

    def one(i: int):
        check_image_file(files[i], sizes[i])
        return _file_digest(files[i])

    with ThreadPoolExecutor(max_workers=max(1, workers)) as pool:
        results = list(pool.map(lambda i: _safe(one, i), range(len(files))))
    for r in results:
        if isinstance(r, BaseException):
            raise r
    first: dict[str, Path] = {}
    out = []
    for f, digest in zip(files, results, strict=True):
        if digest in first and first[digest] != f:
            out.append(
                InputWarning(
                    f"{f} and {first[digest]} are byte-identical files under two frames: if one is a duplicate, "
                    "remove it (two poses for one photo pull the scene apart)",
                    DUPLICATE_PHOTO,
                    f"{f.name} = {first[digest].name}",
                )
            )
        first.setdefault(digest, f)
    return out


def _safe(fn, i):
    try:
        return fn(i)
    except WillagsInputError as e:
        return e


# --------------------------------------------------------------------------------------------------------------------
# cameras


def _frame_name(i: int, names: Sequence[str] | None) -> str:
    return f"frame {i} ({names[i]})" if names is not None and i < len(names) else f"frame {i}"


def check_poses(c2w: Tensor, names: Sequence[str] | None = None, tol: float = ROTATION_TOL) -> None:
    """Camera-to-world poses [C, 3, 4] (or [C, 4, 4]): finite, with a proper rotation (R^T R = I, det R = +1).

    A scaled, sheared or mirrored 3x3 block means the pose is not a camera pose (a wrong convention, a scale folded
    into the rotation); nerfstudio would render it as a distorted view without complaint.
    """
    c2w = c2w.detach().double()
    if c2w.dim() != 3 or c2w.shape[-2] not in (3, 4) or c2w.shape[-1] != 4:
        raise WillagsInputError(f"camera poses must be [C, 3, 4], got {tuple(c2w.shape)}")
    finite = torch.isfinite(c2w[:, :3]).flatten(1).all(-1)
    if not finite.all():
        bad = torch.nonzero(~finite).flatten().tolist()
        extra = ""
        if len(bad) == c2w.shape[0] and c2w.shape[0] > 1:
            extra = (
                " (every pose: nerfstudio's orientation / auto-scaling spreads one NaN or Inf input pose to all; "
                "look for the frame whose transform_matrix or COLMAP pose holds NaN / Inf)"
            )
        raise WillagsInputError(
            f"{_frame_name(bad[0], names)} has a NaN or Inf in its camera pose{extra}: fix or remove that frame"
        )
    R = c2w[:, :3, :3]
    eye = torch.eye(3, dtype=R.dtype)
    ortho_err = (R.transpose(1, 2) @ R - eye).abs().flatten(1).amax(-1)
    det = torch.linalg.det(R)
    bad = (ortho_err > tol) | ((det - 1.0).abs() > tol)
    if bad.any():
        i = int(torch.nonzero(bad).flatten()[0])
        raise WillagsInputError(
            f"{_frame_name(i, names)}: the 3x3 block of its camera pose is not a rotation "
            f"(max |R^T R - I| = {float(ortho_err[i]):.3g}, det = {float(det[i]):.4g}; want 0 and +1): "
            "remove any scale, shear or mirroring from that transform_matrix (scale belongs in the translation)"
        )


def check_intrinsics(
    fx: Tensor, fy: Tensor, cx: Tensor, cy: Tensor, width: Tensor, height: Tensor, names: Sequence[str] | None = None
) -> None:
    """Per-camera intrinsics (any shapes broadcasting to [C] or [C, 1]): fx, fy finite and > 0; cx, cy finite;
    width, height >= 1."""
    fields = {"fx": fx, "fy": fy, "cx": cx, "cy": cy, "w": width, "h": height}
    flat = {k: v.detach().double().reshape(-1) for k, v in fields.items()}
    for k, v in flat.items():
        rule = {"fx": "> 0", "fy": "> 0", "w": ">= 1", "h": ">= 1"}.get(k, "finite")
        ok = torch.isfinite(v)
        if k in ("fx", "fy"):
            ok &= v > 0
        if k in ("w", "h"):
            ok &= v >= 1
        if not ok.all():
            i = int(torch.nonzero(~ok).flatten()[0])
            raise WillagsInputError(
                f"{_frame_name(i, names)}: camera {k} = {float(v[i])} is invalid (must be finite and {rule}): "
                "fix it in the camera parameters (transforms.json fl_x / fl_y / cx / cy / w / h, or the COLMAP "
                "cameras file)"
            )


def check_num_train_images(n: int) -> list[InputWarning]:
    """Zero training images: an error. One: a warning (it trains; see the module docstring)."""
    if n <= 0:
        raise WillagsInputError(
            "the training split has no images: check the dataset's train_filenames / *.tsv split / eval_mode "
            "(e.g. `ns-train ... willags-data --eval-mode all` puts every image in training)"
        )
    if n == 1:
        return [
            InputWarning(
                "only one training image: training runs (the appearance latent and the transient mask work per "
                "image), but nothing constrains the scene away from that view; add images for novel views",
                "training sets of one image",
            )
        ]
    return []


def check_cameras(cameras, names: Sequence[str] | None = None) -> None:
    """Poses and intrinsics of a nerfstudio ``Cameras`` batch ([C])."""
    check_intrinsics(cameras.fx, cameras.fy, cameras.cx, cameras.cy, cameras.width, cameras.height, names)
    check_poses(cameras.camera_to_worlds, names)


def validate_dataparser_outputs(outputs, check_files: bool = True, device: str | None = None) -> list[InputWarning]:
    """Every check over one split's ``DataparserOutputs``: image count, cameras, scene scale, and
    (``check_files``) that every image exists, decodes and has its camera's size; on a CPU ``device``, that the
    largest image fits in memory. Raises WillagsInputError; returns the warnings."""
    files = [Path(p) for p in outputs.image_filenames]
    warn = check_num_train_images(len(files))
    names = [f.name for f in files]
    cams = outputs.cameras
    check_cameras(cams, names)
    points = outputs.metadata.get("points3D_xyz")
    check_scene_scale(cams.camera_to_worlds[:, :3, 3], points)
    if device is not None and str(device).startswith("cpu"):
        pixels = cams.width.reshape(-1) * cams.height.reshape(-1)
        i = int(pixels.argmax())
        n_points = int(points.shape[0]) if points is not None else 0
        largest = [names[k] for k in (pixels == pixels[i]).nonzero().reshape(-1).tolist() if k < len(names)]
        w, h = int(cams.width.reshape(-1)[i]), int(cams.height.reshape(-1)[i])
        check_train_memory(n_points, w, h, names=largest)
    if check_files:
        sizes = [(int(w), int(h)) for w, h in zip(cams.width.reshape(-1), cams.height.reshape(-1), strict=True)]
        if len(sizes) == 1 and len(files) > 1:
            sizes = sizes * len(files)
        warn += check_images(files, sizes)
        masks = outputs.mask_filenames
        if masks is not None:
            for m in masks:
                if not Path(m).is_file():
                    raise WillagsInputError(f"mask {m} does not exist: restore it or remove mask_path from its frame")
    return warn


# --------------------------------------------------------------------------------------------------------------------
# training state


def check_gaussians_alive(num_points: int, step: int) -> None:
    """Raise WillagsTrainingError when densification pruned every Gaussian (nothing left to render or optimise)."""
    if num_points <= 0:
        raise WillagsTrainingError(
            f"every Gaussian was pruned by step {step}: the scene is empty. Resume from the last checkpoint with "
            "a lower --pipeline.model.cull-alpha-thresh, or check that the images match their cameras (a scene "
            "the cameras never see gets culled)"
        )


BYTES_PER_PIXEL = 3000
"""Host memory of one CPU training step per image pixel (forward + backward: render, teacher channels, VGG features
of the mask, SSIM maps, VAE input, autograd buffers), rounded up from a measurement (docs/design.md)."""
BYTES_PER_GAUSSIAN = 2000
"""Per-Gaussian parameters, Adam moments, projections and per-Gaussian colours (generous)."""


def estimate_train_step_bytes(num_gaussians: int, width: int, height: int) -> int:
    """Rough peak host memory (bytes) of one CPU training step at ``width`` x ``height``: BYTES_PER_PIXEL per pixel
    plus BYTES_PER_GAUSSIAN per Gaussian. An estimate for a clear error, not a bound."""
    return BYTES_PER_PIXEL * int(width) * int(height) + BYTES_PER_GAUSSIAN * int(num_gaussians)


MAX_SUGGESTED_DOWNSCALE = 16
"""The largest downscale factor the memory error suggests; beyond it, only a GPU or smaller photos."""


def downscale_command(argv: Sequence[str], factor: int) -> str:
    """The ``ns-train`` command line ``argv`` reading its images at 1/``factor`` size: ``--downscale-factor`` is an
    option of the dataparser subcommand, so it goes after ``willags-data`` (appended when the line names no
    dataparser; replaced when it names one already). Another command line (a script): the words to add."""
    import shlex

    option = ["--downscale-factor", str(int(factor))]
    exe = Path(argv[0]).as_posix() if argv else ""
    if not (Path(exe).name == "ns-train" or exe.endswith("nerfstudio/scripts/train.py")):
        return "ns-train ... " + shlex.join(["willags-data", *option]) + " (after the run's other options)"
    args = list(argv[1:])
    kept: list[str] = []
    i = 0
    while i < len(args):
        name = args[i].split("=", 1)[0].replace("_", "-")
        if name == "--downscale-factor":
            i += 1 if "=" in args[i] else 2
            continue
        kept.append(args[i])
        i += 1
    parsers = {"willags-data", "colmap", "nerfstudio-data"}
    at = next((k + 1 for k, a in enumerate(kept) if a in parsers), None)
    if at is None:
        kept += ["willags-data", *option]
    else:
        kept[at:at] = option
    return shlex.join(["ns-train", *kept])


def check_train_memory(
    num_gaussians: int,
    width: int,
    height: int,
    available: int | None = None,
    names: Sequence[str] = (),
    argv: Sequence[str] | None = None,
) -> None:
    """Raise WillagsInputError when a CPU training step on a ``width`` x ``height`` image would not fit in
    ``available`` bytes (default: the host's MemAvailable) by :func:`estimate_train_step_bytes`. The message names
    the photos of that size (``names``) and gives the command (``argv``, default ``sys.argv``) with the smallest
    power-of-two downscale factor that fits."""
    need = estimate_train_step_bytes(num_gaussians, width, height)
    if available is None:
        available = available_memory_bytes()
    if available is None or need <= available:
        return
    factor = 2
    while (
        factor < MAX_SUGGESTED_DOWNSCALE
        and estimate_train_step_bytes(num_gaussians, width // factor, height // factor) > available
    ):
        factor *= 2
    which = ""
    if names:
        shown = ", ".join(names[:3]) + (f" and {len(names) - 3} more" if len(names) > 3 else "")
        which = f" ({shown})"
    fits = estimate_train_step_bytes(num_gaussians, width // factor, height // factor) <= available
    fix = (
        f"read the images at 1/{factor} size: {downscale_command(sys.argv if argv is None else argv, factor)}; or "
        if fits
        else ""
    )
    raise WillagsInputError(
        f"training on a {width}x{height} image{which} needs about {need / 2**30:.1f} GiB of memory on the CPU but "
        f"{available / 2**30:.1f} GiB is free: {fix}make the photos smaller (willags-process --max-image-size, or "
        "remove the large ones), or train on a GPU"
    )


NEAR_PLANE = 0.01
"""The rasteriser's near plane in scene units (gaussians.rasterize_gaussians): anything closer to a camera is culled."""


def check_scene_scale(camera_centres: Tensor, points: Tensor | None = None, near_plane: float = NEAR_PLANE) -> None:
    """Raise WillagsInputError when the scene is so small in its units that the near plane culls it.

    The distance measured is the median camera's distance to the median seed point, or (no points) the cameras'
    spread. nerfstudio's dataparsers scale poses into [-1, 1] by default (auto_scale_poses), so this fires only when
    that is turned off on a scene in, e.g., kilometres-as-millimetres units. Large scenes (1e4) work as they are.
    """
    c = camera_centres.detach().double().reshape(-1, 3)
    if points is not None and points.numel() >= 3:
        centre = points.detach().double().reshape(-1, 3).median(dim=0).values
        dist = float((c - centre).norm(dim=-1).median())
    elif c.shape[0] >= 2:
        dist = float((c - c.mean(0)).norm(dim=-1).max())
    else:
        return
    if dist < 10 * near_plane:
        raise WillagsInputError(
            f"the cameras are {dist:.3g} scene units from the scene, but willags culls everything closer than "
            f"{near_plane} to a camera: keep the dataparser's auto_scale_poses on (the default), or scale the poses "
            "and points up"
        )


def available_memory_bytes() -> int | None:
    """Free host memory (Linux /proc/meminfo MemAvailable), or None where unknown."""
    try:
        for line in Path("/proc/meminfo").read_text().splitlines():
            if line.startswith("MemAvailable:"):
                return int(line.split()[1]) * 1024
    except OSError:
        return None
    return None


def warn_all(messages: Sequence[str]) -> None:
    """Print each warning once, on nerfstudio's console, and raise it as a :class:`WillagsWarning` (which Python
    does not print again) for code that records warnings."""
    from nerfstudio.utils.rich_utils import CONSOLE

    for m in messages:
        CONSOLE.log(f"[bold yellow]willags warning:[/bold yellow] {m}")
        warnings.warn(m, WillagsWarning, stacklevel=2)


INPUT_WARNINGS_FILE = "input_warnings.txt"
"""The input checks' warnings, one a line, in the run folder (beside config.yml)."""
MAX_LISTED_WARNINGS = 10
"""Up to this many input warnings are printed one by one; more are summarised (:func:`summarise_warnings`)."""
EXAMPLES_PER_KIND = 3
"""Photos a summary names per kind of warning."""


def summarise_warnings(messages: Sequence[str], where: str, examples: int = EXAMPLES_PER_KIND) -> str:
    """Many warnings in a few lines: their number and where the full list is (``where``), then per kind
    (:class:`InputWarning`'s; "other" for a plain string) the count and the first ``examples`` photos."""
    kinds: dict[str, list[str]] = {}
    for m in messages:
        kinds.setdefault(getattr(m, "kind", "") or "other warnings", []).append(m)
    lines = [f"{len(messages)} warnings about the input (the full list: {where}):"]
    for kind, group in kinds.items():
        named = [getattr(m, "photo", "") or m[:80] for m in group[:examples]]
        more = f", and {len(group) - examples} more" if len(group) > examples else ""
        lines.append(f"  {len(group)} {kind}, e.g. {'; '.join(named)}{more}")
    return "\n".join(lines)


def report_warnings(messages: Sequence[str], where: str, max_listed: int = MAX_LISTED_WARNINGS) -> bool:
    """Up to ``max_listed`` warnings one by one (:func:`warn_all`); more as one summary (:func:`summarise_warnings`)
    whose first line names ``where`` the full list goes. Returns whether it summarised."""
    if len(messages) <= max_listed:
        warn_all(messages)
        return False
    warn_all([summarise_warnings(messages, where)])
    return True


def write_warnings(messages: Sequence[str], path: Path) -> Path:
    """Every warning, one a line, to ``path`` (its folder made when missing)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text("".join(f"{m}\n" for m in messages))
    return path


# --------------------------------------------------------------------------------------------------------------------
# the command line: one line, not a traceback


def _excepthook(prev):
    def hook(exc_type, exc, tb):
        if isinstance(exc, (WillagsDataError, WillagsTrainingError, WillagsIOError)):
            print(f"\nwillags: {exc}", file=sys.stderr)
            return
        if isinstance(exc, KeyboardInterrupt):  # Ctrl-C in a command that waits (ns-viewer): stopped, as asked
            print("\nwillags: stopped (Ctrl-C)", file=sys.stderr)
            # at once, whatever the moment: the viewer's server threads would keep the process alive (and may hold a
            # lock the interrupted main thread left taken), so the interpreter's wait for its threads never ends
            sys.stdout.flush()
            sys.stderr.flush()
            os._exit(130)
        prev(exc_type, exc, tb)

    hook.willags = True  # type: ignore[attr-defined]
    return hook


def install_cli_excepthook() -> None:
    """Make an uncaught WillagsDataError / WillagsTrainingError / WillagsIOError print ``willags: <message>`` (exit
    status 1) instead of a 30-frame traceback through nerfstudio, and a Ctrl-C that nothing caught (ns-viewer waits
    in a loop until it comes) one line. Only these; every other error keeps Python's traceback. Idempotent."""
    if not getattr(sys.excepthook, "willags", False):
        sys.excepthook = _excepthook(sys.excepthook)
