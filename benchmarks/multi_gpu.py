"""willags on 1, 2 and 4 GPUs at equal images seen, or under a time budget, with each rank's step profile: where a
data-parallel step's time goes, the wall time to the last checkpoint, the protocol PSNR, and records with
``num_devices`` (docs/distributed.md).

    python -m benchmarks multi-gpu run --data .gpu-cv1/reichstag --out $OUT --images 8000 --runs 4,1,2,4:reference
    python -m benchmarks multi-gpu run --data .gpu-cv1/reichstag --out $OUT --runs 1 --gpus 2   # on GPU 2 only

A run is ``<devices>[x<machines>][:reference][:noshard][:budget<M>][@<images>]``: ``4`` trains on 4 GPUs of one machine;
``2x2`` on two "machines" of 2 GPUs each, started as two launches (``--machine.num-machines 2
--machine.machine-rank 0|1 --machine.dist-url tcp://127.0.0.1:PORT``); ``:reference`` with the first data-parallel
implementation (``--pipeline.data-parallel.reduction reference``) to compare on the same machine; ``:noshard`` with
every rank caching every training image (``--pipeline.data-parallel.shard-image-cache False``: what the sharded
cache saves, in each rank's peak host memory); ``:budget<M>``
under ``--pipeline.time-budget-minutes M``; ``@N`` sees N images instead of ``--images`` (a budget run without
``@N``: at most the method's own steps, 30000, on every device). A run of D devices in all
trains on the first D GPUs of ``--gpus`` (default: $CUDA_VISIBLE_DEVICES, else 0, 1, ...), machine m on the m-th
group of them (CUDA_VISIBLE_DEVICES of each launch).

Without a budget a run takes images / D steps, and every setting counted in steps is divided by D (scale_schedules:
densification warm-up / interval / stop, the resolution and SH schedules, the mask's warm-up, ramp and health
window, the learning-rate decays and warm-ups, which also set MCMC's position noise; the EMA teacher's decay
becomes tau^D), so that it follows the schedule of a one-device run of as many images. Under a budget the schedules
stay as the method has them (the budget plans steps as on one device and fits the schedules itself:
docs/distributed.md, "The time budget on several devices") and images / D steps is only a cap. Configs are
benchmarks/methods.py's (``--method``, with ``schedule="default"``: no evaluation while training, one checkpoint at
the end), handed to nerfstudio's own ``nerfstudio.scripts.train.main`` (its launcher: one process per GPU, NCCL).

Every run trains with ``--pipeline.data-parallel.step-profile True`` (willags_ns/engine/step_profile.py): each rank
writes its per-step spans (CUDA events) and start-up phases; this script reads them back and prints, per run, the
steady state (the last quarter of the steps): the step time, images per second and the ratio to the 1-GPU run, and
the step's breakdown (forward, backward, packing, the all-reduce's transfer and each rank's wait in it, unpacking,
optimiser, after-step callbacks, the rest of the loop); the bytes reduced; the start-up phases from the launch; for
a budget run each rank's last step, whether all ranks stopped after the same one, and the training time against the
budget (time_budget.json). Then every run is scored by ``ns-eval`` (the NeRF-W protocol), one evaluation per GPU of
``--gpus`` at once, after the last training.

``wall_s`` of a run: from the launch of its training processes to the modification time of its last checkpoint
(``nerfstudio_models/step-*.ckpt``: the trained model on disk); ``launcher_wall_s``: to the launcher's return.

Deadline: nothing starts that would not end before ``--deadline-s`` seconds after ``$MULTI_GPU_T0`` (the command's
start, set by benchmarks/remote/multi_gpu.sh; else this script's start); a run or evaluation still going at the
deadline is stopped (its process group killed) and counted as such; the results are rewritten under ``--out``
after every stage: ``multi_gpu.tgz`` (logs, step profiles, configs, evaluations, summary, records),
``multi_gpu_records.json`` (records for benchmarks/records/benchmarks.json: ``python -m benchmarks merge FILE``)
and ``multi_gpu_summary.txt`` (the tables printed at the end).
"""

import argparse
import json
import os
import shutil
import signal
import socket
import statistics
import subprocess
import sys
import tarfile
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parents[1]
STEADY_FRACTION = 0.25
"""The steady state of a run: its last quarter of steps (full resolution, SH degree 3, densification mostly done)."""
SAFE_ENV = {"NCCL_NVLS_ENABLE": "0", "TORCH_SYMM_MEM_DISABLE_MULTICAST": "1", "NVSHMEM_DISABLE_NVLS": "1"}
"""NVLink multicast stays off on the lent machines (KINDS.md): set for every process started here."""
WALL_MEANS = "launch of the run's training processes -> modification time of its last checkpoint"
"""What a record's ``wall_s`` measures."""


# ---------------------------------------------------------------------------------------------------- runs
@dataclass(frozen=True)
class Run:
    """One training run of the comparison."""

    devices: int
    """GPUs per machine."""
    machines: int = 1
    """Launches ("machines") of `devices` GPUs each."""
    reduction: str = "buffer"
    """--pipeline.data-parallel.reduction."""
    images: int | None = None
    """Images seen (None: the script's --images); under a budget, the most images."""
    budget_minutes: float | None = None
    """--pipeline.time-budget-minutes (None: none)."""
    shard: bool = True
    """--pipeline.data-parallel.shard-image-cache: each rank caches only its own training images."""

    @property
    def total(self) -> int:
        return self.devices * self.machines

    @property
    def name(self) -> str:
        shape = f"{self.devices}x{self.machines}" if self.machines > 1 else f"{self.devices}"
        ref = "-reference" if self.reduction == "reference" else ""
        budget = f"-budget{self.budget_minutes:g}" if self.budget_minutes else ""
        noshard = "" if self.shard else "-noshard"
        return f"gpus{shape}{ref}{noshard}{budget}" + (f"-{self.images}" if self.images else "")


def parse_runs(text: str) -> list[Run]:
    """'4,1,2,4:reference,2x2@2000,4:budget1' -> Runs (see the module docstring)."""
    runs = []
    for token in filter(None, (t.strip() for t in text.split(","))):
        images = None
        if "@" in token:
            token, n = token.split("@", 1)
            if not n.isdigit() or int(n) <= 0:
                raise ValueError(f"multi_gpu: images {n!r} in --runs must be a positive integer")
            images = int(n)
        shape, *mods = token.split(":")
        reduction, budget, shard = "buffer", None, True
        for mod in mods:
            if mod in ("buffer", "reference"):
                reduction = mod
            elif mod == "noshard":
                shard = False
            elif mod.startswith("budget"):
                try:
                    budget = float(mod[len("budget") :])
                except ValueError:
                    raise ValueError(f"multi_gpu: {mod!r} in --runs: budget<minutes>, e.g. budget1.5") from None
                if not budget > 0:
                    raise ValueError(f"multi_gpu: {mod!r} in --runs: the budget must be > 0 minutes")
            else:
                raise ValueError(f"multi_gpu: unknown modifier {mod!r} in --runs (reference, noshard, budget<minutes>)")
        try:
            devices, machines = (int(x) for x in shape.split("x")) if "x" in shape else (int(shape), 1)
        except ValueError:
            raise ValueError(f"multi_gpu: run {token!r} in --runs: <devices>[x<machines>]") from None
        if devices < 1 or machines < 1:
            raise ValueError(f"multi_gpu: run {token!r} in --runs: devices and machines must be >= 1")
        runs.append(Run(devices, machines, reduction, images, budget, shard))
    if not runs:
        raise ValueError(f"multi_gpu: no run in --runs {text!r}")
    return runs


def steps_of(images: int, total_devices: int) -> int:
    if images % total_devices:
        raise ValueError(f"multi_gpu: {images} images are not a multiple of {total_devices} devices")
    return images // total_devices


def images_of(run: Run, images: int, method: str) -> int:
    """The images a run sees: its own ``@N``, else `images`; a budget run without ``@N`` is capped at the method's
    own steps on each device (the budget never plans past them), so that the budget, not the cap, ends it."""
    if run.images:
        return run.images
    if run.budget_minutes:
        from benchmarks.methods import METHODS, base_trainer_config

        return base_trainer_config(METHODS[method].base).max_num_iterations * run.total
    return images


def gpus_of_run(gpus: list[str], run: Run) -> list[list[str]]:
    """The GPUs of each launch ("machine") of `run`: the first devices x machines of `gpus`, machine m the m-th
    group of `devices`."""
    if len(gpus) < run.total:
        raise ValueError(f"multi_gpu: run {run.name} needs {run.total} GPUs, --gpus gives {len(gpus)}: {gpus}")
    return [gpus[m * run.devices : (m + 1) * run.devices] for m in range(run.machines)]


def gpu_list(given: str | None, visible: str | None, most: int) -> list[str]:
    """The GPUs this script may use: `given` (--gpus), else `visible` ($CUDA_VISIBLE_DEVICES as the environment says
    them: another job may use the host's others), else 0..most-1."""
    for text in (given, visible):
        listed = [g.strip() for g in (text or "").split(",") if g.strip()]
        if listed:
            return listed
    return [str(i) for i in range(most)]


def eval_gpus(gpus: list[str], most: int) -> list[str]:
    """The GPUs the evaluations run on, one each: the first `most` of the script's GPUs."""
    return gpus[: max(1, most)]


def _div(steps: int, n: int) -> int:
    return max(1, round(steps / n)) if steps > 0 else steps


def scale_schedules(config: Any, n: int) -> dict[str, Any]:
    """Divide every step-counted setting of `config` (a willags TrainerConfig) by `n`, in place, so that a run of
    S / n steps on n devices follows the schedule of S single-device steps; returns what was set. The opacity reset
    (reset_alpha_every) counts refinements and MCMC's refinement window and period are warmup_length, stop_split_at
    and refine_every, so both follow; MCMC's position noise follows the means' learning rate."""
    m = config.pipeline.model
    done: dict[str, Any] = {}
    names = ("warmup_length", "refine_every", "stop_split_at", "stop_screen_size_at", "resolution_schedule")
    for name in (*names, "sh_degree_interval"):
        setattr(m, name, _div(getattr(m, name), n))
        done[name] = getattr(m, name)
    if getattr(m, "appearance", "sh") == "willags" and m.mask.enabled:  # before auto_config decides (it may drop it)
        m.mask.warmup_steps, m.mask.ramp_steps = _div(m.mask.warmup_steps, n), _div(m.mask.ramp_steps, n)
        m.mask.health.window = _div(m.mask.health.window, n)
        m.mask.teacher.tau = m.mask.teacher.tau**n
        done.update({"mask.warmup_steps": m.mask.warmup_steps, "mask.ramp_steps": m.mask.ramp_steps})
        done.update({"mask.health.window": m.mask.health.window, "mask.teacher.tau": m.mask.teacher.tau})
    for group, settings in config.optimizers.items():
        sched = settings.get("scheduler")
        if sched is not None and hasattr(sched, "max_steps"):
            sched.max_steps = _div(sched.max_steps, n)
            done[f"{group}.max_steps"] = sched.max_steps
            if getattr(sched, "warmup_steps", 0):
                sched.warmup_steps = _div(sched.warmup_steps, n)
                done[f"{group}.warmup_steps"] = sched.warmup_steps
    return done


def build_config(spec: dict[str, Any]) -> Any:
    """The TrainerConfig of a run spec (written by `run`, read by `train`): benchmarks/methods.py's config of the
    method, on the run's devices, with the step profile, the schedules divided (no budget) or the time budget."""
    from benchmarks.methods import build_config as method_config

    n = spec["devices"] * spec["machines"]
    output_dir = Path(spec["output_dir"]) / spec["name"]
    config = method_config(
        spec["method"], spec["steps"], spec["device_type"], Path(spec["data"]), None, "default", output_dir
    )
    if not hasattr(config.pipeline, "data_parallel"):
        raise ValueError(f"multi_gpu: method {spec['method']!r} has no data-parallel pipeline (a willags method)")
    config.machine.num_devices = spec["devices"]
    config.machine.num_machines = spec["machines"]
    config.machine.seed = spec["seed"]
    config.machine.dist_url = spec["dist_url"]
    config.viewer.quit_on_train_completion = True
    config.pipeline.data_parallel.reduction = spec["reduction"]
    config.pipeline.data_parallel.step_profile = True
    config.pipeline.data_parallel.shard_image_cache = spec.get("shard_image_cache", True)
    if spec.get("eval_max_images"):
        config.pipeline.eval_protocol.max_images = spec["eval_max_images"]
    if spec.get("budget_minutes"):
        config.pipeline.time_budget_minutes = spec["budget_minutes"]
    else:
        scale_schedules(config, n)
    return config


def run_dir_of(spec: dict[str, Any]) -> Path:
    """Where nerfstudio writes the run (config.yml, nerfstudio_models/, step_profile/): methods.build_config's
    experiment "bench", timestamp "run"."""
    return Path(spec["output_dir"]) / spec["name"] / "bench" / spec["method"] / "run"


# ---------------------------------------------------------------------------------------------------- profiles
def _median(values: list[float]) -> float | None:
    values = [v for v in values if v is not None]
    return statistics.median(values) if values else None


SPANS = ("forward", "backward", "pack", "collective", "unpack", "optimizer", "callbacks")


def breakdown(profile: dict[int, tuple[dict[str, Any], list[dict[str, Any]]]]) -> dict[str, Any]:
    """The steady state of a run (its last STEADY_FRACTION of steps, steps every rank wrote), medians in ms: the
    iteration (rank 0's loop iteration) and each span averaged over the ranks, the all-reduce split into the
    transfer (the quickest rank's time in it) and the wait (each rank's time in it minus the quickest's: the wait for
    the slowest rank), the rest of the loop, and the bytes, host read-backs, Gaussians and pixels of a step. Device
    times (CUDA events) where the ranks recorded them, else the host's."""
    if not profile:
        return {}
    by_rank = {r: {row["step"]: row for row in rows if "step" in row} for r, (_, rows) in profile.items()}
    steps = sorted(set.intersection(*(set(s) for s in by_rank.values())))
    if not steps:
        return {}
    steady = steps[int(len(steps) * (1 - STEADY_FRACTION)) :]
    sample = by_rank[min(by_rank)][steady[0]]
    kind = "d" if "d_iteration" in sample else "h"
    out: dict[str, Any] = {"clock": "device" if kind == "d" else "host", "steps": len(steady)}
    out["iteration"] = _median([by_rank[min(by_rank)][s].get(f"{kind}_iteration") for s in steady])
    for span in SPANS:
        out[span] = _median(
            [statistics.mean(by_rank[r][s].get(f"{kind}_{span}", 0.0) for r in by_rank) for s in steady]
        )
    transfer, wait, wait_max = [], [], []
    for s in steady:
        times = [by_rank[r][s].get(f"{kind}_collective") for r in by_rank]
        if None in times:
            continue
        quickest = min(times)
        transfer.append(quickest)
        wait.append(statistics.mean(t - quickest for t in times))
        wait_max.append(max(times) - quickest)
    out["transfer"] = _median(transfer)
    out["wait"] = _median(wait)
    out["wait_spread"] = _median(wait_max)
    if out["iteration"] is not None:
        out["rest"] = out["iteration"] - sum(out[s] or 0.0 for s in SPANS)
    first = by_rank[min(by_rank)]
    for field in ("bytes", "host_reads", "gaussians", "pixels"):
        out[field] = _median([first[s].get(field) for s in steady])
    out["gaussians_end"] = first[steps[-1]].get("gaussians")
    out["host_iteration"] = _median([first[s].get("h_iteration") for s in steady])
    return out


def peak_memory(profile: dict[int, tuple[dict[str, Any], list[dict[str, Any]]]]) -> dict[str, Any]:
    """Each rank's peak memory at the end of training (the step profile's meta, ranks in order), GB: host (its
    resident set) and device (torch's largest allocation); None for a rank that did not record it."""

    def gb(meta: dict[str, Any], key: str) -> float | None:
        v = meta.get(key)
        return round(v / 1e9, 3) if isinstance(v, (int, float)) else None

    metas = [meta for _, (meta, _) in sorted(profile.items())]
    return {
        "peak_host_gb": [gb(m, "peak_host_bytes") for m in metas],
        "peak_device_gb": [gb(m, "peak_device_bytes") for m in metas],
    }


def startup(profile: dict[int, tuple[dict[str, Any], list[dict[str, Any]]]], t_launch: float) -> dict[str, float]:
    """Start-up phases of rank 0 (the first step: the latest rank's) in seconds after the launch."""
    if not profile:
        return {}
    phases = dict(profile[min(profile)][0].get("phases", {}))
    out = {k: round(v - t_launch, 2) for k, v in phases.items() if isinstance(v, (int, float))}
    firsts = [m.get("phases", {}).get("first_step") for m, _ in profile.values()]
    if all(isinstance(v, (int, float)) for v in firsts):
        out["first_step_last_rank"] = round(max(firsts) - t_launch, 2)
    return out


def last_steps(profile: dict[int, tuple[dict[str, Any], list[dict[str, Any]]]]) -> dict[str, Any]:
    """Each rank's last trained step (its profile's last row with a step, ranks in order) and whether every rank
    stopped after the same one."""
    last = [
        max((row["step"] for row in rows if "step" in row), default=None) for _, (_, rows) in sorted(profile.items())
    ]
    return {"last_steps": last, "same_last_step": bool(last) and None not in last and len(set(last)) == 1}


def budget_summary(run_dir: Path, profile: dict[int, tuple[dict[str, Any], list[dict[str, Any]]]]) -> dict[str, Any]:
    """A budget run's stop: the budget, the training time it counted and where it stopped (time_budget.json's
    ``run``), and each rank's first step to the end of training on its own clock (the step profile's phases)."""
    out: dict[str, Any] = {}
    path = run_dir / "time_budget.json"
    if path.is_file():
        run = json.loads(path.read_text()).get("run") or {}
        for key in ("budget_s", "elapsed_s", "stopped_after_step", "steps_trained", "stop_reason", "max_steps"):
            out[f"budget_{key}" if not key.startswith("budget") else key] = run.get(key)
    spans = []
    for _, (meta, _) in sorted(profile.items()):
        phases = meta.get("phases", {})
        first, end = phases.get("first_step"), phases.get("train_end")
        spans.append(
            round(end - first, 2) if isinstance(first, (int, float)) and isinstance(end, (int, float)) else None
        )
    out["train_span_s"] = spans
    if out.get("budget_s") and out.get("budget_elapsed_s") is not None:
        out["budget_used"] = round(out["budget_elapsed_s"] / out["budget_s"], 4)
    return out


def last_checkpoint(run_dir: Path) -> Path | None:
    """The run's checkpoint written last (nerfstudio_models/step-*.ckpt), or None."""
    ckpts = list((run_dir / "nerfstudio_models").glob("step-*.ckpt"))
    return max(ckpts, key=lambda p: p.stat().st_mtime) if ckpts else None


def steady_images_per_s(result: dict[str, Any]) -> float | None:
    """Images per second at the end: devices x 1000 / the median step (ms) of the last quarter of the steps."""
    step = (result.get("breakdown") or {}).get("iteration")
    return result["num_devices"] * 1000.0 / step if step else None


# ---------------------------------------------------------------------------------------------------- processes
def _env(extra: dict[str, str] | None = None) -> dict[str, str]:
    env = {**os.environ, **(extra or {})}
    for k, v in SAFE_ENV.items():
        env.setdefault(k, v)
    env["PYTHONUNBUFFERED"] = "1"
    env["PYTHONPATH"] = os.pathsep.join(p for p in (str(REPO), env.get("PYTHONPATH", "")) if p)
    return env


def _start(cmd: list[str], log: Path, env: dict[str, str]) -> subprocess.Popen:
    log.parent.mkdir(parents=True, exist_ok=True)
    out = open(log, "w")
    return subprocess.Popen(cmd, cwd=REPO, env=env, stdout=out, stderr=subprocess.STDOUT, start_new_session=True)


def _wait(procs: list[subprocess.Popen], until: float) -> str:
    """'ok', 'failed' (a process exited non-zero: the others are stopped) or 'deadline' (all stopped)."""
    while True:
        codes = [p.poll() for p in procs]
        if any(c not in (None, 0) for c in codes):
            _stop(procs)
            return "failed"
        if all(c == 0 for c in codes):
            return "ok"
        if time.time() >= until:
            _stop(procs)
            return "deadline"
        time.sleep(0.5)


def _stop(procs: list[subprocess.Popen]) -> None:
    for p in procs:
        if p.poll() is None:
            try:
                os.killpg(p.pid, signal.SIGTERM)  # the launcher and the ranks it spawned: one process group
            except ProcessLookupError:
                pass
    deadline = time.time() + 10
    for p in procs:
        try:
            p.wait(timeout=max(0.1, deadline - time.time()))
        except subprocess.TimeoutExpired:
            os.killpg(p.pid, signal.SIGKILL)


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def estimate_s(run: Run, images: int) -> float:
    """A pessimistic wall time of a run on H100s (start-up ~60 s; 12.5 ms a single-device step at the end of a
    reichstag run; a data-parallel step up to 1.45 times that; a budget run: start-up, its budget and a margin), to
    skip what cannot end before the deadline."""
    if run.budget_minutes:
        return 90.0 + 60.0 * run.budget_minutes
    steps = images / run.total
    return 60.0 + steps * 0.0125 * (1.45 if run.total > 1 else 1.0)


# ---------------------------------------------------------------------------------------------------- reporting
def _f(v: Any, fmt: str) -> str:
    return format(v, fmt) if isinstance(v, (int, float)) and not isinstance(v, bool) else "-"


def tables(results: list[dict[str, Any]]) -> str:
    """The summary printed at the end: runs, steady-state breakdowns, start-up phases, budget runs' stops, goals."""
    base = next(
        (r for r in results if r["num_devices"] == 1 and r.get("status") == "ok" and not r.get("budget_minutes")), None
    )
    lines = [
        "run                          GPUs  steps  images  status    wall s  x1 wall  step ms  img/s   x1 img/s   "
        "PSNR   SSIM  Gaussians  MB/step",
    ]
    for r in results:
        b = r.get("breakdown") or {}
        step = b.get("iteration")
        ips = steady_images_per_s(r)
        x_ips = x_wall = None
        if base and base is not r and ips and (base.get("breakdown") or {}).get("iteration"):
            x_ips = ips / (1000.0 / base["breakdown"]["iteration"])
            same = r["images"] == base["images"] and not r.get("budget_minutes")
            if same and r.get("wall_s") and base.get("wall_s"):
                x_wall = base["wall_s"] / r["wall_s"]
        mb = b.get("bytes") / 1e6 if b.get("bytes") else None
        lines.append(
            f"{r['name']:<28} {r['num_devices']:>4} {r.get('steps_trained') or r['steps']:>6} {r['images']:>7}  "
            f"{r['status']:<8} {_f(r.get('wall_s'), '7.1f')}  {_f(x_wall, '6.2f')}x  {_f(step, '6.2f')}  "
            f"{_f(ips, '6.1f')}  {_f(x_ips, '7.2f')}x  {_f(r.get('psnr'), '6.2f')} {_f(r.get('ssim'), '6.4f')} "
            f"{_f(b.get('gaussians_end'), '10.0f')}  {_f(mb, '7.1f')}"
        )
    lines += [
        f"(wall s: {WALL_MEANS}; steps: trained; img/s: the steady state's)",
        "",
        "steady state (last quarter of the steps), median ms per step; transfer = the quickest rank's time in the "
        "all-reduce, wait = the others' extra time there (mean over ranks; spread = slowest - quickest)",
        "run                          clock   fwd     bwd    pack transfer  wait spread  unpack   opt  callbk   rest  "
        " step host-step reads",
    ]
    for r in results:
        b = r.get("breakdown") or {}
        if not b:
            continue
        lines.append(
            f"{r['name']:<28} {b.get('clock', '-'):<6} {_f(b.get('forward'), '6.2f')} {_f(b.get('backward'), '6.2f')} "
            f"{_f(b.get('pack'), '6.2f')} {_f(b.get('transfer'), '7.2f')} {_f(b.get('wait'), '6.2f')} "
            f"{_f(b.get('wait_spread'), '6.2f')} {_f(b.get('unpack'), '6.2f')} {_f(b.get('optimizer'), '6.2f')} "
            f"{_f(b.get('callbacks'), '6.2f')} {_f(b.get('rest'), '6.2f')} {_f(b.get('iteration'), '6.2f')} "
            f"{_f(b.get('host_iteration'), '8.2f')} {_f(b.get('host_reads'), '5.1f')}"
        )
    phases = ("process_start", "pipeline_init", "scene_inspected", "data_parsed", "inputs_checked", "model_built")
    phases += ("data_parallel_ready",)
    phases += ("images_cache_start", "images_cached", "first_step", "first_step_last_rank", "train_end")
    lines += ["", "start-up, seconds after the launch (rank 0): " + ", ".join(phases) + ", last checkpoint"]
    for r in results:
        s = r.get("startup") or {}
        cells = " ".join(_f(s.get(p), "6.1f") for p in phases)
        lines.append(f"{r['name']:<28} {cells} {_f(r.get('wall_s'), '6.1f')}")
    lines += ["", "peak memory per rank at the end of training, GB: host (resident set) / device (torch's allocations)"]
    for r in results:
        host, dev = r.get("peak_host_gb") or [], r.get("peak_device_gb") or []
        if host or dev:
            cells = ", ".join(f"{_f(h, '.2f')} / {_f(d, '.2f')}" for h, d in zip(host, dev, strict=False))
            lines.append(f"{r['name']:<28} {cells}  (host, all ranks: {_f(sum(h or 0 for h in host), '.2f')})")
    budgeted = [r for r in results if r.get("budget_minutes")]
    if budgeted:
        lines += ["", "budget runs: each rank's last step, same on all, training time (time_budget.json) vs budget"]
        for r in budgeted:
            lines.append(
                f"{r['name']:<28} last steps {r.get('last_steps')} same {r.get('same_last_step')} "
                f"elapsed {_f(r.get('budget_elapsed_s'), '.1f')} s of {_f(r.get('budget_s'), '.0f')} s "
                f"(first step to end per rank {r.get('train_span_s')}; {r.get('budget_stop_reason')})"
            )
    if base:
        lines += ["", "goals (equal images seen; steady-state throughput from the step profile):"]
        for r in results:
            if r is base or r.get("status") != "ok" or r["reduction"] != "buffer" or r["machines"] != 1:
                continue
            if r.get("budget_minutes"):
                continue
            b, bb = r.get("breakdown") or {}, base.get("breakdown") or {}
            if not (b.get("iteration") and bb.get("iteration")):
                continue
            x_ips = r["num_devices"] * bb["iteration"] / b["iteration"]
            want = {2: 1.8, 4: 3.2}.get(r["num_devices"])
            x_wall = None
            if r["images"] == base["images"] and r.get("wall_s") and base.get("wall_s"):
                x_wall = base["wall_s"] / r["wall_s"]
            verdict = "" if want is None else (" met" if x_ips >= want else " NOT met")
            lines.append(
                f"  {r['num_devices']} GPUs: throughput {x_ips:.2f}x (goal >= {want}x:{verdict}), wall "
                f"{_f(x_wall, '.2f')}x at {r['images']} images"
            )
    return "\n".join(lines)


def record(result: dict[str, Any], args: argparse.Namespace) -> dict[str, Any]:
    """A benchmarks/records/benchmarks.json record of one run."""
    b = result.get("breakdown") or {}
    eval_max = getattr(args, "eval_max_images", 0)  # (an older command line has none)
    rec = {
        "scene": Path(args.data).name,
        "method": args.method,
        "device": args.device_type,
        "steps": result.get("steps_trained") or result["steps"],
        "tag": f"{args.tag}-{result['name']}",
        "group": args.tag,
        "num_devices": result["num_devices"],
        "num_machines": result["machines"],
        "images": result["images"],
        "reduction": result["reduction"],
        "shard_image_cache": result.get("shard", True),
        "peak_host_gb_per_rank": result.get("peak_host_gb"),
        "peak_device_gb_per_rank": result.get("peak_device_gb"),
        "status": result["status"],
        "psnr": result.get("psnr"),
        "ssim": result.get("ssim"),
        "wall_s": result.get("wall_s"),
        "wall_s_means": WALL_MEANS,
        "launcher_wall_s": result.get("launcher_wall_s"),
        "train_wall_s": result.get("wall_s"),
        "step_ms": b.get("iteration"),
        "images_per_s": steady_images_per_s(result),
        "images_per_s_means": "steady state: devices x 1000 / median step ms of the last quarter of the steps",
        "num_gaussians": b.get("gaussians_end"),
        "breakdown_ms": b,
        "startup_s": result.get("startup"),
        "first_step_s": (result.get("startup") or {}).get("first_step"),
        "schedule": "time budget" if result.get("budget_minutes") else "default, step-counted settings / devices",
        "machine": result.get("machine"),
        "commit": args.commit,
        "date": time.strftime("%Y-%m-%dT%H:%M:%S"),
        "command": (
            f"python -m benchmarks multi-gpu run --data {args.data} --images {args.images} --runs {args.runs} "
            f"--seed {args.seed}" + (f" --eval-max-images {eval_max}" if eval_max else "") + f" (run {result['name']})"
        ),
        "seed": args.seed,
        "eval_max_images": eval_max or None,
    }
    if result.get("budget_minutes"):
        rec["time_budget_minutes"] = result["budget_minutes"]
        rec["images_cap"] = result["images"]  # the budget ended it: images are those seen
        if result.get("steps_trained"):
            rec["images"] = result["steps_trained"] * result["num_devices"]
        for key in ("last_steps", "same_last_step", "budget_s", "budget_elapsed_s", "budget_used", "train_span_s"):
            rec[key] = result.get(key)
        rec["budget_stopped_after_step"] = result.get("budget_stopped_after_step")
        rec["budget_stop_reason"] = result.get("budget_stop_reason")
    return rec


def write_results(out: Path, work: Path, results: list[dict[str, Any]], args: argparse.Namespace) -> str:
    """Rewrite multi_gpu_summary.txt, multi_gpu_records.json and multi_gpu.tgz under `out`; returns the summary."""
    text = tables(results)
    out.mkdir(parents=True, exist_ok=True)
    (work / "results.json").write_text(json.dumps(results, indent=1, default=str))
    (out / "multi_gpu_summary.txt").write_text(text + "\n")
    (out / "multi_gpu_records.json").write_text(json.dumps([record(r, args) for r in results], indent=1) + "\n")
    tmp = out / "multi_gpu.tgz.tmp"
    with tarfile.open(tmp, "w:gz") as tar:
        for path in sorted(work.rglob("*")):
            keep = path.is_file() and path.suffix not in (".ckpt",) and "events.out" not in path.name
            if keep and path.stat().st_size < 8e6:
                tar.add(path, arcname=str(path.relative_to(work)))
    tmp.replace(out / "multi_gpu.tgz")
    return text


def collect(res: dict[str, Any], run_dir: Path, t_launch: float) -> None:
    """What a finished (or stopped) run left in `run_dir`, into its result `res`: the breakdown, the start-up, the
    wall time to the last checkpoint, each rank's last step and, under a budget, where and when it stopped."""
    res["run_dir"] = str(run_dir)
    from willags_ns.engine.step_profile import read_step_profile

    profile = read_step_profile(run_dir)
    res["breakdown"] = breakdown(profile)
    res.update(peak_memory(profile))
    res["startup"] = startup(profile, t_launch)
    res.update(last_steps(profile))
    trained = [s for s in res["last_steps"] if s is not None]
    res["steps_trained"] = min(trained) + 1 if trained else None
    ckpt = last_checkpoint(run_dir)
    res["wall_s"] = round(ckpt.stat().st_mtime - t_launch, 2) if ckpt else None
    res["checkpoint"] = ckpt.name if ckpt else None
    if res.get("budget_minutes"):
        res.update(budget_summary(run_dir, profile))
    if profile:
        meta = profile[min(profile)][0]
        res["machine"] = (
            f"{res['num_devices']}x {meta.get('device')} ({meta.get('host')}, {meta.get('cpu_count')} CPUs)"
        )


# ---------------------------------------------------------------------------------------------------- commands
def cmd_train(args: argparse.Namespace) -> None:
    """One launch of a run (one "machine"): the config from the spec, nerfstudio's own main()."""
    spec = json.loads(Path(args.spec).read_text())
    config = build_config(spec)
    config.machine.machine_rank = args.machine_rank
    from nerfstudio.scripts.train import main

    main(config)


def cmd_run(args: argparse.Namespace) -> None:
    t0 = float(os.environ.get("MULTI_GPU_T0", time.time()))
    deadline = t0 + args.deadline_s
    out, work = Path(args.out), Path(args.work)
    runs = parse_runs(args.runs)
    from benchmarks.methods import METHODS

    if args.method not in METHODS:
        raise ValueError(f"multi_gpu: unknown --method {args.method!r} (benchmarks/methods.py: {', '.join(METHODS)})")
    gpus = gpu_list(args.gpus, os.environ.get("CUDA_VISIBLE_DEVICES"), max(r.total for r in runs))
    cuda = args.device_type == "cuda"
    for run in runs:  # every run's GPUs and steps before anything trains
        if cuda:
            gpus_of_run(gpus, run)
        steps_of(images_of(run, args.images, args.method), run.total)
    if args.commit is None:
        from benchmarks.grid import git_commit

        args.commit = git_commit()
    if work.is_dir():  # this script's scratch: an earlier call's runs would end up in this call's archive
        shutil.rmtree(work)
    work.mkdir(parents=True)
    results: list[dict[str, Any]] = []
    python = sys.executable
    print(f"multi_gpu: GPUs {','.join(gpus) if cuda else '(cpu)'}, seed {args.seed}, commit {args.commit}")
    for run in runs:
        images = images_of(run, args.images, args.method)
        res: dict[str, Any] = {
            "name": run.name,
            "num_devices": run.total,
            "machines": run.machines,
            "reduction": run.reduction,
            "shard": run.shard,
            "budget_minutes": run.budget_minutes,
            "images": images,
            "steps": steps_of(images, run.total),
            "status": "skipped",
        }
        results.append(res)
        left = deadline - time.time() - args.eval_reserve_s
        if estimate_s(run, images) > left and not args.dry_run:
            print(f"multi_gpu: {run.name} skipped: ~{estimate_s(run, images):.0f} s needed, {left:.0f} s left")
            continue
        spec = {
            "name": run.name,
            "method": args.method,
            "data": str(Path(args.data).resolve()),
            "devices": run.devices,
            "machines": run.machines,
            "device_type": args.device_type,
            "seed": args.seed,
            "steps": res["steps"],
            "reduction": run.reduction,
            "shard_image_cache": run.shard,
            "eval_max_images": args.eval_max_images,
            "budget_minutes": run.budget_minutes,
            "output_dir": str(work / "runs"),
            "dist_url": f"tcp://127.0.0.1:{_free_port()}" if run.machines > 1 else "auto",
        }
        spec_path = work / f"{run.name}.spec.json"
        spec_path.write_text(json.dumps(spec, indent=1))
        groups = gpus_of_run(gpus, run) if cuda else [[] for _ in range(run.machines)]
        res["gpus"] = [",".join(g) for g in groups]
        if args.dry_run:
            config = build_config(spec)
            what = f"budget {run.budget_minutes:g} min" if run.budget_minutes else scale_schedules(config, 1)
            print(
                f"{run.name}: {run.total} GPUs ({res['gpus']}), {res['steps']} steps"
                f"{' at most' if run.budget_minutes else ''}, ~{estimate_s(run, images):.0f} s; {what}"
            )
            res["status"] = "dry-run"
            continue
        print(
            f"multi_gpu: train {run.name}: {run.total} GPUs {res['gpus']}, {res['steps']} steps ({time.time() - t0:.0f} s)"
        )
        procs, t_launch = [], time.time()
        for m, group in enumerate(groups):
            extra = {"CUDA_VISIBLE_DEVICES": ",".join(group)} if cuda else {}
            cmd = [python, "-m", "benchmarks.multi_gpu", "train", str(spec_path), "--machine-rank", str(m)]
            procs.append(_start(cmd, work / f"{run.name}.train{m}.log", _env(extra)))
        res["status"] = _wait(procs, deadline - args.eval_reserve_s / 2)
        res["launcher_wall_s"] = round(time.time() - t_launch, 2)
        collect(res, run_dir_of(spec), t_launch)
        print(f"multi_gpu: {run.name} {res['status']}: last checkpoint at {_f(res['wall_s'], '.1f')} s")
        write_results(out, work, results, args)
    # every trained run scored by ns-eval, one per GPU at a time
    todo = [r for r in results if r["status"] == "ok"] if not args.skip_eval else []
    where = eval_gpus(gpus, args.eval_gpus) if cuda else [""]
    while todo and time.time() < deadline - 15:
        batch, todo = todo[: len(where)], todo[len(where) :]
        procs = []
        for gpu, r in zip(where, batch, strict=False):  # the last batch may be shorter
            cmd = [python, "-m", "nerfstudio.scripts.eval", "--load-config", str(Path(r["run_dir"]) / "config.yml")]
            cmd += ["--output-path", str(work / f"{r['name']}.eval.json")]
            # ns-eval looks the method up by name in the entry points: pip's, or those remote/env.sh writes on a lent GPU
            env = _env({"CUDA_VISIBLE_DEVICES": gpu} if cuda else {})
            procs.append(_start(cmd, work / f"{r['name']}.eval.log", env))
        for r, p in zip(batch, procs, strict=True):
            status = _wait([p], deadline - 10)
            path = work / f"{r['name']}.eval.json"
            if status == "ok" and path.is_file():
                scores = json.loads(path.read_text()).get("results", {})
                r["psnr"], r["ssim"] = scores.get("psnr"), scores.get("ssim")
            else:
                r["eval_status"] = status
        write_results(out, work, results, args)
    print(write_results(out, work, results, args))


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="benchmarks multi-gpu", description=__doc__.split("\n\n")[0])
    sub = parser.add_subparsers(dest="command", required=True)
    run = sub.add_parser("run", help="train, profile and score the runs; write the results under --out")
    run.add_argument("--data", required=True, help="the scene (a COLMAP / nerfstudio scene folder: .gpu-cv1/reichstag)")
    run.add_argument("--out", required=True, help="where the results go ($OUT on the device machine)")
    run.add_argument("--images", type=int, default=8000, help="images seen by every run (steps = images / GPUs)")
    run.add_argument("--runs", default="4,1,2,4:reference", help="the runs, in order (module docstring)")
    run.add_argument("--gpus", default=None, help="GPUs to use, e.g. 2,3 (default: $CUDA_VISIBLE_DEVICES, else 0,1,..)")
    run.add_argument("--method", default="willags", help="a willags method of benchmarks/methods.py")
    run.add_argument("--seed", type=int, default=42, help="--machine.seed of every run")
    run.add_argument("--device-type", default="cuda", choices=("cuda", "cpu"))
    run.add_argument("--tag", default="multi-gpu", help="records' tag prefix (each run adds its name)")
    run.add_argument("--commit", default=None, help="the records' commit (default: $WILLAGS_COMMIT, else git's)")
    run.add_argument("--work", default="/tmp/willags-multi-gpu", help="runs, logs and profiles (emptied first)")
    run.add_argument("--deadline-s", type=float, default=555.0, help="after $MULTI_GPU_T0 (or now)")
    run.add_argument("--eval-reserve-s", type=float, default=70.0, help="kept for the evaluations at the end")
    run.add_argument("--eval-gpus", type=int, default=4, help="evaluations at once, one per GPU")
    run.add_argument("--skip-eval", action="store_true", help="no ns-eval (no PSNR in the records)")
    run.add_argument("--eval-max-images", type=int, default=0, help="ns-eval scores the first N test photos (0: all)")
    run.add_argument("--dry-run", action="store_true", help="print the runs, GPUs, steps and schedules; train nothing")
    run.set_defaults(func=cmd_run)
    train = sub.add_parser("train", help="(internal) one launch of a run")
    train.add_argument("spec")
    train.add_argument("--machine-rank", type=int, default=0)
    train.set_defaults(func=cmd_train)
    args = parser.parse_args(sys.argv[1:] if argv is None else argv)
    try:
        args.func(args)
    except ValueError as e:
        if not str(e).startswith("multi_gpu:"):
            raise
        print(e, file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
