"""The models the GPU suite times: the variants (a builder, config overrides, wrappers around the appearance
path), one model per variant on the same synthetic Gaussians, a camera, and one nerfstudio training iteration."""

import contextlib
import copy

import torch

from benchmarks import _synthetic_gaussians as syn
from benchmarks.suite.timing import RegionTimer

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
_FAST = {"mask.every": 4, "mask.max_resolution": 256}
VARIANTS = {
    # name: (builder, config overrides ("a.b" sets a nested field), wrappers around model.appearance_colors)
    "splatfacto": ("stock", {}, ()),
    "willags-3dgs": ("willags", {"appearance": "sh", "mask.enabled": False, "use_field": False}, ()),
    "willags": ("willags", {}, ()),  # the `willags` method's model (method_configs.willags_model_config)
    "willags-vae": ("willags", {"latent.kind": "vae"}, ()),  # ... with the beta-VAE latent
    "willags-everymask": ("willags", {"mask.every": 1, "mask.max_resolution": 512}, ()),  # the paper's mask cadence
    "willags-paper": ("paper", {}, ()),  # the paper preset (colour decoder + tri-plane field)
    "willags-2raster": ("willags", {"mask.teacher.fused": False}, ()),  # the teacher as a second rasterisation
    "willags-mask4": ("willags", {"mask.every": 4}, ()),
    "willags-vgg256": ("willags", {"mask.max_resolution": 256}, ()),
    "willags-nomask": ("willags", {"mask.enabled": False}, ()),
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
            return out._replace(rgb=out.rgb.float())  # the rasteriser takes float32

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
        model.end_step(step)
