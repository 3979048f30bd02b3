"""willags on 1, 2 and 4 GPUs at equal images seen, with each rank's step profile: where a data-parallel step's
time goes, the wall time, the protocol PSNR, and records with ``num_devices`` (docs/distributed.md).

    python -m benchmarks multi-gpu run --data .gpu-r/reichstag --out $OUT --images 8000 --runs 4,1,2,4:reference

A run is ``<devices>[x<machines>][:reference][@<images>]``: ``4`` trains on 4 GPUs of one machine; ``2x2`` on two
"machines" of 2 GPUs each, started as two launches (``--machine.num-machines 2 --machine.machine-rank 0|1
--machine.dist-url tcp://127.0.0.1:PORT``, GPUs 0-1 and 2-3: CUDA_VISIBLE_DEVICES); ``:reference`` with the first
data-parallel implementation (``--pipeline.data-parallel.reduction reference``) to compare on the same machine;
``@N`` sees N images instead of ``--images``. With D devices in all a run takes images / D steps, and every setting
counted in steps is divided by D (densification warm-up / interval / stop, the resolution and SH schedules, the
mask's warm-up and ramp, the learning-rate decays and warm-ups; the EMA teacher's decay becomes tau^D), as
benchmarks/remote/multi_gpu.sh always did. Configs are built here in Python and handed to nerfstudio's own
``nerfstudio.scripts.train.main`` (its launcher: one process per GPU, NCCL), so no method registry and no parsing of
anyone's stdout is involved.

Every run trains with ``--pipeline.data-parallel.step-profile True`` (willags_ns/engine/step_profile.py): each rank writes
its per-step spans (CUDA events) and start-up phases; this script reads them back and prints, per run, the steady
state (the last quarter of the steps): the step time, images per second and the ratio to the 1-GPU run, and the
step's breakdown: forward, backward, packing, the all-reduce's transfer (the quickest rank's time in it) and each
rank's wait in it for the others (its own time there minus the quickest's), unpacking, optimiser, after-step
callbacks, the rest of the loop (logging, evaluation images, checkpoints); the bytes reduced; and the start-up
phases from the launch. Then every run is scored by ``ns-eval`` (the NeRF-W protocol), the evaluations one per GPU
at once after the last training.

Deadline: nothing starts that would not end before ``--deadline-s`` seconds after ``$MULTI_GPU_T0`` (the
command's start, set by benchmarks/remote/multi_gpu.sh; else this script's start); a run or evaluation still going at the
deadline is stopped (its process group killed) and counted as such; the results are rewritten under ``--out``
after every stage: ``multi_gpu.tgz`` (logs, step profiles, configs, evaluations, summary, records),
``multi_gpu_records.json`` (benchmarks/records/benchmarks.json records: copy into benchmarks/records/gpu_runs/ and run
benchmarks/merge_gpu_records.py) and ``multi_gpu_summary.txt`` (the tables printed at the end).
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
    """Images seen (None: the script's --images)."""

    @property
    def total(self) -> int:
        return self.devices * self.machines

    @property
    def name(self) -> str:
        shape = f"{self.devices}x{self.machines}" if self.machines > 1 else f"{self.devices}"
        ref = "-reference" if self.reduction == "reference" else ""
        return f"gpus{shape}{ref}" + (f"-{self.images}" if self.images else "")


def parse_runs(text: str) -> list[Run]:
    """'4,1,2,4:reference,2x2@2000' -> Runs (see the module docstring)."""
    runs = []
    for token in filter(None, (t.strip() for t in text.split(","))):
        images = None
        if "@" in token:
            token, n = token.split("@")
            images = int(n)
        reduction = "buffer"
        if ":" in token:
            token, reduction = token.split(":")
            if reduction not in ("buffer", "reference"):
                raise ValueError(f"multi_gpu: unknown reduction {reduction!r} in --runs")
        devices, machines = (int(x) for x in token.split("x")) if "x" in token else (int(token), 1)
        runs.append(Run(devices, machines, reduction, images))
    return runs


def steps_of(images: int, total_devices: int) -> int:
    if images % total_devices:
        raise ValueError(f"multi_gpu: {images} images are not a multiple of {total_devices} devices")
    return images // total_devices


def scale_schedules(config: Any, n: int) -> dict[str, Any]:
    """Divide every step-counted setting of `config` (a willags TrainerConfig) by `n`, in place, so that a run of
    S / n steps on n devices follows the schedule of S single-device steps; returns what was set."""

    def div(steps: int) -> int:
        return max(1, round(steps / n)) if steps > 0 else steps

    m = config.pipeline.model
    done: dict[str, Any] = {}
    for name in ("warmup_length", "refine_every", "stop_split_at", "stop_screen_size_at", "resolution_schedule"):
        setattr(m, name, div(getattr(m, name)))
        done[name] = getattr(m, name)
    m.sh_degree_interval = div(m.sh_degree_interval)
    done["sh_degree_interval"] = m.sh_degree_interval
    if getattr(m, "appearance", "sh") == "willags" and m.mask.enabled:  # before auto_config decides (it may drop it)
        m.mask.warmup_steps, m.mask.ramp_steps = div(m.mask.warmup_steps), div(m.mask.ramp_steps)
        m.mask.teacher.tau = m.mask.teacher.tau**n
        done.update({"mask.warmup_steps": m.mask.warmup_steps, "mask.ramp_steps": m.mask.ramp_steps})
        done["mask.teacher.tau"] = m.mask.teacher.tau
    for group, settings in config.optimizers.items():
        sched = settings.get("scheduler")
        if sched is not None and hasattr(sched, "max_steps"):
            sched.max_steps = div(sched.max_steps)
            done[f"{group}.max_steps"] = sched.max_steps
            if getattr(sched, "warmup_steps", 0):
                sched.warmup_steps = div(sched.warmup_steps)
                done[f"{group}.warmup_steps"] = sched.warmup_steps
    return done


def build_config(spec: dict[str, Any]) -> Any:
    """The TrainerConfig of a run spec (written by `run`, read by `train`)."""
    import willags_ns.method_configs  # noqa: F401  (registers every method's factory)
    from willags_ns.engine.trainer import PRESET_CONFIGS

    config = PRESET_CONFIGS[spec["method"]]()
    n = spec["devices"] * spec["machines"]
    config.pipeline.datamanager.data = Path(spec["data"])
    config.machine.num_devices = spec["devices"]
    config.machine.num_machines = spec["machines"]
    config.machine.device_type = spec["device_type"]
    config.machine.seed = spec["seed"]
    config.machine.dist_url = spec["dist_url"]
    config.max_num_iterations = spec["steps"]
    config.steps_per_save = spec["steps"]
    config.vis = "tensorboard"
    config.viewer.quit_on_train_completion = True
    config.output_dir = Path(spec["output_dir"])
    config.experiment_name = spec["name"]
    config.timestamp = "run"
    config.pipeline.data_parallel.reduction = spec["reduction"]
    config.pipeline.data_parallel.step_profile = True
    scale_schedules(config, n)
    return config


def run_dir_of(spec: dict[str, Any]) -> Path:
    return Path(spec["output_dir"]) / spec["name"] / spec["method"] / "run"


# ---------------------------------------------------------------------------------------------------- profiles
def read_profile(run_dir: Path) -> dict[int, tuple[dict[str, Any], list[dict[str, Any]]]]:
    """{global rank: (meta, per-step rows)} of a run's step profile."""
    out = {}
    for meta_path in sorted((run_dir / "step_profile").glob("rank*.json")):
        rows_path = meta_path.with_suffix(".jsonl")
        rows = [json.loads(x) for x in rows_path.read_text().splitlines()] if rows_path.is_file() else []
        out[int(meta_path.stem[4:])] = (json.loads(meta_path.read_text()), rows)
    return out


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


def eval_gpus(visible: str | None, most: int) -> list[str]:
    """The GPUs the evaluations run on, one each: the ones this script was given (CUDA_VISIBLE_DEVICES, as the
    environment says them: another job may train on the host's others), else 0..most-1; at most `most`."""
    given = [g.strip() for g in (visible or "").split(",") if g.strip()]
    return (given or [str(i) for i in range(most)])[:most]


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def estimate_s(run: Run, images: int) -> float:
    """A pessimistic wall time of a run on H100s (start-up ~60 s; 12.5 ms a single-device step at the end of a
    reichstag run; a data-parallel step up to 1.45 times that), to skip what cannot end before the deadline."""
    steps = images / run.total
    return 60.0 + steps * 0.0125 * (1.45 if run.total > 1 else 1.0)


# ---------------------------------------------------------------------------------------------------- reporting
def _f(v: Any, fmt: str) -> str:
    return format(v, fmt) if isinstance(v, (int, float)) else "-"


def tables(results: list[dict[str, Any]]) -> str:
    """The summary printed at the end: runs, steady-state breakdowns, start-up phases, goals."""
    base = next((r for r in results if r["num_devices"] == 1 and r.get("status") == "ok"), None)
    lines = [
        "run                 GPUs  steps  images  status    wall s  x1 wall  step ms  img/s   x1 img/s   PSNR   "
        "SSIM  Gaussians  MB/step"
    ]
    for r in results:
        b = r.get("breakdown") or {}
        step = b.get("iteration")
        ips = r["num_devices"] * 1000.0 / step if step else None
        x_ips = x_wall = None
        if base and base is not r and ips and (base.get("breakdown") or {}).get("iteration"):
            x_ips = ips / (1000.0 / base["breakdown"]["iteration"])
            if r.get("train_wall_s") and base.get("train_wall_s") and r["images"] == base["images"]:
                x_wall = base["train_wall_s"] / r["train_wall_s"]
        mb = b.get("bytes") / 1e6 if b.get("bytes") else None
        lines.append(
            f"{r['name']:<19} {r['num_devices']:>4} {r['steps']:>6} {r['images']:>7}  {r['status']:<8} "
            f"{_f(r.get('train_wall_s'), '7.1f')}  {_f(x_wall, '6.2f')}x  {_f(step, '6.2f')}  {_f(ips, '6.1f')}  "
            f"{_f(x_ips, '7.2f')}x  {_f(r.get('psnr'), '6.2f')} {_f(r.get('ssim'), '6.4f')} "
            f"{_f(b.get('gaussians_end'), '10.0f')}  {_f(mb, '7.1f')}"
        )
    lines += [
        "",
        "steady state (last quarter of the steps), median ms per step; transfer = the quickest rank's time in the "
        "all-reduce, wait = the others' extra time there (mean over ranks; spread = slowest - quickest)",
        "run                 clock   fwd     bwd    pack transfer  wait spread  unpack   opt  callbk   rest   step "
        "host-step reads",
    ]
    for r in results:
        b = r.get("breakdown") or {}
        if not b:
            continue
        lines.append(
            f"{r['name']:<19} {b.get('clock', '-'):<6} {_f(b.get('forward'), '6.2f')} {_f(b.get('backward'), '6.2f')} "
            f"{_f(b.get('pack'), '6.2f')} {_f(b.get('transfer'), '7.2f')} {_f(b.get('wait'), '6.2f')} "
            f"{_f(b.get('wait_spread'), '6.2f')} {_f(b.get('unpack'), '6.2f')} {_f(b.get('optimizer'), '6.2f')} "
            f"{_f(b.get('callbacks'), '6.2f')} {_f(b.get('rest'), '6.2f')} {_f(b.get('iteration'), '6.2f')} "
            f"{_f(b.get('host_iteration'), '8.2f')} {_f(b.get('host_reads'), '5.1f')}"
        )
    phases = ("process_start", "pipeline_init", "scene_inspected", "data_parsed", "inputs_checked", "model_built")
    phases += ("data_parallel_ready",)
    phases += ("images_cache_start", "images_cached", "first_step", "first_step_last_rank", "train_end")
    lines += ["", "start-up, seconds after the launch (rank 0): " + ", ".join(phases) + ", exit"]
    for r in results:
        s = r.get("startup") or {}
        cells = " ".join(_f(s.get(p), "6.1f") for p in phases)
        lines.append(f"{r['name']:<19} {cells} {_f(r.get('train_wall_s'), '6.1f')}")
    if base:
        lines += ["", "goals (equal images seen; steady-state throughput from the step profile):"]
        for r in results:
            if r is base or r.get("status") != "ok" or r["reduction"] != "buffer" or r["machines"] != 1:
                continue
            b, bb = r.get("breakdown") or {}, base.get("breakdown") or {}
            if not (b.get("iteration") and bb.get("iteration")):
                continue
            x_ips = r["num_devices"] * bb["iteration"] / b["iteration"]
            want = {2: 1.8, 4: 3.2}.get(r["num_devices"])
            x_wall = base["train_wall_s"] / r["train_wall_s"] if r["images"] == base["images"] else None
            verdict = "" if want is None else (" met" if x_ips >= want else " NOT met")
            lines.append(
                f"  {r['num_devices']} GPUs: throughput {x_ips:.2f}x (goal >= {want}x:{verdict}), wall "
                f"{_f(x_wall, '.2f')}x at {r['images']} images"
            )
    return "\n".join(lines)


def record(result: dict[str, Any], args: argparse.Namespace) -> dict[str, Any]:
    """A benchmarks/records/benchmarks.json record of one run."""
    b = result.get("breakdown") or {}
    step = b.get("iteration")
    return {
        "scene": Path(args.data).name,
        "method": args.method,
        "device": args.device_type,
        "steps": result["steps"],
        "tag": f"{args.tag}-{result['name']}",
        "group": args.tag,
        "num_devices": result["num_devices"],
        "num_machines": result["machines"],
        "images": result["images"],
        "reduction": result["reduction"],
        "status": result["status"],
        "psnr": result.get("psnr"),
        "ssim": result.get("ssim"),
        "train_wall_s": result.get("train_wall_s"),
        "step_ms": step,
        "images_per_s": result["num_devices"] * 1000.0 / step if step else None,
        "num_gaussians": b.get("gaussians_end"),
        "breakdown_ms": b,
        "startup_s": result.get("startup"),
        "schedule": "default",
        "machine": result.get("machine"),
        "commit": os.environ.get("WILLAGS_COMMIT"),
        "date": time.strftime("%Y-%m-%dT%H:%M:%S"),
        "command": f"python -m benchmarks multi-gpu run --images {args.images} --runs {args.runs} (run {result['name']})",
        "seed": args.seed,
    }


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
    if work.is_dir():  # this script's scratch: an earlier call's runs would end up in this call's archive
        shutil.rmtree(work)
    work.mkdir(parents=True)
    results: list[dict[str, Any]] = []
    python = sys.executable
    for run in parse_runs(args.runs):
        images = run.images or args.images
        res: dict[str, Any] = {
            "name": run.name,
            "num_devices": run.total,
            "machines": run.machines,
            "reduction": run.reduction,
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
            "output_dir": str(work / "runs"),
            "dist_url": f"tcp://127.0.0.1:{_free_port()}" if run.machines > 1 else "auto",
        }
        spec_path = work / f"{run.name}.spec.json"
        spec_path.write_text(json.dumps(spec, indent=1))
        if args.dry_run:
            import willags_ns.method_configs  # noqa: F401  (registers every method's factory)
            from willags_ns.engine.trainer import PRESET_CONFIGS

            schedule = scale_schedules(PRESET_CONFIGS[args.method](), run.total)
            print(f"{run.name}: {run.total} GPUs, {res['steps']} steps, ~{estimate_s(run, images):.0f} s; {schedule}")
            res["status"] = "dry-run"
            continue
        print(f"multi_gpu: train {run.name}: {run.total} GPUs, {res['steps']} steps ({time.time() - t0:.0f} s)")
        procs, t_launch = [], time.time()
        for m in range(run.machines):
            extra = {}
            if run.machines > 1:
                extra["CUDA_VISIBLE_DEVICES"] = ",".join(str(m * run.devices + i) for i in range(run.devices))
            cmd = [python, "-m", "benchmarks.multi_gpu", "train", str(spec_path), "--machine-rank", str(m)]
            procs.append(_start(cmd, work / f"{run.name}.train{m}.log", _env(extra)))
        res["status"] = _wait(procs, deadline - args.eval_reserve_s / 2)
        res["train_wall_s"] = round(time.time() - t_launch, 2)
        run_dir = run_dir_of(spec)
        res["run_dir"] = str(run_dir)
        profile = read_profile(run_dir)
        res["breakdown"] = breakdown(profile)
        res["startup"] = startup(profile, t_launch)
        if profile:
            res["machine"] = f"{run.total}x {profile[min(profile)][0].get('device')}"
        print(f"multi_gpu: {run.name} {res['status']} in {res['train_wall_s']:.1f} s")
        write_results(out, work, results, args)
    # every trained run scored by ns-eval, one per GPU at a time
    todo = [r for r in results if r["status"] == "ok"]
    gpus = eval_gpus(os.environ.get("CUDA_VISIBLE_DEVICES"), args.eval_gpus)
    while todo and time.time() < deadline - 15:
        batch, todo = todo[: len(gpus)], todo[len(gpus) :]
        procs = []
        for gpu, r in zip(gpus, batch, strict=False):  # the last batch may be shorter
            cmd = [python, "-m", "nerfstudio.scripts.eval", "--load-config", str(Path(r["run_dir"]) / "config.yml")]
            cmd += ["--output-path", str(work / f"{r['name']}.eval.json")]
            # ns-eval looks the method up by name in the entry points: pip's, or those remote/env.sh writes on a lent GPU
            env = _env({"CUDA_VISIBLE_DEVICES": gpu})
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


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    sub = parser.add_subparsers(dest="command", required=True)
    run = sub.add_parser("run", help="train, profile and score the runs; write the results under --out")
    run.add_argument("--data", required=True, help="the scene (a COLMAP scene folder, e.g. .gpu-r/reichstag)")
    run.add_argument("--out", required=True, help="where the results go ($OUT on the device machine)")
    run.add_argument("--images", type=int, default=8000, help="images seen by every run (steps = images / GPUs)")
    run.add_argument("--runs", default="4,1,2,4:reference", help="the runs, in order (module docstring)")
    run.add_argument("--method", default="willags")
    run.add_argument("--seed", type=int, default=42)
    run.add_argument("--device-type", default="cuda")
    run.add_argument("--tag", default="multi-gpu", help="records' tag prefix (each run adds its name)")
    run.add_argument("--work", default="/tmp/willags-multi-gpu", help="runs, logs and profiles (emptied first)")
    run.add_argument("--deadline-s", type=float, default=555.0, help="after $MULTI_GPU_T0 (or now)")
    run.add_argument("--eval-reserve-s", type=float, default=70.0, help="kept for the evaluations at the end")
    run.add_argument("--eval-gpus", type=int, default=4, help="evaluations at once, one per GPU")
    run.add_argument("--dry-run", action="store_true", help="print the runs, steps and schedules; train nothing")
    run.set_defaults(func=cmd_run)
    train = sub.add_parser("train", help="(internal) one launch of a run")
    train.add_argument("spec")
    train.add_argument("--machine-rank", type=int, default=0)
    train.set_defaults(func=cmd_train)
    args = parser.parse_args(argv)
    args.func(args)


if __name__ == "__main__":
    main()
