"""Pure-PyTorch 3D Gaussian rasterizer: the CPU twin of gsplat 1.4.0's CUDA `rasterization()` (pinhole, 3DGS).

No gsplat import anywhere here: gsplat's own `_torch_impl` still calls CUDA ops for binning, so it cannot run on a
CPU-only machine. Every rule below is gsplat's (checked against its CUDA kernels in tests/test_render_parity_cuda.py
and against a literal replay of its compositing loop in tests/test_render_torch.py).

Pipeline (vectorised: no Python loop over Gaussians, tiles or pixels; never an N x pixels matrix):

1. `project_gaussians` (autograd): EWA splatting as gsplat's `fully_fused_projection`: world->camera, covariance
   R S S^T R^T, Jacobian with gsplat's clipped tx/ty (lim = (W - cx) / fx + 0.3 tan_fovx), cov2d + eps2d I,
   conic = cov2d^-1, radius = ceil(3 sqrt(lambda_max)), culling (depth outside [near, far], radius <= radius_clip,
   3-sigma box off-screen) -> radii 0.
2. `bin_pairs` (no grad): gsplat composites pixel p with splat s iff p lies in one of s's intersected tiles and
   alpha = min(0.999, o exp(-sigma)) >= 1/255 with sigma >= 0. alpha >= 1/255 <=> sigma <= ln(255 o), an ellipse;
   its pixels are enumerated row by row over the ellipse's chords (clipped to the tile box) with repeat_interleave,
   then tested exactly. Splats are enumerated in (camera, depth) order, so ONE stable sort by pixel id gives
   front-to-back lists. In dense scenes splats go in depth chunks and pixels already cut off are skipped.
3. `_Composite` (custom autograd.Function): transmittance is a segmented exclusive cumsum of log(1 - alpha) in
   float64 (global cumsum minus its value at each pixel's first pair); gsplat's early stop (next_T <= 1e-4 ends the
   pixel, exclusive); w = alpha T scattered into the image with index_add. Its backward is the analytic gradient
   of gsplat's kernel, vectorised with a second segmented cumsum. Compared with autograd through the same ops it
   reuses the alpha computed while binning and keeps no graph over the pairs (faster: docs/design.md). The
   gradient reaches meta["means2d"], which densification strategies read.

The pair set and its order are piecewise constant in the parameters, as in gsplat, whose backward ignores them too.
"""

import math

import torch
from torch import Tensor

from willags_ns.render.rotation import quaternion_to_matrix
from willags_ns.render.sh import sh_color

ALPHA_MIN = 1.0 / 255.0  # gsplat skips pairs below this alpha: they change neither colour nor transmittance
ALPHA_MAX = 0.999  # gsplat clamps alpha here (and stops gradients through the clamp)
T_MIN = 1e-4  # gsplat stops a pixel once the transmittance after a Gaussian would be <= this
LAYERS_PER_CHUNK = 16  # early termination granularity of `bin_pairs` in dense scenes (pairs per pixel per chunk)


def quat_scale_to_matrix(quats: Tensor, scales: Tensor) -> Tensor:
    """M = R(q) diag(s), so that the covariance is M M^T. Quaternions wxyz, normalised here like gsplat.

    Args:
        quats: [N, 4] (any non-zero norm).
        scales: [N, 3] (already activated).

    Returns:
        [N, 3, 3]
    """
    R = quaternion_to_matrix(quats)
    return R * scales[..., None, :]


MAX_RADIUS = 2.0**30
"""Pixel radii are capped here so they fit in int32 (a footprint of 2^30 px already covers any image)."""


def project_gaussians(
    means: Tensor,  # [N, 3]
    quats: Tensor,  # [N, 4]
    scales: Tensor,  # [N, 3]
    viewmats: Tensor,  # [C, 4, 4]
    Ks: Tensor,  # [C, 3, 3]
    width: int,
    height: int,
    eps2d: float = 0.3,
    near_plane: float = 0.01,
    far_plane: float = 1e10,
    radius_clip: float = 0.0,
    calc_compensations: bool = False,
) -> dict:
    """EWA projection of 3D Gaussians, a twin of gsplat's `fully_fused_projection` (pinhole, packed=False).

    Returns a dict of [C, N, ...] tensors: radii (int32, 0 = culled), means2d [C, N, 2] (pixels), depths
    (camera z), conics [C, N, 3] (upper triangle of the blurred cov2d^-1), compensations [C, N] or None. Culled
    entries hold finite but meaningless values.
    """
    M = quat_scale_to_matrix(quats, scales)  # [N, 3, 3]
    Rv = viewmats[:, :3, :3]  # [C, 3, 3]
    tv = viewmats[:, :3, 3]  # [C, 3]
    means_c = torch.einsum("cij,nj->cni", Rv, means) + tv[:, None, :]  # [C, N, 3]
    Mc = torch.einsum("cij,njk->cnik", Rv, M)  # [C, N, 3, 3]; camera-space covariance is Mc Mc^T
    x, y, z = means_c.unbind(-1)  # [C, N]

    fx, fy = Ks[:, 0, 0, None], Ks[:, 1, 1, None]  # [C, 1]
    cx, cy = Ks[:, 0, 2, None], Ks[:, 1, 2, None]
    with torch.no_grad():
        in_depth = (z >= near_plane) & (z <= far_plane)  # gsplat culls z < near or z > far
    # Culled Gaussians (behind the camera, at z = 0) must not put inf/NaN into the graph: 0 * inf = NaN in backward.
    z = torch.where(in_depth, z, torch.ones_like(z))
    rz = 1.0 / z
    # gsplat clips the direction used in the Jacobian to 1.3x the field of view (same limits, same gradient rule:
    # clamp passes gradient inside [lo, hi] inclusive, like gsplat's persp_proj_vjp).
    tan_fovx, tan_fovy = 0.5 * width / fx, 0.5 * height / fy
    lim_x_pos, lim_x_neg = (width - cx) / fx + 0.3 * tan_fovx, cx / fx + 0.3 * tan_fovx
    lim_y_pos, lim_y_neg = (height - cy) / fy + 0.3 * tan_fovy, cy / fy + 0.3 * tan_fovy
    tx = z * torch.clamp(x * rz, min=-lim_x_neg, max=lim_x_pos)
    ty = z * torch.clamp(y * rz, min=-lim_y_neg, max=lim_y_pos)
    # J = [[fx/z, 0, -fx tx/z^2], [0, fy/z, -fy ty/z^2]]; cov2d = (J Mc)(J Mc)^T
    j00, j02 = fx * rz, -fx * tx * rz * rz
    j11, j12 = fy * rz, -fy * ty * rz * rz
    # The 2D covariance block runs in float64 (only [C, N] values): a Gaussian whose footprint is ~1e10 px (huge scale,
    # long focal length) squares past float32's 3e38 in c00 * c11, and inf - inf = NaN reaches the conics and, through
    # 0 * inf, the gradients of every Gaussian (found by tests/test_reliability_rasterizer.py).
    dt = means_c.dtype
    Mc64 = Mc.double()
    B0 = j00.double()[..., None] * Mc64[..., 0, :] + j02.double()[..., None] * Mc64[..., 2, :]  # [C, N, 3]
    B1 = j11.double()[..., None] * Mc64[..., 1, :] + j12.double()[..., None] * Mc64[..., 2, :]  # [C, N, 3]
    c00 = (B0 * B0).sum(-1)
    c01 = (B0 * B1).sum(-1)
    c11 = (B1 * B1).sum(-1)
    means2d = torch.stack([fx * x * rz + cx, fy * y * rz + cy], dim=-1)  # [C, N, 2]

    # low-pass filter (gsplat's add_blur) and its Mip-Splatting compensation
    det_orig = c00 * c11 - c01 * c01
    c00 = c00 + eps2d
    c11 = c11 + eps2d
    det = c00 * c11 - c01 * c01  # >= eps2d^2 > 0 for a PSD cov2d
    compensations = None
    if calc_compensations:
        # gsplat: sqrt(max(0, det_orig / det)); the floor keeps the sqrt's gradient finite for degenerate splats
        compensations = torch.sqrt(torch.clamp(det_orig / det, min=1e-12))
    conics = torch.stack([c11 / det, -c01 / det, c00 / det], dim=-1).to(dt)  # [C, N, 3]
    if compensations is not None:
        compensations = compensations.to(dt)

    with torch.no_grad():
        b = 0.5 * (c00 + c11)
        v1 = b + torch.sqrt(torch.clamp(b * b - det, min=0.01))
        radius = torch.ceil(3.0 * torch.sqrt(v1)).clamp(max=MAX_RADIUS).to(dt)
        mx, my = means2d.unbind(-1)
        valid = (
            in_depth
            & (det > 0)
            & (radius > radius_clip)
            & (mx + radius > 0)
            & (mx - radius < width)
            & (my + radius > 0)
            & (my - radius < height)
        )
        radii = torch.where(valid, radius, torch.zeros_like(radius)).to(torch.int32)
    return {
        "radii": radii,
        "means2d": means2d,
        "depths": means_c[..., 2],
        "conics": conics,
        "compensations": compensations,
    }


def tiles_per_gauss(means2d: Tensor, radii: Tensor, tile_size: int, tile_width: int, tile_height: int) -> Tensor:
    """Number of tiles each splat touches, like gsplat's `isect_tiles` (int32, same shape as radii)."""
    x0, x1, y0, y1 = _tile_box(means2d.detach(), radii, tile_size, tile_width, tile_height)
    return ((x1 - x0) * (y1 - y0) * (radii > 0)).to(torch.int32)


def _tile_box(means2d: Tensor, radii: Tensor, tile_size: int, tile_width: int, tile_height: int):
    """gsplat's intersected tile range [x0, x1) x [y0, y1) (floats holding integers) from the 3-sigma radius."""
    r = radii.to(means2d.dtype)
    mx, my = means2d[..., 0], means2d[..., 1]
    x0 = torch.floor((mx - r) / tile_size).clamp(0, tile_width)
    x1 = torch.ceil((mx + r) / tile_size).clamp(0, tile_width)
    y0 = torch.floor((my - r) / tile_size).clamp(0, tile_height)
    y1 = torch.ceil((my + r) / tile_size).clamp(0, tile_height)
    return x0, x1, y0, y1


@torch.no_grad()
def bin_pairs(
    means2d: Tensor,  # [S, 2] splats in (camera, depth) order
    conics: Tensor,  # [S, 3]
    opacities: Tensor,  # [S]
    radii: Tensor,  # [S] > 0
    cams: Tensor,  # [S] camera index
    width: int,
    height: int,
    n_cameras: int,
    tile_size: int,
    layers_per_chunk: int | None = None,
) -> dict:
    """The Gaussian-pixel pairs gsplat composites (before its T cut-off), sorted by (pixel, depth), with alpha.

    No gradient: the pair set is piecewise constant in the parameters. Pixel p is a pair of splat s iff p lies in
    one of gsplat's intersected tiles of s (from the 3-sigma radius) and alpha = min(0.999, o exp(-sigma)) >= 1/255
    with sigma >= 0. alpha >= 1/255 <=> sigma <= ln(255 o), an ellipse: pixels are enumerated row by row over its
    (slightly widened) chords with two repeat_interleaves (splat -> rows -> pixels), then tested exactly, so the
    cost is proportional to the pairs, never to N x pixels.

    Early termination: when the pairs are many times the pixels (dense scenes), splats are processed front to back
    in chunks of about `layers_per_chunk` pairs per pixel; once a pixel's transmittance after a chunk is <= 1e-4,
    gsplat's cut-off has fired there, so later chunks skip it.

    Returns a dict of [M] tensors: sp (splat index), pix (global pixel id (cam * H + y) * W + x), raw (o exp(-sigma),
    alpha before the 0.999 clamp), dx, dy (pixel centre minus 2D mean).
    """
    device, dtype = means2d.device, means2d.dtype
    S = means2d.shape[0]
    n_pix = n_cameras * height * width
    tile_width = math.ceil(width / tile_size)
    tile_height = math.ceil(height / tile_size)
    tx0, tx1, ty0, ty1 = _tile_box(means2d, radii, tile_size, tile_width, tile_height)
    mx, my = means2d.unbind(-1)
    a, b, c = conics.unbind(-1)
    # ellipse a dx^2 + 2 b dx dy + c dy^2 <= 2 t, t = ln(255 o); |dy| <= sqrt(2 t a / det), det = a c - b^2 > 0.
    # The 1e-4 relative / 1e-3 px widening only makes the candidates a safe superset; the exact test decides.
    t = torch.log(opacities * 255.0)
    det = a * c - b * b
    hy = torch.sqrt(2.0 * t.clamp_min(0.0) * a / det) * 1.0001 + 1e-3
    # a near-degenerate conic (det ~ 0 after float32 rounding) gives NaN / inf: fall back to the tile box
    hy = torch.where(torch.isfinite(hy), hy, torch.full_like(hy, float(height)))
    y0 = torch.maximum(torch.ceil(my - hy - 0.5), ty0 * tile_size)
    y1 = torch.minimum(torch.floor(my + hy - 0.5), torch.clamp(ty1 * tile_size, max=height) - 1)
    ny = (y1 - y0 + 1).clamp(0, height)  # float clamp first: huge boxes must not overflow the int conversion
    ny = torch.where(t >= 0, ny, torch.zeros_like(ny)).long()
    y0 = y0.clamp(0, height)

    # rows: one per (splat, image row) crossing the ellipse
    rs = torch.repeat_interleave(torch.arange(S, device=device), ny)  # [R]
    R = rs.numel()
    tab = torch.stack(
        [mx, my, a, b, c, det, t, opacities, y0, tx0 * tile_size, torch.clamp(tx1 * tile_size, max=width)]
    )
    mx_r, my_r, a_r, b_r, c_r, det_r, t_r, o_r, y0_r, xa_r, xb_r = tab.index_select(1, rs)
    y = y0_r + (torch.arange(R, device=device) - (torch.cumsum(ny, 0) - ny).index_select(0, rs)).to(dtype)
    dy = y + 0.5 - my_r
    # the row's chord: dx in [xc - half, xc + half]
    xc = mx_r - b_r * dy / a_r
    half = torch.sqrt(torch.clamp(2.0 * t_r * a_r - dy * dy * det_r, min=0.0)) / a_r * 1.0001 + 1e-3
    x0 = torch.maximum(torch.ceil(xc - half - 0.5), xa_r)
    x1 = torch.minimum(torch.floor(xc + half - 0.5), xb_r - 1)
    chord_ok = torch.isfinite(xc) & torch.isfinite(half)  # else (degenerate conic): the whole tile row; alpha decides
    x0 = torch.where(chord_ok, x0, xa_r)
    x1 = torch.where(chord_ok, x1, xb_r - 1)
    nx = (x1 - x0 + 1).clamp(0, width).long()
    x0 = x0.clamp(0, width)
    # per row: sigma(dx) = (A dx + B) dx + Cc with A = a / 2, B = b dy, Cc = c dy^2 / 2
    rows_f = torch.stack([x0 + 0.5 - mx_r, dy, 0.5 * a_r, b_r * dy, 0.5 * c_r * dy * dy, o_r])  # [6, R]
    base = (cams.index_select(0, rs) * height + y.long()) * width + x0.long()  # pixel id of each chord's start

    ends = torch.cumsum(nx, 0)
    M = int(ends[-1]) if R > 0 else 0
    # int32 pair indices when they fit: half the memory traffic, and int32 keys sort ~2x faster
    idx_dtype = torch.int32 if max(M, n_pix, S) < 2**31 else torch.int64
    chunk = (layers_per_chunk or LAYERS_PER_CHUNK) * n_pix
    bounds = [0, R]
    if M > 3 * chunk:  # below ~50 layers per pixel the extra passes cost more than the cut-off saves
        cuts = torch.searchsorted(ends, torch.arange(chunk, M, chunk, device=device)).tolist()
        bounds = sorted(set([0, R] + cuts))
    log_t = torch.zeros(n_pix, dtype=torch.float64, device=device) if len(bounds) > 2 else None
    rows_i = torch.stack([ends - nx, base, rs]).to(idx_dtype)  # [3, R]: first pair, first pixel, splat
    parts = []
    for r0, r1 in zip(bounds[:-1], bounds[1:], strict=True):
        n = nx[r0:r1]
        first, base_p, sp = torch.repeat_interleave(rows_i[:, r0:r1], n, dim=1)
        dx0, dy_p, A, B, Cc, o = torch.repeat_interleave(rows_f[:, r0:r1], n, dim=1)
        start = int(ends[r0 - 1]) if r0 > 0 else 0
        stop = int(ends[r1 - 1]) if r1 > r0 else start
        local = torch.arange(start, stop, dtype=idx_dtype, device=device) - first  # index within the row's chord
        dx = dx0 + local.to(dtype)
        pix = base_p + local
        sigma = (A * dx + B) * dx + Cc
        raw = o * torch.exp(-sigma)
        ok = (sigma >= 0) & (raw >= ALPHA_MIN)  # alpha = min(0.999, raw) >= 1/255 <=> raw >= 1/255
        if log_t is not None and r0 > 0:
            ok &= (log_t > math.log(T_MIN)).index_select(0, pix)  # pixels already cut off stay done
        keep = torch.nonzero(ok).squeeze(1)
        part = [x.index_select(0, keep) for x in (sp, pix, raw, dx, dy_p)]
        if log_t is not None:
            log_t.index_add_(0, part[1].long(), torch.log1p(-torch.clamp_max(part[2], ALPHA_MAX).double()))
        parts.append(part)
    sp, pix, raw, dx, dy = [torch.cat(x) for x in zip(*parts, strict=True)] if len(parts) > 1 else parts[0]
    # splats were enumerated in (camera, depth) order: one stable sort by pixel gives front-to-back lists
    pix, perm = torch.sort(pix, stable=True)
    return {
        "sp": sp.index_select(0, perm).long(),  # int64: index_add with int32 indices is very slow on CPU
        "pix": pix.long(),
        "raw": raw.index_select(0, perm),
        "dx": dx.index_select(0, perm),
        "dy": dy.index_select(0, perm),
    }


def _segments(pix: Tensor, n_pix: int) -> tuple:
    """For an id array sorted ascending: per element, the index of the first and of the last element with its id."""
    counts = torch.bincount(pix, minlength=n_pix)
    ends = torch.cumsum(counts, 0)
    return (ends - counts).index_select(0, pix), (ends - 1).index_select(0, pix)


class _Composite(torch.autograd.Function):
    """Front-to-back alpha compositing over pairs sorted by (pixel, depth), with gsplat's rules.

    Forward (pairs and their alpha come from `bin_pairs`, computed from the same detached values): T is a segmented
    exclusive cumsum of log(1 - alpha) in float64; a pair whose next_T <= 1e-4 ends its pixel (exclusive). Outputs
    the accumulated features sum(alpha T f) [D, P] and alpha 1 - T_final [P].

    Backward (the analytic gradient of gsplat's kernel, vectorised): with w_i = alpha_i T_i and g = dL/dimage,
        dL/df_i     = w_i g
        dL/dalpha_i = T_i g.f_i - (sum_{j>i} w_j g.f_j) / (1 - alpha_i) + dL/dacc T_final / (1 - alpha_i)
    then through alpha = o exp(-sigma) to the opacity, the conic and the 2D mean (zero where alpha is clamped at
    0.999, like gsplat).

    Per-pair arrays are kept as rows ([6, K], [D, K]): contiguous rows make the elementwise work, the stacking and
    the index_add along dim 1 several times faster on CPU than [K, 6] columns.
    """

    @staticmethod
    def forward(ctx, means2d, conics, opacities, features, sp, pix, raw, dx, dy, n_pix, stats):
        alpha = torch.clamp_max(raw, ALPHA_MAX)
        # exclusive segmented cumsum in float64: a global float32 cumsum over ~1e6 pairs would lose T's precision
        log1m = torch.log1p(-alpha.double())
        cs = torch.cumsum(log1m, 0)
        first, _ = _segments(pix, n_pix)
        log_next_t = cs - (cs - log1m).index_select(0, first)
        keep = torch.nonzero(log_next_t > math.log(T_MIN)).squeeze(1)
        if keep.numel() < pix.numel():
            sp, pix, raw, alpha, dx, dy = [x.index_select(0, keep) for x in (sp, pix, raw, alpha, dx, dy)]
            log1m, log_next_t = log1m.index_select(0, keep), log_next_t.index_select(0, keep)
        T = torch.exp(log_next_t - log1m).to(alpha.dtype)
        w = alpha * T
        img = torch.zeros(features.shape[1], n_pix, dtype=features.dtype, device=features.device)
        img.index_add_(1, pix, features.t().index_select(1, sp) * w)
        log_t_final = torch.zeros(n_pix, dtype=log1m.dtype, device=log1m.device).index_add_(0, pix, log1m)
        t_final = torch.exp(log_t_final).to(alpha.dtype)
        stats["n_pairs"] = int(pix.numel())
        tab = torch.cat([conics.t(), opacities[None]], dim=0)  # [4, S]
        ctx.save_for_backward(tab, features, sp, pix, raw, alpha, T, dx, dy, t_final)
        ctx.n_pix = n_pix
        return img, 1.0 - t_final

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, *grad_outputs):  # type: ignore[override]
        v_img, v_acc = grad_outputs  # [D, P], [P]
        tab, features, sp, pix, raw, alpha, T, dx, dy, t_final = ctx.saved_tensors
        G = v_img.contiguous().index_select(1, pix)  # [D, K] (contiguous: the grad of a sum is a stride-0 view)
        w = alpha * T
        v_features = None
        if ctx.needs_input_grad[3]:
            v_features = torch.zeros_like(features.t()).index_add_(1, sp, G * w).t()
        if not any(ctx.needs_input_grad[:3]):
            return None, None, None, v_features, None, None, None, None, None, None, None
        gf = (G * features.t().index_select(1, sp)).sum(0)  # g . f_i
        # sum over later pairs of the same pixel of w_j g.f_j: segment total minus inclusive cumsum (float64)
        cs = torch.cumsum((w * gf).double(), 0)
        _, last = _segments(pix, ctx.n_pix)
        later = (cs.index_select(0, last) - cs).to(alpha.dtype)
        v_alpha = T * gf + ((v_acc.contiguous() * t_final).index_select(0, pix) - later) / (1.0 - alpha)
        v_alpha = v_alpha * (raw <= ALPHA_MAX)  # no gradient through the clamp

        a, b, c, o = tab.index_select(1, sp)
        v_o = alpha / o * v_alpha  # = exp(-sigma) v_alpha where not clamped; o >= alpha >= 1/255
        v_sigma = -alpha * v_alpha
        hv = 0.5 * v_sigma
        v_pair = torch.stack(
            [
                -v_sigma * (a * dx + b * dy),  # d sigma / d mean2d = -(conic @ (pixel - mean2d))
                -v_sigma * (b * dx + c * dy),
                hv * dx * dx,
                v_sigma * dx * dy,
                hv * dy * dy,
                v_o,
            ]
        )  # [6, K]
        v_tab = torch.zeros(6, tab.shape[1], dtype=tab.dtype, device=tab.device).index_add_(1, sp, v_pair)
        return v_tab[:2].t(), v_tab[2:5].t(), v_tab[5], v_features, None, None, None, None, None, None, None


def composite_pairs(
    means2d: Tensor,  # [S, 2]
    conics: Tensor,  # [S, 3]
    opacities: Tensor,  # [S]
    features: Tensor,  # [S, D]
    pairs: dict,  # from bin_pairs
    n_pix: int,
) -> tuple:
    """Differentiable compositing (see `_Composite`). Returns features [n_pix, D], alpha [n_pix], n_pairs."""
    stats: dict = {}
    img, acc = _Composite.apply(
        means2d,
        conics,
        opacities,
        features,
        pairs["sp"],
        pairs["pix"],
        pairs["raw"],
        pairs["dx"],
        pairs["dy"],
        n_pix,
        stats,
    )
    return img.t(), acc, stats["n_pairs"]


def _depth_sort_key(depths: Tensor, near_plane: float) -> Tensor:
    """A sort key with the order of the depths. Visible depths are >= near_plane; when that is >= 0, the IEEE bit
    pattern read as an integer has the same order (gsplat sorts these bits too), and integer sorts are radix sorts,
    ~15x faster than float sorts on CPU."""
    if near_plane >= 0 and depths.dtype in (torch.float32, torch.float64):
        return depths.contiguous().view(torch.int32 if depths.dtype == torch.float32 else torch.int64)
    return depths


def rasterize_torch(
    means: Tensor,  # [N, 3]
    quats: Tensor,  # [N, 4]
    scales: Tensor,  # [N, 3]
    opacities: Tensor,  # [N]
    colors: Tensor,  # [(C,) N, D] or [(C,) N, K, 3]
    viewmats: Tensor,  # [C, 4, 4]
    Ks: Tensor,  # [C, 3, 3]
    width: int,
    height: int,
    *,
    backgrounds: Tensor | None = None,  # [C, D]
    render_mode: str = "RGB",
    near_plane: float = 0.01,
    far_plane: float = 1e10,
    eps2d: float = 0.3,
    sh_degree: int | None = None,
    packed: bool = False,
    rasterize_mode: str = "classic",
    radius_clip: float = 0.0,
    tile_size: int = 16,
) -> tuple:
    """The torch backend of `willags_ns.render.rasterize` (inputs already validated there)."""
    C, N = viewmats.shape[0], means.shape[0]
    device = means.device
    proj = project_gaussians(
        means,
        quats,
        scales,
        viewmats,
        Ks,
        width,
        height,
        eps2d=eps2d,
        near_plane=near_plane,
        far_plane=far_plane,
        radius_clip=radius_clip,
        calc_compensations=rasterize_mode == "antialiased",
    )
    radii, means2d, depths, conics = proj["radii"], proj["means2d"], proj["depths"], proj["conics"]
    opac = opacities[None, :].expand(C, N)
    if proj["compensations"] is not None:
        opac = opac * proj["compensations"]

    # Flat views over (camera, gaussian); in packed mode the meta tensors are the packed ones and everything
    # downstream indexes into them, so meta["means2d"].grad is the gradient w.r.t. exactly that tensor.
    radii_f = radii.reshape(C * N)
    vis = torch.nonzero(radii_f > 0).squeeze(1)  # [nnz] flat ids, camera-major
    cam_ids = torch.div(vis, max(N, 1), rounding_mode="floor")
    gs_ids = vis - cam_ids * N
    if packed:
        means2d = means2d.reshape(C * N, 2).index_select(0, vis)
        depths = depths.reshape(C * N).index_select(0, vis)
        conics = conics.reshape(C * N, 3).index_select(0, vis)
        opac = opac.reshape(C * N).index_select(0, vis)
        radii = radii_f.index_select(0, vis)
        src = torch.arange(vis.numel(), device=device)  # visible rows of the flat tables
        means2d_f, depths_f, conics_f, opac_f = means2d, depths, conics, opac
    else:
        src = vis
        means2d_f, depths_f = means2d.reshape(C * N, 2), depths.reshape(C * N)
        conics_f, opac_f = conics.reshape(C * N, 3), opac.reshape(C * N)

    # visible splats in (camera, depth) order; ties broken by Gaussian index like gsplat's stable radix sort
    with torch.no_grad():
        order = torch.sort(_depth_sort_key(depths_f.detach().index_select(0, src), near_plane), stable=True).indices
        if C > 1:
            order = order.index_select(0, torch.sort(cam_ids.index_select(0, order), stable=True).indices)
    src = src.index_select(0, order)
    cam_s, gs_s = cam_ids.index_select(0, order), gs_ids.index_select(0, order)
    m2_s = means2d_f.index_select(0, src)  # [S, 2]
    con_s = conics_f.index_select(0, src)
    op_s = opac_f.index_select(0, src)

    # per-splat features: colours (or SH evaluated along camera -> mean), then the depth channel if asked for
    feats = []
    if render_mode in ("RGB", "RGB+D", "RGB+ED"):
        if sh_degree is None:
            col = colors.index_select(0, gs_s) if colors.dim() == 2 else colors[cam_s, gs_s]
        else:
            campos = torch.linalg.inv(viewmats)[:, :3, 3]  # [C, 3], as gsplat
            dirs = means.index_select(0, gs_s) - campos.index_select(0, cam_s)
            shs = colors.index_select(0, gs_s) if colors.dim() == 3 else colors[cam_s, gs_s]
            col = sh_color(sh_degree, dirs, shs)  # gsplat's offset and clamp
        feats.append(col)
    if render_mode != "RGB":
        feats.append(depths_f.index_select(0, src)[:, None])
    feats = torch.cat(feats, dim=-1) if len(feats) > 1 else feats[0]  # [S, D']

    pairs = bin_pairs(
        m2_s.detach(),
        con_s.detach(),
        op_s.detach(),
        radii.reshape(-1).index_select(0, src),
        cam_s,
        width,
        height,
        C,
        tile_size,
    )
    out, acc, n_pairs = composite_pairs(m2_s, con_s, op_s, feats, pairs, C * height * width)
    render = out.reshape(C, height, width, -1)
    alpha = acc.reshape(C, height, width, 1)

    if backgrounds is not None:
        if render_mode in ("RGB+D", "RGB+ED"):
            backgrounds = torch.cat([backgrounds, backgrounds.new_zeros(C, 1)], dim=-1)
        elif render_mode in ("D", "ED"):
            backgrounds = backgrounds.new_zeros(C, 1)
        render = render + (1.0 - alpha) * backgrounds[:, None, None, :]
    if render_mode in ("ED", "RGB+ED"):
        # gsplat 1.4: accumulated depth / accumulated alpha (clamped), background depth is 0
        render = torch.cat([render[..., :-1], render[..., -1:] / alpha.clamp(min=1e-10)], dim=-1)

    tile_width = math.ceil(width / tile_size)
    tile_height = math.ceil(height / tile_size)
    meta = {
        "camera_ids": cam_ids if packed else None,
        "gaussian_ids": gs_ids if packed else None,
        "radii": radii,
        "means2d": means2d,
        "depths": depths,
        "conics": conics,
        "opacities": opac,
        "tile_width": tile_width,
        "tile_height": tile_height,
        "tiles_per_gauss": tiles_per_gauss(means2d, radii, tile_size, tile_width, tile_height),
        # gsplat's tile-intersection buffers have no meaning for this backend
        "isect_ids": None,
        "flatten_ids": None,
        "isect_offsets": None,
        "width": width,
        "height": height,
        "tile_size": tile_size,
        "n_cameras": C,
        # torch-backend extras
        "n_pairs": n_pairs,
        "n_candidates": int(pairs["pix"].numel()),
        "backend": "torch",
    }
    return render, alpha, meta
