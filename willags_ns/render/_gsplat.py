"""Adapter over gsplat 1.4.0's public `gsplat.rasterization()` (CUDA). No private gsplat module is touched."""

from typing import Any, cast

from torch import Tensor


def rasterize_gsplat(
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
    backgrounds: Tensor | None = None,
    render_mode: str = "RGB",
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
    """The gsplat backend of `willags_ns.render.rasterize`: every argument is passed through unchanged."""
    # imported here: importing gsplat is slow and its CUDA extension is only built on first use
    from gsplat import rasterization

    render, alpha, meta = rasterization(
        means=means,
        quats=quats,
        scales=scales,
        opacities=opacities,
        colors=colors,
        viewmats=viewmats,
        Ks=Ks,
        width=width,
        height=height,
        near_plane=near_plane,
        far_plane=far_plane,
        radius_clip=radius_clip,
        eps2d=eps2d,
        sh_degree=sh_degree,
        packed=packed,
        tile_size=tile_size,
        backgrounds=backgrounds,
        render_mode=cast(Any, render_mode),  # validated by `rasterize`
        absgrad=absgrad,
        rasterize_mode=cast(Any, rasterize_mode),
    )
    meta["backend"] = "gsplat"
    return render, alpha, meta
