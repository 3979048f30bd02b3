"""Pure-PyTorch 3D Gaussian rasterizer: the CPU twin of gsplat 1.4.0's CUDA `rasterization()` (pinhole, 3DGS).

No gsplat import anywhere here: gsplat's own `_torch_impl` still calls CUDA ops for binning, so it cannot run on a
CPU-only machine.

Pipeline (all vectorised, no Python loop over Gaussians, tiles or pixels):

1. `project_gaussians`: EWA splatting exactly as gsplat's `fully_fused_projection` (pinhole): world->camera,
   covariance R S S^T R^T, Jacobian with gsplat's clipped tx/ty (lim = (W - cx) / fx + 0.3 tan_fovx),
   cov2d + eps2d I, conic = cov2d^-1, radius = ceil(3 sqrt(lambda_max)), culling (depth outside
   [near, far], radius <= radius_clip, 3-sigma box off-screen) -> radii 0.
2. Binning into Gaussian-pixel pairs, never a dense N x pixels matrix: gsplat rasterises pixel p with splat g
   iff p lies in one of g's intersected 16x16 tiles and alpha = min(0.999, o exp(-sigma)) >= 1/255 (sigma >= 0).
   alpha >= 1/255 <=> sigma <= ln(255 o), an ellipse whose axis-aligned box has half-widths
   sqrt(2 ln(255 o) Sigma_xx) and sqrt(2 ln(255 o) Sigma_yy); the candidate pixels are that box intersected with
   the tile box, enumerated with one repeat_interleave and filtered by the exact alpha test. This is the same pair
   set as gsplat (including the pixels just outside the 3-sigma radius that gsplat still touches in the tile).
3. Splats are enumerated in (camera, depth) order, so ONE stable sort by pixel id gives front-to-back lists per
   pixel. Transmittance is a segmented exclusive cumsum of log(1 - alpha) in float64 (global cumsum minus its
   value at each pixel's first pair). gsplat's early stop (next_T = T (1 - alpha) <= 1e-4 ends the pixel,
   exclusive) keeps a prefix of each pixel's list.
4. Only the surviving pairs are re-evaluated with autograd enabled; weights w = alpha T are scattered into the
   image with index_add. Autograd provides the backward, including d loss / d means2d for densification.

Steps 2-3 run under no_grad on detached values: they only decide *which* pairs exist and in what order; the
pair set is piecewise constant in the parameters, exactly as in gsplat (whose backward ignores it too).
"""

import math
from typing import Optional

import torch
import torch.nn.functional as F
from torch import Tensor

from willags_ns.render.sh import spherical_harmonics

ALPHA_MIN = 1.0 / 255.0  # gsplat skips pairs below this alpha: they change neither colour nor transmittance
ALPHA_MAX = 0.999  # gsplat clamps alpha here (and stops gradients through the clamp)
T_MIN = 1e-4  # gsplat stops a pixel once the transmittance after a Gaussian would be <= this


def quat_scale_to_matrix(quats: Tensor, scales: Tensor) -> Tensor:
    """M = R(q) diag(s), so that the covariance is M M^T. Quaternions wxyz, normalised here like gsplat.

    Args:
        quats: [N, 4] (any non-zero norm).
        scales: [N, 3] (already activated).

    Returns:
        [N, 3, 3]
    """
    w, x, y, z = F.normalize(quats, p=2, dim=-1).unbind(-1)
    R = torch.stack(
        [
            1 - 2 * (y * y + z * z),
            2 * (x * y - w * z),
            2 * (x * z + w * y),
            2 * (x * y + w * z),
            1 - 2 * (x * x + z * z),
            2 * (y * z - w * x),
            2 * (x * z - w * y),
            2 * (y * z + w * x),
            1 - 2 * (x * x + y * y),
        ],
        dim=-1,
    ).reshape(quats.shape[:-1] + (3, 3))
    return R * scales[..., None, :]


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
    (camera z), conics [C, N, 3] (upper triangle of cov2d^-1), cov2d [C, N, 3] (blurred covariance, upper
    triangle), compensations [C, N] or None. Culled entries hold finite but meaningless values.
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
    B0 = j00[..., None] * Mc[..., 0, :] + j02[..., None] * Mc[..., 2, :]  # [C, N, 3]
    B1 = j11[..., None] * Mc[..., 1, :] + j12[..., None] * Mc[..., 2, :]  # [C, N, 3]
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
    conics = torch.stack([c11 / det, -c01 / det, c00 / det], dim=-1)  # [C, N, 3]

    with torch.no_grad():
        b = 0.5 * (c00 + c11)
        v1 = b + torch.sqrt(torch.clamp(b * b - det, min=0.01))
        radius = torch.ceil(3.0 * torch.sqrt(v1))
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
        "cov2d": torch.stack([c00, c01, c11], dim=-1),
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
def _bin_pairs(
    means2d: Tensor,  # [S, 2] splats in (camera, depth) order
    conics: Tensor,  # [S, 3]
    cov2d: Tensor,  # [S, 3]
    opacities: Tensor,  # [S]
    radii: Tensor,  # [S] > 0
    cams: Tensor,  # [S] camera index
    width: int,
    height: int,
    n_cameras: int,
    tile_size: int,
):
    """Gaussian-pixel pairs that gsplat would composite, sorted by (pixel, depth), after the T cut-off.

    Returns (splat index [K], global pixel id [K] = (cam * H + y) * W + x, n_candidates).
    """
    device = means2d.device
    S = means2d.shape[0]
    tile_width = math.ceil(width / tile_size)
    tile_height = math.ceil(height / tile_size)
    tx0, tx1, ty0, ty1 = _tile_box(means2d, radii, tile_size, tile_width, tile_height)
    mx, my = means2d.unbind(-1)
    # alpha >= 1/255 <=> sigma <= ln(255 o): an ellipse; its box half-widths are sqrt(2 t Sigma_xx), sqrt(2 t Sigma_yy).
    # The margin only makes the box a safe superset: the exact alpha test below decides.
    t = torch.log(opacities * 255.0).clamp_min(0.0)
    hx = torch.sqrt(2.0 * t * cov2d[:, 0]) * 1.001 + 1e-3
    hy = torch.sqrt(2.0 * t * cov2d[:, 2]) * 1.001 + 1e-3
    # pixel x is a candidate iff |x + 0.5 - mx| <= hx and its tile is intersected (and it is inside the image)
    x0 = torch.maximum(torch.ceil(mx - hx - 0.5), tx0 * tile_size)
    x1 = torch.minimum(torch.floor(mx + hx - 0.5), torch.clamp(tx1 * tile_size, max=width) - 1)
    y0 = torch.maximum(torch.ceil(my - hy - 0.5), ty0 * tile_size)
    y1 = torch.minimum(torch.floor(my + hy - 0.5), torch.clamp(ty1 * tile_size, max=height) - 1)
    nx = (x1 - x0 + 1).clamp(0, width)  # float clamps first: huge boxes must not overflow int conversion
    ny = (y1 - y0 + 1).clamp(0, height)
    has = opacities >= ALPHA_MIN
    nx = torch.where(has, nx, torch.zeros_like(nx)).long()
    ny = ny.long()
    counts = nx * ny  # [S]
    x0 = x0.clamp(0, width).long()
    y0 = y0.clamp(0, height).long()

    # enumerate candidates: pair j belongs to splat sp[j] and is its local[j]-th pixel (row-major in its box)
    sp = torch.repeat_interleave(torch.arange(S, device=device), counts)  # [M]
    n_cand = sp.numel()
    first = torch.cumsum(counts, 0) - counts
    local = torch.arange(n_cand, device=device) - first.index_select(0, sp)
    nxs = nx.index_select(0, sp)
    ly = torch.div(local, nxs, rounding_mode="floor")
    px = x0.index_select(0, sp) + (local - ly * nxs)
    py = y0.index_select(0, sp) + ly

    # exact alpha test, as gsplat (pixel centres at +0.5)
    dx = px.to(mx.dtype) + 0.5 - mx.index_select(0, sp)
    dy = py.to(mx.dtype) + 0.5 - my.index_select(0, sp)
    con = conics.index_select(0, sp)
    sigma = 0.5 * (con[:, 0] * dx * dx + con[:, 2] * dy * dy) + con[:, 1] * dx * dy
    alpha = torch.clamp_max(opacities.index_select(0, sp) * torch.exp(-sigma), ALPHA_MAX)
    keep = torch.nonzero((sigma >= 0) & (alpha >= ALPHA_MIN)).squeeze(1)
    sp = sp.index_select(0, keep)
    alpha = alpha.index_select(0, keep)
    pix = (cams.index_select(0, sp) * height + py.index_select(0, keep)) * width + px.index_select(0, keep)

    # splats were enumerated in (camera, depth) order: a stable sort by pixel gives front-to-back lists
    pix, perm = torch.sort(pix, stable=True)
    sp = sp.index_select(0, perm)
    alpha = alpha.index_select(0, perm)

    # gsplat's early stop: drop the pair whose next_T = T (1 - alpha) <= 1e-4 and every later one at that pixel.
    log1m = torch.log1p(-alpha.double())
    cs = torch.cumsum(log1m, 0)
    log_next_t = cs - (cs - log1m).index_select(0, _segment_first(pix, n_cameras * height * width))
    keep = torch.nonzero(log_next_t > math.log(T_MIN)).squeeze(1)
    if keep.numel() < sp.numel():
        sp = sp.index_select(0, keep)
        pix = pix.index_select(0, keep)
    return sp, pix, n_cand


def _segment_first(pix: Tensor, n_pix: int) -> Tensor:
    """For a sorted id array, the index of the first element with the same id, for every element."""
    counts = torch.bincount(pix, minlength=n_pix)
    first = torch.cumsum(counts, 0) - counts
    return first.index_select(0, pix)


def composite_pairs(
    means2d: Tensor,  # [S, 2]
    conics: Tensor,  # [S, 3]
    opacities: Tensor,  # [S]
    features: Tensor,  # [S, D]
    sp: Tensor,  # [K] splat of each pair, sorted by (pixel, depth)
    pix: Tensor,  # [K] global pixel id of each pair
    width: int,
    height: int,
    n_cameras: int,
) -> tuple:
    """Differentiable front-to-back alpha compositing over a sorted pair list.

    Returns accumulated features [n_pix, D] (sum of w f) and alpha [n_pix] (sum of w = 1 - T_final),
    w = alpha T with T = prod over earlier pairs of the same pixel of (1 - alpha).
    """
    n_pix = n_cameras * height * width
    px = torch.remainder(pix, width)
    py = torch.remainder(torch.div(pix, width, rounding_mode="floor"), height)  # row within its camera
    dx = px.to(means2d.dtype) + 0.5 - means2d[:, 0].index_select(0, sp)
    dy = py.to(means2d.dtype) + 0.5 - means2d[:, 1].index_select(0, sp)
    con = conics.index_select(0, sp)
    sigma = 0.5 * (con[:, 0] * dx * dx + con[:, 2] * dy * dy) + con[:, 1] * dx * dy
    alpha = torch.clamp_max(opacities.index_select(0, sp) * torch.exp(-sigma), ALPHA_MAX)
    # exclusive segmented cumsum in float64: a global float32 cumsum over ~1e6 pairs would lose T's precision
    log1m = torch.log1p(-alpha).double()
    excl = torch.cumsum(log1m, 0) - log1m
    log_t = excl - excl.index_select(0, _segment_first(pix, n_pix))
    w = alpha * torch.exp(log_t).to(alpha.dtype)  # [K]
    D = features.shape[-1]
    feats = torch.zeros(n_pix, D, dtype=features.dtype, device=features.device).index_add(
        0, pix, features.index_select(0, sp) * w[:, None]
    )
    acc = torch.zeros(n_pix, dtype=w.dtype, device=w.device).index_add(0, pix, w)
    return feats, acc


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
    backgrounds: Optional[Tensor] = None,  # [C, D]
    render_mode: str = "RGB",
    near_plane: float = 0.01,
    far_plane: float = 1e10,
    eps2d: float = 0.3,
    sh_degree: Optional[int] = None,
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
    cov2d = proj["cov2d"].reshape(C * N, 3)
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
        cov2d = cov2d.index_select(0, vis)
        src = torch.arange(vis.numel(), device=device)  # visible rows of the flat tables
        means2d_f, depths_f, conics_f, opac_f = means2d, depths, conics, opac
    else:
        src = vis
        means2d_f, depths_f = means2d.reshape(C * N, 2), depths.reshape(C * N)
        conics_f, opac_f = conics.reshape(C * N, 3), opac.reshape(C * N)

    # visible splats in (camera, depth) order; ties broken by Gaussian index like gsplat's stable radix sort
    with torch.no_grad():
        order = torch.sort(depths_f.detach().index_select(0, src), stable=True).indices
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
            col = torch.clamp_min(spherical_harmonics(sh_degree, dirs, shs) + 0.5, 0.0)  # gsplat's offset
        feats.append(col)
    if render_mode != "RGB":
        feats.append(depths_f.index_select(0, src)[:, None])
    feats = torch.cat(feats, dim=-1) if len(feats) > 1 else feats[0]  # [S, D']

    sp, pix, n_cand = _bin_pairs(
        m2_s.detach(),
        con_s.detach(),
        cov2d.index_select(0, src).detach(),
        op_s.detach(),
        radii.reshape(-1).index_select(0, src),
        cam_s,
        width,
        height,
        C,
        tile_size,
    )
    out, acc = composite_pairs(m2_s, con_s, op_s, feats, sp, pix, width, height, C)
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
        "n_pairs": int(sp.numel()),
        "n_candidates": int(n_cand),
        "backend": "torch",
    }
    return render, alpha, meta
