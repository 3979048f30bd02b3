"""Where a training step's time goes: one method on one scene, a window of steps under torch.profiler.

    python -m benchmarks profile --method willags --data .gpu-r/reichstag --warmup 3000 --steps 50 --out $OUT/p.json

Trains ``--warmup`` steps with splatfacto's stock schedule (as `ns-train <method>`; 3000 puts the window past the
resolution schedule's first switch), times the next ``--steps`` without the profiler (``wall_ms``) and profiles the
``--steps`` after them, in a scratch directory that is not kept. Per step: ``device_ms`` (kernel time; wall minus it is
time the GPU waited on the host), ``launches`` (kernel launches on CUDA, aten operators on the CPU), ``syncs`` and
``sync_sites`` (host-device synchronisations and the willags_ns / nerfstudio / gsplat line that forced each, CUDA
only), ``top_host`` / ``top_device`` (the operators with the most self time) and ``components``: host ms, device ms,
launches and calls of the parts of a step (the model's get_outputs, colours, rasterisation, background, metrics and
loss; the densification strategy; the optimisers; the next photo), each under a ``record_function`` label, inclusive
and nested (the colours are inside get_outputs; the backward pass is what the labels leave out), with ``ops``: the
operators each part's own code calls, nested labels apart.

The warm-up itself is clocked too, so a run's whole-length rate and the window's can be told apart: ``laps`` (every
``--lap-every`` steps, a row each: ``steps`` done, ``gaussians``, ``step_ms`` the lap's mean step, ``event_ms`` the
time of the lap's first step alone, synchronised on both sides (the densification strategy refines on these steps, so
a lap is one such step and ``lap_every - 1`` ordinary ones), ``ordinary_ms`` the mean of the others).
"""

import argparse
import collections
import json
import tempfile
import time
import traceback
import warnings
from collections import Counter, defaultdict
from collections.abc import Iterator
from pathlib import Path
from typing import Any

SITE_PARTS = ("/willags_ns/", "/nerfstudio/", "/gsplat/", "/benchmarks/")
"""Frames a synchronisation is attributed to: the innermost one from these packages."""


def sync_site(stack: list[traceback.FrameSummary]) -> str:
    """``file:line`` of the innermost frame of ``stack`` inside willags_ns, nerfstudio, gsplat or benchmarks (the line
    that asked torch for a host value), or "?" when none is."""
    for frame in reversed(stack):
        path = frame.filename.replace("\\", "/")
        if any(p in path for p in SITE_PARTS) and not path.endswith("profile_step.py"):
            return f"{'/'.join(path.split('/')[-2:])}:{frame.lineno}"
    return "?"


COMPONENTS: dict[str, tuple[str, ...]] = {
    "model": ("get_outputs", "appearance_colors", "_rasterize", "_background", "get_metrics_dict", "get_loss_dict"),
    "strategy": ("step_pre_backward", "step_post_backward"),
    "optimizers": ("zero_grad_some", "optimizer_scaler_step_some", "scheduler_step_all"),  # what the trainer calls
    "datamanager": ("next_train",),
}
"""The methods labelled in a step, by owner (the pipeline's model, its densification strategy, the trainer's
optimisers, the data manager that hands out the step's photo); a method an owner lacks (splatfacto has no appearance_colors) is skipped."""
LABEL = "step/"
LAUNCH_KEYS = ("cudaLaunchKernel", "cuLaunchKernel", "cudaLaunchKernelExC")
"""The runtime calls that launch a kernel: a step's and a component's launches are counted by these."""


def label_components(trainer: Any) -> list[str]:
    """Wrap the COMPONENTS' methods of this trainer's objects in ``record_function("step/<owner>.<method>")`` (on
    the instances, so every call through them is labelled) and return the labels."""
    import torch

    model = trainer.pipeline.model
    owners = {
        "model": model,
        "strategy": getattr(model, "strategy", None),
        "optimizers": trainer.optimizers,
        "datamanager": trainer.pipeline.datamanager,
    }
    labels = []
    for owner, names in COMPONENTS.items():
        obj = owners[owner]
        for name in names:
            fn = getattr(obj, name, None) if obj is not None else None
            if not callable(fn):
                continue
            label = f"{LABEL}{owner}.{name}"

            def labelled(*args, _fn=fn, _label=label, **kwargs):
                with torch.profiler.record_function(_label):
                    return _fn(*args, **kwargs)

            setattr(obj, name, labelled)
            labels.append(label)
    return labels


def own_ops(e: Any) -> Iterator[str]:
    """The names of the outermost operators run inside the labelled event `e` and outside any label nested in it: the
    calls its code makes (``aten::linear``, not the ``aten::addmm`` inside it), what a fused kernel would replace."""
    for c in e.cpu_children:
        if c.name.startswith(LABEL):
            continue
        if c.name.startswith("aten::"):
            yield c.name
        else:
            yield from own_ops(c)


def component_summary(events: Any, steps: int, on_cuda: bool, top: int = 12) -> dict[str, dict[str, Any]]:
    """Per labelled component (``step/...`` events of a profiler's ``events()``): host ms, device ms, launches (CUDA;
    aten operators on the CPU) and calls, per step, each inclusive of what ran inside it; and ``ops``, the ``top``
    operators its own code calls (:func:`own_ops`: nested labels apart) with their calls per step."""

    def descendants(e):
        for c in e.cpu_children:
            yield c
            yield from descendants(c)

    out: dict[str, dict[str, Any]] = {}
    ops: dict[str, Counter] = defaultdict(Counter)
    for e in events:
        if not e.name.startswith(LABEL):
            continue
        row = out.setdefault(e.name[len(LABEL) :], {"host_ms": 0.0, "device_ms": 0.0, "launches": 0.0, "calls": 0.0})
        ops[e.name[len(LABEL) :]].update(own_ops(e))
        inner = list(descendants(e))
        row["host_ms"] += e.cpu_time_total / 1000.0 / steps
        row["calls"] += 1.0 / steps
        if on_cuda:
            row["launches"] += sum(c.name in LAUNCH_KEYS for c in inner) / steps
            # the kernels of the operators inside it (FunctionEvent.device_time_total sums them recursively)
            row["device_ms"] += float(getattr(e, "device_time_total", getattr(e, "cuda_time_total", 0.0)) or 0.0)
        else:
            row["launches"] += sum(c.name.startswith("aten::") for c in inner) / steps
    for name, row in out.items():
        row["device_ms"] = row["device_ms"] / 1000.0 / steps
        row["ops"] = {op: n / steps for op, n in ops[name].most_common(top)}
    return out


BACKWARD_PREFIX = "autograd::engine::evaluate_function: "
"""How the profiler names a node of the backward pass it runs (the node's class follows)."""


def summarize(events: Any, steps: int, on_cuda: bool, top: int = 15) -> dict[str, Any]:
    """Per-step numbers from a profiler's ``key_averages()``: kernel time, launches (CUDA) or aten operators (CPU),
    the ``top`` operators by self host time and by self device time, and the backward pass's nodes (how many a step,
    and the ``top`` node classes by count: the graph the forward built, which the labels of ``components`` leave
    out)."""
    rows = list(events)
    launches = sum(r.count for r in rows if r.key in LAUNCH_KEYS)
    aten = sum(r.count for r in rows if r.key.startswith("aten::"))

    def device_us(r) -> float:
        return float(getattr(r, "self_device_time_total", getattr(r, "self_cuda_time_total", 0.0)) or 0.0)

    device_total = sum(device_us(r) for r in rows) if on_cuda else 0.0

    def top_by(us) -> list[dict[str, Any]]:
        best = sorted(rows, key=us, reverse=True)[:top]
        return [{"op": r.key, "calls": r.count / steps, "self_ms": us(r) / 1000.0 / steps} for r in best]

    nodes = sorted(
        ((r.key[len(BACKWARD_PREFIX) :], r.count) for r in rows if r.key.startswith(BACKWARD_PREFIX)),
        key=lambda kv: -kv[1],
    )
    return {
        "device_ms": device_total / 1000.0 / steps,
        "launches": (launches if on_cuda else aten) / steps,
        "aten_ops": aten / steps,
        "top_host": top_by(lambda r: r.self_cpu_time_total),
        "top_device": top_by(device_us) if on_cuda else [],
        "backward_nodes": sum(n for _, n in nodes) / steps,
        "top_backward_nodes": [{"node": k, "calls": n / steps} for k, n in nodes[:top]],
    }


def lap_rows(laps: list[list[float]], events: dict[int, float]) -> list[dict[str, Any]]:
    """One row a lap (``laps``: [steps done, seconds since the first step, Gaussians]; ``events``: step -> ms of that
    one step): the lap's mean step, the event step inside it and the mean of the lap's other steps."""
    rows, prev_steps, prev_s = [], 0, 0.0
    for done, secs, gaussians in laps:
        n = int(done) - prev_steps
        lap_ms = 1000.0 * (secs - prev_s)
        event = next((events[s] for s in range(prev_steps, int(done)) if s in events), None)
        row = {"steps": int(done), "gaussians": int(gaussians), "step_ms": lap_ms / n, "event_ms": event}
        row["ordinary_ms"] = (lap_ms - event) / (n - 1) if event is not None and n > 1 else None
        rows.append(row)
        prev_steps, prev_s = int(done), secs
    return rows


def profile(
    method: str, data: Path, warmup: int, steps: int, seed: int, run_dir: Path, lap_every: int = 100
) -> dict[str, Any]:
    """Train ``method`` on ``data`` for ``warmup`` steps, time the next ``steps`` and profile the ``steps`` after them
    (see the module docstring); the warm-up is clocked in laps of ``lap_every`` steps (0: not at all)."""
    import torch
    from nerfstudio.engine.callbacks import TrainingCallback, TrainingCallbackLocation
    from torch.profiler import ProfilerActivity
    from torch.profiler import profile as torch_profile

    from benchmarks import long_run
    from benchmarks.child import sync

    on_cuda = torch.cuda.is_available()
    trainer = long_run._setup(method, data, run_dir, warmup + 2 * steps + 1, seed, None, "val")
    _ = trainer.pipeline.datamanager.cached_train
    label_components(trainer)
    activities = [ProfilerActivity.CPU] + ([ProfilerActivity.CUDA] if on_cuda else [])
    prof = torch_profile(activities=activities)
    sites: collections.Counter[str] = collections.Counter()
    clock = {}
    original_showwarning, original_filters = warnings.showwarning, list(warnings.filters)

    def on_warning(message, category, filename, lineno, file=None, line=None):  # a sync: where the host asked
        if "synchroniz" in str(message).lower():
            sites[sync_site(traceback.extract_stack()[:-1])] += 1
            return
        original_showwarning(message, category, filename, lineno, file, line)

    laps: list[list[float]] = []
    events: dict[int, float] = {}
    device = trainer.pipeline.model.device

    def before_step(step: int) -> None:  # registered only with lap_every > 0
        if step < warmup and step % lap_every == 0:
            sync(device)  # the step that refines starts on an idle GPU: its own time, not the queue's
            clock["event"] = time.perf_counter()
            clock.setdefault("start", clock["event"])

    def after_step(step: int) -> None:
        if lap_every > 0 and step < warmup:
            if step % lap_every == 0 and step > 0:
                sync(device)
                events[step] = (time.perf_counter() - clock["event"]) * 1000.0
            if (step + 1) % lap_every == 0:
                sync(device)
                laps.append([step + 1, time.perf_counter() - clock["start"], int(trainer.pipeline.model.num_points)])
        if step == warmup - 1:  # the timed window (no profiler: it adds host time to every operator)
            sync(device)
            clock["t0"] = time.perf_counter()
        elif step == warmup + steps - 1:  # the timed window ends, the profiled one starts with the next step
            sync(device)
            clock["t1"] = time.perf_counter()
            warnings.showwarning = on_warning
            warnings.simplefilter("always")
            if on_cuda:
                torch.cuda.set_sync_debug_mode("warn")
            prof.__enter__()
        elif step == warmup + 2 * steps - 1:
            sync(device)
            prof.__exit__(None, None, None)
            clock["t2"] = time.perf_counter()
            raise long_run.Stop  # the sync mode and the warning hooks are put back below

    if lap_every > 0:
        before = TrainingCallback(
            [TrainingCallbackLocation.BEFORE_TRAIN_ITERATION], before_step, update_every_num_iters=1
        )
        trainer.callbacks.insert(0, before)
    trainer.callbacks.append(
        TrainingCallback([TrainingCallbackLocation.AFTER_TRAIN_ITERATION], after_step, update_every_num_iters=1)
    )
    try:
        trainer.train()
    except long_run.Stop:
        pass
    finally:
        if on_cuda:
            torch.cuda.set_sync_debug_mode("default")
        warnings.showwarning, warnings.filters[:] = original_showwarning, original_filters
    if "t2" not in clock:
        raise RuntimeError(f"profile_step: the windows (steps {warmup}..{warmup + 2 * steps - 1}) were not reached")
    out = {
        "method": method,
        "scene": data.name,
        "device": "cuda" if on_cuda else "cpu",
        "machine": torch.cuda.get_device_name(0) if on_cuda else "cpu",
        "warmup": warmup,
        "steps": steps,
        "num_gaussians": int(trainer.pipeline.model.num_points),
        "wall_ms": (clock["t1"] - clock["t0"]) * 1000.0 / steps,
        "profiled_wall_ms": (clock["t2"] - clock["t1"]) * 1000.0 / steps,
        "syncs": sum(sites.values()) / steps,
        "sync_sites": {k: v / steps for k, v in sites.most_common()},
        "lap_every": lap_every,
        "laps": lap_rows(laps, events),
    }
    out.update(summarize(prof.key_averages(), steps, on_cuda))
    out["components"] = component_summary(prof.events(), steps, on_cuda)
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--method", required=True, help="a benchmarks/methods.py method (willags, splatfacto, peer, ...)")
    ap.add_argument("--data", required=True)
    ap.add_argument("--warmup", type=int, default=3000, help="steps trained before the window")
    ap.add_argument("--steps", type=int, default=50, help="steps profiled")
    ap.add_argument("--seed", type=int, default=42)
    ap.add_argument("--run-dir", default=None, help="scratch directory of the run (default: a temporary one)")
    ap.add_argument("--lap-every", type=int, default=100, help="clock the warm-up in laps of this many steps (0: not)")
    ap.add_argument("--out", required=True, help="JSON file written")
    args = ap.parse_args(argv)
    if args.warmup < 1 or args.steps < 1:
        raise SystemExit(f"profile_step: --warmup and --steps must be >= 1 (got {args.warmup}, {args.steps})")
    if args.lap_every < 0 or args.lap_every == 1:
        raise SystemExit(f"profile_step: --lap-every must be 0 or >= 2 (got {args.lap_every})")
    with tempfile.TemporaryDirectory() as tmp:
        run_dir = Path(args.run_dir or tmp)
        rec = profile(args.method, Path(args.data), args.warmup, args.steps, args.seed, run_dir, args.lap_every)
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps(rec, indent=1))
    print(
        f"profile_step: {args.method} on {rec['scene']} ({rec['machine']}): {rec['wall_ms']:.1f} ms/step wall, "
        f"{rec['device_ms']:.1f} ms on the device, {rec['launches']:.0f} launches, {rec['syncs']:.1f} syncs/step, "
        f"{rec['num_gaussians']:,} Gaussians"
    )
    for lap in rec["laps"]:
        event = "" if lap["event_ms"] is None else f", its refining step {lap['event_ms']:.1f} ms, the others "
        event += "" if lap["ordinary_ms"] is None else f"{lap['ordinary_ms']:.1f} ms"
        print(f"  lap to step {lap['steps']}: {lap['step_ms']:.1f} ms/step{event} ({lap['gaussians']:,} Gaussians)")
    for site, n in list(rec["sync_sites"].items())[:10]:
        print(f"  sync {n:.1f}/step at {site}")
    for name, c in rec["components"].items():
        print(
            f"  {name}: {c['host_ms']:.2f} ms host, {c['device_ms']:.2f} ms device, {c['launches']:.0f} launches, "
            f"{c['calls']:.1f} calls per step"
        )
        if c.get("ops"):
            print("    its own calls: " + ", ".join(f"{op[6:]} {n:g}" for op, n in c["ops"].items()))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
