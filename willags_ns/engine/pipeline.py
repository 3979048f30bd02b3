"""WillagsPipeline: nerfstudio's VanillaPipeline, plus handing the training image to the model.

Why a pipeline at all: the beta-VAE encodes the *training image itself* into the appearance latent before the
scene is rendered, but nerfstudio calls `model(camera)` without the batch. The pipeline gives the model the
batch first (`model.set_train_batch`), then runs the usual forward / metrics / loss sequence unchanged.

It is also where every willags method checks its inputs and guards training, whatever the dataparser
(docs/reliability.md):

- before nerfstudio's parser runs, the raw scene (transforms.json or the COLMAP model) is checked where we know
  its layout (`precheck_dataparser_config`);
- after parsing and before the model is built or an image is cached, `checks.validate_dataparser_outputs`: image
  files exist, decode, match their camera's size; poses finite and rotations proper; fx, fy > 0; >= 1 image;
- during training: a clear error when every Gaussian was pruned; a (rate-limited) warning when the transient mask
  was rejected because it flagged most of an image;
- before training, a warning for a photo whose colours do not follow the SfM points it should show (a photo of
  another place under a registered frame: `check_photo_content`); up to `checks.MAX_LISTED_WARNINGS` warnings are
  printed one by one, more as a summary (counts per kind, a few photos each), and every one is written to the run
  folder's `input_warnings.txt`;
- with `--pipeline.model.auto-config True` (the method willags), the scene is inspected and the model's switches
  set before the model is built (willags_ns/tools/autoconfig.py);
- Ctrl-C (SIGINT) finishes the current step, writes a checkpoint and exits (status 130), so `--load-dir` resumes
  at the next step with the same parameters and optimiser state (`InterruptCheckpoint`); the printed command
  resumes it and ends at the planned step;
- every willags command that loads a checkpoint (ns-eval, ns-render, ns-viewer, willags-render, willags-export)
  reads it through willags_ns/engine/checkpoints.py: the newest readable one, a damaged one named
  (`checkpoints.install_eval_loader`, installed when the pipeline is built).

With `--machine.num-devices N` (N > 1) it trains data-parallel without nerfstudio's DDP wrapper: each rank renders
its own image, gradients are averaged before the optimiser step and densification agrees over the ranks
(willags_ns/engine/distributed.py, docs/distributed.md).
"""

import json
import math
import os
import signal
import sys
from dataclasses import dataclass, field
from pathlib import Path

import torch
from nerfstudio.engine.callbacks import TrainingCallback, TrainingCallbackAttributes, TrainingCallbackLocation
from nerfstudio.engine.optimizers import Optimizers
from nerfstudio.pipelines.base_pipeline import VanillaPipeline, VanillaPipelineConfig
from nerfstudio.utils import comms
from nerfstudio.utils.rich_utils import CONSOLE

from willags_ns.data.consistency import foreign_photo_warnings
from willags_ns.data.datamanager import use_willags_datamanager
from willags_ns.data.dataparser import SCENE_RECORD, WillagsDataError
from willags_ns.engine.checkpoints import eval_setup_run, install_eval_loader, resolve_run_paths
from willags_ns.engine.checks import (
    INPUT_WARNINGS_FILE,
    check_gaussians_alive,
    install_cli_excepthook,
    report_warnings,
    validate_dataparser_outputs,
    write_warnings,
)
from willags_ns.engine.distributed import (
    DataParallelConfig,
    DataParallelError,
    GradientAverager,
    ImageCachePrefetch,
    apply_latent_rows,
    average_gradients,
    broadcast_module,
    comm_device,
    draw_refine_seed,
    from_rank_zero,
    latent_row,
    optimizer_parameters,
    rank_and_world_size,
    shard_image_cache,
    shard_train_images,
    share_train_latents,
    synced_strategy,
    validate_data_parallel,
    validate_train_images,
)
from willags_ns.engine.step_profile import StepProfile
from willags_ns.engine.streams import guard_output, say_on_stderr_too
from willags_ns.eval.protocol import EvalProtocolConfig, describe_protocol, eval_split_images, evaluate_model
from willags_ns.tools.autoconfig import (
    AUTO_CONFIG_FILE,
    apply_auto_config,
    format_summary,
    scene_dir,
    tensorboard_entries,
)
from willags_ns.tools.progress import Progress
from willags_ns.viewer import appearance_controls, guard_viewer_host


@dataclass
class WillagsPipelineConfig(VanillaPipelineConfig):
    """VanillaPipeline that passes the training batch to the model before its forward pass."""

    _target: type = field(default_factory=lambda: WillagsPipeline)
    eval_protocol: EvalProtocolConfig = field(default_factory=lambda: EvalProtocolConfig(fit_max_side=-1))
    """NeRF-W protocol used by `ns-eval` (fit the latent on the left half of each test image, score the right). Its
    fit runs at most CPU_FIT_MAX_SIDE px on the CPU (fit_max_side -1; 0 = full resolution)."""
    check_inputs: bool = True
    """Before training: check every training image (exists, decodes, matches its camera's size), the poses
    (finite, proper rotations) and the intrinsics (fx, fy > 0); stop with a message naming the file / frame."""
    check_photo_content: bool = True
    """Before training: warn about training photos whose colours do not follow the SfM points they should show (a
    photo of another place under a registered frame; willags_ns/data/consistency.py). Needs SfM points; ~2 s per 50
    photos on a CPU."""
    checkpoint_on_interrupt: bool = True
    """Ctrl-C, a closed terminal (SIGHUP) or a closed stdout (`| tee` ended) finishes the current step, writes a
    checkpoint and exits; the printed command (also in resume_command.txt) resumes it. A second Ctrl-C interrupts at
    once."""
    auto_config_keep: tuple[str, ...] = ()
    """Model switches (dotted fields under pipeline.model, e.g. "use_mask") that `auto_config` leaves as they are:
    the trainer fills it with those the command line set (named as a flag, or changed from the method's own preset),
    so a user's flag wins over the inspector's recommendation."""
    data_parallel: DataParallelConfig = field(default_factory=DataParallelConfig)
    """With --machine.num-devices N > 1: how the ranks average gradients and cache images; the step profile (one
    device too). willags_ns/engine/distributed.py, docs/distributed.md."""
    time_budget_minutes: float | None = None
    """Train within this many minutes of training steps (None or 0: off; set-up not counted). Before training
    `ns-train willags` chooses the preset (willags-lite or willags), the step count and the resolution schedule from
    measured points (willags_ns/engine/time_budget.py); after steps 20-70 the run's own step time sets the last step (never
    past the preset's default), the densification and mask schedules fit into it (the learning-rate schedules stay the
    preset's; a plan under 2000 steps trains at 4 times its rates, falling to 0 over its second half), and the choice
    is printed and kept in
    time_budget.json. Other methods (willags-lite named explicitly too) keep their model; only their step count
    follows the budget."""


def precheck_dataparser_config(datamanager_config) -> None:
    """Check the raw scene of nerfstudio's own parsers (nerfstudio-data, colmap) before they run, so a missing
    file or a NaN pose is named instead of failing inside them. willags-data checks its scenes itself."""
    from nerfstudio.data.dataparsers.colmap_dataparser import ColmapDataParserConfig
    from nerfstudio.data.dataparsers.nerfstudio_dataparser import NerfstudioDataParserConfig

    from willags_ns.data.dataparser import WillagsDataParserConfig, check_colmap, check_transforms

    dp = datamanager_config.dataparser
    data = datamanager_config.data if datamanager_config.data is not None else getattr(dp, "data", None)
    if isinstance(dp, WillagsDataParserConfig) or data is None:
        return
    data = Path(data)
    if isinstance(dp, NerfstudioDataParserConfig):
        json_path = data if data.suffix == ".json" else data / "transforms.json"
        if json_path.is_file():
            check_transforms(json_path, dp.downscale_factor)
    elif isinstance(dp, ColmapDataParserConfig):
        model = data / dp.colmap_path
        if model.is_dir():
            check_colmap(data, model, data / dp.images_path, need_points=False)


def use_saved_scene_without_photos(datamanager_config, record: Path) -> bool:
    """When a saved run's scene folder is gone and the run kept its cameras (``record``, written when training
    started), read the scene from the record instead: loading the trained model needs the cameras, not the photos
    (willags-export, trajectory renders). Returns whether it did; commands that read photos (ns-eval, dataset
    renders) then name the missing files."""
    from willags_ns.data.dataparser import SavedSceneDataParserConfig

    dp = datamanager_config.dataparser
    data = datamanager_config.data if datamanager_config.data is not None else getattr(dp, "data", None)
    if data is None or Path(data) == Path() or Path(data).expanduser().exists() or not record.is_file():
        return False
    datamanager_config.dataparser = SavedSceneDataParserConfig(record=record, data=Path(data))
    datamanager_config.data = None
    CONSOLE.log(f"willags: the scene {data} does not exist; using the cameras saved with the run ({record.name})")
    return True


def write_scene_record(datamanager, path: Path) -> None:
    """The run's scene without its photos (willags_ns.data.dataparser.scene_record), beside config.yml."""
    from willags_ns.data.dataparser import scene_record
    from willags_ns.data.sfm_tracks import SFM_OBSERVATIONS_KEY
    from willags_ns.engine.checkpoints import save_atomic

    train = datamanager.train_dataparser_outputs
    try:
        test = datamanager.dataparser.get_dataparser_outputs(split="test")
    except Exception:  # noqa: BLE001 - a scene without a test split: the record holds the training cameras only
        test = None
    save_atomic(scene_record(train, test, SFM_OBSERVATIONS_KEY in train.metadata), path)


STOP_SIGNALS = {"SIGINT": "interrupt (Ctrl-C)", "SIGHUP": "hang-up (the terminal closed)"}
"""Signals that stop training after the current step with a checkpoint (those the platform has), and their names."""
OUTPUT_LOST_STATUS = 141
"""Exit status of a run stopped because its output's reader went away (128 + SIGPIPE, as a shell reports it)."""


class InterruptCheckpoint:
    """Ctrl-C (SIGINT), a closed terminal (SIGHUP) or a closed stdout -> finish the step, checkpoint, exit
    (128 + the signal's number; 141 for a closed stdout).

    The handlers are installed at the first training step (BEFORE_TRAIN_ITERATION) and the previous ones restored
    when training ends (AFTER_TRAIN) or after the checkpoint. The first signal also restores the previous handler, so
    a second Ctrl-C interrupts at once (and, should training have died of an exception before AFTER_TRAIN, the stale
    handler costs one extra Ctrl-C, never a process that cannot be interrupted).

    The output: `ns-train ... | tee log` loses its reader with the Ctrl-C (tee gets it too), a closed terminal with
    the hang-up. From the first step ``sys.stdout`` and ``sys.stderr`` are guarded (willags_ns/engine/streams.py): a
    write whose reader is gone no longer raises in the middle of a step, and a closed stdout itself asks for the stop.
    The handler writes its notice straight to file descriptor 2 (printing through Python's buffered streams from a
    signal handler can re-enter a write it interrupted); the resume command also goes to stderr when stdout is a pipe
    or a file and stderr is elsewhere (the terminal under `| tee`), and it is in resume_command.txt whatever happens.

    Why at the end of a step: a checkpoint written from inside the backward or the optimiser step would hold
    parameters and Adam moments from two different steps. Saved after every AFTER_TRAIN_ITERATION callback of
    step s (this one is the last registered), the checkpoint is exactly the state the next step would start from;
    nerfstudio resumes at s + 1.
    """

    def __init__(self, trainer):
        self.trainer = trainer
        self.requested = False
        self.status = 130
        self.installed = False
        self._prev: dict[int, object] = {}
        self._restore_output = None

    def _handler(self, signum, frame):
        what = STOP_SIGNALS.get(signal.Signals(signum).name, signal.Signals(signum).name)
        again = "; Ctrl-C again to stop at once" if signum == signal.SIGINT else ""
        self._request(128 + signum, f"willags: {what} received; finishing this step and writing a checkpoint{again}")
        self._restore_signals()

    def _output_lost(self, name: str) -> None:
        if name == "stdout" and self.installed:  # during training: stop as on Ctrl-C
            self._request(
                OUTPUT_LOST_STATUS,
                "willags: stdout was closed (nothing reads the output any more); finishing this step and writing a "
                "checkpoint",
            )

    def _request(self, status: int, notice: str) -> None:
        if self.requested:
            return
        self.requested = True
        self.status = status
        try:  # straight to the file descriptor: see the class docstring
            os.write(2, f"\n{notice}\n".encode())
        except OSError:
            pass

    def install(self, step: int) -> None:
        if self.installed or self.requested:
            return
        try:
            for name in STOP_SIGNALS:
                if hasattr(signal, name):
                    num = getattr(signal, name)
                    self._prev[num] = signal.signal(num, self._handler)
            self.installed = True
        except ValueError:  # not the main thread (a trainer driven from a thread): leave the signals alone
            self._restore_signals()
            return
        if self._restore_output is None:
            self._restore_output = guard_output(self._output_lost)

    def _restore_signals(self) -> None:
        for num, prev in self._prev.items():
            default = signal.default_int_handler if num == signal.SIGINT else signal.SIG_DFL
            signal.signal(num, prev if prev is not None else default)  # type: ignore[arg-type]
        self._prev = {}
        self.installed = False

    def uninstall(self, step: int | None = None) -> None:
        self._restore_signals()
        # a run stopped on request keeps its guarded output until the process ends (the reader may be gone)
        if self._restore_output is not None and not self.requested:
            self._restore_output()
            self._restore_output = None

    def after_step(self, step: int) -> None:
        if not self.requested:
            return
        self._restore_signals()
        self.trainer.save_checkpoint(step)
        path = self.trainer.checkpoint_dir / f"step-{step:09d}.ckpt"
        from nerfstudio.utils import writer

        writer.write_out_storage()
        if hasattr(self.trainer, "resume_command"):  # willags' trainer: the exact command
            command = self.trainer.resume_command(step)
        else:
            from willags_ns.engine.checkpoints import resume_command

            end = self.trainer._start_step + self.trainer.config.max_num_iterations
            command = resume_command([], str(self.trainer.config.method_name), path, end - step - 1)
        text = f"willags: interrupted after step {step}; checkpoint {path}\nresume with: {command}"
        CONSOLE.print(text, soft_wrap=True, markup=False, highlight=False)  # one line however long: a shell's
        if say_on_stderr_too():
            print(text, file=sys.stderr, flush=True)
        raise SystemExit(self.status)


class WillagsPipeline(VanillaPipeline):
    config: WillagsPipelineConfig

    def __init__(self, config: WillagsPipelineConfig, *args, **kwargs):
        """nerfstudio's pipeline, set up in steps: the step profile and the devices, the run's paths, the inspection
        that sets the model's switches, the pipeline built with the inputs checked before the model, the model told
        about the scene, the ranks joined."""
        install_cli_excepthook()
        install_eval_loader()  # eval_setup loads the checkpoint after this pipeline is built
        # VanillaPipeline's arguments by name: (device, test_mode, world_size, local_rank, grad_scaler)
        setup_kwargs = dict(
            zip(("device", "test_mode", "world_size", "local_rank", "grad_scaler"), args, strict=False), **kwargs
        )
        test_mode = setup_kwargs.get("test_mode", "val")
        world_size = int(setup_kwargs.get("world_size", 1))
        self._start_step_profile(config, setup_kwargs, test_mode, world_size)
        if world_size > 1:
            self._take_device(config, setup_kwargs, world_size)
        checking = config.check_inputs and test_mode == "val"  # training ("val"); not ns-eval / viewer / render
        self._resolve_run(config, test_mode)
        if checking:
            precheck_dataparser_config(config.datamanager)
        self._inspect_scene(config)
        self._image_prefetch: ImageCachePrefetch | None = None
        self._build(config, setup_kwargs, checking, world_size)
        self.world_size = world_size
        self.rank = rank_and_world_size()[0]
        self._tell_model_the_scene()
        self._pending_rejected: tuple | None = None  # (step, batch, flag tensor) of the last mask step
        self._image_sizes_told = False  # the training images' sizes: told at the first step
        self._step_image_idx = -1
        if world_size > 1:
            self._setup_data_parallel(world_size)
            if self.step_profile is not None:
                self.step_profile.phase("data_parallel_ready")
            if self._image_prefetch is not None:
                self._image_prefetch.wait()
                self._image_prefetch = None
                if self.step_profile is not None:
                    self.step_profile.phase("images_cached")

    def _start_step_profile(self, config: WillagsPipelineConfig, setup_kwargs: dict, test_mode: str, world_size: int):
        """`data_parallel.step_profile` while training: the step profile, from this first phase on."""
        # a config.yml written before the field existed has no data_parallel
        self.data_parallel = getattr(config, "data_parallel", None) or DataParallelConfig()
        self.step_profile: StepProfile | None = None
        if self.data_parallel.step_profile and test_mode == "val":
            rank = rank_and_world_size()[0]
            device = torch.device(str(setup_kwargs.get("device", "cpu")))
            meta = {"local_rank": setup_kwargs.get("local_rank", 0), "reduction": self.data_parallel.reduction}
            self.step_profile = StepProfile(Path("."), rank, world_size, device, meta)
            self.step_profile.phase("pipeline_init")

    def _take_device(self, config: WillagsPipelineConfig, setup_kwargs: dict, world_size: int) -> None:
        """Several devices: check the launch, make this rank's device the current one, and build the pipeline as for
        one device (the ranks are joined at the end: _setup_data_parallel)."""
        validate_data_parallel(world_size, setup_kwargs.get("device"), config.datamanager)
        device = torch.device(str(setup_kwargs.get("device")))
        if device.type == "cuda" and device.index is not None:
            torch.cuda.set_device(device)  # NCCL and gsplat's launches follow the current device
        # no DistributedDataParallel wrapper: its fixed buckets break when densification replaces the
        # Gaussians; gradients are averaged by hand before each optimiser step (willags_ns/engine/distributed.py)
        setup_kwargs["world_size"] = 1

    def _resolve_run(self, config: WillagsPipelineConfig, test_mode: str) -> None:
        """A saved run's paths beside its config.yml (and its scene without photos where they are gone), willags'
        datamanager, and ns-viewer off the network by default."""
        run = eval_setup_run()
        if run is not None and run[1].pipeline is config:  # a saved run: its paths beside its config.yml
            resolve_run_paths(run[1], run[0])
            if test_mode != "val":
                use_saved_scene_without_photos(config.datamanager, Path(run[0]).parent / SCENE_RECORD)
        use_willags_datamanager(config.datamanager)  # an image cache that works on a CPU past 500 photos
        if test_mode == "test":  # ns-viewer / ns-render / ns-eval: keep ns-viewer off the network by default
            guard_viewer_host()

    def _inspect_scene(self, config: WillagsPipelineConfig) -> None:
        """With auto_config, the inspection's switches on the model config before the model exists (they decide which
        modules and parameters it has). Several ranks: rank 0 inspects, the others take its settings (the same scene,
        the same decision)."""
        self.auto_config_summary = None
        if getattr(config.model, "auto_config", False):
            summary, inspected = from_rank_zero(
                lambda: apply_auto_config(config.model, scene_dir(config.datamanager), keep=config.auto_config_keep)
            )
            if not inspected:
                for key, value in summary.get("settings", {}).items():
                    *parents, last = key.split(".")
                    target = config.model
                    for part in parents:
                        target = getattr(target, part)
                    setattr(target, last, value)
            if inspected and not summary.get("missing"):  # a missing scene: the dataparser's one line follows
                CONSOLE.print(format_summary(summary))
            # resolved either way (the recommended switches, or the method's own where nothing could be inspected):
            # config.yml is rewritten with it, so reloading builds the trained model without inspecting again
            config.model.auto_config = False
            self.auto_config_summary = summary
        if self.step_profile is not None:
            self.step_profile.phase("scene_inspected")

    def _build(self, config: WillagsPipelineConfig, setup_kwargs: dict, checking: bool, world_size: int) -> None:
        """VanillaPipeline's set-up, with the input checks between the parsed scene and the model. The model is built
        inside VanillaPipeline.__init__ right after the datamanager parses the scene; the outputs are validated in
        between (a NaN pose would otherwise surface in the model's kNN as a sklearn error). With several devices the
        rank's share of the training images is then cached in the background while the model is built
        (`_prefetch_images`). The hook is an instance attribute on this config only, removed again below."""
        model_config = config.model
        original_setup = model_config.setup
        self.input_warnings: list[str] = []  # the input checks' warnings: run folder's INPUT_WARNINGS_FILE
        self.input_warnings_summarised = False

        def setup_after_checks(**model_kwargs):
            if self.step_profile is not None:
                self.step_profile.phase("data_parsed")
            if checking:
                device = setup_kwargs.get("device")
                outputs = self.datamanager.train_dataparser_outputs
                found = validate_dataparser_outputs(outputs, device=str(device) if device is not None else None)
                if rank_and_world_size()[0] == 0:  # warnings, printed once
                    if config.check_photo_content:
                        found += foreign_photo_warnings(outputs)
                    # one line per photo is fine for a few; a collection of thousands gets a summary
                    where = f"{INPUT_WARNINGS_FILE} in the run folder, beside config.yml"
                    self.input_warnings_summarised = report_warnings(found, where)
                    self.input_warnings = found
            if self.step_profile is not None:
                self.step_profile.phase("inputs_checked")
            if world_size > 1:
                self._prefetch_images(setup_kwargs.get("device"), world_size)
            return original_setup(**model_kwargs)

        model_config.setup = setup_after_checks  # type: ignore[method-assign]
        try:
            super().__init__(config, **setup_kwargs)
        finally:
            del model_config.setup
        if self.step_profile is not None:
            self.step_profile.phase("model_built")

    def _prefetch_images(self, device, world_size: int) -> None:
        """Several devices, once the scene is parsed and checked: this rank's share of the training images (the
        image cache sharded) starts caching in a background thread, so that it overlaps the model's construction
        (joined at the end of the set-up: ImageCachePrefetch)."""
        rank, _ = rank_and_world_size()
        validate_train_images(len(self.datamanager.train_dataset), world_size)
        if self.data_parallel.shard_image_cache:
            shard_image_cache(self.datamanager, rank, world_size)
        if self.step_profile is not None:
            self.step_profile.phase("images_cache_start")
        self._image_prefetch = ImageCachePrefetch(self.datamanager, device)

    def _tell_model_the_scene(self) -> None:
        """The model learns the training photos' names (the appearances users pick) and the test photos (a SPEC naming
        one is told so); the viewer's appearance panel attaches (nerfstudio's viewer finds its elements on the
        pipeline; it shows a training view's transient mask and teacher render from the training dataset)."""
        names = [Path(p).name for p in self.datamanager.train_dataparser_outputs.image_filenames]
        if hasattr(self.model, "set_train_image_names"):
            self.model.set_train_image_names(names)
        eval_dataset = getattr(self.datamanager, "eval_dataset", None)
        if eval_dataset is not None and hasattr(self.model, "set_test_photos"):
            self.model.set_test_photos([str(p) for p in eval_dataset.image_filenames])
        if getattr(self.model, "appearance_nets", None) is not None:
            self.viewer_controls = appearance_controls(self.model)
            self.viewer_controls.set_train_dataset(self.datamanager.train_dataset)

    def _tell_model_the_image_sizes(self) -> None:
        """The training images' (width, height) as the training cameras give them, for the model to know each training
        camera's size on the host (a GPU camera's width read in every forward is a wait for the GPU). Told after the
        first `next_train`: nerfstudio's full-image datamanager caches the images there, and undistorting a photo
        changes its camera's size in the training dataset (OpenCV crops the undistorted image)."""
        self._image_sizes_told = True
        if not hasattr(self.model, "set_train_image_sizes"):
            return
        cameras = self.datamanager.train_dataset.cameras
        widths, heights = cameras.width.reshape(-1).tolist(), cameras.height.reshape(-1).tolist()
        self.model.set_train_image_sizes(list(zip(widths, heights, strict=True)))

    def _setup_data_parallel(self, world_size: int) -> None:
        """Same model on every rank, a share of the images per rank, densification that agrees over the ranks."""
        rank, _ = rank_and_world_size()
        num_images = len(self.datamanager.train_dataset)
        validate_train_images(num_images, world_size)
        shard_train_images(self.datamanager, rank, world_size)  # (the image cache is sharded: _prefetch_images)
        broadcast_module(self.model)  # nerfstudio seeds rank r with seed + r: rank 0's initialisation wins
        strategy = synced_strategy(self.model.strategy, draw_refine_seed(), world_size)
        # after an opacity reset gsplat waits one epoch (splatfacto: num_train_data + refine_every steps) before
        # refining again, so that every image is seen once; with one image per rank an epoch is N times shorter
        if hasattr(strategy, "pause_refine_after_reset"):  # (MCMC densification never resets opacities)
            strategy.pause_refine_after_reset -= num_images - math.ceil(num_images / world_size)
        self.model.strategy = strategy
        if rank == 0:
            CONSOLE.log(
                f"willags: data-parallel training on {world_size} devices: one image per device per step, gradients "
                "averaged before each optimiser step, densification statistics all-reduced before each refinement"
            )

    def get_training_callbacks(self, training_callback_attributes: TrainingCallbackAttributes):
        cbs = super().get_training_callbacks(training_callback_attributes)
        trainer = training_callback_attributes.trainer
        if self.config.time_budget_minutes and trainer is not None and not hasattr(trainer, "time_budget"):
            from willags_ns.engine.time_budget import OPTION, TimeBudgetError

            raise TimeBudgetError(
                f"{OPTION} needs willags' trainer (willags_ns.engine.trainer.WillagsTrainerConfig, which every willags method "
                f"uses); this run's trainer is {type(trainer).__name__}"
            )
        if self.auto_config_summary is not None and trainer is not None:
            cbs.append(self._record_auto_config(trainer))
        if trainer is not None and comms.is_main_process():
            Path(trainer.base_dir).mkdir(parents=True, exist_ok=True)
            write_scene_record(self.datamanager, Path(trainer.base_dir) / SCENE_RECORD)
            if self.input_warnings:
                path = write_warnings(self.input_warnings, Path(trainer.base_dir) / INPUT_WARNINGS_FILE)
                if self.input_warnings_summarised:
                    CONSOLE.print(
                        f"willags: the {len(self.input_warnings)} warnings about the input: {path}",
                        soft_wrap=True,  # one line: a path to copy
                        markup=False,
                        highlight=False,
                    )
        optimizers = training_callback_attributes.optimizers
        profile = self.step_profile
        if profile is not None and trainer is not None:
            profile.directory = Path(trainer.base_dir) / "step_profile"
            cbs += self._profile_callbacks(profile)
        if (self.world_size > 1 or profile is not None) and optimizers is not None:
            self._average_gradients_before_step(optimizers)
        if self.config.checkpoint_on_interrupt and trainer is not None and self.world_size > 1:
            # nerfstudio's launcher terminates every rank on Ctrl-C (the parent gets the SIGINT too), so a rank
            # cannot finish its step first: resume from the last periodic checkpoint instead
            if comms.is_main_process():
                CONSOLE.log("willags: several devices: Ctrl-C stops at once (no interrupt checkpoint)")
        elif self.config.checkpoint_on_interrupt and trainer is not None:
            ic = InterruptCheckpoint(trainer)
            self.interrupt_checkpoint = ic
            cbs.append(TrainingCallback([TrainingCallbackLocation.BEFORE_TRAIN_ITERATION], ic.install))
            cbs.append(TrainingCallback([TrainingCallbackLocation.AFTER_TRAIN_ITERATION], ic.after_step))
            cbs.append(TrainingCallback([TrainingCallbackLocation.AFTER_TRAIN], ic.uninstall))
        return cbs

    def _average_gradients_before_step(self, optimizers: Optimizers) -> None:
        """Data-parallel: the trainer's optimiser step first averages every gradient over the ranks (after the
        backward pass, which nerfstudio runs between get_train_loss_dict and this step) and shares this step's
        image latents (`data_parallel.reduction`). With the step profile, it also marks the reduction and the
        optimiser step (on one device: the optimiser step alone)."""
        step_some = optimizers.optimizer_scaler_step_some
        if getattr(step_some, "willags_averages_gradients", False):
            return  # already installed (callbacks requested twice)
        profile = self.step_profile
        averager = None
        if self.world_size > 1 and self.data_parallel.reduction == "buffer":
            averager = GradientAverager(self.world_size)
            if profile is not None:
                averager.collective = (lambda: profile.mark("collective_start"), lambda: profile.mark("collective_end"))

        def averaged_step_some(grad_scaler, param_groups):
            if profile is not None:
                profile.mark("reduce_start")
            if self.world_size > 1:
                self._average(optimizers, averager)
            if profile is not None:
                profile.mark("reduce_end")
            out = step_some(grad_scaler, param_groups)
            if profile is not None:
                profile.mark("optimizer_end")
            return out

        averaged_step_some.willags_averages_gradients = True  # type: ignore[attr-defined]
        optimizers.optimizer_scaler_step_some = averaged_step_some  # type: ignore[method-assign]

    def _average(self, optimizers: Optimizers, averager: GradientAverager | None) -> None:
        """Average the gradients over the ranks and share this step's training-image latents."""
        params = optimizer_parameters(optimizers.optimizers)
        model, profile = self.model, self.step_profile
        # the memo is written by the rank that drew the image, so each step's row is shared; an embedding table is a
        # parameter (its gradients are averaged with the others) and has no memo
        memo = model.latent_memo() if hasattr(model, "latent_memo") else None
        latents, seen = memo if memo is not None else (None, None)
        if averager is None:  # the reference implementation
            if profile is not None:
                profile.mark("collective_start")
            average_gradients(params, self.world_size)
            if latents is not None:
                share_train_latents(latents, seen, self._step_image_idx)
            if profile is not None:
                profile.mark("collective_end")
                profile.note(bytes=4 * (len(params) + sum(p.numel() for p in params)))
            return
        row, width = None, 0
        if latents is not None:
            width = latents.shape[1] + 1
            row = latent_row(latents, seen, self._step_image_idx, comm_device())
        rows = averager.average(params, row, width)
        if rows is not None and latents is not None:
            apply_latent_rows(latents, seen, rows)
        if profile is not None:
            profile.note(bytes=averager.bytes_reduced, host_reads=averager.host_reads)

    def _profile_callbacks(self, profile: StepProfile) -> list[TrainingCallback]:
        """The step profile's marks around the trainer's loop: the training images cached (timed apart, before the
        first step, so that the first step's timing is its own), the end of the after-step callbacks, the files."""

        def cache_images(step: int) -> None:
            if "images_cached" not in profile.meta["phases"]:
                profile.phase("images_cache_start")
                _ = self.datamanager.cached_train  # nerfstudio loads them at the first access
                profile.phase("images_cached")

        return [
            TrainingCallback([TrainingCallbackLocation.BEFORE_TRAIN_ITERATION], cache_images),
            TrainingCallback(
                [TrainingCallbackLocation.AFTER_TRAIN_ITERATION], lambda step: profile.mark("callbacks_end")
            ),
            TrainingCallback([TrainingCallbackLocation.AFTER_TRAIN], lambda step: profile.flush(final=True)),
        ]

    def _record_auto_config(self, trainer) -> TrainingCallback:
        """auto_config.json and the resolved config.yml now; tensorboard at the first step (writers are set up)."""
        summary = self.auto_config_summary
        base = Path(trainer.base_dir)
        if comms.is_main_process():  # one writer when several devices train (every rank resolved the same)
            base.mkdir(parents=True, exist_ok=True)
            (base / AUTO_CONFIG_FILE).write_text(json.dumps(summary, indent=1, default=str))
            trainer.config.save_config()  # config.yml: the resolved switches, auto_config False
        text, scalars = tensorboard_entries(summary)
        logged = []

        def log_once(step: int) -> None:
            if logged:
                return
            from nerfstudio.utils import writer

            writer.put_config(name="auto_config", config_dict=text, step=step)
            for name, value in scalars.items():
                writer.put_scalar(name=name, scalar=value, step=step)
            logged.append(step)

        return TrainingCallback([TrainingCallbackLocation.BEFORE_TRAIN_ITERATION], log_once)

    def get_train_loss_dict(self, step: int):
        profile = self.step_profile
        if profile is not None:
            profile.mark("start")
        check_gaussians_alive(self.model.num_points, step)
        camera, batch = self.datamanager.next_train(step)
        if not self._image_sizes_told:
            self._tell_model_the_image_sizes()
        self._step_image_idx = int(batch.get("image_idx", -1))  # shared with the other ranks (several devices)
        if self.world_size > 1 and self._step_image_idx >= 0 and self._step_image_idx % self.world_size != self.rank:
            raise DataParallelError(
                f"willags: rank {self.rank} drew training image {self._step_image_idx}, which belongs to rank "
                f"{self._step_image_idx % self.world_size} (its image cache holds a placeholder there)"
            )
        self._report_rejected_mask()
        self.model.set_train_batch(batch)  # type: ignore[attr-defined]
        model_outputs = self._model(camera)
        metrics_dict = self.model.get_metrics_dict(model_outputs, batch)
        loss_dict = self.model.get_loss_dict(model_outputs, batch, metrics_dict)
        if "mask_rejected" in metrics_dict:
            self._pending_rejected = (step, batch, metrics_dict["mask_rejected"])
        if profile is not None:
            profile.mark("forward_end")
            size = getattr(self.model, "last_size", None)
            profile.note(
                step=step,
                image=self._step_image_idx,
                pixels=int(size[0] * size[1]) if size else None,
                gaussians=int(self.model.num_points),
                teacher="teacher_rgb" in model_outputs,
            )
        return model_outputs, loss_dict, metrics_dict

    def _report_rejected_mask(self) -> None:
        """Warn about the previous mask step's rejected mask, read one step late: reading the device flag in its
        own step would stall there until the GPU has run VGG; here, before this step's work is queued, the read waits
        for the previous step's work to finish (on a GPU, the one wait for the device in the step after a mask
        step: the forward pass reads nothing from the device)."""
        pending, self._pending_rejected = self._pending_rejected, None
        if pending is not None and bool(pending[2]):
            self._warn_mask_rejected(pending[0], pending[1])

    def get_average_eval_image_metrics(self, step=None, output_path=None, get_std: bool = False):
        """`ns-eval`: the NeRF-W protocol over the eval split (see willags_ns/eval/protocol.py).

        Headline `psnr`/`ssim`/`lpips` are right-half scores with the fitted latent; `encoder_*` use the encoder's
        latent without optimisation; `full_*` score the whole image.
        """
        ds = self.datamanager.eval_dataset
        missing = [Path(p) for p in ds.image_filenames if not Path(p).is_file()]
        if missing:
            raise WillagsDataError(
                f"ns-eval scores the test photos, and {len(missing)} of them do not exist (first: {missing[0]}): "
                "put the scene back where it was trained, or pass its new folder (ns-eval reads the data path from "
                "config.yml: edit 'data' there)"
            )
        images = eval_split_images(self.datamanager)
        names = [Path(p).name for p in ds.image_filenames]
        self.eval()
        cfg = self.config.eval_protocol
        CONSOLE.print(describe_protocol(cfg, ds.cameras, self.model), soft_wrap=True, markup=False, highlight=False)
        with Progress(label="ns-eval") as progress:
            agg, per_image = evaluate_model(self.model, ds.cameras, images, cfg, names, progress=progress)
        self.train()
        if get_std and len(per_image) > 1:
            import statistics

            for k in ("psnr", "ssim", "lpips"):
                if k in per_image[0]:
                    agg[f"{k}_std"] = statistics.pstdev(float(r[k]) for r in per_image)
        return agg

    def _warn_mask_rejected(self, step: int, batch) -> None:
        """The model's mask-health warning (mask/health.MaskHealth.rejected) for the photo of `batch`."""
        idx = int(batch.get("image_idx", -1))
        names = self.datamanager.train_dataparser_outputs.image_filenames
        name = Path(names[idx]).name if 0 <= idx < len(names) else f"image {idx}"
        message = self.model.mask_health.rejected(step, name, self.model.config.mask.max_masked_fraction)
        if message is not None:
            CONSOLE.log(message)
