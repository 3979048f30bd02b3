"""Train and score a grid of methods x scenes x step budgets, each run in a child process; merge the records into
benchmarks/records/benchmarks.json and regenerate docs/benchmarks.md.

    python -m benchmarks run --grid configs/benchmark_cpu.json             # --dry-run lists the runs
    python -m benchmarks run --grid configs/benchmark_cpu.json --out /tmp/b   # /tmp/b.json, /tmp/b.md
    python -m benchmarks merge gpu_out/records.json                        # records fetched from a GPU machine
    python -m benchmarks merge queues.tgz --keep benchmarks/records/gpu_runs/NAME.json   # a queues archive

Each run is a subprocess (``python -m benchmarks.child SPEC RESULT``), so peak memory and the global state nerfstudio
keeps belong to that run alone. Records merge into the existing JSON (:mod:`benchmarks.records`) and the markdown is
regenerated after every run, so an interrupted grid keeps what it finished. A grid file (JSON) holds
:data:`GRID_KEYS`, a run (one of its ``runs``) :data:`RUN_KEYS`, which override the grid's::

    {"device": "auto", "steps": [300], "downscale": 2, "protocol_steps": 32, "max_test_images": 4,
     "runs": [{"scene": "../shared/data/fox-wild", "methods": ["willags", "willags-3dgs"], "steps": [150, 300]}]}

``scene`` is ``"default"`` (the embedded synthetic scene), a path (relative to the repository root) or a bare scene
name looked up in ``data_roots``, $WILLAGS_BENCH_DATA, ../shared/data next to the repository and ./data.
``downscale`` > 1 resamples a path scene's images once into a mirror in the cache (:func:`downscaled_scene`).
"""

import argparse
import contextlib
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

from benchmarks.cv import parse_fold
from benchmarks.methods import METHODS
from benchmarks.records import (
    CV_RECORDS,
    RECORDS,
    REPO,
    load_records,
    merge_records,
    merged_records,
    queue_records,
    record_key,
    replaced_across_commits,
    write_records,
)
from benchmarks.tables import write_outputs


def scene_name(scene: str) -> str:
    """The scene as records name it: "default" or the folder's name."""
    return "default" if scene in ("default", "", ".") else Path(scene).name


@dataclasses.dataclass
class RunSpec:
    """One (scene, method, steps) run of a grid; every other field is a key of the grid file (grid or run level)."""

    scene: str
    """"default", a path or a bare name, as the grid writes it."""
    method: str
    steps: int
    tag: str = ""
    downscale: int = 1
    protocol_steps: int = 32
    protocol_lr: float = 0.01
    max_test_images: int = -1
    mask_max_images: int = -1
    fps_views: int = 3
    schedule: str = "short"
    timeout_s: float = 0.0
    seed: int = 42
    oracle: bool = False
    """Also score the right half with the latent fitted on the whole test image (oracle_* keys)."""
    train_views: int = 8
    """Training views scored with their own latents (train_* keys: fitting capacity); 0 = none."""
    concurrent_runs: int | None = None
    """Runs on the GPU at once while this one trained, itself included (benchmarks/remote/grid.sh says); None: not
    recorded."""

    @property
    def scene_name(self) -> str:
        return scene_name(self.scene)


RUN_KEYS = {f.name for f in dataclasses.fields(RunSpec)} - {"method"} | {"methods"}
GRID_KEYS = {f.name: f.default for f in dataclasses.fields(RunSpec)[3:]}
GRID_KEYS.update(steps=[300], tag=None, device="auto", threads=0, data_roots=None, description="", runs=[])
"""Grid-level keys and defaults. threads 0: all cores; timeout_s 0: none; tag None: "ds<k>" when downscaled."""


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
        steps = r.pop("steps") if isinstance(r["steps"], list) else [r.pop("steps")]
        if not steps or any(int(s) < 1 for s in steps):
            raise ValueError(f"runs[{i}]: steps must be positive integers, got {steps}")
        methods = r.pop("methods") if isinstance(r["methods"], list) else [r.pop("methods")]
        for m in methods:
            if m not in METHODS:
                raise ValueError(f"runs[{i}]: unknown method {m!r}; known: {sorted(METHODS)}")
        r["downscale"] = 1 if scene_name(r["scene"]) == "default" else int(r["downscale"] or 1)
        r["tag"] = r["tag"] if r["tag"] is not None else (f"ds{r['downscale']}" if r["downscale"] > 1 else "")
        specs += [RunSpec(method=m, steps=int(s), **r) for m in methods for s in steps]
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


def downscaled_scene(src: Path, factor: int, cache_root: Path | None = None) -> Path:
    """A mirror of scene `src` with `images_<factor>/` beside `images/` (the layout nerfstudio's parsers read
    with ``downscale_factor``). Everything else is symlinked; the source is never written. Images are resampled
    with PIL's box (area) filter to floor(w / factor) x floor(h / factor), nerfstudio's camera rounding."""
    from PIL import Image

    src = Path(src).resolve()
    if factor <= 1:
        return src
    if cache_root is None:
        base = os.environ.get("WILLAGS_CACHE")
        cache_root = (Path(base).expanduser() if base else Path.home() / ".cache" / "willags") / "bench-scenes"
    dst = Path(cache_root) / f"{src.name}-{hashlib.sha256(str(src).encode()).hexdigest()[:8]}-ds{factor}"
    if (dst / MIRROR_MARKER).is_file():
        return dst
    tmp = Path(cache_root) / f".{dst.name}.tmp{os.getpid()}"
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
                small = im.resize((im.width // factor, im.height // factor), resample=Image.Resampling.BOX)
                if f.suffix.lower() in (".jpg", ".jpeg"):
                    small.convert("RGB").save(out / f.name, quality=95, subsampling=0)
                else:
                    small.save(out / f.name)
    (tmp / MIRROR_MARKER).write_text(f"{src} downscaled by {factor}\n")
    if dst.exists():
        shutil.rmtree(dst, ignore_errors=True)
    os.rename(tmp, dst)
    return dst


def machine_description(device: str) -> str:
    import torch

    if device == "cuda":
        return f"{torch.cuda.get_device_name(0)} ({os.cpu_count()} CPU cores)"
    model = platform.processor() or platform.machine()
    with contextlib.suppress(OSError):  # the CPU's name, where Linux says it
        lines = Path("/proc/cpuinfo").read_text().splitlines()
        model = next((ln.split(":", 1)[1].strip() for ln in lines if ln.startswith("model n")), model)
    return f"{os.cpu_count()} CPU cores ({model}), no GPU"


def git_commit(repo: Path = REPO) -> str | None:
    """Short HEAD (+dirty) of the checkout, or $WILLAGS_COMMIT when set: a remote GPU machine may run a copy of the
    working tree whose git metadata is not the source's, so GPU commands pass the commit they were written at."""
    if os.environ.get("WILLAGS_COMMIT"):
        return os.environ["WILLAGS_COMMIT"]
    try:
        git = {"cwd": repo, "capture_output": True, "text": True, "timeout": 10}
        sha = subprocess.run(["git", "rev-parse", "--short", "HEAD"], **git).stdout.strip()
        dirty = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"], **git).stdout.strip()
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
    if data is not None and spec.downscale > 1:
        data = downscaled_scene(data, spec.downscale)
    run_dir = work_root / f"{spec.scene_name}-{spec.method}-{spec.steps}{('-' + spec.tag) if spec.tag else ''}-{device}"
    shutil.rmtree(run_dir, ignore_errors=True)
    run_dir.mkdir(parents=True)
    child_spec = {
        **dataclasses.asdict(spec),
        "scene_name": spec.scene_name,
        "device": device,
        "data": str(data) if data is not None else None,
        "work_dir": str(run_dir / "out"),
        "threads": int(settings.get("threads") or 0),
    }
    spec_path, result_path, log_path = run_dir / "spec.json", run_dir / "result.json", run_dir / "log.txt"
    spec_path.write_text(json.dumps(child_spec, indent=1))
    kept = ("method", "steps", "tag", "downscale", "schedule", "seed", "protocol_steps", "max_test_images")
    rec: dict[str, Any] = {
        **{k: getattr(spec, k) for k in kept},
        "scene": spec.scene_name,
        "device": device,
        "method_note": METHODS[spec.method].note,
        "scene_path": spec.scene,
        "date": _dt.datetime.now().isoformat(timespec="seconds"),
        "command": command,
        "machine": machine,
        "commit": git_commit(),
        "concurrent_runs": spec.concurrent_runs,
    }
    t = time.perf_counter()
    with open(log_path, "w") as logf:
        try:
            cmd = [sys.executable, "-m", "benchmarks.child", str(spec_path), str(result_path)]
            kw = {"cwd": REPO, "env": _child_env(), "stdout": logf, "stderr": subprocess.STDOUT}
            rc = subprocess.run(cmd, timeout=spec.timeout_s or None, **kw).returncode
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
    rec.setdefault("lpips", None)
    if not keep_runs:
        shutil.rmtree(run_dir / "out", ignore_errors=True)
    return rec


def run_grid(
    grid_path: Path,
    out_prefix: Path,
    work_root: Path,
    command: str,
    only_methods: Sequence[str] | None = None,
    only_scenes: Sequence[str] | None = None,
    dry_run: bool = False,
    keep_runs: bool = False,
    overrides: dict[str, Any] | None = None,
    log=print,
) -> list[dict[str, Any]]:
    """Run every spec of the grid (sequentially), merging each record into `<out>.json` as it finishes (a grid cut
    short keeps what it finished). ``command`` is recorded; overrides: RunSpec fields set on every run (e.g. {"tag":
    "r2", "seed": 43} for a repeat)."""
    settings, specs = parse_grid(json.loads(Path(grid_path).read_text()))
    device = resolve_device(settings["device"])
    specs = [s for s in specs if (not only_methods or s.method in only_methods)]
    specs = [s for s in specs if (not only_scenes or s.scene_name in only_scenes)]
    specs = [dataclasses.replace(s, **(overrides or {})) for s in specs]
    for s in [s for s in specs if METHODS[s.method].needs_cuda and device != "cuda"]:
        log(f"skip {s.scene_name}/{s.method}/{s.steps}: needs CUDA (device is {device})")
        specs.remove(s)
    machine = machine_description(device)
    log(f"{len(specs)} runs on {device} ({machine}); records -> {Path(out_prefix).with_suffix('.json')}")
    if dry_run:
        for s in specs:
            log(f"  {s.scene_name:22s} {s.method:16s} steps={s.steps:<6d} tag={s.tag!r} downscale={s.downscale}")
        return []
    if device == "cuda":
        warm_gsplat(log)
    done: list[dict[str, Any]] = []
    t0 = time.perf_counter()
    for i, s in enumerate(specs):
        log(f"[{i + 1}/{len(specs)}] {s.scene_name} {s.method} steps={s.steps} tag={s.tag!r}")
        rec = run_one(s, device, settings, Path(work_root), command, machine, keep_runs, log)
        if rec["status"] == "ok":
            log(f"  psnr {rec.get('psnr', float('nan')):.2f}  train {rec['train_s']:.0f} s  N {rec['num_gaussians']}")
        done.append(rec)
        write_outputs(merge_records(load_records(Path(out_prefix).with_suffix(".json")), [rec]), out_prefix)
    log(f"grid done in {time.perf_counter() - t0:.0f} s")
    return done


def warm_gsplat(log=print) -> None:
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


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--grid", type=Path, help="grid JSON (configs/benchmark_*.json)")
    ap.add_argument(
        "--out",
        type=Path,
        default=RECORDS.with_suffix(""),
        help="writes <out>.json and its markdown (default: the project's records and docs/benchmarks.md)",
    )
    ap.add_argument("--work-dir", type=Path, default=Path("/tmp/willags-bench"), help="per-run folders")
    ap.add_argument("--methods", nargs="*", help="only these methods of the grid")
    ap.add_argument("--scenes", nargs="*", help="only these scenes of the grid (short names: default, fox-wild, ...)")
    ap.add_argument("--dry-run", action="store_true", help="list the runs and exit")
    ap.add_argument("--keep-runs", action="store_true", help="keep each run's checkpoint and config.yml")
    ap.add_argument("--tag", help="override every run's tag (repeats: r1, r2, ...)")
    ap.add_argument("--seed", type=int, help="override every run's seed")
    ap.add_argument("--concurrent", type=int, help="runs on the GPU at once, this one included (recorded)")
    ap.add_argument("--render-only", action="store_true", help="regenerate the markdown from <out>.json and exit")
    ap.add_argument(
        "--merge",
        nargs="*",
        type=Path,
        default=[],
        help="merge these record files into <out>.json; a queues archive (queues.tgz) needs --keep",
    )
    ap.add_argument(
        "--keep",
        type=Path,
        help="with a queues archive in --merge: the file its records are kept in (benchmarks/records/gpu_runs/...)",
    )
    args = ap.parse_args(argv)
    out = args.out if args.out.is_absolute() else Path.cwd() / args.out
    archives = [p for p in args.merge if p.name.endswith((".tgz", ".tar.gz"))]
    if archives:
        if args.keep is None:
            ap.error(f"{archives[0]} is a queues archive: name the file its records are kept in with --keep")
        write_records([r for a in archives for r in queue_records(a)], args.keep)
        print(f"{args.keep}: the records of {', '.join(map(str, archives))}")
        args.merge = [p for p in args.merge if p not in archives] + [args.keep]
    if args.merge or args.render_only:
        old, cv_old, new = load_records(out.with_suffix(".json")), load_records(CV_RECORDS), merged_records(args.merge)
        for was, now in replaced_across_commits(old + cv_old, new):
            print(
                f"benchmarks: {' '.join(map(str, record_key(was)))}: the record of {was['commit']} is replaced by "
                f"{now['commit']}'s (the same scene, method, device, steps and tag); a tag of its own keeps both"
            )
        recs = merge_records(old, new)  # = merged_records([out.json, *args.merge]): a later record wins
        folds = [r for r in recs if parse_fold(str(r.get("scene", ""))) is not None]
        if folds:  # the cross-validation's fold runs go to their own file
            recs = [r for r in recs if parse_fold(str(r.get("scene", ""))) is None]
            write_records(merge_records(cv_old, folds), CV_RECORDS)
            print(f"{len(folds)} fold records -> {CV_RECORDS}")
        j, m = write_outputs(recs, out)
        print(f"{len(recs)} records -> {j}, {m}")
        return 0
    if args.grid is None:
        ap.error("--grid is required (unless --merge or --render-only)")
    given = (("tag", args.tag), ("seed", args.seed), ("concurrent_runs", args.concurrent))
    overrides = {k: v for k, v in given if v is not None}
    command = "python -m benchmarks run " + " ".join(sys.argv[1:] if argv is None else argv)
    run_grid(args.grid, out, args.work_dir, command, args.methods, args.scenes, args.dry_run, args.keep_runs, overrides)
    return 0


if __name__ == "__main__":
    sys.exit(main())
