"""One parser for appearance SPECs: the render and export CLIs, the viewer panel and $WILLAGS_APPEARANCE use it.

    mean                      the mean of the training images' latents (the model's default)
    image:<name|stem|index>   a training image's latent (file name, file name without extension, or dataset index)
    photo:<path>              any photo through the VAE encoder (optionally refined on that photo, see below)
    sample:<seed>             z ~ N(0, I) (an embedding-table model: the training latents' Gaussian), reproducible
    latent:<file.npy>         a latent saved with numpy ([D] or [1, D])
    interp:<A>,<B>[,T]        (1 - T) z_A + T z_B, A and B any of the above (bare names/indices mean image:);
                              without T a video sweeps T from 0 to 1 along its camera path

Parsing (:func:`parse_spec`) is pure and checks the syntax; resolving (:func:`resolve_latent`) needs the model and
checks the rest (known image, readable photo, finite latent of the right size). Every error is an
:class:`AppearanceSpecError` (a ValueError) whose message names the bad part.

This module imports neither the model nor the viewer (both import it), so there is no import cycle.
"""

import math
import re
from collections.abc import Mapping
from dataclasses import dataclass, fields, replace
from pathlib import Path
from typing import TYPE_CHECKING, ClassVar, Union

import numpy as np
import torch
from torch import Tensor

from willags_ns.appearance.latents import (
    APPEARANCE_ENV,
    MAX_LATENT_NORM,
    AppearanceSpecError,
    checked_latent,
    mean_latent,
)

if TYPE_CHECKING:
    from nerfstudio.cameras.cameras import Cameras

KINDS = ("mean", "image", "photo", "sample", "latent", "interp")
USAGE = "mean | image:NAME | photo:PATH | sample:SEED | latent:FILE.npy | interp:A,B[,T]"


@dataclass(frozen=True)
class MeanSpec:
    """The mean of the training images' latents."""

    def __str__(self) -> str:
        return "mean"


class _OneArgSpec:
    """A SPEC of one argument: prints back as `<KIND>:<argument>`."""

    KIND: ClassVar[str] = ""

    def __str__(self) -> str:
        return f"{self.KIND}:{getattr(self, fields(self)[0].name)}"  # type: ignore[arg-type]


@dataclass(frozen=True)
class ImageSpec(_OneArgSpec):
    KIND: ClassVar[str] = "image"
    key: str
    """Training image file name, stem or dataset index."""


@dataclass(frozen=True)
class PhotoSpec(_OneArgSpec):
    KIND: ClassVar[str] = "photo"
    path: Path
    """Any photo: fitted to (--refine-steps) and/or encoded by the VAE encoder."""


@dataclass(frozen=True)
class SampleSpec(_OneArgSpec):
    KIND: ClassVar[str] = "sample"
    seed: int
    """Seed of the draw (z ~ N(0, I), or the embedding rows' Gaussian)."""


@dataclass(frozen=True)
class LatentFileSpec(_OneArgSpec):
    KIND: ClassVar[str] = "latent"
    path: Path
    """A .npy file holding one latent."""


@dataclass(frozen=True)
class InterpSpec:
    a: "Spec"
    """Appearance at T = 0."""
    b: "Spec"
    """Appearance at T = 1."""
    t: float | None = None
    """Weight of b; None = a sweep (a video's frames go from 0 to 1)."""

    def __str__(self) -> str:
        return f"interp:{self.a},{self.b}" + ("" if self.t is None else f",{self.t:g}")


Spec = Union[MeanSpec, ImageSpec, PhotoSpec, SampleSpec, LatentFileSpec, InterpSpec]


def _parse_single(text: str, context: str) -> Spec:
    """A SPEC that is not interp (interp endpoints); a bare name or index means image:."""
    kind, sep, arg = text.partition(":")
    kind = kind.strip()
    if not sep:
        if kind == "mean":
            return MeanSpec()
        if kind in KINDS:
            raise AppearanceSpecError(f"{context}: {kind!r} needs an argument ({kind}:...); expected {USAGE}")
        if not kind:
            raise AppearanceSpecError(f"{context}: empty appearance; expected {USAGE}")
        return ImageSpec(kind)  # interp:a.png,b.png: bare training image names
    if kind == "mean":
        if arg.strip():
            raise AppearanceSpecError(f"{context}: 'mean' takes no argument, got {text!r}")
        return MeanSpec()
    if kind == "image":
        if not arg.strip():
            raise AppearanceSpecError(f"{context}: image: needs a training image name, stem or index")
        return ImageSpec(arg.strip())
    if kind in ("photo", "latent"):
        if not arg.strip():
            raise AppearanceSpecError(f"{context}: {kind}: needs a file path")
        path = Path(arg.strip()).expanduser()
        return PhotoSpec(path) if kind == "photo" else LatentFileSpec(path)
    if kind == "sample":
        try:
            return SampleSpec(int(arg.strip()))
        except ValueError:
            raise AppearanceSpecError(f"{context}: sample seed must be an integer, got {arg.strip()!r}") from None
    if kind == "interp":
        raise AppearanceSpecError(f"{context}: interp endpoints cannot be interp themselves: {text!r}")
    raise AppearanceSpecError(f"{context}: unknown appearance kind {kind!r} in {text!r}; expected {USAGE}")


_KIND_PREFIX = re.compile(r"^\s*(mean\b|image:|photo:|sample:|latent:)")
_INNER_KIND = re.compile(r",\s*(mean\b|image:|photo:|sample:|latent:)")


def parse_spec(text: str, context: str = "appearance") -> Spec:
    """SPEC text -> a Spec. `context` prefixes error messages (e.g. '--appearance', the env variable's name).

    interp:A,B[,T] is split at the comma where both halves are valid SPECs, preferring commas followed by a kind
    (so photo paths may contain commas: interp:photo:a,b.jpg,sample:1 splits before 'sample:'). A last part that is
    a number is T (0 <= T <= 1).
    """
    text = text.strip()
    if not text.startswith("interp:"):
        return _parse_single(text, context)
    parts = text[len("interp:") :].split(",")
    t = None
    if len(parts) >= 3:
        try:
            t = float(parts[-1])
        except ValueError:
            t = None
        else:
            parts = parts[:-1]
            if not math.isfinite(t) or not 0.0 <= t <= 1.0:
                raise AppearanceSpecError(f"{context}: interpolation T must be in [0, 1], got {t:g} in {text!r}")
    splits = []
    for k in range(1, len(parts)):
        a, b = ",".join(parts[:k]), ",".join(parts[k:])
        if _INNER_KIND.search(a) or _INNER_KIND.search(b):
            continue  # one side would swallow another SPEC: not this comma
        splits.append((0 if _KIND_PREFIX.match(b) else 1, a, b))
    errors = []
    for _, a, b in sorted(splits, key=lambda s: s[0]):
        try:
            return InterpSpec(_parse_single(a, context), _parse_single(b, context), t)
        except AppearanceSpecError as e:
            errors.append(str(e))
    detail = f" ({errors[0]})" if errors else ""
    raise AppearanceSpecError(
        f"{context}: interp needs two appearances, 'interp:A,B' or 'interp:A,B,T', got {text!r}{detail}"
    )


# ---------------------------------------------------------------------------------------------- latent helpers


def interpolate_latents(z_a: Tensor, z_b: Tensor, t: float) -> Tensor:
    """Linear interpolation between two latents; t=0 gives z_a, t=1 gives z_b."""
    return (1.0 - t) * z_a + t * z_b


def sample_latent(dim: int, seed: int, device: "torch.device | str" = "cpu") -> Tensor:
    """A new appearance: z ~ N(0, I), reproducible from the seed (the same on every device)."""
    g = torch.Generator().manual_seed(int(seed))
    return torch.randn(dim, generator=g).to(device)


def embedding_sample(model, eps: Tensor) -> Tensor:
    """eps ~ N(0, I) mapped onto the training latents' own Gaussian (mean + Cholesky of their covariance).

    Why: an embedding table has no prior (a VAE's latents are pulled to N(0, I) by its KL term, an embedding
    table's are wherever training put them), so N(0, I) itself would be an appearance far from every photo."""
    lat, seen = model.image_latents()
    lat = lat[seen]
    mu = lat.mean(0)
    if lat.shape[0] < 2:
        return mu
    x = (lat - mu).double()
    cov = x.T @ x / (lat.shape[0] - 1)
    cov = cov + 1e-6 * (cov.diagonal().mean() + 1e-12) * torch.eye(cov.shape[0], dtype=cov.dtype, device=cov.device)
    chol = torch.linalg.cholesky(cov)
    return (mu.double() + chol @ eps.to(chol)).to(lat.dtype)


def image_index(
    key: str,
    image_names: list[str],
    seen: Tensor | None = None,
    context: str = "image",
    test_photos: Mapping[str, str] | None = None,
) -> int:
    """Dataset index of a training image given by file name, stem or index (a name or stem first: ``0012`` is the
    photo 0012.png, not the 12th); errors name the key. ``test_photos`` (file name -> path of the run's test photos):
    a key naming one of them is an error that says so and gives the ``photo:PATH`` SPEC that fits its appearance (a
    test photo has no trained latent)."""
    key = key.strip()
    stems = [Path(n).stem for n in image_names]
    if key in image_names:
        i = image_names.index(key)
    elif key in stems:
        i = stems.index(key)
    elif (path := _test_photo(key, test_photos or {})) is not None:
        raise AppearanceSpecError(
            f"{context}: {key!r} is a test photo, held out of training, so it has no trained appearance; "
            f"photo:{path} fits its appearance (a latent fitted to the photo)"
        )
    elif key.isdigit() and int(key) < len(image_names):
        i = int(key)
    else:
        shown = ", ".join(image_names[:8]) + (" ..." if len(image_names) > 8 else "")
        raise AppearanceSpecError(
            f"{context}: unknown training image {key!r} ({len(image_names)} training images: {shown})"
        )
    if seen is not None and not bool(seen[i]):
        raise AppearanceSpecError(
            f"{context}: training image {image_names[i]!r} was never encoded during training (no latent yet)"
        )
    return i


def _test_photo(key: str, test_photos: Mapping[str, str]) -> str | None:
    """The path of the test photo a key names (file name or stem), or None."""
    for name, path in test_photos.items():
        if key in (name, Path(name).stem):
            return path
    return None


def load_photo(path: Path, context: str = "photo") -> Tensor:
    """A photo as float [H, W, 3] in [0, 1]; errors name the path."""
    from PIL import Image, UnidentifiedImageError

    if not path.is_file():
        raise AppearanceSpecError(f"{context}: cannot read photo {str(path)!r}: no such file")
    try:
        with Image.open(path) as im:
            arr = np.asarray(im.convert("RGB"), dtype=np.float32) / 255.0
    except (UnidentifiedImageError, OSError) as e:
        raise AppearanceSpecError(f"{context}: cannot read photo {str(path)!r} as an image ({e})") from None
    return torch.from_numpy(arr)


def load_latent_file(path: Path, dim: int, context: str = "latent") -> Tensor:
    """A latent [D] from a .npy file ([D] or [1, D]); errors name the file."""
    if not path.is_file():
        raise AppearanceSpecError(f"{context}: cannot read latent file {str(path)!r}: no such file")
    try:
        arr = np.load(path, allow_pickle=False)
    except (ValueError, OSError) as e:
        raise AppearanceSpecError(f"{context}: cannot read latent file {str(path)!r} as .npy ({e})") from None
    if not isinstance(arr, np.ndarray) or not np.issubdtype(arr.dtype, np.number):
        raise AppearanceSpecError(f"{context}: latent file {str(path)!r} holds no numeric array")
    if arr.reshape(-1).shape[0] != dim or (arr.ndim == 2 and arr.shape[0] != 1) or arr.ndim > 2:
        raise AppearanceSpecError(
            f"{context}: latent file {str(path)!r} has shape {arr.shape}; this model needs [{dim}] or [1, {dim}]"
        )
    if not np.isfinite(arr).all():
        raise AppearanceSpecError(f"{context}: latent file {str(path)!r} holds NaN or Inf values")
    return torch.from_numpy(arr.astype(np.float32).reshape(-1))


# ---------------------------------------------------------------------------------------------- resolving


PHOTO_FIT_STEPS = 50
"""Adam steps fitting a photo's latent when the model has no encoder and no --refine-steps was given."""


@dataclass
class RefineOptions:
    """Latent refinement of `photo:` SPECs: the encoder's latent, then Adam on the photo (NeRF-W protocol's fit)."""

    steps: int = 0
    """Adam steps (0 = the encoder's latent as it is)."""
    lr: float = 0.01
    """Adam learning rate (the protocol's)."""
    view: str | None = None
    """Training image (name, stem or index) whose camera sees what the photo shows; None = the training view
    whose render is closest to the photo (L1 at 48 px)."""
    max_size: int = 128
    """Refine at most at this many pixels on the longer side (the photo and the render are downscaled)."""
    start_candidates: int = 16
    """Training latents also tried as the fit's start, spread over the table farthest-first: whichever of them and
    the usual start (the encoder's latent, or the mean) renders the photo's view closest to the photo starts the
    Adam steps, so a photo whose appearance lies far from the mean (night, snow) is not fitted from the mean with
    too few steps to get there. One render each at `max_size`, no gradients; 0: the usual start alone."""


def _resized(img: Tensor, h: int, w: int) -> Tensor:
    import torch.nn.functional as F

    return F.interpolate(img.permute(2, 0, 1)[None], size=(h, w), mode="area")[0].permute(1, 2, 0)


def _render_at(model, camera, z: Tensor, max_size: int) -> Tensor:
    cam = camera.to(model.device)
    scale = min(1.0, max_size / float(max(int(cam.width), int(cam.height))))
    cam.rescale_output_resolution(scale)
    cam.metadata = {"appearance_latent": z}
    return model.get_outputs(cam)["rgb"]


@torch.no_grad()
def nearest_view(model, photo: Tensor, z: Tensor, cameras: "Cameras", size: int = 48) -> int:
    """Index of the camera whose render under latent z looks most like `photo` [H, W, 3] (L1 at `size` px)."""
    errs = []
    for i in range(len(cameras)):
        r = _render_at(model, cameras[i : i + 1], z, size)
        errs.append(float((r - _resized(photo, *r.shape[:2]).to(r.device)).abs().mean()))
    return int(np.argmin(errs))


def refine_photo_latent(model, photo: Tensor, z0: Tensor, cameras: "Cameras", opts: RefineOptions) -> Tensor:
    """The latent z0 optimised so the model's render of the photo's view matches the photo (scene frozen).

    A photo carries no pose: its view is a training camera (opts.view, or the one whose render under z0 looks most
    like the photo). The fit starts from z0 or one of `opts.start_candidates` training latents, whichever renders
    that view closest to the photo. The loss and optimiser are the NeRF-W protocol's (`fit_latent`), on the whole
    image.
    """
    from willags_ns.eval.protocol import fit_latent, frozen, training_start

    if opts.view is not None:
        idx = image_index(opts.view, list(model.image_names), context="--refine-view")
    else:
        idx = nearest_view(model, photo, z0, cameras)
    cam = cameras[idx : idx + 1]
    was_training = model.training
    model.eval()
    with torch.no_grad():
        h, w = _render_at(model, cam, z0, opts.max_size).shape[:2]
    gt = _resized(photo, h, w).to(model.device)

    def render(z: Tensor) -> Tensor:
        return _render_at(model, cam, z, opts.max_size)

    z0, _ = training_start(model, render, gt, slice(None), z0, opts.start_candidates)
    with frozen(model), torch.enable_grad():
        z, _ = fit_latent(render, gt, z0, slice(None), opts.steps, opts.lr)
    model.train(was_training)
    return z


def resolve_latent(
    spec: "Spec | str",
    model,
    t: float | None = None,
    refine: RefineOptions | None = None,
    cameras: "Cameras | None" = None,
    cache: dict | None = None,
    context: str = "appearance",
) -> Tensor:
    """The latent [D] (on the model's device) a SPEC describes for `model` (a WillagsModel).

    `t` is the weight of an interp SPEC without its own T (a video's sweep). `refine` refines `photo:` latents on
    the photo (needs the training `cameras`). `cache` (a dict) keeps photo latents between calls (the viewer).
    """
    if isinstance(spec, str):
        spec = parse_spec(spec, context)
    if getattr(model.config, "appearance", "willags") != "willags" or model.appearance_nets is None:
        raise AppearanceSpecError(f"{context}: this model has no appearance latent (appearance='sh')")
    dim = int(model.train_latents.shape[1])
    device = model.train_latents.device
    if isinstance(spec, MeanSpec):
        z = mean_latent(model)
    elif isinstance(spec, ImageSpec):
        lat, seen = model.image_latents()
        i = image_index(spec.key, list(model.image_names), seen, context, getattr(model, "test_photos", None))
        z = lat[i].clone()
    elif isinstance(spec, SampleSpec):
        z = sample_latent(dim, spec.seed, device)
        if model.appearance_nets.vae is None:
            z = embedding_sample(model, z)
    elif isinstance(spec, LatentFileSpec):
        z = load_latent_file(spec.path, dim, context).to(device)
    elif isinstance(spec, PhotoSpec):
        steps = refine.steps if refine is not None else 0
        key = (
            str(spec.path),
            steps,
            refine.view if refine is not None else None,
            refine.start_candidates if refine is not None else None,
        )
        if cache is not None and key in cache:
            return cache[key]
        photo = load_photo(spec.path, context)
        if model.appearance_nets.vae is not None:
            z = model.encode_image(photo)
        else:
            z = mean_latent(model)  # no encoder (embedding-table model): the latent is fitted, from the mean
            if steps == 0:
                steps = PHOTO_FIT_STEPS
                refine = replace(refine, steps=steps) if refine is not None else RefineOptions(steps=steps)
        if steps > 0:
            if cameras is None:
                raise AppearanceSpecError(
                    f"{context}: photo:{spec.path} is fitted to the photo from a training view, which needs the "
                    "training cameras (use willags-render / willags-export, or the viewer's 'Use photo')"
                )
            assert refine is not None
            z = refine_photo_latent(model, photo, z, cameras, refine)
        z = checked_latent(z.detach(), f"{context}: photo:{spec.path}")
        if cache is not None:
            cache[key] = z
        return z
    else:
        w = spec.t if spec.t is not None else t
        if w is None:
            raise AppearanceSpecError(
                f"{context}: {spec} gives no weight: a still image needs interp:A,B,T (T in [0, 1]); "
                "only a video sweeps T along its camera path"
            )
        za = resolve_latent(spec.a, model, refine=refine, cameras=cameras, cache=cache, context=context)
        zb = resolve_latent(spec.b, model, refine=refine, cameras=cameras, cache=cache, context=context)
        z = interpolate_latents(za, zb, float(w))
    return checked_latent(z, f"{context}: {spec}")


def latent_from_env(spec: str, model) -> Tensor | None:
    """What the model renders for $WILLAGS_APPEARANCE=spec: None for 'mean' (the model's default), else the
    latent. Errors name the variable."""
    parsed = parse_spec(spec, APPEARANCE_ENV)
    if isinstance(parsed, MeanSpec):
        return None
    return resolve_latent(parsed, model, context=APPEARANCE_ENV)


__all__ = [
    "APPEARANCE_ENV",
    "MAX_LATENT_NORM",
    "AppearanceSpecError",
    "checked_latent",
    "mean_latent",
]
