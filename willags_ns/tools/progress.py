"""Progress of commands that can run for minutes (ns-eval, willags-render, willags-export, willags-process).

:class:`Progress` is rich's progress display (the same API: ``add_task``, ``advance``, ``update``, ``track``) that also
works where rich's does not: on a terminal it is rich's bar; on anything else (a log file, a pipe, a CI job), where
rich draws nothing until the end, it prints a plain line per task after its first advance, then at most every
``every_s`` seconds and once when the task completes, with the rate and the time left. So a long command never looks
hung in a log, and the first line tells how long the whole will take.
"""

import time
from collections.abc import Callable
from dataclasses import dataclass
from operator import length_hint

from rich import progress as rp
from rich.console import Console

DEFAULT_EVERY_S = 30.0
"""Seconds between two progress lines of one task in a log (the first and the last are always printed)."""


def format_duration(seconds: float) -> str:
    """``42 s``, ``3.5 min`` or ``2.1 h``: durations as a person reads them in a log."""
    s = max(0.0, float(seconds))
    if s < 90:
        return f"{s:.0f} s"
    if s < 90 * 60:
        return f"{s / 60:.1f} min"
    return f"{s / 3600:.1f} h"


def _count(x: float) -> str:
    return str(int(x)) if float(x).is_integer() else f"{x:.1f}"


def progress_line(label: str, completed: float, total: float | None, elapsed_s: float) -> str:
    """One progress line: ``label: 3/10 (30%), 12 s, ~28 s left`` (without a total: ``label: 3, 12 s``)."""
    done = _count(completed)
    if total is None or total <= 0:
        return f"{label}: {done}, {format_duration(elapsed_s)}"
    pct = 100.0 * completed / total
    text = f"{label}: {done}/{_count(total)} ({pct:.0f}%), {format_duration(elapsed_s)}"
    if 0 < completed < total and elapsed_s > 0:
        text += f", ~{format_duration(elapsed_s * (total - completed) / completed)} left"
    return text


@dataclass
class _LineState:
    start: float
    last: float
    lines: int = 0
    done: bool = False


class Progress(rp.Progress):
    """rich's Progress; without a terminal, plain progress lines instead of the bar (see the module docstring).

    ``label``: the text of tasks whose description is empty or rich's default (nerfstudio's renders use ``""``).
    ``clock``: the time source of the lines (tests inject one)."""

    def __init__(
        self,
        *columns,
        console: Console | None = None,
        label: str = "progress",
        every_s: float = DEFAULT_EVERY_S,
        clock: Callable[[], float] = time.monotonic,
        **kwargs,
    ):
        if console is None:
            from nerfstudio.utils.rich_utils import CONSOLE

            console = CONSOLE
        self.lines = not console.is_terminal
        if self.lines:
            kwargs["disable"] = True  # rich would print the bar once, at the end
        if not columns:
            columns = (
                rp.TextColumn("{task.description}"),
                rp.BarColumn(),
                rp.MofNCompleteColumn(),
                rp.TimeElapsedColumn(),
                rp.TimeRemainingColumn(),
            )
        super().__init__(*columns, console=console, **kwargs)
        self.label = label
        self.every_s = every_s
        self.clock = clock
        self._line_state: dict[rp.TaskID, _LineState] = {}

    def add_task(self, description: str, *args, **kwargs) -> rp.TaskID:
        task_id = super().add_task(description, *args, **kwargs)
        now = self.clock()
        self._line_state[task_id] = _LineState(start=now, last=now)
        return task_id

    def track(self, sequence, total=None, completed=0, task_id=None, description="Working...", update_period=0.1):
        """rich's track; in lines mode it advances after each item itself (rich's updater thread stops at once
        when the display is off, and would report nothing)."""
        if not self.lines:
            yield from super().track(sequence, total, completed, task_id, description, update_period)
            return
        if total is None:
            total = float(length_hint(sequence)) or None
        if task_id is None:
            task_id = self.add_task(description, total=total, completed=completed)
        else:
            self.update(task_id, total=total, completed=completed)
        for value in sequence:
            yield value
            self.advance(task_id, 1)

    def advance(self, task_id: rp.TaskID, advance: float = 1) -> None:
        super().advance(task_id, advance)
        self._report(task_id)

    def update(self, task_id: rp.TaskID, *args, **kwargs) -> None:
        super().update(task_id, *args, **kwargs)
        self._report(task_id)

    def _report(self, task_id: rp.TaskID) -> None:
        if not self.lines or task_id not in self._line_state:
            return
        with self._lock:
            task = self._tasks[task_id]
            completed, total, description = task.completed, task.total, task.description
        state = self._line_state[task_id]
        if state.done:
            return
        now = self.clock()
        finished = total is not None and completed >= total
        first = state.lines == 0 and completed > 0
        if not (first or finished or now - state.last >= self.every_s):
            return
        label = description if description and description != "Working..." else self.label
        self.console.print(
            progress_line(label, completed, total, now - state.start), markup=False, highlight=False, soft_wrap=True
        )
        state.last, state.lines, state.done = now, state.lines + 1, finished
