"""Where a training step's time goes, per rank (`--pipeline.data-parallel.step-profile True`).

Each step is cut at marks the pipeline sets, in this order:

    start            get_train_loss_dict called (the batch is drawn)
    forward_end      the loss is built (the forward pass queued)
    reduce_start     the trainer's backward has returned and the optimiser step is called
    collective_start the gradients are in the reduction buffer, the all-reduce is called
    collective_end   the all-reduce is queued (on a GPU the device waits there for every rank)
    reduce_end       averaged gradients and latents in place
    optimizer_end    the optimisers have stepped
    callbacks_end    every after-step callback has run (densification, the teacher's EMA, ...)

and the span between two marks is written twice: on the host clock (``h_<span>``: how long Python took to queue
it, waits for the device included) and, on a GPU, between CUDA events recorded at the marks (``d_<span>``: when the
device reached each mark, so ``d_collective`` is the time this rank's device spent in the all-reduce: the wait for
the slowest rank plus the transfer). The spans: ``forward`` (start -> forward_end), ``backward`` (forward_end ->
reduce_start), ``pack`` (reduce_start -> collective_start), ``collective``, ``unpack`` (collective_end ->
reduce_end), ``optimizer``, ``callbacks``, and ``iteration`` (start -> the next step's start: the trainer's logging,
evaluation images and checkpoints included). A step without a reduction (one device) has no collective marks; its
``reduce`` span is then empty. Across ranks of one step, ``d_collective`` minus the smallest ``d_collective`` of
that step is the rank's wait for the others.

Files, per global rank r, under ``<run>/step_profile/``: ``rank<r>.jsonl`` (one JSON object per step) and
``rank<r>.json`` (rank, world size, device, CPU count and torch's threads, and the start-up phases as Unix times:
the process started, the pipeline was entered, the data parsed, the inputs checked, the model built, the
data-parallel set-up done, the training images cached, the first step started, training ended), and at the end of
training the process's peak memory (host, and on a GPU the device's).

Cost when on: eight CUDA events and eight clock reads per step (tens of microseconds of host time); events are read
back only once the device has passed them (``Event.query``), so the profile adds no host wait. When off, nothing of
this module runs.
"""

import json
import os
import socket
import time
from collections import deque
from pathlib import Path
from typing import Any

import torch

MARKS = (
    "start",
    "forward_end",
    "reduce_start",
    "collective_start",
    "collective_end",
    "reduce_end",
    "optimizer_end",
    "callbacks_end",
)
SPANS = {
    "forward": ("start", "forward_end"),
    "backward": ("forward_end", "reduce_start"),
    "pack": ("reduce_start", "collective_start"),
    "collective": ("collective_start", "collective_end"),
    "unpack": ("collective_end", "reduce_end"),
    "reduce": ("reduce_start", "reduce_end"),
    "optimizer": ("reduce_end", "optimizer_end"),
    "callbacks": ("optimizer_end", "callbacks_end"),
}
"""Each span's (first mark, last mark); ``iteration`` (start -> next start) comes on top."""
FLUSH_EVERY = 200
"""Steps between writes of the per-step file (and at the end of training)."""


def process_start_time() -> float | None:
    """Unix time this process started (Linux /proc), or None where unknown."""
    try:
        ticks = int(Path("/proc/self/stat").read_text().rsplit(")", 1)[1].split()[19])
        boot = next(
            float(line.split()[1]) for line in Path("/proc/stat").read_text().splitlines() if line.startswith("btime")
        )
        return boot + ticks / os.sysconf("SC_CLK_TCK")
    except (OSError, ValueError, IndexError, StopIteration):
        return None


def peak_memory(cuda: bool) -> dict[str, int]:
    """This process's peak memory so far, bytes: ``peak_host_bytes`` (its resident set, Linux's ru_maxrss) and on a
    GPU ``peak_device_bytes`` (torch's largest allocation on the current device)."""
    import resource

    out = {"peak_host_bytes": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024}
    if cuda:
        out["peak_device_bytes"] = int(torch.cuda.max_memory_allocated())
    return out


def read_step_profile(run_dir: Path) -> dict[int, tuple[dict[str, Any], list[dict[str, Any]]]]:
    """{global rank: (rank<r>.json's meta, rank<r>.jsonl's per-step rows)} of the step profile a run wrote under
    ``<run_dir>/step_profile/`` (no rows for a rank whose steps file is missing); {} without a profile."""
    out = {}
    for meta_path in sorted((Path(run_dir) / "step_profile").glob("rank*.json")):
        rows_path = meta_path.with_suffix(".jsonl")
        rows = [json.loads(x) for x in rows_path.read_text().splitlines()] if rows_path.is_file() else []
        out[int(meta_path.stem[4:])] = (json.loads(meta_path.read_text()), rows)
    return out


def spans_ms(times: dict[str, float], scale: float = 1000.0) -> dict[str, float]:
    """Each span of SPANS whose two marks are in `times` (seconds), in milliseconds."""
    return {name: (times[b] - times[a]) * scale for name, (a, b) in SPANS.items() if a in times and b in times}


class StepProfile:
    """Marks of the steps of one rank, written to `directory` (see the module docstring)."""

    def __init__(
        self, directory: Path, rank: int, world_size: int, device: torch.device, meta: dict[str, Any] | None = None
    ):
        self.directory = Path(directory)
        self.rank = rank
        self.cuda = device.type == "cuda"
        cuda = self.cuda
        self.meta: dict[str, Any] = {
            "rank": rank,
            "world_size": world_size,
            "host": socket.gethostname(),
            "device": torch.cuda.get_device_name(device) if cuda else "cpu",  # not the current device: not set yet
            "cpu_count": os.cpu_count(),
            "torch_threads": torch.get_num_threads(),
            "phases": {"process_start": process_start_time()},
            **(meta or {}),
        }
        self._open: dict[str, Any] | None = None  # the step being marked
        self._pending: deque[dict[str, Any]] = deque()  # steps waiting for their events
        self._done: list[dict[str, Any]] = []
        self._written = 0
        self.steps = 0

    # ------------------------------------------------------------------ phases (start-up)
    def phase(self, name: str, when: float | None = None) -> None:
        """Record the Unix time of a start-up phase (now by default)."""
        self.meta["phases"][name] = time.time() if when is None else when

    # ------------------------------------------------------------------ steps
    def mark(self, name: str) -> None:
        """The host clock, and a CUDA event on a GPU, at mark `name` of the current step ("start" opens a step)."""
        if name == "start":
            self._start_step()
        rec = self._open
        if rec is None:  # a mark before the first step (the optimiser stepped outside the trainer's loop)
            return
        rec["host"][name] = time.perf_counter()
        if self.cuda:
            ev = torch.cuda.Event(enable_timing=True)
            ev.record()
            rec["events"][name] = ev

    def note(self, **fields: Any) -> None:
        """Values to write with the current step (image, pixels, bytes reduced, ...)."""
        if self._open is not None:
            self._open["fields"].update(fields)

    def _start_step(self) -> None:
        if self._open is not None:  # the previous step ends where this one starts
            self._close(self._open)
        self._resolve(block=False)
        self._open = {"fields": {}, "host": {}, "events": {}}
        if not self.steps:
            self.phase("first_step")
        if self.steps and self.steps % FLUSH_EVERY == 0:
            self.flush()
        self.steps += 1

    def _close(self, rec: dict[str, Any]) -> None:
        rec["host_next"] = time.perf_counter()
        if self.cuda:
            ev = torch.cuda.Event(enable_timing=True)
            ev.record()
            rec["events"]["next"] = ev
        self._pending.append(rec)

    def _resolve(self, block: bool) -> None:
        while self._pending:
            rec = self._pending[0]
            events = rec["events"]
            last = events.get("next") if self.cuda else None
            if last is not None and not block and not last.query():
                return
            if last is not None and block:
                last.synchronize()
            self._pending.popleft()
            self._done.append(self._row(rec))

    def _row(self, rec: dict[str, Any]) -> dict[str, Any]:
        host, events = rec["host"], rec["events"]
        row = dict(rec["fields"])
        row.update({f"h_{k}": round(v, 4) for k, v in spans_ms(host).items()})
        if "start" in host:
            row["h_iteration"] = round((rec["host_next"] - host["start"]) * 1000.0, 4)
        if self.cuda and "start" in events:
            t0 = events["start"]
            rel = {k: t0.elapsed_time(ev) / 1000.0 for k, ev in events.items()}  # seconds after start
            row.update({f"d_{k}": round(v, 4) for k, v in spans_ms({**rel, "start": 0.0}).items()})
            row["d_iteration"] = round(rel["next"] * 1000.0, 4)
        return row

    # ------------------------------------------------------------------ files
    def flush(self, final: bool = False) -> None:
        """Append the resolved steps to rank<r>.jsonl and rewrite rank<r>.json; `final` closes the open step and
        waits for the device to pass every event first."""
        if final:
            if self._open is not None:
                self._close(self._open)
                self._open = None
            self._resolve(block=True)
            self.phase("train_end")
            self.meta.update(peak_memory(self.cuda))
        self.directory.mkdir(parents=True, exist_ok=True)
        if self._done:
            with open(self.directory / f"rank{self.rank}.jsonl", "a") as f:
                for row in self._done:
                    f.write(json.dumps(row) + "\n")
            self._written += len(self._done)
            self._done = []
        self.meta["steps_written"] = self._written
        (self.directory / f"rank{self.rank}.json").write_text(json.dumps(self.meta, indent=1, default=str))
