"""The transient mask of one training step: whose render is the pseudo-GT, the EMA teacher's latent, the perceptual
distance to the photo, the threshold, and the static-scene safeguard.

    which steps render the teacher, and how (fused, a second rasterisation, the student's own)  MaskStep.teacher_pass
    teacher latent (teacher VAE mean of the photo, or its embedding row)                       teacher_latent
    teacher colours, rasterisation, background and composite: the student's functions, in the model's forward
        (appearance/color_path.teacher_colors, splats/gaussians.py, appearance/sky.py)
    transient = the mask's one rule on photo and teacher render (willags_ns/mask/rule.compare_to_teacher: VGG
        distance or colour residual against the step's bar; rejected when it would drop more than
        mask.max_masked_fraction of the image)
    static = ~transient | SfM support (pixels near points many photos saw; willags_ns/mask/static_support.py)

:func:`mask_networks` builds the teacher and the VGG features. :class:`MaskStep` holds the per-image state (each
image's last mask at one bit a pixel, its visit count, its support grid and the scene's SfM observations) and reads
the model's config; the teacher networks, the VGG features and the step arrive as arguments.
"""

from typing import Literal, NamedTuple, cast

import torch
import torch.nn.functional as F
from torch import Tensor

from willags_ns.appearance.networks import AppearanceNetworks
from willags_ns.mask.rule import compare_to_teacher, mask_active
from willags_ns.mask.static_support import apply_support, support_map
from willags_ns.mask.store import PackedMasks
from willags_ns.mask.teacher import make_teacher
from willags_ns.mask.transient import PerceptualFeatures


def mask_networks(cfg, nets: AppearanceNetworks) -> tuple[AppearanceNetworks | None, PerceptualFeatures | None]:
    """(EMA teacher, VGG16 features) of the mask for the student's networks `nets` (cfg: the model's config): the
    teacher a frozen copy of `nets` (mask.enabled with mask.teacher.enabled), the features per cfg.mask
    (mask.enabled); None where off."""
    m = cfg.mask
    if not m.enabled:
        return None, None
    teacher = cast(AppearanceNetworks, make_teacher(nets)) if m.teacher.enabled else None
    return teacher, PerceptualFeatures(weights=m.vgg_weights, path=m.vgg_weights_path, max_resolution=m.max_resolution)


class StepMask(NamedTuple):
    """A training step's static mask and what made it."""

    mask: Tensor | None
    """[H, W] float, 1 = supervised; None when masking is off, warming up, or the image has no mask yet."""
    distance: Tensor | None
    """[H, W] the perceptual distance D of this step's teacher render, None on a step that reused a mask."""
    rejected: Tensor | None
    """0-d float, 1 when the new mask would drop more than mask.max_masked_fraction (then every pixel is
    supervised), None on a step that reused a mask."""


TeacherPass = Literal["fused", "second", "student"]
"""How a training step renders its pseudo-GT: the EMA teacher's colours as channels 3:6 of the student's
rasterisation ("fused", mask.teacher.fused), the teacher's own second rasterisation ("second"), or the student's
render (no teacher: mask.teacher.enabled False)."""


class MaskStep:
    """Which steps render the teacher, and the static mask [H, W] those steps (and the ones between) supervise."""

    def __init__(self, cfg, observations: list | None):
        self.cfg = cfg
        """The model's config (WillagsModelConfig: appearance and the mask group), read at every call so edits
        after construction count."""
        self.observations = observations
        """SfM observations per training image (COLMAP scenes; None elsewhere): the safeguard's input."""
        self.masks = PackedMasks()
        """Each image's last perceptual mask (True = static), before the support; kept at one bit a pixel
        (willags_ns/mask/store.py), since every training image's stays for the whole run."""
        self.visits: dict[int, int] = {}
        self.support_cache: dict[int, Tensor | None] = {}
        self.start_decision: dict | None = None
        """The start rule's {step, share, start} once taken (mask.start_rule "transients", rule.mask_start); None
        before it, and under start_rule "always"."""

    @property
    def declined(self) -> bool:
        """The start rule kept the mask off for the rest of the run."""
        d = self.start_decision
        return d is not None and not d["start"]

    def active(self, step: int) -> bool:
        cfg = self.cfg
        on = cfg.appearance == "willags" and cfg.mask.enabled and not self.declined
        return on and mask_active(step, cfg.mask.warmup_steps)

    def teacher_needed(self, step: int, idx: int) -> bool:
        """Whether this training step renders the teacher for image `idx` (counts the visit): on every mask.every-th
        visit of the image, and whenever it has no mask yet."""
        if not self.active(step):
            return False
        visits = self.visits.get(idx, 0)
        self.visits[idx] = visits + 1
        return idx not in self.masks or visits % max(1, self.cfg.mask.every) == 0

    def teacher_pass(self, step: int, idx: int, has_teacher: bool) -> TeacherPass | None:
        """How this training step renders image `idx`'s pseudo-GT (:data:`TeacherPass`; counts the visit), None on a
        step that reuses the image's mask (teacher_needed). `has_teacher`: the model has an EMA teacher."""
        if not self.teacher_needed(step, idx):
            return None
        if not has_teacher:
            return "student"
        return "fused" if self.cfg.mask.teacher.fused else "second"

    def static_mask(
        self,
        step: int,
        idx: int,
        gt_img: Tensor,
        teacher_rgb: Tensor | None,
        perceptual: PerceptualFeatures | None,
        device,
        expected: Tensor | None = None,
    ) -> StepMask:
        """The static mask of image `idx` at this step. With this step's teacher render, a new mask (with its D and
        rejection flag); without, the image's last one at the current resolution. `expected` [H, W]: the scene's
        expected residual on this step's render (willags_ns/mask/expected.py), or None."""
        cfg = self.cfg.mask
        if not self.active(step):
            return StepMask(None, None, None)
        H, W = gt_img.shape[:2]
        d = rejected = None
        if teacher_rgb is not None:
            transient, flag, d = compare_to_teacher(cfg, step, gt_img, teacher_rgb, perceptual, expected=expected)
            mask = ~transient  # a rejected mask supervises every pixel rather than none
            rejected = flag.float()  # a device tensor: no wait for VGG here
            self.masks[idx] = mask
        elif idx in self.masks:
            mask = self.masks[idx]
        else:
            return StepMask(None, None, None)
        if mask.shape != (H, W):  # resolution schedule moved on since the mask was cached
            mask = F.interpolate(mask[None, None].float(), size=(H, W), mode="nearest")[0, 0] > 0.5
        return StepMask(apply_support(mask, self.support(idx, H, W, device)).float(), d, rejected)

    def support(self, idx: int, height: int, width: int, device) -> Tensor | None:
        """Training image `idx`'s SfM support grid (True = vouched static; willags_ns/mask/static_support.py), or None
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
def teacher_latent(teacher: AppearanceNetworks, vae_in: Tensor | None, image_idx: int) -> Tensor:
    """The EMA teacher's z [D] for training image `image_idx` (no grad): the mean of its latent source, as the
    student's (AppearanceNetworks.latent_stats): its VAE's mean of the photo (`vae_in` [3, H, W], the encoder's
    input), or its row of the teacher's table."""
    return teacher.latent_stats(vae_in, image_idx)[0]


def log_step_images(
    step: int, outputs: dict, gt_img: Tensor, mask: Tensor | None, distance: Tensor | None, recon: Tensor | None
) -> None:
    """Tensorboard pictures of a training step: photo | render, the teacher's render, the perceptual distance D,
    the static mask, and the VAE's reconstruction of the photo (each when this step made one)."""
    from nerfstudio.utils import writer

    writer.put_image("train/render_vs_gt", torch.cat([gt_img, outputs["rgb"].detach()], dim=1), step)
    if "teacher_rgb" in outputs:
        writer.put_image("train/teacher_render", outputs["teacher_rgb"], step)
    if distance is not None:
        d = distance
        writer.put_image("train/perceptual_D", (d / d.max().clamp_min(1e-6))[..., None].expand(-1, -1, 3), step)
    if mask is not None:
        writer.put_image("train/static_mask", mask[..., None].expand(-1, -1, 3), step)
    if recon is not None:
        writer.put_image("train/vae_reconstruction", recon[0].permute(1, 2, 0), step)
