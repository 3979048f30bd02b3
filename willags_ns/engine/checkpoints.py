"""Checkpoint files that survive a full disk, a killed process and damage: written atomically, read with the damage
named, resumed with one exact command.

Writing (:func:`save_atomic`): the checkpoint is serialised into a hidden partial file in the checkpoint directory
(``.step-000000100.ckpt.<pid>.partial``), flushed and fsync'ed, then renamed over its final name (``os.replace``, atomic
on one filesystem) and the directory fsync'ed. So a ``step-*.ckpt`` is always complete: a process killed mid-save
leaves the previous checkpoint and at worst a stale partial file (removed by the next save, never read). A write that
fails removes its partial file and raises :class:`CheckpointSpaceError` (``no space left on DIR: the checkpoint needs
about N MB, M MB free``) or :class:`CheckpointError`, both one line from the command line.

Why a wrapper around the file: ``torch.save`` turns the ``OSError`` of a failed write into a C++ ``RuntimeError``
("enforce fail at inline_container.cc:672 unexpected pos"); writing through :class:`_RecordingWriter` keeps the
original error (its errno says whether the disk was full).

Reading (:func:`load_latest`): the newest *readable* ``step-*.ckpt`` of a directory; each newer one that cannot be read
(truncated, corrupt, not a checkpoint) is skipped with a warning naming it. A file chosen explicitly (``--load-step``,
``--load-checkpoint``) that cannot be read is a one-line error naming it and the newest readable one beside it. A
checkpoint holding pickled Python objects other than tensors is refused (``weights_only`` loading: unpickling it
could run code), never skipped silently.

:func:`install_eval_loader` puts :func:`eval_load_checkpoint` in place of nerfstudio's, so ``ns-eval``,
``ns-render``, ``ns-viewer``, ``willags-render``, ``willags-export`` and ``willags-latents`` read checkpoints this way;
the training side (``--load-dir``) is ``WillagsTrainer._load_checkpoint``.

:func:`resume_command` writes the command that continues a run from a checkpoint file and ends it at the planned step
(nerfstudio counts ``--max-num-iterations`` from the resumed step). :class:`SaveTimer` decides saves by wall time.
"""

import contextlib
import errno
import os
import pickle
import re
import shlex
import shutil
import sys
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import torch

from willags_ns.engine.checks import WillagsIOError
from willags_ns.files import PARTIAL_SUFFIX, partial_path

CKPT_RE = re.compile(r"^step-(\d+)\.ckpt$")
"""nerfstudio's checkpoint file names (``step-000000100.ckpt``)."""
RESUME_FILE = "resume_command.txt"
"""Written next to config.yml at every save of a run that has steps left: the command that resumes from that save."""
MB = 1024 * 1024


class CheckpointError(WillagsIOError):
    """A checkpoint cannot be written or read; the message names the file or directory and what to do (the command
    line prints it as one line: checks.install_cli_excepthook)."""


class CheckpointSpaceError(CheckpointError):
    """A checkpoint write ran out of disk space (ENOSPC / EDQUOT)."""


class CheckpointRefusedError(CheckpointError):
    """A checkpoint holds pickled objects other than tensors and numbers: refused, it could run code when loaded."""


# --------------------------------------------------------------------------------------------------------------------
# names


def checkpoint_path(ckpt_dir: Path, step: int) -> Path:
    """nerfstudio's file name for the checkpoint of ``step`` in ``ckpt_dir``."""
    return Path(ckpt_dir) / f"step-{int(step):09d}.ckpt"


def checkpoint_step(path: Path) -> int | None:
    """The step of a ``step-*.ckpt`` file name, None for any other name (partial files included)."""
    m = CKPT_RE.match(Path(path).name)
    return int(m.group(1)) if m else None


def list_checkpoints(ckpt_dir: Path) -> list[Path]:
    """The ``step-*.ckpt`` files of ``ckpt_dir``, newest (highest step) first; [] when it does not exist."""
    d = Path(ckpt_dir)
    if not d.is_dir():
        return []
    found = [(s, p) for p in d.iterdir() if (s := checkpoint_step(p)) is not None and p.is_file()]
    return [p for _, p in sorted(found, key=lambda sp: sp[0], reverse=True)]


def _mb(n: float) -> str:
    return f"{n / MB:.1f} MB"


# --------------------------------------------------------------------------------------------------------------------
# writing


def state_nbytes(obj: Any) -> int:
    """Bytes the tensors of a (nested dict / list / tuple) state occupy, each storage counted once: about the size
    ``torch.save`` writes (plus a small pickle), known before writing it."""
    seen: set[tuple[int, int]] = set()
    total = 0

    def walk(x: Any) -> None:
        nonlocal total
        if torch.is_tensor(x):
            st = x.untyped_storage()
            key = (st.data_ptr(), st.nbytes())
            if key not in seen:
                seen.add(key)
                total += st.nbytes()
        elif isinstance(x, dict):
            for v in x.values():
                walk(v)
        elif isinstance(x, (list, tuple)):
            for v in x:
                walk(v)

    walk(obj)
    return total


class _RecordingWriter:
    """A file for ``torch.save`` that keeps the OSError of a failed write (torch replaces it with a RuntimeError)."""

    def __init__(self, f):
        self.f = f
        self.error: OSError | None = None

    def write(self, data) -> int:
        try:
            return self.f.write(data)
        except OSError as e:
            self.error = e
            raise

    def flush(self) -> None:
        self.f.flush()


def _fsync_dir(d: Path) -> None:
    try:
        fd = os.open(d, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass  # directories cannot be fsync'ed on every platform; the rename itself is atomic
    finally:
        os.close(fd)


def remove_stale_partials(ckpt_dir: Path, keep: Path | None = None) -> list[Path]:
    """Remove the partial files of earlier, interrupted saves in ``ckpt_dir`` (a killed process leaves one); returns
    those removed. ``keep``: a partial file being written now."""
    d = Path(ckpt_dir)
    removed = []
    if not d.is_dir():
        return removed
    for p in d.iterdir():
        if p.name.startswith(".step-") and p.name.endswith(PARTIAL_SUFFIX) and p != keep:
            try:
                p.unlink()
                removed.append(p)
            except OSError:
                pass
    return removed


def _free_bytes(d: Path) -> int | None:
    try:
        return shutil.disk_usage(d).free
    except OSError:
        return None


def is_disk_full(e: BaseException) -> bool:
    """Whether an error is a full disk or an exhausted quota."""
    return isinstance(e, OSError) and e.errno in (errno.ENOSPC, errno.EDQUOT)


def no_space_message(d: Path, need_bytes: int, what: str) -> str:
    """``no space left on DIR: <what> needs about N MB, M MB free`` (free space measured now)."""
    free = _free_bytes(d)
    return f"no space left on {d}: {what} needs about {_mb(need_bytes)}" + (
        f", {_mb(free)} free" if free is not None else ""
    )


def _open_partial(path: Path):
    """Opens a partial checkpoint file for writing (a module function: tests replace it with a disk that fills)."""
    return open(path, "wb")


def save_atomic(state: dict, path: Path, opener: Callable[[Path], Any] | None = None) -> Path:
    """Write ``state`` with ``torch.save`` to ``path`` atomically (see the module docstring). ``opener(path)``
    opens the partial file for binary writing (default: :func:`_open_partial`).

    Raises CheckpointSpaceError when the disk is full, CheckpointError for any other failed write (the partial file
    removed, an existing ``path`` untouched). Returns ``path``."""
    path = Path(path)
    d = path.parent
    try:
        d.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise CheckpointError(f"cannot create the checkpoint directory {d}: {e.strerror or e}") from None
    tmp = partial_path(path)
    remove_stale_partials(d, keep=tmp)
    need = state_nbytes(state)
    writer = None
    try:
        f = (opener or _open_partial)(tmp)
        try:
            writer = _RecordingWriter(f)
            torch.save(state, writer)
            f.flush()
            os.fsync(f.fileno())
        finally:
            f.close()
        os.replace(tmp, path)
    except (OSError, RuntimeError) as e:
        try:
            tmp.unlink()
        except OSError:
            pass
        cause = writer.error if writer is not None and writer.error is not None else e
        if not isinstance(cause, OSError):
            raise  # not an I/O failure (e.g. an object torch cannot pickle): a bug, keep its traceback
        if is_disk_full(cause):
            raise CheckpointSpaceError(no_space_message(d, need, "the checkpoint")) from None
        raise CheckpointError(f"cannot write checkpoint {path}: {cause.strerror or cause}") from None
    _fsync_dir(d)
    return path


def write_file_atomic(path: Path, write: Callable[[Any], None], need_bytes: int) -> Path:
    """`write(f)` into `path`'s partial file (willags_ns/files.py), renamed over `path` when it returns: a full disk
    or a kill leaves the previous file whole and no partial one. A failed write is one WillagsIOError naming the
    file (a full disk: the `need_bytes` it needs and what is free). Returns `path`."""
    path = Path(path)
    tmp = partial_path(path)
    try:
        with open(tmp, "wb") as f:
            write(f)
        os.replace(tmp, path)
    except OSError as e:
        with contextlib.suppress(OSError):
            tmp.unlink()
        if is_disk_full(e):
            raise WillagsIOError(no_space_message(path.parent, need_bytes, path.name)) from None
        raise WillagsIOError(f"cannot write {path}: {e.strerror or e}") from None
    return path


# --------------------------------------------------------------------------------------------------------------------
# reading


def _reason(e: BaseException) -> str:
    text = " ".join(str(e).split())
    first = re.split(r"(?<=\.)\s", text, maxsplit=1)[0] if text else ""  # the first sentence, not a clause
    first = first[:120]
    return f"{type(e).__name__}: {first}" if first else type(e).__name__


def _refused(e: BaseException) -> bool:
    text = str(e)
    return isinstance(e, pickle.UnpicklingError) and ("Unsupported global" in text or "GLOBAL" in text)


def read_checkpoint(path: Path, map_location: str = "cpu") -> dict:
    """Load one checkpoint with ``torch.load`` (weights only, as nerfstudio's own calls under torch >= 2.6).

    Raises CheckpointRefusedError for pickled objects other than tensors and numbers, CheckpointError (naming the
    file and its size) when it is truncated, corrupt or not a nerfstudio checkpoint."""
    path = Path(path)
    try:
        state = torch.load(path, map_location=map_location)
    except FileNotFoundError:
        raise CheckpointError(f"checkpoint {path} does not exist") from None
    except Exception as e:  # noqa: BLE001 - torch raises RuntimeError, OSError, EOFError, KeyError ... on damage
        if _refused(e):
            raise CheckpointRefusedError(
                f"checkpoint {path} holds pickled Python objects other than tensors and numbers; refused (loading "
                "it could run code): use checkpoints written by ns-train, or re-save it from code you trust"
            ) from None
        size = path.stat().st_size if path.exists() else 0
        raise CheckpointError(f"checkpoint {path} ({_mb(size)}) is truncated or corrupt ({_reason(e)})") from None
    if not isinstance(state, dict) or "pipeline" not in state or "step" not in state:
        raise CheckpointError(f"checkpoint {path} is not a nerfstudio checkpoint (no 'pipeline' and 'step' entries)")
    return state


def _default_warn(message: str) -> None:
    from willags_ns.engine.checks import warn_all

    warn_all([message])


def load_latest(
    ckpt_dir: Path,
    step: int | None = None,
    map_location: str = "cpu",
    warn: Callable[[str], None] | None = None,
) -> tuple[Path, dict]:
    """(path, state) of the checkpoint to resume or evaluate from ``ckpt_dir``: the given ``step``'s, or the newest
    readable one (each unreadable newer one skipped with ``warn(message)`` naming it). Raises CheckpointError (one
    line naming the directory or file, and the newest readable alternative) when there is nothing to load."""
    warn = warn or _default_warn
    d = Path(ckpt_dir)
    if not d.is_dir():
        raise CheckpointError(
            f"no checkpoint directory {d}: checkpoints are written during training (nerfstudio_models/ beside "
            "config.yml); check the path, or train first"
        )
    found = list_checkpoints(d)
    if not found:
        raise CheckpointError(f"no checkpoint (step-*.ckpt) in {d}: checkpoints are written during training")
    if step is not None:
        path = checkpoint_path(d, step)
        if path not in found:
            have = ", ".join(str(checkpoint_step(p)) for p in found)
            raise CheckpointError(f"no checkpoint of step {step} in {d} (steps there: {have})")
        return path, _read_or_point_elsewhere(path, [p for p in found if p != path], map_location)
    skipped = []
    for path in found:
        try:
            state = read_checkpoint(path, map_location)
        except CheckpointRefusedError:
            raise
        except CheckpointError as e:
            skipped.append(str(e))
            continue
        for message in skipped:
            warn(f"{message}: skipped; using {path.name}, the newest readable checkpoint")
        return path, state
    raise CheckpointError(f"no readable checkpoint in {d}: " + "; ".join(skipped))


def _read_or_point_elsewhere(path: Path, others: Sequence[Path], map_location: str) -> dict:
    """read_checkpoint(path); when it is damaged, the error also names the newest readable one of ``others``."""
    try:
        return read_checkpoint(path, map_location)
    except CheckpointRefusedError:
        raise
    except CheckpointError as e:
        alt = newest_readable(others)
        hint = (
            f"; {alt} (step {checkpoint_step(alt)}) is readable: load it instead"
            if alt is not None
            else "; no other readable checkpoint beside it"
        )
        raise CheckpointError(f"{e}{hint}") from None


def newest_readable(paths: Sequence[Path]) -> Path | None:
    """The first of ``paths`` (newest first) that loads as a checkpoint, or None."""
    for p in paths:
        try:
            read_checkpoint(p)
            return p
        except CheckpointError:
            continue
    return None


def load_file(path: Path, map_location: str = "cpu") -> dict:
    """The state of one checkpoint file chosen by name (``--load-checkpoint``): a damaged one is an error naming it
    and the newest readable checkpoint beside it."""
    path = Path(path)
    if not path.is_file():
        raise CheckpointError(f"checkpoint {path} does not exist")
    others = [p for p in list_checkpoints(path.parent) if p != path]
    return _read_or_point_elsewhere(path, others, map_location)


def eval_setup_run() -> tuple[Path, Any] | None:
    """(config.yml path, its TrainerConfig) of the nerfstudio ``eval_setup`` call running on this thread's stack, or
    None outside one. ``eval_setup`` reads config.yml itself and keeps its path to itself; the run's folder is that
    path's directory."""
    frame = sys._getframe(1)
    while frame is not None:
        if frame.f_code.co_name == "eval_setup" and frame.f_globals.get("__name__") == "nerfstudio.utils.eval_utils":
            path, config = frame.f_locals.get("config_path"), frame.f_locals.get("config")
            if path is not None and config is not None:
                return Path(path), config
        frame = frame.f_back
    return None


def run_root(config, config_path: Path) -> Path | None:
    """The directory a run's relative paths (its ``output_dir``, its ``--data``) were relative to: ``config_path``'s
    directory less the stored ``output_dir/experiment/method/timestamp`` parts, when config.yml still sits under
    them (a run used in place or a copied ``outputs`` tree); None otherwise (a run folder moved on its own)."""
    stored = Path(config.get_base_dir())
    if stored.is_absolute():
        return None
    here = Path(config_path).resolve().parent
    parts = stored.parts
    if len(here.parts) <= len(parts) or here.parts[-len(parts) :] != parts:
        return None
    return here.parents[len(parts) - 1]


def resolve_run_paths(config, config_path: Path) -> None:
    """Point a loaded run's paths at the run whose config.yml is ``config_path``, whatever the working directory:

    - checkpoints: always ``nerfstudio_models/`` beside config.yml (``load_dir``). The stored path is relative to the
      directory training ran in; from elsewhere it names nothing, or another run (the original of a copied run);
    - ``output_dir``: the folder under which config.yml sits, so files nerfstudio writes into the run folder
      (the viewer's log) land there;
    - the scene (``--data``), when stored relative and not found from the working directory: relative to the
      directory training ran in (:func:`run_root`)."""
    here = Path(config_path).resolve().parent
    config.load_dir = here / config.relative_model_dir
    root = run_root(config, config_path)
    if root is not None:
        config.output_dir = root / config.output_dir
    dm = config.pipeline.datamanager
    for owner in (dm, getattr(dm, "dataparser", None)):
        data = getattr(owner, "data", None)
        if data is None or Path(data) == Path() or Path(data).is_absolute() or Path(data).exists():
            continue
        if root is not None and (root / data).exists():
            owner.data = root / data


def eval_load_checkpoint(config, pipeline) -> tuple[Path, int]:
    """nerfstudio's ``eval_utils.eval_load_checkpoint`` (ns-eval, ns-render, ns-viewer, ns-export and willags'
    commands), reading with :func:`load_latest`: the newest readable checkpoint, a damaged one named. Inside
    ``eval_setup`` the checkpoints are those beside the config.yml it was given (:func:`resolve_run_paths`), never the
    directory its stored, relative paths name from the working directory."""
    from nerfstudio.utils.rich_utils import CONSOLE

    run = eval_setup_run()
    if run is not None and run[1] is config:
        resolve_run_paths(config, run[0])
        if not Path(config.load_dir).is_dir():
            raise CheckpointError(
                f"no checkpoint directory {config.load_dir} beside {run[0]}: a run's checkpoints are loaded from "
                f"{config.relative_model_dir}/ in the folder of its config.yml; copy that folder with it"
            )
    if config.load_dir is None:
        raise CheckpointError("the run's config names no checkpoint directory (load_dir)")
    path, state = load_latest(config.load_dir, config.load_step)
    pipeline.load_pipeline(state["pipeline"], state["step"])
    CONSOLE.print(f":white_check_mark: Done loading checkpoint from {path}")
    return path, int(state["step"])


def install_eval_loader() -> None:
    """Make nerfstudio's ``eval_setup`` load through :func:`eval_load_checkpoint` (it looks the function up in its
    module at each call). Called when a willags pipeline is built, so every command that loads a willags checkpoint
    gets it; idempotent. Only where nerfstudio's eval_utils is imported already (eval_setup is running): importing
    it builds nerfstudio's method list, seconds a training process does not need."""
    eval_utils = sys.modules.get("nerfstudio.utils.eval_utils")
    if eval_utils is not None:
        eval_utils.eval_load_checkpoint = eval_load_checkpoint


# --------------------------------------------------------------------------------------------------------------------
# resuming


RESET_FLAGS = ("--load-dir", "--load-step", "--load-checkpoint", "--max-num-iterations")
"""ns-train options the resume command sets itself (both spellings, ``--a-b`` and ``--a_b``, are recognised)."""


def _flag_name(arg: str) -> str:
    return arg.split("=", 1)[0].replace("_", "-")


def is_ns_train(argv: Sequence[str]) -> bool:
    """Whether ``argv`` (sys.argv) is an ``ns-train`` command line (its console script or nerfstudio's module)."""
    if not argv:
        return False
    exe = Path(argv[0])
    return exe.name == "ns-train" or exe.as_posix().endswith("nerfstudio/scripts/train.py")


BUDGET_FLAG = "--pipeline.time-budget-minutes"
"""The time budget's option: a resumed run gets what is left of it, not the whole budget again."""


def resume_command(
    argv: Sequence[str], method: str, checkpoint: Path, remaining_steps: int, budget_minutes_left: float | None = None
) -> str:
    """The shell command that resumes a run from ``checkpoint`` (a file) and trains its ``remaining_steps``
    (nerfstudio runs ``--max-num-iterations`` steps from the resumed one, so the count left, not the original plan,
    ends the run at the planned step). A run under a time budget passes ``budget_minutes_left``: the command's
    ``--pipeline.time-budget-minutes`` is what the run had left of its budget when it stopped, so the two parts
    together train within the budget asked for.

    The file is named (``--load-checkpoint``), not the newest of its directory (``--load-dir``), so the command and
    its step count always agree: the trainer writes the command of a new checkpoint after the checkpoint and before
    it deletes the older one, so a process killed in between leaves a command whose file still exists.

    ``argv`` is the original ``ns-train`` command line: the command is that line with ``--load-checkpoint`` and
    ``--max-num-iterations`` set right after the method (before any dataparser subcommand, where tyro reads them),
    earlier values of these and of ``--load-dir`` / ``--load-step`` removed. For another command line (a script
    driving the trainer), ``ns-train METHOD`` with the two options and a note to add the run's other options."""
    own = ["--load-checkpoint", str(checkpoint), "--max-num-iterations", str(int(remaining_steps))]
    reset = RESET_FLAGS
    if budget_minutes_left is not None:
        own += [BUDGET_FLAG, f"{max(budget_minutes_left, 0.01):.2f}"]
        reset = (*RESET_FLAGS, BUDGET_FLAG)
    if not is_ns_train(argv) or method not in argv[1:] or any(_flag_name(a) == "--load-config" for a in argv):
        return shlex.join(["ns-train", method, *own]) + "  (plus this run's other ns-train options)"
    args = list(argv[1:])
    kept: list[str] = []
    i = 0
    while i < len(args):
        a = args[i]
        if _flag_name(a) in reset:
            i += 1 if "=" in a else 2
            continue
        kept.append(a)
        i += 1
    at = kept.index(method) + 1
    return shlex.join(["ns-train", *kept[:at], *own, *kept[at:]])


class SaveTimer:
    """Saves by wall time: :meth:`due` once ``every_s`` seconds passed since the last save (or the start). A pure
    clock-driven rule; ``clock`` is injectable (tests advance it without sleeping). ``every_s`` <= 0: never due."""

    def __init__(self, every_s: float, clock: Callable[[], float] = time.monotonic):
        self.every_s = float(every_s)
        self.clock = clock
        self.last = clock()

    def due(self) -> bool:
        return self.every_s > 0 and self.clock() - self.last >= self.every_s

    def saved(self) -> None:
        self.last = self.clock()
