"""Appearance-conditioned background ("sky"): what a pixel shows where no Gaussian covers it, as a function of the
image's appearance latent and the ray direction.

Tourist photos are mostly sky above a building, and the sky is the part of a photo that changes most between
photos (sun, overcast, dusk, clouds) while carrying no geometry. Splatfacto composites a constant (random while
training) colour behind the Gaussians, so the Gaussians must paint every photo's sky themselves: they grow into the
sky at whatever depth fits the training views, carry one photo's clouds into another's, and a new view shows them
as blobs. Here the background is a smooth function at infinity whose colour follows the latent:

    bg(z, d) = clamp( sum_k c_k(z) Y_k(d) + 0.5, 0, 1 )        c(z) = MLP(z) in R^{K x 3}, K = (degree + 1)^2

- ``Y_k``: real spherical harmonics of the world-space ray direction up to ``sh_degree`` (low degree: a sky is a
  gradient, not a texture; a cloud pattern that differs in every photo is not predictable from the left half of a
  test photo, so a smooth mean is the best a model can do there).
- ``c(z)``: zero at initialisation (a grey background), learnt with the latent: under the NeRF-W protocol the latent
  fitted on a test photo's left half sets its sky's colour on the right half too.
- ``alpha_penalty`` (optional): where the background alone already reproduces the photo, Gaussians covering those
  pixels pay ``alpha_penalty * mean(alpha)`` there, so the sky stays background instead of being painted over.

Pure functions: :func:`pixel_directions` (camera -> world ray directions), :func:`background_alpha_penalty`,
:func:`background` (what shows behind the Gaussians of a render: the sky, or splatfacto's colour), :func:`composite`
(a render over it: the student's and the EMA teacher's alike).
"""

from dataclasses import dataclass
from typing import Literal

import torch
import torch.nn.functional as F
from jaxtyping import Float
from nerfstudio.utils.rich_utils import CONSOLE
from torch import Tensor, nn

from willags_ns.appearance.latent_mlp import latent_mlp
from willags_ns.data.sfm_tracks import open_background_map, support_at
from willags_ns.render.sh import homogeneous_monomials, monomial_to_sh, num_sh_bases
from willags_ns.tensor_constants import as_dtype, constant


@dataclass
class SkyConfig:
    """The appearance-conditioned background."""

    enabled: bool = True
    """Composite the Gaussians over bg(z, ray direction) instead of splatfacto's constant (random while training)
    colour. With region "open" on a scene without SfM keypoints there is no skyline to train it above, and no sky
    is built (`sky_for_scene`)."""
    sh_degree: int = 3
    """Degree of the real SH basis of the ray direction (0..4; (degree + 1)**2 coefficients per colour channel)."""
    hidden: int = 64
    """Width of the hidden layer of z -> SH coefficients."""
    alpha_penalty: float = 0.0
    """Weight of the mean accumulated alpha over pixels that the background alone reproduces (0 = off)."""
    region: Literal["everywhere", "open"] = "open"
    """Where the sky is composited while training. "everywhere": behind every pixel. "open": only above the scene's
    skyline in each training photo (cells above the first SfM keypoint of each column, data/sfm_tracks
    .open_background_map; COLMAP scenes), splatfacto's random background elsewhere, so the Gaussians of the scene
    stay opaque: with the sky everywhere and no alpha penalty, Gaussians of a near background (the fox scenes' wall)
    turn transparent and the sky paints it (docs/inspect.md). Rendering and the NeRF-W protocol use the sky behind
    every pixel."""
    alpha_tol: float = 0.03
    """A pixel counts as reproduced by the background when |photo - bg|, averaged over the colour channels and a
    5x5 window, is below this."""


class SkyModel(nn.Module):
    """z [D] -> SH coefficients [K, 3] of the background; (z, directions [..., 3]) -> RGB [..., 3]."""

    def __init__(self, latent_dim: int, cfg: SkyConfig):
        super().__init__()
        if not 0 <= cfg.sh_degree <= 4:
            raise ValueError(f"sky.sh_degree must be in 0..4, got {cfg.sh_degree}")
        if latent_dim <= 0:
            raise ValueError(f"latent_dim must be > 0, got {latent_dim}")
        self.sh_degree = cfg.sh_degree
        self.num_coeffs = num_sh_bases(cfg.sh_degree)
        self.mlp = nn.Sequential(
            nn.Linear(latent_dim, cfg.hidden), nn.ReLU(), nn.Linear(cfg.hidden, self.num_coeffs * 3)
        )
        # grey at initialisation, and no direction dependence until the data asks for it
        nn.init.zeros_(self.mlp[-1].weight)
        nn.init.zeros_(self.mlp[-1].bias)
        # Y(d) = monomials(d) @ P on the unit sphere: the per-pixel work is a handful of tensor operations whatever
        # the degree (render/sh.py); not saved in checkpoints (a constant of the degree)
        self.register_buffer("monomial_to_sh", monomial_to_sh(cfg.sh_degree).float().contiguous(), persistent=False)

    def coefficients(self, z: Float[Tensor, " D"]) -> Float[Tensor, "K 3"]:
        return latent_mlp(self.mlp, z).view(self.num_coeffs, 3)

    def forward(self, z: Float[Tensor, " D"], dirs: Float[Tensor, "*B 3"]) -> Float[Tensor, "*B 3"]:
        """Background colour in [0, 1] along unit world directions ``dirs``: sum_k c_k(z) Y_k(d) + 0.5, clamped,
        evaluated as monomials(d) @ (P c(z)) (the same function on the unit sphere)."""
        coeffs = as_dtype(self.monomial_to_sh, dirs.dtype) @ as_dtype(self.coefficients(z), dirs.dtype)  # [K, 3]
        return (homogeneous_monomials(self.sh_degree, dirs) @ coeffs + constant(0.5, coeffs)).clamp(0.0, 1.0)


def pixel_directions(
    c2w: Float[Tensor, "3 4"], K: Float[Tensor, "3 3"], width: int, height: int
) -> Float[Tensor, "H W 3"]:
    """Unit world-space directions of the rays through the pixel centres of a nerfstudio camera (OpenGL axes:
    +x right, +y up, -z forward; the same rays as ``Cameras.generate_rays``): x_c R[:, 0] + y_c R[:, 1] - R[:, 2],
    normalised, with x_c = (u + 0.5 - cx) / fx across and y_c = -(v + 0.5 - cy) / fy down. Built from a row and a
    column by broadcasting: a dozen tensor operations per frame, whatever the size. `K` has c2w's dtype."""
    # (i + 0.5 - c) / f for x (row 0) and y (row 1) in one pass over max(W, H) indices; -(a / b) is a / -b exactly
    i = torch.arange(max(width, height), device=c2w.device, dtype=c2w.dtype)
    xy = (i + (constant(0.5, K) - K[:2, 2:])) / K.diagonal()[:2, None]  # [2, max(W, H)]
    x, y = xy[0, :width, None], -xy[1, :height].view(height, 1, 1)  # [W, 1], [H, 1, 1]
    R = c2w[:3, :3]
    d = x * R[:, 0] + (y * R[:, 1] - R[:, 2])  # [W, 3] + [H, 1, 3] -> [H, W, 3]
    return d / d.norm(dim=-1, keepdim=True)


def background_alpha_penalty(
    alpha: Float[Tensor, "H W 1"],
    gt: Float[Tensor, "H W 3"],
    background: Float[Tensor, "H W 3"],
    tol: float,
    mask: Float[Tensor, "H W"] | None = None,
) -> Tensor | None:
    """Mean alpha over the pixels the background alone reproduces (|gt - bg| averaged over channels and a 5x5
    window below ``tol``; within ``mask`` when given), or None when there are none (no 0/0)."""
    err = (gt - background.detach()).abs().mean(-1)[None, None]  # [1, 1, H, W]
    err = F.avg_pool2d(err, 5, stride=1, padding=2, count_include_pad=False)[0, 0]
    explained = err < tol
    if mask is not None:
        explained = explained & (mask > 0.5)
    if not bool(explained.any()):
        return None
    return alpha[..., 0][explained].mean()


class OpenRegions:
    """Per training image, where the learnt sky shows while training with ``region="open"``: the cells above the
    scene's skyline (data/sfm_tracks.open_background_map of the image's SfM keypoints), built once per image."""

    def __init__(self, observations: list | None):
        self.observations = observations
        self.cache: dict[int, Tensor] = {}
        """Per training image, its open cells [rows, cols] as float (1 = open)."""

    def at(self, idx: int, height: int, width: int, device) -> Tensor | None:
        """[H, W] bool (True = open) for training image `idx`, or None when the scene has no keypoints for it."""
        obs = self.observations
        if obs is None or not 0 <= idx < len(obs):
            return None
        if idx not in self.cache:  # as float: what support_at reads, converted once
            self.cache[idx] = open_background_map(obs[idx], width, height).float().to(device)
        return support_at(self.cache[idx], height, width)


def sky_for_scene(cfg: SkyConfig, observations: list | None) -> tuple[bool, OpenRegions | None]:
    """(whether the model builds a sky, where it shows while training: :class:`OpenRegions` of the scene's SfM
    keypoints with region "open", None for behind every pixel). A scene without keypoints has no skyline, and a sky
    trained nowhere would show everywhere: with region "open" there it builds none (said once). The config is
    read, never written: the same config.yml rebuilds the same model on the same scene."""
    if not cfg.enabled:
        return False, None
    if cfg.region != "open":
        return True, None
    if observations is None:
        CONSOLE.log("willags: sky.region 'open' needs SfM keypoints (a COLMAP scene); no sky is built here")
        return False, None
    return True, OpenRegions(observations)


def composite_background(
    sky: Float[Tensor, "1 H W 3"], fallback: Float[Tensor, " 3"], open_region: Tensor | None
) -> Float[Tensor, "1 H W 3"]:
    """The sky where `open_region` [H, W] is True, the fallback colour elsewhere (the sky alone when None)."""
    if open_region is None:
        return sky
    return torch.where(open_region[..., None], sky, fallback.to(sky))  # [H, W, 1] broadcast over sky's [1, H, W, 3]


def background(
    sky: SkyModel | None,
    z: Float[Tensor, " D"] | None,
    dirs: Float[Tensor, "H W 3"] | None,
    fallback: Float[Tensor, " 3"],
    open_regions: OpenRegions | None = None,
    image_idx: int = -1,
) -> Tensor:
    """What shows behind the Gaussians: the `sky` under latent z along the pixel directions `dirs` as [1, H, W, 3]
    (with `open_regions`, training with region "open": only in training image `image_idx`'s open cells, `fallback`
    elsewhere), or `fallback`, splatfacto's background colour [3] (random while training), without a sky."""
    if sky is None or z is None or dirs is None:
        return fallback
    bg = sky(z, dirs)[None]
    if open_regions is not None:
        H, W = dirs.shape[:2]
        bg = composite_background(bg, fallback, open_regions.at(image_idx, H, W, bg.device))
    return bg


def composite(rgb: Tensor, alpha: Tensor, background: Tensor) -> Tensor:
    """What a photo shows: rendered colours `rgb` [..., 3] over `background` ([3], or per pixel) where the
    accumulated `alpha` [..., 1] is below 1, clamped to [0, 1]."""
    return torch.clamp(rgb + (constant(1.0, alpha) - alpha) * background, 0.0, 1.0)
