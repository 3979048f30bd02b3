"""The model's settings: every field of WillagsModelConfig (willags_ns/model.py adds only the class it builds).

Defaults are the method `willags` (willags_ns/method_configs.py derives the other methods from them; why each is set
as it is: docs/design.md). Settings come in groups, one flag prefix each:

    --pipeline.model.latent.*     the appearance latent z: kind (per-image embedding or beta-VAE), dim
    --pipeline.model.mask.*       the transient mask: teacher, threshold, cadence (every), safeguard, health
    --pipeline.model.sky.*        the appearance-conditioned background
    --pipeline.model.mcmc.*       the MCMC densification (`densification`: auto, mcmc or splatfacto)
    --pipeline.model.modulation.* / decoder.* / triplane.*   how z makes a Gaussian's colour

No field is rewritten while the model is built: what a scene lacks (a skyline without SfM keypoints) is decided
again from the same config and scene, so config.yml is what trains. Splatfacto's knobs that willags does not read are
refused with a message (`check_settings`). config.yml files of the flat layout (`use_vae`,
`use_mask`, `mask_every`, `teacher`, `static_support`, ... at the top: RENAMED) load through
`WillagsModelConfig.__setstate__`, which moves each value to its place in the groups.
"""

import dataclasses
import math
from dataclasses import dataclass, field
from typing import Any, Literal

from nerfstudio.models.splatfacto import SplatfactoModelConfig

from willags_ns.appearance.decoder import ColorDecoderConfig
from willags_ns.appearance.modulation import ColorModulationConfig
from willags_ns.appearance.sky import SkyConfig
from willags_ns.appearance.triplane import TriplaneConfig
from willags_ns.appearance.vae import VAEConfig
from willags_ns.eval.holdout import HoldoutConfig
from willags_ns.mask.rule import MaskConfig
from willags_ns.mask.teacher import TeacherConfig
from willags_ns.model import WillagsModel
from willags_ns.objective.sfm_depth import SfmDepthConfig
from willags_ns.splats.mcmc import Densification, McmcConfig


@dataclass
class LatentConfig:
    """The per-image appearance latent z (appearance/latents.py)."""

    kind: Literal["embedding", "vae"] = "embedding"
    """Where z comes from. "embedding": a row per training image in a learnt table (NeRF-W / Splatfacto-W style); a
    new photo's latent is fitted (`willags-render --appearance photo:P --refine-steps N`). "vae": the paper's
    beta-VAE encoder of the photo itself (settings: latent.vae)."""
    dim: int = 64
    """Size D of z: the table's rows or the VAE's code, and the input of the colour transform, the tri-plane field
    and the sky."""
    embedding_init_std: float = 0.01
    """Init std of the embedding table (kind "embedding")."""
    prior_weight: float = 0.002
    """Weight w of a Gaussian prior on the embedding table's rows (kind "embedding"): each step adds
    w * 0.5 * ||z_i - mean||^2 for its photo's row z_i, the mean of all rows held fixed (appearance/latents.latent_prior).
    Why: a row a photo's gradient moves once per epoch keeps drifting in the directions the render barely feels, so
    the rows spread with training length; a new photo's latent is fitted from the rows' mean (the NeRF-W protocol,
    `--appearance photo:P`), and the further the rows lie, the more of that fit's steps it takes to reach one. 0.002,
    a tenth of the pull the beta-VAE's KL puts on its posterior mean (latent.vae.weight 0.01 x beta 2), keeps the rows
    within reach and scores above no prior over every real collection at once under cross-validation; 0.02 and 0 do
    not (docs/design.md, "The latent prior"). 0: no prior."""
    vae: VAEConfig = field(default_factory=VAEConfig)
    """The beta-VAE encoder/decoder and its loss weight (kind "vae")."""


@dataclass
class WillagsModelConfig(SplatfactoModelConfig):
    """WilLaGS: splatfacto + appearance latent + colour transform (or tri-plane field and decoder) + EMA teacher +
    perceptual transient mask + sky. The defaults are the method `willags`."""

    _target: type = field(default_factory=lambda: WillagsModel)

    appearance: Literal["willags", "sh"] = "willags"
    """'willags': the latent-conditioned appearance field (the method). 'sh': plain 3DGS colours (splatfacto's
    spherical harmonics), no appearance model and no mask: the baseline configuration (method willags-3dgs)."""
    color_mode: Literal["modulated", "decoder"] = "modulated"
    """How the appearance makes a Gaussian's colour. 'modulated' (measured best: docs/benchmarks.md): the
    Gaussian's own 3DGS SH colour transformed by the latent (a global colour transform of z plus an optional,
    penalised per-Gaussian residual fed by f_s, z and the tri-plane feature; appearance/modulation.py). 'decoder':
    the paper's T_color MLP regresses the colour from (f_d, f_s, view direction) (method willags-paper)."""
    latent: LatentConfig = field(default_factory=LatentConfig)
    """The appearance latent z: its kind (per-image embedding or beta-VAE encoder) and size."""
    modulation: ColorModulationConfig = field(default_factory=ColorModulationConfig)
    """The colour transform of color_mode='modulated' (global transform, local residual and its penalty)."""
    use_field: bool = False
    """Tri-plane hypernetwork field f_d(z, x) (the paper's). Off: no spatial field (the decoder sees z beside f_s)."""
    triplane: TriplaneConfig = field(default_factory=TriplaneConfig)
    """Tri-plane hypernetwork field (plane resolution/channels, MLP sizes), with use_field."""
    decoder: ColorDecoderConfig = field(default_factory=ColorDecoderConfig)
    """Colour decoder T_color(f_d, f_s, view direction), with color_mode='decoder'."""
    intrinsic_dim: int = 16
    """Size of the learnable per-Gaussian intrinsic feature f_s (the decoder's input, the local residual's)."""
    mask: MaskConfig = field(default_factory=MaskConfig)
    """The transient mask: EMA teacher, VGG16 threshold, cadence, SfM safeguard, health watch."""
    sky: SkyConfig = field(default_factory=SkyConfig)
    """Appearance-conditioned background bg(z, ray direction) behind the Gaussians (appearance/sky.py)."""
    densification: Densification = "auto"
    """How Gaussians are added and removed. "mcmc": as 3DGS-MCMC (splats/mcmc.py: dead Gaussians relocated, growth
    by sampling up to mcmc.cap_max, position noise, opacity and scale penalties). "splatfacto": splatfacto's split /
    clone / prune with opacity resets (gsplat's DefaultStrategy and its thresholds). "auto": MCMC on a GPU, where it
    was measured better on every scene's long runs, splatfacto's on the CPU, whose short runs MCMC's gradual growth
    leaves with too few Gaussians (docs/design.md)."""
    splitclone_cap: int = 300_000
    """The most Gaussians splatfacto's densification (densification "splatfacto", the CPU's) grows to; 0: no cap.
    Why: its gradient rule has no budget of its own, and on some collections it grows at every refinement until the
    machine's memory or time runs out (docs/design.md, "Capacity"); at the cap a refinement grows only the Gaussians
    with the largest gradients, as many as there is room for (splats/splitclone.py). The same budget as MCMC's
    default cap (mcmc.cap_max), so that either densification gives a scene at most as many Gaussians."""
    mcmc: McmcConfig = field(default_factory=McmcConfig)
    """Settings of the MCMC densification (cap, noise, penalties, initial Gaussians)."""
    holdout: HoldoutConfig = field(default_factory=HoldoutConfig)
    """The right halves of a few training photos kept out of the loss and scored as the NeRF-W protocol scores a test
    photo; the run ends with its best-scoring step's model when its last step scores worse (eval/holdout.py). Off
    (photos 0) by default."""
    sfm_depth: SfmDepthConfig = field(default_factory=SfmDepthConfig)
    """The render's expected depth held to the depths of each training photo's own SfM points (COLMAP scenes;
    objective/sfm_depth.py). Off (weight 0) by default."""
    rasterize_mode: Literal["classic", "antialiased"] = "antialiased"
    """gsplat's rasterisation mode. "antialiased" (opacity compensation for the 2D dilation) keeps renders consistent
    across the resolution schedule (a run trains at 1/4 and 1/2 resolution and is scored at full)."""
    backend: Literal["auto", "gsplat", "torch"] = "auto"
    """Rasteriser backend: gsplat (CUDA), our pure-torch rasteriser (any device), or auto (gsplat on CUDA)."""
    log_images_every: int = 500
    """Write training images (render, teacher render, D map, mask, VAE reconstruction) to tensorboard every N
    steps (0 = never)."""
    render_sh_degree: int = 3
    """Rendering with a chosen appearance and no gradient (viewer, ns-render, eval images during training; not
    training, not the NeRF-W protocol, whose latent arrives in the camera's metadata): once per appearance change the
    colour decoder is projected by least squares onto real SH of this degree per Gaussian (over RENDER_SH_SAMPLES
    view directions), and every frame the rasteriser evaluates SH like 3DGS instead of running the decoder MLP
    per frame. The bake happens on the second frame with the same appearance and Gaussians (a viewer open during
    training, where the Gaussians change every step, keeps the exact decoder). -1 = the decoder every frame."""
    export_view_samples: int = 26
    """Number of view directions averaged when baking the view-dependent colour into a PLY (ns-export)."""
    auto_config: bool = True
    """Before the model is built, inspect the scene (willags-inspect) and switch off what it does not need: the
    appearance latent, the transient mask and its teacher, the tri-plane field, the sky; the latent size follows the
    image count (willags_ns/tools/autoconfig.py). The choice is printed, logged to tensorboard and written to
    auto_config.json; the pipeline stores the resolved switches in config.yml (with auto_config False), so a reload
    builds the trained model. Off: the configuration as given (method willags-full)."""

    def __post_init__(self) -> None:
        check_settings(self)

    def check(self) -> None:
        """Refuse what the model cannot train (check_settings): the model calls it when it is built, so a field
        set after construction is checked too."""
        check_settings(self)

    def __getattr__(self, name: str) -> Any:
        # only reached for names the object lacks: a field of the flat layout says where it is
        if name in _RENAMED_FROM:
            raise AttributeError(renamed_message(name))
        raise AttributeError(f"{type(self).__name__!r} object has no attribute {name!r}")

    def __setattr__(self, name: str, value: Any) -> None:
        if name in _RENAMED_FROM:
            raise AttributeError(renamed_message(name))
        super().__setattr__(name, value)

    def __setstate__(self, state: dict[str, Any]) -> None:
        """Unpickling and YAML loading (config.yml): fields of the flat layout move to their places in the groups
        (`migrate_state`), and fields a file lacks get their defaults, except two that say how the file's run
        trained, and it resumes so: a file without `densification` trained with splatfacto's, and one without
        `mask.start_rule` started its mask at `mask.warmup_steps` whatever the renders left ("always")."""
        state = migrate_state(dict(state))
        state.setdefault("densification", "splatfacto")
        mask = state.get("mask")
        if mask is not None and hasattr(mask, "__dict__"):
            vars(mask).setdefault("start_rule", "always")
        self.__dict__.update(state)
        fill_defaults(self)


RENAMED: tuple[tuple[str, str], ...] = (
    ("vae.latent_dim", "latent.dim"),
    ("vae", "latent.vae"),
    ("use_vae", "latent.kind"),
    ("lambda_vae", "latent.vae.weight"),
    ("embedding_init_std", "latent.embedding_init_std"),
    ("use_mask", "mask.enabled"),
    ("mask_every", "mask.every"),
    ("max_masked_fraction", "mask.max_masked_fraction"),
    ("teacher", "mask.teacher"),
    ("fuse_teacher_render", "mask.teacher.fused"),
    ("static_support", "mask.safeguard"),
    ("mask_health", "mask.health"),
)
"""(field of the flat layout, its place in the groups) of the model config, in the order `migrate_state` moves them
(a group before the fields moved into it). use_vae True / False is latent.kind "vae" / "embedding"."""

DROPPED: dict[str, str] = {
    "triplane.latent_dim": "the field's input is latent.dim",
    "decoder.dynamic_dim": "the decoder's f_d input is triplane.feature_dim",
    "decoder.intrinsic_dim": "the decoder's f_s input is intrinsic_dim",
}
"""Fields of the flat layout that set nothing (the model overwrote or ignored them): dropped when a file is loaded."""

_RENAMED_FROM = {old: new for old, new in RENAMED if "." not in old}


def renamed_message(old: str) -> str:
    """Where a field of the flat layout is in the groups, as field and flag."""
    new = dict(RENAMED).get(old)
    if new is None:
        return f"willags: {old} was removed ({DROPPED[old]})"
    flag = f"--pipeline.model.{new.replace('_', '-')}"
    extra = ' ("vae" for True, "embedding" for False)' if old == "use_vae" else ""
    return f"willags: the model setting {old} is {new} ({flag}{extra})"


def _convert(old: str, value: Any) -> Any:
    return ("vae" if value else "embedding") if old == "use_vae" else value


def migrate_state(state: dict[str, Any]) -> dict[str, Any]:
    """A config.yml's model fields (`state`: attribute name -> value, nested configs as objects) in the groups: each
    RENAMED field moved to its place, each DROPPED one removed. A state of the groups passes through unchanged."""
    for old, new in RENAMED:
        found, value = _pop(state, old)
        if found:
            _put(state, new, _convert(old, value))
    for old in DROPPED:
        _pop(state, old)
    return state


def _pop(state: dict[str, Any], dotted: str) -> tuple[bool, Any]:
    head, _, rest = dotted.partition(".")
    if head not in state:
        return False, None
    if not rest:
        return True, state.pop(head)
    inner = state[head].__dict__
    return (True, inner.pop(rest)) if rest in inner else (False, None)


def _put(state: dict[str, Any], dotted: str, value: Any) -> None:
    *parents, leaf = dotted.split(".")
    owner: Any = None
    for i, name in enumerate(parents):
        container = state if owner is None else owner.__dict__
        if name not in container:
            container[name] = _GROUPS[".".join(parents[: i + 1])]()
        owner = container[name]
    (state if owner is None else owner.__dict__)[leaf] = value


_GROUPS: dict[str, Any] = {
    "latent": LatentConfig,
    "latent.vae": VAEConfig,
    "mask": MaskConfig,
    "mask.teacher": TeacherConfig,
}
"""The config class of each group a moved field may land in (made with its defaults when a file predates it)."""


def fill_defaults(obj: Any) -> None:
    """Give every dataclass field `obj` (and its nested configs) lacks its default: a file without a field loads
    with the field's default."""
    for f in dataclasses.fields(obj):
        if f.name not in obj.__dict__:
            if f.default is not dataclasses.MISSING:
                obj.__dict__[f.name] = f.default
            elif f.default_factory is not dataclasses.MISSING:
                obj.__dict__[f.name] = f.default_factory()
        value = obj.__dict__.get(f.name)
        if dataclasses.is_dataclass(value) and not isinstance(value, type):
            fill_defaults(value)


INERT_KNOBS: dict[str, str] = {
    "enable_collider": "splats are rasterised, not ray-marched",
    "collider_params": "splats are rasterised, not ray-marched",
    "loss_coefficients": "the loss is reconstruction + the terms of willags_ns/objective/regularizers.py",
    "eval_num_rays_per_chunk": "splats are rendered per camera, not per ray chunk",
    "prompt": "willags has no text prompt",
    "n_split_samples": "gsplat's DefaultStrategy splits each Gaussian in two",
    "use_bilateral_grid": "the appearance field models the camera's colour pipeline",
    "grid_shape": "there is no bilateral grid",
}
"""Fields inherited from splatfacto that willags does not read, and why: a value other than splatfacto's default is
refused (`check_settings`) rather than silently ignored."""


def check_settings(cfg: WillagsModelConfig) -> None:
    """Raise ValueError naming each inherited splatfacto knob (INERT_KNOBS) set to something willags would ignore, and
    a switch set without the one it works through (mask.residual.expected without mask.distance residual). Runs when
    the config is made (the command line) and when the model is built (config.yml, later edits)."""
    defaults = {f.name: f for f in dataclasses.fields(SplatfactoModelConfig)}
    wrong = []
    for name, why in INERT_KNOBS.items():
        f = defaults[name]
        default = f.default if f.default is not dataclasses.MISSING else f.default_factory()  # type: ignore[misc]
        if getattr(cfg, name) != default:
            wrong.append(f"--pipeline.model.{name.replace('_', '-')} ({why})")
    if wrong:
        raise ValueError("willags: these splatfacto settings do nothing here; leave them out: " + "; ".join(wrong))
    h = cfg.holdout
    if h.photos < 0 or h.every < 1 or h.start < 0 or h.margin < 0:
        raise ValueError(
            f"willags: --pipeline.model.holdout.* must be photos >= 0, every >= 1, start >= 0, margin >= 0 (got photos "
            f"{h.photos}, every {h.every}, start {h.start}, margin {h.margin})"
        )
    d = cfg.sfm_depth
    if not (math.isfinite(d.weight) and d.weight >= 0 and d.min_track >= 2 and 0 <= d.min_alpha < 1):
        raise ValueError(
            "willags: --pipeline.model.sfm-depth.* must be weight >= 0 (finite), min-track >= 2, 0 <= min-alpha < 1 "
            f"(got weight {d.weight}, min-track {d.min_track}, min-alpha {d.min_alpha})"
        )
    if cfg.mask.residual.expected and cfg.mask.distance != "residual":
        raise ValueError(
            "willags: --pipeline.model.mask.residual.expected True needs --pipeline.model.mask.distance residual "
            f"(it is the colour residual's expected level; with mask.distance {cfg.mask.distance!r} nothing would "
            "learn or use it)"
        )
    m = cfg.mask
    if m.start_rule not in ("always", "transients") or not (0.0 <= m.start_share <= 1.0):
        raise ValueError(
            "willags: --pipeline.model.mask.start-rule must be always or transients and --pipeline.model.mask.start-share "
            f"within [0, 1] (got start-rule {m.start_rule!r}, start-share {m.start_share})"
        )
