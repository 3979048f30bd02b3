"""`rasterize`: one function, gsplat 1.4.0's `rasterization()` contract, two backends.

- "gsplat": gsplat's public CUDA `rasterization()`, every argument passed through.
- "torch": our pure-PyTorch rasterizer (`_torch.py`), same projection, pair set, ordering, early stop and
  compositing as gsplat, differentiable through autograd; runs anywhere (CPU tests, CPU training).
- "auto": gsplat for CUDA tensors, torch otherwise.

Example:
    >>> render, alpha, meta = rasterize(means, quats, scales, opacities, colors, viewmats, Ks, 64, 48)
    >>> render.shape, alpha.shape  # [C, 48, 64, D], [C, 48, 64, 1]
"""

from typing import Any

from jaxtyping import Float
from torch import Tensor

from willags_ns.render._gsplat import rasterize_gsplat
from willags_ns.render._torch import rasterize_torch
from willags_ns.render.sh import MAX_SH_DEGREE, num_sh_bases

BACKENDS = ("auto", "gsplat", "torch")
RENDER_MODES = ("RGB", "D", "ED", "RGB+D", "RGB+ED")
RASTERIZE_MODES = ("classic", "antialiased")


def rasterize(
    means: Float[Tensor, "N 3"],
    quats: Float[Tensor, "N 4"],
    scales: Float[Tensor, "N 3"],
    opacities: Float[Tensor, " N"],
    colors: Tensor,  # [N, D] | [C, N, D] | SH [N, K, 3] | [C, N, K, 3]
    viewmats: Float[Tensor, "C 4 4"],
    Ks: Float[Tensor, "C 3 3"],
    width: int,
    height: int,
    *,
    backgrounds: Float[Tensor, "C D"] | None = None,
    render_mode: str = "RGB",
    backend: str = "auto",
    near_plane: float = 0.01,
    far_plane: float = 1e10,
    eps2d: float = 0.3,
    sh_degree: int | None = None,
    packed: bool = False,
    absgrad: bool = False,
    rasterize_mode: str = "classic",
    radius_clip: float = 0.0,
    tile_size: int = 16,
) -> tuple[Tensor, Tensor, dict[str, Any]]:
    """Rasterize N 3D Gaussians into C pinhole cameras (shapes and semantics of gsplat 1.4.0 `rasterization`).

    Args:
        means: Gaussian centres (world). [N, 3]
        quats: rotations, wxyz, need not be normalised. [N, 4]
        scales: activated (exp'ed) scales. [N, 3]
        opacities: activated (sigmoid'ed) opacities. [N]
        colors: post-activation features [N, D] / [C, N, D], or SH coefficients [N, K, 3] / [C, N, K, 3] when
            `sh_degree` is set (evaluated along camera -> mean, then + 0.5 and clamped at 0, like gsplat).
        viewmats: world-to-camera matrices. [C, 4, 4]
        Ks: intrinsics. [C, 3, 3]
        width, height: image size in pixels.
        backgrounds: colour behind the splats, render + (1 - alpha) * bg. [C, D]
        render_mode: "RGB", "D" (accumulated z), "ED" (expected z = accumulated z / alpha), "RGB+D", "RGB+ED"
            (depth appended as the last channel).
        backend: "auto" (gsplat if `means.is_cuda`, else torch), "gsplat" or "torch".
        near_plane, far_plane: Gaussians with camera z outside [near, far] are culled.
        eps2d: low-pass filter added to the 2D covariance diagonal (pixels^2).
        sh_degree: SH degree to evaluate, or None for plain features.
        packed: gsplat's packed meta layout ([nnz, ...] plus camera_ids / gaussian_ids) instead of [C, N, ...].
        absgrad: also accumulate |d loss / d means2d| per pixel (gsplat backend only).
        rasterize_mode: "classic" or "antialiased" (opacity times the Mip-Splatting compensation).
        radius_clip: Gaussians whose pixel radius is <= this are skipped.
        tile_size: gsplat's tile size; it also decides which pixels a Gaussian touches (its intersected tiles).

    Returns:
        render [C, H, W, D'], alpha [C, H, W, 1], meta (dict). meta holds gsplat's keys: radii [C, N] int32
        (0 = culled), means2d [C, N, 2] (non-leaf: `retain_grad()` it before backward to read d loss / d means2d
        in pixels, as gsplat's strategies do), depths, conics, opacities, camera_ids, gaussian_ids, width, height,
        n_cameras, tile_width, tile_height, tile_size, tiles_per_gauss, isect_ids, flatten_ids, isect_offsets
        (the last three are None for the torch backend), plus "backend"; the torch backend adds "n_pairs" and
        "n_candidates" (Gaussian-pixel pairs composited / tested).

    Raises:
        ValueError: wrong shapes or options, a CUDA-only option with the torch backend, or CPU tensors with the
            gsplat backend.
    """
    _check_inputs(
        means, quats, scales, opacities, colors, viewmats, Ks, width, height, backgrounds, render_mode, sh_degree
    )
    if backend not in BACKENDS:
        raise ValueError(f"backend must be one of {BACKENDS}, got {backend!r}")
    if rasterize_mode not in RASTERIZE_MODES:
        raise ValueError(f"rasterize_mode must be one of {RASTERIZE_MODES}, got {rasterize_mode!r}")
    if not isinstance(tile_size, int) or tile_size <= 0:
        raise ValueError(f"tile_size must be a positive int, got {tile_size!r}")
    if backend == "auto":
        backend = "gsplat" if means.is_cuda else "torch"
    kwargs: dict[str, Any] = dict(
        backgrounds=backgrounds,
        render_mode=render_mode,
        near_plane=near_plane,
        far_plane=far_plane,
        eps2d=eps2d,
        sh_degree=sh_degree,
        packed=packed,
        rasterize_mode=rasterize_mode,
        radius_clip=radius_clip,
        tile_size=tile_size,
    )
    if backend == "gsplat":
        if not means.is_cuda:
            raise ValueError("backend='gsplat' needs CUDA tensors; use backend='torch' (or 'auto') on CPU")
        return rasterize_gsplat(
            means, quats, scales, opacities, colors, viewmats, Ks, width, height, absgrad=absgrad, **kwargs
        )
    if absgrad:
        raise ValueError(
            "absgrad=True needs gsplat's CUDA backward (it accumulates |grad| per pixel inside the kernel); "
            "the torch backend does not provide it: pass absgrad=False (and a strategy with absgrad=False)"
        )
    return rasterize_torch(means, quats, scales, opacities, colors, viewmats, Ks, width, height, **kwargs)


def _check_inputs(
    means, quats, scales, opacities, colors, viewmats, Ks, width, height, backgrounds, render_mode, sh_degree
) -> None:
    """Shape-only checks (no values read, no host sync), with messages that name the offending argument."""

    def shape_error(name: str, want: str, t: Tensor) -> ValueError:
        return ValueError(f"{name} must have shape {want}, got {tuple(t.shape)}")

    if means.dim() != 2 or means.shape[1] != 3:
        raise shape_error("means", "[N, 3]", means)
    N = means.shape[0]
    if quats.shape != (N, 4):
        raise shape_error("quats", f"[N={N}, 4]", quats)
    if scales.shape != (N, 3):
        raise shape_error("scales", f"[N={N}, 3]", scales)
    if opacities.shape != (N,):
        raise shape_error("opacities", f"[N={N}]", opacities)
    if viewmats.dim() != 3 or viewmats.shape[1:] != (4, 4):
        raise shape_error("viewmats", "[C, 4, 4]", viewmats)
    C = viewmats.shape[0]
    if C == 0:
        raise ValueError("viewmats must hold at least one camera")
    if Ks.shape != (C, 3, 3):
        raise shape_error("Ks", f"[C={C}, 3, 3]", Ks)
    if not isinstance(width, int) or not isinstance(height, int) or width <= 0 or height <= 0:
        raise ValueError(f"width and height must be positive ints, got {width!r} x {height!r}")
    if render_mode not in RENDER_MODES:
        raise ValueError(f"render_mode must be one of {RENDER_MODES}, got {render_mode!r}")
    if sh_degree is None:
        if not ((colors.dim() == 2 and colors.shape[0] == N) or (colors.dim() == 3 and colors.shape[:2] == (C, N))):
            raise shape_error("colors (sh_degree=None)", f"[N={N}, D] or [C={C}, N={N}, D]", colors)
        n_channels = colors.shape[-1]
    else:
        if not isinstance(sh_degree, int) or not 0 <= sh_degree <= MAX_SH_DEGREE:
            raise ValueError(f"sh_degree must be None or an int in [0, {MAX_SH_DEGREE}], got {sh_degree!r}")
        ok = (colors.dim() == 3 and colors.shape[0] == N) or (colors.dim() == 4 and colors.shape[:2] == (C, N))
        if not ok or colors.shape[-1] != 3:
            raise shape_error("colors (SH coefficients)", f"[N={N}, K, 3] or [C={C}, N={N}, K, 3]", colors)
        if colors.shape[-2] < num_sh_bases(sh_degree):
            raise ValueError(
                f"sh_degree={sh_degree} needs K >= {num_sh_bases(sh_degree)} SH coefficients, got {colors.shape[-2]}"
            )
        n_channels = 3
    if backgrounds is not None and backgrounds.shape != (C, n_channels):
        raise shape_error("backgrounds", f"[C={C}, D={n_channels}]", backgrounds)
