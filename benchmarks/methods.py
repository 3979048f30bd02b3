"""The benchmarked methods and the TrainerConfig of one run.

:data:`METHODS` names every method a grid may ask for: a base trainer config (ours or nerfstudio's splatfacto)
plus model-field overrides. :func:`build_config` turns (method, steps, device, scene) into the TrainerConfig a run
trains with, what ``ns-train`` would build; :func:`apply_schedule` scales the step-based schedules to a short budget.
"""

import copy
import dataclasses
from pathlib import Path
from typing import Any


@dataclasses.dataclass(frozen=True)
class MethodSpec:
    """A benchmarked method: a base trainer config plus model-field overrides."""

    base: str
    """"willags" (the full model, no inspection), "willags-paper", "willags-lite", "willags-3dgs" (our method configs),
    "peer" (Splatfacto-W light), "peer-full" (Splatfacto-W) or "splatfacto" (stock nerfstudio)."""
    overrides: tuple[tuple[str, Any], ...] = ()
    """(model field, value) pairs applied after the base config."""
    note: str = ""
    """Shown next to the method in the tables."""
    needs_cuda: bool = False
    keep: tuple[str, ...] = ()
    """Switches the overrides set that the inspector (auto_config) must leave as they are, as a user's flags."""


PEER_BASES = ("peer", "peer-full")
"""The bases that are the peer's own model (its package on the path, its protocol adapter)."""


def is_peer(base: str) -> bool:
    return base in PEER_BASES


METHODS: dict[str, MethodSpec] = {
    # The base "willags" is the full model without inspection (base_trainer_config): every ablation below changes
    # one part of it. The method `willags` itself (ns-train willags) inspects the scene first (auto_config); its
    # records before AUTO_DEFAULT_SINCE (below, configuration()) are of the full model, now `willags-full`.
    "willags": MethodSpec(
        "willags",
        (("auto_config", True),),
        note="default: the full model with the scene inspected first (auto_config: willags-inspect switches latent / "
        "mask / sky)",
    ),
    "willags-full": MethodSpec(
        "willags",
        note="every component, no inspection: per-image embedding, SH colour x latent colour transform, teacher + "
        "mask, sky above the skyline, safeguard (the default before it inspected the scene)",
    ),
    "willags-paper": MethodSpec("willags-paper", note="the paper: beta-VAE, colour decoder over tri-plane + f_s"),
    "willags-foreachadam": MethodSpec(
        "willags",
        (("optimizers.stock_adam", True),),
        note="default with torch's foreach Adam (control of the fused one)",
    ),
    "willags-lite": MethodSpec("willags-lite", note="fast preset"),
    "willags-3dgs": MethodSpec(
        "willags-3dgs", note="plain 3DGS through willags' rasteriser: CPU stand-in for splatfacto"
    ),
    "willags-vae": MethodSpec(
        "willags",
        (("latent.kind", "vae"), ("mask.every", 1), ("mask.max_resolution", 512)),
        note="default with the paper's beta-VAE latent (mask every step)",
    ),
    "willags-slowemb": MethodSpec(
        "willags",
        (("optimizers.appearance_embed.lr", 1e-3), ("mask.every", 1), ("mask.max_resolution", 512)),
        note="per-image embedding at the shared networks' lr 1e-3 (before the embedding had its own group)",
    ),
    "willags-novae": MethodSpec(
        "willags", (("latent.kind", "embedding"),), note="= the default (per-image embedding, no VAE)"
    ),
    "willags-everymask": MethodSpec(
        "willags",
        (("mask.every", 1), ("mask.max_resolution", 512)),
        note="default with the paper's mask cadence: refreshed every step, VGG at 512 px",
    ),
    "willags-lowlr": MethodSpec(
        "willags",
        (("optimizers.means.lr", 1.6e-5), ("mask.every", 1), ("mask.max_resolution", 512)),
        note="default (mask every step), means lr 1.6e-5",
    ),
    "willags-fast": MethodSpec(
        "willags",
        (("mask.every", 4), ("mask.max_resolution", 256)),
        note="= the default's mask cadence (every 4th visit of an image, VGG at 256 px)",
    ),
    "willags-auto": MethodSpec(
        "willags",
        (("auto_config", True),),
        note="the full model with auto_config (today's default, its earlier name): willags-inspect switches latent / "
        "mask / sky",
    ),
    # willags-auto on top of the candidate defaults (auto's sky switch keeps the method's sky.region)
    "willags-auto-support": MethodSpec(
        "willags",
        (("auto_config", True), ("sky.region", "everywhere"), ("mask.safeguard.enabled", True)),
        note="auto_config with the mask's SfM-track safeguard, auto's sky behind every pixel (candidate: the safeguard alone)",
    ),
    "willags-auto-skyopen-support": MethodSpec(
        "willags",
        (("auto_config", True), ("sky.region", "open"), ("mask.safeguard.enabled", True)),
        note="auto_config with the sky above the skyline and the safeguard (candidate default: willags-skyopen-support)",
    ),
    "willags-plain": MethodSpec(
        "willags",
        (("appearance", "sh"), ("mask.enabled", False)),
        note="plain 3DGS colours with the default's antialiased rasterisation (what auto picks for a static scene)",
    ),
    "willags-nofield": MethodSpec(
        "willags-paper", (("use_field", False),), note="paper ablation: decoder without the tri-plane field"
    ),
    "willags-paper-novae": MethodSpec("willags-paper", (("latent.kind", "embedding"),), note="paper ablation: no VAE"),
    # candidates for the default, each the default (the scene inspected first) with one change
    "willags-residual": MethodSpec(
        "willags",
        (("auto_config", True), ("mask.enabled", True), ("mask.distance", "residual"), ("densification", "splatfacto")),
        note="willags-splitclone with the transient mask on every scene, by the weight-free colour residual against "
        "the teacher's render (mask.distance residual)",
        keep=("mask.enabled",),
    ),
    "willags-mcmc": MethodSpec(
        "willags",
        (("auto_config", True), ("densification", "mcmc")),
        note="the default's configuration named in full: MCMC densification (relocation, growth to 300k, position "
        "noise, opacity and scale penalties)",
    ),
    "willags-splitclone": MethodSpec(
        "willags",
        (("auto_config", True), ("densification", "splatfacto")),
        note="default with splatfacto's densification (split / clone / prune, opacity resets) in place of MCMC",
    ),
    "splatfacto": MethodSpec("splatfacto", note="stock nerfstudio splatfacto (gsplat)", needs_cuda=True),
    "peer": MethodSpec(
        "peer",
        note="the peer Splatfacto-W, light preset (KevinXu02/splatfacto-w, fetched and run beside ours)",
        needs_cuda=True,
    ),
    "peer-full": MethodSpec(
        "peer-full",
        note="the peer Splatfacto-W, its full method: background model, alpha loss, robust mask from step 6000",
        needs_cuda=True,
    ),
    # rasterize_mode "antialiased" (gsplat's opacity compensation for the 2D dilation): consistent renders across
    # resolutions, which the stock schedule (trained at 1/4 and 1/2 resolution, evaluated at full) needs
    "splatfacto-aa": MethodSpec(
        "splatfacto", (("rasterize_mode", "antialiased"),), note="stock splatfacto, antialiased", needs_cuda=True
    ),
}
# Ablations of the VAE-latent default (measured when `willags` used the beta-VAE, up to commit 46d6320): the
# default with latent.kind "vae" plus the change
for _name, _over, _note in (
    ("field", (("use_field", True),), "tri-plane field feeding the local residual"),
    ("global", (("modulation.local", False),), "global colour transform only (no local residual)"),
    ("nomask", (("mask.enabled", False),), "no transient mask"),
    ("noteacher", (("mask.teacher.enabled", False),), "the student's own render makes the mask"),
    ("classic", (("rasterize_mode", "classic"),), "classic rasterisation"),
    ("lowlr", (("optimizers.means.lr", 1.6e-5),), "means lr 1.6e-5"),
    ("fast", (("mask.every", 4), ("mask.max_resolution", 256)), "mask every 4th visit, VGG at 256 px"),
):
    METHODS[f"willags-vae-{_name}"] = MethodSpec(
        "willags",
        (("latent.kind", "vae"), ("mask.every", 1), ("mask.max_resolution", 512), *_over),
        note=f"VAE latent, {_note}",
    )
# ablations of the default itself
for _name, _over, _note in (
    ("field", (("use_field", True),), "tri-plane field feeding the local residual"),
    ("nomask", (("mask.enabled", False),), "no transient mask"),
    ("noteacher", (("mask.teacher.enabled", False),), "the student's own render makes the mask"),
    ("global", (("modulation.local", False),), "global colour transform only"),
    ("classic", (("rasterize_mode", "classic"),), "classic rasterisation"),
    ("sh1", (("sh_degree", 1),), "SH degree 1 (less view-dependent colour to overfit)"),
    ("sh0", (("sh_degree", 0),), "SH degree 0 (no view-dependent colour)"),
    ("scalereg", (("use_scale_regularization", True),), "splatfacto's scale regularisation"),
    ("dense", (("densify_grad_thresh", 0.0004),), "densify at half splatfacto's gradient threshold"),
    ("sparse", (("densify_grad_thresh", 0.0016),), "densify at twice splatfacto's gradient threshold"),
    (
        "sky",
        (("sky.enabled", True), ("sky.region", "everywhere"), ("mask.safeguard.enabled", False)),
        "appearance-conditioned sky behind every pixel, no safeguard",
    ),
    (
        "skyalpha",
        (
            ("sky.enabled", True),
            ("sky.region", "everywhere"),
            ("sky.alpha_penalty", 0.1),
            ("mask.safeguard.enabled", False),
        ),
        "sky everywhere, Gaussians pay alpha where the sky alone explains the photo, no safeguard",
    ),
    (
        "skyalpha-nomask",
        (
            ("sky.enabled", True),
            ("sky.region", "everywhere"),
            ("sky.alpha_penalty", 0.1),
            ("mask.enabled", False),
        ),
        "sky everywhere with the alpha penalty, no transient mask",
    ),
    (
        "sky-sh1",
        (("sky.enabled", True), ("sky.region", "everywhere"), ("mask.safeguard.enabled", False), ("sh_degree", 1)),
        "sky everywhere and SH degree 1, no safeguard",
    ),
    # the sky and the safeguard (settings named in full, so each keeps its meaning whatever the default has):
    # the mask's SfM-track safeguard, and the first candidate default (sky with its alpha penalty and the safeguard),
    # measured with 2 seeds on the six shared scenes (h200-r2) and rejected: -0.5 to -1.8 dB
    (
        "support",
        (("sky.enabled", False), ("mask.safeguard.enabled", True)),
        "the mask's SfM-track safeguard (mask.safeguard), no sky",
    ),
    (
        "skyalpha-support",
        (
            ("sky.enabled", True),
            ("sky.region", "everywhere"),
            ("sky.alpha_penalty", 0.1),
            ("mask.safeguard.enabled", True),
        ),
        "sky with the alpha penalty and the mask's safeguard (a candidate default, rejected)",
    ),
    # the sky only above each training photo's SfM skyline, random background elsewhere (sky.region "open"), so the
    # scene's Gaussians stay opaque; alone and with the safeguard. The pair is the default's setting
    # (h200-r3: better on all three real scenes, 2 seeds each; willags-skyopen-support = willags)
    (
        "skyopen",
        (("sky.enabled", True), ("sky.region", "open"), ("mask.safeguard.enabled", False)),
        "sky above each training photo's SfM skyline only (sky.region open), no safeguard",
    ),
    (
        "skyopen-support",
        (("sky.enabled", True), ("sky.region", "open"), ("mask.safeguard.enabled", True)),
        "sky above the skyline only, and the mask's safeguard (= the default)",
    ),
    (
        "prev",
        (("sky.enabled", False), ("mask.safeguard.enabled", False)),
        "the default without the sky and the safeguard",
    ),
    ("gamma", (("modulation.gamma", True),), "per-channel gamma g(z) in the global colour transform"),
    # the local residual's price and width (modulation.local_penalty 0.01, local_hidden 64): tried because the
    # peer's oracle beats the default's by 1.7 dB on reichstag's one test view with a dark, cloudy sky (06373813),
    # a loss of capacity, not inference; measured, none of the three moves it (records h100-r10, h100-r10b)
    ("lowpen", (("modulation.local_penalty", 0.001),), "local residual penalised at a tenth (0.001)"),
    ("nopen", (("modulation.local_penalty", 0.0),), "local residual unpenalised"),
    (
        "widelocal",
        (("modulation.local_hidden", 128), ("modulation.latent_proj", 32), ("modulation.local_penalty", 0.001)),
        "local residual twice as wide (hidden 128, z projected to 32), penalised at 0.001",
    ),
):
    METHODS[f"willags-{_name}"] = MethodSpec("willags", _over, note=f"default, {_note}")
BASELINES = ("splatfacto", "willags-3dgs")
"""Baseline for the goals, in order of preference: stock splatfacto where it ran, else the CPU stand-in."""


def apply_schedule(config, steps: int, schedule: str = "short") -> None:
    """Set the step budget, and for ``schedule="short"`` scale every step-based schedule to it (all methods alike).

    "default": only ``max_num_iterations`` changes (what ``ns-train <method> --max-num-iterations N`` does).
    "short": the demo's short-run schedule (willags_ns/scripts/demo.py::train_args): full resolution from the
    first step (num_downscales 0), densification from steps/6 (at least 50) every 50 steps until 0.8 * steps, no
    opacity reset, the transient mask from steps/4, and learning-rate schedules that end at `steps`.
    """
    if schedule not in ("short", "default"):
        raise ValueError(f"unknown schedule {schedule!r} (short | default)")
    config.max_num_iterations = steps
    if schedule == "default":
        return
    m = config.pipeline.model
    m.num_downscales = 0
    m.warmup_length = max(50, steps // 6)
    m.refine_every = 50
    m.reset_alpha_every = 1000  # x refine_every steps: never within a short run
    m.stop_split_at = int(steps * 0.8)
    if hasattr(m, "mask"):
        m.mask.warmup_steps = steps // 4
    for group in config.optimizers.values():
        sched = group.get("scheduler")
        if sched is not None and hasattr(sched, "max_steps"):
            sched.max_steps = steps
            if getattr(sched, "warmup_steps", 0) and sched.warmup_steps >= steps:
                sched.warmup_steps = max(1, steps // 10)


def set_nested(obj, dotted: str, value) -> None:
    """setattr through a dotted path ("modulation.local"): the overrides of a MethodSpec."""
    from willags_ns.config import RENAMED, renamed_message

    if dotted in dict(RENAMED):  # an earlier version's name: say the new one
        raise AttributeError(renamed_message(dotted) + f" (override {dotted!r})")
    *parents, leaf = dotted.split(".")
    for p in parents:
        obj = getattr(obj, p)
    if not hasattr(obj, leaf):
        raise AttributeError(f"{type(obj).__name__} has no field {leaf!r} (override {dotted!r})")
    setattr(obj, leaf, value)


def set_lr(config, dotted: str, lr: float) -> None:
    """ "optimizers.<group>.lr": that group's Adam learning rate; its scheduler's final rate keeps its ratio."""
    _, group, leaf = dotted.split(".")
    if leaf != "lr" or group not in config.optimizers:
        raise KeyError(f"override {dotted!r}: want optimizers.<group>.lr with group in {sorted(config.optimizers)}")
    opt = config.optimizers[group]["optimizer"]
    sched = config.optimizers[group].get("scheduler")
    if sched is not None and getattr(sched, "lr_final", None) is not None:
        sched.lr_final = sched.lr_final * lr / opt.lr
    opt.lr = lr


def stock_adam(config) -> None:
    """Every group's optimiser as splatfacto's torch Adam (foreach), same settings: the control of the fused one."""
    from nerfstudio.engine.optimizers import AdamOptimizerConfig

    for group in config.optimizers.values():
        o = group["optimizer"]
        group["optimizer"] = AdamOptimizerConfig(lr=o.lr, eps=o.eps, max_norm=o.max_norm, weight_decay=o.weight_decay)


AUTO_DEFAULT_SINCE = "2026-11-25T20:05:00"
"""From here on (a record is dated when its run starts) the method `willags` inspects the scene first
(auto_config); its earlier records are of the full model without inspection, the configuration now named
`willags-full` (at its version of the time: the default changed before, see docs/design.md)."""


AUTO_SAME_SINCE = "2026-11-25T15:26:40"
"""From here on (commit 7bf8eff: the full model's sky and safeguard, the inspector's transient threshold 0.12)
`willags-auto` ran the default of its time; benchmarks/generalisation.py dates its records from it too."""


MCMC_DEFAULT_SINCE = "2026-11-27T16:30:00"
"""From here on `willags` densifies by MCMC (splats/mcmc.py); its earlier records since AUTO_DEFAULT_SINCE are of
the configuration now named `willags-splitclone`, and `willags-mcmc` records are today's `willags`. (`willags-full`
and the ablations of the default recorded before it densified as splatfacto does.)"""


def configuration(rec: dict[str, Any]) -> str:
    """The method name of the configuration a record measured: its own, except `willags` records from before
    AUTO_DEFAULT_SINCE, which are `willags-full`, and from before MCMC_DEFAULT_SINCE, which are
    `willags-splitclone`; `willags-mcmc` records, which are today's `willags`. Undated records keep their name."""
    method = str(rec.get("method"))
    date = str(rec.get("date") or "")
    if method == "willags" and date and date < AUTO_DEFAULT_SINCE:
        return "willags-full"
    if method == "willags" and date and date < MCMC_DEFAULT_SINCE:
        return "willags-splitclone"
    if method == "willags-auto" and date >= AUTO_SAME_SINCE:
        return "willags-splitclone"
    if method == "willags-mcmc":
        return "willags"
    return method


def base_trainer_config(base: str):
    """A fresh TrainerConfig of `base` (our method configs or nerfstudio's splatfacto with our data parser)."""
    from willags_ns import method_configs as mc
    from willags_ns.data.dataparser import WillagsDataParserConfig

    if is_peer(base):
        from benchmarks.peer import peer_trainer_config

        return peer_trainer_config(full=base == "peer-full")
    if base == "splatfacto":
        from nerfstudio.configs.method_configs import method_configs as ns_methods

        config = copy.deepcopy(ns_methods["splatfacto"])
        # the same parser (splits, downscale, default scene, COLMAP) as every other method
        config.pipeline.datamanager.dataparser = WillagsDataParserConfig()
        return config
    factory = {
        "willags": mc.willags_full_config,  # the full model: METHODS' overrides (auto_config too) apply to it
        "willags-paper": mc.willags_paper_config,
        "willags-lite": mc.willags_lite_config,
        "willags-3dgs": mc.willags_3dgs_config,
    }
    return factory[base]()


def build_config(
    method: str,
    steps: int,
    device_type: str,
    data: Path | None,
    downscale: int | None,
    schedule: str,
    output_dir: Path,
):
    """The TrainerConfig of one benchmark run (saved to output_dir like ns-train would)."""
    spec = METHODS[method]
    config = base_trainer_config(spec.base)
    apply_schedule(config, steps, schedule)
    config.method_name = method
    config.vis = "tensorboard"
    config.output_dir = output_dir
    config.experiment_name = "bench"
    config.timestamp = "run"
    config.machine.device_type = device_type
    config.steps_per_save = steps
    # no evaluation while training: train_s is training only; everything is measured after it
    config.steps_per_eval_image = 0
    config.steps_per_eval_batch = 0
    config.steps_per_eval_all_images = 0
    dm = config.pipeline.datamanager
    dm.data = data
    dm.dataparser.data = data
    if downscale is not None and downscale > 1:
        dm.dataparser.downscale_factor = downscale
    m = config.pipeline.model
    for k, v in spec.overrides:
        if k == "optimizers.stock_adam" and v:
            stock_adam(config)
        elif k.startswith("optimizers."):
            set_lr(config, k, v)
        else:
            set_nested(m, k, v)
    if spec.keep:
        config.pipeline.auto_config_keep = tuple(sorted({*config.pipeline.auto_config_keep, *spec.keep}))
    if hasattr(m, "log_images_every"):
        m.log_images_every = 0
    return config
