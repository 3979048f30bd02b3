"""WillagsModel: splatfacto's Gaussians with a latent-conditioned appearance field, an EMA teacher and a
perceptual transient mask (WilLaGS). Runs on any device; rasterises through `willags_ns.render.rasterize`.

Per training step (the pipeline hands the model the training image first):

    camera --camera optimiser, render scale--> View                      render/camera.py
    image --table row or VAE encoder--> z [D]                           appearance/latents.py
        (a mask step: the EMA teacher's z too, and how it renders)      mask/step.py
    z, Gaussians, camera --> colours [N, 3] (+ the teacher's)           appearance/color_path.py, networks.py
    colours (+ the teacher's, fused) --rasterize--> render              splats/gaussians.py, render/
    render over the background (the sky of z) --> rgb (+ pseudo-GT)     appearance/sky.py
    VGG16(GT) vs VGG16(teacher render) --> D; static mask = D < 0.85    mask/step.py
    loss = 0.8 L1 + 0.2 D-SSIM on static pixels + the regularisers      objective/losses.py, objective/regularizers.py

get_outputs is that sequence of stage calls, each into one room; the teacher goes through the same functions as the
student (its colours fused as 3 more channels of the one rasterisation, or rasterised on their own).

The step's intermediates travel in `get_outputs`' dictionary (nerfstudio's habit) to `get_metrics_dict` and
`get_loss_dict`: the image index, the latent (and the VAE's posterior and input), the colour model's penalty, the
teacher's latent and render, the ground truth at the render's resolution. This file is the wiring (parameter groups,
get_outputs, losses, callbacks; the settings: config.py); docs/architecture.md maps the rooms. The class subclasses
SplatfactoModel because nerfstudio's exporter and viewer check `isinstance(model, SplatfactoModel)`; it reuses
splatfacto's densification (gsplat's DefaultStrategy), resolution schedule and metrics, and replaces what hard-codes
CUDA (`populate_modules`, `get_outputs`) or downloads weights (LPIPS). `appearance="sh"` turns it into plain 3DGS
(splatfacto's SH colours, no appearance model, no mask): the CPU stand-in for splatfacto in benchmarks
(method `willags-3dgs`).
"""

import numbers
import os
from typing import Any, Union

import torch
import torch.nn.functional as F
from nerfstudio.cameras.cameras import Cameras
from nerfstudio.data.scene_box import OrientedBox
from nerfstudio.engine.callbacks import TrainingCallback, TrainingCallbackAttributes, TrainingCallbackLocation
from nerfstudio.model_components.lib_bilagrid import color_correct
from nerfstudio.models.splatfacto import RGB2SH, SplatfactoModel
from nerfstudio.utils.rich_utils import CONSOLE
from torch import Tensor, nn
from torch.nn import Parameter

from willags_ns.appearance.color_path import ColorContext, ColorPath, GaussianColors, teacher_colors
from willags_ns.appearance.latents import (
    AppearanceLatents,
    TrainingLatent,
    image_chw,
    keeps_latent_memo,
    mean_latent,
    stored_latents,
    training_latent,
)
from willags_ns.appearance.networks import AppearanceNetworks, gaussian_layout
from willags_ns.appearance.sky import background, composite, pixel_directions, sky_for_scene
from willags_ns.appearance.triplane import robust_bounds
from willags_ns.appearance_spec import latent_from_env
from willags_ns.data.sfm_tracks import SFM_DEPTHS_KEY, SFM_OBSERVATIONS_KEY
from willags_ns.eval.holdout import (
    BestStep,
    copy_state,
    holdout_indices,
    holdout_psnr,
    is_scoring_step,
    left_half_weight,
    restore_state,
)
from willags_ns.eval.image_metrics import image_metrics
from willags_ns.eval.lpips import make_lpips
from willags_ns.eval.protocol import training_outlier_share
from willags_ns.mask.expected import LEVEL, expected_on, initial_levels, level_channels, level_loss
from willags_ns.mask.health import MaskHealth
from willags_ns.mask.residual import colour_residual
from willags_ns.mask.rule import mask_start
from willags_ns.mask.step import (
    MaskStep,
    StepMask,
    TeacherPass,
    log_step_images,
    mask_networks,
    teacher_latent,
)
from willags_ns.mask.store import PackedMasks
from willags_ns.mask.teacher import ema_update_
from willags_ns.mask.transient import PerceptualFeatures
from willags_ns.objective.losses import reconstruction_loss
from willags_ns.objective.regularizers import regularization_terms
from willags_ns.objective.sfm_depth import select_observations, sfm_depth_loss
from willags_ns.render.camera import View, camera_view
from willags_ns.splats.gaussians import (
    active_sh_degree,
    densification_strategy,
    initial_gauss_params,
    initial_points,
    opacity_reset_period,
    rasterize_gaussians,
    sh_coeffs,
    sh_colors,
    strategy_absgrad,
)
from willags_ns.splats.mcmc import McmcDensification, transient_cap, uses_mcmc

__all__ = ["WillagsModel"]


def _several_ranks() -> bool:
    """Whether this process is one rank of a data-parallel run: the rules that measure the training photos (MCMC's
    transients cap, the mask's start) do not measure there, since each rank holds only its share of them."""
    dist = torch.distributed
    return dist.is_available() and dist.is_initialized() and dist.get_world_size() > 1


class WillagsModel(SplatfactoModel):
    """WilLaGS on top of splatfacto. See the module docstring for the per-step data flow. Its public methods are
    here, each section a line or two over its room: the latents (`current_latent`, `render_latent`, `image_latents`,
    `encode_image`, ...: appearance/latents.py), the mask (`update_teacher`, `static_support`, `sfm_observations`,
    ...: mask/step.py), the exporter's names (`shs_0`, `shs_rest`, `colors`, `export_sh`, the bakes:
    appearance/color_path.py)."""

    config: Any  # willags_ns.config.WillagsModelConfig (which names this class as its _target)
    # buffers registered in populate_modules (declared for type checkers: nn.Module.__getattr__ is untyped)
    train_latents: Tensor
    train_latent_seen: Tensor
    bounds_lo: Tensor
    bounds_hi: Tensor

    # ------------------------------------------------------------------ set-up
    def populate_modules(self):
        cfg = self.config
        cfg.check()
        means, seed_rgb = initial_points(cfg, self.seed_points)
        distances, _ = self.k_nearest_sklearn(means, 3)
        avg_dist = torch.from_numpy(distances).mean(dim=-1, keepdim=True).clamp_min(1e-7)
        # the densification ("auto": MCMC on a GPU) sets the initial Gaussians and the strategy below
        self.mcmc_on = uses_mcmc(cfg.densification, self.kwargs.get("device") or "cpu")
        layout = gaussian_layout(cfg)  # the per-Gaussian tensors the colour model reads (SH, f_s)
        self.gauss_params = nn.ParameterDict(initial_gauss_params(cfg, means, seed_rgb, avg_dist, layout, self.mcmc_on))
        if expected_on(cfg):  # each Gaussian's expected residual, densified and saved with the rest (mask/expected.py)
            self.gauss_params[LEVEL] = nn.Parameter(initial_levels(means.shape[0]))

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
        self.strategy = densification_strategy(cfg, self.num_train_data, self.mcmc_on)
        self.strategy_state = self.strategy.initialize_state(scene_scale=1.0)

        # --- the appearance model (absent for appearance="sh")
        self.appearance_nets: AppearanceNetworks | None = None
        self.teacher: AppearanceNetworks | None = None
        self.perceptual: PerceptualFeatures | None = None
        observations = (self.kwargs.get("metadata") or {}).get(SFM_OBSERVATIONS_KEY)
        # whether there is a sky and where it shows while training (region "open" without keypoints: no sky); plain
        # 3DGS colours (appearance "sh") have no appearance model, so no sky
        with_sky, self.open_regions = (
            sky_for_scene(cfg.sky, observations) if cfg.appearance == "willags" else (False, None)
        )
        if cfg.appearance == "willags":
            self.appearance_nets = AppearanceNetworks(cfg, self.num_train_data, with_sky)
            self.teacher, self.perceptual = mask_networks(cfg, self.appearance_nets)
            lo, hi = robust_bounds(means)  # fixed at initialisation (see triplane.robust_bounds for the rule)
            self.register_buffer("bounds_lo", lo.float())
            self.register_buffer("bounds_hi", hi.float())
            d = cfg.latent.dim
            # mean latent of each training image, refreshed whenever it is visited: the appearances users pick
            self.register_buffer("train_latents", torch.zeros(max(self.num_train_data, 1), d))
            self.register_buffer("train_latent_seen", torch.zeros(max(self.num_train_data, 1), dtype=torch.bool))
        self.latents = AppearanceLatents()  # the chosen appearance; the memo of the latents handed out
        self.color_path = ColorPath(self.latents.key_of)  # the f_d and baked-SH caches
        # each image's last mask, visits and SfM support (the safeguard's observations: COLMAP scenes)
        self.mask_step = MaskStep(cfg, observations)
        # the SfM depth loss (COLMAP scenes; objective/sfm_depth.py): the dataparser's reader of the observations'
        # depths, called on the loss's first step; then each photo's used observations, on the device
        depths_of = (self.kwargs.get("metadata") or {}).get(SFM_DEPTHS_KEY)
        on = cfg.sfm_depth.weight > 0 and observations is not None and depths_of is not None
        self._sfm_depths_of = depths_of if on else None
        self._sfm_depths: list | None = None
        self._sfm_depth_cache: dict[int, tuple[Tensor, Tensor]] = {}
        self.mask_health = MaskHealth(cfg.mask.health)
        self._train_batch: dict | None = None  # this step's batch (set_train_batch), until the step ends
        self.image_names = [f"image {i}" for i in range(max(self.num_train_data, 1))]
        self.train_image_sizes: list[tuple[int, int]] | None = None  # (width, height) per training image (pipeline)
        self.test_photos: dict[str, str] = {}  # file name -> path of the run's test photos (set by the pipeline)
        # the training photos whose right half is held out of the loss and scored (eval/holdout.py), and the scorings
        self.holdout = holdout_indices(self.num_train_data, cfg.holdout.photos)
        self.holdout_best = BestStep(cfg.holdout.margin)
        self._train_photos = None  # () -> (cameras, images) of the training photos (get_training_callbacks)
        self.cap_decision: dict[str, Any] | None = None  # the "transients" rule's {step, share, cap}, once taken
        self._finished_at: int | None = None  # the step finish_training ended the run at

    # ------------------------------------------------------------------ latents (appearance/latents.py)
    def set_train_batch(self, batch: dict) -> None:
        """Called by WillagsPipeline before each training forward (nerfstudio's forward takes only the camera): the
        step's image, which feeds the latent (the VAE encoder, or the table's row) and the ground truth."""
        self._train_batch = batch

    def set_train_image_names(self, names: list[str]) -> None:
        """Training image file names, in dataset order (from the pipeline): the appearances users can pick."""
        self.image_names = list(names)

    def set_train_image_sizes(self, sizes: list[tuple[int, int]] | None) -> None:
        """(width, height) of each training image, in dataset order, as the training cameras give them (from the
        pipeline, once its image cache has made them final): a training forward takes its camera's size from here,
        on the host, instead of reading it from the camera (a wait for the GPU)."""
        self.train_image_sizes = None if sizes is None else [(int(w), int(h)) for w, h in sizes]

    def set_test_photos(self, paths: list[str]) -> None:
        """The run's test photos (from the pipeline): an appearance SPEC naming one is told that it is a test photo
        (no trained latent) and which ``photo:PATH`` fits it."""
        self.test_photos = {os.path.basename(str(p)): str(p) for p in paths}

    @property
    def render_latent(self) -> Tensor | None:
        """The chosen appearance [D] (viewer, ns-render, export), or None: $WILLAGS_APPEARANCE, else the mean."""
        return self.latents.render_latent

    @render_latent.setter
    def render_latent(self, z: Tensor | None) -> None:
        self.latents.render_latent = z

    def image_latents(self) -> tuple[Tensor, Tensor]:
        """(latents [num_train, D], known [num_train] bool) of the training images, detached (stored_latents)."""
        assert self.appearance_nets is not None
        return stored_latents(self.appearance_nets, self.train_latents, self.train_latent_seen)

    def latent_memo(self) -> tuple[Tensor, Tensor] | None:
        """The buffers (train_latents, train_latent_seen) that remember the training images' latents, written in
        place by the rank that trains an image (keeps_latent_memo); None when the model keeps no such memo."""
        nets = self.appearance_nets
        if nets is None or not keeps_latent_memo(nets):
            return None
        return self.train_latents, self.train_latent_seen

    def default_latent(self) -> Tensor:
        """The appearance used when none is chosen: the mean of the training images' latents."""
        assert self.appearance_nets is not None
        nets, lat, seen = self.appearance_nets, self.train_latents, self.train_latent_seen
        return self.latents.default(nets, lat, seen, lambda: mean_latent(self))

    def current_latent(self) -> Tensor:
        """The chosen appearance: `render_latent` if set, else $WILLAGS_APPEARANCE if set, else the default."""
        return self.latents.chosen(self.device, self.latent_from_spec, self.default_latent)

    @torch.no_grad()
    def encode_image(self, image: Tensor) -> Tensor:
        """Mean latent [D] of an image [H, W, 3] (uint8 or float in [0, 1]) through the VAE encoder."""
        assert self.appearance_nets is not None and self.appearance_nets.vae is not None, "needs latent.kind='vae'"
        mu, _ = self.appearance_nets.vae.encode(self._image_chw(image)[None])
        return mu[0]

    def _image_chw(self, image: Tensor) -> Tensor:
        return image_chw(image, self.device)  # [3, H, W]

    def forward_latent(self, camera: "Cameras") -> Tensor:
        """z [D] of a forward pass outside training: the camera's metadata, its training image, the chosen or the
        default appearance (AppearanceLatents.for_render)."""
        return self.latents.for_render(camera.metadata or {}, self.device, self.image_latents, self.current_latent)

    def step_latent(self, camera: "Cameras") -> TrainingLatent:
        """This training step's image's latent (the VAE's reparameterised sample, or the table's row)."""
        assert self.appearance_nets is not None
        nets, lat, seen = self.appearance_nets, self.train_latents, self.train_latent_seen
        return training_latent(nets, self._train_batch, camera.metadata or {}, self.device, lat, seen)

    # ------------------------------------------------------------------ the mask (mask/step.py)
    def update_teacher(self, step: int) -> None:
        """EMA: W_T <- tau W_T + (1 - tau) W_S after every optimiser step (none once the mask's start rule kept the
        mask off: nothing reads the teacher then)."""
        assert self.teacher is not None and self.appearance_nets is not None
        if self.mask_step.declined:
            return
        ema_update_(self.teacher, self.appearance_nets, self.config.mask.teacher.tau)

    def step_static_mask(self, outputs, gt_img: Tensor) -> StepMask:
        """This step's static mask (MaskStep.static_mask) of the image get_outputs rendered (`outputs`)."""
        idx = int(outputs.get("image_idx", -1))
        teacher_rgb = outputs.get("teacher_rgb")
        expected = outputs.get("expected_residual")
        return self.mask_step.static_mask(self.step, idx, gt_img, teacher_rgb, self.perceptual, self.device, expected)

    def static_support(self, idx: int, height: int, width: int) -> Tensor | None:
        """Training image `idx`'s SfM support grid (True = vouched static), or None (MaskStep.support)."""
        return self.mask_step.support(idx, height, width, self.device)

    @property
    def sfm_observations(self) -> list | None:
        """SfM observations per training image (COLMAP scenes): the mask's safeguard (MaskStep.observations)."""
        return self.mask_step.observations

    @sfm_observations.setter
    def sfm_observations(self, obs: list | None) -> None:
        self.mask_step.observations = obs

    @property
    def last_masks(self) -> PackedMasks:
        """Each image's last perceptual mask (MaskStep.masks: {image index: bool [H, W]}, stored packed), for looking
        at what the mask did."""
        return self.mask_step.masks

    # ------------------------------------------------------------------ what nerfstudio's exporter reads
    # splatfacto's names (`shs_0`, `shs_rest`, `colors`, `features_dc`, `features_rest`): with an appearance model the
    # Gaussians have no colour of their own, so they hand out the chosen appearance baked to SH or to view-averaged
    # colours by the colour path (appearance/color_path.py: exact where the colour model has an exact SH)
    @property
    def features_dc(self):
        """Splatfacto's name for the degree-0 SH parameter; with the paper's decoder (no SH parameters), the chosen
        appearance baked to SH."""
        return self.gauss_params["features_dc"] if "features_dc" in self.gauss_params else self.export_sh()[:, 0, :]

    @property
    def features_rest(self):
        return self.gauss_params["features_rest"] if "features_rest" in self.gauss_params else self.export_sh()[:, 1:]

    @property
    def colors(self):
        return super().colors if self.config.appearance == "sh" else self.baked_colors()  # type: ignore[misc]

    @property
    def shs_0(self):
        """What exporters write as f_dc: splatfacto's SH, or the chosen appearance baked to SH."""
        return super().shs_0 if self.config.appearance == "sh" else self.export_sh()[:, 0, :]  # type: ignore[misc]

    @property
    def shs_rest(self):
        return super().shs_rest if self.config.appearance == "sh" else self.export_sh()[:, 1:, :]  # type: ignore[misc]

    @torch.no_grad()
    def export_sh(self) -> Tensor:
        """SH [N, K, 3] of the chosen appearance for exporters (`ns-export gaussian-splat` writes f_dc + f_rest): the
        decoder fitted by SH of degree render_sh_degree (view-dependent, 3DGS layout); with render_sh_degree=-1, the
        decoder colour averaged over export_view_samples directions as degree 0."""
        deg = self.config.render_sh_degree
        if deg < 0:
            return RGB2SH(self.baked_colors())[:, None, :]
        return self.baked_sh(self.current_latent(), self.means, self.intrinsic_features, deg)

    @torch.no_grad()
    def baked_sh(self, z: Tensor, means: Tensor, f_s, degree: int, key: tuple | None = None, sh=None) -> Tensor:
        """SH coefficients [N, (degree + 1)**2, 3] reproducing the appearance's colour (ColorPath.baked_sh)."""
        sh = self.sh_coeffs() if sh is None else sh
        return self.color_path.baked_sh(self.student_nets(), z, means, f_s, degree, self.color_context(), sh, key)

    @torch.no_grad()
    def baked_colors(self, z: Tensor | None = None) -> Tensor:
        """View-independent colours [N, 3] for export: the appearance averaged over a Fibonacci sphere of views."""
        z = self.current_latent() if z is None else z.to(self.device)
        nets, k, ctx = self.student_nets(), max(1, self.config.export_view_samples), self.color_context()
        return self.color_path.baked_colors(nets, z, self.means, self.intrinsic_features, k, ctx, self.sh_coeffs())

    # ------------------------------------------------------------------ the Gaussians, parameter groups, checkpoints
    @property
    def intrinsic_features(self) -> Tensor | None:
        """f_s [N, Fs], or None when the configuration has none (modulated colours without a local residual)."""
        return self.gauss_params["features"] if "features" in self.gauss_params else None

    def get_gaussian_param_groups(self) -> dict[str, list[Parameter]]:
        return {name: [p] for name, p in self.gauss_params.items()}

    def get_param_groups(self) -> dict[str, list[Parameter]]:
        gps = self.get_gaussian_param_groups()
        if self.appearance_nets is not None:  # the embedding table apart (AppearanceNetworks.param_groups)
            gps.update(self.appearance_nets.param_groups())
        self.camera_optimizer.get_param_groups(param_groups=gps)
        return gps

    def load_state_dict(self, dict, **kwargs):  # type: ignore[override]
        # splatfacto resizes gauss_params to the checkpoint's point count; names are ours, so do it here
        self.step = 30000
        newp = dict["gauss_params.means"].shape[0]
        for param in self.gauss_params.values():  # resized in place: the optimisers hold these Parameter objects
            param.data = torch.zeros((newp,) + param.shape[1:], device=self.device)
        nn.Module.load_state_dict(self, dict, **kwargs)

    def latent_from_spec(self, spec: str) -> Tensor | None:
        """The latent of an appearance SPEC, for $WILLAGS_APPEARANCE (appearance_spec.latent_from_env: the SPEC
        parser sits above the rooms, so the latents reach it through the model)."""
        return latent_from_env(spec, self)

    # ------------------------------------------------------------------ colours (appearance/color_path.py)
    def sh_coeffs(self, gp: dict | None = None) -> Tensor | None:
        """SH coefficients [N, K, 3] of the Gaussians (`gp`: a cropped gauss_params view), or None without them."""
        return sh_coeffs(self.gauss_params if gp is None else gp)

    def student_nets(self) -> AppearanceNetworks:
        """The student's appearance networks, as the colour path reads them now: outside training, a colour model
        that anchors its per-Gaussian part (ColorModel.anchors_render: modulation.residual_latent "mean") is given
        the training latents' mean (`default_latent`, recomputed only when the latents change); while training, or
        once the colour model no longer anchors (its residual_latent set back to "own"), none."""
        nets = self.appearance_nets
        assert nets is not None
        color_model = nets.color_model
        anchored = not self.training and color_model.anchors_render()
        color_model.set_render_anchor(self.default_latent() if anchored else None)
        return nets

    def color_context(self) -> ColorContext:
        return ColorContext(self.bounds_lo, self.bounds_hi, self.step, active_sh_degree(self.config, self.step))

    def appearance_colors(
        self, z: Tensor, means: Tensor, f_s, cam_center: Tensor, nets=None, cacheable=False, sh=None, base=None
    ) -> GaussianColors:
        """Colours of Gaussians at `means` [N, 3] seen from `cam_center` [3] under latent z [D] (ColorPath.cached_colors),
        with what the colour model prepared (its penalty's input) and the SH colours they came from.

        `nets`: the student's networks by default. `sh` [N, K, 3]: the Gaussians' SH coefficients (for a colour model
        that reads them); default: all the model's Gaussians. `base` [N, 3]: their SH colours from cam_center,
        already evaluated (then sh is not used)."""
        nets = nets if nets is not None else self.student_nets()
        if sh is None and base is None and nets.color_model.reads_sh:
            sh = self.sh_coeffs()
        return self.color_path.cached_colors(nets, z, means, f_s, cam_center, self.color_context(), cacheable, sh, base)

    # ------------------------------------------------------------------ rendering: one forward pass, stage by stage
    def get_outputs(self, camera: Cameras) -> dict[str, Union[torch.Tensor, list]]:
        """One forward pass, top-down: the camera, this view's latent, the Gaussians' colours, the rasterisation, the
        background and the composite. On a step that renders the pseudo-GT, the EMA teacher joins each stage through
        the same functions: its latent, its colours (channels 3:6 of the one rasterisation, or their own), its
        background and composite. The step's intermediates travel in the returned dictionary."""
        if not isinstance(camera, Cameras):
            raise TypeError(f"WillagsModel.get_outputs expects nerfstudio Cameras, got {type(camera).__name__}")
        gp = self._gaussians_in_crop()
        if gp is None:  # the viewer's crop box holds no Gaussian
            return self.get_empty_outputs(int(camera.width.item()), int(camera.height.item()), self.background_color)
        view = self._view(camera)  # render/camera.py
        z, teacher, outputs = self._latents(camera)  # appearance/latents.py; the teacher's pass: mask/step.py
        colors, sh_degree, teacher_colors = self._colors(camera, gp, view, z, teacher, outputs)  # color_path.py
        render, alpha = self._rasterize(gp, colors, view, sh_degree)  # splats/gaussians.py
        teacher_raster = self._teacher_raster(teacher, render, alpha, gp, teacher_colors, view)
        outputs.update(self._level_maps(render, teacher, gp))  # mask/expected.py
        outputs.update(self._composite(view, render, alpha, z, teacher_raster, outputs))  # appearance/sky.py
        return outputs

    def _gaussians_in_crop(self) -> dict | None:
        """gauss_params (the same tensors) inside the viewer's crop box when rendering with one, else all of them;
        None when the box holds none."""
        if self.crop_box is None or self.training:
            return dict(self.gauss_params.items())
        crop_ids = self.crop_box.within(self.means).squeeze()
        if crop_ids.sum() == 0:
            return None
        return {k: v[crop_ids] for k, v in self.gauss_params.items()}

    def _view(self, camera: Cameras) -> View:
        """The camera at the render's scale (render/camera.py); while training (one camera at a time), after the
        camera optimiser."""
        if self.training and camera.shape[0] != 1:
            raise ValueError("willags trains on one camera at a time")
        c2w = self.camera_optimizer.apply_to_camera(camera) if self.training else camera.camera_to_worlds
        view = camera_view(camera, c2w, self._get_downscale_factor(), self.device, self._train_image_size(camera))
        self.last_size = (view.height, view.width)
        return view

    def _train_image_size(self, camera: Cameras) -> tuple[int, int] | None:
        """While training, the camera's (width, height) from the training images' sizes (set_train_image_sizes) by its
        training image index (metadata "cam_idx"); None elsewhere: an evaluation, viewer or render camera's index
        is no training index, and its size is read from the camera."""
        sizes = self.train_image_sizes
        if not self.training or sizes is None:
            return None
        idx = (camera.metadata or {}).get("cam_idx")
        if isinstance(idx, bool) or not isinstance(idx, numbers.Integral) or not 0 <= idx < len(sizes):
            return None
        return sizes[idx]

    def _latents(self, camera: Cameras) -> tuple[Tensor | None, TeacherPass | None, dict]:
        """(z [D] of this view, None for appearance "sh"; how this training step renders the pseudo-GT, None on a step
        without; the step's intermediates): the training image's latent (appearance/latents.py) with its index and
        the VAE's posterior and input, and on a step where the teacher renders, the teacher's latent (mask/step.py).
        Outside training z is no output: the viewer offers every output as an image."""
        if self.config.appearance == "sh":
            return None, None, {}
        if not self.training:
            return self.forward_latent(camera), None, {}
        lat = self.step_latent(camera)
        outputs: dict = {"image_idx": lat.image_idx, "latent": lat.z, "latent_mu": lat.mu}
        outputs.update({k: v for k, v in (("latent_logvar", lat.logvar), ("vae_in", lat.vae_in)) if v is not None})
        table = self.appearance_nets.embeddings
        if self.config.latent.prior_weight > 0 and table is not None:  # the prior's centre (objective/regularizers.py)
            outputs["latent_center"] = table.weight.detach().mean(0)
        teacher = self.mask_step.teacher_pass(self.step, lat.image_idx, self.teacher is not None)
        if teacher in ("fused", "second"):
            assert self.teacher is not None
            outputs["teacher_latent"] = teacher_latent(self.teacher, lat.vae_in, lat.image_idx)
        return lat.z, teacher, outputs

    def _colors(
        self, camera: Cameras, gp: dict, view: View, z: Tensor | None, teacher: TeacherPass | None, outputs: dict
    ) -> tuple[Tensor, int | None, Tensor | None]:
        """(the colours to rasterise, the SH degree the rasteriser evaluates them at or None for RGB, the teacher's
        colours for its own rasterisation or None): appearance "sh": the Gaussians' SH (splats/gaussians.sh_colors);
        training: the student's colours under this step's latent (`appearance_colors`; the colour model's penalty
        goes to `outputs`), the teacher's (appearance/color_path.teacher_colors) as channels 3:6 when fused; a fixed
        appearance (no gradient): its baked SH (ColorPath.frame_sh) from its second frame on."""
        cfg = self.config
        if z is None:
            colors, sh_degree = sh_colors(cfg, gp, self.step)
            return colors, sh_degree, None
        means, f_s, center = gp["means"], gp.get("features"), view.center
        if not self.training:
            fixed, degree = not torch.is_grad_enabled(), cfg.render_sh_degree
            if fixed and degree >= 0 and "appearance_latent" not in (camera.metadata or {}):
                baked = self.color_path.frame_sh(self.student_nets(), z, means, f_s, degree, self.color_context(), gp)
                if baked is not None:
                    return baked, degree, None
            return self.appearance_colors(z, means, f_s, center, cacheable=fixed, sh=sh_coeffs(gp)).rgb, None, None
        student = self.appearance_colors(z, means, f_s, center, sh=sh_coeffs(gp))
        assert self.appearance_nets is not None
        penalty = self.appearance_nets.color_model.penalty(student.prepared)
        if penalty is not None:
            outputs["color_penalty"] = penalty
        if teacher not in ("fused", "second"):
            return self._with_levels(student.rgb, teacher, gp), None, None
        assert self.teacher is not None
        sh_base = student.sh_base.detach() if student.sh_base is not None else None
        t_colors = teacher_colors(self.teacher, outputs["teacher_latent"], gp, center, self.color_context(), sh_base)
        if teacher == "fused":  # student RGB | teacher RGB (detached) in one rasterisation: channels 0:3 | 3:6
            return self._with_levels(torch.cat([student.rgb, t_colors], dim=-1), teacher, gp), None, None
        return self._with_levels(student.rgb, teacher, gp), None, t_colors

    @staticmethod
    def _with_levels(colors: Tensor, teacher: TeacherPass | None, gp: dict) -> Tensor:
        """`colors` and, on a step that computes a mask with the expected residual on, the two channels of the
        Gaussians' levels after them (mask/expected.level_channels)."""
        if teacher is None or LEVEL not in gp:
            return colors
        return torch.cat([colors, level_channels(gp[LEVEL])], dim=-1)

    @staticmethod
    def _level_maps(render: Tensor, teacher: TeacherPass | None, gp: dict) -> dict[str, Tensor]:
        """The expected residual E [H, W] and its probe Q [H, W] from the channels `_with_levels` appended (after the
        student's colours and, fused, the teacher's); empty on a step without them."""
        if teacher is None or LEVEL not in gp:
            return {}
        c = 6 if teacher == "fused" else 3
        return {"expected_residual": render[0, ..., c], "expected_probe": render[0, ..., c + 1]}

    def _render_mode(self) -> str:
        """gsplat's render mode: the expected depth after the colours while rendering (or when asked to train)."""
        asked = self.config.output_depth_during_training or self.sfm_depth_on
        return "RGB+ED" if (asked or not self.training) else "RGB"

    def _rasterize(self, gp: dict, colors: Tensor, view: View, sh_degree: int | None = None) -> tuple[Tensor, Tensor]:
        """The student's rasterisation (splats/gaussians.rasterize_gaussians): render [1, H, W, ch] (the colour
        channels, then the expected depth with RGB+ED) and alpha [1, H, W, 1]. Its `info` is what densification
        reads; while training, gsplat's strategy keeps the 2D means' gradients (step_pre_backward)."""
        absgrad = strategy_absgrad(self.strategy, self.config, gp["means"])  # |grad| only where the backend writes it
        args = (gp["means"], gp["quats"], gp["scales"], gp["opacities"], colors, view.viewmat, view.K)
        render, alpha, self.info = rasterize_gaussians(
            self.config, *args, view.width, view.height, self._render_mode(), sh_degree, absgrad
        )
        if self.training:
            self.strategy.step_pre_backward(
                self.gauss_params, self.optimizers, self.strategy_state, self.step, self.info
            )
        return render, alpha

    @torch.no_grad()
    def render_teacher(self, gp: dict, colors: Tensor, view: View) -> tuple[Tensor, Tensor]:
        """The teacher's own rasterisation (without mask.teacher.fused; the fused channels are the same image): its
        `colors` [N, 3] on the student's current Gaussians, detached, through the student's rasteriser function:
        (render [1, H, W, 3], alpha [1, H, W, 1])."""
        means, quats, scales, opacities = (gp[k].detach() for k in ("means", "quats", "scales", "opacities"))
        args = (means, quats, scales, opacities, colors, view.viewmat.detach(), view.K, view.width, view.height)
        render, alpha, _ = rasterize_gaussians(self.config, *args, "RGB", None, False)
        return render, alpha

    def _teacher_raster(
        self, teacher: TeacherPass | None, render: Tensor, alpha: Tensor, gp: dict, colors: Tensor | None, view: View
    ) -> tuple[Tensor, Tensor] | None:
        """The pseudo-GT's pixels and alpha before compositing: the fused channels 3:6, the teacher's own
        rasterisation of its `colors`, or the student's channels (no teacher); None on a step without."""
        if teacher == "second":
            assert colors is not None
            return self.render_teacher(gp, colors, view)
        if teacher is None:
            return None
        return (render[..., 3:6] if teacher == "fused" else render[..., :3]), alpha

    def _composite(
        self,
        view: View,
        render: Tensor,
        alpha: Tensor,
        z: Tensor | None,
        teacher_raster: tuple[Tensor, Tensor] | None,
        outputs: dict,
    ) -> dict:
        """nerfstudio's outputs of the rasterisation: rgb over what shows behind the Gaussians (appearance/sky.py
        through `_background`, and its `composite`), depth, accumulation, background; on a step that renders
        it, the pseudo-GT teacher_rgb (`teacher_raster` over the teacher's own background, or the student's without
        a teacher); while training, the photo at the render's resolution over the same background."""
        idx, nets = outputs.get("image_idx", -1), self.appearance_nets
        dirs = None
        if z is not None and nets is not None and nets.sky is not None:
            dirs = pixel_directions(view.c2w[0], view.K[0], view.width, view.height)
        fallback = self._get_background_color()  # random while training: one colour for student and teacher
        background = self._background(nets, z, dirs, fallback, idx)
        rgb = composite(render[..., :3], alpha, background)
        out: dict[str, Tensor | None] = {}
        if teacher_raster is not None:
            with torch.no_grad():
                z_t = outputs.get("teacher_latent")
                t_bg = background if z_t is None else self._background(self.teacher, z_t, dirs, fallback, idx)
                out["teacher_rgb"] = composite(*teacher_raster, t_bg).squeeze(0)
        depth = None
        if self._render_mode() == "RGB+ED":
            depth = render[..., -1:]  # gsplat appends expected depth after the colour channels
            depth = torch.where(alpha > 0, depth, depth.detach().max()).squeeze(0)
        if background.dim() == 1 and not self.training:
            background = background.expand(view.height, view.width, 3)
        elif background.dim() == 4:  # the sky: [1, H, W, 3]
            background = background.squeeze(0)
        out.update({"rgb": rgb.squeeze(0), "depth": depth, "accumulation": alpha.squeeze(0), "background": background})
        if self.training and self._train_batch is not None:  # the ground truth, once per step (metrics and loss)
            out["gt_rgb"] = self.composite_with_background(self.get_gt_img(self._train_batch["image"]), background)
        return out

    def _background(self, nets, z: Tensor | None, dirs: Tensor | None, fallback: Tensor, idx: int = -1) -> Tensor:
        """What shows behind the Gaussians rendered with `nets` (appearance/sky.py's `background`): their sky under z,
        only above training image `idx`'s skyline while training with sky.region "open"; `fallback` without a sky."""
        regions = self.open_regions if self.training else None
        return background(nets.sky if nets is not None else None, z, dirs, fallback, regions, idx)

    # ------------------------------------------------------------------ losses / metrics
    def _gt_image(self, outputs, batch) -> Tensor:
        """The ground truth [H, W, 3] of `batch` (float, at the render's resolution, composited on its background):
        what get_outputs made of it when it is this step's training batch (set_train_batch), else made here."""
        if "gt_rgb" in outputs and batch is self._train_batch:
            return outputs["gt_rgb"]
        return self.composite_with_background(self.get_gt_img(batch["image"]), outputs["background"])

    def get_metrics_dict(self, outputs, batch) -> dict[str, torch.Tensor]:
        """splatfacto's training metrics, with the PSNR as a function: torchmetrics' module updates and resets its
        state on every call (host work each step, for a number the trainer logs one step in ten). Same value."""
        pred, gt = outputs["rgb"], self._gt_image(outputs, batch)
        metrics: dict = {"psnr": -10.0 * torch.log10(F.mse_loss(pred.detach(), gt)), "gaussian_count": self.num_points}
        if self.config.color_corrected_metrics:
            metrics["cc_psnr"] = self.psnr(color_correct(pred, gt), gt)
        self.camera_optimizer.get_metrics_dict(metrics)
        if self.training and "latent" in outputs:
            metrics["latent_norm"] = outputs["latent"].detach().norm()
        return metrics

    def get_loss_dict(self, outputs, batch, metrics_dict=None) -> dict[str, torch.Tensor]:
        cfg = self.config
        gt_img = self._gt_image(outputs, batch)
        pred_img = outputs["rgb"]
        step_mask = self.step_static_mask(outputs, gt_img) if self.training else StepMask(None, None, None)
        mask = step_mask.mask
        if "mask" in batch:  # user-provided masks (nerfstudio convention) combine with ours
            user = self._downscale_if_required(batch["mask"]).to(self.device)[..., 0].float()
            mask = user if mask is None else mask * user
        pred_b, gt_b = pred_img.permute(2, 0, 1)[None], gt_img.permute(2, 0, 1)[None]
        loss_mask = self._holdout_mask(batch, mask, gt_img)
        mask_b = None if loss_mask is None else loss_mask[None]
        loss_dict = {"main_loss": reconstruction_loss(pred_b, gt_b, mask_b, ssim_lambda=cfg.ssim_lambda)}
        if self.training and self.sfm_depth_on:
            loss_dict.update(self._sfm_depth_term(outputs, batch, metrics_dict))
        if "expected_probe" in outputs and "teacher_rgb" in outputs:  # 0 in value: fits the levels (mask/expected.py)
            r = colour_residual(gt_img, outputs["teacher_rgb"])
            loss_dict[LEVEL] = level_loss(outputs["expected_residual"], outputs["expected_probe"], r)
        if mask is not None and metrics_dict is not None:
            metrics_dict["masked_fraction"] = 1.0 - mask.mean().detach()
            if step_mask.rejected is not None:
                metrics_dict["mask_rejected"] = step_mask.rejected
            if self.training and "psnr" in metrics_dict:
                # compared within one resolution and between opacity resets: both move the PSNR by themselves
                resets = opacity_reset_period(self.strategy)
                regime = (self._get_downscale_factor(), self.step // resets if resets else 0)
                warning = self.mask_health.observe(
                    self.step, metrics_dict["masked_fraction"], metrics_dict["psnr"], regime
                )
                if warning is not None:
                    CONSOLE.log(warning)

        # the VAE term, the sky's alpha penalty, the local residual's penalty, the scale penalty (objective/regularizers.py)
        vae = self.appearance_nets.vae if self.appearance_nets is not None else None
        args = (
            cfg,
            vae,
            outputs,
            gt_img,
            loss_mask,
            self.scales,
            self.opacities,
            self.mcmc_on,
            self.step,
            self.training,
        )
        terms, term_metrics, recon = regularization_terms(*args)
        loss_dict.update(terms)
        if metrics_dict is not None:
            metrics_dict.update(term_metrics)
        if self.training:
            self.camera_optimizer.get_loss_dict(loss_dict)
            if cfg.log_images_every > 0 and self.step % cfg.log_images_every == 0:
                log_step_images(self.step, outputs, gt_img, mask, step_mask.distance, recon)
        return loss_dict

    @property
    def sfm_depth_on(self) -> bool:
        """Whether training adds the SfM depth loss: a weight above 0 on a scene with SfM observations and depths."""
        return self._sfm_depths_of is not None

    def _sfm_depth_term(self, outputs, batch, metrics_dict) -> dict[str, Tensor]:
        """{"sfm_depth": weight x the SfM depth loss} of this step's training photo (objective/sfm_depth.py), its
        observations and depths moved to the device once per photo; empty for a photo without any. The depths are
        read on the first call; a points file that cannot be read turns the loss off with one line."""
        idx = int(batch.get("image_idx", -1))
        assert self._sfm_depths_of is not None
        if self._sfm_depths is None:
            try:
                self._sfm_depths = self._sfm_depths_of()
            except Exception as e:  # the run goes on without the loss, as the mask does without its tracks
                CONSOLE.log(
                    f"willags: the SfM points' depths are unreadable ({e!r}): training without the SfM depth loss"
                )
                self._sfm_depths_of = None
                return {}
        observations, depths = self.sfm_observations, self._sfm_depths
        if observations is None or not 0 <= idx < min(len(observations), len(depths)):
            return {}
        if idx not in self._sfm_depth_cache:
            obs = torch.as_tensor(observations[idx], dtype=torch.float32).reshape(-1, 3)
            target = torch.as_tensor(depths[idx], dtype=torch.float32).reshape(-1)
            if obs.shape[0] != target.shape[0]:
                raise ValueError(
                    f"willags: training image {idx} has {obs.shape[0]} SfM observations but {target.shape[0]} depths"
                )
            uv, target = select_observations(obs, target, self.config.sfm_depth)
            self._sfm_depth_cache[idx] = (uv.to(self.device), target.to(self.device))
        uv, target = self._sfm_depth_cache[idx]
        if uv.shape[0] == 0:
            return {}
        loss, used = sfm_depth_loss(outputs["depth"], outputs["accumulation"], uv, target, self.config.sfm_depth)
        if metrics_dict is not None:
            metrics_dict["sfm_depth_used"] = used
        return {"sfm_depth": self.config.sfm_depth.weight * loss}

    def _holdout_mask(self, batch, mask: Tensor | None, gt_img: Tensor) -> Tensor | None:
        """The step's loss mask: `mask` (transient and user masks), times the left half when the step's training
        photo lends its right half to the held-out score (eval/holdout.py)."""
        if not self.training or not self.holdout or int(batch.get("image_idx", -1)) not in self.holdout:
            return mask
        left = left_half_weight(gt_img.shape[0], gt_img.shape[1], gt_img.device)
        return left if mask is None else mask * left

    def get_image_metrics_and_images(self, outputs, batch):
        gt_rgb = self.composite_with_background(self.get_gt_img(batch["image"]), outputs["background"])
        metrics = image_metrics(gt_rgb, outputs["rgb"], self.psnr, self.ssim, self.lpips_metric())
        return metrics, {"img": torch.cat([gt_rgb, outputs["rgb"]], dim=1)}

    def lpips_metric(self):
        """torchmetrics LPIPS when AlexNet's ImageNet weights are on disk; else None with a one-line notice."""
        if self._lpips is None and self._lpips_status is None:
            self._lpips, self._lpips_status = make_lpips(self.device)
        return self._lpips

    # ------------------------------------------------------------------ callbacks
    def get_training_callbacks(
        self, training_callback_attributes: TrainingCallbackAttributes
    ) -> list[TrainingCallback]:
        cbs = super().get_training_callbacks(training_callback_attributes)
        if self.teacher is not None:
            cbs.append(TrainingCallback([TrainingCallbackLocation.AFTER_TRAIN_ITERATION], self.update_teacher))
        cbs.append(TrainingCallback([TrainingCallbackLocation.AFTER_TRAIN_ITERATION], self.end_step))
        pipeline = training_callback_attributes.pipeline
        if pipeline is not None:
            dm = pipeline.datamanager
            self._train_photos = lambda: (dm.train_dataset.cameras, [d["image"] for d in dm.cached_train])
            if self.holdout:
                cbs.append(TrainingCallback([TrainingCallbackLocation.AFTER_TRAIN_ITERATION], self.score_holdout))
            if isinstance(self.strategy, McmcDensification) and self.config.mcmc.cap_rule == "transients":
                cbs.append(TrainingCallback([TrainingCallbackLocation.AFTER_TRAIN_ITERATION], self.decide_cap))
            mask = self.config.mask
            if self.appearance_nets is not None and mask.enabled and mask.start_rule == "transients":
                cbs.append(TrainingCallback([TrainingCallbackLocation.AFTER_TRAIN_ITERATION], self.decide_mask))
        return cbs

    @property
    def mask_decision(self) -> dict[str, Any] | None:
        """The mask's start rule's {step, share, start}, once taken (MaskStep.start_decision)."""
        return self.mask_step.start_decision

    def decide_mask(self, step: int) -> None:
        """The mask's "transients" start rule (mask/rule.mask_start) after the last step before mask.warmup_steps:
        the training photos' residual-blob share, measured on their renders with their own latents
        (eval/protocol.training_outlier_share), starts the mask or keeps it off for the rest of the run. A
        data-parallel run starts it: each rank holds only its share of the photos."""
        if self._train_photos is None or self.mask_decision is not None or step < self.config.mask.warmup_steps - 1:
            return
        if _several_ranks():
            self.mask_step.start_decision = {"step": step, "share": None, "start": True}
            CONSOLE.log("willags: the mask's start rule does not measure a data-parallel run: the mask starts")
            return
        cameras, images = self._train_photos()
        share = training_outlier_share(self, cameras, images)
        start, reason = mask_start(share, self.config.mask)
        self.mask_step.start_decision = {"step": step, "share": share, "start": start}
        CONSOLE.log(f"willags: step {step + 1:,}: {reason}")

    def decide_cap(self, step: int) -> None:
        """The "transients" cap rule (splats/mcmc.transient_cap) at the first step whose Gaussians fill MCMC's cap while
        it still grows them: the training photos' transient share, measured on their renders with their own latents
        (eval/protocol.training_outlier_share), sets the cap for the rest of the run. A data-parallel run keeps its
        cap: each rank holds only its share of the photos."""
        strategy = self.strategy
        if self._train_photos is None or self.cap_decision is not None or self.num_points < strategy.cap_max:
            return
        if step >= strategy.refine_stop_iter:  # the growth has ended: nothing left to decide
            return
        if _several_ranks():
            self.cap_decision = {"step": step, "share": None, "cap": int(strategy.cap_max)}
            CONSOLE.log(
                "willags: the transients cap rule does not measure a data-parallel run: "
                f"at most {strategy.cap_max:,} Gaussians"
            )
            return
        cameras, images = self._train_photos()
        share = training_outlier_share(self, cameras, images)
        cap, reason = transient_cap(share, self.config.mcmc)
        strategy.cap_max = cap
        self.cap_decision = {"step": step, "share": share, "cap": cap}
        CONSOLE.log(f"willags: step {step:,}: {reason}")

    def score_holdout(self, step: int, last_step: int = -1) -> None:
        """On a scoring step (eval/holdout.is_scoring_step; the last one is `finish_training`'s), the held-out right
        halves' PSNR; a new best keeps a copy of the model (its Gaussians, networks and latents)."""
        if not self.holdout or self._train_photos is None or not is_scoring_step(step, self.config.holdout, last_step):
            return
        if self.holdout_best.history and self.holdout_best.history[-1][0] == step:
            return
        cameras, images = self._train_photos()
        latents = self.image_latents()[0] if self.appearance_nets is not None else None
        score = holdout_psnr(self, cameras, images, self.holdout, latents)
        self.holdout_best.observe(step, score, lambda: copy_state(self))

    def finish_training(self, step: int) -> str | None:
        """Called by the trainer after the last step, before the last checkpoint: with held-out halves, score the
        last step and end with the best step's model when the last scores worse by more than holdout.margin. Returns
        what it did, in one line (None without held-out halves)."""
        if not self.holdout or self._train_photos is None or self._finished_at == step:
            return None
        self._finished_at = step
        self.score_holdout(step, last_step=step)
        best = self.holdout_best
        if not best.history:
            return f"willags: the held-out right halves were not scored (the run ended before step {self.config.holdout.start})"
        copy = best.to_restore()
        last_step, last = best.history[-1]
        line = (
            f"willags: the held-out right halves of {len(self.holdout)} training photos score {last:.2f} dB at step "
            f"{last_step}, best {best.best_psnr:.2f} at step {best.best_step}"
        )
        if copy is None:
            return line + "; the run ends with its last step"
        self._restore(copy)
        best.copy = None
        return line + f"; the run ends with step {best.best_step}'s model"

    def _restore(self, state: dict[str, Tensor]) -> None:
        """Put a copy back (eval/holdout.restore_state) and start the densification's statistics again."""
        restore_state(self, self.gauss_params, getattr(self, "optimizers", None) or {}, state)
        self.strategy_state = self.strategy.initialize_state(scene_scale=1.0)

    def step_post_backward(self, step):
        """After the optimiser's step: gsplat's densification (splatfacto's), or MCMC's relocation, growth and
        position noise, whose noise follows the means' current learning rate."""
        if not isinstance(self.strategy, McmcDensification):
            return super().step_post_backward(step)
        assert step == self.step
        lr = self.optimizers["means"].param_groups[0]["lr"]
        self.strategy.step_post_backward(self.gauss_params, self.optimizers, self.strategy_state, step, self.info, lr)

    def end_step(self, step: int) -> None:
        self._train_batch = None

    # ------------------------------------------------------------------ checkpoints carry the mask provenance
    def get_extra_state(self):
        """Saved as `_extra_state` in every checkpoint: which VGG weights made the transient masks."""
        src = self.perceptual.source if self.perceptual is not None else None
        state = {"perceptual_source": src or self.__dict__.get("loaded_perceptual_source")}
        if self.holdout_best.history:
            state["holdout"] = self.holdout_best.summary()
        if self.cap_decision is not None:
            state["cap_decision"] = dict(self.cap_decision)
        if self.mask_decision is not None:
            state["mask_decision"] = dict(self.mask_decision)
        return state

    def set_extra_state(self, state) -> None:
        self.loaded_perceptual_source = (state or {}).get("perceptual_source")
        decision = (state or {}).get("cap_decision")
        if decision is not None and isinstance(self.strategy, McmcDensification):  # a resumed run keeps its cap
            self.cap_decision = dict(decision)
            self.strategy.cap_max = int(decision["cap"])
        started = (state or {}).get("mask_decision")
        if started is not None:  # a resumed run keeps its mask on or off
            self.mask_step.start_decision = dict(started)
