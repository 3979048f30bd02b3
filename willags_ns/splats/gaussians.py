"""The 3DGS side of the model: the initial Gaussians, gsplat's densification strategy, and the rasteriser call.

The Gaussians' tensors live in the model's `gauss_params` (one optimiser group each); this module builds them and
says how they are rendered. Colours come from the appearance (appearance/color_path.py) or, for appearance='sh',
from splatfacto's SH, which then sit in gauss_params too.
"""

import torch
from nerfstudio.models.splatfacto import RGB2SH, num_sh_bases, random_quat_tensor
from nerfstudio.utils.rich_utils import CONSOLE
from torch import Tensor
from torch.nn import Parameter

from willags_ns.render import rasterize
from willags_ns.splats.mcmc import initial_opacity_and_scale, mcmc_strategy


def initial_points(cfg, seed_points) -> tuple[Tensor, Tensor | None]:
    """(means [N, 3], seed colours [N, 3] in [0, 1] or None): the dataparser's points, or cfg.num_random random
    points in a cube of side cfg.random_scale."""
    if seed_points is not None and not cfg.random_init:
        means = seed_points[0].float().clone()
        seed_rgb = seed_points[1].float() / 255.0 if seed_points[1].shape[0] > 0 else None
    else:
        means = (torch.rand((cfg.num_random, 3)) - 0.5) * cfg.random_scale
        seed_rgb = None
    if means.shape[0] < 4:
        raise ValueError(
            f"willags needs at least 4 initial points to initialise Gaussians, got {means.shape[0]} "
            "(check the dataparser's seed points: sparse_pc.ply / points3D.bin)"
        )
    return means, seed_rgb


def initial_gauss_params(
    cfg, means: Tensor, seed_rgb: Tensor | None, avg_dist: Tensor, layout, mcmc: bool = False
) -> dict[str, Parameter]:
    """The Gaussians' parameters at initialisation (splatfacto's rule: isotropic scales from the mean distance
    `avg_dist` [N, 1] to the 3 nearest points, random rotations, opacity 0.1), and the colour parameters `layout`
    names (`sh`, `intrinsic_dim` and `initial_features(n, seed_rgb)`: appearance/color_model.GaussianLayout, which
    the model takes from its colour model, appearance/networks.gaussian_layout)."""
    n = means.shape[0]
    opacity, scale = initial_opacity_and_scale(cfg, avg_dist, mcmc)  # splatfacto's, or MCMC's (cfg.mcmc)
    params = {
        "means": Parameter(means),
        "scales": Parameter(torch.log(scale.repeat(1, 3))),
        "quats": Parameter(random_quat_tensor(n)),
        "opacities": Parameter(torch.logit(opacity * torch.ones(n, 1))),
    }
    if layout.sh:  # 3DGS colours (a colour model's base colour, or plain 3DGS)
        dim_sh = num_sh_bases(cfg.sh_degree)
        shs = torch.zeros((n, dim_sh, 3))
        if seed_rgb is not None:
            shs[:, 0, :] = (
                RGB2SH(seed_rgb) if (cfg.sh_degree > 0 or cfg.appearance != "sh") else torch.logit(seed_rgb, eps=1e-10)
            )
        else:
            shs[:, 0, :] = torch.rand(n, 3)
        params["features_dc"] = Parameter(shs[:, 0, :].contiguous())
        params["features_rest"] = Parameter(shs[:, 1:, :].contiguous())
    f_s = layout.initial_features(n, seed_rgb)
    if f_s is not None:
        params["features"] = Parameter(f_s)
    return params


def densification_strategy(cfg, num_train: int, mcmc: bool = False):
    """gsplat's DefaultStrategy with splatfacto's settings and a budget of cfg.splitclone_cap Gaussians
    (splats/splitclone.py; cfg: the model config), or with `mcmc` the MCMC densification of splats/mcmc.py over the
    same refinement window."""
    from willags_ns.splats.splitclone import BudgetedDefaultStrategy

    if mcmc:
        return mcmc_strategy(cfg)

    return BudgetedDefaultStrategy(
        cap_max=cfg.splitclone_cap,
        prune_opa=cfg.cull_alpha_thresh,
        grow_grad2d=cfg.densify_grad_thresh,
        grow_scale3d=cfg.densify_size_thresh,
        grow_scale2d=cfg.split_screen_size,
        prune_scale3d=cfg.cull_scale_thresh,
        prune_scale2d=cfg.cull_screen_size,
        refine_scale2d_stop_iter=cfg.stop_screen_size_at,
        refine_start_iter=cfg.warmup_length,
        refine_stop_iter=cfg.stop_split_at,
        reset_every=cfg.reset_alpha_every * cfg.refine_every,
        refine_every=cfg.refine_every,
        pause_refine_after_reset=num_train + cfg.refine_every,
        absgrad=cfg.use_absgrad,
        revised_opacity=False,
        verbose=False,
    )


def opacity_reset_period(strategy) -> int:
    """Steps between the strategy's opacity resets (0: it never resets them, as MCMC)."""
    return int(getattr(strategy, "reset_every", 0) or 0)


def uses_gsplat(backend: str, means: Tensor) -> bool:
    return backend == "gsplat" or (backend == "auto" and means.is_cuda)


def strategy_absgrad(strategy, cfg, means: Tensor) -> bool:
    """Whether this rasterisation keeps |grad| for densification (cfg.use_absgrad), with gsplat's `strategy` set to
        agree. Only gsplat's CUDA backward writes |grad|: a strategy that expects it on the torch backend would read a
        gradient that was never written, so it densifies on plain gradients there (said once per switch on a GPU, where
    gsplat was an option; on the CPU it is the only one)."""
    absgrad = cfg.use_absgrad and uses_gsplat(cfg.backend, means)
    if strategy.absgrad != absgrad:
        if not absgrad and cfg.use_absgrad and means.is_cuda:  # on the CPU plain gradients are the only kind
            CONSOLE.log(
                "willags: use_absgrad needs gsplat's CUDA backward; densifying on plain gradients "
                "(--pipeline.model.backend auto uses gsplat on a GPU)"
            )
        strategy.absgrad = absgrad
    return absgrad


def rasterize_gaussians(
    cfg, means, quats, scales, opacities, colors, viewmat, K, W: int, H: int, render_mode: str, sh_degree, absgrad: bool
):
    """`willags_ns.render.rasterize` of the Gaussians' raw parameters (log scales, logit opacities) with the model's
    settings (cfg: backend, rasterize_mode); returns (render [C, H, W, ch], alpha [C, H, W, 1], info)."""
    return rasterize(
        means=means,
        quats=quats,
        scales=torch.exp(scales),
        opacities=torch.sigmoid(opacities).squeeze(-1),
        colors=colors,
        viewmats=viewmat,
        Ks=K,
        width=W,
        height=H,
        packed=False,
        near_plane=0.01,
        far_plane=1e10,
        render_mode=render_mode,
        sh_degree=sh_degree,
        absgrad=absgrad,
        rasterize_mode=cfg.rasterize_mode,
        backend=cfg.backend,
    )


def active_sh_degree(cfg, step: int) -> int:
    """SH degree in use at `step`: splatfacto's schedule, one more degree every cfg.sh_degree_interval steps up to
    cfg.sh_degree (the 3DGS colours of appearance='sh' and the base colour of color_mode='modulated' alike)."""
    return min(step // max(1, cfg.sh_degree_interval), cfg.sh_degree)


def sh_coeffs(gp) -> Tensor | None:
    """SH coefficients [N, K, 3] of the Gaussians in `gp` (gauss_params or a cropped view), None without them."""
    if "features_dc" not in gp:
        return None
    return torch.cat((gp["features_dc"][:, None, :], gp["features_rest"]), dim=1)


def sh_colors(cfg, gp, step: int) -> tuple[Tensor, int | None]:
    """appearance='sh' (plain 3DGS): (SH coefficients [N, K, 3], the active degree by splatfacto's schedule), or
    with sh_degree=0 (RGB [N, 3] through a sigmoid, None) as splatfacto renders them."""
    colors = sh_coeffs(gp)
    assert colors is not None
    if cfg.sh_degree > 0:
        return colors, active_sh_degree(cfg, step)
    return torch.sigmoid(colors).squeeze(1), None
