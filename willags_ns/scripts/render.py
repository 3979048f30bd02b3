"""`willags-render`: nerfstudio's `ns-render` (same subcommands and options) plus `--appearance SPEC`.

    willags-render camera-path --load-config run/config.yml --camera-path-filename path.json --appearance image:IMG_0042
    willags-render interpolate --load-config run/config.yml --appearance interp:image:3,sample:1   # a sweep
    willags-render dataset --load-config run/config.yml --split test --appearance photo:new.jpg --refine-steps 50

SPECs are parsed by willags_ns.appearance_spec (see its docstring). The render classes are nerfstudio's own,
subclassed with the appearance options; their `main()` is run unchanged inside :func:`appearance_hooks`, which
chooses the appearance right after nerfstudio loads the checkpoint (its `eval_setup`) and, for `interp:A,B`
without T, gives each camera of the path its own latent (camera metadata `appearance_latent`, which the model
honours), sweeping T from 0 to 1 along the path.

The commands print the appearance they resolved (which training image, photo, seed or file, and the latent's norm)
and the path they wrote with the step of the checkpoint it came from; frame progress is a bar on a terminal and a line every half minute in a log
(willags_ns.tools.progress). A damaged checkpoint is named in one line (willags_ns.engine.checkpoints).
"""

import contextlib
import dataclasses
import shutil
from pathlib import Path
from typing import Annotated, Any, Union

import torch
import tyro
from nerfstudio.scripts import render as ns_render
from nerfstudio.utils import install_checks

from willags_ns.appearance_spec import (
    PHOTO_FIT_STEPS,
    AppearanceSpecError,
    ImageSpec,
    InterpSpec,
    LatentFileSpec,
    MeanSpec,
    PhotoSpec,
    RefineOptions,
    SampleSpec,
    image_index,
    interpolate_latents,
    parse_spec,
    resolve_latent,
)
from willags_ns.tools.progress import Progress

APPEARANCE_HELP = (
    "Appearance SPEC: mean | image:NAME|STEM|INDEX | photo:PATH | sample:SEED | latent:FILE.npy | interp:A,B[,T] "
    "(A, B any of the others; without T a video sweeps T from 0 to 1 along the camera path). Default: mean, or "
    "training image N's appearance with --camera-idx N."
)


_OPTION_FIELDS = [
    ("appearance", Annotated[str | None, tyro.conf.arg(help=APPEARANCE_HELP)], None),
    (
        "refine_steps",
        Annotated[
            int,
            tyro.conf.arg(
                help="photo: SPECs: Adam steps fitting the latent to the photo (from the encoder's latent, or the "
                "mean; 0 = the encoder's latent as it is, or 50 steps for a model without an encoder)."
            ),
        ],
        0,
    ),
    (
        "refine_view",
        Annotated[
            str | None,
            tyro.conf.arg(
                help="photo: refinement: training image (name, stem or index) seen from the photo's viewpoint; "
                "default: the training view whose render looks most like the photo."
            ),
        ],
        None,
    ),
    (
        "refine_starts",
        Annotated[
            int,
            tyro.conf.arg(
                help="photo: refinement: training appearances also tried as the fit's start (spread over the "
                "training photos' latents); the one rendering the photo's view closest to it starts the fit. "
                "0 = start from the encoder's latent or the mean."
            ),
        ],
        16,
    ),
]


def with_appearance_options(cls: type, module: Any = ns_render) -> type:
    """nerfstudio's command dataclass `cls` (defined in `module`) plus the options --appearance, --refine-steps,
    --refine-view and --refine-starts; its own `main()` runs inside :func:`appearance_hooks`.

    A generated subclass (rather than a hand-written one per command) keeps the options identical everywhere."""

    def main(self) -> None:
        try:  # a SPEC with a syntax error fails before the checkpoint is loaded
            parse_spec(_spec_text(self), "--appearance")
        except AppearanceSpecError as e:
            raise SystemExit(f"error: {e}") from None
        check_render_options(self, module)  # before the checkpoint is loaded too
        if isinstance(self, ns_render.DatasetRender) and self.downscale_factor is not None:
            self.downscale_factor = dataset_downscale_factor(self.load_config, self.downscale_factor)
        with appearance_hooks(self, module) as state:
            cls.main(self)
        out = written_path(self)
        size = f", {out.stat().st_size / 2**20:.1f} MB" if out.is_file() else ""
        step = f", from the checkpoint of step {state['step']}" if "step" in state else ""
        _print_plain(f"{_command(module)}: wrote {out}{size}{step} (appearance: {state.get('appearance', '-')})")

    fields = [(n, t, dataclasses.field(default=d)) for n, t, d in _OPTION_FIELDS]
    sub = dataclasses.make_dataclass(cls.__name__, fields, bases=(cls,), namespace={"main": main})
    sub.__doc__ = cls.__doc__
    sub.__module__ = __name__
    return sub


FFMPEG_HELP = (
    "add --output-format images to write the frames as image files, or install ffmpeg (Debian/Ubuntu: "
    "sudo apt install ffmpeg; macOS: brew install ffmpeg; conda: conda install -c conda-forge ffmpeg)"
)
"""The way out when a video is asked for and ffmpeg is missing."""


def writes_video(opts: Any) -> bool:
    """Whether a render command writes a video (and so needs ffmpeg): every trajectory render unless
    ``--output-format images``; the dataset render writes image files."""
    if isinstance(opts, ns_render.DatasetRender) or not hasattr(opts, "output_format"):
        return False
    return opts.output_format == "video"


def check_render_options(opts: Any, module: Any = ns_render) -> None:
    """Options that would fail or mislead only after the checkpoint is loaded, refused before it with one line:
    a video without ffmpeg on the PATH, and a ``--downscale-factor`` below 1 (nerfstudio renders at 1 / factor of
    the training size, so 0.5 would render at twice it)."""
    if module is not ns_render:
        return
    factor = getattr(opts, "downscale_factor", None)
    if factor is not None and not (factor >= 1):
        raise SystemExit(
            f"error: --downscale-factor {factor:g}: renders are 1/factor of the training size, so the factor must be "
            ">= 1 (1: the training size, 2: half of it)"
        )
    if writes_video(opts) and shutil.which("ffmpeg") is None:
        raise SystemExit(f"error: writing a video needs ffmpeg, which is not on the PATH: {FFMPEG_HELP}")


def training_downscale_factor(config: Any, config_path: Any) -> int:
    """The factor N at which the run of `config` (loaded from `config_path`) read its photos when it trained: its
    dataparser's own, else, for willags-data, the one that parser resolves for the scene (nerfstudio's rule: the
    largest side at most 1600 px). 1 when the scene cannot be read (the render that needs it says why)."""
    from willags_ns.data.dataparser import WillagsDataParserConfig
    from willags_ns.engine.checkpoints import resolve_run_paths
    from willags_ns.engine.checks import WillagsDataError

    dm = config.pipeline.datamanager
    dp = dm.dataparser
    if getattr(dp, "downscale_factor", None):
        return int(dp.downscale_factor)
    if not isinstance(dp, WillagsDataParserConfig):
        return 1
    resolve_run_paths(config, config_path)  # a --data stored relative, from any working directory
    data = getattr(dm, "data", None) or dp.data
    try:
        return dataclasses.replace(dp, data=data).setup().image_downscale_factor()
    except (WillagsDataError, OSError):
        return 1


def dataset_downscale_factor(config_path: Any, factor: float) -> float:
    """The image downscale factor a dataset render of ``--downscale-factor factor`` gives the dataparser, so that it
    renders at 1/factor of the training size, as the trajectory renders do: nerfstudio passes the factor to the
    dataparser, which reads the photos at 1/factor of *their* size; a run that trained at 1/N of its photos (photos
    above 1600 px, or its own --downscale-factor N) reads them at 1/(N x factor). Refused in one line when that is
    not a whole number (images are read at whole fractions of their size)."""
    import yaml

    config = yaml.load(Path(config_path).read_text(), Loader=yaml.Loader)
    trained = training_downscale_factor(config, config_path)
    total = trained * float(factor)
    if not total.is_integer():
        raise SystemExit(
            f"error: --downscale-factor {factor:g}: the run trained at 1/{trained} of its photos' size, so a dataset "
            f"render reads them at 1/{total:g}, which must be a whole fraction: use a factor that makes "
            f"{trained} x factor a whole number"
        )
    if trained > 1:
        _print_plain(
            f"willags-render: --downscale-factor {factor:g}: 1/{factor:g} of the training size (the run trained at "
            f"1/{trained} of its photos' size: they are read at 1/{int(total)})"
        )
    return int(total)


def distinct_frames(cameras):
    """The cameras of a path without repeats of the previous frame. nerfstudio's interpolated path ends each
    transition at the camera the next one starts from, so every training camera but the ends appears twice in a
    row, as two identical frames."""
    if cameras.size < 2:
        return cameras
    c2w = cameras.camera_to_worlds.reshape(cameras.size, -1)
    intr = torch.stack([cameras.fx.reshape(-1), cameras.fy.reshape(-1), cameras.cx.reshape(-1), cameras.cy.reshape(-1)])
    same = (c2w[1:] == c2w[:-1]).all(dim=1) & (intr[:, 1:] == intr[:, :-1]).all(dim=0)
    keep = torch.cat([torch.ones(1, dtype=torch.bool), ~same])
    if bool(keep.all()):
        return cameras
    return cameras[torch.nonzero(keep).reshape(-1)]


def _spec_text(opts) -> str:
    if opts.appearance is not None:
        return opts.appearance
    cam_idx = getattr(opts, "camera_idx", None)
    return f"image:{cam_idx}" if cam_idx is not None else "mean"  # ns-render --camera-idx N: image N's look


def _print_plain(text: str) -> None:
    from nerfstudio.utils.rich_utils import CONSOLE

    CONSOLE.print(text, soft_wrap=True, markup=False, highlight=False)


def _command(module: Any) -> str:
    return "willags-render" if module is ns_render else "willags-export"


def written_path(opts: Any) -> Any:
    """Where a render or export command writes: the video file, the folder of images (nerfstudio names it after the
    output path without its suffix), the dataset render's folder, or the export's PLY."""
    if hasattr(opts, "output_filename") and hasattr(opts, "output_dir"):  # ns-export gaussian-splat
        return opts.output_dir / opts.output_filename
    path = opts.output_path
    if isinstance(opts, ns_render.DatasetRender) or getattr(opts, "output_format", "video") == "video":
        return path
    return path.parent / path.stem


def _fit_start(opts: Any, usual: str) -> str:
    starts = _refine_options(opts).start_candidates
    return f"the closest of {usual} and {starts} training latents" if starts else usual


def describe_appearance(spec: Any, model, opts: Any) -> str:
    """What a SPEC resolved to for `model`, in words: the training image (index and file name), the photo and how
    its latent was found, the seed, the file; for interp, both ends and the weight (or the sweep)."""
    if isinstance(spec, MeanSpec):
        return "mean (the mean of the training images' latents)"
    if isinstance(spec, ImageSpec):
        names = list(model.image_names)
        i = image_index(spec.key, names)
        return f"{spec} = training image {i} ({names[i]})"
    if isinstance(spec, PhotoSpec):
        steps = opts.refine_steps
        if model.appearance_nets is not None and model.appearance_nets.vae is None:
            how = f"fitted {steps or PHOTO_FIT_STEPS} steps from {_fit_start(opts, 'the mean latent')} (no encoder)"
        else:
            encoder = "the encoder's latent"
            how = f"{_fit_start(opts, encoder)}, refined {steps} steps" if steps else encoder
        return f"{spec} ({how})"
    if isinstance(spec, SampleSpec):
        return f"{spec} (a random latent, the same for the same seed)"
    if isinstance(spec, LatentFileSpec):
        return f"{spec} (a latent saved with numpy)"
    if isinstance(spec, InterpSpec):
        ends = f"{describe_appearance(spec.a, model, opts)} -> {describe_appearance(spec.b, model, opts)}"
        weight = f"T = {spec.t:g}" if spec.t is not None else "T from 0 to 1 along the path"
        return f"interp {ends}, {weight}"
    return str(spec)


def _training_cameras(pipeline):
    ds = getattr(pipeline.datamanager, "train_dataset", None)
    return None if ds is None else ds.cameras


def _refine_options(opts) -> RefineOptions:
    """The photo: fit's settings from a command's --refine-* options."""
    return RefineOptions(
        steps=opts.refine_steps,
        view=opts.refine_view,
        start_candidates=getattr(opts, "refine_starts", RefineOptions.start_candidates),
    )


def choose_appearance(pipeline, opts, context: str = "--appearance") -> InterpSpec | None:
    """Set the model's appearance from `opts` (a command with the appearance options). Returns the SPEC when it is a sweep (interp
    without T: each frame needs its own latent), else None."""
    model = pipeline.model
    text = _spec_text(opts)
    spec = parse_spec(text, context)
    if isinstance(spec, InterpSpec) and spec.t is None:
        return spec
    if isinstance(spec, MeanSpec):
        model.render_latent = None
        return None
    refine = _refine_options(opts)
    model.render_latent = resolve_latent(
        spec, model, refine=refine, cameras=_training_cameras(pipeline), context=context
    )
    return None


def sweep_latents(pipeline, spec: InterpSpec, n: int, opts, context: str = "--appearance") -> torch.Tensor:
    """Latents [n, D] for n frames: T = 0 at the first frame, 1 at the last."""
    model = pipeline.model
    refine = _refine_options(opts)
    cams = _training_cameras(pipeline)
    za = resolve_latent(spec.a, model, refine=refine, cameras=cams, context=context)
    zb = resolve_latent(spec.b, model, refine=refine, cameras=cams, context=context)
    ts = torch.linspace(0.0, 1.0, n) if n > 1 else torch.zeros(1)
    return torch.stack([interpolate_latents(za, zb, float(t)) for t in ts])


@contextlib.contextmanager
def appearance_hooks(opts: Any, module: Any = ns_render):
    """Run a nerfstudio command of `module` (nerfstudio.scripts.render or .exporter) with the appearance of `opts`.

    nerfstudio's commands load the checkpoint and build the camera path inside `main()`, so the appearance is set
    through module-level functions of that module, wrapped for the duration: `eval_setup` (choose the appearance
    once the model exists) and, for renders, `_render_trajectory_video` (per-frame latents of a sweep). Writing
    images (`--output-format images`) does not need ffmpeg, so its check only runs for videos.
    """
    state: dict = {}
    orig_setup = module.eval_setup
    orig_video = getattr(module, "_render_trajectory_video", None)
    orig_ffmpeg = install_checks.check_ffmpeg_installed

    def eval_setup(*args, **kwargs):
        out = orig_setup(*args, **kwargs)
        pipeline = out[1]
        state["step"] = int(out[3])  # the checkpoint loaded (an older one when the newest is damaged)
        if getattr(pipeline.model.config, "appearance", None) != "willags":
            if opts.appearance is not None:
                raise SystemExit("--appearance: this checkpoint has no appearance model (willags-3dgs)")
            state["appearance"] = "the model's own colours (no appearance model)"
            _print_plain(f"{_command(module)}: appearance: {state['appearance']}")
            return out
        try:
            state["sweep"] = choose_appearance(pipeline, opts)
            spec = parse_spec(_spec_text(opts), "--appearance")
            text = describe_appearance(spec, pipeline.model, opts)
        except AppearanceSpecError as e:
            raise SystemExit(f"error: {e}") from None
        z = pipeline.model.render_latent
        state["appearance"] = text + (f", |z| = {float(z.norm()):.3g}" if z is not None else "")
        _print_plain(f"{_command(module)}: appearance: {state['appearance']}")
        if state["sweep"] is not None and (isinstance(opts, ns_render.DatasetRender) or orig_video is None):
            raise SystemExit(
                f"error: --appearance {_spec_text(opts)}: only videos sweep; a still needs the weight: interp:A,B,T"
            )
        return out

    def render_trajectory_video(pipeline, cameras, *args, **kwargs):
        if isinstance(opts, ns_render.RenderInterpolated):
            cameras = distinct_frames(cameras)
            if "seconds" in kwargs:  # the video's length follows its frames
                kwargs["seconds"] = int(cameras.size) / opts.frame_rate
        spec = state.get("sweep")
        if spec is not None:
            try:
                z = sweep_latents(pipeline, spec, int(cameras.size), opts)
            except AppearanceSpecError as e:
                raise SystemExit(f"error: {e}") from None
            # indexed with the cameras (nerfstudio's TensorDataclass slices metadata tensors per camera)
            cameras.metadata = {**(cameras.metadata or {}), "appearance_latent": z.to(cameras.device)}
        assert orig_video is not None
        return orig_video(pipeline, cameras, *args, **kwargs)

    def check_ffmpeg_installed():
        if getattr(opts, "output_format", "video") == "video":
            orig_ffmpeg()

    def progress(*columns, **kwargs):
        return Progress(*columns, label=f"{_command(module)}: frames", **kwargs)

    orig_progress = getattr(module, "Progress", None)
    orig_panel = getattr(module, "Panel", None)

    def panel(*args, title=None, **kwargs):  # nerfstudio's dataset banner leaves its split as "{}"
        if isinstance(title, str) and "{}" in title:
            title = title.replace("{}", str(getattr(opts, "split", "")))
        assert orig_panel is not None
        return orig_panel(*args, title=title, **kwargs)

    if orig_panel is not None and isinstance(opts, ns_render.DatasetRender):
        module.Panel = panel
    module.eval_setup = eval_setup
    if orig_video is not None:
        module._render_trajectory_video = render_trajectory_video
    if orig_progress is not None:
        module.Progress = progress  # frames: a line every half minute where rich's bar would not show
    install_checks.check_ffmpeg_installed = check_ffmpeg_installed
    try:
        yield state
    finally:
        module.eval_setup = orig_setup
        if orig_video is not None:
            module._render_trajectory_video = orig_video
        if orig_progress is not None:
            module.Progress = orig_progress
        if orig_panel is not None:
            module.Panel = orig_panel
        install_checks.check_ffmpeg_installed = orig_ffmpeg


RenderCameraPath = with_appearance_options(ns_render.RenderCameraPath)
RenderInterpolated = with_appearance_options(ns_render.RenderInterpolated)
SpiralRender = with_appearance_options(ns_render.SpiralRender)
DatasetRender = with_appearance_options(ns_render.DatasetRender)

Commands = tyro.conf.FlagConversionOff[
    Union[
        Annotated[RenderCameraPath, tyro.conf.subcommand(name="camera-path")],
        Annotated[RenderInterpolated, tyro.conf.subcommand(name="interpolate")],
        Annotated[SpiralRender, tyro.conf.subcommand(name="spiral")],
        Annotated[DatasetRender, tyro.conf.subcommand(name="dataset")],
    ]
]


def entrypoint() -> None:
    """Entrypoint for use with pyproject scripts."""
    tyro.extras.set_accent_color("bright_yellow")
    tyro.cli(Commands).main()


if __name__ == "__main__":
    entrypoint()
