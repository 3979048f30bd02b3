"""Photo-Tourism scale: how start-up, memory, step time, checkpoints, ns-eval and willags-inspect grow with the photos.

    python -m benchmarks scale run --source ../shared/data/reichstag --photos 100 300 1000 --work /tmp/scale
    python -m benchmarks scale run --source synthetic --photos 100 300 --work /tmp/scale    # the built-in scene
    python -m benchmarks scale cache --source ../shared/data/reichstag --photos 1000 --ranks 1 2 4 --work /tmp/scale
    python -m benchmarks scale report                                  # docs/scale.md from the records

``run`` makes, for each N, a PT-like collection of N photos (:func:`make_collection`: one camera per photo, a COLMAP
model and a tsv split) from a source scene's photos copied under their own poses (their own camera, pose, SfM
observations and split; each copy's file differs from the others by a JPEG comment, as no real collection holds the
same file twice), resized to ``--long-side`` px on the long side; ``--source synthetic`` writes the built-in synthetic
scene as such a source first. Then, one after the other and each in its own process:

- ``willags-inspect --data`` (its wall time);
- ``ns-train willags`` for ``--steps`` steps, viewer off, with the step profile (willags_ns/engine/step_profile.py):
  time from the process's start to its first step (and the start-up phases in between), the process's peak host
  memory (its rusage), the GPU's peak (``torch.cuda.max_memory_allocated``, from the profile), the median step early
  (steps 2-6) and late (the last 5 before the final one, which also saves), the Gaussians, the checkpoint's size;
- ``ns-eval`` of that run: wall time, per test photo, and its peak host memory;
- the viewer's start on that run (benchmarks/viewer_start.py: what ``ns-viewer --load-config`` does, timed to its
  scene set up, then stopped): seconds, peak host memory, the frustums it draws of the training cameras.

The device is CUDA when torch sees one, else the CPU. The record goes to
``benchmarks/records/{gpu_runs,cpu_runs}/scale_<source>.json`` (``--out`` to choose), and ``report`` writes
docs/scale.md from every ``scale_*.json`` there: a table per record, a slope per measure (least squares over the
photo counts), the goals met or missed by a number, and docs/scale.png (start-up, host memory, the viewer's start and
the inspection against the photos, a line per record). ``cache`` measures one rank's training-image cache, whole
and sharded over R ranks, on the same collections (benchmarks/rank_cache.py); ``report`` adds those records.
"""

import argparse
import json
import os
import shlex
import shutil
import statistics
import struct
import subprocess
import sys
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from benchmarks import rank_cache
from benchmarks.records import RECORDS_DIR, REPO, json_default, shown_path

LONG_SIDE = 800
"""The long side of a PT collection's photos, px."""
PAGE = REPO / "docs" / "scale.md"
RECORD_GLOB = "scale_*.json"
DEVICES_GLOB = "multi_gpu_*.json"
"""Records of `python -m benchmarks multi-gpu run` on a scale collection (a list of its records, each with
``photos``): the page's section on several GPUs."""
DEVICES_GOAL = {2: 1.8, 4: 3.2}
"""Images per second on N GPUs over one GPU's, at equal images seen."""

# --------------------------------------------------------------------------------------------------- COLMAP model

CAMERA_MODELS = {"SIMPLE_PINHOLE": (0, 3), "PINHOLE": (1, 4), "SIMPLE_RADIAL": (2, 4), "RADIAL": (3, 5)}
CAMERA_MODELS.update({"OPENCV": (4, 8), "OPENCV_FISHEYE": (5, 8), "FULL_OPENCV": (6, 12)})
"""COLMAP camera models a collection is made from: name -> (id, number of parameters)."""
MODEL_NAMES = {mid: name for name, (mid, _) in CAMERA_MODELS.items()}
ONE_FOCAL = ("SIMPLE_PINHOLE", "SIMPLE_RADIAL", "RADIAL")
"""Models whose parameters start f, cx, cy (the others: fx, fy, cx, cy)."""


@dataclass
class View:
    """One photo of a source scene: its file, camera, pose (COLMAP world-to-camera), observations and split."""

    path: Path
    model: str
    width: int
    height: int
    params: np.ndarray
    qvec: np.ndarray
    tvec: np.ndarray
    xys: np.ndarray
    """[n, 2] keypoints that observe a 3D point (px)."""
    point_ids: np.ndarray
    """[n] the 3D point each observes."""
    split: str


@dataclass
class Source:
    """A scene to copy photos from: its views and its 3D points (id -> xyz, rgb, error)."""

    name: str
    views: list[View]
    point_ids: np.ndarray
    xyz: np.ndarray
    rgb: np.ndarray
    error: np.ndarray


def read_source(root: Path) -> Source:
    """The views and points of a COLMAP scene (images/, a model where willags' parser finds one, an optional tsv
    split; without one every 8th photo is a test photo, nerfstudio's rule)."""
    from nerfstudio.data.utils.colmap_parsing_utils import read_model

    from willags_ns.data.dataparser import find_colmap_model, read_split_tsv

    root = Path(root)
    model = find_colmap_model(root)
    if model is None:
        raise SystemExit(f"benchmarks scale: {root} holds no COLMAP model (colmap/sparse/0, sparse/0, ...)")
    ext = ".bin" if (model / "images.bin").is_file() else ".txt"
    cameras, images, points = read_model(str(model), ext)
    tsvs = sorted(root.glob("*.tsv"))
    table = read_split_tsv(tsvs[0]) if tsvs else {}
    views = []
    for k, im in enumerate(sorted(images.values(), key=lambda im: im.name)):
        cam = cameras[im.camera_id]
        if cam.model not in CAMERA_MODELS:
            raise SystemExit(f"benchmarks scale: {im.name}'s camera model {cam.model} is not supported")
        keep = im.point3D_ids >= 0
        path = root / "images" / im.name
        if not path.is_file():
            continue
        split = table.get(im.name, "test" if k % 8 == 0 else "train") if table else ("test" if k % 8 == 0 else "train")
        views.append(
            View(path, cam.model, cam.width, cam.height, np.asarray(cam.params, float), np.asarray(im.qvec, float),
                 np.asarray(im.tvec, float), np.asarray(im.xys, float)[keep], np.asarray(im.point3D_ids)[keep], split)
        )  # fmt: skip
    ids = np.array(sorted(points), dtype=np.int64)
    return Source(
        name=root.name,
        views=views,
        point_ids=ids,
        xyz=np.array([points[i].xyz for i in ids], float).reshape(-1, 3),
        rgb=np.array([points[i].rgb for i in ids], np.uint8).reshape(-1, 3),
        error=np.array([points[i].error for i in ids], float),
    )


def write_colmap(model: Path, cameras: list[tuple], images: list[tuple], source: Source, tracks: dict) -> None:
    """COLMAP binary model files: ``cameras`` [(id, model, w, h, params)], ``images`` [(id, qvec, tvec, camera id,
    name, xys, point ids)], the source's points with ``tracks`` (point id -> [(image id, point2D index)])."""
    model.mkdir(parents=True, exist_ok=True)
    with open(model / "cameras.bin", "wb") as f:
        f.write(struct.pack("<Q", len(cameras)))
        for cid, name, w, h, params in cameras:
            f.write(struct.pack("<iiQQ", cid, CAMERA_MODELS[name][0], w, h) + np.asarray(params, "<f8").tobytes())
    with open(model / "images.bin", "wb") as f:
        f.write(struct.pack("<Q", len(images)))
        for iid, qvec, tvec, cid, name, xys, pids in images:
            f.write(struct.pack("<i", iid) + np.asarray(qvec, "<f8").tobytes() + np.asarray(tvec, "<f8").tobytes())
            f.write(struct.pack("<i", cid) + name.encode() + b"\0" + struct.pack("<Q", len(pids)))
            rows = np.zeros(len(pids), dtype=[("x", "<f8"), ("y", "<f8"), ("p", "<i8")])
            rows["x"], rows["y"], rows["p"] = xys[:, 0], xys[:, 1], pids
            f.write(rows.tobytes())
    with open(model / "points3D.bin", "wb") as f:
        f.write(struct.pack("<Q", len(source.point_ids)))
        for k, pid in enumerate(source.point_ids.tolist()):
            track = np.asarray(tracks.get(pid, ()), "<i4").reshape(-1, 2)
            f.write(struct.pack("<Q", pid) + source.xyz[k].astype("<f8").tobytes() + source.rgb[k].tobytes())
            f.write(struct.pack("<dQ", source.error[k], len(track)) + track.tobytes())


# --------------------------------------------------------------------------------------------------- collections


def jpeg_with_comment(data: bytes, comment: str) -> bytes:
    """A JPEG's bytes with a comment segment after its start marker: the same pixels, another file."""
    if data[:2] != b"\xff\xd8":
        raise ValueError("not a JPEG")
    text = comment.encode()
    return data[:2] + b"\xff\xfe" + struct.pack(">H", len(text) + 2) + text + data[2:]


def base_jpeg(view: View, long_side: int) -> tuple[bytes, float]:
    """A view's photo as JPEG bytes with ``long_side`` px on its long side, and the scale applied: the file as it is
    when it already is such a JPEG."""
    from PIL import Image

    scale = long_side / max(view.width, view.height)
    data = view.path.read_bytes()
    if abs(scale - 1.0) < 1e-9 and data[:2] == b"\xff\xd8":
        return data, 1.0
    import io

    with Image.open(view.path) as im:
        im = im.convert("RGB")
        if abs(scale - 1.0) >= 1e-9:
            im = im.resize((round(view.width * scale), round(view.height * scale)), Image.LANCZOS)
        out = io.BytesIO()
        im.save(out, format="JPEG", quality=95)
    return out.getvalue(), scale


def scaled_camera(view: View, scale: float) -> tuple[int, int, np.ndarray]:
    """(width, height, params) of a view's camera for its photo resized by ``scale`` (focal lengths and principal
    point scale; distortion does not)."""
    params = view.params.copy()
    n = 3 if view.model in ONE_FOCAL else 4
    params[:n] *= scale
    return round(view.width * scale), round(view.height * scale), params


def make_collection(source: Source, photos: int, dst: Path, long_side: int = LONG_SIDE) -> Path:
    """A PT-like collection of ``photos`` photos in ``dst``: the source's photos in turn (copy k of photo i is named
    ``c<k>_<name>``) under their own camera (one per photo), pose, observations and split, ``long_side`` px on the
    long side, each file distinct; ``images/``, ``colmap/sparse/0`` and ``<dst name>.tsv``. Written into a temporary
    sibling and renamed, so ``dst`` is complete or absent."""
    dst = Path(dst)
    if (dst / "images").is_dir():
        return dst
    if not source.views:
        raise SystemExit(f"benchmarks scale: the source {source.name} has no photos")
    tmp = dst.with_name(f".{dst.name}.tmp")
    shutil.rmtree(tmp, ignore_errors=True)
    (tmp / "images").mkdir(parents=True)
    bases = [base_jpeg(v, long_side) for v in source.views]
    cameras, images, rows = [], [], ["filename\tid\tsplit\tdataset"]
    tracks: dict[int, list] = {}
    for i in range(photos):
        k, view = divmod(i, len(source.views))[0], source.views[i % len(source.views)]
        data, scale = bases[i % len(source.views)]
        name = f"c{k:03d}_{view.path.stem}.jpg"
        (tmp / "images" / name).write_bytes(jpeg_with_comment(data, f"willags scale copy {k} of {view.path.name}"))
        w, h, params = scaled_camera(view, scale)
        cameras.append((i + 1, view.model, w, h, params))
        images.append((i + 1, view.qvec, view.tvec, i + 1, name, view.xys * scale, view.point_ids))
        for j, pid in enumerate(view.point_ids.tolist()):
            tracks.setdefault(pid, []).append((i + 1, j))
        rows.append(f"{name}\t{i + 1}\t{view.split}\t{dst.name}")
    write_colmap(tmp / "colmap" / "sparse" / "0", cameras, images, source, tracks)
    (tmp / f"{dst.name}.tsv").write_text("\n".join(rows) + "\n")
    shutil.rmtree(dst, ignore_errors=True)
    os.rename(tmp, dst)
    return dst


def synthetic_source(
    dst: Path, views: int = 40, long_side: int = LONG_SIDE, points: int = 8000, unique_texture: float = 0.8
) -> Path:
    """The built-in synthetic scene (willags_ns/data/synthetic.py: appearance changes and transients) written as a
    COLMAP source of ``views`` photos (every 8th a test photo) at ``long_side`` x 3/4 px: JPEG photos, one pinhole
    camera each, its seed points as the 3D points, each observed where it projects into a photo.

    ``unique_texture`` (the scene config's field) overlays a non-repeating pattern on every surface, so that SfM run on
    these photos (willags-process) can place them against their true poses; 0 gives the plain scene, whose repeated
    textures make SIFT match the wrong copies."""
    from PIL import Image

    from willags_ns.data.synthetic import SyntheticSceneConfig, make_scene, project

    dst = Path(dst)
    if (dst / "images").is_dir():
        return dst
    num_test = max(1, views // 8)
    cfg = SyntheticSceneConfig(num_train=views - num_test, num_test=num_test, width=long_side,
                               height=max(1, long_side * 3 // 4), num_points=points, supersample=1,
                               unique_texture=unique_texture)  # fmt: skip
    scene = make_scene(cfg)
    tmp = dst.with_name(f".{dst.name}.tmp")
    shutil.rmtree(tmp, ignore_errors=True)
    (tmp / "images").mkdir(parents=True)
    h, w = scene.images.shape[1:3]
    fx, fy, cx, cy = scene.K[0, 0], scene.K[1, 1], scene.K[0, 2], scene.K[1, 2]
    flip = np.diag([1.0, -1.0, -1.0])  # nerfstudio's camera axes (OpenGL) -> COLMAP's (OpenCV)
    cameras, images, rows = [], [], ["filename\tid\tsplit\tdataset"]
    tracks: dict[int, list] = {}
    ids = np.arange(1, len(scene.points) + 1, dtype=np.int64)
    for i, name in enumerate(scene.filenames):
        jpg = f"{Path(name).stem}.jpg"
        Image.fromarray(scene.images[i]).save(tmp / "images" / jpg, format="JPEG", quality=95)
        c2w = np.asarray(scene.c2w[i], float)[:3, :4]
        R = c2w[:3, :3] @ flip
        w2c_r, w2c_t = R.T, -R.T @ c2w[:3, 3]
        uv, depth = project(scene.points, scene.c2w[i], scene.K)
        seen = (depth > 0) & (uv[:, 0] >= 0) & (uv[:, 0] < w) & (uv[:, 1] >= 0) & (uv[:, 1] < h)
        cameras.append((i + 1, "PINHOLE", w, h, np.array([fx, fy, cx, cy])))
        images.append((i + 1, rotmat_to_qvec(w2c_r), w2c_t, i + 1, jpg, uv[seen], ids[seen]))
        for j, pid in enumerate(ids[seen].tolist()):
            tracks.setdefault(pid, []).append((i + 1, j))
        rows.append(f"{jpg}\t{i + 1}\t{scene.split[i]}\tsynthetic")
    src = Source("synthetic", [], ids, np.asarray(scene.points, float), np.asarray(scene.colors, np.uint8),
                 np.full(len(ids), 0.5))  # fmt: skip
    write_colmap(tmp / "colmap" / "sparse" / "0", cameras, images, src, tracks)
    (tmp / "synthetic.tsv").write_text("\n".join(rows) + "\n")
    shutil.rmtree(dst, ignore_errors=True)
    os.rename(tmp, dst)
    return dst


def rotmat_to_qvec(R: np.ndarray) -> np.ndarray:
    """COLMAP's quaternion (w, x, y, z) of a rotation matrix."""
    from nerfstudio.data.utils.colmap_parsing_utils import rotmat2qvec

    return np.asarray(rotmat2qvec(R), float)


# --------------------------------------------------------------------------------------------------- measurements


def console_script(name: str) -> str:
    """A console script of this interpreter's environment (ns-train, ns-eval, willags-inspect): beside the
    interpreter in a venv, else ``name`` for PATH to find (an install into a --target folder, as on the GPU machines,
    puts its scripts apart from the interpreter)."""
    path = Path(sys.executable).with_name(name)
    return str(path) if path.exists() else name


def run_process(cmd: list[str], log: Path, marker: str | None = None, cwd: Path | None = None) -> dict[str, Any]:
    """Run ``cmd`` (in ``cwd``) to its end with its output in ``log``: exit code, wall time, the process's peak
    resident memory (its own rusage: ru_maxrss) and, with ``marker``, the seconds until a line starting with it was
    printed."""
    log.parent.mkdir(parents=True, exist_ok=True)
    start = time.perf_counter()
    seen = None
    with open(log, "w") as out:
        env = {**os.environ, "PYTHONUNBUFFERED": "1"}  # each line as printed: the marker's time is when it came
        proc = subprocess.Popen(
            cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, errors="replace", env=env, cwd=cwd
        )
        assert proc.stdout is not None
        for line in proc.stdout:
            out.write(line)
            out.flush()  # the log follows the process (a long ns-eval shows its progress there)
            if marker is not None and seen is None and line.startswith(marker):
                seen = round(time.perf_counter() - start, 2)
        _, status, usage = os.wait4(proc.pid, 0)
    proc.returncode = os.waitstatus_to_exitcode(status)
    return {
        "rc": proc.returncode,
        "wall_s": round(time.perf_counter() - start, 2),
        "peak_host_gb": round(usage.ru_maxrss * 1024 / 2**30, 3),
        "marker_s": seen,
    }


EVAL_MARKER = "ns-eval: NeRF-W protocol on"
"""The line ns-eval prints once the model and the test photos are loaded, before it scores the first."""


def _median(values: Sequence[float]) -> float | None:
    return round(statistics.median(values), 4) if values else None


def profile_measures(run_dir: Path) -> dict[str, Any]:
    """What the step profile of a finished run says: seconds from the process's start to each start-up phase and to
    the first step, the median step early (steps 2-6) and late (the last 5 before the final one, which also saves), the
    Gaussians at the end, the device's peak memory."""
    from willags_ns.engine.step_profile import read_step_profile

    meta, rows = read_step_profile(run_dir)[0]
    phases = meta.get("phases", {})
    t0 = phases.get("process_start")
    since = {
        k: round(v - t0, 2) for k, v in phases.items() if t0 is not None and v is not None and k != "process_start"
    }
    steps = [r["h_iteration"] / 1000.0 for r in rows if "h_iteration" in r]
    device_peak = meta.get("peak_device_bytes")
    return {
        "first_step_s": since.get("first_step"),
        "phases_s": since,
        "step_s_early": _median(steps[1:6]),
        "step_s_late": _median(steps[-6:-1] if len(steps) > 6 else steps[1:]),
        "step_s_fastest": round(min(steps[1:] or steps), 4) if steps else None,
        "steps_timed": len(steps),
        "gaussians": rows[-1].get("gaussians") if rows else None,
        "peak_gpu_gb": round(device_peak / 2**30, 3) if device_peak is not None else None,
        "device_name": meta.get("device"),
    }


def split_counts(collection: Path) -> tuple[int, int]:
    """(training photos, test photos) of a collection's tsv."""
    from willags_ns.data.dataparser import read_split_tsv

    table = read_split_tsv(next(collection.glob("*.tsv")))
    test = sum(1 for s in table.values() if s == "test")
    return len(table) - test, test


def measure(collection: Path, out: Path, args: argparse.Namespace) -> dict[str, Any]:
    """willags-inspect, ns-train and ns-eval of one collection, one after the other (see the module docstring)."""
    train_photos, test_photos = split_counts(collection)
    rec: dict[str, Any] = {"photos": train_photos + test_photos, "train_photos": train_photos}
    rec["test_photos"] = test_photos
    rec["load_average"] = round(os.getloadavg()[0], 2)  # how busy the machine was as the measurements began
    inspect = run_process([console_script("willags-inspect"), "--data", str(collection), "--output", str(out / "inspect.json")],
                          out / "inspect.log")  # fmt: skip
    rec["inspect_s"], rec["inspect_rc"] = inspect["wall_s"], inspect["rc"]
    name = f"n{rec['photos']}"
    train_cmd = [console_script("ns-train"), args.method, "--data", str(collection), "--output-dir", str(out / "runs")]
    train_cmd += ["--experiment-name", "scale", "--timestamp", name, "--vis", "tensorboard", "--machine.seed", "42"]
    train_cmd += ["--max-num-iterations", str(args.steps), "--steps-per-save", str(args.steps)]
    train_cmd += ["--save-every-minutes", "0", "--pipeline.data-parallel.step-profile", "True"]
    train_cmd += ["--pipeline.eval-protocol.steps", str(args.eval_steps), *args.train_args]
    train = run_process(train_cmd, out / "train.log")
    rec.update(train_rc=train["rc"], train_wall_s=train["wall_s"], peak_host_gb=train["peak_host_gb"])
    run_dir = out / "runs" / "scale" / args.method / name
    if train["rc"] != 0 or not (run_dir / "step_profile" / "rank0.json").is_file():
        rec["error"] = (out / "train.log").read_text()[-2000:]
        return rec
    rec.update(profile_measures(run_dir))
    ckpts = sorted((run_dir / "nerfstudio_models").glob("step-*.ckpt"))
    rec["checkpoint_mb"] = round(ckpts[-1].stat().st_size / 2**20, 2) if ckpts else None
    if args.eval:
        ev = run_process([console_script("ns-eval"), "--load-config", str(run_dir / "config.yml"), "--output-path",
                          str(out / "eval.json")], out / "eval.log", marker=EVAL_MARKER)  # fmt: skip
        rec.update(eval_rc=ev["rc"], eval_s=ev["wall_s"], eval_peak_host_gb=ev["peak_host_gb"])
        rec["eval_startup_s"] = ev["marker_s"]
        if ev["rc"] == 0:
            scored = int(json.loads((out / "eval.json").read_text())["results"].get("num_images", test_photos))
            rec["eval_photos"] = scored
            scoring = ev["wall_s"] - (ev["marker_s"] or 0.0)
            rec["eval_s_per_test_photo"] = round(scoring / max(1, scored), 3)
    rec.update(viewer_measures(run_dir / "config.yml", out / "viewer.log"))
    return rec


def viewer_measures(config: Path, log: Path) -> dict[str, Any]:
    """The viewer's start on a trained run (benchmarks/viewer_start.py, in its own process): seconds until its scene
    is set up, its peak host memory, the training cameras and the frustums it draws of them."""
    cmd = [sys.executable, "-m", "benchmarks.viewer_start", str(config)]
    run = run_process(cmd, log, cwd=REPO)
    out: dict[str, Any] = {"viewer_rc": run["rc"], "viewer_peak_host_gb": run["peak_host_gb"]}
    for line in reversed(log.read_text().splitlines()):
        if line.startswith("{"):
            out.update(json.loads(line))
            break
    return out


def machine() -> dict[str, Any]:
    """The device (CUDA when torch sees one), its name, the host's cores and memory."""
    import torch

    cuda = torch.cuda.is_available()
    mem = None
    try:
        line = next(x for x in Path("/proc/meminfo").read_text().splitlines() if x.startswith("MemTotal:"))
        mem = round(int(line.split()[1]) * 1024 / 2**30, 1)
    except (OSError, StopIteration):
        pass
    return {
        "device": "cuda" if cuda else "cpu",
        "device_name": torch.cuda.get_device_name(0) if cuda else "cpu",
        "gpu_memory_gb": round(torch.cuda.get_device_properties(0).total_memory / 2**30, 1) if cuda else None,
        "cpu_count": os.cpu_count(),
        "host_memory_gb": mem,
    }


def default_record(source: str, device: str) -> Path:
    """benchmarks/records/{gpu_runs,cpu_runs}/scale_<source>.json."""
    return RECORDS_DIR / ("gpu_runs" if device == "cuda" else "cpu_runs") / f"scale_{source}.json"


def run(args: argparse.Namespace) -> int:
    from benchmarks.grid import git_commit

    work = Path(args.work)
    if args.source == "synthetic":
        source_dir = synthetic_source(work / "source-synthetic", views=args.synthetic_views, long_side=args.long_side,
                                      unique_texture=args.synthetic_unique_texture)  # fmt: skip
        name = "synthetic"
    else:
        source_dir, name = Path(args.source), Path(args.source).name
    source = read_source(source_dir)
    env = machine()
    path = Path(args.out) if args.out else default_record(name, env["device"])
    old = json.loads(path.read_text()) if path.is_file() else {}
    runs = {int(r["photos"]): r for r in old.get("runs", [])}
    for n in args.photos:
        collection = make_collection(source, n, work / "collections" / f"{name}-{n}", args.long_side)
        print(f"benchmarks scale: {n} photos ({collection}) ...", flush=True)
        rec = measure(collection, work / "runs" / f"{name}-{n}", args)
        rec["commit"] = git_commit()
        runs[rec["photos"]] = rec
        print(json.dumps({k: v for k, v in rec.items() if k != "error"}, default=json_default), flush=True)
        record = {
            "what": f"Photo-Tourism scale on {name}'s photos copied under their own poses (benchmarks/scale.py): "
            f"{args.method}, {args.steps} training steps, ns-eval with {args.eval_steps} protocol steps per test photo",
            "machine": {**env, "note": args.note},
            "source": name,
            "title": args.title or old.get("title", ""),
            "long_side": args.long_side,
            "method": args.method,
            "steps": args.steps,
            "eval_protocol_steps": args.eval_steps,
            "train_args": list(args.train_args),
            "runs": [runs[k] for k in sorted(runs)],
        }
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(json.dumps(record, indent=1, default=json_default) + "\n")
    print(f"benchmarks scale: record {path}")
    return 0


# --------------------------------------------------------------------------------------------------- the page

MEASURES = (
    ("first_step_s", "first step s", ".1f", 1000.0, "ms"),
    ("peak_host_gb", "host peak GB", ".2f", 1024.0, "MB"),
    ("peak_gpu_gb", "GPU peak GB", ".2f", 1024.0, "MB"),
    ("step_s_early", "step s early", ".3f", 1000.0, "ms"),
    ("step_s_late", "step s late", ".3f", 1000.0, "ms"),
    ("step_s_fastest", "fastest step s", ".3f", 1000.0, "ms"),
    ("gaussians", "Gaussians", ",.0f", 1.0, ""),
    ("checkpoint_mb", "checkpoint MB", ".1f", 1.0, "MB"),
    ("eval_startup_s", "ns-eval start s", ".1f", 1000.0, "ms"),
    ("eval_s_per_test_photo", "ns-eval s / test photo", ".2f", 1000.0, "ms"),
    ("eval_peak_host_gb", "ns-eval host peak GB", ".2f", 1024.0, "MB"),
    ("inspect_s", "willags-inspect s", ".1f", 1000.0, "ms"),
    ("viewer_ready_s", "viewer ready s", ".1f", 1000.0, "ms"),
    ("viewer_peak_host_gb", "viewer host peak GB", ".2f", 1024.0, "MB"),
)
"""(field, column, format, factor to the slope's unit, the slope's unit per photo)."""


def slope(xs: Sequence[float], ys: Sequence[float]) -> float | None:
    """Least-squares slope of ys over xs (None with fewer than two distinct xs)."""
    pairs = [(float(x), float(y)) for x, y in zip(xs, ys, strict=True) if y is not None]
    if len({x for x, _ in pairs}) < 2:
        return None
    mx = sum(x for x, _ in pairs) / len(pairs)
    my = sum(y for _, y in pairs) / len(pairs)
    return sum((x - mx) * (y - my) for x, y in pairs) / sum((x - mx) ** 2 for x, _ in pairs)


def _cell(value: Any, fmt: str) -> str:
    return "–" if value is None else format(value, fmt)


def completed_runs(record: dict[str, Any]) -> list[dict[str, Any]]:
    """The record's runs that reached their first training step (a failed run keeps its row, not its measures)."""
    return [r for r in record["runs"] if r.get("first_step_s") is not None]


def table(record: dict[str, Any]) -> list[str]:
    """The record's runs, one row per photo count, and a row of slopes per photo (least squares over the runs)."""
    from benchmarks.tables import md_table

    runs = completed_runs(record)
    shown = [m for m in MEASURES if any(r.get(m[0]) is not None for r in record["runs"])]
    head = ["photos (train / test)", *(m[1] for m in shown)]
    rows = []
    for r in record["runs"]:
        cells = [f"{r['photos']:,} ({r['train_photos']:,} / {r['test_photos']:,})"]
        if r.get("first_step_s") is None:
            rows.append(cells + [f"failed (exit {r.get('train_rc')})"] + ["–"] * (len(shown) - 1))
            continue
        rows.append(cells + [_cell(r.get(field), fmt) for field, _, fmt, _, _ in shown])
    slopes = ["slope per photo"]
    for field, _, _, factor, unit in shown:
        s = slope([r["photos"] for r in runs], [r.get(field) for r in runs])
        slopes.append("–" if s is None else f"{s * factor:.3g} {unit}/photo" if unit else f"{s * factor:.3g}/photo")
    return md_table(head, rows + [slopes])


PHASES = (
    ("pipeline_init", "imports and set-up"),
    ("scene_inspected", "scene inspected"),
    ("data_parsed", "data parsed"),
    ("inputs_checked", "inputs checked"),
    ("model_built", "model built"),
    ("images_cached", "images cached"),
)
"""The start-up phases of the step profile, in order: each is timed from the one before (the first from the process's
start)."""


def phase_table(record: dict[str, Any]) -> list[str]:
    """Where the time to the first step goes: seconds of each start-up phase per run, and a slope per photo."""
    from benchmarks.tables import md_table

    runs = [r for r in record["runs"] if r.get("phases_s")]
    if not runs:
        return []

    def durations(r: dict[str, Any]) -> list[float | None]:
        at, prev, out = r["phases_s"], 0.0, []
        for key, _ in PHASES:
            if at.get(key) is None:
                out.append(None)
                continue
            out.append(round(at[key] - prev, 2))
            prev = at[key]
        return out

    rows = [[f"{r['photos']:,}", *(_cell(d, ".1f") for d in durations(r))] for r in runs]
    cols = list(zip(*(durations(r) for r in runs), strict=True))
    slopes = [slope([r["photos"] for r in runs], list(c)) for c in cols]
    rows.append(["slope per photo", *("–" if v is None else f"{v * 1000:.3g} ms/photo" for v in slopes)])
    return md_table(["photos", *(f"{name} s" for _, name in PHASES)], rows)


def cpu_goal(record: dict[str, Any]) -> list[str]:
    """On the CPU: 1,000 photos at 800 px start training without running out of memory."""
    host = record["machine"].get("host_memory_gb")
    big = [r for r in record["runs"] if r["photos"] >= 1000]
    if not big or record.get("long_side", 0) < LONG_SIDE:
        return ["- 1,000 photos at 800 px start training without running out of memory: not measured"]
    r = max(big, key=lambda r: r["photos"])
    if r.get("first_step_s") is None:
        return [f"- 1,000 photos at 800 px start training without running out of memory: **missed** ({r['photos']:,} "
                f"photos: training failed, exit {r.get('train_rc')})"]  # fmt: skip
    spare = f", {host - r['peak_host_gb']:.1f} GB to spare" if host else ""
    return [f"- 1,000 photos at 800 px start training without running out of memory: **met** ({r['photos']:,} photos: "
            f"first step after {r['first_step_s']:.0f} s, host peak {r['peak_host_gb']:.2f} GB of "
            f"{host if host else '?'} GB{spare})"]  # fmt: skip


def gpu_goals(record: dict[str, Any]) -> list[str]:
    """On the GPU: 2,000 photos within 24 GB GPU and 16 GB host memory; the late step within 10 % of the 100-photo
    run's; time to the first step under 60 s + 20 ms a photo; ns-eval linear in the test photos."""
    from willags_ns.splats.mcmc import McmcConfig

    runs = completed_runs(record)
    out = []
    big = [r for r in record["runs"] if r["photos"] >= 2000]
    if not big:
        out.append("- 2,000 photos within 24 GB GPU / 16 GB host memory: not measured")
    else:
        r = max(big, key=lambda r: r["photos"])
        ok = r.get("first_step_s") is not None and r.get("peak_gpu_gb", 99) <= 24 and r["peak_host_gb"] <= 16
        grown = (r.get("gaussians") or 0) >= McmcConfig().cap_max
        what = "the model at MCMC's cap" if grown else "the photos' share of memory, not a model grown to its cap"
        out.append(f"- 2,000 photos within 24 GB GPU / 16 GB host memory: **{'met' if ok else 'missed'}** at "
                   f"{record.get('steps', '?')} steps ({r['photos']:,} photos: GPU {_cell(r.get('peak_gpu_gb'), '.2f')} "
                   f"GB, host {r['peak_host_gb']:.2f} GB, {r.get('gaussians') or 0:,} Gaussians: {what})")  # fmt: skip
    small = [r for r in runs if r["photos"] <= 100 and r.get("step_s_late")]
    if small and len(runs) > 1:
        base = max(small, key=lambda r: r["photos"])
        worst = max((r for r in runs if r.get("step_s_late")), key=lambda r: r["step_s_late"] / base["step_s_late"])
        ratio = worst["step_s_late"] / base["step_s_late"] - 1
        out.append(f"- step within 10 % of the 100-photo step: **{'met' if ratio <= 0.10 else 'missed'}** (worst "
                   f"{ratio:+.0%} at {worst['photos']:,} photos: {worst['step_s_late']:.3f} s against "
                   f"{base['step_s_late']:.3f} s)")  # fmt: skip
    else:
        out.append("- step within 10 % of the 100-photo step: not measured")
    if runs:
        over = [(r["first_step_s"] - (60 + 0.02 * r["photos"]), r) for r in runs]
        margin, r = max(over, key=lambda t: t[0])
        out.append(f"- time to the first step < 60 s + 20 ms/photo: **{'met' if margin < 0 else 'missed'}** (worst: "
                   f"{r['first_step_s']:.1f} s at {r['photos']:,} photos, bound {60 + 0.02 * r['photos']:.1f} s)")  # fmt: skip
    out.append(eval_linearity_goal(runs))
    return out


def eval_linearity_goal(runs: list[dict[str, Any]]) -> str:
    """ns-eval linear in the test photos: the seconds each further test photo costs between runs that scored
    different numbers of them (at least three such runs), their largest over their smallest within 1.25."""
    by_count = {r["eval_photos"]: r for r in runs if r.get("eval_photos")}  # distinct counts of scored photos
    evals = [by_count[k] for k in sorted(by_count)]
    if len(evals) < 3:
        return ("- ns-eval linear in the test photos: not measured (fewer than three runs scoring different numbers "
                "of test photos)")  # fmt: skip
    marginal = [(b["eval_s"] - a["eval_s"]) / max(1, b["eval_photos"] - a["eval_photos"]) for a, b in
                zip(evals, evals[1:], strict=False)]  # fmt: skip
    spread = max(marginal) / min(marginal) if min(marginal) > 0 else float("inf")
    return (f"- ns-eval linear in the test photos: **{'met' if spread <= 1.25 else 'missed'}** (seconds per further "
            f"test photo between successive runs: {', '.join(f'{m:.2f}' for m in marginal)}; largest over smallest "
            f"{spread:.2f}, linear within 1.25)")  # fmt: skip


PLOTTED = (
    ("first_step_s", "time to the first step (s)"),
    ("peak_host_gb", "host peak memory (GB)"),
    ("viewer_ready_s", "viewer ready (s)"),
    ("inspect_s", "willags-inspect (s)"),
)
"""The measures the page's plot draws against the photos, one panel each."""


def record_label(rec: dict[str, Any]) -> str:
    """A record's name, "<source>, CPU" or "<source>, <GPU name>" and its title if it has one: its heading on the
    page, its line in the plot."""
    m = rec["machine"]
    title = f" ({rec['title']})" if rec.get("title") else ""
    return f"{rec['source']}, {m['device_name'] if m['device'] == 'cuda' else 'CPU'}{title}"


def plot_records(records: list[tuple[Path, dict[str, Any]]], path: Path) -> Path | None:
    """The page's plot: each measure of PLOTTED against the photos (log axis), a line per record. None when no
    record has a measure at two photo counts (nothing to draw a line through)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    def series(rec: dict[str, Any], key: str) -> tuple[list[int], list[float]]:
        pts = sorted((r["photos"], r[key]) for r in rec["runs"] if r.get(key) is not None)
        return [p for p, _ in pts], [v for _, v in pts]

    if not any(len(series(rec, key)[0]) >= 2 for _, rec in records for key, _ in PLOTTED):
        return None
    fig, axes = plt.subplots(1, len(PLOTTED), figsize=(4.0 * len(PLOTTED), 3.4))
    for ax, (key, title) in zip(axes, PLOTTED, strict=True):
        for _, rec in records:
            xs, ys = series(rec, key)
            if xs:
                ax.plot(xs, ys, marker="o", label=record_label(rec))
        ax.set_xscale("log")
        ax.set_xlabel("photos")
        ax.set_title(title, fontsize=10)
        ax.set_ylim(bottom=0)
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=8)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return path


def _gb_list(values: Any) -> str:
    return " / ".join(_cell(v, ".2f") for v in values) if values else "–"


def devices_section(path: Path, runs: list[dict[str, Any]]) -> list[str]:
    """One multi-gpu record file on a scale collection: a row per run (the steady state's step and images per
    second, the training span from the first step to the end, the start-up, each rank's peak memory) and the goal
    on several GPUs against the 1-GPU run at equal images seen; a run that failed is listed with its note."""
    ok = [r for r in runs if r.get("status") == "ok"]
    base = next((r for r in ok if r["num_devices"] == 1), None)
    first = runs[0]
    lines = [
        "",
        f"## {first['scene']}: {first['photos']:,} photos ({first.get('train_photos', '?')} training) on several GPUs",
        "",
        f"`{first['method']}`, {first['images']:,} images seen by every run (steps = images / GPUs, every setting "
        "counted in steps divided by the GPUs: docs/distributed.md), `python -m benchmarks multi-gpu run` on the "
        f"scale collection. Record: `{shown_path(path)}`.",
        "",
        "| run | GPUs | image cache | status | first step s | step ms (steady) | images/s (steady) | x 1 GPU | "
        "training s (first step to end) | x 1 GPU | wall s (launch to checkpoint) | host peak GB per rank | "
        "GPU peak GB per rank | Gaussians | commit |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]

    def span(r: dict[str, Any]) -> float | None:
        st = r.get("startup_s") or {}
        timed = isinstance(st.get("train_end"), (int, float)) and isinstance(st.get("first_step"), (int, float))
        return st["train_end"] - st["first_step"] if timed else None

    for r in runs:
        ips, sp = r.get("images_per_s"), span(r)
        x_ips = ips / base["images_per_s"] if base and base is not r and ips and base.get("images_per_s") else None
        x_span = span(base) / sp if base and base is not r and sp and span(base) else None
        held = "–" if r["num_devices"] == 1 else "sharded" if r.get("shard_image_cache", True) else "whole on each rank"
        lines.append(
            f"| {r['tag']} | {r['num_devices']} | {held} | {r['status']} | {_cell(r.get('first_step_s'), '.1f')} | "
            f"{_cell(r.get('step_ms'), '.2f')} | {_cell(ips, '.1f')} | {_cell(x_ips, '.2f')} | {_cell(sp, '.1f')} | "
            f"{_cell(x_span, '.2f')} | {_cell(r.get('wall_s'), '.1f')} | {_gb_list(r.get('peak_host_gb_per_rank'))} | "
            f"{_gb_list(r.get('peak_device_gb_per_rank'))} | {_cell(r.get('num_gaussians'), ',')} | "
            f"{r.get('commit') or '–'} |"
        )
    notes = [f"- {r['tag']}: {r['note']}" for r in runs if r.get("note")]
    if notes:
        lines += ["", *notes]
    lines += ["", "Goals:", ""]
    for n, want in DEVICES_GOAL.items():
        if n != 2 and not any(r["num_devices"] == n for r in runs):
            continue
        runs_n = [r for r in ok if r["num_devices"] == n and r.get("shard_image_cache", True) and r.get("images_per_s")]
        if not (base and base.get("images_per_s") and runs_n):
            lines.append(f"- {n} GPUs at {first['photos']:,} photos >= {want}x images per second: not measured")
            continue
        x = max(r["images_per_s"] for r in runs_n) / base["images_per_s"]
        lines.append(
            f"- {n} GPUs at {first['photos']:,} photos >= {want}x images per second: **{'met' if x >= want else 'missed'}**"
            f" ({x:.2f}x in the steady state)"
        )
    sharded = [r for r in ok if r["num_devices"] > 1 and r.get("shard_image_cache", True)]
    whole = [r for r in ok if r["num_devices"] > 1 and not r.get("shard_image_cache", True)]
    if sharded and whole:
        a, b = max(sharded[0]["peak_host_gb_per_rank"]), max(whole[0]["peak_host_gb_per_rank"])
        lines.append(f"- the sharded image cache: host peak per rank {a:.2f} GB against {b:.2f} GB caching every image")
    else:
        lines.append(
            "- the sharded image cache against every image on every rank: not measured in training (no `:noshard` "
            "run); the cache's own bytes per rank: the section on the training-image cache"
        )
    return lines


def render_page(
    records: list[tuple[Path, dict[str, Any]]],
    plot: str | None = None,
    devices: list[tuple[Path, list[dict[str, Any]]]] | None = None,
    caches: list[tuple[Path, dict[str, Any]]] | None = None,
) -> str:
    """docs/scale.md: per record its settings, table and goals; `plot`, the plot's file name beside the page, after
    the introduction; `devices`, the multi-gpu record files on scale collections, then `caches`, the image-cache
    records (benchmarks/rank_cache.py), last."""
    lines = [
        "# Photo-Tourism scale",
        "",
        "<!-- generated by `python -m benchmarks scale report` from benchmarks/records/*/scale_*.json; do not edit "
        "by hand -->",
        "",
        "How start-up, memory, step time, checkpoints, `ns-eval` and `willags-inspect` grow with the photos of a "
        "collection. Each collection is a source scene's photos copied under their own poses (own camera, pose, SfM "
        "observations and split; each file distinct) up to N photos at 800 px on the long side, with a COLMAP model "
        "and a tsv split, as a Photo-Tourism collection has (`python -m benchmarks scale run`, benchmarks/scale.py "
        "says how each number is measured). *first step*: from the process's start to its first training step "
        "(inspection, input checks, model, image cache); *host peak*: the process's peak resident memory; *step "
        "early / late*: median of steps 2-6 / of the five before the last; *fastest step*: the least disturbed on a "
        "shared machine; *ns-eval start*: until it has loaded the model and the test photos; *ns-eval s / test "
        "photo*: the rest of its run over the photos it scored; *viewer ready*: `ns-viewer --load-config` on the "
        "trained run until its scene is set up (the training cameras' frustums, at most 512 of them, and the "
        "panels). The slope row is a least-squares slope over the runs, per photo of the collection.",
    ]
    if plot:
        lines += ["", f"![The measures against the photos, a line per machine]({plot})"]
    for path, rec in records:
        m = rec["machine"]
        lines += ["", f"## {record_label(rec)}", ""]
        lines.append(
            f"`{rec['method']}`, {rec['steps']} training steps (viewer off), ns-eval with {rec['eval_protocol_steps']} "
            f"protocol step{'s' if rec['eval_protocol_steps'] != 1 else ''} per test photo"
            f"{', ' + ' '.join(rec['train_args']) if rec.get('train_args') else ''}; "
            f"{m['cpu_count']} cores, {m.get('host_memory_gb')} GB host memory"
            + (f", {m['gpu_memory_gb']} GB GPU" if m.get("gpu_memory_gb") else "")
            + (f". {m['note'].rstrip('.')}" if m.get("note") else "")
            + f". Record: `{shown_path(path)}`."
        )
        lines += ["", *table(rec), "", "The time to the first step, phase by phase (seconds):", "", *phase_table(rec)]
        lines += ["", "Goals:", ""]
        lines += [*cpu_goal(rec), eval_linearity_goal(completed_runs(rec))] if m["device"] == "cpu" else gpu_goals(rec)
    for path, runs in devices or []:
        lines += devices_section(path, runs)
    for path, rec in caches or []:
        lines += rank_cache.section(path, rec)
    return "\n".join(lines) + "\n"


def cache(args: argparse.Namespace) -> int:
    """`scale cache`: one rank's image cache, whole and sharded, per collection and rank count (rank_cache.py)."""
    from benchmarks.grid import git_commit

    source_dir = Path(args.source)
    source = read_source(source_dir)
    runs = []
    for n in args.photos:
        collection = make_collection(source, n, Path(args.work) / "collections" / f"{source_dir.name}-{n}", LONG_SIDE)
        for ranks in args.ranks:
            row = {"photos": n, **rank_cache.measure(collection, ranks)}
            print(json.dumps(row), flush=True)
            runs.append(row)
    env = machine()
    if args.note:
        env["note"] = args.note
    command = (
        f"python -m benchmarks scale cache --source {args.source} --photos {' '.join(map(str, args.photos))} "
        f"--ranks {' '.join(map(str, args.ranks))}"
    )
    record = {"source": source_dir.name, "long_side": LONG_SIDE, "machine": env, "commit": git_commit(),
              "date": time.strftime("%Y-%m-%dT%H:%M:%S"), "runs": runs, "command": command}  # fmt: skip
    print(f"benchmarks scale cache: {rank_cache.write_record(record, args.out)}")
    return 0


def report(args: argparse.Namespace) -> int:
    paths = [Path(p) for p in args.records] if args.records else sorted(RECORDS_DIR.glob(f"*/{RECORD_GLOB}"))
    records = [(p, json.loads(p.read_text())) for p in paths]
    devices = [(p, json.loads(p.read_text())) for p in sorted(RECORDS_DIR.glob(f"*/{DEVICES_GLOB}"))]
    if not records:
        print("benchmarks scale: no scale records (run `python -m benchmarks scale run` first)", file=sys.stderr)
        return 1
    page = Path(args.page)
    plot = plot_records(records, page.with_suffix(".png"))
    page.write_text(render_page(records, plot.name if plot else None, devices, rank_cache.records()))
    print(f"benchmarks scale: {page}" + (f", {plot}" if plot else ""))
    return 0


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="benchmarks scale", description=__doc__.split("\n\n")[0])
    sub = parser.add_subparsers(dest="cmd", required=True)
    r = sub.add_parser("run", help="make the collections and measure each")
    r.add_argument("--source", required=True, help="a COLMAP scene (images/, a model, a tsv) or 'synthetic'")
    r.add_argument("--photos", type=int, nargs="+", default=[100, 300, 1000, 2000], help="photo counts")
    r.add_argument("--work", required=True, help="where the collections and runs go (outside the repository)")
    r.add_argument("--long-side", type=int, default=LONG_SIDE, help="the photos' long side, px")
    r.add_argument("--steps", type=int, default=20, help="training steps per collection")
    r.add_argument("--eval-steps", type=int, default=128, help="NeRF-W protocol steps per test photo in ns-eval")
    r.add_argument("--no-eval", dest="eval", action="store_false", help="skip ns-eval")
    r.add_argument("--method", default="willags", help="the method ns-train trains")
    r.add_argument("--synthetic-views", type=int, default=40, help="views of the synthetic source")
    r.add_argument("--synthetic-unique-texture", type=float, default=0.8,
                   help="contrast of the synthetic source's non-repeating texture (0: the plain, repeating one)")  # fmt: skip
    r.add_argument("--train-args", default="", help="more ns-train arguments, one string (after the method's)")
    r.add_argument("--note", default="", help="a note on the machine (shared, alone, ...) kept in the record")
    r.add_argument("--title", default="", help="what the record is for, beside its source and device on the page")
    r.add_argument("--out", help="the record (default benchmarks/records/{gpu,cpu}_runs/scale_<source>.json)")
    c = sub.add_parser("cache", help="one rank's training-image cache, whole and sharded (benchmarks/rank_cache.py)")
    c.add_argument("--source", required=True, help="a COLMAP scene (images/, a model, a tsv)")
    c.add_argument("--photos", type=int, nargs="+", default=[1000, 2000], help="photo counts")
    c.add_argument("--ranks", type=int, nargs="+", default=[1, 2, 4], help="rank counts (1: the whole cache)")
    c.add_argument("--work", required=True, help="where the collections go (outside the repository)")
    c.add_argument("--note", default="", help="a note on the machine kept in the record")
    c.add_argument("--out", help="the record (default benchmarks/records/cpu_runs/rank_cache_<source>.json)")
    p = sub.add_parser("report", help="write docs/scale.md from the scale records")
    p.add_argument("--records", nargs="*", help="record files (default every benchmarks/records/*/scale_*.json)")
    p.add_argument("--page", default=str(PAGE), help="the page to write")
    args = parser.parse_args(list(argv) if argv is not None else sys.argv[1:])
    if args.cmd == "run":
        args.train_args = shlex.split(args.train_args)
    return {"run": run, "cache": cache, "report": report}[args.cmd](args)


if __name__ == "__main__":
    sys.exit(main())
