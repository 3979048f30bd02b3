"""Colour modulation: a per-Gaussian base colour (3DGS spherical harmonics) transformed by the appearance latent.

The paper's decoder (``decoder.py``) regresses every Gaussian's colour from features alone, so the static scene's
colours must pass through a small MLP: that costs fitting capacity, even on a scene with no transients and almost
no appearance change (docs/design.md). Here the scene's colour is what 3DGS uses (SH of degree 3 per Gaussian: full
capacity, view dependence included) and the latent only *transforms* it:

    base_i(d) = max(SH_i(d) + 0.5, 0)                                   the Gaussian's own colour (as gsplat)
    c_i(d)    = (A(z) base_i(d)^g(z) + b(z)) * (1 + s_i) + o_i          A 3x3, b 3: global (camera, exposure, WB)
    (s_i, o_i) = L([f_s,i, P z, f_d,i])                                 local residual: per-Gaussian, optional

- ``g(z)``: an optional per-channel gamma (``gamma``; off by default: g = 1), from the same MLP.
- ``A(z), b(z)``: a small MLP of z (12 outputs, 15 with the gamma), initialised at the identity. A global colour
  transform is what changes between tourist photos most (exposure, white balance, camera response, time of day) and, unlike a
  spatial field, a latent fitted on one half of an image carries it to the other half (the NeRF-W protocol).
- ``(s_i, o_i)``: optional per-Gaussian scale and offset from the Gaussian's intrinsic feature f_s, a projection of
  z and, when the tri-plane field is on, its dynamic feature f_d (``field``: spatially varying light, shadows).
  Initialised at zero and penalised (``local_penalty``): it models only what the global transform cannot.

Without the gamma, linear in the SH coefficients, so rendering with a fixed appearance bakes exactly to SH of the
same degree; with it, the bake is a least-squares fit over view directions (as for the paper's decoder).
"""

import math
from dataclasses import dataclass
from typing import Any, Literal

import torch
from jaxtyping import Float
from torch import Tensor, nn

from willags_ns.appearance.color_model import ColorModel, GaussianLayout
from willags_ns.appearance.latent_mlp import latent_mlp
from willags_ns.render.sh import SH_C0
from willags_ns.tensor_constants import as_dtype, constant, made_once


@dataclass
class ColorModulationConfig:
    """Hyper-parameters of the latent-conditioned colour transform (``color_mode="modulated"``)."""

    global_hidden: int = 64
    """Width of the hidden layer of z -> (A, b)."""
    gamma: bool = False
    """A per-channel gamma g(z) on the base colour before the 3x3 transform (base^g, g in [1/3, 3], 1 at
    initialisation). Why: cameras' tone curves are not affine, and on a perfect reconstruction a log-linear transform
    (exposure, white balance, gamma) fitted on the left half scores higher than the best affine one (docs/design.md).
    Off by default: on the benchmark scenes it changed nothing beyond the seed
    spread (docs/design.md), and with it the SH bake (viewer, export) is a least-squares fit instead of exact."""
    local: bool = True
    """Per-Gaussian residual scale/offset (s_i, o_i) on top of the global transform. Off: global transform only."""
    local_hidden: int = 64
    """Width of the hidden layer of the local residual MLP."""
    latent_proj: int = 16
    """z is projected to this size (P z) before it enters the local residual's hidden layer, where it is the same
    for every Gaussian (one vector added to each Gaussian's pre-activation): at most this many directions of z move
    the residual, at no per-Gaussian cost. 0: the residual does not see z at all, a static per-Gaussian colour scale
    and offset, so that every change between photos goes through the global transform."""
    local_penalty: float = 0.01
    """Weight of mean(s^2 + o^2) in the loss: the local residual pays for what it adds, so appearance that a global
    transform explains stays global (and transfers across an image under the NeRF-W protocol)."""
    residual_latent: Literal["own", "mean"] = "own"
    """Which latent the local residual reads outside training (rendering, export, the NeRF-W protocol's fit and
    score). "own": the appearance's, as in training. "mean": the training images' mean latent whatever the
    appearance (its projection P z; the tri-plane field's feature, when on, still follows the appearance), so a
    chosen or fitted latent moves the global transform and the residual keeps what the photos share: what it learnt
    of single photos (a crowd's colours on the ground under one photo's latent) is not carried to another. Training
    is the same either way. "own" scores higher under the NeRF-W protocol on every collection measured
    (docs/design.md): what the residual reads of a fitted latent carries across the photo."""
    residual_chunk: int = 131072
    """Gaussians per chunk of the local residual's own backward (``LocalResidualMLP``): it keeps no [N, hidden]
    activation between forward and backward and recomputes the hidden layer chunk by chunk, so the MLP's extra
    memory is two [chunk, hidden] buffers instead of ~3 x [N, hidden], which roughly halves the model's extra peak
    memory over splatfacto for a little more time per step (docs/design.md). 0: plain autograd (also what runs with the tri-plane field, whose feature enters the hidden
    layer per Gaussian)."""


GAMMA_LOG_RANGE = math.log(3.0)
"""g(z) = exp(GAMMA_LOG_RANGE tanh(h)): the gamma stays within [1/3, 3]."""
GAMMA_FLOOR = 1e-3
"""Base colours are floored here before the gamma (1e-3^3 = 1e-9: black stays black within 8-bit precision)."""


@made_once
def identity3(device: torch.device, dtype: torch.dtype) -> Tensor:
    """The 3x3 identity on `device`, made once (A = I + dA is built every step)."""
    return torch.eye(3, device=device, dtype=dtype)


class ColorModulation(ColorModel):
    """(z, base colours, f_s, f_d) -> colours: the colour model of color_mode 'modulated' (appearance/color_model.py).
    See the module docstring for the formula."""

    reads_sh = True

    def __init__(self, latent_dim: int, intrinsic_dim: int, dynamic_dim: int, cfg: ColorModulationConfig):
        super().__init__()
        if latent_dim <= 0:
            raise ValueError(f"latent_dim must be > 0, got {latent_dim}")
        self.intrinsic_dim = intrinsic_dim
        self.dynamic_dim = dynamic_dim
        self.residual_chunk = cfg.residual_chunk
        self.residual_latent = cfg.residual_latent
        self.render_anchor: Tensor | None = None
        """The latent the local residual reads outside training (residual_latent "mean"; None: z itself)."""
        self.gamma = cfg.gamma
        self.penalty_weight = cfg.local_penalty
        self.global_mlp = nn.Sequential(
            nn.Linear(latent_dim, cfg.global_hidden), nn.ReLU(), nn.Linear(cfg.global_hidden, 15 if cfg.gamma else 12)
        )
        # identity at initialisation: the model starts as plain 3DGS and the latent learns deviations from it
        nn.init.zeros_(self.global_mlp[-1].weight)
        nn.init.zeros_(self.global_mlp[-1].bias)
        self.local_mlp: nn.Sequential | None = None
        self.latent_proj: nn.Linear | None = None
        if cfg.local:
            self.latent_proj = nn.Linear(latent_dim, cfg.latent_proj)
            d_in = intrinsic_dim + cfg.latent_proj + dynamic_dim
            self.local_mlp = nn.Sequential(nn.Linear(d_in, cfg.local_hidden), nn.ReLU(), nn.Linear(cfg.local_hidden, 6))
            nn.init.zeros_(self.local_mlp[-1].weight)
            nn.init.zeros_(self.local_mlp[-1].bias)

    @classmethod
    def build(cls, cfg: Any, latent_dim: int, field_dim: int) -> "ColorModulation":
        """From the model config: f_s of the local residual (intrinsic_dim, when modulation.local), the field's
        feature when the field is on."""
        if field_dim > 0 and not cfg.modulation.local:
            raise ValueError(
                "willags: use_field=True with color_mode='modulated' needs modulation.local=True (the tri-plane "
                "feature feeds the per-Gaussian residual); set --pipeline.model.use-field False or "
                "--pipeline.model.modulation.local True"
            )
        return cls(latent_dim, cfg.intrinsic_dim if cfg.modulation.local else 0, field_dim, cfg.modulation)

    @classmethod
    def layout(cls, cfg: Any) -> GaussianLayout:
        """The Gaussians' own SH (the base colour) and, with the local residual, its f_s."""
        return GaussianLayout(sh=True, intrinsic_dim=cfg.intrinsic_dim if cfg.modulation.local else 0)

    def prepare(self, z: Tensor, f_s: Tensor | None, f_d: Tensor | None, n: int) -> Tensor | None:
        """The local residual [N, 6] (:meth:`local_residual`), None without one."""
        return self.local_residual(z, f_s, f_d, n)

    def anchors_render(self) -> bool:
        """With residual_latent "mean" and a local residual that reads z: outside training the residual reads the
        training latents' mean (:meth:`set_render_anchor`)."""
        return self.residual_latent == "mean" and self.latent_proj is not None and self.latent_proj.out_features > 0

    def set_render_anchor(self, z: Tensor | None) -> None:
        self.render_anchor = None if z is None or not self.anchors_render() else z.detach()

    def rgb(self, z, base, f_s, f_d, dirs, prepared) -> Tensor:
        """:meth:`forward` of the base colours, clamped at 0 as gsplat clamps SH colours, so that the exact render
        and the SH bake agree."""
        if base is None:
            raise ValueError("color_mode='modulated' needs the Gaussians' SH colours (base=...)")
        return self(z, base, f_s, f_d, residual=prepared).clamp_min(0.0)

    def penalty(self, prepared: Tensor | None) -> Tensor | None:
        """local_penalty x mean(s^2 + o^2) of the local residual (None without one, or with a zero weight)."""
        pen = local_penalty(prepared)
        return None if pen is None or self.penalty_weight <= 0 else constant(self.penalty_weight, pen) * pen

    def exact_sh(self, z, sh, f_s, f_d, degree: int, active_degree: int) -> Tensor | None:
        """The transform applied to the SH coefficients (:func:`modulated_sh`); None with the gamma (not affine)."""
        return None if self.gamma else modulated_sh(self, z, f_s, f_d, degree, active_degree, sh)

    def global_params(self, z: Float[Tensor, " D"]) -> tuple[Tensor, Tensor, Tensor | None]:
        """(A, b, g) of latent z from one pass of the global MLP: A = I + dA; g the per-channel gamma (None when
        ``gamma`` is off), exp(ln 3 tanh(h)), so g stays in [1/3, 3] with a gradient everywhere (a clamp would stop
        it at the bounds) and is 1 where the MLP's output is 0."""
        h = latent_mlp(self.global_mlp, z)
        # split, not sliced: the backward joins the parts' gradients in one cat instead of a zero-filled copy each
        dA, b, *gamma = h.split((9, 3, 3) if self.gamma else (9, 3))
        A = identity3(h.device, h.dtype) + dA.view(3, 3)
        g = torch.exp(GAMMA_LOG_RANGE * torch.tanh(gamma[0])) if self.gamma else None
        return A, b, g

    def global_transform(self, z: Float[Tensor, " D"]) -> tuple[Float[Tensor, "3 3"], Float[Tensor, " 3"]]:
        """(A, b) of latent z: A = I + dA."""
        A, b, _ = self.global_params(z)
        return A, b

    def gamma_of(self, z: Float[Tensor, " D"]) -> Float[Tensor, " 3"] | None:
        """The per-channel gamma g(z), None when ``gamma`` is off (see :meth:`global_params`)."""
        return self.global_params(z)[2]

    def local_residual(
        self, z: Float[Tensor, " D"], f_s: Tensor | None, f_d: Tensor | None, n: int
    ) -> Float[Tensor, "N 6"] | None:
        """Per-Gaussian (s, o) [N, 6], or None when the local residual is off. Outside training with a render anchor
        (residual_latent "mean") it reads the anchor instead of z."""
        if self.local_mlp is None or self.latent_proj is None:
            return None
        if self.render_anchor is not None and not self.training:
            z = self.render_anchor
        if self.intrinsic_dim > 0 and (f_s is None or f_s.shape[-1] != self.intrinsic_dim):
            raise ValueError(f"f_s must be [N, {self.intrinsic_dim}], got {None if f_s is None else tuple(f_s.shape)}")
        if self.dynamic_dim > 0 and (f_d is None or f_d.shape[-1] != self.dynamic_dim):
            raise ValueError(f"f_d must be [N, {self.dynamic_dim}], got {None if f_d is None else tuple(f_d.shape)}")
        # The first layer on [f_s, P z, f_d] split by its input columns: the z part is the same for every Gaussian,
        # so it is one [hidden] vector added as a bias instead of a [N, latent_proj] copy concatenated to each
        # Gaussian (same numbers, N x latent_proj less memory and compute per step).
        first, act, last = self.local_mlp
        # the weight's column blocks of f_s, P z and f_d (split: one cat joins their gradients in the backward)
        w_s, w_z, w_d = first.weight.split((self.intrinsic_dim, self.latent_proj.out_features, self.dynamic_dim), 1)
        h = torch.addmv(first.bias, w_z, latent_mlp(self.latent_proj, z))  # [hidden]: bias + w_z (P z)
        if self.intrinsic_dim > 0 and self.dynamic_dim == 0 and self.residual_chunk > 0:
            assert f_s is not None
            return LocalResidualMLP.apply(f_s, w_s, h, last.weight, last.bias, self.residual_chunk)
        if self.intrinsic_dim > 0:
            assert f_s is not None
            h = torch.nn.functional.linear(f_s, w_s, h)
        else:
            h = h.expand(n, -1)
        if self.dynamic_dim > 0:
            assert f_d is not None
            h = h + torch.nn.functional.linear(f_d, w_d)
        return last(act(h))

    def forward(
        self,
        z: Float[Tensor, " D"],
        base: Float[Tensor, "N 3"],
        f_s: Tensor | None = None,
        f_d: Tensor | None = None,
        residual: Tensor | None = None,
    ) -> Float[Tensor, "N 3"]:
        """Colours [N, 3] (not clamped: the rasteriser's compositing and the final clamp handle the range).

        ``residual``: a precomputed :meth:`local_residual` (it does not depend on the view direction, so a caller
        evaluating many directions computes it once)."""
        A, b, g = self.global_params(z)
        if g is not None:
            # base >= GAMMA_FLOOR: d(x^g)/dx = g x^(g-1) is unbounded at x = 0 for g < 1
            base = base.clamp_min(GAMMA_FLOOR).pow(g)
        c = torch.mm(base, A.mT) + b  # base A^T + b
        if residual is None:
            residual = self.local_residual(z, f_s, f_d, base.shape[0])
        if residual is not None:
            scale, offset = residual.split(3, dim=-1)
            c = c * (constant(1.0, scale) + scale) + offset
        return c


def _rows(t: Tensor, start: int, chunk: int) -> Tensor:
    """Rows start : start + chunk of `t`; `t` itself when that is all of it (one chunk: no slice operators)."""
    return t if start == 0 and chunk >= t.shape[0] else t[start : start + chunk]


class LocalResidualMLP(torch.autograd.Function):
    """out = W2 relu(f W1^T + h0) + b2 over N Gaussians, with a backward that recomputes the hidden layer chunk by
    chunk (``ColorModulation.local_residual``'s default path: f = f_s [N, Fs], h0 [hidden] = the layer's bias plus
    z's share).

    Plain autograd keeps the [N, hidden] ReLU output from forward to backward and then holds it with two more
    [N, hidden] gradients: the largest transient buffers of a willags step (docs/design.md), which splatfacto does
    not have. Here only the inputs are saved; the backward rebuilds each chunk's hidden layer
    (an [chunk, Fs] x [Fs, hidden] product, cheaper than reading it back from memory at this width) and accumulates
    the weight gradients chunk by chunk. Same numbers as the plain MLP (``tests/appearance/test_modulation.py``)."""

    @staticmethod
    def forward(ctx, f, w1, h0, w2, b2, chunk: int):  # type: ignore[override]
        ctx.dtypes = [t.dtype for t in (f, w1, h0, w2, b2)]
        # at least float32 whatever autocast is active (CPU or CUDA): the per-chunk writes below need one dtype
        # (float32 throughout, the usual case, decided without the two promote_types operators)
        dt = torch.float32
        if not f.dtype == w1.dtype == torch.float32:
            dt = torch.promote_types(torch.promote_types(f.dtype, w1.dtype), torch.float32)
        with torch.autocast(f.device.type, enabled=False):
            f, w1, h0, w2, b2 = (as_dtype(t, dt) for t in (f, w1, h0, w2, b2))
            n = f.shape[0]
            out = f.new_empty(n, w2.shape[0])
            w1t, w2t = w1.t(), w2.t()  # transposed once, not per chunk
            for i in range(0, n, chunk):
                h = torch.addmm(h0, _rows(f, i, chunk), w1t).relu_()
                torch.addmm(b2, h, w2t, out=_rows(out, i, chunk))
        ctx.save_for_backward(f, w1, h0, w2)
        ctx.chunk = chunk
        return out

    @staticmethod
    def backward(ctx, g):  # type: ignore[override]
        f, w1, h0, w2 = ctx.saved_tensors
        chunk, n = ctx.chunk, f.shape[0]
        need_f, need_w1, need_h0, need_w2, need_b2 = ctx.needs_input_grad[:5]
        with torch.autocast(f.device.type, enabled=False):
            g = as_dtype(g, f.dtype).contiguous()
            gf = torch.empty_like(f) if need_f else None
            # the weight gradients summed over the chunks: the first chunk's is the sum so far (no zero-filled buffer
            # to add it to; zeros without any Gaussian)
            wanted = ((w1, need_w1), (h0, need_h0), (w2, need_w2))
            gw1, gh0, gw2 = (torch.zeros_like(t) if need and n == 0 else None for t, need in wanted)
            w1t = w1.t()
            for i in range(0, n, chunk):
                fc, gc = _rows(f, i, chunk), _rows(g, i, chunk)
                act = torch.addmm(h0, fc, w1t).relu_()  # the chunk's hidden layer, rebuilt
                if need_w2:
                    gw2 = gc.t() @ act if gw2 is None else gw2.addmm_(gc.t(), act)
                # d out / d pre-activation: one fused kernel (ReLU's own backward, masked where act == 0)
                gh = torch.ops.aten.threshold_backward(gc @ w2, act, 0.0)
                del act
                if need_h0:
                    gh0 = gh.sum(0) if gh0 is None else gh0.add_(gh.sum(0))
                if need_w1:
                    gw1 = gh.t() @ fc if gw1 is None else gw1.addmm_(gh.t(), fc)
                if gf is not None:
                    torch.mm(gh, w1, out=_rows(gf, i, chunk))
            gb2 = g.sum(0) if need_b2 else None
        grads = (gf, gw1, gh0, gw2, gb2)
        return (*(None if gr is None else as_dtype(gr, dt) for gr, dt in zip(grads, ctx.dtypes, strict=True)), None)


def modulated_sh(mod: ColorModulation, z: Tensor, f_s, f_d, degree: int, active_degree: int, sh: Tensor) -> Tensor:
    """The colour transform applied to the SH coefficients: with M_i = diag(1 + s_i) A and t_i = (1 + s_i) b + o_i,
    c_i(d) = M_i (SH_i(d) + 0.5) + t_i = sum_k (M_i c_k) Y_k(d) + 0.5 + (M_i 0.5 + t_i - 0.5), the constant going
    into the degree-0 coefficient (Y_0 = C0). Exact up to the clamps at 0 (base colour, final colour)."""
    k_out = (degree + 1) ** 2
    k_use = min(k_out, (active_degree + 1) ** 2, sh.shape[1])
    A, b = mod.global_transform(z)
    n = sh.shape[0]
    M = A.expand(n, 3, 3)
    t = b.expand(n, 3)
    residual = mod.local_residual(z, f_s, f_d, n)
    if residual is not None:
        scale = 1.0 + residual[:, :3]
        M = scale[:, :, None] * M
        t = scale * t + residual[:, 3:]
    out = torch.zeros(n, k_out, 3, device=sh.device, dtype=sh.dtype)
    out[:, :k_use] = torch.einsum("nij,nkj->nki", M, sh[:, :k_use])
    const = (M @ torch.full((3,), 0.5, device=sh.device, dtype=M.dtype)) + t - 0.5
    out[:, 0] += const / SH_C0
    return out


def local_penalty(residual: Tensor | None) -> Tensor | None:
    """mean(s^2 + o^2) of a local residual [N, 6] (None -> None): the price of per-Gaussian appearance."""
    if residual is None or residual.numel() == 0:
        return None
    return residual.square().sum(-1).mean()
