"""WillagsTrainer: nerfstudio's Trainer, plus the time budget (`--pipeline.time-budget-minutes N`) and checkpoints
that survive faults.

Why a Trainer of our own: the budget decides things only the trainer owns. Before the pipeline is built it picks the
preset (its model config) and the step cap; during training it fits the step schedules (densification, mask) into
the planned steps and stops the loop at the step the run's own clock allows (nerfstudio's loop runs a fixed ``max_num_iterations``). The decisions
themselves are pure functions in willags_ns/engine/time_budget.py, and so is their wiring into this trainer (its
last section: the preset's switch, the callbacks that measure and stop, the step table, the learning rates, the
record), which the trainer's set-up calls.

Checkpoints (willags_ns/engine/checkpoints.py, docs/reliability.md): every save is atomic, and one that fails (a full disk)
stops training with one line naming the directory, the size needed, the last good checkpoint and the command that
resumes from it; saves come every ``steps_per_save`` steps and also every ``save_every_minutes`` of wall time (a
killed run loses at most that much work); after each save, ``resume_command.txt`` beside config.yml holds the exact
command that resumes from it (``--load-checkpoint`` naming its file) and ends at the planned step. ``--load-dir`` resumes from the newest readable
checkpoint, naming any damaged newer one it skipped. On a log that is not a terminal, nerfstudio's step table (which
redraws itself with cursor movements, and with it the viewer's address, at every log step) prints each line once.
When training ends the process ends, unless the viewer is kept (a browser connected to it, or
``--viewer.quit-on-train-completion False``), which one line says with the way out.
"""

import dataclasses
import re
import sys
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

from nerfstudio.engine.callbacks import TrainingCallback, TrainingCallbackLocation
from nerfstudio.engine.trainer import Trainer, TrainerConfig
from nerfstudio.utils import writer
from nerfstudio.utils.decorators import check_main_thread
from nerfstudio.utils.misc import step_check
from nerfstudio.utils.rich_utils import CONSOLE

from willags_ns.engine.checkpoints import (
    RESUME_FILE,
    CheckpointError,
    SaveTimer,
    checkpoint_path,
    checkpoint_step,
    list_checkpoints,
    load_file,
    load_latest,
    resume_command,
    save_atomic,
)
from willags_ns.engine.checks import install_cli_excepthook
from willags_ns.engine.time_budget import (
    COOLDOWN_FLOOR,
    PRESET_CONFIGS,
    TimeBudget,
    apply_budget,
    attach_budget,
    attach_rates,
    device_class,
    format_choice,
    preset_defaults,
    resolution_for_images,
    validate_minutes,
    validate_rates,
)
from willags_ns.files import write_text_atomic

_SAVE_AFTER_SETUP: set[int] = set()
"""ids of configs whose ns-train start printed nothing instead of the whole configuration: config.yml is written
once the scene has been read (WillagsTrainer.setup), so a run that never starts leaves no run folder."""


def resumed_run(config: TrainerConfig) -> Path | None:
    """The run folder (config.yml beside its checkpoint directory) whose checkpoint ``config`` resumes from
    (``load_checkpoint``'s directory, or ``load_dir``), or None."""
    if config.load_checkpoint is not None:
        ckpt_dir = Path(config.load_checkpoint).parent
    elif config.load_dir is not None:
        ckpt_dir = Path(config.load_dir)
    else:
        return None
    if ckpt_dir.name != Path(config.relative_model_dir).name or not (ckpt_dir.parent / "config.yml").is_file():
        return None
    return ckpt_dir.parent


def make_run_folder(base_dir: Path) -> None:
    """The run folder, made before training on every rank. nerfstudio's Trainer.train writes
    dataparser_transforms.json there on every rank after an exists-then-mkdir check, so ranks starting together race:
    one made the folder between another's check and its mkdir, whose FileExistsError then stopped the whole run.
    Made here with exist_ok, the check finds it on every rank."""
    base_dir.mkdir(parents=True, exist_ok=True)


def mask_after_the_end(mask_step: Any, planned_end: int, budgeted: bool) -> str | None:
    """A line for a run whose mask would start after its last step, else None: the model's own MaskStep says
    whether the mask is on at all (at its warm-up's end) and whether it is on at the run's last step. A time budget
    fits the warm-up into its plan (time_budget.STEP_SCHEDULES), so a budgeted run gets no line; so does a model
    without a mask step."""
    if budgeted or mask_step is None:
        return None
    warmup = mask_step.cfg.mask.warmup_steps
    if not mask_step.active(warmup) or mask_step.active(planned_end - 1):  # no mask, or it starts within the run
        return None
    return (
        f"willags: the transient mask starts at step {warmup:,}, and this run ends at step {planned_end:,}: "
        "it trains without the mask (--pipeline.model.mask.warmup-steps N starts it earlier)"
    )


@dataclass
class WillagsTrainerConfig(TrainerConfig):
    """nerfstudio's TrainerConfig whose trainer applies `--pipeline.time-budget-minutes` (willags_ns/engine/time_budget.py).

    At ns-train's start the configuration (some 350 lines) is not printed: config.yml is written after the scene has
    been read, and one line then says where it is, so a bad --data leaves no run folder behind and nothing is said
    about a run that never starts."""

    _target: type = field(default_factory=lambda: WillagsTrainer)

    def print_to_terminal(self) -> None:
        _SAVE_AFTER_SETUP.add(id(self))

    def set_timestamp(self) -> None:
        """ns-train's run folder: a resume (--load-checkpoint or --load-dir naming a run's checkpoints, as the
        printed resume command does) goes on in the folder of the run it resumes, so that the run stays whole (its
        checkpoints, config.yml, events and resume_command.txt in one place); otherwise, or with --timestamp given,
        nerfstudio's new timestamp."""
        run = resumed_run(self)
        if self.timestamp == "{timestamp}" and run is not None and run.parent.name == str(self.method_name):
            self.output_dir = run.parent.parent.parent
            self.experiment_name = run.parent.parent.name
            self.timestamp = run.name
            return
        super().set_timestamp()

    def save_config(self) -> None:
        """config.yml, written as nerfstudio writes it but atomically (a partial file renamed over it): a process
        killed or a disk filled mid-write leaves the previous config.yml whole, which every resume, ns-eval and
        render of the run reads."""
        if id(self) in _SAVE_AFTER_SETUP:  # ns-train's save right after print_to_terminal: WillagsTrainer.setup saves
            _SAVE_AFTER_SETUP.discard(id(self))
            return
        import yaml

        base_dir = self.get_base_dir()
        base_dir.mkdir(parents=True, exist_ok=True)
        path = base_dir / "config.yml"
        CONSOLE.log(f"Saving config to: {path}")
        write_text_atomic(path, yaml.dump(self))

    save_every_minutes: float = 5.0
    """Also write a checkpoint once this many minutes of wall time have passed since the last one (0: only every
    steps_per_save steps), so a killed run loses at most this much work. Saves are atomic and, with
    save_only_latest_checkpoint, replace the previous one; a CPU step can take seconds, so steps alone can leave
    hours between saves."""
    lr_scale: float | None = None
    """Multiplies every learning rate of the run (their schedules included). None: under a time budget whose plan is
    shorter than time_budget.SHORT_RUN_STEPS, time_budget.SHORT_RUN_LR_SCALE; else 1 (the preset's rates)."""
    lr_cooldown: float | None = None
    """Share of the run's last steps over which every learning rate falls linearly to ``lr_cooldown_floor`` of its
    value (0: off; at most 1). The run's end: a time budget's latest plan, else max_num_iterations. None: under a
    time budget whose plan is shorter than time_budget.SHORT_RUN_STEPS, time_budget.SHORT_RUN_COOLDOWN; else off (the
    presets' schedules are a whole run's)."""
    lr_cooldown_floor: float = COOLDOWN_FLOOR
    """The learning rates' factor at the last step of the cooldown (0 to 1)."""


def _say(text: str) -> None:
    """One plain line on nerfstudio's console (no markup, no wrapping)."""
    CONSOLE.print(text, soft_wrap=True, markup=False, highlight=False)


def quiet_local_writer(writers: list, is_terminal: bool) -> list[str]:
    """On a log that is not a terminal, make nerfstudio's LocalWriter in ``writers`` print each step line once
    (``max_log_size`` 0, on a copy of its config) without its banner (re-printed with every redraw). Returns the
    banner lines taken off, for the caller to print once."""
    if is_terminal:
        return []
    banner: list[str] = []
    for w in writers:
        if not isinstance(w, writer.LocalWriter):
            continue
        if w.banner_len:
            banner += [m for m in w.past_mssgs[-(w.banner_len - 1) :] if m]
            w.past_mssgs = w.past_mssgs[: -w.banner_len]
            w.banner_len = 0
        w.config = dataclasses.replace(w.config, max_log_size=0)
    return banner


def drop_stale_local_writers(writers: list) -> None:
    """Keep only the newest of nerfstudio's step tables (LocalWriter) in ``writers``: nerfstudio appends one at every
    trainer set-up and never removes it, so a second training in one process (a script, a test) would print every
    row once per earlier run, with the earlier runs' numbers."""
    tables = [w for w in writers if isinstance(w, writer.LocalWriter)]
    for w in tables[:-1]:
        writers.remove(w)


RENDER_JOIN_S = 60.0
"""How long the end of a run waits for a viewer render thread to finish its frame (a CPU frame takes seconds)."""


def join_render_threads(timeout_s: float = RENDER_JOIN_S) -> None:
    """Stop nerfstudio's viewer render threads and wait for each to finish the frame it is drawing. They are daemon
    threads: one still inside torch when the interpreter exits aborts the process ("terminate called without an
    active exception", status -6) after a run that completed, as when a browser left the viewer mid-frame."""
    from nerfstudio.viewer.render_state_machine import RenderStateMachine

    for thread in threading.enumerate():
        if isinstance(thread, RenderStateMachine) and thread is not threading.current_thread():
            thread.running = False
            thread.join(timeout_s)


class WillagsTrainer(Trainer):
    """nerfstudio's Trainer; with a time budget it also chooses, measures and stops; its checkpoints are atomic, by
    steps and by time, and resumable with one printed command (see the module docstring)."""

    config: WillagsTrainerConfig
    clock: Callable[[], float] = staticmethod(time.monotonic)  # type: ignore[assignment]
    """Wall clock of the timed saves and the time budget (tests replace it)."""

    def __init__(self, config: TrainerConfig, local_rank: int = 0, world_size: int = 1) -> None:
        # nerfstudio's constructor prints "Saving checkpoints to: <run folder>" and a note on mixed precision before
        # the scene has been read: a run that will not start (a bad --data) would be announced. The folder is named
        # when training starts (train()), with the save cadence and the resume file
        quiet = CONSOLE.quiet
        CONSOLE.quiet = True
        try:
            super().__init__(config, local_rank, world_size)
        finally:
            CONSOLE.quiet = quiet

    def setup(self, test_mode: Literal["test", "val", "inference"] = "val") -> None:
        install_cli_excepthook()  # a bad budget prints one line, as bad inputs do
        validate_rates(self.config.lr_scale, self.config.lr_cooldown, self.config.lr_cooldown_floor)
        self.time_budget: TimeBudget | None = None
        self.budget_record: dict[str, Any] = {}
        """What BUDGET_FILE records of the time budget (time_budget.write_budget_record)."""
        self._keep_user_switches()
        minutes = validate_minutes(getattr(self.config.pipeline, "time_budget_minutes", None))
        choice = None
        if minutes is not None and test_mode == "val":
            choice, notes, replaced = apply_budget(self.config, minutes * 60.0)
            device = device_class(self.config.machine.device_type)
            CONSOLE.print(format_choice(choice, minutes, device, notes, num_devices=self.world_size))
            self.budget_record = {
                "budget_minutes": minutes,
                "device_class": device,
                "choice": {
                    k: (None if v != v else v) for k, v in dataclasses.asdict(choice).items()
                },  # NaN step time -> null
                "notes": notes,
            }
        # config.yml once the scene is read and the model built (a bad --data leaves no run folder), before the
        # viewer writes into the run folder: the resolved settings (the time budget's preset and steps), not the
        # invoked ones (setup_optimizers runs between the two in nerfstudio's setup)
        self._save_config_when_built = self.local_rank == 0 and test_mode == "val"
        super().setup(test_mode)
        # the step table's progress and ETA count to the run's end: a resumed run starts at its checkpoint's step
        # (nerfstudio counts to max_num_iterations, the steps left, from step 0: 116 % and a negative ETA)
        writer.GLOBAL_BUFFER["max_iter"] = self._start_step + self.config.max_num_iterations
        drop_stale_local_writers(writer.EVENT_WRITERS)
        if choice is not None and minutes is not None:
            if replaced is not None:
                resolution_for_images(self, replaced)
            attach_budget(self, self._start_step, minutes * 60.0, choice)
        attach_rates(
            self, self._start_step, choice.steps if self.time_budget is not None and choice is not None else None
        )
        for line in quiet_local_writer(writer.EVENT_WRITERS, sys.stdout.isatty()):
            CONSOLE.print(line)
        # last: after the model's own callbacks (densification) the step's state is complete; train() restarts the
        # timer, so that the first timed save comes save_every_minutes after training starts
        self._save_timer = SaveTimer(self.config.save_every_minutes * 60.0, clock=self.clock)
        self.callbacks.append(TrainingCallback([TrainingCallbackLocation.AFTER_TRAIN_ITERATION], self._save_if_due))

    def setup_optimizers(self):
        optimizers = super().setup_optimizers()
        if getattr(self, "_save_config_when_built", False):
            self._save_config_when_built = False
            self.config.save_config()
            CONSOLE.print(
                f"willags: training {self.config.method_name}; every setting is in {self.base_dir / 'config.yml'} "
                "(ns-train willags --help explains each)",
                soft_wrap=True,
                markup=False,
                highlight=False,
            )
        return optimizers

    # ---- checkpoints

    def train(self) -> None:
        make_run_folder(Path(self.base_dir))
        # the step after the last one this run plans to train (nerfstudio: max_num_iterations from the start)
        self.planned_end = self._start_step + self.config.max_num_iterations
        self._save_timer = SaveTimer(self.config.save_every_minutes * 60.0, clock=self.clock)
        if self.local_rank == 0:
            every = [f"every {self.config.steps_per_save} steps"] if self.config.steps_per_save > 0 else []
            if self.config.save_every_minutes > 0:
                every.append(f"every {self.config.save_every_minutes:g} min")
            CONSOLE.print(
                f"willags: checkpoints {' and '.join(every) or 'at the end only'} in {self.checkpoint_dir}; "
                f"if the run stops, {Path(self.base_dir) / RESUME_FILE} holds the command that resumes it",
                soft_wrap=True,
                markup=False,
                highlight=False,
            )
            mask_step = getattr(self.pipeline.model, "mask_step", None)
            note = mask_after_the_end(mask_step, self.planned_end, self.time_budget is not None)
            if note:
                CONSOLE.print(note, soft_wrap=True, markup=False, highlight=False)
        try:
            super().train()
        except CheckpointError:
            self.shutdown()  # the viewer's server threads would keep the process alive
            raise
        finally:  # training ended by an error: give Ctrl-C back (a normal end has done so already)
            interrupt = getattr(self.pipeline, "interrupt_checkpoint", None)
            if interrupt is not None:
                interrupt.uninstall()

    def _save_if_due(self, step: int) -> None:
        if self._save_timer.due() and not step_check(step, self.config.steps_per_save):
            self.save_checkpoint(step)  # nerfstudio's loop saves the steps_per_save steps itself

    def resume_command(self, saved_step: int) -> str:
        """The command that resumes this run from the checkpoint of ``saved_step`` and ends at its planned step; under
        a time budget, with what is left of the budget."""
        end = getattr(self, "planned_end", self._start_step + self.config.max_num_iterations)
        path = checkpoint_path(self.checkpoint_dir, saved_step)
        budget = getattr(self, "time_budget", None)
        left = None if budget is None else (budget.budget_s - budget.elapsed()) / 60.0
        return resume_command(sys.argv, str(self.config.method_name), path, end - saved_step - 1, left)

    @check_main_thread
    def save_checkpoint(self, step: int) -> None:
        """nerfstudio's checkpoint (same file, same contents) written atomically; the older ones removed only once it
        is complete. A failed write stops training: CheckpointError naming the last good checkpoint and the
        command that resumes from it."""
        path = checkpoint_path(self.checkpoint_dir, step)
        state = {
            "step": step,
            "pipeline": self.pipeline.module.state_dict()  # type: ignore
            if hasattr(self.pipeline, "module")
            else self.pipeline.state_dict(),
            "optimizers": {k: v.state_dict() for (k, v) in self.optimizers.optimizers.items()},
            "schedulers": {k: v.state_dict() for (k, v) in self.optimizers.schedulers.items()},
            "scalers": self.grad_scaler.state_dict(),
        }
        try:
            save_atomic(state, path)
        except CheckpointError as e:
            raise type(e)(f"{e}. {self._stopped_at(step)}") from None
        self._write_resume_file(step)  # before the older checkpoints go: the command in it always names a file
        if self.config.save_only_latest_checkpoint:
            for f in list_checkpoints(self.checkpoint_dir):
                if f != path:
                    f.unlink()
        if hasattr(self, "_save_timer"):
            self._save_timer.saved()

    def _stopped_at(self, step: int) -> str:
        """What a failed save at ``step`` leaves: the last good checkpoint and the command that resumes from it."""
        good = list_checkpoints(self.checkpoint_dir)
        if not good:
            return f"Training stopped at step {step}; no checkpoint was written yet: make room and start again"
        last = checkpoint_step(good[0])
        assert last is not None
        return (
            f"Training stopped at step {step}; the last good checkpoint is {good[0]} (step {last}). Make room, then "
            f"resume with:\n  {self.resume_command(last)}"
        )

    def _write_resume_file(self, step: int) -> None:
        path = Path(self.base_dir) / RESUME_FILE
        try:
            end = getattr(self, "planned_end", None)
            if end is not None and end - step - 1 > 0:
                write_text_atomic(path, self.resume_command(step) + "\n")
            elif path.exists():
                path.unlink()
        except OSError as e:
            CONSOLE.print(f"[bold yellow]willags warning:[/bold yellow] cannot write {path}: {e.strerror or e}")

    def _load_checkpoint(self) -> None:
        """nerfstudio's resume (--load-dir / --load-step / --load-checkpoint), reading through
        willags_ns/engine/checkpoints.py: the newest readable checkpoint of --load-dir, a damaged one named."""
        cfg = self.config
        if cfg.load_dir is not None:
            path, state = load_latest(cfg.load_dir, cfg.load_step)
        elif cfg.load_checkpoint is not None:
            path, state = Path(cfg.load_checkpoint), load_file(cfg.load_checkpoint)
        else:
            super()._load_checkpoint()
            return
        self._start_step = int(state["step"]) + 1
        self.pipeline.load_pipeline(state["pipeline"], state["step"])
        self.optimizers.load_optimizers(state["optimizers"])
        if "schedulers" in state and cfg.load_scheduler:
            self.optimizers.load_schedulers(state["schedulers"])
        self.grad_scaler.load_state_dict(state["scalers"])
        CONSOLE.print(f"Done loading Nerfstudio checkpoint from {path}")

    def _keep_user_switches(self) -> None:
        """With auto_config, name the switches the user set (a flag on the command line, or a value other than the
        invoked method's own preset) in pipeline.auto_config_keep, so the inspector leaves them (autoconfig.py).
        Before the time budget, which may swap the preset and carry these settings over."""
        model = self.config.pipeline.model
        if not getattr(model, "auto_config", False) or not hasattr(self.config.pipeline, "auto_config_keep"):
            return
        from willags_ns.tools.autoconfig import user_switches

        method = str(self.config.method_name)
        preset = preset_defaults(method)[0] if method in PRESET_CONFIGS else None
        keep = user_switches(model, preset, sys.argv[1:])
        self.config.pipeline.auto_config_keep = tuple(sorted({*self.config.pipeline.auto_config_keep, *keep}))

    def finish_run(self, step: int) -> None:
        """After the run's last step, before its last checkpoint: the model's own end of training (with held-out
        halves, the best-scoring step's model; eval/holdout.py), said in one line."""
        finish = getattr(self.pipeline.model, "finish_training", None)
        said = finish(step) if finish is not None else None
        if said and self.local_rank == 0:
            _say(said)

    def _after_train(self) -> None:
        # the loop set self.step to the step it broke before (never trained): checkpoint the last trained one
        if self.time_budget is not None and self.time_budget.stopped_after is not None:
            self.step = self.time_budget.stopped_after
        self.planned_end = self.step + 1  # finished (the budget may end it early): nothing left to resume
        self.finish_run(self.step)
        super()._after_train()  # with --viewer.quit-on-train-completion False it waits in _train_complete_viewer
        if self.config.viewer.quit_on_train_completion:
            self._viewer_after_training(asked=False)

    def _train_complete_viewer(self) -> None:
        """nerfstudio's wait after training, asked for by --viewer.quit-on-train-completion False."""
        self._viewer_after_training(asked=True)

    def shutdown(self) -> None:
        """nerfstudio's shutdown (stop training, stop the viewer's server), once: the viewer is stopped when training
        ends, and a second stop of its server fails. Then the viewer's render threads are let finish the frame they
        are drawing (join_render_threads)."""
        if getattr(self, "_shut_down", False):
            self.stop_training = True
            return
        self._shut_down = True
        super().shutdown()
        join_render_threads()

    def _viewer_clients(self) -> int:
        """How many browsers are connected to the viewer now (0 without a viewer)."""
        get = getattr(getattr(self.viewer_state, "viser_server", None), "get_clients", None)
        return len(get()) if callable(get) else 0

    def _viewer_after_training(self, asked: bool) -> None:
        """After training, ns-train ends (willags' methods set --viewer.quit-on-train-completion True): nerfstudio
        alone keeps the process alive for the viewer until Ctrl-C, which a finished run in a script or a terminal
        left alone never gets. The viewer stays open, with one line saying why and how to leave, where that is
        wanted: ``asked`` (--viewer.quit-on-train-completion False: until Ctrl-C), or while a browser is connected
        (until it closes, or Ctrl-C). Ctrl-C there is how ns-train ends, not a failure: one line, exit status 0."""
        state = self.viewer_state
        if state is None:
            return
        if not asked and not self._viewer_clients():
            self.shutdown()  # the viewer's server threads would keep the process alive
            return
        self.training_state = "completed"
        try:
            state.training_complete()
        except RuntimeError:
            pass
        found = re.search(r"https?://\S+", " ".join(getattr(state, "viewer_info", None) or []))
        where = f"the viewer at {found.group(0)}" if found else "the viewer"
        why = (
            "(--viewer.quit-on-train-completion False): Ctrl-C ends ns-train"
            if asked
            else "while a browser is connected to it: close the browser tab, or press Ctrl-C, to end ns-train"
        )
        config = Path(self.base_dir) / "config.yml"
        try:  # from the line on: a Ctrl-C may come as soon as it is read
            _say(f"willags: training is complete ({config}); {where} stays open {why}")
            while asked or self._viewer_clients():
                time.sleep(0.1)
        except KeyboardInterrupt:
            self.shutdown()
            _say(f"willags: viewer closed (Ctrl-C); the run is complete: {config}")
            return
        self.shutdown()
        _say(f"willags: the browser left, viewer closed; the run is complete: {config}")
