"""Densification as Markov chain Monte Carlo (3DGS-MCMC, Kheradmand et al. 2024), on any device.

In place of splatfacto's clone / split / prune heuristics (gsplat's DefaultStrategy), the Gaussians are treated as
samples of a distribution whose density is their opacity:

- every `refine_every` steps between `warmup_length` and `stop_split_at`, the dead Gaussians (opacity at or below
  `min_opacity`) are moved onto live ones drawn in proportion to their opacity, and 5 % more are added the same way
  until `cap_max`; a Gaussian drawn k times shares its place with its k - 1 copies under an opacity and scale that
  keep the rendered sum unchanged (`relocation`, the paper's Eq. 9);
- after every step, the means of nearly transparent Gaussians get noise shaped by their own covariance, scaled by
  the means' learning rate (`noise_lr`): they explore instead of sitting where they do not help;
- the loss pays `opacity_reg` x mean opacity and `scale_reg` x mean scale (objective/regularizers.py), so that
  Gaussians that do not earn their opacity die and are moved where they are needed.

The number of Gaussians is capped (`cap_max`): the cost of a step is chosen, not grown by the gradients. gsplat
ships the same algorithm with a CUDA kernel for the relocation; the functions here are plain torch so that the CPU
backend trains the same way; `replace_params` swaps each Gaussian tensor and the optimiser state that follows it
(what gsplat's strategies do internally).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Literal

import torch
from gsplat.strategy import MCMCStrategy
from torch import Tensor

from willags_ns.render.rotation import quaternion_to_matrix
from willags_ns.tensor_constants import constant

N_MAX = 51
"""Largest number of copies one Gaussian is split into at one relocation (gsplat's table size)."""


Densification = Literal["auto", "mcmc", "splatfacto"]
"""How Gaussians are added and removed (the model setting `densification`)."""


def uses_mcmc(densification: str, device: torch.device | str) -> bool:
    """Whether a model densifies by MCMC: "mcmc", or "auto" on a CUDA device (where it was measured better; on the
    CPU, whose runs are short, splatfacto's: docs/design.md)."""
    if densification not in ("auto", "mcmc", "splatfacto"):
        raise ValueError(f"willags: densification must be auto, mcmc or splatfacto, got {densification!r}")
    return densification == "mcmc" or (densification == "auto" and torch.device(device).type == "cuda")


@dataclass
class McmcConfig:
    """Settings of the MCMC densification (splats/mcmc.py), used where `densification` resolves to MCMC. The
    refinement window and period are splatfacto's warmup_length, stop_split_at and refine_every."""

    cap_max: int = 300_000
    """Most Gaussians: growth stops here (5 % more per refinement until then)."""
    noise_lr: float = 5e5
    """Position noise of a step = noise_lr x the means' current learning rate x the Gaussian's covariance applied to
    a standard normal draw, gated to Gaussians of opacity below ~0.005."""
    opacity_reg: float = 0.01
    """Weight of the mean opacity in the loss."""
    scale_reg: float = 0.01
    """Weight of the mean scale (exp of the log scales, all three axes) in the loss."""
    min_opacity: float = 0.005
    """A Gaussian at or below this opacity is dead: it is moved at the next refinement."""
    init_opacity: float = 0.5
    """Opacity of the initial Gaussians (splatfacto's: 0.1)."""
    init_scale: float = 0.1
    """Initial scale as a fraction of the mean distance to the 3 nearest points (splatfacto's: 1)."""
    cap_rule: Literal["fixed", "pixels", "transients"] = "fixed"
    """How `cap_max` is chosen: "fixed" (as set); "pixels" (`scene_cap`: the automatic configuration sets it from
    the training photos' pixels, gaussians_per_megapixel per megapixel within [cap_min, cap_ceiling]; why: a few
    photos constrain fewer Gaussians than many); "transients" (`transient_cap`: when MCMC first fills `cap_max`,
    training measures how much of its own photos it leaves unexplained, and a collection below `clean_share` grows
    on to `cap_ceiling`; why: more Gaussians helped the clean collections and learned the crowds of the crowded
    ones, docs/design.md "Capacity")."""
    gaussians_per_megapixel: float = 12_500.0
    """The "pixels" rule's Gaussians per megapixel of the training photos (at the size training reads them)."""
    cap_min: int = 50_000
    """The "pixels" rule's smallest cap."""
    cap_ceiling: int = 1_000_000
    """The largest cap of the "pixels" rule, and the "transients" rule's cap for a clean collection."""
    clean_share: float = 0.02
    """The "transients" rule's bar: a collection whose training photos, rendered with their own latents when the
    Gaussians first fill `cap_max`, leave less than this share of their pixels as residual blobs
    (mask/residual.outlier_share) counts as clean and gets `cap_ceiling`. Measured at the cap, not at a fixed step:
    a model with few Gaussians leaves blobs wherever it is still coarse, people or not."""


def scene_cap(train_megapixels: float, cfg: McmcConfig) -> tuple[int, str]:
    """(cap, reason) of the "pixels" rule for training photos of `train_megapixels` in all: gaussians_per_megapixel
    per megapixel, clamped to [cap_min, cap_ceiling] and rounded to thousands."""
    if train_megapixels < 0 or not math.isfinite(train_megapixels):
        raise ValueError(f"willags: training megapixels must be finite and >= 0, got {train_megapixels}")
    raw = cfg.gaussians_per_megapixel * train_megapixels
    cap = int(round(min(max(raw, cfg.cap_min), cfg.cap_ceiling) / 1000.0) * 1000)
    reason = (
        f"{train_megapixels:.1f} Mpx of training photos x {cfg.gaussians_per_megapixel:,.0f} per Mpx = {raw:,.0f}"
        + ("" if cfg.cap_min <= raw <= cfg.cap_ceiling else f", within [{cfg.cap_min:,}, {cfg.cap_ceiling:,}]")
        + f": at most {cap:,} Gaussians"
    )
    return cap, reason


MORE_GAUSSIANS = 1_000_000
"""The larger cap the inspector names as the other side of the trade (docs/usage.md, docs/design.md "Capacity")."""


def transient_cap(share: float, cfg: McmcConfig) -> tuple[int, str]:
    """(cap, reason) of the "transients" rule for a measured transient `share` of the training photos' pixels:
    `cap_ceiling` below `clean_share` (a clean collection: more Gaussians model more of the scene), else `cap_max`
    (a crowded one: more Gaussians would model its passers-by)."""
    if not 0.0 <= share <= 1.0:
        raise ValueError(f"willags: a transient share is within [0, 1], got {share}")
    clean = share < cfg.clean_share
    cap = max(cfg.cap_max, cfg.cap_ceiling) if clean else cfg.cap_max
    side = "below" if clean else "at or above"
    kind = "clean" if clean else "crowded"
    return cap, (
        f"the training photos leave {share:.1%} of their pixels as residual blobs, {side} the bar of "
        f"{cfg.clean_share:.1%}: a {kind} collection, at most {cap:,} Gaussians"
    )


def cap_and_reason(cfg: McmcConfig, train_megapixels: float | None) -> tuple[int, str]:
    """(cap, reason): MCMC's cap for training photos of `train_megapixels` in all (None: not measured) under
    `cfg.cap_rule`, and why: the "pixels" rule's (`scene_cap`), or `cap_max` as set, with what the "pixels" rule
    would allow beside it and, below MORE_GAUSSIANS, the larger cap's trade (what a user weighs when choosing)."""
    if cfg.cap_rule == "pixels" and train_megapixels is not None:
        return scene_cap(train_megapixels, cfg)
    if cfg.cap_rule == "pixels":
        return cfg.cap_max, f"at most {cfg.cap_max:,} Gaussians (rule pixels, but no megapixels measured: as set)"
    if cfg.cap_rule == "transients":
        return cfg.cap_max, (
            f"at most {cfg.cap_max:,} Gaussians until MCMC fills them (rule transients): then training measures how "
            f"much of its photos it leaves unexplained, and below {cfg.clean_share:.1%} of their pixels left as "
            f"residual blobs the cap rises to {max(cfg.cap_max, cfg.cap_ceiling):,}"
        )
    reason = (
        f"at most {cfg.cap_max:,} Gaussians (rule fixed, as set: a cap from the photos' pixels has not scored better "
        "in the cross-validated runs, docs/design.md)"
    )
    if train_megapixels is not None:
        alt, _ = scene_cap(train_megapixels, cfg)
        reason += f"; --pipeline.model.mcmc.cap-rule pixels would allow {alt:,} for these {train_megapixels:.1f} Mpx"
    if cfg.cap_max < MORE_GAUSSIANS:
        reason += (
            f"; more (--pipeline.model.mcmc.cap-max {MORE_GAUSSIANS}) cost training time and helped clean and small "
            "collections, not crowded ones (docs/usage.md)"
        )
    return cfg.cap_max, reason


def relocation(opacities: Tensor, scales: Tensor, ratios: Tensor, n_max: int = N_MAX) -> tuple[Tensor, Tensor]:
    """Opacity [M] and scales [M, 3] of each of the `ratios` [M] copies that replace a Gaussian of opacity
    `opacities` [M] and scales `scales` [M, 3] (the paper's Eq. 9):

        o' = 1 - (1 - o)^(1 / n)
        s' = s * o / sum_{k=0}^{n-1} C(n, k+1) (-1)^k o'^(k+1) / sqrt(k+1)

    (the paper's double sum over i <= n and k < i, summed over i with the hockey-stick identity). n is clamped to
    [1, n_max]. Computed in float64: the alternating sum cancels."""
    n = ratios.clamp(1, n_max).to(torch.float64)
    o = opacities.to(torch.float64)
    o_new = 1.0 - torch.pow(1.0 - o, 1.0 / n)
    k = torch.arange(n_max, dtype=torch.float64, device=o.device)  # [n_max]: k = 0 .. n_max - 1
    # C(n, k+1) through lgamma, zero where k + 1 > n
    log_c = torch.lgamma(n[:, None] + 1) - torch.lgamma(k + 2) - torch.lgamma((n[:, None] - k - 1).clamp_min(0) + 1)
    c = torch.where(k[None] + 1 <= n[:, None], torch.exp(log_c), torch.zeros((), dtype=torch.float64))
    terms = c * torch.pow(-1.0, k) / torch.sqrt(k + 1) * torch.pow(o_new[:, None], k + 1)
    coeff = o / terms.sum(dim=1)
    return o_new.to(opacities.dtype), scales * coeff.to(scales.dtype)[:, None]


def covariances(quats: Tensor, scales: Tensor) -> Tensor:
    """Covariance matrices [N, 3, 3] = R diag(scales^2) R^T of Gaussians with (unnormalised) quaternions `quats`
    [N, 4] (w, x, y, z) and scales [N, 3]."""
    rot = quaternion_to_matrix(quats)
    m = rot * scales[:, None, :]
    return m @ m.transpose(1, 2)


def covariance_times(quats: Tensor, log_scales: Tensor, v: Tensor) -> Tensor:
    """Sigma v [N, 3] for each Gaussian's covariance Sigma = R diag(exp(log_scales)^2) R^T, without building Sigma: v is
    turned into the Gaussian's frame (R^T v), scaled by the squared scales and turned back, each turn two cross
    products with the normalised quaternion's vector part u: R v = v + 2w (u x v) + 2 u x (u x v). The same
    numbers as ``covariances(quats, exp(log_scales)) @ v`` in a third of the operations (it runs every step)."""
    q = quats / quats.norm(dim=-1, keepdim=True).clamp_min(1e-12)  # F.normalize's arithmetic, without its expand
    w, u = q.split((1, 3), dim=-1)

    def turn(x: Tensor, sign: float) -> Tensor:  # R x (sign +1) or R^T x (sign -1)
        t = torch.linalg.cross(u, x, dim=-1)
        return torch.add(torch.addcmul(x, w, t, value=2.0 * sign), torch.linalg.cross(u, t, dim=-1), alpha=2.0)

    return turn(turn(v, -1.0) * torch.exp(constant(2.0, log_scales) * log_scales), 1.0)


def _sampled_copies(params, n: int, candidates: Tensor | None, min_opacity: float, generator=None):
    """Draw `n` Gaussians (among `candidates`, default all) in proportion to their opacity, with replacement; return
    (their indices, the logit opacity and log scales each copy gets)."""
    opacities = torch.sigmoid(params["opacities"]).flatten()
    probs = opacities if candidates is None else opacities[candidates]
    drawn = torch.multinomial(probs, n, replacement=True, generator=generator)
    idx = drawn if candidates is None else candidates[drawn]
    ratios = torch.bincount(idx)[idx] + 1
    new_o, new_s = relocation(opacities[idx], torch.exp(params["scales"])[idx], ratios)
    eps = torch.finfo(torch.float32).eps
    new_o = new_o.clamp(min=min_opacity, max=1.0 - eps)
    return idx, torch.logit(new_o), torch.log(new_s)


@torch.no_grad()
def relocate_dead(params, optimizers, min_opacity: float, generator=None) -> int:
    """Move every Gaussian at or below `min_opacity` onto a live one drawn by opacity (from `generator`, default
    torch's); returns how many moved."""
    dead = torch.sigmoid(params["opacities"]).flatten() <= min_opacity
    n = int(dead.sum())
    alive = (~dead).nonzero(as_tuple=True)[0]
    if n == 0 or alive.numel() == 0:
        return 0
    idx, logit_o, log_s = _sampled_copies(params, n, alive, min_opacity, generator)
    dead_idx = dead.nonzero(as_tuple=True)[0]
    shape = params["opacities"].shape[1:]

    def param_fn(name: str, p: Tensor) -> Tensor:
        if name == "opacities":
            p[idx] = logit_o.reshape(-1, *shape)
        elif name == "scales":
            p[idx] = log_s
        p[dead_idx] = p[idx]
        return torch.nn.Parameter(p)

    def optimizer_fn(key: str, v: Tensor) -> Tensor:
        v[idx] = 0  # the sources and their copies start with fresh moments
        v[dead_idx] = 0
        return v

    replace_params(param_fn, optimizer_fn, params, optimizers)
    return n


def replace_params(param_fn, state_fn, params, optimizers) -> None:
    """Give every Gaussian tensor of `params` (name -> Parameter) the new Parameter `param_fn(name, p)` and move its
    optimiser's per-parameter state along: each state tensor but the step count becomes `state_fn(key, value)`
    (Adam's moments grow, shrink or reset with the Gaussians they belong to). The optimiser then steps the new
    Parameter, and `params` holds it."""
    for name in list(params.keys()):
        opt = optimizers[name]
        for group in opt.param_groups:
            old = group["params"][0]
            state = opt.state.pop(old, {})
            new = param_fn(name, old)
            group["params"] = [new]
            opt.state[new] = {k: (v if k == "step" else state_fn(k, v)) for k, v in state.items()}
            params[name] = new


@torch.no_grad()
def add_sampled(params, optimizers, n: int, min_opacity: float, generator=None) -> int:
    """Add `n` Gaussians, each a copy of one drawn by opacity (its opacity and scale shared with it, Eq. 9)."""
    if n <= 0:
        return 0
    idx, logit_o, log_s = _sampled_copies(params, n, None, min_opacity, generator)
    shape = params["opacities"].shape[1:]

    def param_fn(name: str, p: Tensor) -> Tensor:
        if name == "opacities":
            p[idx] = logit_o.reshape(-1, *shape)
        elif name == "scales":
            p[idx] = log_s
        return torch.nn.Parameter(torch.cat([p, p[idx]]))

    def optimizer_fn(key: str, v: Tensor) -> Tensor:
        return torch.cat([v, torch.zeros((n, *v.shape[1:]), device=v.device, dtype=v.dtype)])

    replace_params(param_fn, optimizer_fn, params, optimizers)
    return n


@torch.no_grad()
def position_noise(params, scaler: float, generator=None) -> None:
    """Add noise to the means, shaped by each Gaussian's covariance and gated to the nearly transparent ones (a
    sigmoid of steepness 100 centred at opacity 0.005), `scaler` x a standard normal draw."""
    means = params["means"]
    logits = params["opacities"]
    opacity = torch.sigmoid(logits if logits.dim() == 2 else logits.reshape(-1, 1))  # [N, 1]
    gate = torch.sigmoid(constant(100.0, opacity) * (constant(0.005, opacity) - opacity))
    draw = torch.randn(means.shape, generator=generator, device=means.device, dtype=means.dtype)
    means.add_(covariance_times(params["quats"], params["scales"], draw * gate), alpha=scaler)


@dataclass
class McmcDensification(MCMCStrategy):
    """gsplat's MCMCStrategy settings, stepped with this module's device-independent functions. `reset_every` 0:
    MCMC never resets opacities (read by the mask's health watch, which compares steps between resets)."""

    reset_every: int = 0
    absgrad: bool = False
    seed: int | None = None
    """None: the draws come from torch's global generators. A seed: each step's draws come from a generator seeded
    with seed + step, so that ranks of a data-parallel run, which hold the same Gaussians, move them alike."""

    def initialize_state(self, scene_scale: float = 1.0) -> dict[str, Any]:
        return {}

    def _generator(self, step: int, device: torch.device) -> torch.Generator | None:
        if self.seed is None:
            return None
        return torch.Generator(device=device).manual_seed(self.seed + step)

    def step_post_backward(self, params, optimizers, state, step: int, info, lr: float) -> None:  # type: ignore[override]
        """After the optimiser's step: relocate and grow on refinement steps, then the position noise."""
        gen = self._generator(step, params["means"].device)
        if self.refine_start_iter < step < self.refine_stop_iter and step % self.refine_every == 0:
            relocate_dead(params, optimizers, self.min_opacity, gen)
            current = len(params["means"])
            grow = max(0, min(self.cap_max, int(1.05 * current)) - current)
            add_sampled(params, optimizers, grow, self.min_opacity, gen)
        position_noise(params, lr * self.noise_lr, gen)


def mcmc_strategy(cfg) -> McmcDensification:
    """The MCMC strategy of a model config (`cfg.mcmc` and splatfacto's refinement window)."""
    m = cfg.mcmc
    return McmcDensification(
        cap_max=m.cap_max,
        noise_lr=m.noise_lr,
        refine_start_iter=cfg.warmup_length,
        refine_stop_iter=cfg.stop_split_at,
        refine_every=cfg.refine_every,
        min_opacity=m.min_opacity,
    )


def mcmc_penalty(cfg, logit_opacities: Tensor, log_scales: Tensor) -> Tensor:
    """opacity_reg x mean opacity + scale_reg x mean scale of the Gaussians (`cfg`: the model config)."""
    m = cfg.mcmc
    opacity, scale = torch.sigmoid(logit_opacities).mean(), torch.exp(log_scales).mean()
    return constant(m.opacity_reg, opacity) * opacity + constant(m.scale_reg, scale) * scale


def initial_opacity_and_scale(cfg, avg_dist: Tensor, mcmc: bool) -> tuple[float, Tensor]:
    """(initial opacity, initial scale [N, 1]) of the Gaussians: splatfacto's (0.1, mean distance) or, with `mcmc`,
    MCMC's (cfg.mcmc)."""
    if mcmc:
        return cfg.mcmc.init_opacity, avg_dist * cfg.mcmc.init_scale
    return 0.1, avg_dist


__all__ = [
    "Densification",
    "McmcConfig",
    "McmcDensification",
    "add_sampled",
    "covariances",
    "initial_opacity_and_scale",
    "mcmc_penalty",
    "mcmc_strategy",
    "position_noise",
    "relocate_dead",
    "relocation",
    "uses_mcmc",
]
