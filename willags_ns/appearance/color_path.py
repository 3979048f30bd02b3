"""The colour path: per-Gaussian RGB for a latent and a camera, and the same colours baked into SH.

    z, normalised means --field--> f_d [N, F]                                  (cached per latent and Gaussians)
    color_mode='modulated': SH colour of the Gaussian (3DGS) --colour transform of z (+ local residual)--> RGB
    color_mode='decoder':   T_color(f_d, f_s, view direction) --> RGB (the paper)
    bake (a fixed appearance, no gradient): those colours as SH coefficients [N, K, 3] that the rasteriser evaluates
    per frame like 3DGS; exact for the affine modulation, a least-squares fit over view directions otherwise.

The colour models behind `AppearanceNetworks.color_model` share one contract (appearance/color_model.py); this module
calls only that contract and adds what depends on the camera and the caches. The student's colours and the EMA teacher's (:func:`teacher_colors`) are the same
:func:`gaussian_colors`. :class:`ColorPath` holds the caches and nothing else: the networks, the Gaussians'
tensors and the model's step arrive as arguments (:class:`ColorContext` for what every call shares).
"""

import math
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from typing import NamedTuple

import torch
from torch import Tensor

from willags_ns.appearance.networks import AppearanceNetworks
from willags_ns.appearance.triplane import normalize_points
from willags_ns.render.sh import sh_basis, sh_color
from willags_ns.splats.gaussians import sh_coeffs

RENDER_SH_SAMPLES = 64
"""View directions over which the decoder is fitted by SH when rendering with a fixed appearance."""


def fibonacci_directions(k: int, device=None) -> Tensor:
    """k unit vectors [k, 3] spread evenly over the sphere (Fibonacci lattice)."""
    i = torch.arange(k, device=device, dtype=torch.float32) + 0.5
    phi, cos_t = math.pi * (1 + 5**0.5) * i, 1 - 2 * i / k
    sin_t = (1 - cos_t**2).clamp_min(0).sqrt()
    return torch.stack([sin_t * phi.cos(), sin_t * phi.sin(), cos_t], -1)


@dataclass(frozen=True)
class ColorContext:
    """What a colour call reads of the model besides the networks and the Gaussians."""

    bounds_lo: Tensor
    """[3] lower corner of the box the tri-plane field normalises means into (fixed at initialisation)."""
    bounds_hi: Tensor
    """[3] upper corner of that box."""
    step: int
    """Training step: the Gaussians change with it, so it is part of every cache key."""
    sh_degree: int
    """SH degree in use now (splatfacto's schedule): how much of the Gaussians' SH the base colour evaluates."""


def field_features(nets: AppearanceNetworks, z: Tensor, means: Tensor, ctx: ColorContext) -> Tensor | None:
    """The tri-plane field's f_d [N, F] under z at `means` (normalised into the model's box), None without it."""
    if nets.field is None:
        return None
    return nets.dynamic_features(z, normalize_points(means, ctx.bounds_lo, ctx.bounds_hi))


class GaussianColors(NamedTuple):
    """The appearance's colours of some Gaussians from one camera, and what the step's losses and teacher reuse."""

    rgb: Tensor
    """[N, 3] colours."""
    prepared: Tensor | None
    """What the colour model prepared for this latent (ColorModel.prepare: the modulation's per-Gaussian residual),
    which its penalty prices; None without."""
    sh_base: Tensor | None
    """[N, 3] the Gaussians' own SH colours from the camera (a colour model that reads them; the teacher colours the
    same Gaussians from the same camera), None otherwise."""


def gaussian_colors(
    nets: AppearanceNetworks,
    z: Tensor,
    means: Tensor,
    f_s: Tensor | None,
    f_d: Tensor | None,
    cam_center: Tensor,
    sh_degree: int,
    sh: Tensor | None = None,
    base: Tensor | None = None,
) -> GaussianColors:
    """The colours of `nets` (the student's or the EMA teacher's) under latent z [D] for Gaussians at `means`
    [N, 3] seen from `cam_center` [3], with their f_s [N, Fs] and the field's f_d [N, F] (or None). A colour model
    that reads the Gaussians' SH gets their colours from the camera: `base` [N, 3] when given, else their SH `sh`
    [N, K, 3] evaluated up to `sh_degree`."""
    dirs = means - cam_center  # [N, 3]: the centre broadcast over the Gaussians
    model = nets.color_model
    prepared = model.prepare(z, f_s, f_d, means.shape[0])
    if model.reads_sh and base is None:
        if sh is None:
            raise ValueError(f"color_mode={nets.color_mode!r} needs the Gaussians' SH coefficients (sh=...)")
        base = sh_color(sh_degree, dirs, sh)
    return GaussianColors(model.rgb(z, base, f_s, f_d, dirs, prepared), prepared, base if model.reads_sh else None)


@torch.no_grad()
def teacher_colors(
    teacher: AppearanceNetworks, z: Tensor, gp, cam_center: Tensor, ctx: ColorContext, sh_base: Tensor | None
) -> Tensor:
    """Per-Gaussian RGB [N, 3] of the EMA teacher networks under z (no grad) for the student's current Gaussians
    `gp`, seen from `cam_center`: :func:`gaussian_colors`, as the student's, on the detached Gaussians. `sh_base`:
    the student's SH colours of this step (same Gaussians, same camera), reused; None: evaluated from their SH."""
    means = gp["means"].detach()
    f_s = gp["features"].detach() if "features" in gp else None
    sh = None
    if sh_base is None:
        sh = sh_coeffs(gp)
        sh = sh.detach() if sh is not None else None
    f_d = field_features(teacher, z, means, ctx)
    return gaussian_colors(teacher, z, means, f_s, f_d, cam_center, ctx.sh_degree, sh, sh_base).rgb


def colors_over_directions(
    nets: AppearanceNetworks,
    z: Tensor,
    means: Tensor,
    f_s: Tensor | None,
    f_d: Tensor | None,
    dirs: Tensor,
    sh: Tensor | None,
    sh_degree: int,
) -> Iterator[Tensor]:
    """The appearance's colours [N, 3] seen from each of `dirs` [M, 3], one colour pass per direction (no
    [M, N, 3] buffer). What the colour model prepares per latent does not depend on the direction: computed once.
    The Gaussians' SH `sh` feeds a colour model that reads them."""
    model = nets.color_model
    prepared = model.prepare(z, f_s, f_d, means.shape[0])
    for d in dirs:
        view = d.expand_as(means)
        base = sh_color(sh_degree, view, sh) if model.reads_sh and sh is not None else None
        yield model.rgb(z, base, f_s, f_d, view, prepared)


class ColorPath:
    """Colours of the Gaussians for a latent and a camera, with the caches of rendering a fixed appearance: the
    field's f_d and the baked SH, each keyed by (latent, Gaussians, step)."""

    def __init__(self, key_of: Callable[[Tensor], tuple]):
        self.key_of = key_of
        """A latent's cache key (AppearanceLatents.key_of: no host sync for the latents it handed out)."""
        self.fd_cache: tuple[tuple, Tensor] | None = None
        self.sh_cache: tuple[tuple, Tensor] | None = None
        self.sh_seen: tuple | None = None

    def dynamic_features(
        self, nets: AppearanceNetworks, z: Tensor, means: Tensor, ctx: ColorContext, cacheable: bool
    ) -> Tensor | None:
        """f_d [N, F] (:func:`field_features`), recomputed only when z or the Gaussians change while rendering
        (viewer / eval)."""
        if nets.field is None:
            return None
        if not cacheable:
            return field_features(nets, z, means, ctx)
        key = (self.key_of(z), means.data_ptr(), means.shape[0], ctx.step)
        if self.fd_cache is not None and self.fd_cache[0] == key:
            return self.fd_cache[1]
        f_d = field_features(nets, z, means, ctx)
        if f_d is not None:
            self.fd_cache = (key, f_d)
        return f_d

    def cached_colors(
        self,
        nets: AppearanceNetworks,
        z: Tensor,
        means: Tensor,
        f_s: Tensor | None,
        cam_center: Tensor,
        ctx: ColorContext,
        cacheable: bool = False,
        sh: Tensor | None = None,
        base: Tensor | None = None,
    ) -> GaussianColors:
        """:func:`gaussian_colors`, with the field's f_d cached while rendering (`cacheable`)."""
        f_d = self.dynamic_features(nets, z, means, ctx, cacheable)
        return gaussian_colors(nets, z, means, f_s, f_d, cam_center, ctx.sh_degree, sh, base)

    def sh_key(self, z: Tensor, means: Tensor, ctx: ColorContext, degree: int) -> tuple:
        return (self.key_of(z), means.data_ptr(), means.shape[0], ctx.step, degree)

    def frame_sh(
        self, nets: AppearanceNetworks, z: Tensor, means: Tensor, f_s, degree: int, ctx: ColorContext, gp
    ) -> Tensor | None:
        """The baked SH for this frame, or None to run the colour path. Bakes on the second frame with the same
        (latent, Gaussians): a viewer refreshing during training, where the Gaussians change every step, keeps the
        exact colours instead of paying a bake per frame. The Gaussians' own SH (`gp`) is gathered only for a bake:
        a cached frame costs no [N, 16, 3] copy."""
        key = self.sh_key(z, means, ctx, degree)
        if self.sh_cache is not None and self.sh_cache[0] == key:
            return self.sh_cache[1]
        if self.sh_seen != key:
            self.sh_seen = key
            return None
        return self.baked_sh(nets, z, means, f_s, degree, ctx, sh_coeffs(gp), key)

    @torch.no_grad()
    def baked_sh(
        self,
        nets: AppearanceNetworks,
        z: Tensor,
        means: Tensor,
        f_s: Tensor | None,
        degree: int,
        ctx: ColorContext,
        sh: Tensor | None,
        key: tuple | None = None,
    ) -> Tensor:
        """SH coefficients [N, (degree + 1)**2, 3] whose evaluation (gsplat's: sum_k c_k Y_k(d) + 0.5) reproduces the
        appearance's colour. Cached per (latent, Gaussians); `key` is :meth:`sh_key` when the caller already has it
        (one host sync per frame, not two).

        The colour model's exact SH where it has one (color_mode='modulated': the affine map of the SH colour applied to
        the coefficients); otherwise ('decoder', 'modulated' with its gamma) the colours fitted by least squares over
        RENDER_SH_SAMPLES directions."""
        key = self.sh_key(z, means, ctx, degree) if key is None else key
        if self.sh_cache is not None and self.sh_cache[0] == key:
            return self.sh_cache[1]
        f_d = self.dynamic_features(nets, z, means, ctx, cacheable=True)
        coeffs = nets.color_model.exact_sh(z, sh, f_s, f_d, degree, ctx.sh_degree) if sh is not None else None
        if coeffs is None:
            dirs = fibonacci_directions(max(RENDER_SH_SAMPLES, 2 * (degree + 1) ** 2), means.device)  # [M, 3]
            proj = torch.linalg.pinv(sh_basis(dirs, degree))  # [K, M]: coefficients from samples
            coeffs = torch.zeros(means.shape[0], proj.shape[0], 3, device=means.device)
            for m, rgb in enumerate(colors_over_directions(nets, z, means, f_s, f_d, dirs, sh, ctx.sh_degree)):
                coeffs += proj[None, :, m, None] * (rgb - 0.5)[:, None, :]  # gsplat adds 0.5 back
        self.sh_cache = (key, coeffs)
        return coeffs

    @torch.no_grad()
    def baked_colors(
        self,
        nets: AppearanceNetworks,
        z: Tensor,
        means: Tensor,
        f_s: Tensor | None,
        num_views: int,
        ctx: ColorContext,
        sh: Tensor | None,
    ) -> Tensor:
        """View-independent colours [N, 3] for export: the appearance averaged over `num_views` directions of a
        Fibonacci sphere."""
        dirs = fibonacci_directions(num_views, means.device)  # [k, 3]
        acc = torch.zeros(means.shape[0], 3, device=means.device)
        f_d = self.dynamic_features(nets, z, means, ctx, cacheable=False)
        for rgb in colors_over_directions(nets, z, means, f_s, f_d, dirs, sh, ctx.sh_degree):
            acc += rgb
        return acc / num_views
