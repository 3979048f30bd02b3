"""GPU measurement suite for willags: rasteriser parity, train-step time and profile, render FPS, peak VRAM.

One call does everything a lent GPU session needs (see docs/gpu_notes.md):

    python benchmarks/gpu_suite.py --all --n-gaussians 1000000 --size 800 --json-out $OUT/gpu_suite.json
    python benchmarks/gpu_suite.py --quick --all            # CPU smoke test (< 60 s): torch backend only

Sections (each in its own try/except: a failure is recorded and the others still run; the JSON is rewritten
after every section, so a run killed at its time limit keeps what it finished):

- ``--parity``: ``willags_ns.render.rasterize`` torch backend vs gsplat (both float32, CUDA) over random scenes
  and extremes; forward relative error (render, alpha) and gradient relative error per parameter (means, quats,
  scales, opacities, colors); a float64 torch reference says which side the error comes from. Without CUDA:
  torch float32 vs torch float64 only (gsplat skipped).
- ``--step``: mean train-step time (CUDA events, warm-up first) of a WillagsModel built directly (no ns-train)
  on a synthetic ~N-Gaussian scene, for splatfacto (stock nerfstudio, CUDA only), willags-3dgs (appearance="sh":
  the same code with splatfacto's colours) and willags variants; a per-component profile; host syncs per step.
- ``--memory``: peak ``torch.cuda.max_memory_allocated`` over the timed train steps per model (CUDA only).
- ``--render``: FPS of ``model.get_outputs`` with a fixed latent (eval, no grad) vs gsplat with the same
  Gaussians' colours precomputed.
- ``--components``: isolated forward+backward timings (tri-plane query, decoder MLP, hypernetwork, VGG, gsplat)
  next to their FLOP / byte floors from the measured device ceilings (METHOD.md's "two numbers").

The comparison is always at the same Gaussians (same seed points, scales from the same 3-NN distances, same
quaternions), the same camera and the same full resolution (num_downscales=0), at a step past every warm-up
(SH degree 3, mask active) with densification off (N stays fixed).
"""

import argparse
import contextlib
import copy
import gc
import json
import math
import os
import platform
import statistics
import sys
import time
import traceback
import warnings
from collections import defaultdict
from pathlib import Path

import torch

REPO = Path(__file__).resolve().parents[1]
if str(REPO) not in sys.path:  # `python benchmarks/gpu_suite.py` from anywhere
    sys.path.insert(0, str(REPO))
os.environ.setdefault("MAX_JOBS", str(os.cpu_count() or 4))  # gsplat's JIT build

from benchmarks import _synthetic_gaussians as syn  # noqa: E402

STEP0 = 10_000
"""Step counter while timing: past SH warm-up (degree 3 from step 3000) and past the mask warm-up."""
TIMING_OVERRIDES = dict(
    warmup_length=10**9,  # no densification: N stays fixed and every variant renders the same Gaussians
    reset_alpha_every=10**6,
    stop_split_at=10**9,  # ... but gsplat's per-step gradient statistics still run, as in the first 15k steps
    num_downscales=0,  # full resolution at any step
)
LRS = {  # method_configs._optimizers (splatfacto's per-group Adam learning rates)
    "means": 1.6e-4,
    "scales": 0.005,
    "quats": 0.001,
    "opacities": 0.05,
    "features_dc": 0.0025,
    "features_rest": 0.0025 / 20,
    "features": 0.0025,
    "appearance": 1e-3,
    "camera_opt": 1e-4,
}
_FAST = {"mask_every": 4, "mask.max_resolution": 256}
VARIANTS = {
    # name: (builder, config overrides ("a.b" sets a nested field), wrappers around model.appearance_colors)
    "splatfacto": ("stock", {}, ()),
    "willags-3dgs": ("willags", dict(appearance="sh", use_mask=False, use_vae=False, use_field=False), ()),
    "willags": ("willags", {}, ()),  # the `willags` method's model (method_configs.willags_model_config)
    "willags-vae": ("willags", {"use_vae": True}, ()),  # ... with the beta-VAE latent
    "willags-everymask": ("willags", {"mask_every": 1, "mask.max_resolution": 512}, ()),  # the paper's mask cadence
    "willags-paper": ("paper", {}, ()),  # the paper preset (colour decoder + tri-plane field)
    "willags-2raster": ("willags", dict(fuse_teacher_render=False), ()),  # the teacher as a second rasterisation
    "willags-mask4": ("willags", dict(mask_every=4), ()),
    "willags-vgg256": ("willags", {"mask.max_resolution": 256}, ()),
    "willags-nomask": ("willags", dict(use_mask=False), ()),
    "willags-sky": ("willags", {"sky.enabled": True}, ()),  # + the appearance-conditioned sky
    # the local residual through plain autograd (keeps [N, hidden] activations; the default recomputes them)
    "willags-plainres": ("willags", {"modulation.residual_chunk": 0}, ()),
    "willags-chunk128k": ("willags", {"modulation.residual_chunk": 131072}, ()),  # = the default
    "willags-chunk256k": ("willags", {"modulation.residual_chunk": 262144}, ()),
    "willags-chunk1m": ("willags", {"modulation.residual_chunk": 1 << 20}, ()),  # one chunk at 1M: recompute only
    "willags-foreachadam": ("willags", {}, ("foreach-adam",)),  # stock torch Adam instead of the fused one
    "willags-bf16": ("willags", {}, ("bf16",)),
    "willags-ckpt": ("willags", {}, ("ckpt",)),
    "willags-fast": ("willags", _FAST, ()),  # mask every 4th visit of an image, VGG at 256 px
    "willags-fast-bf16": ("willags", _FAST, ("bf16",)),  # ... and bf16 appearance MLPs
    "willags-lite": ("lite", {}, ()),
    # torch.compile of the appearance path (Triton on CUDA: fused query + decoder); each costs a compile
    "willags-compile": ("willags", {}, ("compile",)),
    "willags-fast-compile": ("willags", _FAST, ("compile", "bf16")),
}
DEFAULT_VARIANTS = list(VARIANTS)  # compile variants last: the deadline drops them first
QUICK_VARIANTS = ["splatfacto", "willags-3dgs", "willags", "willags-mask4", "willags-nomask"]


def log(*a) -> None:
    print(*a, flush=True)


def short_exc(e: BaseException) -> str:
    return f"{type(e).__name__}: {e}".strip()[:400]


# ------------------------------------------------------------------------------------------------- timing tools
class Stamp:
    """A point in time on the device's timeline: a CUDA event (no host sync when taken), else perf_counter."""

    def __init__(self, cuda: bool):
        self.cuda = cuda
        if cuda:
            self.ev = torch.cuda.Event(enable_timing=True)
            self.ev.record()
        else:
            self.t = time.perf_counter()

    def ms_until(self, other: "Stamp") -> float:
        return self.ev.elapsed_time(other.ev) if self.cuda else 1e3 * (other.t - self.t)


def sync(cuda: bool) -> None:
    if cuda:
        torch.cuda.synchronize()


class RegionTimer:
    """Accumulates device time per label; regions are closed lazily (one sync at `collect`)."""

    def __init__(self, cuda: bool):
        self.cuda = cuda
        self.pending: list[tuple[str, Stamp, Stamp]] = []
        self.totals: dict[str, float] = defaultdict(float)
        self.suspended = False  # True inside the teacher render: its inner calls belong to it

    @contextlib.contextmanager
    def region(self, label: str):
        if self.suspended:
            yield
            return
        s = Stamp(self.cuda)
        try:
            yield
        finally:
            self.pending.append((label, s, Stamp(self.cuda)))

    def collect(self) -> dict[str, float]:
        sync(self.cuda)
        for label, s, e in self.pending:
            self.totals[label] += s.ms_until(e)
        self.pending.clear()
        return dict(self.totals)


def bench_fn(fn, cuda: bool, warmup: int, iters: int) -> float:
    """Median ms of `fn()` (device events around each call, after `warmup` calls)."""
    for _ in range(warmup):
        fn()
    sync(cuda)
    spans = []
    for _ in range(iters):
        s = Stamp(cuda)
        fn()
        spans.append((s, Stamp(cuda)))
    sync(cuda)
    return statistics.median(s.ms_until(e) for s, e in spans)


@contextlib.contextmanager
def count_host_syncs(cuda: bool, sink: list):
    """Record (file:line) of every synchronising CUDA call made inside (torch's sync debug mode)."""
    if not cuda or not hasattr(torch.cuda, "set_sync_debug_mode"):
        yield
        return
    with warnings.catch_warnings(record=True) as rec:
        warnings.simplefilter("always")
        torch.cuda.set_sync_debug_mode("warn")
        try:
            yield
        finally:
            torch.cuda.set_sync_debug_mode(0)
    for w in rec:
        if "synchroniz" in str(w.message):
            f = str(w.filename)
            f = f[len(str(REPO)) + 1 :] if f.startswith(str(REPO)) else "/".join(Path(f).parts[-3:])
            sink.append(f"{f}:{w.lineno}")


# --------------------------------------------------------------------------------------------- environment info
def environment(cuda: bool) -> dict:
    info = {
        "device": torch.cuda.get_device_name(0) if cuda else f"cpu ({platform.processor() or platform.machine()})",
        "torch": torch.__version__,
        "python": platform.python_version(),
        "cuda": torch.version.cuda if cuda else None,
    }
    try:
        import gsplat

        info["gsplat"] = gsplat.__version__
    except Exception as e:
        info["gsplat"] = f"unavailable ({short_exc(e)})"
    try:
        from importlib.metadata import version

        import nerfstudio  # noqa: F401

        info["nerfstudio"] = version("nerfstudio")
    except Exception as e:
        info["nerfstudio"] = f"unavailable ({short_exc(e)})"
    if cuda:
        info["tf32_matmul"] = torch.backends.cuda.matmul.allow_tf32
        info["tf32_cudnn"] = torch.backends.cudnn.allow_tf32
    return info


def measure_ceilings(cuda: bool) -> dict:
    """Device-to-device copy bandwidth and matmul rates (fp32 as the trainer runs it, bf16), METHOD.md style."""
    if not cuda:
        return {}
    out = {}
    n = 256 * 2**20  # 1 GiB of float32
    src = torch.randn(n, device="cuda")
    dst = torch.empty_like(src)
    ms = bench_fn(lambda: dst.copy_(src), True, 3, 10)
    out["copy_GBps"] = 2 * n * 4 / ms / 1e6  # bytes read + bytes written
    for dt, name in ((torch.float32, "fp32"), (torch.bfloat16, "bf16")):
        m = 8192 if dt == torch.bfloat16 else 4096
        x = torch.randn(m, m, device="cuda", dtype=dt)  # random data: zeros run faster (METHOD.md)
        y = torch.randn(m, m, device="cuda", dtype=dt)
        ms = bench_fn(lambda x=x, y=y: x @ y, True, 3, 10)
        out[f"matmul_{name}_TFLOPs"] = 2 * m**3 / ms / 1e9
    return out


# ------------------------------------------------------------------------------------------------------ parity
def _rel(a: torch.Tensor, b: torch.Tensor) -> float:
    """||a - b|| / ||b|| in float64 (0 when both vanish; inf on any non-finite value)."""
    a, b = a.double(), b.double()
    if not (torch.isfinite(a).all() and torch.isfinite(b).all()):
        return math.inf
    nb = b.norm().item()
    diff = (a - b).norm().item()
    if nb < 1e-30:
        return 0.0 if diff < 1e-30 else math.inf
    return diff / nb


def _run_case(case, backend: str, device, dtype, weights):
    from willags_ns.render import rasterize

    params = {k: v.to(device=device, dtype=dtype).clone().requires_grad_(True) for k, v in case.tensors().items()}
    render, alpha, _ = rasterize(
        params["means"],
        params["quats"],
        params["scales"],
        params["opacities"],
        params["colors"],
        case.viewmats.to(device=device, dtype=dtype),
        case.Ks.to(device=device, dtype=dtype),
        case.width,
        case.height,
        sh_degree=case.sh_degree,
        render_mode=case.render_mode,
        backend=backend,
    )
    w_r, w_a = weights
    loss = (render * w_r.to(device=device, dtype=dtype)).sum() + (alpha * w_a.to(device=device, dtype=dtype)).sum()
    loss.backward()
    grads = {k: (p.grad if p.grad is not None else torch.zeros_like(p)).detach() for k, p in params.items()}
    return render.detach(), alpha.detach(), grads


def section_parity(args, cuda: bool) -> dict:
    cases = syn.parity_cases(quick=args.quick)
    dev = torch.device("cuda" if cuda else "cpu")
    rows = []
    names = ["means", "quats", "scales", "opacities", "colors"]
    mode = "torch-vs-gsplat" if cuda else "torch-fp32-vs-torch-fp64 (gsplat skipped: no CUDA)"
    for case in cases:
        g = torch.Generator().manual_seed(7)
        nch = 3 + (1 if case.render_mode == "RGB+ED" else 0)
        weights = (
            torch.rand(1, case.height, case.width, nch, generator=g),
            torch.rand(1, case.height, case.width, 1, generator=g),
        )
        row = {"case": case.name, "n": case.means.shape[0], "size": f"{case.width}x{case.height}"}
        try:
            t32 = _run_case(case, "torch", dev, torch.float32, weights)
            ref = None
            try:  # float64 reference of the same maths: a diagnostic, never a reason to lose the case
                ref = _run_case(case, "torch", dev, torch.float64, weights)
            except Exception as e:
                row["f64_error"] = short_exc(e)
            if cuda:
                gs = _run_case(case, "gsplat", dev, torch.float32, weights)
                a, b = t32, gs  # the metric: torch backend vs gsplat
                if ref is not None:
                    row["fwd_gsplat_vs_f64"] = max(_rel(gs[0], ref[0]), _rel(gs[1], ref[1]))
                    row["grad_gsplat_vs_f64"] = max(_rel(gs[2][k], ref[2][k]) for k in names)
            else:
                if ref is None:
                    raise RuntimeError(f"no reference: {row['f64_error']}")
                a, b = t32, ref
            row["fwd_render"] = _rel(a[0], b[0])
            row["fwd_alpha"] = _rel(a[1], b[1])
            for k in names:
                row[f"grad_{k}"] = _rel(a[2][k], b[2][k])
            row["fwd"] = max(row["fwd_render"], row["fwd_alpha"])
            row["grad"] = max(row[f"grad_{k}"] for k in names)
        except Exception as e:
            row["error"] = short_exc(e)
        rows.append(row)
    ok = [r for r in rows if "error" not in r]
    out = {"mode": mode, "cases": rows, "n_cases": len(rows), "n_errors": len(rows) - len(ok)}
    if ok:
        wf = max(ok, key=lambda r: r["fwd"])
        wg = max(ok, key=lambda r: r["grad"])
        out["worst_fwd"] = {"value": wf["fwd"], "case": wf["case"]}
        out["worst_grad"] = {"value": wg["grad"], "case": wg["case"]}
        out["worst_grad_per_param"] = {}
        for k in names:
            r = max(ok, key=lambda r: r[f"grad_{k}"])
            out["worst_grad_per_param"][k] = {"value": r[f"grad_{k}"], "case": r["case"]}
        out["pass_fwd_1e-4"] = wf["fwd"] <= 1e-4
        out["pass_grad_1e-3"] = wg["grad"] <= 1e-3
    log(f"\n## parity ({mode}); limits: forward <= 1e-4, gradients <= 1e-3")
    hdr = "| case | N | size | fwd render | fwd alpha | " + " | ".join(f"d {k}" for k in names)
    hdr += " | gsplat vs f64 fwd / grad |" if cuda else " |"
    log(hdr)
    log("|" + "---|" * (hdr.count("|") - 1))
    for r in rows:
        if "error" in r:
            log(f"| {r['case']} | {r['n']} | {r['size']} | ERROR {r['error']} |")
            continue
        cells = [f"{r['fwd_render']:.1e}", f"{r['fwd_alpha']:.1e}"] + [f"{r[f'grad_{k}']:.1e}" for k in names]
        tail = " |"
        if cuda:
            tail = (
                f" | {r['fwd_gsplat_vs_f64']:.1e} / {r['grad_gsplat_vs_f64']:.1e} |"
                if "fwd_gsplat_vs_f64" in r
                else " | - |"
            )
        log(f"| {r['case']} | {r['n']} | {r['size']} | " + " | ".join(cells) + tail)
    return out


# ------------------------------------------------------------------------------------------ models for timing
_KNN_CACHE: dict = {}


def _patch_knn() -> None:
    """Memoise splatfacto's 3-NN initial scales: one sklearn pass (all cores) for 1M points, not one per model."""
    from nerfstudio.models.splatfacto import SplatfactoModel

    if getattr(SplatfactoModel, "_bench_knn_patched", False):
        return

    def k_nearest(self, x: torch.Tensor, k: int):
        key = (tuple(x.shape), k, float(x[:64].double().sum()), float(x[-64:].double().sum()))
        if key not in _KNN_CACHE:
            from sklearn.neighbors import NearestNeighbors

            xn = x.detach().cpu().numpy()
            nn_model = NearestNeighbors(n_neighbors=k + 1, algorithm="auto", metric="euclidean", n_jobs=-1).fit(xn)
            d, i = nn_model.kneighbors(xn)
            _KNN_CACHE[key] = (d[:, 1:].astype("float32"), i[:, 1:].astype("float32"))
        return _KNN_CACHE[key]

    SplatfactoModel.k_nearest_sklearn = k_nearest
    SplatfactoModel._bench_knn_patched = True


class _NoLPIPS(torch.nn.Module):
    """Stands in for torchmetrics' LPIPS in stock splatfacto: it would download AlexNet weights (no network)."""

    def __init__(self, *a, **k):
        super().__init__()


def _set_nested(cfg, key: str, value) -> None:
    obj = cfg
    parts = key.split(".")
    for p in parts[:-1]:
        obj = getattr(obj, p)
    setattr(obj, parts[-1], value)


def build_model(variant: str, seeds, n_train: int, dev: torch.device, backend: str):
    """(model on dev, optimizers dict, is_willags). Same Gaussians for every variant (seeded quaternions)."""
    from nerfstudio.data.scene_box import SceneBox

    _patch_knn()
    kind, overrides, wrapper = VARIANTS[variant]
    scene_box = SceneBox(aabb=torch.tensor([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]]))
    torch.manual_seed(0)  # random_quat_tensor draws from the global generator
    if kind == "stock":
        if dev.type != "cuda":
            raise RuntimeError("stock splatfacto hard-codes .cuda(): skipped without CUDA")
        import torchmetrics.image.lpip as tm_lpip
        from nerfstudio.models import splatfacto as sf

        from willags_ns.render.camera import viewmat_from_c2w

        tm_lpip.LearnedPerceptualImagePatchSimilarity = _NoLPIPS  # weights cannot be downloaded; unused here
        sf.get_viewmat = viewmat_from_c2w  # same maths without torch.compile's first-call compile
        cfg = sf.SplatfactoModelConfig(**TIMING_OVERRIDES)
        model = cfg.setup(scene_box=scene_box, num_train_data=n_train, seed_points=seeds)
        model.strategy.verbose = False
        is_willags = False
    else:
        from willags_ns import method_configs as mc
        from willags_ns.model import WillagsModelConfig

        if kind == "lite":
            cfg = copy.deepcopy(mc.willags_lite_config().pipeline.model)
        elif kind == "paper":
            cfg = mc.willags_paper_model_config()
        elif kind == "willags":
            cfg = mc.willags_model_config()
        else:
            cfg = WillagsModelConfig()
        for k, v in {**TIMING_OVERRIDES, **overrides}.items():
            _set_nested(cfg, k, v)
        cfg.backend = backend
        cfg.log_images_every = 0
        cfg.mask.warmup_steps = 0
        cfg.mask.ramp_steps = 0
        model = cfg.setup(scene_box=scene_box, num_train_data=n_train, seed_points=seeds)
        is_willags = True
    model = model.to(dev)
    model.train()
    opts = {}
    # each method's own optimiser: stock splatfacto's torch Adam; willags' FusedAdamOptimizerConfig (fused on CUDA)
    # unless the variant asks for the stock one ("foreach-adam")
    fused = is_willags and "foreach-adam" not in wrapper
    for name, params in model.get_param_groups().items():
        params = [p for p in params if p.requires_grad]
        if params:
            if fused:
                from willags_ns.method_configs import FusedAdamOptimizerConfig

                opts[name] = FusedAdamOptimizerConfig(lr=LRS.get(name, 1e-3), eps=1e-15).setup(params)
            else:
                opts[name] = torch.optim.Adam(params, lr=LRS.get(name, 1e-3), eps=1e-15)
    model.optimizers = opts
    for w in wrapper:
        if w != "foreach-adam":
            _wrap_appearance(model, w, dev)
    return model, opts, is_willags


def _wrap_appearance(model, wrapper: str, dev: torch.device) -> None:
    """Benchmark-only variants of the appearance path (tri-plane query + decoder), without touching the model.

    Applied in order, each around the previous: ("compile", "bf16") runs the compiled function under autocast.
    """
    orig = model.appearance_colors
    if wrapper == "bf16":

        def colors_bf16(*a, **k):
            with torch.autocast(device_type=dev.type, dtype=torch.bfloat16):
                out = orig(*a, **k)
            return out.float()  # the rasteriser takes float32

        model.appearance_colors = colors_bf16
    elif wrapper == "ckpt":
        from torch.utils.checkpoint import checkpoint

        def colors_ckpt(z, means, f_s, cam_center, nets=None, cacheable=False, **k):
            if nets is not None or not torch.is_grad_enabled():
                return orig(z, means, f_s, cam_center, nets=nets, cacheable=cacheable, **k)
            return checkpoint(lambda *t: orig(*t, **k), z, means, f_s, cam_center, use_reentrant=False)

        model.appearance_colors = colors_ckpt
    elif wrapper == "compile":
        compiled = torch.compile(orig, dynamic=True)

        def colors_compiled(z, means, f_s, cam_center, nets=None, cacheable=False, **k):
            if cacheable:  # the render cache keys on host values: keep it out of the graph
                return orig(z, means, f_s, cam_center, nets=nets, cacheable=cacheable, **k)
            return compiled(z, means, f_s, cam_center, nets=nets, **k)

        model.appearance_colors = colors_compiled
    else:
        raise ValueError(wrapper)


def make_camera(size: int, dev: torch.device, c2w: torch.Tensor | None = None):
    from nerfstudio.cameras.cameras import Cameras, CameraType

    if c2w is None:
        c2w = syn.orbit_c2ws(8)[1]
    f = syn.focal_for(size)
    return Cameras(
        camera_to_worlds=c2w[None].float(),
        fx=f,
        fy=f,
        cx=size / 2,
        cy=size / 2,
        width=size,
        height=size,
        camera_type=CameraType.PERSPECTIVE,
    ).to(dev)


def train_step(model, opts, camera, batch, step: int, is_willags: bool, timer: RegionTimer | None = None) -> None:
    """One nerfstudio training iteration, as Trainer + WillagsPipeline run it (callbacks included)."""
    region = timer.region if timer is not None else (lambda _label: contextlib.nullcontext())
    model.step = step  # splatfacto's step_cb
    for o in opts.values():
        o.zero_grad(set_to_none=True)
    if is_willags:
        model.set_train_batch(batch)
    outputs = model.get_outputs(camera)
    with region("metrics"):
        metrics = model.get_metrics_dict(outputs, batch)
    loss_dict = model.get_loss_dict(outputs, batch, metrics)
    loss = sum(loss_dict.values())
    with region("backward"):
        loss.backward()
    with region("optimizer"):
        for o in opts.values():
            o.step()
    with region("strategy (grad stats)"):
        model.step_post_backward(step)
    if is_willags:
        if model.teacher is not None:
            with region("teacher EMA"):
                model.update_teacher(step)
        model._end_step(step)


def install_profile(model, timer: RegionTimer, is_willags: bool) -> list:
    """Wrap the model's components with event regions (instance attributes; returns an undo list)."""
    undo = []

    def wrap(obj, name, label, on_enter=None, on_exit=None):
        orig = getattr(obj, name)

        def f(*a, **k):
            with timer.region(label):
                if on_enter:
                    on_enter()
                try:
                    return orig(*a, **k)
                finally:
                    if on_exit:
                        on_exit()

        setattr(obj, name, f)
        undo.append((obj, name))

    wrap(model, "get_outputs", "get_outputs (incl.)")
    wrap(model, "get_loss_dict", "get_loss_dict (incl.)")
    if is_willags:
        nets = model.appearance_nets
        wrap(model, "_rasterize", "rasterize")
        if nets is not None:
            if nets.vae is not None:
                wrap(nets.vae, "encode", "VAE encode")
                wrap(nets.vae, "decode", "VAE decode (loss)")
            if nets.field is not None:
                wrap(nets.field, "planes", "hypernetwork planes")
                wrap(nets.field, "query", "tri-plane query (incl.)")
                wrap(nets.field.mlp, "forward", "field MLP")
            if nets.color is not None:
                wrap(nets.color, "forward", "decoder MLP")
            if nets.modulation is not None:  # SH evaluation + local residual + colour transform, student and teacher
                wrap(model, "appearance_colors", "appearance colours (SH + modulation)")
        if model.teacher is not None:

            def enter():
                timer.suspended = True

            def leave():
                timer.suspended = False

            # the label's region opens before `enter` and closes after `leave`: it is recorded, its inside is not
            wrap(model, "_teacher_render", "teacher render", enter, leave)
        if model.perceptual is not None:
            wrap(model, "_static_mask", "VGG + mask")
    else:
        from nerfstudio.models import splatfacto as sf

        orig = sf.rasterization

        def timed(*a, **k):
            with timer.region("rasterize"):
                return orig(*a, **k)

        sf.rasterization = timed
        undo.append((sf, "rasterization", orig))
        if hasattr(model, "_rasterize"):
            wrap(model, "_rasterize", "rasterize")
    return undo


def _allocator_counts(cuda: bool) -> dict[str, int]:
    """The caching allocator's device allocations, frees and retries so far (CUDA; empty elsewhere)."""
    if not cuda:
        return {}
    st = torch.cuda.memory_stats()
    keys = ("num_device_alloc", "num_device_free", "num_alloc_retries", "num_sync_all_streams")
    return {k: int(st.get(k, 0)) for k in keys}


def kernel_profile(run_step, iters: int, top: int = 25) -> dict:
    """torch.profiler over `iters` calls of run_step(): device (kernel + copy) time per step, the kernels that take
    it (ms and launches per step) and the busy share of the wall time. Busy well below the wall time means the
    step waits on the host (launch-bound); the kernel list says where device time goes."""
    from torch.profiler import ProfilerActivity, profile

    torch.cuda.synchronize()
    with profile(activities=[ProfilerActivity.CPU, ProfilerActivity.CUDA]) as prof:
        t0 = time.perf_counter()
        for _ in range(iters):
            run_step()
        torch.cuda.synchronize()
        wall = (time.perf_counter() - t0) * 1e3 / iters
    rows = []
    for e in prof.key_averages():
        if e.device_type != torch.autograd.DeviceType.CUDA:
            continue
        us = getattr(e, "self_device_time_total", None)
        us = e.self_cuda_time_total if us is None else us
        rows.append((e.key[:120], us / 1e3 / iters, e.count / iters))
    rows.sort(key=lambda r: -r[1])
    busy = sum(r[1] for r in rows)
    return {
        "iters": iters,
        "device_busy_ms_per_step": busy,
        "wall_ms_per_step_profiled": wall,
        "launches_per_step": sum(r[2] for r in rows),
        "top_kernels": [(k, round(ms, 4), round(n, 2)) for k, ms, n in rows[:top]],
    }


def remove_profile(undo: list) -> None:
    for item in reversed(undo):
        if len(item) == 3:
            setattr(item[0], item[1], item[2])
        else:
            obj, name = item
            with contextlib.suppress(AttributeError):
                delattr(obj, name)  # back to the class attribute


def profile_table(totals: dict, steps: int, step_ms: float) -> list[tuple[str, float]]:
    """Exclusive ms per step per component, 'other' = the rest of the step."""
    t = {k: v / steps for k, v in totals.items()}
    rows = []
    for k in ("VAE encode", "hypernetwork planes"):
        if k in t:
            rows.append((k, t[k]))
    if "tri-plane query (incl.)" in t:
        rows.append(("tri-plane sampling (grid_sample)", t["tri-plane query (incl.)"] - t.get("field MLP", 0.0)))
        rows.append(("field MLP (planes -> f_d)", t.get("field MLP", 0.0)))
    for k in ("decoder MLP", "appearance colours (SH + modulation)", "rasterize", "teacher render"):
        if k in t:
            rows.append((k, t[k]))
    fwd_known = sum(
        t.get(k, 0.0)
        for k in (
            "VAE encode",
            "hypernetwork planes",
            "tri-plane query (incl.)",
            "decoder MLP",
            "appearance colours (SH + modulation)",
            "rasterize",
            "teacher render",
        )
    )
    rows.append(("forward, rest", t.get("get_outputs (incl.)", 0.0) - fwd_known))
    if "VGG + mask" in t:
        rows.append(("VGG + mask", t["VGG + mask"]))
    if "VAE decode (loss)" in t:
        rows.append(("VAE decode (loss)", t["VAE decode (loss)"]))
    rows.append(
        (
            "loss (L1 + SSIM + rest)",
            t.get("get_loss_dict (incl.)", 0.0) - t.get("VGG + mask", 0) - t.get("VAE decode (loss)", 0),
        )
    )
    for k in ("metrics", "backward", "optimizer", "strategy (grad stats)", "teacher EMA"):
        if k in t:
            rows.append((k, t[k]))
    rows.append(("other (host gaps, glue)", step_ms - sum(v for _, v in rows)))
    return rows


def section_step(args, cuda: bool, dev, backend: str, variants: list[str], memory: bool, timing: bool) -> dict:
    n, size = args.n_gaussians, args.size
    seeds = syn.seed_points(n, seed=0)
    image = syn.smooth_image(size, size, seed=1).to(dev)  # uint8 [H, W, 3], as the datamanager caches it
    batch = {"image": image, "image_idx": 0}
    camera = make_camera(size, dev)
    results: dict[str, dict] = {}
    step = STEP0
    n_it = args.iters if timing else 4
    log(f"\n## train step: N={n:,} Gaussians, {size}x{size} px, backend {backend}")
    for v in variants:
        r: dict = {}
        results[v] = r
        need = 150.0 if "compile" in VARIANTS[v][2] and cuda else 0.0  # a compile is ~1-2 min and cannot be cut
        if time.perf_counter() + need > args.step_deadline:
            r["error"] = "skipped: time budget spent"
            log(f"{v}: skipped (time budget)")
            continue
        model = opts = None
        try:
            gc.collect()
            base = 0
            if cuda:
                torch.cuda.empty_cache()
                base = torch.cuda.memory_allocated()
            t0 = time.perf_counter()
            model, opts, is_w = build_model(v, seeds, args.n_train, dev, backend)
            r["build_s"] = time.perf_counter() - t0
            r["n_gaussians"] = int(model.num_points)
            t0 = time.perf_counter()
            for _ in range(args.warmup):  # also builds the lazy VGG, the Adam states, compiled graphs
                train_step(model, opts, camera, batch, step, is_w)
                step += 1
            sync(cuda)
            r["warmup_s"] = time.perf_counter() - t0
            if cuda:
                gc.collect()
                torch.cuda.reset_peak_memory_stats()
                r["static_gb"] = (torch.cuda.memory_allocated() - base) / 2**30  # params, Adam, caches
            # The mean, not the median, is the headline: with mask_every=k one step in k also renders the teacher
            # and runs VGG (iters is a multiple of 4), and the mean is what a training run pays per step. The peak
            # VRAM is taken over the same steps, so it includes a teacher step.
            spans = []
            host = []
            alloc0 = _allocator_counts(cuda)
            t0 = time.perf_counter()
            for _ in range(n_it):
                s = Stamp(cuda)
                h0 = time.perf_counter()
                train_step(model, opts, camera, batch, step, is_w)
                host.append((time.perf_counter() - h0) * 1e3)
                spans.append((s, Stamp(cuda)))
                step += 1
            sync(cuda)
            wall = (time.perf_counter() - t0) * 1e3 / n_it
            # host ms: the CPU's time in the step (launches, Python, and its waits at host syncs); cudaMalloc /
            # cudaFree calls of the caching allocator (a cudaFree waits for the device) per step
            r["host_ms_median"] = statistics.median(host)
            alloc1 = _allocator_counts(cuda)
            r["allocator_per_step"] = {k: (alloc1[k] - alloc0[k]) / n_it for k in alloc1}
            if timing:
                ms = [s.ms_until(e) for s, e in spans]
                r.update(step_ms=statistics.fmean(ms), step_ms_median=statistics.median(ms), step_ms_wall=wall)
                r.update(step_ms_min=min(ms), step_ms_max=max(ms))
            if memory and cuda:
                r["peak_gb"] = (torch.cuda.max_memory_allocated() - base) / 2**30
            if cuda and timing:
                sites: list[str] = []
                with count_host_syncs(cuda, sites):
                    for _ in range(4):
                        train_step(model, opts, camera, batch, step, is_w)
                        step += 1
                r["host_syncs_per_step"] = len(sites) / 4
                top: dict[str, int] = defaultdict(int)
                for s_ in sites:
                    top[s_] += 1
                r["host_sync_sites"] = [(k, c / 4) for k, c in sorted(top.items(), key=lambda kv: -kv[1])[:8]]
            # (compiled variants are not profiled: the event wrappers would enter the traced graph)
            if timing and args.profile and v in args.profile_variants and "compile" not in VARIANTS[v][2]:
                timer = RegionTimer(cuda)
                undo = install_profile(model, timer, is_w)
                try:
                    for _ in range(args.profile_iters):
                        train_step(model, opts, camera, batch, step, is_w, timer)
                        step += 1
                    totals = timer.collect()
                finally:
                    remove_profile(undo)
                r["profile_ms"] = profile_table(totals, args.profile_iters, r["step_ms"])
            if cuda and timing and v in args.kernel_variants:
                at = [step]

                def one_step(m=model, o=opts, w=is_w, at=at):
                    train_step(m, o, camera, batch, at[0], w)
                    at[0] += 1

                r["kernels"] = kernel_profile(one_step, 8)  # two mask steps of four at mask_every=4
                step = at[0]
            msg = f"{v}: " + ", ".join(
                f"{k}={r[k]:.2f}"
                for k in ("step_ms", "step_ms_median", "step_ms_wall", "host_ms_median", "peak_gb", "static_gb")
                if k in r
            )
            if "host_syncs_per_step" in r:
                msg += f", host syncs/step={r['host_syncs_per_step']:.2f}"
            if r.get("allocator_per_step"):
                msg += ", allocator/step " + " ".join(f"{k}={v:g}" for k, v in r["allocator_per_step"].items())
            log(msg + f" (build {r['build_s']:.1f}s, warm-up {r['warmup_s']:.1f}s)")
        except Exception as e:
            r["error"] = short_exc(e)
            r["traceback"] = traceback.format_exc()[-2000:]
            log(f"{v}: ERROR {r['error']}")
        finally:
            del model, opts
            gc.collect()
            if cuda:
                torch.cuda.empty_cache()
    # tables
    base_name = _baseline_name(results, "step_ms")
    if timing:
        log(f"\n| variant | step ms (mean) | median | wall ms/step | ratio vs {base_name} | host syncs/step |")
        log("|---|---|---|---|---|---|")
        for v, r in results.items():
            if "step_ms" not in r:
                log(f"| {v} | {r.get('error', 'n/a')} | | | | |")
                continue
            ratio = r["step_ms"] / results[base_name]["step_ms"] if base_name else float("nan")
            r["step_ratio_vs_baseline"] = ratio
            syncs = r.get("host_syncs_per_step")
            log(
                f"| {v} | {r['step_ms']:.2f} | {r['step_ms_median']:.2f} | {r['step_ms_wall']:.2f} | {ratio:.2f} "
                f"| {'-' if syncs is None else f'{syncs:.2f}'} |"
            )
        for v, r in results.items():
            if "profile_ms" in r:
                log(f"\n### profile {v} (mean ms per step, device events, {args.profile_iters} steps)")
                log("| component | ms | share |")
                log("|---|---|---|")
                for k, ms in r["profile_ms"]:
                    log(f"| {k} | {ms:.2f} | {100 * ms / r['step_ms']:.0f}% |")
            if "kernels" in r:
                kp = r["kernels"]
                log(
                    f"\n### kernels {v} (torch.profiler, {kp['iters']} steps): device busy "
                    f"{kp['device_busy_ms_per_step']:.2f} ms/step of {kp['wall_ms_per_step_profiled']:.2f} wall "
                    f"(profiled), {kp['launches_per_step']:.0f} device ops/step"
                )
                for k, ms, n in kp["top_kernels"]:
                    log(f"| {k} | {ms:.3f} ms | x{n:g} |")
            if r.get("host_sync_sites"):
                log(f"host-sync sites {v} (per step): " + "; ".join(f"{s} x{c:g}" for s, c in r["host_sync_sites"]))
    if memory and cuda:
        mb = _baseline_name(results, "peak_gb")
        log(f"\n| variant | static GB (params, Adam, caches) | peak GB ({n_it} train steps) | extra vs {mb} |")
        log("|---|---|---|---|")
        for v, r in results.items():
            if "peak_gb" in r:
                r["extra_vram_gb"] = r["peak_gb"] - results[mb]["peak_gb"] if mb else float("nan")
                log(f"| {v} | {r['static_gb']:.3f} | {r['peak_gb']:.3f} | {r['extra_vram_gb']:+.3f} |")
    return {"baseline": base_name, "variants": results}


def _baseline_name(results: dict, key: str) -> str | None:
    for name in ("splatfacto", "willags-3dgs"):
        if key in results.get(name, {}):
            return name
    return None


# ------------------------------------------------------------------------------------------------------ render
def section_render(args, cuda: bool, dev, backend: str) -> dict:
    from willags_ns.render import rasterize

    n, size, frames = args.n_gaussians, args.size, args.frames
    seeds = syn.seed_points(n, seed=0)
    c2ws = syn.orbit_c2ws(8)
    cams = [make_camera(size, dev, c) for c in c2ws]
    out: dict = {"frames": frames, "render_mode": "RGB+ED (what get_outputs renders in eval)"}
    log(f"\n## render: N={n:,}, {size}x{size} px, {frames} frames over 8 orbit views, fixed latent, no grad")

    def fps_of(render_one) -> float:
        with torch.no_grad():
            for i in range(3):
                render_one(i)
            sync(cuda)
            t0 = time.perf_counter()
            for i in range(frames):
                render_one(i)
            sync(cuda)
        return frames / (time.perf_counter() - t0)

    holder: list = []  # the model, dropped in `finally` so the baselines below get the memory back
    try:
        holder.append(build_model("willags", seeds, args.n_train, dev, backend)[0])
        model = holder[0]
        model.eval()
        nets = model.appearance_nets
        g = torch.Generator().manual_seed(3)
        model.render_latent = (0.5 * torch.randn(nets.latent_dim, generator=g)).to(dev)
        calls = {"planes": 0}
        if nets.field is not None:  # the default has no tri-plane field
            orig_planes = nets.field.planes

            def counted(*a, **k):
                calls["planes"] += 1
                return orig_planes(*a, **k)

            nets.field.planes = counted
        out["willags_fps"] = fps_of(lambda i: model.get_outputs(cams[i % 8]))
        out["hypernetwork_calls"] = calls["planes"]  # 1 when the f_d cache holds across frames
        # the decoder every frame (render_sh_degree=-1) vs the per-appearance SH bake (default), and the bake's cost
        deg = model.config.render_sh_degree
        model.config.render_sh_degree = -1
        out["willags_exact_fps"] = fps_of(lambda i: model.get_outputs(cams[i % 8]))
        model.config.render_sh_degree = deg
        if deg >= 0:
            model.color_path.sh_cache = None
            sync(cuda)
            t_b = time.perf_counter()
            with torch.no_grad():
                model.get_outputs(cams[0])
            sync(cuda)
            out["sh_bake_ms"] = 1e3 * (time.perf_counter() - t_b)
        sites: list[str] = []
        with count_host_syncs(cuda, sites), torch.no_grad():
            model.get_outputs(cams[0])
        out["host_syncs_per_frame"] = len(sites)

        # the same Gaussians through gsplat, colours precomputed once (what an exported splat viewer does)
        with torch.no_grad():
            z = model.render_latent
            cam0 = cams[0]
            c2w0 = cam0.camera_to_worlds
            colors = model.appearance_colors(z, model.means, model.intrinsic_features, c2w0[0, :3, 3]).contiguous()
            means, quats = model.means.contiguous(), model.quats.contiguous()
            scales = torch.exp(model.scales).contiguous()
            opac = torch.sigmoid(model.opacities).squeeze(-1).contiguous()
            from willags_ns.render.camera import viewmat_from_c2w

            vms = [viewmat_from_c2w(c.camera_to_worlds) for c in cams]
            Ks = [c.get_intrinsics_matrices().to(dev) for c in cams]
        for mode in ("RGB+ED", "RGB"):
            out[f"precomputed_fps_{mode}"] = fps_of(
                lambda i, mode=mode: rasterize(
                    means,
                    quats,
                    scales,
                    opac,
                    colors,
                    vms[i % 8],
                    Ks[i % 8],
                    size,
                    size,
                    render_mode=mode,
                    backend=backend,
                )
            )
        # per-frame appearance work alone (f_d cached): what render_sh_degree=-1 pays every frame
        f_s = model.intrinsic_features
        centers = [c.camera_to_worlds[0, :3, 3] for c in cams]
        out["decoder_only_ms"] = 1e3 / fps_of(
            lambda i: model.appearance_colors(z, model.means, f_s, centers[i % 8], cacheable=True)
        )
        out["render_fps_ratio_vs_gsplat"] = out["willags_fps"] / out["precomputed_fps_RGB+ED"]
        out["baseline_backend"] = backend
    except Exception as e:
        out["error"] = short_exc(e)
        out["traceback"] = traceback.format_exc()[-2000:]
    finally:
        holder.clear()
        gc.collect()
        if cuda:
            torch.cuda.empty_cache()
    for v in ("willags-3dgs", "splatfacto"):
        m = None
        try:
            m, _, _ = build_model(v, seeds, args.n_train, dev, backend)
            m.eval()
            m.step = STEP0  # SH degree 3
            out[f"{v}_fps"] = fps_of(lambda i, m=m: m.get_outputs(cams[i % 8]))
        except Exception as e:
            out[f"{v}_error"] = short_exc(e)
        finally:
            del m
            gc.collect()
            if cuda:
                torch.cuda.empty_cache()
    if "willags_fps" in out and "splatfacto_fps" in out:
        out["render_fps_ratio_vs_splatfacto"] = out["willags_fps"] / out["splatfacto_fps"]
    log("| renderer | FPS | note |")
    log("|---|---|---|")
    for k, note in (
        (
            "willags_fps",
            f"get_outputs, fixed latent (hypernetwork calls: {out.get('hypernetwork_calls', '?')}); decoder baked to SH once per appearance ({out.get('sh_bake_ms', float('nan')):.0f} ms)",
        ),
        ("willags_exact_fps", "get_outputs, fixed latent, decoder every frame (render_sh_degree=-1)"),
        ("precomputed_fps_RGB+ED", f"rasterize ({backend}), same Gaussians, colours precomputed: the baseline"),
        ("precomputed_fps_RGB", "same, RGB only"),
        ("willags-3dgs_fps", "get_outputs with SH degree 3 (same code path)"),
        ("splatfacto_fps", "stock splatfacto get_outputs"),
    ):
        if k in out:
            log(f"| {k} | {out[k]:.1f} | {note} |")
    if "decoder_only_ms" in out:
        log(
            f"decoder per frame: {out['decoder_only_ms']:.2f} ms; host syncs per frame: {out.get('host_syncs_per_frame')}"
        )
    if "render_fps_ratio_vs_gsplat" in out:
        log(f"render_fps_ratio_vs_gsplat = {out['render_fps_ratio_vs_gsplat']:.3f} (goal >= 0.9)")
    for k in [k for k in out if k.endswith("error")]:
        log(f"{k}: {out[k]}")
    return out


# -------------------------------------------------------------------------------------------------- components
def _vgg_flops(h: int, w: int) -> float:
    """Multiply-adds x2 of VGG16 features[:16] (conv1_1 .. conv3_3) on one h x w image."""
    from willags_ns.transient import VGG16_CFG

    flops, c_in = 0.0, 3
    for v in VGG16_CFG:
        if v == "M":
            h, w = h // 2, w // 2
        else:
            flops += 2.0 * h * w * int(v) * c_in * 9
            c_in = int(v)
    return flops


def section_components(args, cuda: bool, dev, backend: str, ceilings: dict) -> dict:
    """Isolated fwd+bwd timings of the appearance path at N Gaussians, with FLOP / byte floors."""
    from willags_ns.appearance.decoder import ColorDecoder, ColorDecoderConfig
    from willags_ns.appearance.triplane import TriplaneConfig, TriplaneHyperField
    from willags_ns.render import rasterize
    from willags_ns.transient import PerceptualFeatures

    n, size = args.n_gaussians, args.size
    tp, dc = TriplaneConfig(), ColorDecoderConfig()
    field = TriplaneHyperField(
        tp.latent_dim, tp.resolution, tp.channels, tuple(tp.hyper_hidden), tp.feature_dim, tp.mlp_hidden
    ).to(dev)
    dec = ColorDecoder(tp.feature_dim, 32, dc.hidden, dc.dir_sh_degree).to(dev)
    g = torch.Generator().manual_seed(5)
    z = torch.randn(tp.latent_dim, generator=g).to(dev).requires_grad_(True)
    xyz = (torch.rand(n, 3, generator=g) * 2 - 1).to(dev).requires_grad_(True)
    f_s = torch.randn(n, 32, generator=g).to(dev).requires_grad_(True)
    dirs = torch.randn(n, 3, generator=g).to(dev)
    planes = field.planes(z).detach().requires_grad_(True)
    f_d = (0.1 * torch.randn(n, tp.feature_dim, generator=g)).to(dev).requires_grad_(True)
    w_it, it = (2, 5) if args.quick else (3, 10)

    def fb(fn, autocast: bool = False):
        def run():
            with torch.autocast(dev.type, dtype=torch.bfloat16, enabled=autocast):
                y = fn()
            y.float().sum().backward()

        return run

    def fwd(fn, autocast: bool = False):
        def run():
            with torch.no_grad(), torch.autocast(dev.type, dtype=torch.bfloat16, enabled=autocast):
                fn()

        return run

    d_in = tp.feature_dim + 32 + (dc.dir_sh_degree + 1) ** 2
    dec_macs = d_in * dc.hidden + dc.hidden * dc.hidden + dc.hidden * 3
    q_macs = 3 * tp.channels * tp.mlp_hidden + tp.mlp_hidden * tp.feature_dim + 3 * tp.channels * 4  # + bilinear taps
    plane_out = 3 * tp.channels * tp.resolution**2
    hyper_macs = (
        tp.latent_dim * tp.hyper_hidden[0] + tp.hyper_hidden[0] * tp.hyper_hidden[1] + tp.hyper_hidden[1] * plane_out
    )
    # fewest bytes: inputs read once, outputs written once (fwd), + output grads read, input grads written (bwd)
    dec_bytes_fb = 4 * n * (2 * (tp.feature_dim + 32) + 3 + 3 + 3)
    q_bytes_fb = 4 * n * (3 + tp.feature_dim + tp.feature_dim + 3) + 2 * 4 * plane_out
    items = [
        (
            "hypernetwork planes fwd+bwd",
            fb(lambda: field.planes(z)),
            6 * hyper_macs,
            4 * 3 * tp.hyper_hidden[1] * plane_out,
        ),
        ("tri-plane query fwd+bwd fp32", fb(lambda: field.query(planes, xyz)), 6 * n * q_macs, q_bytes_fb),
        ("tri-plane query fwd+bwd bf16", fb(lambda: field.query(planes, xyz), True), 6 * n * q_macs, q_bytes_fb // 2),
        ("decoder MLP fwd+bwd fp32", fb(lambda: dec(f_d, f_s, dirs)), 6 * n * dec_macs, dec_bytes_fb),
        ("decoder MLP fwd+bwd bf16", fb(lambda: dec(f_d, f_s, dirs), True), 6 * n * dec_macs, dec_bytes_fb // 2),
        (
            "query + decoder fwd (teacher)",
            fwd(lambda: dec(field.query(planes, xyz), f_s, dirs)),
            2 * n * (q_macs + dec_macs),
            4 * n * (3 + 32 + 3 + 3),
        ),
        (
            "decoder fwd (per render frame)",
            fwd(lambda: dec(f_d, f_s, dirs)),
            2 * n * dec_macs,
            4 * n * (tp.feature_dim + 32 + 3 + 3),
        ),
        (
            "decoder fwd bf16 (per frame)",
            fwd(lambda: dec(f_d, f_s, dirs), True),
            2 * n * dec_macs,
            2 * n * (tp.feature_dim + 32 + 3 + 3),
        ),
    ]
    rows = []
    peak32 = ceilings.get("matmul_fp32_TFLOPs")
    peak16 = ceilings.get("matmul_bf16_TFLOPs")
    bw = ceilings.get("copy_GBps")
    for name, fn, flops, nbytes in items:
        row = {"name": name, "flops": flops, "bytes": nbytes}
        try:
            row["ms"] = bench_fn(fn, cuda, w_it, it)
            if peak32 and bw:
                peak = peak16 if "bf16" in name else peak32
                row["floor_ms"] = max(flops / (peak * 1e9), nbytes / (bw * 1e6))
        except Exception as e:
            row["error"] = short_exc(e)
        rows.append(row)
        for t in (z, xyz, f_s, planes, f_d):
            t.grad = None
        field.zero_grad(set_to_none=True)
        dec.zero_grad(set_to_none=True)
    # VGG on GT + teacher render at the mask's resolution
    try:
        pf = PerceptualFeatures(max_resolution=512)
        imgs = torch.rand(1, 3, size, size, generator=g).to(dev)
        side = min(size, 512)
        ms = bench_fn(lambda: (pf(imgs), pf(imgs)), cuda, w_it, it)
        rows.append(
            {
                "name": f"VGG16 relu1_2..3_3 x2 at {side}px (no grad)",
                "ms": ms,
                "flops": 2 * _vgg_flops(side, side),
                "bytes": 0,
            }
        )
    except Exception as e:
        rows.append({"name": "VGG16 x2", "error": short_exc(e)})
    # gsplat (or torch) rasterisation of the benchmark scene: fwd+bwd, plain colours and SH degree 3
    try:
        from nerfstudio.models.splatfacto import SplatfactoModel

        _patch_knn()
        xyz0, rgb0 = syn.seed_points(n, seed=0)
        d, _ = SplatfactoModel.k_nearest_sklearn(None, xyz0, 3)
        scales = torch.log(torch.from_numpy(d).mean(-1, keepdim=True).repeat(1, 3)).to(dev)
        torch.manual_seed(0)
        means = xyz0.to(dev).requires_grad_(True)
        quats = torch.nn.functional.normalize(torch.randn(n, 4), dim=-1).to(dev).requires_grad_(True)
        log_s = scales.clone().requires_grad_(True)
        opa = torch.full((n,), -2.197, device=dev).requires_grad_(True)  # logit(0.1), splatfacto's init
        col = (rgb0.float() / 255).to(dev).requires_grad_(True)
        sh = torch.zeros(n, 16, 3, device=dev)
        sh[:, 0] = (col.detach() - 0.5) / 0.28209479177387814
        sh.requires_grad_(True)
        from willags_ns.render.camera import viewmat_from_c2w

        cam = make_camera(size, dev)
        vm = viewmat_from_c2w(cam.camera_to_worlds)
        K = cam.get_intrinsics_matrices().to(dev)

        def rast(colors, shd):
            def run():
                r, a, _ = rasterize(
                    means,
                    quats,
                    torch.exp(log_s),
                    torch.sigmoid(opa),
                    colors,
                    vm,
                    K,
                    size,
                    size,
                    sh_degree=shd,
                    backend=backend,
                )
                (r.sum() + a.sum()).backward()

            return run

        rows.append({"name": f"rasterize fwd+bwd RGB ({backend})", "ms": bench_fn(rast(col, None), cuda, w_it, it)})
        rows.append({"name": f"rasterize fwd+bwd SH3 ({backend})", "ms": bench_fn(rast(sh, 3), cuda, w_it, it)})
    except Exception as e:
        rows.append({"name": "rasterize", "error": short_exc(e)})
    log(
        f"\n## components at N={n:,} ({size}px for image-space ones); floors from measured ceilings {ceilings or '(none: CPU)'}"
    )
    log("| component | ms | floor ms | GFLOP | min MB |")
    log("|---|---|---|---|---|")
    for r in rows:
        if "error" in r:
            log(f"| {r['name']} | ERROR {r['error']} | | | |")
            continue
        fl = f"{r['floor_ms']:.3f}" if "floor_ms" in r else "-"
        log(f"| {r['name']} | {r['ms']:.3f} | {fl} | {r.get('flops', 0) / 1e9:.2f} | {r.get('bytes', 0) / 1e6:.0f} |")
    return {"rows": rows}


# --------------------------------------------------------------------------------------------------------- main
def build_records(res: dict, env: dict, args) -> list[dict]:
    """docs/benchmarks.json records: {"scene", "method", "device", metric fields...}."""
    scene = f"synthetic-box-{args.n_gaussians}-{args.size}px"
    common = {"device": env["device"], "torch": env["torch"], "gsplat": env.get("gsplat"), "quick": args.quick}
    records = []
    step = res.get("step", {}).get("variants", {})
    base = res.get("step", {}).get("baseline")
    parity = res.get("parity", {})
    render = res.get("render", {})
    for v, r in step.items():
        rec = {"scene": scene, "method": v, **common, "n_gaussians": r.get("n_gaussians"), "image_size": args.size}
        for k in ("step_ms", "step_ms_wall", "peak_gb", "static_gb", "extra_vram_gb", "host_syncs_per_step"):
            if k in r:
                rec[k] = r[k]
        if "step_ratio_vs_baseline" in r:
            rec["step_ratio_vs_splatfacto"] = r["step_ratio_vs_baseline"]
            rec["step_baseline"] = base
        if "error" in r:
            rec["error"] = r["error"]
        records.append(rec)
    head = next((r for r in records if r["method"] == "willags"), None)
    if head is None:
        head = {"scene": scene, "method": "willags", **common}
        records.append(head)
    if "render_fps_ratio_vs_gsplat" in render:
        head["render_fps"] = render["willags_fps"]
        head["render_fps_ratio_vs_gsplat"] = render["render_fps_ratio_vs_gsplat"]
        head["render_baseline_backend"] = render.get("baseline_backend")
    if "render_fps_ratio_vs_splatfacto" in render:
        head["render_fps_ratio_vs_splatfacto"] = render["render_fps_ratio_vs_splatfacto"]
        head["splatfacto_render_fps"] = render["splatfacto_fps"]
    if "worst_fwd" in parity:
        head["parity_fwd_rel_err"] = parity["worst_fwd"]["value"]
        head["parity_grad_rel_err"] = parity["worst_grad"]["value"]
        head["parity_mode"] = parity["mode"]
    return records


def _finite(x):
    """Strict JSON: non-finite floats become strings ("inf", "nan")."""
    if isinstance(x, float) and not math.isfinite(x):
        return str(x)
    if isinstance(x, dict):
        return {k: _finite(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_finite(v) for v in x]
    return x


def write_json(path: str | None, res: dict, env: dict, args) -> None:
    if not path:
        return
    records = _finite(build_records(res, env, args))
    res = _finite(res)
    doc = {"records": records, "environment": env, "details": res}
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    with open(path, "w") as f:
        json.dump(records, f, indent=1, default=str)
    with open(str(Path(path).with_suffix("")) + "_details.json", "w") as f:
        json.dump(doc, f, indent=1, default=str)


def summary(res: dict, env: dict, args, t_start: float) -> None:
    log("\n" + "=" * 100)
    log(
        f"# summary: {env['device']}, torch {env['torch']}, gsplat {env.get('gsplat')}, "
        f"N={args.n_gaussians:,}, {args.size}px, {time.perf_counter() - t_start:.0f}s total"
    )
    p = res.get("parity", {})
    s = res.get("step", {})
    r = res.get("render", {})
    v = s.get("variants", {})
    w = v.get("willags", {})
    rows = []
    if "worst_fwd" in p:
        rows.append(
            ("parity fwd rel err (worst)", f"{p['worst_fwd']['value']:.2e} [{p['worst_fwd']['case']}]", "<= 1e-4")
        )
        rows.append(
            ("parity grad rel err (worst)", f"{p['worst_grad']['value']:.2e} [{p['worst_grad']['case']}]", "<= 1e-3")
        )
        for k, x in p.get("worst_grad_per_param", {}).items():
            rows.append((f"  grad {k}", f"{x['value']:.2e} [{x['case']}]", ""))
    if "step_ratio_vs_baseline" in w:
        rows.append(
            (
                f"step ratio willags / {s.get('baseline')}",
                f"{w['step_ratio_vs_baseline']:.2f} ({w['step_ms']:.1f} ms)",
                "<= 1.5 (issue 11)",
            )
        )
        for name, x in v.items():
            if name != "willags" and "step_ratio_vs_baseline" in x:
                rows.append((f"  {name}", f"{x['step_ratio_vs_baseline']:.2f} ({x['step_ms']:.1f} ms)", ""))
    if "render_fps_ratio_vs_gsplat" in r:
        rows.append(
            (
                f"render FPS ratio vs {r.get('baseline_backend', 'gsplat')} (precomputed colours)",
                f"{r['render_fps_ratio_vs_gsplat']:.3f} ({r['willags_fps']:.0f} fps)",
                ">= 0.9",
            )
        )
    if "extra_vram_gb" in w:
        rows.append(("extra peak VRAM (GB)", f"{w['extra_vram_gb']:+.3f}", "<= 0.5"))
        for name, x in v.items():
            if name != "willags" and "extra_vram_gb" in x:
                rows.append((f"  {name}", f"{x['extra_vram_gb']:+.3f}", ""))
    log("| metric | value | goal |")
    log("|---|---|---|")
    for a, b, c in rows:
        log(f"| {a} | {b} | {c} |")
    for k, e in res.get("errors", {}).items():
        log(f"SECTION ERROR {k}: {e.splitlines()[-1] if e else e}")
    for k, e in res.get("skipped", {}).items():
        log(f"skipped {k}: {e}")


def parse_args(argv=None):
    ap = argparse.ArgumentParser(
        description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("--parity", action="store_true", help="torch backend vs gsplat: forward and gradient errors")
    ap.add_argument("--step", action="store_true", help="train-step time per variant + profile + host syncs")
    ap.add_argument("--render", action="store_true", help="FPS with a fixed latent vs gsplat, precomputed colours")
    ap.add_argument("--memory", action="store_true", help="peak VRAM over one train step per variant (CUDA)")
    ap.add_argument("--components", action="store_true", help="isolated fwd+bwd timings with FLOP/byte floors")
    ap.add_argument("--all", action="store_true", help="every section")
    ap.add_argument("--quick", action="store_true", help="tiny sizes (CPU smoke test, < 60 s)")
    ap.add_argument("--cpu", action="store_true", help="ignore CUDA even when present")
    ap.add_argument("--n-gaussians", type=int, default=None, help="Gaussians in the synthetic scene (1000000)")
    ap.add_argument("--size", type=int, default=None, help="image side in pixels (800)")
    ap.add_argument("--n-train", type=int, default=50, help="num_train_data given to the model")
    ap.add_argument("--warmup", type=int, default=None, help="warm-up train steps per variant (5)")
    ap.add_argument("--iters", type=int, default=None, help="timed train steps per variant (20)")
    ap.add_argument("--frames", type=int, default=None, help="timed render frames (100)")
    ap.add_argument("--variants", default=None, help=f"comma list from {','.join(VARIANTS)}")
    ap.add_argument("--no-profile", dest="profile", action="store_false", help="skip the per-component profile")
    ap.add_argument("--profile-variants", default="willags,willags-3dgs,splatfacto,willags-fast")
    ap.add_argument("--profile-iters", type=int, default=None)
    ap.add_argument(
        "--kernel-variants", default="", help="comma list: a torch.profiler kernel table for these (CUDA only)"
    )
    ap.add_argument(
        "--time-budget",
        type=float,
        default=480.0,
        help="seconds from start; sections (and step variants) that would start later are skipped. A device call is "
        "killed at 600 s, and the wheel install and imports run before this clock starts: keep <= 480",
    )
    ap.add_argument("--json-out", default=None, help="write the records (a JSON list) here, and *_details.json")
    args = ap.parse_args(argv)
    q = args.quick
    args.n_gaussians = args.n_gaussians or (3000 if q else 1_000_000)
    args.size = args.size or (64 if q else 800)
    args.warmup = args.warmup if args.warmup is not None else (1 if q else 5)
    args.iters = args.iters or (4 if q else 20)  # a multiple of 4: mask_every=4 variants average fairly
    args.frames = args.frames or (4 if q else 100)
    args.profile_iters = args.profile_iters or (4 if q else 12)
    args.variants = args.variants.split(",") if args.variants else (QUICK_VARIANTS if q else DEFAULT_VARIANTS)
    bad = [v for v in args.variants if v not in VARIANTS]
    if bad:
        ap.error(f"unknown variants {bad}; choose from {list(VARIANTS)}")
    args.profile_variants = args.profile_variants.split(",")
    args.kernel_variants = [v for v in args.kernel_variants.split(",") if v]
    if args.all or not (args.parity or args.step or args.render or args.memory or args.components):
        args.parity = args.step = args.render = args.memory = args.components = True
    return args


def main(argv=None) -> int:
    args = parse_args(argv)
    t_start = time.perf_counter()
    args.deadline = t_start + args.time_budget
    # the step section stops starting new variants early enough to leave the components section its minute
    args.step_deadline = args.deadline - (60.0 if args.components and not args.quick else 0.0)
    cuda = torch.cuda.is_available() and not args.cpu
    dev = torch.device("cuda" if cuda else "cpu")
    backend = "gsplat" if cuda else "torch"
    if not cuda and args.quick:
        torch.set_num_threads(1)  # a smoke test: steadier on a shared 2-core machine; its times are not measurements
    env = environment(cuda)
    log(f"# gpu_suite: {json.dumps(env)}")
    if not cuda:
        log("NOTE: no CUDA: gsplat parts are SKIPPED (parity compares torch fp32 with torch fp64; the step/render")
        log("      sections use the torch backend; stock splatfacto and VRAM numbers need CUDA).")
    res: dict = {"errors": {}, "skipped": {}}

    def run(name: str, fn) -> None:
        if time.perf_counter() - t_start > args.time_budget:
            res["skipped"][name] = f"time budget {args.time_budget:.0f}s spent"
            log(f"\n## {name}: skipped (time budget)")
            return
        t0 = time.perf_counter()
        try:
            res[name] = fn()
        except Exception:
            res["errors"][name] = traceback.format_exc()[-3000:]
            log(f"\n## {name}: FAILED\n{res['errors'][name]}")
        log(f"({name}: {time.perf_counter() - t0:.1f}s)")
        write_json(args.json_out, res, env, args)

    if cuda:
        run("ceilings", lambda: measure_ceilings(cuda))
        log(f"ceilings: {res.get('ceilings')}")

        def jit():
            from willags_ns.render import rasterize

            t0 = time.perf_counter()
            c = syn.make_parity_case("jit", 10, 32, 32, 0)
            t = {k: v.cuda() for k, v in c.tensors().items()}
            rasterize(
                t["means"],
                t["quats"],
                t["scales"],
                t["opacities"],
                t["colors"],
                c.viewmats.cuda(),
                c.Ks.cuda(),
                32,
                32,
                backend="gsplat",
            )
            torch.cuda.synchronize()
            return {"gsplat_first_call_s": time.perf_counter() - t0}

        run("gsplat_jit", jit)
        log(f"gsplat first call (JIT build or cache load): {res.get('gsplat_jit')}")
    if args.parity:
        run("parity", lambda: section_parity(args, cuda))
    if args.render:
        run("render", lambda: section_render(args, cuda, dev, backend))
    if args.memory and not args.step and not cuda:
        res["skipped"]["memory"] = "peak VRAM needs CUDA"
    elif args.step or args.memory:
        variants = [v for v in args.variants if cuda or VARIANTS[v][0] != "stock"]
        for v in args.variants:
            if v not in variants:
                res["skipped"][f"step:{v}"] = "stock splatfacto needs CUDA (hard-coded .cuda())"
        if not cuda:  # CPU bf16 autocast and inductor's C++ build are not the question here
            for v in [v for v in variants if set(VARIANTS[v][2]) & {"bf16", "compile"}]:
                variants.remove(v)
                res["skipped"][f"step:{v}"] = "bf16 / compile variants are measured on CUDA only"
        run("step", lambda: section_step(args, cuda, dev, backend, variants, memory=args.memory, timing=args.step))
        if args.memory and not cuda:
            res["skipped"]["memory"] = "peak VRAM needs CUDA"
    if args.components:
        run("components", lambda: section_components(args, cuda, dev, backend, res.get("ceilings", {})))
    summary(res, env, args, t_start)
    write_json(args.json_out, res, env, args)
    if args.json_out:
        log(f"records -> {args.json_out} (details: {str(Path(args.json_out).with_suffix(''))}_details.json)")
    return 1 if res["errors"] else 0


if __name__ == "__main__":
    sys.exit(main())
