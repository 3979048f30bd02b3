"""WillagsTrainer: nerfstudio's Trainer, plus the time budget (`--pipeline.time-budget-minutes N`) and checkpoints
that survive faults.

Why a Trainer of our own: the budget decides things only the trainer owns. Before the pipeline is built it picks the
preset (its model config) and the step cap; during training it fits the step schedules (densification, mask) into
the planned steps and stops the loop at the step the run's own clock allows (nerfstudio's loop runs a fixed ``max_num_iterations``). The decisions
themselves are pure functions in willags_ns/engine/time_budget.py.

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

import copy
import dataclasses
import json
import math
import re
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import torch
from nerfstudio.engine.callbacks import TrainingCallback, TrainingCallbackLocation
from nerfstudio.engine.trainer import Trainer, TrainerConfig
from nerfstudio.utils import writer
from nerfstudio.utils.decorators import check_main_thread
from nerfstudio.utils.misc import step_check
from nerfstudio.utils.printing import human_format
from nerfstudio.utils.rich_utils import CONSOLE

from willags_ns.engine import time_budget
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
    write_text_atomic,
)
from willags_ns.engine.checks import install_cli_excepthook
from willags_ns.engine.time_budget import (
    COOLDOWN_FLOOR,
    DEFAULT_PRESET,
    PRESETS,
    BudgetChoice,
    TimeBudget,
    choose,
    device_class,
    fixed_choice,
    format_choice,
    validate_minutes,
    validate_rates,
)

BUDGET_FILE = "time_budget.json"
"""Written next to config.yml: the choice, the table point, every plan and where training stopped."""


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
        if id(self) in _SAVE_AFTER_SETUP:  # ns-train's save right after print_to_terminal: WillagsTrainer.setup saves
            _SAVE_AFTER_SETUP.discard(id(self))
            return
        super().save_config()

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


PRESET_CONFIGS: dict[str, Any] = {}
"""method name -> factory of its TrainerConfig, registered by willags_ns/method_configs.py (which builds its methods
on this module's WillagsTrainerConfig, so the trainer must not import it back): the time budget's presets
(PRESETS) and every method's own defaults (a user's auto_config switches are those that differ)."""


def preset_defaults(preset: str) -> tuple[Any, int]:
    """(model config, default step count) of a preset, fresh from its registered factory."""
    if preset not in PRESET_CONFIGS:
        raise KeyError(f"time budget: preset {preset!r} is not registered (import willags_ns.method_configs first)")
    config = PRESET_CONFIGS[preset]()
    return config.pipeline.model, config.max_num_iterations


def carry_overrides(current: Any, base: Any, target: Any) -> list[str]:
    """Copy onto ``target`` every field where ``current`` differs from ``base`` (what the user changed in the preset
    he ran: ``--pipeline.model.backend torch`` survives a switch to the other preset), recursing into nested config
    dataclasses. Returns the dotted names copied."""
    copied = []
    for f in dataclasses.fields(current):
        if f.name == "_target" or not hasattr(target, f.name):
            continue
        a, b = getattr(current, f.name), getattr(base, f.name, None)
        if a == b:
            continue
        sub = getattr(target, f.name)
        if dataclasses.is_dataclass(a) and type(a) is type(b) and type(sub) is type(a):
            copied += [f"{f.name}.{n}" for n in carry_overrides(a, b, sub)]
        else:
            setattr(target, f.name, copy.deepcopy(a))
            copied.append(f.name)
    return copied


def apply_budget(config: TrainerConfig, budget_s: float) -> tuple[BudgetChoice, list[str], int | None]:
    """Choose the preset and the steps for ``budget_s`` and write them into ``config`` (model, max_num_iterations,
    resolution schedule; the learning-rate schedules stay the preset's). Returns the choice, notes for the
    printed block, and the preset's num_downscales when this set full resolution from the first step in its place
    (None otherwise: kept schedule, or the user's own num_downscales), which the trainer restores for large images."""
    device = device_class(config.machine.device_type)
    method = str(config.method_name)
    notes: list[str] = []
    replaced: int | None = None
    if method != DEFAULT_PRESET:  # a method named explicitly (willags-lite too) keeps its model
        choice = fixed_choice(method, config.max_num_iterations)
    else:
        defaults = {p: preset_defaults(p) for p in PRESETS}
        caps = {p: min(steps, config.max_num_iterations) for p, (_, steps) in defaults.items()}
        choice = choose(budget_s, device, caps)
        base_model = defaults[method][0]
        model: Any = config.pipeline.model  # a WillagsModelConfig (both presets' model)
        if choice.preset != method:
            target = copy.deepcopy(defaults[choice.preset][0])
            kept = carry_overrides(model, base_model, target)
            config.pipeline.model = model = target
            base_model = defaults[choice.preset][0]
            notes.append(
                f"model switched from {method} to {choice.preset}"
                + (f"; your settings kept: {', '.join(kept)}" if kept else "")
            )
        if not choice.keep_resolution_schedule:
            if model.num_downscales == base_model.num_downscales:
                replaced, model.num_downscales = model.num_downscales, 0
            else:
                notes.append(f"your --pipeline.model.num-downscales {model.num_downscales} kept")
    config.max_num_iterations = choice.max_steps
    return choice, notes, replaced


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


def table_time(seconds: float) -> str:
    """A duration as nerfstudio's step table writes it: ``350.123 ms``, ``2 s, 149.675 ms``, ``7 m, 58 s``,
    ``1 h, 2 m, 3 s``."""
    seconds = max(0.0, float(seconds))
    whole = int(seconds)
    ms = (seconds - whole) * 1e3
    hours, rest = divmod(whole, 3600)
    minutes, secs = divmod(rest, 60)
    if hours:
        return f"{hours} h, {minutes} m, {secs} s"
    if minutes:
        return f"{minutes} m, {secs} s"
    if secs:
        return f"{secs} s, {ms:0.3f} ms"
    return f"{ms:0.3f} ms"


class BudgetStepTable(writer.LocalWriter):
    """nerfstudio's step table (its LocalWriter, whose class this becomes: :meth:`attach`) for a run under a time
    budget. nerfstudio counts the step against the planned end and the ETA as the steps left times the step time;
    the budget re-plans the end as the run measures itself, so its percentage went backwards when a plan grew
    (88 % then 87 %), and its first ETA multiplied the table's step count by this machine's slower steps (31 minutes
    for an 8-minute budget). Here every row says, from the first one: the step, the planned end (a range while the
    run has not measured its own step time: the plans at the table's step time and at the run's own so far), the
    share of the run's time done (which only grows), and in the ETA column the time left of the budget
    (time_budget.budget_progress). The other columns are nerfstudio's."""

    budget: TimeBudget
    table_step_s: float
    shown_share: float
    HEADER = "Step of plan (% time)"
    WIDTH = 30

    @classmethod
    def attach(cls, writers: list, budget: TimeBudget, table_step_s: float) -> None:
        """Make nerfstudio's LocalWriter in ``writers`` this table for ``budget`` (the table's step time:
        ``table_step_s``)."""
        for w in writers:
            if type(w) is writer.LocalWriter:
                w.__class__ = cls
                w.budget, w.table_step_s, w.shown_share = budget, table_step_s, 0.0

    def row(self, step: int, latest_map: dict) -> str:
        """The table's row after ``step`` (see the class docstring)."""
        b = self.budget
        elapsed = b.elapsed()
        done = step - b.start_step + 1
        own = elapsed / done if done > 0 and elapsed > 0 else math.nan
        progress = time_budget.budget_progress(
            b.budget_s, elapsed, step, b.start_step, b.end_step, b.max_steps, (self.table_step_s, own)
        )
        self.shown_share = max(self.shown_share, progress.share)
        low, high = progress.end_low, progress.end_high
        plan = f"{low}" if low == high else f"{low}-{high}"
        first = f"{step} of {plan} ({100 * self.shown_share:.2f}%)"
        cells = [f"{first:<{self.WIDTH}}"]
        for name, v in latest_map.items():
            if name not in self.stats_to_track:
                continue
            if name == writer.EventName.ETA.value:
                v = table_time(progress.time_left_s)
            elif "(time)" in name:
                v = table_time(v)
            elif "Rays" in name:
                v = human_format(v)
            else:
                v = f"{v:0.4f}"
            cells.append(f"{v:<20} ")
        return "".join(cells)

    def _update_header(self, latest_map, new_key):
        names = "".join(f"{name:<20} " for name in latest_map if name in self.stats_to_track)
        header = f"{self.HEADER:<{self.WIDTH}}{names}"
        if not self.config.max_log_size:  # a log: the header once, before the first row (a resumed run's too)
            if not getattr(self, "said_header", False):
                self.said_header = True
                print(header)
                print("-" * len(header))
            return
        if len(self.past_mssgs) - self.banner_len <= 2 or new_key:
            self.past_mssgs[0], self.past_mssgs[1] = header, "-" * len(header)
            if not self.has_printed:
                print(header)
                print("-" * len(header))

    def _print_stats(self, latest_map, padding=" "):
        curr = self.row(writer.GLOBAL_BUFFER["step"], latest_map)
        if not self.config.max_log_size:
            print(curr)
            return
        # nerfstudio's redrawn table: the last max_log_size rows above the banner
        if not self.has_printed:
            cursor_idx = len(self.past_mssgs) - self.banner_len
            self.has_printed = True
        else:
            cursor_idx = len(self.past_mssgs)
        if len(self.past_mssgs[2:]) - self.banner_len >= self.config.max_log_size:
            self.past_mssgs.pop(2)
        self.past_mssgs.insert(len(self.past_mssgs) - self.banner_len, curr)
        print(f"\r\033[{cursor_idx}A", end="\x1b[1K\r")
        pad_len = len(max(self.past_mssgs, key=len))
        for i, mssg in enumerate(self.past_mssgs):
            style = "\x1b[30;42m" if self.banner_len and i >= len(self.past_mssgs) - self.banner_len + 1 else ""
            print(f"{style}{mssg:{padding}<{pad_len}} \x1b[0m")


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
        self._budget_record: dict[str, Any] = {}
        self._keep_user_switches()
        minutes = validate_minutes(getattr(self.config.pipeline, "time_budget_minutes", None))
        choice = None
        if minutes is not None and test_mode == "val":
            choice, notes, replaced = apply_budget(self.config, minutes * 60.0)
            device = device_class(self.config.machine.device_type)
            CONSOLE.print(format_choice(choice, minutes, device, notes, num_devices=self.world_size))
            self._budget_record = {
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
                self._resolution_for_images(replaced)
            self._attach_budget(minutes * 60.0, choice)
        self._attach_rates(choice.steps if self.time_budget is not None and choice is not None else None)
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
        """The command that resumes this run from the checkpoint of ``saved_step`` and ends at its planned step."""
        end = getattr(self, "planned_end", self._start_step + self.config.max_num_iterations)
        path = checkpoint_path(self.checkpoint_dir, saved_step)
        return resume_command(sys.argv, str(self.config.method_name), path, end - saved_step - 1)

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

    def _resolution_for_images(self, downscales: int) -> None:
        """The budget set full resolution from the first step in place of the preset's ``downscales`` (the CPU points
        were measured so, on 128 px images); with larger training images (known only now, the data loaded) put the
        preset's resolution schedule back (time_budget.full_resolution_suits): a full-resolution step costs too much.
        The model reads num_downscales at every step, so the change counts from the first one."""
        cams = getattr(getattr(self.pipeline.datamanager, "train_dataset", None), "cameras", None)
        if cams is None:
            return
        side = int(max(cams.width.max().item(), cams.height.max().item()))
        if time_budget.full_resolution_suits(side):
            return
        self.pipeline.model.config.num_downscales = downscales  # what the model reads
        self.config.pipeline.model.num_downscales = downscales  # what config.yml says (the same object in nerfstudio)
        note = (
            f"training images up to {side} px (the {device_class(self.config.machine.device_type)} points: "
            f"{time_budget.CPU_SCENE_SIDE} px): splatfacto's resolution schedule kept (num_downscales {downscales}) instead of "
            "full resolution from the first step"
        )
        CONSOLE.print(f"  note:     {note}")
        self._budget_record["notes"].append(note)
        if self.local_rank == 0:
            self.config.save_config()

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

    def _attach_budget(self, budget_s: float, choice: BudgetChoice) -> None:
        start = self._start_step  # > 0 when resumed with --load-dir: the budget is this run's

        # the step schedules are the preset's, for its own run: their shares are of that run, not of a lower cap
        # (--max-num-iterations 5000 would keep a 30000-step run's last split at 3 times the planned run)
        own_steps = preset_defaults(choice.preset)[1] if choice.preset in PRESET_CONFIGS else choice.max_steps
        fit = self._schedule_fitter(own_steps)

        def on_plan(end_step: int) -> None:
            fit(end_step - start)
            # progress and ETA count against the planned end, not the cap (nerfstudio's step table reads max_iter)
            writer.GLOBAL_BUFFER["max_iter"] = end_step

        on_plan(start + choice.steps)
        cuda = str(self.device).startswith("cuda") and torch.cuda.is_available()
        budget = TimeBudget(
            budget_s,
            max_steps=choice.max_steps,
            start_step=start,
            on_plan=on_plan,
            log=CONSOLE.print,
            sync=torch.cuda.synchronize if cuda else None,
            clock=self.clock,
            warmup_steps=time_budget.WARMUP_STEPS,  # read now, so a test can shorten them
            window_steps=time_budget.WINDOW_STEPS,
            replan_every=time_budget.REPLAN_EVERY,
        )

        def after_step(step: int) -> None:
            if budget.after_step(step):
                self.stop_training = True  # nerfstudio's loop breaks before the next step

        # first, so that the interrupt checkpoint (the pipeline's last AFTER_TRAIN_ITERATION callback) stays last
        self.callbacks[:0] = [
            TrainingCallback([TrainingCallbackLocation.BEFORE_TRAIN_ITERATION], budget.before_step),
            TrainingCallback([TrainingCallbackLocation.AFTER_TRAIN_ITERATION], after_step),
            TrainingCallback([TrainingCallbackLocation.AFTER_TRAIN], self._budget_done),
        ]
        self.time_budget = budget
        BudgetStepTable.attach(writer.EVENT_WRITERS, budget, choice.step_s)
        self._budget_record["gaussians_at_start"] = self._num_gaussians()
        self._write_budget_record()

    def _attach_rates(self, budget_steps: int | None) -> None:
        """Before every step, each learning rate = its scheduled value x ``lr_scale`` x time_budget.cooldown_factor
        (``lr_cooldown``). The run's end: the budget's latest plan (``budget_steps`` from the first step until the run
        has measured its own), else max_num_iterations from the first step; under a budget, unset switches follow
        time_budget.short_run_rates of that plan. The schedulers set their groups' rates from their own base every
        step; a group without one is at its configured rate (not the rate a resumed checkpoint saved: that one was
        already scaled). Nothing is attached when neither a budget nor a switch asks for it."""
        cfg = self.config
        budget = self.time_budget
        if budget is None and cfg.lr_scale in (None, 1) and not cfg.lr_cooldown:
            return
        optimizers = self.optimizers
        start = self._start_step
        fixed_end = start + (cfg.max_num_iterations if budget_steps is None else budget_steps)
        used: dict[str, float] = {}

        def before_step(step: int) -> None:
            end = budget.end_step if budget is not None and budget.end_step is not None else fixed_end
            scale, share = time_budget.short_run_rates(end - start) if budget is not None else (1.0, 0.0)
            scale = scale if cfg.lr_scale is None else cfg.lr_scale
            share = share if cfg.lr_cooldown is None else cfg.lr_cooldown
            factor = scale * time_budget.cooldown_factor(step, start, end, share, cfg.lr_cooldown_floor)
            for name, opt in optimizers.optimizers.items():
                scheduler = optimizers.schedulers.get(name)
                own = optimizers.config[name]["optimizer"].lr
                rates = scheduler.get_last_lr() if scheduler is not None else [own] * len(opt.param_groups)
                for group, lr in zip(opt.param_groups, rates, strict=True):
                    group["lr"] = lr * factor
            if used.get("scale") != scale or used.get("cooldown") != share:
                used.update(scale=scale, cooldown=share, floor=cfg.lr_cooldown_floor)
                if budget is not None:
                    self._budget_record["learning_rates"] = dict(used)

        self.callbacks.append(TrainingCallback([TrainingCallbackLocation.BEFORE_TRAIN_ITERATION], before_step))

    def _num_gaussians(self) -> int | None:
        """The model's Gaussian count (None for a model without Gaussians)."""
        means = getattr(self.pipeline.model, "means", None)
        return None if means is None else int(means.shape[0])

    def _densification_window(self) -> dict[str, int] | None:
        """The densification steps as the strategy runs them now (after the budget fitted them): refinements every
        ``refine_every`` steps after ``refine_start_iter`` until ``refine_stop_iter``."""
        strategy = getattr(self.pipeline.model, "strategy", None)
        if strategy is None or not hasattr(strategy, "refine_start_iter"):
            return None
        keys = ("refine_start_iter", "refine_every", "refine_stop_iter", "reset_every")
        return {k: int(getattr(strategy, k)) for k in keys if isinstance(getattr(strategy, k, None), int)}

    def _schedule_fitter(self, preset_steps: int) -> Callable[[int], None]:
        """A function of the run's planned steps that fits the model's step schedules into them
        (time_budget.fit_schedules, from the values the run started with): the config (what config.yml says and
        what the model reads at each step) and the densification strategy, which copied them when it was built.
        Both strategies have the refinement window and period; splatfacto's (gsplat's DefaultStrategy) also stops
        its screen-size splits and resets opacities (its period and the pause after each reset), which MCMC's never
        does (its reset_every stays 0)."""
        model = self.pipeline.model
        cfg = model.config

        def get(name: str) -> Any:
            target = cfg
            for part in name.split("."):
                target = getattr(target, part, None)
            return target

        own = {
            k: int(v) for k in time_budget.STEP_SCHEDULES if isinstance(v := get(k), int) and not isinstance(v, bool)
        }
        strategy = getattr(model, "strategy", None)
        base_pause = getattr(strategy, "pause_refine_after_reset", None)

        def fit(run_steps: int) -> None:
            values = time_budget.fit_schedules(own, run_steps, preset_steps)
            for name, value in values.items():
                *parents, last = name.split(".")
                target = cfg
                for part in parents:
                    target = getattr(target, part)
                setattr(target, last, value)
            if strategy is None or not hasattr(strategy, "refine_start_iter"):
                return
            strategy.refine_start_iter = values.get("warmup_length", strategy.refine_start_iter)
            strategy.refine_stop_iter = values.get("stop_split_at", strategy.refine_stop_iter)
            if "refine_every" in values:
                strategy.refine_every = values["refine_every"]
            if base_pause is None:  # MCMC's densification: no screen-size splits, no opacity resets
                return
            strategy.refine_scale2d_stop_iter = values.get("stop_screen_size_at", strategy.refine_scale2d_stop_iter)
            if "refine_every" in values:
                strategy.reset_every = values.get("reset_alpha_every", 0) * values["refine_every"]
                # an epoch after each reset; in a shorter run, one refinement
                pause = base_pause - own["refine_every"] + values["refine_every"]
                if values != own:
                    pause = min(pause, values["refine_every"])
                strategy.pause_refine_after_reset = pause

        return fit

    def _after_train(self) -> None:
        # the loop set self.step to the step it broke before (never trained): checkpoint the last trained one
        if self.time_budget is not None and self.time_budget.stopped_after is not None:
            self.step = self.time_budget.stopped_after
        self.planned_end = self.step + 1  # finished (the budget may end it early): nothing left to resume
        super()._after_train()  # with --viewer.quit-on-train-completion False it waits in _train_complete_viewer
        if self.config.viewer.quit_on_train_completion:
            self._viewer_after_training(asked=False)

    def _train_complete_viewer(self) -> None:
        """nerfstudio's wait after training, asked for by --viewer.quit-on-train-completion False."""
        self._viewer_after_training(asked=True)

    def shutdown(self) -> None:
        """nerfstudio's shutdown (stop training, stop the viewer's server), once: the viewer is stopped when training
        ends, and a second stop of its server fails."""
        if getattr(self, "_shut_down", False):
            self.stop_training = True
            return
        self._shut_down = True
        super().shutdown()

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

    def _budget_done(self, step: int) -> None:
        budget = self.time_budget
        assert budget is not None
        trained = step - budget.start_step + 1
        how = budget.stop_reason or "trained every step allowed"
        CONSOLE.print(
            f"willags time budget: stopped after step {step} ({trained} steps; {how}) at {budget.elapsed():.0f} s of "
            f"{budget.budget_s:.0f} s"
        )
        if self.local_rank == 0:
            self.config.max_num_iterations = trained
            self.config.save_config()  # config.yml says what was trained
        # whether the run densified: Gaussians at the end against those it started from (the SfM points)
        self._budget_record["gaussians_at_end"] = self._num_gaussians()
        self._budget_record["densification"] = self._densification_window()
        self._write_budget_record()

    def _write_budget_record(self) -> None:
        if self.local_rank != 0:
            return
        record = {**self._budget_record}
        if self.time_budget is not None:
            record["run"] = self.time_budget.summary()
        path = Path(self.base_dir) / BUDGET_FILE
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(json.dumps(record, indent=1, default=str))
