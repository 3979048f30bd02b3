"""Console output that survives the loss of its reader: `ns-train ... | tee train.log` (a Ctrl-C in the terminal ends
tee with ns-train), a closed terminal (SIGHUP, then every write fails) or `ns-train ... | head`.

Once the reader is gone, the write or flush of ``sys.stdout`` / ``sys.stderr`` raises BrokenPipeError (EPIPE; Python
ignores SIGPIPE) or OSError EIO (a hung-up terminal): anywhere in training (nerfstudio's step table, a log line, the
interrupt's own message), so the process would die in the middle of a step, before its checkpoint. :class:`GuardedStream`
wraps a stream: at the first such error it points the stream's file descriptor at /dev/null (Python's documented way
with SIGPIPE: every later write, and the interpreter's last flush, then succeed and go nowhere) and calls
``on_lost(name)``, once; the trainer then stops as on Ctrl-C, writing its checkpoint and resume_command.txt
(willags_ns/engine/pipeline.py, ``InterruptCheckpoint``). Any other error is raised as it was.
"""

import errno
import io
import os
import sys
from collections.abc import Callable

LOST_READER = (errno.EPIPE, errno.EIO, errno.ECONNRESET)
"""errno values of a write whose reader is gone (a closed pipe or socket, a hung-up terminal)."""


class GuardedStream:
    """A text stream (``sys.stdout``, ``sys.stderr``) whose writes survive the loss of its reader (see the module
    docstring); everything else is the wrapped stream's."""

    def __init__(self, stream, name: str, on_lost: Callable[[str], None]):
        self.stream = stream
        self.name = name
        self.on_lost = on_lost
        self.lost = False

    def write(self, text: str) -> int:
        try:
            return self.stream.write(text)
        except OSError as e:
            self._lose(e)
            return len(text)

    def flush(self) -> None:
        try:
            self.stream.flush()
        except OSError as e:
            self._lose(e)

    def _lose(self, error: OSError) -> None:
        if error.errno not in LOST_READER:
            raise error
        if self.lost:
            return
        self.lost = True
        try:
            null = os.open(os.devnull, os.O_WRONLY)
            try:
                os.dup2(null, self.stream.fileno())
            finally:
                os.close(null)
        except (OSError, ValueError, io.UnsupportedOperation):
            pass  # a stream without a file descriptor: its later writes are caught here, one by one
        self.on_lost(self.name)

    def __getattr__(self, name: str):
        return getattr(self.stream, name)


def guard_output(on_lost: Callable[[str], None]) -> Callable[[], None]:
    """Put :class:`GuardedStream` wrappers in place of ``sys.stdout`` and ``sys.stderr`` (those not wrapped already),
    calling ``on_lost("stdout")`` / ``on_lost("stderr")`` when their reader goes. Returns the function that puts the
    original streams back (those still in place)."""
    guards: dict[str, GuardedStream] = {}
    for name in ("stdout", "stderr"):
        stream = getattr(sys, name)
        if stream is not None and not isinstance(stream, GuardedStream):
            guards[name] = GuardedStream(stream, name, on_lost)
            setattr(sys, name, guards[name])

    def restore() -> None:
        for name, guard in guards.items():
            if getattr(sys, name) is guard:
                setattr(sys, name, guard.stream)

    return restore


def is_lost(name: str) -> bool:
    """Whether ``sys.<name>`` is a guarded stream whose reader has gone."""
    stream = getattr(sys, name, None)
    return isinstance(stream, GuardedStream) and stream.lost


def say_on_stderr_too() -> bool:
    """Whether a line that matters (the resume command) should also go to stderr: stdout's reader is gone, or stdout
    is not a terminal (a pipe, a file) and stderr is somewhere else (``ns-train ... | tee log``: the terminal)."""
    if is_lost("stderr"):
        return False
    if is_lost("stdout"):
        return True
    try:
        if sys.stdout.isatty():
            return False
        out, err = os.fstat(sys.stdout.fileno()), os.fstat(sys.stderr.fileno())
    except (OSError, ValueError, AttributeError, io.UnsupportedOperation):
        return False
    return (out.st_dev, out.st_ino) != (err.st_dev, err.st_ino)
