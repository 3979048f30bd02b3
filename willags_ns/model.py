"""WillagsModel: splatfacto's Gaussians with a latent-conditioned appearance field, an EMA teacher and a
perceptual transient mask (WilLaGS). Runs on any device; rasterises through `willags_ns.render.rasterize`.

Per training step (the pipeline hands the model the training image first):

    image --table row or VAE encoder--> z [D]                           appearance/latents.py
    z, Gaussians, camera --> colours [N, 3]                             appearance/color_path.py, networks.py
    colours (+ the EMA teacher's, fused) --rasterize--> render          splats/gaussians.py, render/
    VGG16(GT) vs VGG16(teacher render) --> D; static mask = D < 0.85    mask/step.py
    loss = 0.8 L1 + 0.2 D-SSIM on static pixels + the regularisers      objective/losses.py, objective/regularizers.py

The step's intermediates travel in `get_outputs`' dictionary (nerfstudio's habit) to `get_metrics_dict` and
`get_loss_dict`: the image index, the latent (and the VAE's posterior and input), the modulation's residual, the
teacher's latent and render, the ground truth at the render's resolution. This file is the wiring (parameter groups,
get_outputs, losses, callbacks; the settings: config.py); docs/architecture.md maps the rooms. The class subclasses
SplatfactoModel because nerfstudio's exporter and viewer check `isinstance(model, SplatfactoModel)`; it reuses
splatfacto's densification (gsplat's DefaultStrategy), resolution schedule and metrics, and replaces what hard-codes
CUDA (`populate_modules`, `get_outputs`) or downloads weights (LPIPS). `appearance="sh"` turns it into plain 3DGS
(splatfacto's SH colours, no appearance model, no mask): the CPU stand-in for splatfacto in benchmarks
(method `willags-3dgs`).
"""

from dataclasses import dataclass, field
from typing import Union

import torch
import torch.nn.functional as F
from nerfstudio.cameras.cameras import Cameras
from nerfstudio.data.scene_box import OrientedBox
from nerfstudio.engine.callbacks import TrainingCallback, TrainingCallbackAttributes, TrainingCallbackLocation
from nerfstudio.model_components.lib_bilagrid import color_correct
from nerfstudio.models.splatfacto import SplatfactoModel
from nerfstudio.utils.rich_utils import CONSOLE
from torch import Tensor, nn
from torch.nn import Parameter

from willags_ns.appearance.color_path import ColorContext, ColorPath, GaussianColors, teacher_colors
from willags_ns.appearance.latents import AppearanceLatents, LatentFace
from willags_ns.appearance.networks import AppearanceNetworks
from willags_ns.appearance.sky import background, composite, pixel_directions, sky_for_scene
from willags_ns.appearance.triplane import robust_bounds
from willags_ns.config import WillagsSettings, check_settings
from willags_ns.data.sfm_tracks import SFM_OBSERVATIONS_KEY
from willags_ns.eval.image_metrics import image_metrics
from willags_ns.eval.lpips import make_lpips
from willags_ns.mask.health import MaskHealth
from willags_ns.mask.step import (
    MaskFace,
    MaskStep,
    StepMask,
    fused_teacher_rgb,
    log_step_images,
    mask_networks,
    teacher_latent,
)
from willags_ns.mask.transient import PerceptualFeatures
from willags_ns.objective.losses import reconstruction_loss
from willags_ns.objective.regularizers import regularization_terms
from willags_ns.render.camera import intrinsics_at, viewmat_from_c2w
from willags_ns.splats.export import SplatExport
from willags_ns.splats.gaussians import (
    active_sh_degree,
    densification_strategy,
    initial_gauss_params,
    initial_points,
    rasterize_gaussians,
    sh_coeffs,
    sh_colors,
    strategy_absgrad,
)

__all__ = ["WillagsModel", "WillagsModelConfig"]


@dataclass
class WillagsModelConfig(WillagsSettings):
    """WilLaGS: splatfacto + appearance latent + colour transform (or tri-plane field and decoder) + EMA teacher +
    perceptual transient mask + sky. Every field and its group: willags_ns/config.py; the defaults are `willags`."""

    _target: type = field(default_factory=lambda: WillagsModel)


class WillagsModel(SplatExport, LatentFace, MaskFace, SplatfactoModel):
    """WilLaGS on top of splatfacto. See the module docstring for the per-step data flow. Three mixins carry public
    faces: the exporter's names (`shs_0`, `shs_rest`, `colors`, `export_sh`, ...: splats.export.SplatExport), the
    latent methods (`current_latent`, `render_latent`, `image_latents`, `encode_image`, ...:
    appearance/latents.LatentFace) and the mask's (`update_teacher`, `static_support`, `sfm_observations`, the
    teacher's second rasterisation, ...: mask.step.MaskFace)."""

    config: WillagsModelConfig
    # buffers registered in populate_modules (declared for type checkers: nn.Module.__getattr__ is untyped)
    train_latents: Tensor
    train_latent_seen: Tensor
    bounds_lo: Tensor
    bounds_hi: Tensor

    # ------------------------------------------------------------------ set-up
    def populate_modules(self):
        cfg = self.config
        check_settings(cfg)
        means, seed_rgb = initial_points(cfg, self.seed_points)
        distances, _ = self.k_nearest_sklearn(means, 3)
        avg_dist = torch.from_numpy(distances).mean(dim=-1, keepdim=True).clamp_min(1e-7)
        self.gauss_params = nn.ParameterDict(initial_gauss_params(cfg, means, seed_rgb, avg_dist))

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
        self.strategy = densification_strategy(cfg, self.num_train_data)
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
        self.mask_health = MaskHealth(cfg.mask.health)
        self._train_batch: dict | None = None  # this step's batch (set_train_batch), until the step ends
        self.image_names = [f"image {i}" for i in range(max(self.num_train_data, 1))]

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

    # ------------------------------------------------------------------ colours (appearance/color_path.py)
    def sh_coeffs(self, gp: dict | None = None) -> Tensor | None:
        """SH coefficients [N, K, 3] of the Gaussians (`gp`: a cropped gauss_params view), or None without them."""
        return sh_coeffs(self.gauss_params if gp is None else gp)

    def color_context(self) -> ColorContext:
        return ColorContext(self.bounds_lo, self.bounds_hi, self.step, active_sh_degree(self.config, self.step))

    def appearance_colors(
        self, z: Tensor, means: Tensor, f_s, cam_center: Tensor, nets=None, cacheable=False, sh=None, base=None
    ) -> GaussianColors:
        """Colours of Gaussians at `means` [N, 3] seen from `cam_center` [3] under latent z [D] (ColorPath.cached_colors),
        with the modulation's residual and the SH colours they came from.

        `nets`: the student's networks by default. `sh` [N, K, 3]: the Gaussians' SH coefficients
        (color_mode='modulated'); default: all the model's Gaussians. `base` [N, 3]: their SH colours from
        cam_center, already evaluated (then sh is not used)."""
        nets = nets if nets is not None else self.appearance_nets
        assert nets is not None
        if sh is None and base is None and nets.modulation is not None:
            sh = self.sh_coeffs()
        return self.color_path.cached_colors(nets, z, means, f_s, cam_center, self.color_context(), cacheable, sh, base)

    # ------------------------------------------------------------------ rendering
    def _rasterize(self, means, quats, scales, opacities, colors, viewmat, K, W, H, render_mode, sh_degree=None):
        absgrad = strategy_absgrad(self.strategy, self.config, means)  # |grad| only where the backend writes it
        args = (means, quats, scales, opacities, colors, viewmat, K, W, H, render_mode, sh_degree, absgrad)
        return rasterize_gaussians(self.config, *args)

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
        crop_ids = None
        if self.crop_box is not None and not self.training:
            crop_ids = self.crop_box.within(self.means).squeeze()
            if crop_ids.sum() == 0:
                w, h = int(camera.width.item()), int(camera.height.item())
                return self.get_empty_outputs(w, h, self.background_color)
        gp = {k: (v[crop_ids] if crop_ids is not None else v) for k, v in self.gauss_params.items()}

        viewmat = viewmat_from_c2w(c2w)
        K, W, H = intrinsics_at(camera, self._get_downscale_factor(), self.device)
        self.last_size = (H, W)
        render_mode = "RGB+ED" if (cfg.output_depth_during_training or not self.training) else "RGB"
        cam_center = c2w[0, :3, 3]

        # the Gaussians' colours: 3DGS SH, the training image's latent, or a chosen appearance
        outputs: dict[str, Union[Tensor, list]] = {}
        z = lat = student = None
        if cfg.appearance == "sh":
            colors, sh_degree = sh_colors(cfg, gp, self.step)
        elif self.training:
            lat = self.step_latent(camera)
            z = lat.z
            student = self.appearance_colors(z, gp["means"], gp.get("features"), cam_center, sh=sh_coeffs(gp))
            colors, sh_degree = student.rgb, None
            step_data = {"image_idx": lat.image_idx, "latent": z, "latent_mu": lat.mu, "latent_logvar": lat.logvar}
            step_data.update(vae_in=lat.vae_in, local_residual=student.residual)
            outputs.update({k: v for k, v in step_data.items() if v is not None})  # type: ignore[misc]
        else:  # a fixed appearance (no gradient) renders its baked SH (render_sh_degree) once it is cached
            z = self.forward_latent(camera)
            colors, fixed, sh_degree = None, not torch.is_grad_enabled(), cfg.render_sh_degree
            if fixed and sh_degree >= 0 and "appearance_latent" not in (camera.metadata or {}):
                ctx, f_s = self.color_context(), gp.get("features")
                colors = self.color_path.frame_sh(self.appearance_nets, z, gp["means"], f_s, sh_degree, ctx, gp)
            if colors is None:
                args = (z, gp["means"], gp.get("features"), cam_center)
                colors, sh_degree = self.appearance_colors(*args, cacheable=fixed, sh=sh_coeffs(gp)).rgb, None

        idx = lat.image_idx if lat is not None else -1
        teacher_needed = self.training and self.mask_step.teacher_needed(self.step, idx)
        fused = teacher_needed and cfg.mask.teacher.fused and self.teacher is not None
        sh_base = student.sh_base.detach() if student is not None and student.sh_base is not None else None
        z_t = None
        if fused:  # student RGB | teacher RGB (detached) in one rasterisation: channels 0:3 | 3:6
            assert self.teacher is not None and lat is not None
            with torch.no_grad():
                z_t = teacher_latent(self.teacher, lat.vae_in, idx)
            t_colors = teacher_colors(self.teacher, z_t, gp, cam_center, self.color_context(), sh_base)
            colors = torch.cat([colors, t_colors], dim=-1)
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
        fallback = self._get_background_color()  # random while training: one colour for student and teacher
        background = self._background(self.appearance_nets, z, dirs, fallback, idx)
        rgb = composite(render[..., :3], alpha, background)

        if fused:  # over the teacher's own sky, under the teacher's latent
            teacher_bg = self._background(self.teacher, z_t, dirs, fallback, idx)
            outputs["teacher_rgb"] = fused_teacher_rgb(render, alpha, teacher_bg)
        elif teacher_needed and self.teacher is None:  # teacher.enabled=False: the student's own render
            outputs["teacher_rgb"] = rgb.detach().squeeze(0)
        elif teacher_needed:
            assert lat is not None
            with torch.no_grad():
                z_t = teacher_latent(self.teacher, lat.vae_in, idx)
                teacher_bg = self._background(self.teacher, z_t, dirs, fallback, idx)
            view = (cam_center, viewmat, K, W, H)
            outputs["teacher_rgb"] = self.render_teacher(gp, z_t, *view, teacher_bg, sh_base)
        if z_t is not None:
            outputs["teacher_latent"] = z_t

        depth_im = None
        if render_mode == "RGB+ED":
            depth_im = render[..., -1:]  # gsplat appends expected depth after the colour channels
            depth_im = torch.where(alpha > 0, depth_im, depth_im.detach().max()).squeeze(0)
        if background.dim() == 1 and not self.training:
            background = background.expand(H, W, 3)
        elif background.dim() == 4:  # the sky: [1, H, W, 3]
            background = background.squeeze(0)
        outputs.update({"rgb": rgb.squeeze(0), "depth": depth_im, "accumulation": alpha.squeeze(0)})  # type: ignore[dict-item]
        outputs["background"] = background
        if self.training and self._train_batch is not None:  # the ground truth, once per step (metrics and loss)
            outputs["gt_rgb"] = self.composite_with_background(self.get_gt_img(self._train_batch["image"]), background)
        return outputs

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
        mask_b = None if mask is None else mask[None]
        loss_dict = {"main_loss": reconstruction_loss(pred_b, gt_b, mask_b, ssim_lambda=cfg.ssim_lambda)}
        if mask is not None and metrics_dict is not None:
            metrics_dict["masked_fraction"] = 1.0 - mask.mean().detach()
            if step_mask.rejected is not None:
                metrics_dict["mask_rejected"] = step_mask.rejected
            if self.training and "psnr" in metrics_dict:
                # compared within one resolution and between opacity resets: both move the PSNR by themselves
                regime = (self._get_downscale_factor(), self.step // self.strategy.reset_every)
                warning = self.mask_health.observe(
                    self.step, metrics_dict["masked_fraction"], metrics_dict["psnr"], regime
                )
                if warning is not None:
                    CONSOLE.log(warning)

        # the VAE term, the sky's alpha penalty, the local residual's penalty, the scale penalty (objective/regularizers.py)
        vae = self.appearance_nets.vae if self.appearance_nets is not None else None
        args = (cfg, vae, outputs, gt_img, mask, self.scales, self.step, self.training)
        terms, term_metrics, recon = regularization_terms(*args)
        loss_dict.update(terms)
        if metrics_dict is not None:
            metrics_dict.update(term_metrics)
        if self.training:
            self.camera_optimizer.get_loss_dict(loss_dict)
            if cfg.log_images_every > 0 and self.step % cfg.log_images_every == 0:
                log_step_images(self.step, outputs, gt_img, mask, step_mask.distance, recon)
        return loss_dict

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
        return cbs

    def end_step(self, step: int) -> None:
        self._train_batch = None

    # ------------------------------------------------------------------ checkpoints carry the mask provenance
    def get_extra_state(self):
        """Saved as `_extra_state` in every checkpoint: which VGG weights made the transient masks."""
        src = self.perceptual.source if self.perceptual is not None else None
        return {"perceptual_source": src or self.__dict__.get("loaded_perceptual_source")}

    def set_extra_state(self, state) -> None:
        self.loaded_perceptual_source = (state or {}).get("perceptual_source")
