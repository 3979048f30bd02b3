"""The benchmarked methods and the TrainerConfig of one run.

:data:`METHODS` names every method a run may ask for: a base trainer config (ours, nerfstudio's splatfacto or the
peer's) plus model-field overrides. :func:`build_config` turns (method, steps, device, scene) into the TrainerConfig
a run trains with, what ``ns-train`` would build; :func:`apply_schedule` scales the step-based schedules to a short
budget. :func:`configuration` names the configuration a record measured (records keep the method name they ran as).
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
    """(dotted model field, value) pairs applied after the base config; a field under "optimizers." names a parameter
    group's learning rate instead ("optimizers.means.lr", its schedule's end "optimizers.means.lr_final")."""
    note: str = ""
    """What the method is, kept in its records."""
    needs_cuda: bool = False
    keep: tuple[str, ...] = ()
    """Switches the overrides set that the inspector (auto_config) must leave as they are, as a user's flags."""


def is_peer(base: str) -> bool:
    """Whether ``base`` is the peer's own model (its package on the path, its protocol adapter)."""
    return base in ("peer", "peer-full")


_AUTO = ("auto_config", True)


_NO_PRIOR = ("latent.prior_weight", 0.0)
"""The latent table without its prior (the default's is 0.002): the configurations measured without it name it, so
that their records say what they measured."""

_PRIOR_LOW = ("latent.prior_weight", 0.002)
"""The default's own latent prior, named: the candidates measured against the default set it explicitly, so that their
records say what they measured whatever the default's weight becomes."""


_EARLY_MASK = (("mask.warmup_steps", 500), ("mask.start_rule", "always"))
"""The mask's start before the start rule was the default's: from step 500, whatever the renders leave. Every
configuration measured with it names it (with the mask off it changes nothing), so that its records say what they
measured and a new run of it trains the same model; `willags-earlymask` is the default with it."""

_START_RULE = (("mask.warmup_steps", 5000), ("mask.start_rule", "transients"))
"""The default's own mask start, named: a candidate on today's default sets it explicitly, so that its records say
what they measured whatever the default's start becomes (as _PRIOR_LOW for the prior)."""

_RESIDUAL_MASK = (("mask.enabled", True), ("mask.distance", "residual"))
"""The transient mask on every scene, by the colour residual to the teacher (the inspector keeps it: keep=...)."""


def _masked_on_gpu(*overrides: tuple[str, Any], note: str) -> MethodSpec:
    """The default as a GPU trains it with the residual mask forced on every scene, and `overrides` on top."""
    return MethodSpec("willags", (_AUTO, *_RESIDUAL_MASK, ("densification", "mcmc"), *_EARLY_MASK, *overrides),
                      note=note, keep=("mask.enabled",))  # fmt: skip


def _default_on_gpu(*overrides: tuple[str, Any], note: str, keep: tuple[str, ...] = ()) -> MethodSpec:
    """The default as a GPU trains it (the scene inspected, MCMC's densification) with `overrides` on top: one
    switch changed against `willags-mcmc`."""
    return MethodSpec("willags", (_AUTO, ("densification", "mcmc"), *overrides), note=note, keep=keep)


def _early_mask_on_gpu(*overrides: tuple[str, Any], note: str, keep: tuple[str, ...] = ()) -> MethodSpec:
    """_default_on_gpu with the mask's start of the configurations measured before the start rule (_EARLY_MASK):
    the inspector's mask, where it turns it on, from step 500 whatever the renders leave."""
    return _default_on_gpu(*_EARLY_MASK, *overrides, note=note, keep=keep)


METHODS: dict[str, MethodSpec] = {
    # The base "willags" is the full model without inspection (base_trainer_config); the method `willags` itself
    # (ns-train willags) inspects the scene first (auto_config).
    "willags": MethodSpec("willags", (_AUTO,), note="the default: the full model with the scene inspected first"),
    "willags-full": MethodSpec(
        "willags", (_NO_PRIOR, *_EARLY_MASK), note="every component, no inspection, no latent prior"
    ),
    "willags-paper": MethodSpec("willags-paper", note="the paper: beta-VAE, colour decoder over tri-plane + f_s"),
    "willags-lite": MethodSpec("willags-lite", note="fast preset"),
    "willags-3dgs": MethodSpec(
        "willags-3dgs", note="plain 3DGS through willags' rasteriser: CPU stand-in for splatfacto"
    ),
    "willags-mcmc": MethodSpec(
        "willags", (_AUTO, ("densification", "mcmc")), note="the default named in full on a GPU (MCMC densification)"
    ),
    "willags-noprior": _early_mask_on_gpu(_NO_PRIOR, note="the default without the latent prior on its table's rows"),
    "willags-splitclone": MethodSpec(
        "willags",
        (_AUTO, ("densification", "splatfacto"), _NO_PRIOR, *_EARLY_MASK),
        note="willags-noprior with splatfacto's split / clone / prune",
    ),
    "willags-residual": MethodSpec(
        "willags",
        (_AUTO, *_RESIDUAL_MASK, ("densification", "splatfacto"), _NO_PRIOR, *_EARLY_MASK),
        note="willags-splitclone with the transient mask on every scene, by the colour residual to the teacher",
        keep=("mask.enabled",),
    ),
    "willags-mask": _masked_on_gpu(
        _NO_PRIOR, note="willags-noprior with the transient mask on every scene, by the colour residual to the teacher"
    ),
    "willags-cap150k": _early_mask_on_gpu(
        ("mcmc.cap_max", 150_000), _NO_PRIOR, note="willags-noprior, MCMC capped at 150k"
    ),
    "willags-cap1m": _early_mask_on_gpu(
        ("mcmc.cap_max", 1_000_000), _NO_PRIOR, note="willags-noprior, MCMC capped at 1M"
    ),
    "willags-capscene": _early_mask_on_gpu(
        ("mcmc.cap_rule", "pixels"),
        _NO_PRIOR,
        note="willags-noprior, MCMC's cap from the training photos' megapixels (splats/mcmc.scene_cap)",
    ),
    "willags-field": _early_mask_on_gpu(
        ("use_field", True),
        _NO_PRIOR,
        note="willags-noprior with the latent-conditioned tri-plane field on (its feature feeds the per-Gaussian "
        "residual)",
        keep=("use_field",),
    ),
    "willags-prior": _early_mask_on_gpu(
        ("latent.prior_weight", 0.02),
        note="the default with ten times its latent prior (0.02, the pull the VAE's KL puts on its latent)",
    ),
    "willags-prior-low": _default_on_gpu(
        _PRIOR_LOW,
        note="the default's own prior weight named (0.002, a tenth of willags-prior's): the same model as willags",
    ),
    "willags-earlymask": _early_mask_on_gpu(
        note="the default with the inspector's mask, where it turns it on, from step 500 whatever the renders leave "
        "(mask.warmup_steps 500, mask.start_rule always): what the default was before its mask's start rule; where "
        "the mask is off the default's model",
    ),
    "willags-prior-low-mask": _masked_on_gpu(
        _PRIOR_LOW,
        note="the default (its prior weight named) with the transient mask on every scene, by the colour residual to "
        "the teacher",
    ),
    "willags-prior-low-nomask": _default_on_gpu(
        _PRIOR_LOW,
        ("mask.enabled", False),
        note="the default (its prior weight named) with the transient mask off on every scene, also where the "
        "inspector turns it on (sacre-coeur-mini, hochiminh-mausoleum): what the mask changes there; elsewhere the "
        "default's model, whose runs it takes (cv.BORROWS)",
        keep=("mask.enabled",),
    ),
    "willags-prior-low-maskres": _early_mask_on_gpu(
        _PRIOR_LOW,
        ("mask.distance", "residual"),
        note="the default (its prior weight named) with its mask, where the inspector turns it on, comparing the photo "
        "with the teacher by the colour residual instead of the features of VGG16 (a seeded random VGG16 where no "
        "ImageNet weights are on the machine): the residual mask drops 1-9 % of the training pixels where it was "
        "forced on, the seeded VGG mask 15-22 % where the inspector turned it on; elsewhere the default's model, "
        "whose runs it takes (cv.BORROWS)",
    ),
    "willags-prior-low-mask5k": _early_mask_on_gpu(
        _PRIOR_LOW,
        ("mask.warmup_steps", 5000),
        note="the default (its prior weight named) with its mask, where the inspector turns it on, applied from step "
        "5000 instead of 500: on hochiminh-mausoleum what the mask drops renders at 10-12 dB and the mask off scored "
        "1.6 dB higher, as if the mask dropped what the latent had not yet learned of a large appearance change; "
        "elsewhere the default's model, whose runs it takes (cv.BORROWS)",
    ),
    "willags-prior-low-mask5k-gate": _default_on_gpu(
        _PRIOR_LOW,
        ("mask.warmup_steps", 5000),
        ("mask.start_rule", "transients"),
        note="the default with its mask's start named (the same model as willags, whose rows its records join): "
        "willags-prior-low-mask5k whose mask starts at step 5000 only where the training photos' own renders then "
        "leave at least 10 % of their pixels as residual blobs (mask.start_rule transients, willags_ns/mask/rule.py "
        "mask_start): at step 5000 with the mask not yet started, fox-wild's renders left 11.8-13.1 % (the mask then "
        "gained there), hochiminh-mausoleum's 5.0-7.3 % and sacre-coeur-mini's 3.0-3.7 % (the mask off scored 1.6 dB "
        "higher on the first); elsewhere the default's model, whose runs it takes (cv.BORROWS)",
    ),
    "willags-prior-low-mask-expected": _masked_on_gpu(
        _PRIOR_LOW,
        ("mask.residual.expected", True),
        note="willags-prior-low-mask thresholding the residual beyond the scene's expected residual at each pixel "
        "(mask/expected.py: a level per Gaussian fitted over every photo)",
    ),
    "willags-prior-low-mask-late": _masked_on_gpu(
        _PRIOR_LOW,
        ("mask.warmup_steps", 5000),
        note="willags-prior-low-mask with the mask from step 5000: the mask held reichstag from 5000 to 15000 steps "
        "where the default lost, and cost most before 5000",
    ),
    "willags-prior-low-mask-expected-late": _masked_on_gpu(
        _PRIOR_LOW,
        ("mask.residual.expected", True),
        ("mask.warmup_steps", 5000),
        note="willags-prior-low-mask-expected with the mask from step 5000",
    ),
    "willags-prior-low-sky": _early_mask_on_gpu(
        _PRIOR_LOW,
        ("sky.enabled", True),
        note="the default (its prior weight named) with the sky above each photo's skyline on every scene: the "
        "inspector leaves it off below 0.15 of open background (westminster-abbey 0.148, south-building 0.05)",
        keep=("sky.enabled",),
    ),
    "willags-prior-low-meanslr": _early_mask_on_gpu(
        _PRIOR_LOW,
        ("optimizers.means.lr", 1.6e-5),
        ("optimizers.means.lr_final", 1.6e-7),
        note="the default (its prior weight named) with the light peer's learning rate for the means (1.6e-5 to "
        "1.6e-7, a tenth of splatfacto's; MCMC's position noise follows it): the geometry moves less, where the "
        "default's training photos rise with length while its new photos fall on the crowded collections",
    ),
    "willags-prior-low-camopt": _early_mask_on_gpu(
        _PRIOR_LOW,
        ("camera_optimizer.mode", "SO3xR3"),
        note="the default (its prior weight named) refining each training photo's pose as it trains (nerfstudio's "
        "camera optimiser, splatfacto's rate for it): a textured collection's photo against itself shifted by one "
        "pixel scores 24-28 dB, and COLMAP's reprojection residuals are 0.3-0.65 px; test photos keep their COLMAP "
        "poses, as the protocol has them",
    ),
    "willags-prior-low-holdout": _early_mask_on_gpu(
        _PRIOR_LOW,
        ("holdout.photos", 8),
        note="the default (its prior weight named) with the right halves of 8 training photos (at most a quarter) "
        "held out of the loss and scored every 1000 steps from step 3000; the run ends with its best-scoring step "
        "when the last scores 0.1 dB worse: reichstag and westminster-abbey score higher at 5000 steps than at 15000",
    ),
    "willags-prior-low-mask-expected-cap1m": _masked_on_gpu(
        _PRIOR_LOW,
        ("mask.residual.expected", True),
        ("mcmc.cap_max", 1_000_000),
        note="willags-prior-low-mask-expected with MCMC's cap at 1M Gaussians: the capacity a million gave the clean "
        "collections, with the mask keeping it off the crowds that a million learned on reichstag",
    ),
    "willags-prior-low-cap1m": _early_mask_on_gpu(
        _PRIOR_LOW,
        ("mcmc.cap_max", 1_000_000),
        note="the default (its prior weight named) with MCMC's cap at 1M Gaussians instead of 300,000",
    ),
    "willags-startrule-cap1m": _default_on_gpu(
        _PRIOR_LOW,
        *_START_RULE,
        ("mcmc.cap_max", 1_000_000),
        note="the default (its prior and its mask's start named) with MCMC's cap at 1M Gaussians: "
        "willags-prior-low-cap1m on today's default; where the inspector keeps the mask off the same model, whose "
        "runs it takes (cv.BORROWS), so it needs runs only on the masked folds and the collections cap1m lacks",
    ),
    "willags-prior-low-captransients": _early_mask_on_gpu(
        _PRIOR_LOW,
        ("mcmc.cap_rule", "transients"),
        note="the default (its prior weight named) with MCMC's cap set by the transients rule: 300,000 until MCMC fills "
        "them, then 1,000,000 where the training photos leave under 2 % of their pixels as residual blobs",
    ),
    "willags-prior-low-captransients25": _early_mask_on_gpu(
        _PRIOR_LOW,
        ("mcmc.cap_rule", "transients"),
        ("mcmc.clean_share", 0.025),
        note="the transients rule with its bar at 2.5 % instead of 2 %: the bar at which the rule's own runs and the "
        "million's, composed fold by fold from their measured shares, scored highest over the six collections "
        "(`python -m benchmarks cv bar`); a bar read off the runs it scores is in-sample, so these runs test it",
    ),
    "willags-prior-low-lowpen": _early_mask_on_gpu(
        _PRIOR_LOW,
        ("modulation.local_penalty", 0.001),
        note="the default (its prior weight named) with a tenth of the per-Gaussian residual's penalty (0.001)",
    ),
    "willags-prior-low-proj64": _early_mask_on_gpu(
        _PRIOR_LOW,
        ("modulation.latent_proj", 64),
        note="the default (its prior weight named) with the latent projected to 64 instead of 16 before the "
        "per-Gaussian residual: the photo's latent shifts the residual's hidden layer along up to as many directions "
        "as the latent has (32 or 64) instead of 16; read at the mean latent instead of the fitted one, the residual "
        "scores 0.48 dB lower over four collections, so the latent's path into it carries to new photos. The same "
        "per-Gaussian work (the latent's share is one vector added to the hidden layer)",
    ),
    "willags-prior-low-latent8": _early_mask_on_gpu(
        _PRIOR_LOW,
        ("latent.dim", 8),
        note="the default (its prior weight named) with an 8-d latent on every scene instead of the inspector's 32 or "
        "64: a photo's appearance fitted on the left half through fewer directions, so less of the fit is spent on "
        "what only the left half shows",
        keep=("latent.dim",),
    ),
    "willags-prior-low-field": _early_mask_on_gpu(
        _PRIOR_LOW,
        ("use_field", True),
        note="the default (its prior weight named) with the latent-conditioned tri-plane field on (its feature feeds "
        "the per-Gaussian residual): the paper's spatially varying appearance at the deciding length",
        keep=("use_field",),
    ),
    "willags-prior-low-capscene": _early_mask_on_gpu(
        _PRIOR_LOW,
        ("mcmc.cap_rule", "pixels"),
        note="the default (its prior weight named) with MCMC's cap from the training photos' megapixels "
        "(splats/mcmc.scene_cap): a 12-photo collection is not given the Gaussians of a 128-photo one",
    ),
    "willags-prior-low-capshrink": _early_mask_on_gpu(
        _PRIOR_LOW,
        ("mcmc.cap_rule", "pixels"),
        ("mcmc.cap_ceiling", 300_000),
        note="the default (its prior weight named) with MCMC's cap from the training photos' megapixels, never above "
        "the default's 300,000 (splats/mcmc.scene_cap): fewer Gaussians where fewer pixels pin them down, the "
        "default's cap on collections with more; it trains the default's model wherever the rule reaches 300,000",
    ),
    "willags-prior-low-sh1": _early_mask_on_gpu(
        _PRIOR_LOW,
        ("sh_degree", 1),
        note="the default (its prior weight named) with the Gaussians' SH at degree 1 instead of 3: 12 colour "
        "coefficients a Gaussian instead of 48, so a collection of few photos fits less view dependence that a "
        "new view does not share",
    ),
    "willags-prior-low-sfmdepth": _early_mask_on_gpu(
        _PRIOR_LOW,
        ("sfm_depth.weight", 0.1),
        note="the default (its prior weight named) with the SfM depth loss at 0.1: each training render's expected "
        "depth held to the depths of its photo's own SfM points (track >= 3), so that novel views see the "
        "geometry the photos agree on rather than what fits one photo's colours",
    ),
    "willags-prior-low-mcmcreg": _early_mask_on_gpu(
        _PRIOR_LOW,
        ("mcmc.opacity_reg", 0.001),
        ("mcmc.scale_reg", 0.001),
        note="the default (its prior weight named) with a tenth of MCMC's opacity and scale penalties (0.001 each): "
        "the default fits its training photos 1.6-12.5 dB below the light peer and a million Gaussians did not close "
        "that, while these penalties pull every Gaussian towards transparent and small",
    ),
    "willags-lowpen": _early_mask_on_gpu(
        ("modulation.local_penalty", 0.001),
        _NO_PRIOR,
        note="willags-noprior with a tenth of the per-Gaussian residual's penalty (0.001)",
    ),
    "willags-staticres": _early_mask_on_gpu(
        ("modulation.latent_proj", 0),
        _NO_PRIOR,
        note="willags-noprior with a per-Gaussian residual that does not see the latent (a static colour scale and "
        "offset)",
    ),
    "willags-cap1m-mask": _masked_on_gpu(
        ("mcmc.cap_max", 1_000_000),
        _NO_PRIOR,
        note="willags-cap1m with the transient mask on every scene, by the colour residual to the teacher",
    ),
    "splatfacto": MethodSpec("splatfacto", note="stock nerfstudio splatfacto (gsplat)", needs_cuda=True),
    # antialiased: gsplat's opacity compensation for the 2D dilation, consistent renders across resolutions
    "splatfacto-aa": MethodSpec(
        "splatfacto", (("rasterize_mode", "antialiased"),), note="stock splatfacto, antialiased", needs_cuda=True
    ),
    "peer": MethodSpec("peer", note="the peer Splatfacto-W, light preset (KevinXu02/splatfacto-w)", needs_cuda=True),
    "peer-full": MethodSpec("peer-full", note="the peer Splatfacto-W, its full method", needs_cuda=True),
}


def apply_schedule(config, steps: int, schedule: str = "short") -> None:
    """Set the step budget, and for ``schedule="short"`` scale every step-based schedule to it (all methods alike).

    "default": only ``max_num_iterations`` changes (what ``ns-train <method> --max-num-iterations N`` does).
    "short": the demo's short-run schedule (willags_ns/scripts/demo.py::train_args): full resolution from the
    first step (num_downscales 0), densification from steps/6 (at least 50) every 50 steps until 0.8 * steps, no
    opacity reset, the transient mask from steps/4 (whatever step a method's overrides start it at), and
    learning-rate schedules that end at `steps`.
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
    """setattr through a dotted path ("mask.distance"): the overrides of a MethodSpec."""
    from willags_ns.config import RENAMED, renamed_message

    if dotted in dict(RENAMED):  # an earlier version's name: say the new one
        raise AttributeError(renamed_message(dotted) + f" (override {dotted!r})")
    *parents, leaf = dotted.split(".")
    for p in parents:
        obj = getattr(obj, p)
    if not hasattr(obj, leaf):
        raise AttributeError(f"{type(obj).__name__} has no field {leaf!r} (override {dotted!r})")
    setattr(obj, leaf, value)


OPTIMIZERS = "optimizers."
"""The prefix of an override that sets a parameter group's learning rate (set_learning_rate), not a model field."""


def set_learning_rate(optimizers: dict, dotted: str, value: float) -> None:
    """Set "optimizers.<group>.lr" (the optimiser's rate) or "optimizers.<group>.lr_final" (where its exponential
    schedule ends) in a TrainerConfig's `optimizers`: the overrides of a MethodSpec that change how fast a parameter
    group learns."""
    parts = dotted.split(".")
    if len(parts) != 3 or parts[0] + "." != OPTIMIZERS or parts[2] not in ("lr", "lr_final"):
        raise AttributeError(f"override {dotted!r}: expected optimizers.<group>.lr or optimizers.<group>.lr_final")
    group, field = parts[1], parts[2]
    if group not in optimizers:
        raise AttributeError(f"no optimizer group {group!r} (override {dotted!r}); groups: {sorted(optimizers)}")
    target = optimizers[group]["optimizer"] if field == "lr" else optimizers[group].get("scheduler")
    if target is None or not hasattr(target, field):
        raise AttributeError(f"optimizer group {group!r} has no schedule with {field!r} (override {dotted!r})")
    setattr(target, field, value)


DEFAULT_NAMED = ("willags-mcmc", "willags-prior-low", "willags-prior-low-mask5k-gate")
"""Methods that name the default's own settings: their runs are the default's (configuration)."""


def configuration(rec: dict[str, Any]) -> str:
    """The method name of the configuration a record measured: the ``configuration`` it carries where the name it ran
    as meant another one then (`willags` before the default inspected the scene: `willags-full`; before it densified
    by MCMC, and `willags-auto` runs of that time: `willags-splitclone`; before its latent prior:
    `willags-noprior`; before its mask's start rule, where the mask was on: `willags-earlymask`), `willags` for
    `willags-mcmc`, `willags-prior-low` and `willags-prior-low-mask5k-gate` (the default named in full), else its
    own."""
    if rec.get("configuration"):
        return str(rec["configuration"])
    return "willags" if rec.get("method") in DEFAULT_NAMED else str(rec.get("method"))


def base_trainer_config(base: str):
    """A fresh TrainerConfig of `base` (our method configs, the peer's, or nerfstudio's splatfacto with our parser)."""
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
    method: str, steps: int, device_type: str, data: Path | None, downscale: int | None, schedule: str, output_dir: Path
):
    """The TrainerConfig of one benchmark run (saved to output_dir like ns-train would)."""
    spec = METHODS[method]
    config = base_trainer_config(spec.base)
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
        if k.startswith(OPTIMIZERS):
            set_learning_rate(config.optimizers, k, v)
        else:
            set_nested(m, k, v)
    if spec.keep:
        config.pipeline.auto_config_keep = tuple(sorted({*config.pipeline.auto_config_keep, *spec.keep}))
    # after the overrides: the short schedule sets every method's step schedules alike, a method's own included
    apply_schedule(config, steps, schedule)
    if hasattr(m, "log_images_every"):
        m.log_images_every = 0
    return config
