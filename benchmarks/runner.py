"""The harness's runner: read a grid of methods x scenes x step budgets, run each in a child process, keep the
records.

    python -m benchmarks run --grid configs/benchmark_cpu.json

Each (scene, method, steps) run is a *subprocess* (``python -m benchmarks.harness child SPEC RESULT``, run from the
repository root; its side is :mod:`benchmarks.child`), so peak memory and the global state nerfstudio keeps
(writers, compiled kernels) belong to that run alone. The child trains in-process exactly as ``ns-train`` does
(``config.setup() -> trainer.setup() -> trainer.train()``, vis tensorboard, no viewer, no evaluation during
training), then measures on the test split:

- the NeRF-W protocol (:func:`willags_ns.eval.protocol.evaluate_model`): PSNR / SSIM / LPIPS of the right half
  with the latent fitted on the left half; also ``encoder_*`` (encoder latent, no fit) and ``full_*`` (whole image);
- render FPS: median wall time of ``model.get_outputs`` per test view (eval mode, no grad, one fixed latent);
- number of Gaussians, training wall time (``trainer.train()`` only: data loading is ``setup_s``), peak memory
  (CUDA: ``torch.cuda.max_memory_allocated`` during training; CPU: the child's peak RSS);
- transient-mask scores against ``masks_gt/`` when the scene has one (:mod:`willags_ns.eval.mask_eval`).

The parent merges each result into ``<out>.json`` (records keyed by (scene, method, device, steps, tag); a new
record replaces the old one with the same key, the others are kept; :mod:`benchmarks.records`) and regenerates
``<out>.md`` from the whole file after every run, so an interrupted grid keeps what it finished.

Grid file (JSON)::

    {"device": "auto", "steps": [300], "downscale": 2, "protocol_steps": 32, "max_test_images": 4,
     "schedule": "short", "runs": [{"scene": "../shared/data/fox-wild", "methods": ["willags", "willags-3dgs"],
                                    "steps": [150, 300]}]}

Run-level keys override the grid-level ones. ``scene`` is ``"default"`` (the embedded synthetic scene), a path
(relative to the repository root) or a bare scene name looked up in ``data_roots`` (default: ../shared/data next
to the repository, then ./data). ``downscale`` > 1 applies to path scenes: the images are resampled once into a
mirror of the scene in the cache (``images_<k>/``, the layout nerfstudio's parsers read with ``downscale_factor``).
"""

import dataclasses
import datetime as _dt
import hashlib
import json
import os
import platform
import shutil
import subprocess
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from benchmarks.methods import METHODS
from benchmarks.records import load_records, merge_records
from benchmarks.tables import write_outputs

REPO = Path(__file__).resolve().parents[1]

# ---------------------------------------------------------------------------------------------- grid


GRID_KEYS = {
    "device": "auto",
    "steps": [300],
    "downscale": 1,
    "protocol_steps": 32,
    "protocol_lr": 0.01,
    "max_test_images": -1,
    "mask_max_images": -1,
    "fps_views": 3,
    "schedule": "short",
    "tag": None,
    "seed": 42,
    "oracle": False,
    "train_views": 8,
    "threads": 0,
    "timeout_s": 0,
    "data_roots": None,
    "description": "",
    "runs": [],
}
"""Grid-level keys and defaults. threads 0: all cores; timeout_s 0: none; tag None: "ds<k>" when downscaled."""
RUN_KEYS = {
    "scene",
    "methods",
    "steps",
    "downscale",
    "protocol_steps",
    "protocol_lr",
    "max_test_images",
    "mask_max_images",
    "fps_views",
    "schedule",
    "tag",
    "seed",
    "oracle",
    "train_views",
    "timeout_s",
}


@dataclasses.dataclass
class RunSpec:
    """One (scene, method, steps) run of a grid."""

    scene: str
    """As written in the grid ("default", a path, or a bare name)."""
    scene_name: str
    """Short name used in the records ("default", "fox-wild", ...)."""
    method: str
    steps: int
    tag: str
    downscale: int
    protocol_steps: int
    protocol_lr: float
    max_test_images: int
    mask_max_images: int
    fps_views: int
    schedule: str
    timeout_s: float
    seed: int = 42
    """nerfstudio's machine.seed (repeats use different seeds and tags)."""
    oracle: bool = False
    """Also score the right half with the latent fitted on the whole test image (oracle_* keys)."""
    train_views: int = 8
    """Training views scored with their own latents (train_* keys: fitting capacity); 0 = none."""

    def key(self, device: str) -> tuple:
        return (self.scene_name, self.method, device, self.steps, self.tag)


def scene_name(scene: str) -> str:
    return "default" if scene in ("default", "", ".") else Path(scene).name


def parse_grid(grid: dict[str, Any]) -> tuple[dict[str, Any], list[RunSpec]]:
    """(settings, runs) of a grid dict; unknown keys and unknown methods raise ValueError."""
    unknown = set(grid) - set(GRID_KEYS)
    if unknown:
        raise ValueError(f"unknown grid keys {sorted(unknown)}; known: {sorted(GRID_KEYS)}")
    settings = {k: grid.get(k, v) for k, v in GRID_KEYS.items()}
    if settings["device"] not in ("auto", "cpu", "cuda"):
        raise ValueError(f"device must be auto, cpu or cuda, got {settings['device']!r}")
    if not isinstance(settings["runs"], list) or not settings["runs"]:
        raise ValueError("the grid has no runs")
    specs: list[RunSpec] = []
    for i, run in enumerate(settings["runs"]):
        bad = set(run) - RUN_KEYS
        if bad:
            raise ValueError(f"runs[{i}]: unknown keys {sorted(bad)}; known: {sorted(RUN_KEYS)}")
        if "scene" not in run or "methods" not in run:
            raise ValueError(f"runs[{i}] needs 'scene' and 'methods'")
        r = {k: run.get(k, settings.get(k)) for k in RUN_KEYS}
        steps = r["steps"] if isinstance(r["steps"], list) else [r["steps"]]
        if not steps or any(int(s) < 1 for s in steps):
            raise ValueError(f"runs[{i}]: steps must be positive integers, got {steps}")
        methods = r["methods"] if isinstance(r["methods"], list) else [r["methods"]]
        for m in methods:
            if m not in METHODS:
                raise ValueError(f"runs[{i}]: unknown method {m!r}; known: {sorted(METHODS)}")
        name = scene_name(str(run["scene"]))
        downscale = 1 if name == "default" else int(r["downscale"] or 1)
        tag = r["tag"] if r["tag"] is not None else (f"ds{downscale}" if downscale > 1 else "")
        for m in methods:
            for s in steps:
                specs.append(
                    RunSpec(
                        scene=str(run["scene"]),
                        scene_name=name,
                        method=m,
                        steps=int(s),
                        tag=str(tag),
                        downscale=downscale,
                        protocol_steps=int(r["protocol_steps"]),
                        protocol_lr=float(r["protocol_lr"]),
                        max_test_images=int(r["max_test_images"]),
                        mask_max_images=int(r["mask_max_images"]),
                        fps_views=int(r["fps_views"]),
                        schedule=str(r["schedule"]),
                        timeout_s=float(r["timeout_s"] or 0),
                        seed=int(r["seed"]),
                        oracle=bool(r["oracle"]),
                        train_views=int(r["train_views"]),
                    )
                )
    return settings, specs


def resolve_device(device: str) -> str:
    import torch

    if device == "auto":
        return "cuda" if torch.cuda.is_available() else "cpu"
    if device == "cuda" and not torch.cuda.is_available():
        raise RuntimeError("the grid asks for device cuda but CUDA is not available")
    return device


def resolve_scene(scene: str, data_roots: Sequence[str] | None = None, repo: Path = REPO) -> Path | None:
    """None for the default scene, else the scene directory (relative paths are relative to the repo root)."""
    if scene in ("default", "", "."):
        return None
    p = Path(scene).expanduser()
    candidates = [p] if p.is_absolute() else [repo / p]
    if not p.is_absolute() and len(p.parts) == 1:
        roots = list(data_roots) if data_roots else []
        if os.environ.get("WILLAGS_BENCH_DATA"):
            roots.insert(0, os.environ["WILLAGS_BENCH_DATA"])
        roots += [str(repo.parent / "shared" / "data"), str(repo / "data")]
        candidates += [(Path(r) if Path(r).is_absolute() else repo / r) / p for r in roots]
    for c in candidates:
        if c.is_dir():
            return c.resolve()
    raise FileNotFoundError(f"scene {scene!r} not found (looked in {', '.join(str(c) for c in candidates)})")


IMAGE_SUFFIXES = {".jpg", ".jpeg", ".png", ".JPG", ".JPEG", ".PNG"}
MIRROR_MARKER = ".willags-mirror-complete"


def bench_cache_root() -> Path:
    base = os.environ.get("WILLAGS_CACHE")
    return (Path(base).expanduser() if base else Path.home() / ".cache" / "willags") / "bench-scenes"


def downscaled_scene(src: Path, factor: int, cache_root: Path | None = None) -> Path:
    """A mirror of scene `src` with `images_<factor>/` beside `images/` (the layout nerfstudio's parsers read
    with ``downscale_factor``). Everything else is symlinked; the source is never written. Images are resampled
    with PIL's box (area) filter to floor(w / factor) x floor(h / factor), nerfstudio's camera rounding."""
    from PIL import Image

    src = Path(src).resolve()
    if factor <= 1:
        return src
    root = Path(cache_root) if cache_root is not None else bench_cache_root()
    h = hashlib.sha256(str(src).encode()).hexdigest()[:8]
    dst = root / f"{src.name}-{h}-ds{factor}"
    if (dst / MIRROR_MARKER).is_file():
        return dst
    tmp = root / f".{dst.name}.tmp{os.getpid()}"
    shutil.rmtree(tmp, ignore_errors=True)
    tmp.mkdir(parents=True)
    for entry in src.iterdir():
        (tmp / entry.name).symlink_to(entry)
        if entry.is_dir() and entry.name == "images":
            out = tmp / f"images_{factor}"
            out.mkdir()
            for f in sorted(entry.iterdir()):
                if f.suffix not in IMAGE_SUFFIXES:
                    continue
                im = Image.open(f)
                im.load()
                size = (im.width // factor, im.height // factor)
                small = im.resize(size, resample=Image.Resampling.BOX)
                if f.suffix.lower() in (".jpg", ".jpeg"):
                    small.convert("RGB").save(out / f.name, quality=95, subsampling=0)
                else:
                    small.save(out / f.name)
    (tmp / MIRROR_MARKER).write_text(f"{src} downscaled by {factor}\n")
    if dst.exists():
        shutil.rmtree(dst, ignore_errors=True)
    os.rename(tmp, dst)
    return dst


# ---------------------------------------------------------------------------------------------- parent


def machine_description(device: str) -> str:
    import torch

    if device == "cuda":
        return f"{torch.cuda.get_device_name(0)} ({os.cpu_count()} CPU cores)"
    model = platform.processor() or platform.machine()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                model = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    return f"{os.cpu_count()} CPU cores ({model}), no GPU"


def _git_commit(repo: Path = REPO) -> str | None:
    """Short HEAD (+dirty) of the checkout, or $WILLAGS_COMMIT when set: a remote GPU machine may run a copy of the
    working tree whose git metadata is not the source's (it can report another commit), so GPU commands pass the
    commit they were written at."""
    if os.environ.get("WILLAGS_COMMIT"):
        return os.environ["WILLAGS_COMMIT"]
    try:
        sha = subprocess.run(
            ["git", "rev-parse", "--short", "HEAD"], cwd=repo, capture_output=True, text=True, timeout=10
        ).stdout.strip()
        dirty = subprocess.run(
            ["git", "status", "--porcelain", "--untracked-files=no"],
            cwd=repo,
            capture_output=True,
            text=True,
            timeout=10,
        ).stdout.strip()
        return (sha + ("+dirty" if dirty else "")) or None
    except (OSError, subprocess.SubprocessError):
        return None


def _child_env() -> dict[str, str]:
    env = dict(os.environ)
    env.setdefault("PYTHONWARNINGS", "ignore")
    env["PYTHONPATH"] = str(REPO) + (os.pathsep + env["PYTHONPATH"] if env.get("PYTHONPATH") else "")
    return env


def run_one(
    spec: RunSpec,
    device: str,
    settings: dict[str, Any],
    work_root: Path,
    command: str,
    machine: str,
    keep_runs: bool = False,
    log=print,
) -> dict[str, Any]:
    """Run one spec in a child process; returns its record (status "ok" or "failed: ...")."""
    data = resolve_scene(spec.scene, settings.get("data_roots"))
    downscale = spec.downscale
    if data is not None and downscale > 1:
        data = downscaled_scene(data, downscale)
    run_dir = work_root / f"{spec.scene_name}-{spec.method}-{spec.steps}{('-' + spec.tag) if spec.tag else ''}-{device}"
    shutil.rmtree(run_dir, ignore_errors=True)
    run_dir.mkdir(parents=True)
    child_spec = {
        **dataclasses.asdict(spec),
        "device": device,
        "data": str(data) if data is not None else None,
        "work_dir": str(run_dir / "out"),
        "threads": int(settings.get("threads") or 0),
    }
    spec_path, result_path, log_path = run_dir / "spec.json", run_dir / "result.json", run_dir / "log.txt"
    spec_path.write_text(json.dumps(child_spec, indent=1))
    cmd = [sys.executable, "-m", "benchmarks.harness", "child", str(spec_path), str(result_path)]
    rec: dict[str, Any] = {
        "scene": spec.scene_name,
        "method": spec.method,
        "device": device,
        "steps": spec.steps,
        "tag": spec.tag,
        "downscale": downscale,
        "schedule": spec.schedule,
        "protocol_steps": spec.protocol_steps,
        "max_test_images": spec.max_test_images,
        "seed": spec.seed,
        "method_note": METHODS[spec.method].note,
        "scene_path": spec.scene,
        "date": _dt.datetime.now().isoformat(timespec="seconds"),
        "command": command,
        "machine": machine,
        "commit": _git_commit(),
    }
    t = time.perf_counter()
    timeout = spec.timeout_s or None
    with open(log_path, "w") as logf:
        try:
            proc = subprocess.run(
                cmd, cwd=REPO, env=_child_env(), stdout=logf, stderr=subprocess.STDOUT, timeout=timeout
            )
            rc = proc.returncode
        except subprocess.TimeoutExpired:
            rc = None
    rec["wall_s"] = time.perf_counter() - t
    if rc == 0 and result_path.is_file():
        rec.update(json.loads(result_path.read_text()))
        rec["status"] = "ok"
    else:
        tail = log_path.read_text(errors="replace").strip().splitlines()[-8:]
        reason = "timeout" if rc is None else f"exit {rc}"
        rec["status"] = f"failed ({reason})"
        rec["error_tail"] = tail
        log(f"  FAILED ({reason}); log: {log_path}\n    " + "\n    ".join(tail))
    if rec.get("lpips") is None:
        rec["lpips"] = None
    if not keep_runs:
        shutil.rmtree(run_dir / "out", ignore_errors=True)
    return rec


def run_grid(
    grid_path: Path,
    out_prefix: Path,
    work_root: Path,
    only_methods: Sequence[str] | None = None,
    only_scenes: Sequence[str] | None = None,
    dry_run: bool = False,
    keep_runs: bool = False,
    command: str | None = None,
    log=print,
    stop_after_s: float = 0.0,
    only_steps: Sequence[int] | None = None,
    overrides: dict[str, Any] | None = None,
) -> list[dict[str, Any]]:
    """Run every spec of the grid (sequentially), merging each record into `<out>.json` as it finishes.

    overrides: RunSpec fields set on every run (e.g. {"tag": "r2", "seed": 43} for a repeat).

    stop_after_s > 0: start no new run once that many seconds have passed (for machines lent for a limited time: the
    records of the finished runs are already written; rerun with --methods / --scenes for the rest)."""
    grid = json.loads(Path(grid_path).read_text())
    settings, specs = parse_grid(grid)
    device = resolve_device(settings["device"])
    if only_methods:
        specs = [s for s in specs if s.method in only_methods]
    if only_scenes:
        specs = [s for s in specs if s.scene_name in only_scenes]
    if only_steps:
        specs = [s for s in specs if s.steps in set(int(x) for x in only_steps)]
    if overrides:
        specs = [dataclasses.replace(s, **overrides) for s in specs]
    skipped = [s for s in specs if METHODS[s.method].needs_cuda and device != "cuda"]
    specs = [s for s in specs if s not in skipped]
    for s in skipped:
        log(f"skip {s.scene_name}/{s.method}/{s.steps}: needs CUDA (device is {device})")
    command = command or " ".join(["python"] + [str(a) for a in sys.argv])
    machine = machine_description(device)
    log(f"{len(specs)} runs on {device} ({machine}); records -> {Path(out_prefix).with_suffix('.json')}")
    if dry_run:
        for s in specs:
            log(f"  {s.scene_name:22s} {s.method:16s} steps={s.steps:<6d} tag={s.tag!r} downscale={s.downscale}")
        return []
    if device == "cuda":
        _warm_gsplat(log)
    jpath = Path(out_prefix).with_suffix(".json")
    done: list[dict[str, Any]] = []
    t0 = time.perf_counter()
    for i, s in enumerate(specs):
        if stop_after_s > 0 and time.perf_counter() - t0 > stop_after_s:
            log(f"stop_after_s={stop_after_s:.0f} reached: {len(specs) - i} runs not started")
            break
        log(
            f"[{i + 1}/{len(specs)}] {s.scene_name} {s.method} steps={s.steps} tag={s.tag!r} "
            f"(elapsed {time.perf_counter() - t0:.0f} s)"
        )
        rec = run_one(s, device, settings, Path(work_root), command, machine, keep_runs, log)
        if rec["status"] == "ok":
            log(
                f"  psnr {rec.get('psnr', float('nan')):.2f}  full {rec.get('full_psnr', float('nan')):.2f}  "
                f"train {rec['train_s']:.0f} s  N {rec['num_gaussians']}  fps {rec['fps']:.1f}"
                + (
                    f"  mask IoU {rec['mask_iou']:.2f} FP {rec['mask_fp_rate']:.3f}"
                    if rec.get("mask_iou") is not None
                    else ""
                )
            )
        done.append(rec)
        write_outputs(merge_records(load_records(jpath), [rec]), out_prefix)
    log(f"grid done in {time.perf_counter() - t0:.0f} s")
    return done


def _warm_gsplat(log=print) -> None:
    """Build gsplat's CUDA extension once (JIT, minutes) before any timed run, so no train_s includes it."""
    code = (
        "import torch; from gsplat.rendering import rasterization as r; d='cuda'; "
        "m=torch.zeros(1,3,device=d); m[:,2]=2; q=torch.tensor([[1.,0,0,0]],device=d); s=torch.full((1,3),.1,device=d); "
        "K=torch.tensor([[[10.,0,8],[0,10,8],[0,0,1]]],device=d); r(m,q,s,torch.ones(1,device=d),torch.ones(1,3,device=d),"
        "torch.eye(4,device=d)[None],K,16,16); torch.cuda.synchronize()"
    )
    t = time.perf_counter()
    subprocess.run([sys.executable, "-c", code], cwd=REPO, env=_child_env(), check=False)
    log(f"gsplat warm-up (JIT build if not cached): {time.perf_counter() - t:.0f} s")
