"""The speed suite: train-step time, peak VRAM and host syncs per model variant, and render FPS, on one GPU.

    python -m benchmarks speed --n-gaussians 1000000 --size 800 --tag h100 --out $OUT/speed.json
    python -m benchmarks speed --quick       # a smoke test (CPU: the torch backend, tiny sizes; its times are no measurement)

Every variant trains the same Gaussians (same seed points, scales from the same 3-NN distances, same quaternions)
seen by the same camera at full resolution, at a step past every warm-up (SH degree 3, mask active) with
densification off, so N stays fixed. ``step_ms``: the mean train step (CUDA events; with the mask on every 4th visit
one step in 4 also renders the teacher, so the mean is what training pays per step); ``peak_gb``: peak
``max_memory_allocated`` over those steps, ``extra_vram_gb`` against the baseline (splatfacto, else willags-3dgs);
``host_syncs_per_step``: synchronising CUDA calls (torch's sync debug mode). The render numbers go on the `willags`
record: ``get_outputs`` with a fixed latent (eval, no grad) against the same Gaussians through the rasteriser with
their colours precomputed (``render_fps_ratio_vs_gsplat``) and against stock splatfacto. The records (a JSON list,
rewritten after every variant, so a run killed at its time limit keeps what it finished) merge with
``python -m benchmarks merge``. Where a step's time goes on a real scene: ``python -m benchmarks profile``.
"""

import argparse
import gc
import json
import math
import os
import statistics
import sys
import time
import warnings
from pathlib import Path

import torch

from benchmarks.child import patch_offline, sync
from benchmarks.grid import git_commit
from benchmarks.records import REPO

STEP0 = 10_000
"""Step counter while timing: past SH warm-up (degree 3 from step 3000) and past the mask warm-up."""
TIMING_OVERRIDES = {
    "warmup_length": 10**9,  # no densification: N stays fixed and every variant renders the same Gaussians
    "reset_alpha_every": 10**6,
    "stop_split_at": 10**9,  # ... but gsplat's per-step gradient statistics still run, as in the first 15k steps
    "num_downscales": 0,  # full resolution at any step
}
LRS = {"means": 1.6e-4, "scales": 0.005, "quats": 0.001, "opacities": 0.05, "features_dc": 0.0025}
LRS.update({"features_rest": 0.0025 / 20, "features": 0.0025, "appearance": 1e-3, "camera_opt": 1e-4})
"""splatfacto's per-group Adam learning rates (method_configs._optimizers); 1e-3 for the groups not named."""
VARIANTS = {  # name: (model config, overrides: "a.b" sets a nested field)
    "splatfacto": ("stock", {}),
    "willags-3dgs": ("willags", {"appearance": "sh", "mask.enabled": False, "use_field": False}),
    "willags": ("willags", {}),  # the `willags` method's full model (method_configs.willags_model_config)
    "willags-nomask": ("willags", {"mask.enabled": False}),
    "willags-2raster": ("willags", {"mask.teacher.fused": False}),  # the teacher as a second rasterisation
    "willags-paper": ("paper", {}),
    "willags-lite": ("lite", {}),
}
QUICK_VARIANTS = ["splatfacto", "willags-3dgs", "willags", "willags-nomask"]


def seed_points(n: int, seed: int = 0) -> tuple[torch.Tensor, torch.Tensor]:
    """(xyz float32 [n, 3], rgb uint8 [n, 3]) uniform in [-1, 1]^3: at 1M the 3-NN spacing is ~0.01, so seen from the
    camera below (distance 3, 60 deg) each Gaussian starts a few pixels wide at 800 px."""
    g = torch.Generator().manual_seed(seed)
    return torch.rand(n, 3, generator=g) * 2.0 - 1.0, torch.randint(0, 256, (n, 3), generator=g, dtype=torch.uint8)


def camera(size: int, dev: torch.device, view: int = 0):
    """A pinhole camera (60 deg) on a circle of 8 around the z axis, 3 away, looking at the origin (OpenGL axes)."""
    from nerfstudio.cameras.cameras import Cameras

    a = 2.0 * math.pi * (1 + view) / 8
    eye = torch.tensor([3.0 * math.cos(a), 3.0 * math.sin(a), 0.8])
    fwd = torch.nn.functional.normalize(-eye, dim=0)
    right = torch.nn.functional.normalize(torch.linalg.cross(fwd, torch.tensor([0.0, 0.0, 1.0])), dim=0)
    c2w = torch.stack([right, torch.linalg.cross(right, fwd), -fwd, eye], dim=1)
    f = 0.5 * size / math.tan(math.radians(30.0))
    return Cameras(camera_to_worlds=c2w[None], fx=f, fy=f, cx=size / 2, cy=size / 2, width=size, height=size).to(dev)


def smooth_image(size: int, seed: int = 1) -> torch.Tensor:
    """A smooth random uint8 image [H, W, 3]: a ground truth that is not constant, as the datamanager caches it."""
    g = torch.Generator().manual_seed(seed)
    img = torch.nn.functional.interpolate(torch.rand(1, 3, 8, 8, generator=g), size=(size, size), mode="bicubic")
    return ((img + 0.05 * torch.rand(1, 3, size, size, generator=g)).clamp(0, 1)[0].permute(1, 2, 0) * 255).byte()


_KNN_CACHE: dict = {}


def _patch_knn() -> None:
    """Memoise splatfacto's 3-NN initial scales: one sklearn pass (all cores) for 1M points, not one per model."""
    from nerfstudio.models.splatfacto import SplatfactoModel

    def k_nearest(self, x: torch.Tensor, k: int):
        key = (tuple(x.shape), k, float(x[:64].double().sum()), float(x[-64:].double().sum()))
        if key not in _KNN_CACHE:
            from sklearn.neighbors import NearestNeighbors

            xn = x.detach().cpu().numpy()
            d, i = NearestNeighbors(n_neighbors=k + 1, n_jobs=-1).fit(xn).kneighbors(xn)
            _KNN_CACHE[key] = (d[:, 1:].astype("float32"), i[:, 1:].astype("float32"))
        return _KNN_CACHE[key]

    SplatfactoModel.k_nearest_sklearn = k_nearest


def build_model(variant: str, seeds, n_train: int, dev: torch.device, backend: str):
    """(model on dev in train mode with its optimisers, is_willags); the same Gaussians for every variant."""
    from nerfstudio.data.scene_box import SceneBox

    from benchmarks.methods import set_nested
    from willags_ns import method_configs as mc
    from willags_ns.method_configs import FusedAdamOptimizerConfig

    _patch_knn()
    kind, overrides = VARIANTS[variant]
    box = SceneBox(aabb=torch.tensor([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]]))
    torch.manual_seed(0)  # random_quat_tensor draws from the global generator
    if kind == "stock":
        if dev.type != "cuda":
            raise RuntimeError("stock splatfacto hard-codes .cuda(): skipped without CUDA")
        from nerfstudio.models.splatfacto import SplatfactoModelConfig

        patch_offline("splatfacto")
        cfg = SplatfactoModelConfig(**TIMING_OVERRIDES)
    else:
        lite = lambda: mc.willags_lite_config().pipeline.model  # noqa: E731
        cfg = {"willags": mc.willags_model_config, "paper": mc.willags_paper_model_config, "lite": lite}[kind]()
        for k, v in {**TIMING_OVERRIDES, **overrides}.items():
            set_nested(cfg, k, v)
        cfg.backend, cfg.log_images_every, cfg.mask.warmup_steps, cfg.mask.ramp_steps = backend, 0, 0, 0
    model = cfg.setup(scene_box=box, num_train_data=n_train, seed_points=seeds).to(dev)
    if kind == "stock":
        model.strategy.verbose = False
    model.train()
    # each method's own optimiser: stock splatfacto's torch Adam; willags' fused one (on CUDA)
    opts = {}
    for name, params in model.get_param_groups().items():
        params = [p for p in params if p.requires_grad]
        if params and kind == "stock":
            opts[name] = torch.optim.Adam(params, lr=LRS.get(name, 1e-3), eps=1e-15)
        elif params:
            opts[name] = FusedAdamOptimizerConfig(lr=LRS.get(name, 1e-3), eps=1e-15).setup(params)
    model.optimizers = opts
    return model, kind != "stock"


def train_step(model, camera, batch, step: int, is_willags: bool) -> None:
    """One nerfstudio training iteration, as Trainer + WillagsPipeline run it (callbacks included)."""
    model.step = step  # splatfacto's step_cb
    for o in model.optimizers.values():
        o.zero_grad(set_to_none=True)
    if is_willags:
        model.set_train_batch(batch)
    outputs = model.get_outputs(camera)
    loss = sum(model.get_loss_dict(outputs, batch, model.get_metrics_dict(outputs, batch)).values())
    loss.backward()
    for o in model.optimizers.values():
        o.step()
    model.step_post_backward(step)
    if is_willags:
        if model.teacher is not None:
            model.update_teacher(step)
        model.end_step(step)


def _stamp(cuda: bool):
    """A point on the device's timeline: a CUDA event (no host sync when taken), else perf_counter."""
    if not cuda:
        return time.perf_counter()
    event = torch.cuda.Event(enable_timing=True)
    event.record()
    return event


def _ms(start, end, cuda: bool) -> float:
    return start.elapsed_time(end) if cuda else 1e3 * (end - start)


def time_steps(variant: str, args, cuda: bool, dev, backend: str) -> dict:
    """Build ``variant``, warm it up, then time ``args.iters`` train steps (mean and wall), peak VRAM, host syncs."""
    batch = {"image": smooth_image(args.size).to(dev), "image_idx": 0}
    base = torch.cuda.memory_allocated() if cuda else 0
    model, is_w = build_model(variant, seed_points(args.n_gaussians), 50, dev, backend)
    cam, step = camera(args.size, dev), STEP0
    r: dict = {"n_gaussians": int(model.num_points)}
    for _ in range(args.warmup):  # also builds the lazy VGG and the Adam states
        train_step(model, cam, batch, step, is_w)
        step += 1
    sync(dev)
    if cuda:
        gc.collect()
        torch.cuda.reset_peak_memory_stats()
        r["static_gb"] = (torch.cuda.memory_allocated() - base) / 2**30  # parameters, Adam, caches
    spans, t0 = [], time.perf_counter()
    for _ in range(args.iters):
        s = _stamp(cuda)
        train_step(model, cam, batch, step, is_w)
        spans.append((s, _stamp(cuda)))
        step += 1
    sync(dev)
    ms = [_ms(s, e, cuda) for s, e in spans]
    r.update(step_ms=statistics.fmean(ms), step_ms_median=statistics.median(ms))
    r["step_ms_wall"] = (time.perf_counter() - t0) * 1e3 / args.iters
    if cuda:
        r["peak_gb"] = (torch.cuda.max_memory_allocated() - base) / 2**30
        with warnings.catch_warnings(record=True) as caught:  # torch's sync debug mode warns at every host sync
            warnings.simplefilter("always")
            torch.cuda.set_sync_debug_mode("warn")
            try:
                for _ in range(4):
                    train_step(model, cam, batch, step, is_w)
                    step += 1
            finally:
                torch.cuda.set_sync_debug_mode(0)
        r["host_syncs_per_step"] = sum("synchroniz" in str(w.message) for w in caught) / 4
    return r


def render_fps(args, cuda: bool, dev, backend: str) -> dict:
    """FPS of ``get_outputs`` (fixed latent, eval, no grad) against the same Gaussians through the rasteriser with
    their colours precomputed, and against stock splatfacto's ``get_outputs``."""
    from willags_ns.render import rasterize
    from willags_ns.render.camera import viewmat_from_c2w

    seeds, cams, out = seed_points(args.n_gaussians), [camera(args.size, dev, v) for v in range(8)], {}

    def fps(render_one) -> float:
        with torch.no_grad():
            for i in range(3):
                render_one(i)
            sync(dev)
            t0 = time.perf_counter()
            for i in range(args.frames):
                render_one(i % 8)
            sync(dev)
        return args.frames / (time.perf_counter() - t0)

    def willags() -> None:  # its model freed on return, before splatfacto's is built
        model, _ = build_model("willags", seeds, 50, dev, backend)
        model.eval()
        z = (0.5 * torch.randn(model.appearance_nets.latent_dim, generator=torch.Generator().manual_seed(3))).to(dev)
        model.render_latent = z
        out["willags_fps"] = fps(lambda i: model.get_outputs(cams[i]))
        with torch.no_grad():
            center = cams[0].camera_to_worlds[0, :3, 3]
            colors = model.appearance_colors(z, model.means, model.intrinsic_features, center).rgb.contiguous()
            gauss = (model.means, model.quats, torch.exp(model.scales), torch.sigmoid(model.opacities).squeeze(-1))
            views = [(viewmat_from_c2w(c.camera_to_worlds), c.get_intrinsics_matrices().to(dev)) for c in cams]
        size, mode = args.size, "RGB+ED"  # what get_outputs renders in eval
        out["precomputed_fps"] = fps(
            lambda i: rasterize(*gauss, colors, *views[i], size, size, render_mode=mode, backend=backend)
        )
        out["render_fps_ratio_vs_gsplat"] = out["willags_fps"] / out["precomputed_fps"]
        out["render_baseline_backend"] = backend

    willags()
    gc.collect()
    if cuda:
        splatfacto, _ = build_model("splatfacto", seeds, 50, dev, backend)
        splatfacto.eval()
        splatfacto.step = STEP0  # SH degree 3
        out["splatfacto_fps"] = fps(lambda i: splatfacto.get_outputs(cams[i]))
        out["render_fps_ratio_vs_splatfacto"] = out["willags_fps"] / out["splatfacto_fps"]
    return out


def records(steps: dict, render: dict, env: dict, args) -> list[dict]:
    """benchmarks.json records: one per variant (steps 0), the render numbers on `willags`'s."""
    scene = f"synthetic-box-{args.n_gaussians}-{args.size}px"
    base = next((v for v in ("splatfacto", "willags-3dgs") if "step_ms" in steps.get(v, {})), None)
    out = []
    for v, r in steps.items():
        if "error" in r:
            continue
        rec = {"scene": scene, "method": v, "steps": 0, "tag": args.tag, "image_size": args.size, **env, **r}
        if base is not None and "step_ms" in r:
            rec.update(step_ratio_vs_splatfacto=r["step_ms"] / steps[base]["step_ms"], step_baseline=base)
        if base is not None and "peak_gb" in r and "peak_gb" in steps[base]:
            rec["extra_vram_gb"] = r["peak_gb"] - steps[base]["peak_gb"]
        out.append(rec)
    head = next((r for r in out if r["method"] == "willags"), None)
    if head is None and render:
        out.append(head := {"scene": scene, "method": "willags", "steps": 0, "tag": args.tag, **env})
    if head is not None:
        head.update({("render_fps" if k == "willags_fps" else k): v for k, v in render.items()})
    return [{k: (str(v) if isinstance(v, float) and not math.isfinite(v) else v) for k, v in r.items()} for r in out]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true", help="tiny sizes: a smoke test")
    ap.add_argument("--n-gaussians", type=int, default=None, help="Gaussians in the synthetic scene (1000000)")
    ap.add_argument("--size", type=int, default=None, help="image side in pixels (800)")
    ap.add_argument("--warmup", type=int, default=None, help="warm-up train steps per variant (5)")
    ap.add_argument("--iters", type=int, default=None, help="timed train steps per variant (20, a multiple of 4)")
    ap.add_argument("--frames", type=int, default=None, help="timed render frames (100)")
    ap.add_argument("--variants", default=None, help=f"comma list from {','.join(VARIANTS)} (default: all)")
    ap.add_argument("--no-render", dest="render", action="store_false", help="time train steps only")
    ap.add_argument("--time-budget", type=float, default=480.0, help="seconds: no variant starts after them")
    ap.add_argument("--tag", default="", help="the records' tag (the machine, e.g. h100)")
    ap.add_argument("--out", default=None, help="write the records (a JSON list) here")
    args = ap.parse_args(argv)
    q = args.quick
    args.n_gaussians = args.n_gaussians or (3000 if q else 1_000_000)
    args.size = args.size or (64 if q else 800)
    args.warmup = args.warmup if args.warmup is not None else (1 if q else 5)
    args.iters, args.frames = args.iters or (4 if q else 20), args.frames or (4 if q else 100)
    variants = args.variants.split(",") if args.variants else (QUICK_VARIANTS if q else list(VARIANTS))
    if set(variants) - set(VARIANTS):
        ap.error(f"unknown variants {sorted(set(variants) - set(VARIANTS))}; choose from {list(VARIANTS)}")
    os.environ.setdefault("MAX_JOBS", str(os.cpu_count() or 4))  # gsplat's JIT build
    cuda = torch.cuda.is_available()
    dev, backend = torch.device("cuda" if cuda else "cpu"), "gsplat" if cuda else "torch"
    if not cuda:
        torch.set_num_threads(1)  # steadier on a shared machine; CPU times are no measurement here
    env = {"device": torch.cuda.get_device_name(0) if cuda else "cpu", "torch": torch.__version__}
    env.update(commit=git_commit(REPO), quick=q)
    t_end, steps, render = time.perf_counter() + args.time_budget, {}, {}

    def write() -> None:
        if args.out:
            Path(args.out).parent.mkdir(parents=True, exist_ok=True)
            Path(args.out).write_text(json.dumps(records(steps, render, env, args), indent=1, default=str))

    for v in variants:
        if v == "splatfacto" and not cuda:
            continue  # stock splatfacto hard-codes .cuda()
        if time.perf_counter() > t_end:
            steps[v] = {"error": "skipped: time budget spent"}
        else:
            try:
                steps[v] = time_steps(v, args, cuda, dev, backend)
            except Exception as e:
                steps[v] = {"error": f"{type(e).__name__}: {e}"[:400]}
            gc.collect()
            if cuda:
                torch.cuda.empty_cache()
        print(f"{v}: " + ", ".join(f"{k}={x:.2f}" if isinstance(x, float) else f"{k}={x}" for k, x in steps[v].items()))
        write()
    if args.render and time.perf_counter() < t_end:
        render = render_fps(args, cuda, dev, backend)
        print("render: " + ", ".join(f"{k}={x:.3f}" for k, x in render.items() if isinstance(x, float)))
        write()
    return 1 if any("error" in r for r in steps.values()) else 0


if __name__ == "__main__":
    sys.exit(main())
