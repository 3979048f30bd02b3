"""The transient mask of one training step: the EMA teacher's render, its perceptual distance to the photo, the
threshold, and the static-scene safeguard.

    teacher latent (teacher VAE mean of the photo, or its embedding row) --teacher colours--> teacher render
    (fused into the student's rasterisation as 3 extra channels, or a second one: `teacher_render`)
    D = perceptual_error(VGG(photo), VGG(teacher render))                 [H, W]   (willags_ns/transient.py)
    transient = D > threshold(step)   (rejected when it would drop more than mask.max_masked_fraction of the image)
    static = ~transient | SfM support (pixels near points many photos saw; willags_ns/static_support.py)

:func:`mask_networks` builds the teacher and the VGG features. :class:`MaskStep` holds the per-image state (each
image's last mask, its visit count, its support grid and the scene's SfM observations) and reads the model's config;
the teacher networks, the VGG features, the step and the step's scratch record arrive as arguments.
"""

from collections.abc import Callable
from typing import cast

import torch
import torch.nn.functional as F
from torch import Tensor

from willags_ns.appearance.color_path import sh_coeffs
from willags_ns.appearance.networks import AppearanceNetworks
from willags_ns.static_support import apply_support, support_map
from willags_ns.teacher import make_teacher
from willags_ns.transient import PerceptualFeatures, image_distance, mask_active, mask_threshold, transient_mask


def mask_networks(cfg, nets: AppearanceNetworks) -> tuple[AppearanceNetworks | None, PerceptualFeatures | None]:
    """(EMA teacher, VGG16 features) of the mask for the student's networks `nets` (cfg: the model's config): the
    teacher a frozen copy of `nets` (mask.enabled with mask.teacher.enabled), the features per cfg.mask
    (mask.enabled); None where off."""
    m = cfg.mask
    if not m.enabled:
        return None, None
    teacher = cast(AppearanceNetworks, make_teacher(nets)) if m.teacher.enabled else None
    return teacher, PerceptualFeatures(weights=m.vgg_weights, path=m.vgg_weights_path, max_resolution=m.max_resolution)


class MaskStep:
    """Which steps render the teacher, and the static mask [H, W] those steps (and the ones between) supervise."""

    def __init__(self, cfg, observations: list | None):
        self.cfg = cfg
        """The model's config (WillagsModelConfig: appearance and the mask group), read at every call so edits
        after construction count."""
        self.observations = observations
        """SfM observations per training image (COLMAP scenes; None elsewhere): the safeguard's input."""
        self.masks: dict[int, Tensor] = {}
        """Each image's last perceptual mask (True = static), before the support."""
        self.visits: dict[int, int] = {}
        self.support_cache: dict[int, Tensor | None] = {}

    def active(self, step: int) -> bool:
        cfg = self.cfg
        return cfg.appearance == "willags" and cfg.mask.enabled and mask_active(step, cfg.mask.warmup_steps)

    def teacher_needed(self, step: int, idx: int) -> bool:
        """Whether this training step renders the teacher for image `idx` (counts the visit): on every mask.every-th
        visit of the image, and whenever it has no mask yet."""
        if not self.active(step):
            return False
        visits = self.visits.get(idx, 0)
        self.visits[idx] = visits + 1
        return idx not in self.masks or visits % max(1, self.cfg.mask.every) == 0

    def static_mask(
        self,
        step: int,
        idx: int,
        gt_img: Tensor,
        teacher_rgb: Tensor | None,
        perceptual: PerceptualFeatures | None,
        record: dict,
        device,
    ) -> Tensor | None:
        """[H, W] float mask of static pixels (1 = supervised) of image `idx`, or None when masking is off / warming
        up / the image has no mask yet. With this step's teacher render, a new mask (D and the rejection flag go
        into `record`); without, the image's last one at the current resolution."""
        cfg = self.cfg.mask
        if not self.active(step):
            return None
        H, W = gt_img.shape[:2]
        if teacher_rgb is not None:
            assert perceptual is not None
            d = image_distance(perceptual, gt_img, teacher_rgb)  # [H, W]
            record["D"] = d
            thr = mask_threshold(step, cfg.threshold, cfg.warmup_steps, cfg.ramp_steps)
            transient, rejected = transient_mask(d, thr, cfg.threshold_rule, cfg.robust_k, cfg.max_masked_fraction)
            mask = ~transient  # a rejected mask supervises every pixel rather than none
            record["mask_rejected"] = rejected.float()  # a device tensor: no wait for VGG here
            self.masks[idx] = mask
        elif idx in self.masks:
            mask = self.masks[idx]
        else:
            return None
        if mask.shape != (H, W):  # resolution schedule moved on since the mask was cached
            mask = F.interpolate(mask[None, None].float(), size=(H, W), mode="nearest")[0, 0] > 0.5
        return apply_support(mask, self.support(idx, H, W, device)).float()

    def support(self, idx: int, height: int, width: int, device) -> Tensor | None:
        """Training image `idx`'s SfM support grid (True = vouched static; willags_ns/static_support.py), or None
        (safeguard off, no tracks in the scene). Built once per image on the device; the grid's aspect follows the
        image's, so any resolution of the schedule maps onto it."""
        cfg = self.cfg.mask.safeguard
        obs = self.observations
        if not cfg.enabled or obs is None or not 0 <= idx < len(obs):
            return None
        if idx not in self.support_cache:
            self.support_cache[idx] = support_map(obs[idx], width, height, cfg).to(device)
        return self.support_cache[idx]


@torch.no_grad()
def teacher_colors(teacher: AppearanceNetworks, gp, cam_center: Tensor, record: dict, colors: Callable) -> Tensor:
    """Per-Gaussian RGB [N, 3] of the EMA teacher networks for this step's image (no grad), through `colors` (the
    model's appearance_colors). The teacher's latent goes into `record` ("teacher_z": its sky needs it); the
    student's SH colours of this step, when recorded, are reused (same Gaussians, same camera)."""
    if teacher.vae is not None:
        mu, _ = teacher.vae.encode(record["vae_in"][None])
        z = mu[0]
    else:
        z = teacher.embeddings.weight[int(record["image_idx"])]  # type: ignore[union-attr]
    record["teacher_z"] = z
    f_s = gp["features"].detach() if "features" in gp else None
    base = record.pop("sh_base", None)
    sh = None
    if base is None:
        sh = sh_coeffs(gp)
        sh = sh.detach() if sh is not None else None
    return colors(z, gp["means"].detach(), f_s, cam_center, nets=teacher, sh=sh, base=base)


def fused_teacher_rgb(render: Tensor, alpha: Tensor, background: Tensor) -> Tensor:
    """Pseudo-GT [H, W, 3] from the fused rasterisation (mask.teacher.fused): the teacher's channels 3:6 of
    `render` [1, H, W, >=6] composited on `background` (the teacher's sky, or the student's colour), all detached."""
    teacher = render[..., 3:6].detach() + (1 - alpha.detach()) * background.detach()
    return torch.clamp(teacher, 0.0, 1.0).squeeze(0)


@torch.no_grad()
def teacher_render(colors: Tensor, gp, viewmat: Tensor, K, W: int, H: int, background, rasterize) -> Tensor:
    """Pseudo-GT [H, W, 3]: the teacher's `colors` on the student's current Gaussians (detached), rasterised by
    `rasterize` (the model's) and composited on `background`: the unfused path (without mask.teacher.fused)."""
    render, alpha, _ = rasterize(
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


def log_step_images(step: int, outputs: dict, gt_img: Tensor, mask: Tensor | None, record: dict) -> None:
    """Tensorboard pictures of a training step: photo | render, the teacher's render, the perceptual distance D,
    the static mask, and the VAE's reconstruction of the photo (each when this step made one)."""
    from nerfstudio.utils import writer

    writer.put_image("train/render_vs_gt", torch.cat([gt_img, outputs["rgb"].detach()], dim=1), step)
    if "teacher_rgb" in outputs:
        writer.put_image("train/teacher_render", outputs["teacher_rgb"], step)
    if "D" in record:
        d = record["D"]
        writer.put_image("train/perceptual_D", (d / d.max().clamp_min(1e-6))[..., None].expand(-1, -1, 3), step)
    if mask is not None:
        writer.put_image("train/static_mask", mask[..., None].expand(-1, -1, 3), step)
    if "vae_recon_img" in record:
        writer.put_image("train/vae_reconstruction", record["vae_recon_img"][0].permute(1, 2, 0), step)
