"""WillagsModel: splatfacto's Gaussians with a latent-conditioned appearance field, an EMA teacher and a
perceptual transient mask (WilLaGS). Runs on any device; rasterises through `willags_ns.render.rasterize`.

Per training step (the pipeline hands the model the training image first):

    image --VAE encoder--> mu, logvar --reparameterise--> z              [D]
    z --hypernetwork--> tri-planes [3, Cp, R, R]; means --bounds--> [-1,1]^3 --bilinear--> MLP --> f_d [N, 32]
    T_color(f_d, f_s, view dir) --> colours [N, 3] --rasterize--> render
    EMA teacher (same networks, EMA weights) --> pseudo-GT render (no grad)
    VGG16(GT) vs VGG16(teacher) --> D(p); static mask = D < 0.85 (after a warm-up)
    loss = 0.8 L1 + 0.2 D-SSIM on static pixels + 0.01 (L1 recon + beta KL)

The class subclasses SplatfactoModel because nerfstudio's exporter and viewer check
`isinstance(model, SplatfactoModel)`; it reuses splatfacto's densification (gsplat's DefaultStrategy), resolution
schedule and metrics, and replaces what hard-codes CUDA (`populate_modules`, `get_outputs`) or downloads weights
(LPIPS). `appearance="sh"` turns it into plain 3DGS (splatfacto's SH colours, no appearance model, no mask): the
CPU stand-in for splatfacto in benchmarks (method `willags-3dgs`).
"""

import math
import os
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal, Union, cast

import torch
import torch.nn.functional as F
from nerfstudio.cameras.cameras import Cameras
from nerfstudio.data.scene_box import OrientedBox
from nerfstudio.engine.callbacks import TrainingCallback, TrainingCallbackAttributes, TrainingCallbackLocation
from nerfstudio.model_components.lib_bilagrid import color_correct
from nerfstudio.models.splatfacto import (
    RGB2SH,
    SplatfactoModel,
    SplatfactoModelConfig,
    num_sh_bases,
    random_quat_tensor,
)
from nerfstudio.utils.rich_utils import CONSOLE
from torch import Tensor, nn
from torch.nn import Parameter

from willags_ns.appearance.decoder import ColorDecoder, ColorDecoderConfig, sh_basis
from willags_ns.appearance.modulation import ColorModulation, ColorModulationConfig, local_penalty
from willags_ns.appearance.sky import SkyConfig, SkyModel, background_alpha_penalty, pixel_directions
from willags_ns.appearance.triplane import TriplaneConfig, TriplaneHyperField, normalize_points, robust_bounds
from willags_ns.appearance.vae import AppearanceVAE, VAEConfig, reparameterize, vae_loss
from willags_ns.appearance_spec import APPEARANCE_ENV, checked_latent, latent_from_env, mean_latent
from willags_ns.data.sfm_tracks import SFM_OBSERVATIONS_KEY
from willags_ns.losses import reconstruction_loss
from willags_ns.render import rasterize
from willags_ns.render.sh import spherical_harmonics
from willags_ns.static_support import StaticSupportConfig, apply_support, support_map
from willags_ns.teacher import TeacherConfig, ema_update_, make_teacher
from willags_ns.transient import (
    PerceptualFeatures,
    PerceptualMaskConfig,
    image_distance,
    mask_active,
    mask_threshold,
    transient_mask,
)
from willags_ns.viewer import AppearanceControls


def viewmat_from_c2w(c2w: Tensor) -> Tensor:
    """nerfstudio camera-to-world [C, 3, 4] (OpenGL: -z forward, +y up) -> gsplat world-to-camera [C, 4, 4].

    Same maths as splatfacto's `get_viewmat`, without its torch.compile (15-20 s on the first CPU call).
    """
    # flip the y and z axes (columns 1, 2); negation on the device, not a constant copied from the host (a blocking
    # copy that drains the GPU's queue once per step)
    R = torch.cat((c2w[:, :3, :1], -c2w[:, :3, 1:3]), dim=-1)
    T = c2w[:, :3, 3:4]
    R_inv = R.transpose(1, 2)
    viewmat = torch.zeros(c2w.shape[0], 4, 4, device=c2w.device, dtype=c2w.dtype)
    viewmat[:, 3, 3] = 1.0
    viewmat[:, :3, :3] = R_inv
    viewmat[:, :3, 3:4] = -torch.bmm(R_inv, T)
    return viewmat


RENDER_SH_SAMPLES = 64
"""View directions over which the decoder is fitted by SH when rendering with a fixed appearance."""


def image_as_float(image: Tensor) -> Tensor:
    """A datamanager's cached image (uint8 or float, [H, W, C]) as float in [0, 1]."""
    return image.float() / 255.0 if image.dtype == torch.uint8 else image.float()


def _versions(tensors: list[Tensor]) -> tuple:
    """(storage pointer, version counter) of each tensor: changes when a tensor is replaced or edited in place
    (optimiser steps, load_state_dict, buffer writes), never otherwise."""
    return tuple((t.data_ptr(), t._version) for t in tensors)


def fibonacci_directions(k: int, device=None) -> Tensor:
    """k unit vectors [k, 3] spread evenly over the sphere (Fibonacci lattice)."""
    i = torch.arange(k, device=device, dtype=torch.float32) + 0.5
    phi, cos_t = math.pi * (1 + 5**0.5) * i, 1 - 2 * i / k
    sin_t = (1 - cos_t**2).clamp_min(0).sqrt()
    return torch.stack([sin_t * phi.cos(), sin_t * phi.sin(), cos_t], -1)


def _lpips_weights_cached() -> bool:
    """torchmetrics' LPIPS builds torchvision's AlexNet with ImageNet weights: only try when they are on disk."""
    hub = Path(torch.hub.get_dir()) / "checkpoints"
    return any(hub.glob("alexnet-owt-*.pth"))


@dataclass
class WillagsModelConfig(SplatfactoModelConfig):
    """WilLaGS: splatfacto + beta-VAE latent + tri-plane hypernetwork colour field + EMA teacher + perceptual mask."""

    _target: type = field(default_factory=lambda: WillagsModel)
    appearance: Literal["willags", "sh"] = "willags"
    """'willags': the latent-conditioned appearance field (the method). 'sh': plain 3DGS colours (splatfacto's
    spherical harmonics), no appearance model and no mask: the baseline configuration (method willags-3dgs)."""
    color_mode: Literal["modulated", "decoder"] = "modulated"
    """How the appearance makes a Gaussian's colour. 'modulated' (default, measured best: docs/benchmarks.md): the
    Gaussian's own 3DGS SH colour transformed by the latent (a global colour transform of z plus an optional,
    penalised per-Gaussian residual fed by f_s, z and the tri-plane feature; appearance/modulation.py). 'decoder':
    the paper's T_color MLP regresses the colour from (f_d, f_s, view direction) (method willags-paper)."""
    modulation: ColorModulationConfig = field(default_factory=ColorModulationConfig)
    """The colour transform of color_mode='modulated' (global transform, local residual and its penalty)."""
    sky: SkyConfig = field(default_factory=SkyConfig)
    """Appearance-conditioned background bg(z, ray direction) behind the Gaussians (appearance/sky.py)."""
    use_vae: bool = True
    """Appearance latent from the beta-VAE encoder. Off: a per-image embedding table (NeRF-W / Splatfacto-W style)."""
    use_field: bool = True
    """Tri-plane hypernetwork field f_d(z, x). Off: the latent z is concatenated with f_s (no spatial field)."""
    use_mask: bool = True
    """Perceptual transient mask from the EMA teacher. Off: every pixel is supervised."""
    intrinsic_dim: int = 32
    """Size of the learnable per-Gaussian intrinsic feature f_s."""
    vae: VAEConfig = field(default_factory=VAEConfig)
    """beta-VAE appearance encoder/decoder (latent size, input size, beta)."""
    triplane: TriplaneConfig = field(default_factory=TriplaneConfig)
    """Tri-plane hypernetwork field (plane resolution/channels, MLP sizes). Its latent_dim follows vae.latent_dim."""
    decoder: ColorDecoderConfig = field(default_factory=ColorDecoderConfig)
    """Colour decoder T_color(f_d, f_s, view direction)."""
    teacher: TeacherConfig = field(default_factory=TeacherConfig)
    """EMA teacher (decay tau) that renders the pseudo ground truth for the mask."""
    mask: PerceptualMaskConfig = field(default_factory=PerceptualMaskConfig)
    """Perceptual transient mask (VGG16 weights source, threshold 0.85, warm-up)."""
    static_support: StaticSupportConfig = field(default_factory=StaticSupportConfig)
    """The mask's safeguard: pixels around observations of SfM points seen by many training images are static and
    never masked (willags_ns/static_support.py; COLMAP scenes, where the tracks exist)."""
    mask_every: int = 1
    """Recompute an image's mask on every k-th step (teacher render + VGG); other steps reuse that image's last
    mask. 1 = the paper (every step). Larger values trade mask freshness for speed."""
    fuse_teacher_render: bool = True
    """Render the teacher's colours as 3 extra channels of the student's rasterisation (same Gaussians, same
    camera) instead of a second rasterisation. Identical pseudo-GT and identical student gradients (the teacher
    channels are detached, so their share of every geometry gradient is zero); saves the teacher's projection,
    sorting and compositing (measured in docs/gpu_notes.md)."""
    max_masked_fraction: float = 0.5
    """If the mask would drop more than this fraction of an image, the teacher is not trustworthy there (still
    training, or an appearance it cannot explain): that image is supervised everywhere instead (logged as
    mask_rejected). Occluders in photo collections cover far less than half an image."""
    lambda_vae: float = 0.01
    """Weight of L_VAE = L1 recon + beta * KL in the total loss."""
    embedding_init_std: float = 0.01
    """Init std of the per-image embedding table (use_vae=False only)."""
    backend: Literal["auto", "gsplat", "torch"] = "auto"
    """Rasteriser backend: gsplat (CUDA), our pure-torch rasteriser (any device), or auto (gsplat on CUDA)."""
    log_images_every: int = 500
    """Write training images (render, teacher render, D map, mask, VAE reconstruction) to tensorboard every N
    steps (0 = never)."""
    render_sh_degree: int = 3
    """Rendering with a chosen appearance and no gradient (viewer, ns-render, eval images during training; not
    training, not the NeRF-W protocol, whose latent arrives in the camera's metadata): once per appearance change the
    colour decoder is projected by least squares onto real SH of this degree per Gaussian (over RENDER_SH_SAMPLES
    view directions), and every frame the rasteriser evaluates SH like 3DGS: the decoder MLP no longer runs per
    frame. The bake happens on the second frame with the same appearance and Gaussians (a viewer open during
    training, where the Gaussians change every step, keeps the exact decoder). -1 = the decoder every frame."""
    export_view_samples: int = 26
    """Number of view directions averaged when baking the view-dependent colour into a PLY (ns-export)."""
    auto_config: bool = False
    """Before the model is built, inspect the scene (willags-inspect) and switch off what it does not need: the
    appearance latent, the transient mask and its teacher, the tri-plane field; the latent size follows the image
    count (willags_ns/autoconfig.py). The choice is printed, logged to tensorboard and written to auto_config.json;
    config.yml is rewritten with the resolved switches. Method `willags-auto` turns it on."""


class AppearanceNetworks(nn.Module):
    """Every network the EMA teacher copies: VAE (or embedding table), tri-plane field, colour decoder.

    Per-Gaussian tensors (means, f_s) live in the model's gauss_params, so densification never touches this.
    """

    def __init__(self, cfg: WillagsModelConfig, num_train: int):
        super().__init__()
        d = cfg.vae.latent_dim
        self.latent_dim = d
        self.color_mode = cfg.color_mode
        if cfg.color_mode == "modulated" and cfg.use_field and not cfg.modulation.local:
            raise ValueError(
                "willags: use_field=True with color_mode='modulated' needs modulation.local=True (the tri-plane "
                "feature feeds the per-Gaussian residual); set --pipeline.model.use-field False or "
                "--pipeline.model.modulation.local True"
            )
        self.vae = (
            AppearanceVAE(latent_dim=d, image_size=cfg.vae.image_size, channels=tuple(cfg.vae.channels))
            if cfg.use_vae
            else None
        )
        self.embeddings = None
        if not cfg.use_vae:
            self.embeddings = nn.Embedding(max(num_train, 1), d)
            nn.init.normal_(self.embeddings.weight, std=cfg.embedding_init_std)
        tp = cfg.triplane
        self.field = (
            TriplaneHyperField(
                latent_dim=d,
                resolution=tp.resolution,
                channels=tp.channels,
                hyper_hidden=tuple(tp.hyper_hidden),
                feature_dim=tp.feature_dim,
                mlp_hidden=tp.mlp_hidden,
            )
            if cfg.use_field
            else None
        )
        self.sky = SkyModel(d, cfg.sky) if cfg.sky.enabled else None
        self.color: ColorDecoder | None = None
        self.modulation: ColorModulation | None = None
        if cfg.color_mode == "decoder":
            self.color = ColorDecoder(
                dynamic_dim=tp.feature_dim if cfg.use_field else 0,
                intrinsic_dim=cfg.intrinsic_dim + (0 if cfg.use_field else d),
                hidden=cfg.decoder.hidden,
                dir_sh_degree=cfg.decoder.dir_sh_degree,
            )
        else:
            self.modulation = ColorModulation(
                latent_dim=d,
                intrinsic_dim=cfg.intrinsic_dim if cfg.modulation.local else 0,
                dynamic_dim=tp.feature_dim if cfg.use_field else 0,
                cfg=cfg.modulation,
            )

    def latent_stats(self, image_chw: Tensor | None, image_idx: int | None) -> tuple[Tensor, Tensor | None]:
        """(mu [D], logvar [D] or None) of one training image: the VAE posterior, or the embedding row."""
        if self.vae is not None:
            assert image_chw is not None
            mu, logvar = self.vae.encode(image_chw[None])
            return mu[0], logvar[0]
        assert self.embeddings is not None and image_idx is not None
        # the row by a Python index: an index tensor built on the device is a blocking host -> device copy per step;
        # the same row and the same (dense) gradient as the module's lookup
        n = self.embeddings.num_embeddings
        if not 0 <= image_idx < n:
            raise IndexError(f"willags: training image index {image_idx} outside the appearance table's {n} rows")
        return self.embeddings.weight[image_idx], None

    def dynamic_features(self, z: Tensor, xyz_norm: Tensor) -> Tensor | None:
        """f_d [N, F] for latent z [D] at normalised means [N, 3]; None without the field."""
        if self.field is None:
            return None
        return self.field(z, xyz_norm)

    def colors(
        self,
        z: Tensor,
        f_d: Tensor | None,
        f_s: Tensor | None,
        dirs: Tensor,
        sh: Tensor | None = None,
        sh_degree: int = 0,
        residual: Tensor | None = None,
        base: Tensor | None = None,
    ) -> Tensor:
        """Per-Gaussian RGB [N, 3] from f_d [N, F] (or None), f_s [N, Fs] (or None), view directions [N, 3] and,
        for color_mode='modulated', the Gaussians' SH coefficients sh [N, K, 3] evaluated up to sh_degree
        (``residual``: a precomputed local residual, see ColorModulation.forward; ``base``: the SH colours
        already evaluated, which then replace sh)."""
        if self.modulation is not None:
            if base is None:
                if sh is None:
                    raise ValueError("color_mode='modulated' needs the Gaussians' SH coefficients (sh=...)")
                base = (spherical_harmonics(sh_degree, dirs, sh) + 0.5).clamp_min(0.0)  # gsplat's SH colour
            # clamped like gsplat clamps SH colours, so the exact render and the SH bake agree
            return self.modulation(z, base, f_s, f_d, residual=residual).clamp_min(0.0)
        assert self.color is not None and f_s is not None
        if self.field is None:
            f_s = torch.cat([f_s, z.expand(f_s.shape[0], -1)], dim=-1)  # the "w/o field" ablation
        return self.color(f_d, f_s, dirs)


class WillagsModel(SplatfactoModel):
    """WilLaGS on top of splatfacto. See the module docstring for the per-step data flow."""

    config: WillagsModelConfig
    # buffers registered in populate_modules (declared for type checkers: nn.Module.__getattr__ is untyped)
    train_latents: Tensor
    train_latent_seen: Tensor
    bounds_lo: Tensor
    bounds_hi: Tensor

    # ------------------------------------------------------------------ set-up
    def populate_modules(self):
        cfg = self.config
        if self.seed_points is not None and not cfg.random_init:
            means = self.seed_points[0].float().clone()
            seed_rgb = self.seed_points[1].float() / 255.0 if self.seed_points[1].shape[0] > 0 else None
        else:
            means = (torch.rand((cfg.num_random, 3)) - 0.5) * cfg.random_scale
            seed_rgb = None
        if means.shape[0] < 4:
            raise ValueError(
                f"willags needs at least 4 initial points to initialise Gaussians, got {means.shape[0]} "
                "(check the dataparser's seed points: sparse_pc.ply / points3D.bin)"
            )
        distances, _ = self.k_nearest_sklearn(means, 3)
        avg_dist = torch.from_numpy(distances).mean(dim=-1, keepdim=True).clamp_min(1e-7)
        n = means.shape[0]
        params = {
            "means": Parameter(means),
            "scales": Parameter(torch.log(avg_dist.repeat(1, 3))),
            "quats": Parameter(random_quat_tensor(n)),
            "opacities": Parameter(torch.logit(0.1 * torch.ones(n, 1))),
        }
        if cfg.appearance == "sh" or cfg.color_mode == "modulated":  # 3DGS colours (modulated: the base colour)
            dim_sh = num_sh_bases(cfg.sh_degree)
            shs = torch.zeros((n, dim_sh, 3))
            if seed_rgb is not None:
                shs[:, 0, :] = (
                    RGB2SH(seed_rgb)
                    if (cfg.sh_degree > 0 or cfg.appearance != "sh")
                    else torch.logit(seed_rgb, eps=1e-10)
                )
            else:
                shs[:, 0, :] = torch.rand(n, 3)
            params["features_dc"] = Parameter(shs[:, 0, :].contiguous())
            params["features_rest"] = Parameter(shs[:, 1:, :].contiguous())
            if cfg.appearance == "willags" and cfg.modulation.local and cfg.intrinsic_dim > 0:
                params["features"] = Parameter(0.1 * torch.randn(n, cfg.intrinsic_dim))  # f_s of the residual
        else:
            # f_s starts small and random; its first 3 entries carry the seed colour (centred), which gives the
            # colour decoder an easy first solution without changing the method.
            f_s = 0.1 * torch.randn(n, cfg.intrinsic_dim)
            if seed_rgb is not None and cfg.intrinsic_dim >= 3:
                f_s[:, :3] = seed_rgb * 2.0 - 1.0
            params["features"] = Parameter(f_s)
        self.gauss_params = nn.ParameterDict(params)

        self.camera_optimizer = cfg.camera_optimizer.setup(num_cameras=self.num_train_data, device="cpu")
        from pytorch_msssim import SSIM
        from torchmetrics.image import PeakSignalNoiseRatio

        self.psnr = PeakSignalNoiseRatio(data_range=1.0)
        self.ssim = SSIM(data_range=1.0, size_average=True, channel=3)
        self._lpips = None  # built lazily (needs AlexNet ImageNet weights on disk)
        self._lpips_status: str | None = None
        self.step = 0
        self.crop_box: OrientedBox | None = None
        self.background_color = torch.tensor([0.1490, 0.1647, 0.2157])
        if cfg.background_color != "random":
            from nerfstudio.utils.colors import get_color

            self.background_color = get_color(cfg.background_color)
        if cfg.use_bilateral_grid:
            raise ValueError("willags: use_bilateral_grid is not supported (the appearance field models the ISP)")

        from gsplat.strategy import DefaultStrategy

        self.strategy = DefaultStrategy(
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
            pause_refine_after_reset=self.num_train_data + cfg.refine_every,
            absgrad=cfg.use_absgrad,
            revised_opacity=False,
            verbose=False,
        )
        self.strategy_state = self.strategy.initialize_state(scene_scale=1.0)

        # --- the appearance model (absent for appearance="sh")
        self.appearance_nets: AppearanceNetworks | None = None
        self.teacher: AppearanceNetworks | None = None
        self.perceptual: PerceptualFeatures | None = None
        if cfg.appearance == "willags":
            cfg.triplane.latent_dim = cfg.vae.latent_dim
            self.appearance_nets = AppearanceNetworks(cfg, self.num_train_data)
            if cfg.use_mask and cfg.teacher.enabled:
                self.teacher = cast(AppearanceNetworks, make_teacher(self.appearance_nets))
            if cfg.use_mask:
                self.perceptual = PerceptualFeatures(
                    weights=cfg.mask.vgg_weights, path=cfg.mask.vgg_weights_path, max_resolution=cfg.mask.max_resolution
                )
            lo, hi = robust_bounds(means)  # fixed at initialisation (see triplane.robust_bounds for the rule)
            self.register_buffer("bounds_lo", lo.float())
            self.register_buffer("bounds_hi", hi.float())
            d = cfg.vae.latent_dim
            # mean latent of each training image, refreshed whenever it is visited: the appearances users pick
            self.register_buffer("train_latents", torch.zeros(max(self.num_train_data, 1), d))
            self.register_buffer("train_latent_seen", torch.zeros(max(self.num_train_data, 1), dtype=torch.bool))
        self.render_latent: Tensor | None = None  # appearance override for eval/viewer/export ([D])
        self._train_batch: dict | None = None
        self._step_cache: dict[str, Tensor] = {}
        self._mask_cache: dict[int, Tensor] = {}  # each image's last perceptual mask (True = static), before support
        self._mask_visits: dict[int, int] = {}
        # SfM observations per training image (COLMAP scenes): the mask's safeguard, built per image on first use
        self.sfm_observations = (self.kwargs.get("metadata") or {}).get(SFM_OBSERVATIONS_KEY)
        self._support_cache: dict[int, Tensor | None] = {}
        self._fd_cache: tuple[tuple, Tensor] | None = None
        self._sh_cache: tuple[tuple, Tensor] | None = None
        self._sh_seen: tuple | None = None
        # latents handed out for rendering, keyed by what they are computed from (see _memo_latent)
        self._latent_memo: dict[str, tuple[tuple, Tensor]] = {}
        self._absgrad_notice = False
        self.image_names = [f"image {i}" for i in range(max(self.num_train_data, 1))]
        if cfg.appearance == "willags":
            self.viewer_controls = AppearanceControls(self)

    # ------------------------------------------------------------------ properties used by exporter / viewer
    @property
    def features_dc(self):
        """Splatfacto's name for the degree-0 SH parameter; with the paper's decoder (no SH parameters), the chosen
        appearance baked to SH."""
        if "features_dc" in self.gauss_params:
            return self.gauss_params["features_dc"]
        return self.export_sh()[:, 0, :]

    @property
    def features_rest(self):
        if "features_rest" in self.gauss_params:
            return self.gauss_params["features_rest"]
        return self.export_sh()[:, 1:, :]

    @property
    def intrinsic_features(self) -> Tensor | None:
        """f_s [N, Fs], or None when the configuration has none (modulated colours without a local residual)."""
        return self.gauss_params["features"] if "features" in self.gauss_params else None

    @property
    def colors(self):
        if self.config.appearance == "sh":
            return super().colors
        return self.baked_colors()

    @property
    def shs_0(self):
        """What exporters write as f_dc: splatfacto's SH, or the chosen appearance baked to SH."""
        if self.config.appearance == "sh":
            return super().shs_0
        return self.export_sh()[:, 0, :]

    @property
    def shs_rest(self):
        if self.config.appearance == "sh":
            return super().shs_rest
        return self.export_sh()[:, 1:, :]

    @torch.no_grad()
    def export_sh(self) -> Tensor:
        """SH [N, K, 3] of the chosen appearance for exporters (`ns-export gaussian-splat` writes f_dc + f_rest): the
        decoder fitted by SH of degree render_sh_degree (view-dependent, 3DGS layout); with render_sh_degree=-1, the
        decoder colour averaged over export_view_samples directions as degree 0."""
        deg = self.config.render_sh_degree
        if deg < 0:
            return RGB2SH(self.baked_colors())[:, None, :]
        return self.baked_sh(self.current_latent(), self.means, self.intrinsic_features, deg)

    def get_gaussian_param_groups(self) -> dict[str, list[Parameter]]:
        return {name: [p] for name, p in self.gauss_params.items()}

    def get_param_groups(self) -> dict[str, list[Parameter]]:
        gps = self.get_gaussian_param_groups()
        if self.appearance_nets is not None:
            emb = self.appearance_nets.embeddings
            # the per-image embedding table gets its own group: a table row is updated only when its image is
            # drawn (once per epoch), so it needs a far higher learning rate than the shared networks
            own = {id(p) for p in emb.parameters()} if emb is not None else set()
            gps["appearance"] = [p for p in self.appearance_nets.parameters() if id(p) not in own]
            if emb is not None:
                gps["appearance_embed"] = list(emb.parameters())
        self.camera_optimizer.get_param_groups(param_groups=gps)
        return gps

    def load_state_dict(self, dict, **kwargs):  # type: ignore[override]
        # splatfacto resizes gauss_params to the checkpoint's point count; names are ours, so do it here
        self.step = 30000
        newp = dict["gauss_params.means"].shape[0]
        for param in self.gauss_params.values():  # resized in place: the optimisers hold these Parameter objects
            param.data = torch.zeros((newp,) + param.shape[1:], device=self.device)
        nn.Module.load_state_dict(self, dict, **kwargs)

    # ------------------------------------------------------------------ appearance
    def set_train_batch(self, batch: dict) -> None:
        """Called by WillagsPipeline before each training forward: the image feeds the VAE encoder."""
        self._train_batch = batch

    def _image_chw(self, image: Tensor) -> Tensor:
        return image_as_float(image)[..., :3].permute(2, 0, 1).to(self.device)  # [3, H, W]

    def image_latents(self) -> tuple[Tensor, Tensor]:
        """(latents [num_train, D], known [num_train] bool) of the training images, detached.

        An embedding table's rows are the latents (current values; every row exists from the start). With the VAE,
        the encoder's mean recorded at each image's last training visit, known once the image was drawn."""
        assert self.appearance_nets is not None
        emb = self.appearance_nets.embeddings
        if emb is not None:
            lat = emb.weight.detach()
            return lat, torch.ones(lat.shape[0], dtype=torch.bool, device=lat.device)
        return self.train_latents, self.train_latent_seen

    def default_latent(self) -> Tensor:
        """The appearance used when none is chosen: the mean of the training images' latents."""
        nets = self.appearance_nets
        assert nets is not None
        src = [nets.embeddings.weight] if nets.embeddings is not None else [self.train_latents, self.train_latent_seen]
        return self._memo_latent("default", _versions(src), lambda: mean_latent(self))

    def _memo_latent(self, name: str, key: tuple, make) -> Tensor:
        """`make()`, recomputed only when `key` changes. A rendered frame needs its latent twice (to choose it, then
        to key the per-appearance caches); recomputing it each frame costs host syncs (boolean indexing, value
        checks, a copy to the host for the cache key) that stall a renderer otherwise bound by kernel launches."""
        hit = self._latent_memo.get(name)
        if hit is not None and hit[0] == key:
            return hit[1]
        z = make()
        self._latent_memo[name] = (key, z)
        return z

    def _latent_key(self, z: Tensor) -> tuple:
        """Cache key of latent z: its memo key when z came from _memo_latent (no host sync), else its bytes."""
        for name, (key, t) in self._latent_memo.items():
            if t is z:
                return (name, *key)
        return ("value", z.detach().cpu().numpy().tobytes())

    def _camera_idx_latent(self, cam_idx) -> Tensor | None:
        """Training image `cam_idx`'s latent when nothing else chose the appearance: `ns-render camera-path
        --camera-idx N` (nerfstudio's convention: that image's appearance). Not while the viewer is open: its cameras
        carry cam_idx too (0, or the last training frustum clicked) and the panel's choice, the mean included, is
        what it shows."""
        if cam_idx is None or self.render_latent is not None or os.environ.get(APPEARANCE_ENV):
            return None
        controls = getattr(self, "viewer_controls", None)
        if controls is not None and getattr(controls.p01_a, "gui_handle", None) is not None:
            return None
        lat, known = self.image_latents()
        i = int(cam_idx)
        if not (0 <= i < lat.shape[0]) or not bool(known[i]):
            return None
        return lat[i].to(self.device)

    def current_latent(self) -> Tensor:
        """The chosen appearance: `render_latent` if set, else $WILLAGS_APPEARANCE if set, else the default."""
        if self.render_latent is not None:
            chosen = self.render_latent

            def checked() -> Tensor:
                self.render_latent = checked_latent(chosen, "render_latent")  # no NaN pixels, ever
                return self.render_latent.to(self.device)

            # keyed by the chosen tensor itself (kept alive by the key, so its id cannot be reused) and its version
            # counter (bumped by any in-place edit): a new or edited latent is checked again
            return self._memo_latent("render", (id(chosen), chosen._version, chosen), checked)
        spec = os.environ.get(APPEARANCE_ENV)
        if spec:
            z = latent_from_env(spec, self)
            if z is not None:
                self.render_latent = z
                return z.to(self.device)
        return self.default_latent()

    def set_train_image_names(self, names: list[str]) -> None:
        """Training image file names, in dataset order (from the pipeline): the appearances users can pick."""
        self.image_names = list(names)
        if self.config.appearance == "willags":
            self.viewer_controls.set_image_names(self.image_names)

    @torch.no_grad()
    def encode_image(self, image: Tensor) -> Tensor:
        """Mean latent [D] of an image [H, W, 3] (uint8 or float in [0, 1]) through the VAE encoder."""
        assert self.appearance_nets is not None and self.appearance_nets.vae is not None, "needs use_vae=True"
        mu, _ = self.appearance_nets.vae.encode(self._image_chw(image)[None])
        return mu[0]

    def _normalized_means(self, means: Tensor) -> Tensor:
        return normalize_points(means, self.bounds_lo, self.bounds_hi)

    def _dynamic_features(self, nets: AppearanceNetworks, z: Tensor, means: Tensor, cacheable: bool):
        """f_d, recomputed only when z or the Gaussians change while rendering (viewer / eval)."""
        if nets.field is None:
            return None
        if not cacheable:
            return nets.dynamic_features(z, self._normalized_means(means))
        key = (self._latent_key(z), means.data_ptr(), means.shape[0], self.step)
        if self._fd_cache is not None and self._fd_cache[0] == key:
            return self._fd_cache[1]
        f_d = nets.dynamic_features(z, self._normalized_means(means))
        if f_d is not None:
            self._fd_cache = (key, f_d)
        return f_d

    def sh_coeffs(self, gp: dict | None = None) -> Tensor | None:
        """SH coefficients [N, K, 3] of the Gaussians (`gp`: a cropped gauss_params view), or None without them."""
        gp = self.gauss_params if gp is None else gp
        if "features_dc" not in gp:
            return None
        return torch.cat((gp["features_dc"][:, None, :], gp["features_rest"]), dim=1)

    def active_sh_degree(self) -> int:
        """SH degree in use now: splatfacto's schedule (one more degree every sh_degree_interval steps)."""
        return min(self.step // max(1, self.config.sh_degree_interval), self.config.sh_degree)

    def appearance_colors(
        self,
        z: Tensor,
        means: Tensor,
        f_s: Tensor | None,
        cam_center: Tensor,
        nets: AppearanceNetworks | None = None,
        cacheable: bool = False,
        sh: Tensor | None = None,
        base: Tensor | None = None,
    ) -> Tensor:
        """RGB [N, 3] of Gaussians at `means` [N, 3] seen from `cam_center` [3] under latent z [D].

        `sh` [N, K, 3]: the Gaussians' SH coefficients (color_mode='modulated'); default: all the model's Gaussians.
        `base` [N, 3]: their SH colours from cam_center, already evaluated (then sh is not used).
        When the student's networks run in training, the local residual is kept for its penalty."""
        nets = nets if nets is not None else self.appearance_nets
        assert nets is not None
        f_d = self._dynamic_features(nets, z, means, cacheable)
        dirs = means - cam_center[None, :]
        if nets.modulation is None:
            assert f_s is not None
            return nets.colors(z, f_d, f_s, dirs)
        residual = nets.modulation.local_residual(z, f_s, f_d, means.shape[0])
        student_step = self.training and nets is self.appearance_nets and torch.is_grad_enabled()
        if student_step:
            self._step_cache["local_residual"] = residual  # type: ignore[assignment]
        if base is None:
            sh = self.sh_coeffs() if sh is None else sh
            base = (spherical_harmonics(self.active_sh_degree(), dirs, sh) + 0.5).clamp_min(0.0)
            if student_step:
                # the teacher colours the same Gaussians' SH from the same camera: it reuses these (detached)
                self._step_cache["sh_base"] = base.detach()  # type: ignore[assignment]
        return nets.colors(z, f_d, f_s, dirs, residual=residual, base=base)

    def _sh_key(self, z: Tensor, means: Tensor, degree: int) -> tuple:
        return (self._latent_key(z), means.data_ptr(), means.shape[0], self.step, degree)

    def _frame_sh(self, z: Tensor, means: Tensor, f_s: Tensor | None, degree: int, gp: dict) -> Tensor | None:
        """The baked SH for this frame, or None to run the decoder. Bakes on the second frame with the same (latent,
        Gaussians): a viewer refreshing during training, where the Gaussians change every step, keeps the exact
        decoder instead of paying a bake per frame. The Gaussians' own SH (`gp`) is gathered only for a bake: a
        cached frame costs no [N, 16, 3] copy."""
        key = self._sh_key(z, means, degree)
        if self._sh_cache is not None and self._sh_cache[0] == key:
            return self._sh_cache[1]
        if self._sh_seen != key:
            self._sh_seen = key
            return None
        return self.baked_sh(z, means, f_s, degree, key, sh=self.sh_coeffs(gp))

    @torch.no_grad()
    def baked_sh(
        self,
        z: Tensor,
        means: Tensor,
        f_s: Tensor | None,
        degree: int,
        key: tuple | None = None,
        sh: Tensor | None = None,
    ) -> Tensor:
        """SH coefficients [N, (degree + 1)**2, 3] whose evaluation (gsplat's: sum_k c_k Y_k(d) + 0.5) reproduces the
        appearance's colour. Cached per (latent, Gaussians); `key` is :meth:`_sh_key` when the caller already has it
        (one host sync per frame, not two).

        color_mode='modulated': exact (the colour is an affine map of the SH colour: the map is applied to the
        coefficients). 'decoder', and 'modulated' with its gamma (not affine): the colours fitted by least squares
        over RENDER_SH_SAMPLES directions."""
        nets = self.appearance_nets
        assert nets is not None
        key = self._sh_key(z, means, degree) if key is None else key
        if self._sh_cache is not None and self._sh_cache[0] == key:
            return self._sh_cache[1]
        f_d = self._dynamic_features(nets, z, means, cacheable=True)
        if nets.modulation is not None and not nets.modulation.gamma:
            coeffs = self._modulated_sh(nets.modulation, z, means, f_s, f_d, degree, sh)
        else:
            dirs = fibonacci_directions(max(RENDER_SH_SAMPLES, 2 * (degree + 1) ** 2), means.device)  # [M, 3]
            proj = torch.linalg.pinv(sh_basis(dirs, degree))  # [K, M]: coefficients from samples
            coeffs = torch.zeros(means.shape[0], proj.shape[0], 3, device=means.device)
            for m, rgb in enumerate(self._colors_over_directions(z, means, f_s, f_d, dirs, sh)):
                coeffs += proj[None, :, m, None] * (rgb - 0.5)[:, None, :]  # gsplat adds 0.5 back
        self._sh_cache = (key, coeffs)
        return coeffs

    def _modulated_sh(self, mod: ColorModulation, z, means, f_s, f_d, degree: int, sh: Tensor | None) -> Tensor:
        """The colour transform applied to the SH coefficients: with M_i = diag(1 + s_i) A and t_i = (1 + s_i) b + o_i,
        c_i(d) = M_i (SH_i(d) + 0.5) + t_i = sum_k (M_i c_k) Y_k(d) + 0.5 + (M_i 0.5 + t_i - 0.5), the constant going
        into the degree-0 coefficient (Y_0 = C0). Exact up to the clamps at 0 (base colour, final colour)."""
        sh = self.sh_coeffs() if sh is None else sh
        k_out = (degree + 1) ** 2
        k_use = min(k_out, (self.active_sh_degree() + 1) ** 2, sh.shape[1])
        A, b = mod.global_transform(z)
        n = means.shape[0]
        M = A.expand(n, 3, 3)
        t = b.expand(n, 3)
        residual = mod.local_residual(z, f_s, f_d, n)
        if residual is not None:
            scale = 1.0 + residual[:, :3]
            M = scale[:, :, None] * M
            t = scale * t + residual[:, 3:]
        out = torch.zeros(n, k_out, 3, device=means.device, dtype=sh.dtype)
        out[:, :k_use] = torch.einsum("nij,nkj->nki", M, sh[:, :k_use])
        const = (M @ torch.full((3,), 0.5, device=means.device, dtype=M.dtype)) + t - 0.5
        out[:, 0] += const / 0.28209479177387814  # SH_C0
        return out

    @torch.no_grad()
    def baked_colors(self, z: Tensor | None = None) -> Tensor:
        """View-independent colours [N, 3] for export: the appearance averaged over a Fibonacci sphere of views."""
        assert self.appearance_nets is not None
        z = self.current_latent() if z is None else z.to(self.device)
        means, f_s = self.means, self.intrinsic_features
        k = max(1, self.config.export_view_samples)
        dirs = fibonacci_directions(k, self.device)  # [k, 3]
        acc = torch.zeros(means.shape[0], 3, device=self.device)
        f_d = self._dynamic_features(self.appearance_nets, z, means, cacheable=False)
        for rgb in self._colors_over_directions(z, means, f_s, f_d, dirs):
            acc += rgb
        return acc / k

    def _colors_over_directions(
        self, z: Tensor, means: Tensor, f_s: Tensor | None, f_d: Tensor | None, dirs: Tensor, sh: Tensor | None = None
    ) -> Iterator[Tensor]:
        """The appearance's colours [N, 3] seen from each of `dirs` [M, 3], one colour pass per direction (no
        [M, N, 3] buffer). The local residual does not depend on the direction: computed once. The Gaussians' SH
        (`sh`, gathered here when None) feeds color_mode='modulated'; the decoder does not read it."""
        nets = self.appearance_nets
        assert nets is not None
        mod = nets.modulation
        sh = self.sh_coeffs() if sh is None else sh
        residual = mod.local_residual(z, f_s, f_d, means.shape[0]) if mod is not None else None
        for d in dirs:
            yield nets.colors(
                z, f_d, f_s, d.expand_as(means), sh=sh, sh_degree=self.active_sh_degree(), residual=residual
            )

    # ------------------------------------------------------------------ rendering
    def _uses_gsplat(self, means: Tensor) -> bool:
        return self.config.backend == "gsplat" or (self.config.backend == "auto" and means.is_cuda)

    def _rasterize(self, means, quats, scales, opacities, colors, viewmat, K, W, H, render_mode, sh_degree=None):
        # absgrad (densify on |grad|) exists only in gsplat's CUDA backward; the strategy must agree with the
        # rasteriser or it reads a gradient that was never written
        absgrad = self.config.use_absgrad and self._uses_gsplat(means)
        if self.strategy.absgrad != absgrad:
            if not absgrad and self.config.use_absgrad and not self._absgrad_notice:
                CONSOLE.log("willags: use_absgrad needs gsplat's CUDA backward; densifying on plain gradients")
                self._absgrad_notice = True
            self.strategy.absgrad = absgrad
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
            rasterize_mode=self.config.rasterize_mode,
            backend=self.config.backend,
        )

    def get_outputs(self, camera: Cameras) -> dict[str, Union[torch.Tensor, list]]:
        if not isinstance(camera, Cameras):
            raise TypeError(f"WillagsModel.get_outputs expects nerfstudio Cameras, got {type(camera).__name__}")
        cfg = self.config
        if self.training:
            if camera.shape[0] != 1:
                raise ValueError("willags trains on one camera at a time")
            c2w = self.camera_optimizer.apply_to_camera(camera)
        else:
            c2w = camera.camera_to_worlds
        if self.crop_box is not None and not self.training:
            crop_ids = self.crop_box.within(self.means).squeeze()
            if crop_ids.sum() == 0:
                return self.get_empty_outputs(
                    int(camera.width.item()), int(camera.height.item()), self.background_color
                )
        else:
            crop_ids = None
        gp = {k: (v[crop_ids] if crop_ids is not None else v) for k, v in self.gauss_params.items()}

        scale_fac = self._get_downscale_factor()
        camera.rescale_output_resolution(1 / scale_fac)
        viewmat = viewmat_from_c2w(c2w)
        K = camera.get_intrinsics_matrices().to(self.device)
        W, H = int(camera.width.item()), int(camera.height.item())
        self.last_size = (H, W)
        camera.rescale_output_resolution(scale_fac)
        render_mode = "RGB+ED" if (cfg.output_depth_during_training or not self.training) else "RGB"
        cam_center = c2w[0, :3, 3]

        outputs: dict[str, Union[Tensor, list]] = {}
        z: Tensor | None = None
        if cfg.appearance == "sh":
            colors = torch.cat((gp["features_dc"][:, None, :], gp["features_rest"]), dim=1)
            if cfg.sh_degree > 0:
                sh_degree = min(self.step // cfg.sh_degree_interval, cfg.sh_degree)
            else:
                colors, sh_degree = torch.sigmoid(colors).squeeze(1), None
        else:
            z = self._latent_for_forward(camera, outputs)
            fixed = not self.training and not torch.is_grad_enabled()
            deg = cfg.render_sh_degree
            sh = None
            if fixed and deg >= 0 and "appearance_latent" not in (camera.metadata or {}):
                sh = self._frame_sh(z, gp["means"], gp.get("features"), deg, gp)
            if sh is not None:
                colors, sh_degree = sh, deg
            else:
                colors = self.appearance_colors(
                    z, gp["means"], gp.get("features"), cam_center, cacheable=fixed, sh=self.sh_coeffs(gp)
                )
                sh_degree = None

        teacher_needed = self.training and self._teacher_needed()
        fused = teacher_needed and cfg.fuse_teacher_render and self.teacher is not None
        if fused:  # student RGB | teacher RGB (detached) in one rasterisation: channels 0:3 | 3:6
            colors = torch.cat([colors, self._teacher_colors(gp, cam_center)], dim=-1)
        render, alpha, self.info = self._rasterize(
            gp["means"], gp["quats"], gp["scales"], gp["opacities"], colors, viewmat, K, W, H, render_mode, sh_degree
        )
        if self.training:
            self.strategy.step_pre_backward(
                self.gauss_params, self.optimizers, self.strategy_state, self.step, self.info
            )
        dirs = None
        if z is not None and self.appearance_nets is not None and self.appearance_nets.sky is not None:
            dirs = pixel_directions(c2w[0], K[0], W, H)
        background = self._background(self.appearance_nets, z, dirs)
        rgb = torch.clamp(render[..., :3] + (1 - alpha) * background, 0.0, 1.0)

        if fused:
            teacher_bg = background
            if dirs is not None:  # the teacher's own sky under the teacher's latent (set with its colours)
                teacher_bg = self._background(self.teacher, self._step_cache.get("teacher_z"), dirs).detach()
            teacher = render[..., 3:6].detach() + (1 - alpha.detach()) * teacher_bg
            outputs["teacher_rgb"] = torch.clamp(teacher, 0.0, 1.0).squeeze(0)
        elif teacher_needed and self.teacher is None:  # teacher.enabled=False: the student's own render
            outputs["teacher_rgb"] = rgb.detach().squeeze(0)
        elif teacher_needed:
            outputs["teacher_rgb"] = self._teacher_render(gp, cam_center, viewmat, K, W, H, background, dirs)

        depth_im = None
        if render_mode == "RGB+ED":
            depth_im = render[..., -1:]  # gsplat appends expected depth after the colour channels
            depth_im = torch.where(alpha > 0, depth_im, depth_im.detach().max()).squeeze(0)
        if background.dim() == 1 and not self.training:
            background = background.expand(H, W, 3)
        elif background.dim() == 4:  # the sky: [1, H, W, 3]
            background = background.squeeze(0)
        outputs.update(
            {"rgb": rgb.squeeze(0), "depth": depth_im, "accumulation": alpha.squeeze(0), "background": background}  # type: ignore[dict-item]
        )
        return outputs

    def _background(self, nets: "AppearanceNetworks | None", z: Tensor | None, dirs: Tensor | None) -> Tensor:
        """What shows behind the Gaussians: the sky of `nets` under latent z along the pixel directions `dirs`
        [H, W, 3] as [1, H, W, 3], or splatfacto's background colour [3] (random while training) without a sky."""
        if nets is not None and nets.sky is not None and z is not None and dirs is not None:
            return nets.sky(z, dirs)[None]
        return self._get_background_color()

    def _latent_for_forward(self, camera: Cameras, outputs: dict) -> Tensor:
        """Training: encode this step's image (reparameterised). Otherwise: camera metadata / chosen / default."""
        nets = self.appearance_nets
        assert nets is not None
        md = camera.metadata or {}
        if not self.training:
            if "appearance_latent" in md:
                return torch.as_tensor(md["appearance_latent"], device=self.device).reshape(-1).float()
            z = self._camera_idx_latent(md.get("cam_idx"))
            return z if z is not None else self.current_latent()
        batch = self._train_batch
        if batch is None:
            raise RuntimeError(
                "willags: the model got no training image; train it through WillagsPipeline (method configs "
                "'willags*' do) or call model.set_train_batch(batch) before model(camera)"
            )
        idx = int(batch["image_idx"]) if "image_idx" in batch else int(md.get("cam_idx", 0))
        img = self._image_chw(batch["image"])
        mu, logvar = nets.latent_stats(img, idx)
        if logvar is not None:
            z = reparameterize(mu[None], logvar[None])[0]
            self._step_cache.update({"mu": mu, "logvar": logvar, "z": z, "vae_in": img})
        else:
            z = mu
            self._step_cache.update({"z": z})
        self._step_cache["image_idx"] = torch.tensor(idx)
        if idx < self.train_latents.shape[0]:
            self.train_latents[idx] = mu.detach()
            self.train_latent_seen[idx] = True
        return z

    def _teacher_needed(self) -> bool:
        cfg = self.config
        if cfg.appearance != "willags" or not cfg.use_mask:
            return False
        if not mask_active(self.step, cfg.mask.warmup_steps):
            return False
        idx = int(self._step_cache.get("image_idx", torch.tensor(-1)))
        visits = self._mask_visits.get(idx, 0)
        self._mask_visits[idx] = visits + 1
        return idx not in self._mask_cache or visits % max(1, cfg.mask_every) == 0

    @torch.no_grad()
    def _teacher_colors(self, gp, cam_center) -> Tensor:
        """Per-Gaussian RGB [N, 3] of the EMA teacher networks for this step's image (no grad)."""
        teacher = self.teacher
        assert teacher is not None
        if teacher.vae is not None:
            mu, _ = teacher.vae.encode(self._step_cache["vae_in"][None])
            z = mu[0]
        else:
            z = teacher.embeddings.weight[int(self._step_cache["image_idx"])]  # type: ignore[union-attr]
        self._step_cache["teacher_z"] = z
        f_s = gp["features"].detach() if "features" in gp else None
        base = self._step_cache.pop("sh_base", None)  # the student's SH colours of this step (same Gaussians)
        sh = None
        if base is None:
            sh = self.sh_coeffs(gp)
            sh = sh.detach() if sh is not None else None
        return self.appearance_colors(z, gp["means"].detach(), f_s, cam_center, nets=teacher, sh=sh, base=base)

    @torch.no_grad()
    def _teacher_render(self, gp, cam_center, viewmat, K, W, H, background, dirs=None) -> Tensor:
        """Pseudo-GT [H, W, 3] from the EMA teacher networks with the student's current Gaussians (no grad): a
        second rasterisation (fuse_teacher_render=False; the fused path renders the same image). With a sky
        (`dirs` given), the teacher's own sky replaces `background`."""
        colors = self._teacher_colors(gp, cam_center)
        if dirs is not None:
            background = self._background(self.teacher, self._step_cache.get("teacher_z"), dirs)
        render, alpha, _ = self._rasterize(
            gp["means"].detach(),
            gp["quats"].detach(),
            gp["scales"].detach(),
            gp["opacities"].detach(),
            colors,
            viewmat.detach(),
            K,
            W,
            H,
            "RGB",
        )
        return torch.clamp(render[..., :3] + (1 - alpha) * background, 0.0, 1.0).squeeze(0)

    # ------------------------------------------------------------------ losses / metrics
    def _static_mask(self, outputs, gt_img: Tensor) -> Tensor | None:
        """[H, W] float mask of static pixels (1 = supervised), or None when masking is off / warming up."""
        cfg = self.config
        if cfg.appearance != "willags" or not cfg.use_mask or not mask_active(self.step, cfg.mask.warmup_steps):
            return None
        idx = int(self._step_cache.get("image_idx", torch.tensor(-1)))
        H, W = gt_img.shape[:2]
        if "teacher_rgb" in outputs:
            assert self.perceptual is not None
            d = image_distance(self.perceptual, gt_img, outputs["teacher_rgb"])  # [H, W]
            self._step_cache["D"] = d
            thr = mask_threshold(self.step, cfg.mask.threshold, cfg.mask.warmup_steps, cfg.mask.ramp_steps)
            transient, rejected = transient_mask(
                d, thr, cfg.mask.threshold_rule, cfg.mask.robust_k, cfg.max_masked_fraction
            )
            mask = ~transient  # a rejected mask supervises every pixel rather than none
            self._step_cache["mask_rejected"] = rejected.float()  # a device tensor: no wait for VGG here
            self._mask_cache[idx] = mask
        elif idx in self._mask_cache:
            mask = self._mask_cache[idx]
        else:
            return None
        if mask.shape != (H, W):  # resolution schedule moved on since the mask was cached
            mask = F.interpolate(mask[None, None].float(), size=(H, W), mode="nearest")[0, 0] > 0.5
        return apply_support(mask, self.static_support(idx, H, W)).float()

    def static_support(self, idx: int, height: int, width: int) -> Tensor | None:
        """Training image `idx`'s SfM support grid (True = vouched static; willags_ns/static_support.py), or None
        (safeguard off, no tracks in the scene). Built once per image on the device; the grid's aspect follows the
        image's, so any resolution of the schedule maps onto it."""
        cfg = self.config.static_support
        obs = self.sfm_observations
        if not cfg.enabled or obs is None or not 0 <= idx < len(obs):
            return None
        if idx not in self._support_cache:
            self._support_cache[idx] = support_map(obs[idx], width, height, cfg).to(self.device)
        return self._support_cache[idx]

    def _gt_image(self, outputs, batch) -> Tensor:
        """This step's ground truth [H, W, 3] (float, at the render's resolution, composited on its background),
        made once for the metrics and the loss: both need it, and each conversion of a cached uint8 photo is a
        full-image pass."""
        cached = self._step_cache.get("gt_img")
        # keyed by the objects themselves (held, so never a recycled id): this step's render of this photo
        if cached is not None and cached[0] is outputs and cached[1] is batch["image"]:
            return cached[2]
        gt = self.composite_with_background(self.get_gt_img(batch["image"]), outputs["background"])
        if self.training:  # the step cache is emptied after every training step (_end_step)
            self._step_cache["gt_img"] = (outputs, batch["image"], gt)  # type: ignore[assignment]
        return gt

    def get_metrics_dict(self, outputs, batch) -> dict[str, torch.Tensor]:
        """splatfacto's training metrics, with the PSNR as a function: torchmetrics' module updates and resets its
        state on every call (host work each step, for a number the trainer logs one step in ten). Same value."""
        pred, gt = outputs["rgb"], self._gt_image(outputs, batch)
        metrics: dict = {"psnr": -10.0 * torch.log10(F.mse_loss(pred.detach(), gt)), "gaussian_count": self.num_points}
        if self.config.color_corrected_metrics:
            metrics["cc_psnr"] = self.psnr(color_correct(pred, gt), gt)
        self.camera_optimizer.get_metrics_dict(metrics)
        if self.training and "z" in self._step_cache:
            metrics["latent_norm"] = self._step_cache["z"].detach().norm()
        return metrics

    def get_loss_dict(self, outputs, batch, metrics_dict=None) -> dict[str, torch.Tensor]:
        cfg = self.config
        gt_img = self._gt_image(outputs, batch)
        pred_img = outputs["rgb"]
        mask = self._static_mask(outputs, gt_img) if self.training else None
        if "mask" in batch:  # user-provided masks (nerfstudio convention) combine with ours
            user = self._downscale_if_required(batch["mask"]).to(self.device)[..., 0].float()
            mask = user if mask is None else mask * user
        pred_b, gt_b = pred_img.permute(2, 0, 1)[None], gt_img.permute(2, 0, 1)[None]
        mask_b = None if mask is None else mask[None]
        loss_dict = {"main_loss": reconstruction_loss(pred_b, gt_b, mask_b, ssim_lambda=cfg.ssim_lambda)}
        if mask is not None and metrics_dict is not None:
            metrics_dict["masked_fraction"] = 1.0 - mask.mean().detach()
            if "mask_rejected" in self._step_cache:
                metrics_dict["mask_rejected"] = self._step_cache["mask_rejected"]

        if self.training and "logvar" in self._step_cache and self.appearance_nets is not None:
            vae = self.appearance_nets.vae
            assert vae is not None
            sc = self._step_cache
            recon = vae.decode(sc["z"][None])
            target = vae.prepare(sc["vae_in"][None])
            l_vae, parts = vae_loss(
                recon,
                target,
                sc["mu"][None],
                sc["logvar"][None],
                beta=cfg.vae.beta,
                recon_reduction=cfg.vae.recon_reduction,
            )
            loss_dict["vae_loss"] = cfg.lambda_vae * l_vae
            if metrics_dict is not None:
                metrics_dict["vae_kl"] = parts["vae_kl"].detach()
                metrics_dict["vae_recon"] = parts["vae_recon"].detach()
            sc["vae_recon_img"] = recon.detach()

        if self.training and cfg.sky.enabled and cfg.sky.alpha_penalty > 0 and outputs["background"].dim() == 3:
            pen_sky = background_alpha_penalty(
                outputs["accumulation"], gt_img, outputs["background"], cfg.sky.alpha_tol, mask
            )
            if pen_sky is not None:
                loss_dict["sky_alpha"] = cfg.sky.alpha_penalty * pen_sky

        pen = local_penalty(self._step_cache.get("local_residual")) if self.training else None
        if pen is not None and cfg.modulation.local_penalty > 0:
            loss_dict["appearance_local"] = cfg.modulation.local_penalty * pen

        if cfg.use_scale_regularization and self.step % 10 == 0:
            s = torch.exp(self.scales)
            ratio = s.amax(dim=-1) / s.amin(dim=-1)
            loss_dict["scale_reg"] = 0.1 * (torch.clamp_min(ratio, cfg.max_gauss_ratio) - cfg.max_gauss_ratio).mean()
        if self.training:
            self.camera_optimizer.get_loss_dict(loss_dict)
            self._maybe_log_images(outputs, gt_img, mask)
        return loss_dict

    def _maybe_log_images(self, outputs, gt_img: Tensor, mask: Tensor | None) -> None:
        every = self.config.log_images_every
        if every <= 0 or self.step % every != 0:
            return
        from nerfstudio.utils import writer

        writer.put_image("train/render_vs_gt", torch.cat([gt_img, outputs["rgb"].detach()], dim=1), self.step)
        if "teacher_rgb" in outputs:
            writer.put_image("train/teacher_render", outputs["teacher_rgb"], self.step)
        if "D" in self._step_cache:
            d = self._step_cache["D"]
            writer.put_image(
                "train/perceptual_D", (d / d.max().clamp_min(1e-6))[..., None].expand(-1, -1, 3), self.step
            )
        if mask is not None:
            writer.put_image("train/static_mask", mask[..., None].expand(-1, -1, 3), self.step)
        if "vae_recon_img" in self._step_cache:
            writer.put_image(
                "train/vae_reconstruction", self._step_cache["vae_recon_img"][0].permute(1, 2, 0), self.step
            )

    def get_image_metrics_and_images(self, outputs, batch):
        gt_rgb = self.composite_with_background(self.get_gt_img(batch["image"]), outputs["background"])
        pred = outputs["rgb"]
        combined = torch.cat([gt_rgb, pred], dim=1)
        gt_b, pred_b = gt_rgb.permute(2, 0, 1)[None], pred.permute(2, 0, 1)[None]
        metrics = {"psnr": float(self.psnr(gt_b, pred_b).item()), "ssim": float(self.ssim(gt_b, pred_b))}
        lpips = self.lpips_metric()
        if lpips is not None:
            metrics["lpips"] = float(lpips(gt_b, pred_b))
        return metrics, {"img": combined}

    def lpips_metric(self):
        """torchmetrics LPIPS when AlexNet's ImageNet weights are on disk; else None with a one-line notice."""
        if self._lpips is None and self._lpips_status is None:
            if _lpips_weights_cached():
                from torchmetrics.image.lpip import LearnedPerceptualImagePatchSimilarity

                self._lpips = LearnedPerceptualImagePatchSimilarity(normalize=True).to(self.device)
                self._lpips_status = "torchmetrics alexnet"
            else:
                self._lpips_status = "unavailable"
                CONSOLE.log(
                    f"willags: LPIPS unavailable (no AlexNet weights in {torch.hub.get_dir()}/checkpoints; "
                    "offline): reporting PSNR and SSIM only"
                )
        return self._lpips

    # ------------------------------------------------------------------ callbacks
    def get_training_callbacks(
        self, training_callback_attributes: TrainingCallbackAttributes
    ) -> list[TrainingCallback]:
        cbs = super().get_training_callbacks(training_callback_attributes)
        if self.teacher is not None:
            cbs.append(TrainingCallback([TrainingCallbackLocation.AFTER_TRAIN_ITERATION], self.update_teacher))
        cbs.append(TrainingCallback([TrainingCallbackLocation.AFTER_TRAIN_ITERATION], self._end_step))
        return cbs

    def update_teacher(self, step: int) -> None:
        """EMA: W_T <- tau W_T + (1 - tau) W_S after every optimiser step."""
        assert self.teacher is not None and self.appearance_nets is not None
        ema_update_(self.teacher, self.appearance_nets, self.config.teacher.tau)

    def _end_step(self, step: int) -> None:
        self._step_cache = {}
        self._train_batch = None

    # ------------------------------------------------------------------ checkpoints carry the mask provenance
    def get_extra_state(self):
        """Saved as `_extra_state` in every checkpoint: which VGG weights made the transient masks."""
        src = self.perceptual.source if self.perceptual is not None else None
        return {"perceptual_source": src or self.__dict__.get("loaded_perceptual_source")}

    def set_extra_state(self, state) -> None:
        self.loaded_perceptual_source = (state or {}).get("perceptual_source")
