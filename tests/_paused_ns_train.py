"""`ns-train ARGS` in a process that stops at a point the test chooses and waits there for a signal.

    python -m tests._paused_ns_train MARKER WHERE STEP ARGS...

WHERE is where the process stops:
- ``step``: inside training step STEP, after its update and before its callbacks (its interrupt check and its
  periodic save), so the parameters in memory are one step ahead of the last checkpoint;
- ``save``: inside the write of step STEP's checkpoint, its partial file half written;
- ``viewer``: inside training step STEP, until a browser is connected to the viewer (a client that has sent its
  camera, as nerfstudio's viewer counts them); then training goes on, with the browser connected.

There it writes its pid to MARKER (atomically) and waits for a signal (``signal.pause``): the test reads MARKER and
sends the signal, so what the process has done when the signal arrives does not depend on the machine's speed. A
SIGINT lets the step finish (willags' interrupt checkpoint); SIGKILL ends the process where it stands; SIGUSR1 lets
it go on as if it had never stopped (the test did something meanwhile, e.g. closed the pipe of its output).

``sys.argv[0]`` is the venv's ``ns-train``, so the resume command the trainer writes is the one a user would get.
"""

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import torch


def launch_paused(args: list[str], where: str, step: int, marker: Path, **popen) -> subprocess.Popen:
    """`ns-train ARGS` stopped inside step ``step`` or inside the write of its checkpoint (``where``: "step" or
    "save"), waiting for a signal, or inside step ``step`` until a browser connects to its viewer ("viewer"); :func:`wait_until_paused` returns once it waits there.
    Its output goes to MARKER.log (a file: a pipe nobody reads could fill up and block it), unless ``popen`` names
    other ``stdout`` / ``stderr`` (subprocess.Popen's arguments)."""
    repo = Path(__file__).resolve().parents[1]
    env = {**os.environ, "PYTHONUNBUFFERED": "1", "OMP_NUM_THREADS": str(torch.get_num_threads())}
    env["PYTHONPATH"] = os.pathsep.join([str(repo), *filter(None, [env.get("PYTHONPATH")])])
    cmd = [sys.executable, "-m", "tests._paused_ns_train", str(marker), where, str(step), *args]
    with open(marker.with_suffix(".log"), "wb") as log:
        popen = {"stdout": log, "stderr": subprocess.STDOUT, **popen}
        return subprocess.Popen(cmd, env=env, cwd=repo, **popen)


def wait_until_paused(proc: subprocess.Popen, marker: Path) -> None:
    """Until the process has reached its stopping point (or ended: an error with its output). The deadline only
    guards against a hang; how long the process takes to get there does not matter."""
    deadline = time.monotonic() + 1800
    while not marker.exists():
        if proc.poll() is not None or time.monotonic() > deadline:
            proc.kill()
            proc.wait()
            log = marker.with_suffix(".log").read_text(errors="replace")
            raise AssertionError(f"the run never reached its stopping point:\n{log[-3000:]}")
        time.sleep(0.05)


def _pause(marker: Path) -> None:
    tmp = marker.with_name(marker.name + ".tmp")
    tmp.write_text(str(os.getpid()))
    os.replace(tmp, marker)
    signal.signal(signal.SIGUSR1, lambda *_: None)  # go on: pause() returns once a handler has run
    signal.pause()


def _stop_in_step(marker: Path, step: int) -> None:
    from willags_ns.engine.trainer import WillagsTrainer

    train_iteration = WillagsTrainer.train_iteration

    def paused(self, s: int):
        out = train_iteration(self, s)
        if s == step:
            _pause(marker)
        return out

    WillagsTrainer.train_iteration = paused


def _wait_for_a_browser(marker: Path, step: int) -> None:
    from willags_ns.engine.trainer import WillagsTrainer

    train_iteration = WillagsTrainer.train_iteration

    def waiting(self, s: int):
        out = train_iteration(self, s)
        if s == step:
            tmp = marker.with_name(marker.name + ".tmp")
            tmp.write_text(str(os.getpid()))
            os.replace(tmp, marker)
            while not self.viewer_state.viser_server.get_clients():
                time.sleep(0.05)
        return out

    WillagsTrainer.train_iteration = waiting


def _stop_in_save(marker: Path, step: int) -> None:
    from willags_ns.engine import checkpoints
    from willags_ns.engine.checkpoints import checkpoint_path

    opener = checkpoints._open_partial  # the module's seam for the partial file (tests replace it)

    class HalfWritten:
        def __init__(self, f):
            self.f = f

        def write(self, data) -> int:
            n = self.f.write(data)
            self.f.flush()
            _pause(marker)
            return n

        def __getattr__(self, name):
            return getattr(self.f, name)

    def paused_open(path: Path):
        f = opener(path)
        name = checkpoint_path(path.parent, step).name
        return HalfWritten(f) if path.name.startswith(f".{name}.") else f

    checkpoints._open_partial = paused_open


def main(argv: list[str]) -> None:
    marker, where, step, args = Path(argv[0]), argv[1], int(argv[2]), argv[3:]
    {"step": _stop_in_step, "save": _stop_in_save, "viewer": _wait_for_a_browser}[where](marker, step)
    sys.argv = [str(Path(sys.executable).with_name("ns-train")), *args]
    from nerfstudio.scripts.train import entrypoint

    entrypoint()


if __name__ == "__main__":
    main(sys.argv[1:])
