"""How well the perceptual transient mask finds the occluders: IoU / recall / clean false positives vs masks_gt.

For every training image with a ground-truth mask (``masks_gt/<stem>.png``, 255 = transient) the mask is computed
exactly as a training step at the end of training computes it: the one rule, ``compare_to_teacher``
(willags_ns/mask/rule.py), on the teacher's render:

    z   = teacher VAE encoder mean of the training image      (latent.kind embedding: the teacher's table row)
    R   = teacher render of the view (teacher networks, the student's current Gaussians, full resolution)
    D   = perceptual_error(VGG(I), VGG(R))                     [H, W]   (mask.distance "residual": the colour residual)
    static = D < threshold(step)     (an image with more than max_masked_fraction flagged is rejected:
                                      training then supervises it everywhere, so nothing counts as transient)

Images and cameras are what training saw: nerfstudio's FullImageDatamanager undistorts OPENCV images (and crops
them to the valid region) before caching them; :func:`training_view` repeats that on the image and the GT mask
together, from the dataparser's original camera. GT masks at another resolution than the images (a downscaled
scene) are area-resampled and thresholded at one half.

Scores (transient = positive class), over the images that have a GT mask:

- ``iou``: pooled over all pixels of all images, sum(|P & G|) / sum(|P | G|) (defined whenever any image has a
  transient or a prediction; images without transients still count through their false positives);
- ``iou_mean``: mean per-image IoU over the images that do have GT transients (an image without transients has
  no IoU of its own, so it is left out of this mean rather than scored 0 or 1);
- ``recall``: sum(|P & G|) / sum(|G|);  ``fp_rate``: predicted transient among GT-clean pixels;
- ``precision``, ``rejected`` (images whose mask the max_masked_fraction guard dropped), ``threshold``,
  ``num_images`` / ``num_with_transients``, D medians on transient and clean pixels.
"""

import copy
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from PIL import Image
from torch import Tensor

from willags_ns.mask.expected import LEVEL
from willags_ns.mask.rule import compare_to_teacher, step_threshold, transient_mask
from willags_ns.mask.static_support import apply_support
from willags_ns.render.camera import View, viewmat_from_c2w


@dataclass
class MaskCounts:
    """Pixel counts of one image (transient = positive)."""

    tp: int
    fp: int
    fn: int
    tn: int
    rejected: bool = False

    @property
    def gt_pos(self) -> int:
        return self.tp + self.fn

    @property
    def iou(self) -> float | None:
        union = self.tp + self.fp + self.fn
        return self.tp / union if union > 0 else None


def count_pixels(pred: Tensor, gt: Tensor, rejected: bool = False) -> MaskCounts:
    """Confusion counts of boolean masks pred, gt [H, W] (True = transient)."""
    if pred.shape != gt.shape:
        raise ValueError(f"mask shapes differ: {tuple(pred.shape)} vs {tuple(gt.shape)}")
    pred, gt = pred.bool(), gt.bool()
    tp = int((pred & gt).sum())
    fp = int((pred & ~gt).sum())
    fn = int((~pred & gt).sum())
    return MaskCounts(tp=tp, fp=fp, fn=fn, tn=int(pred.numel()) - tp - fp - fn, rejected=rejected)


def _ratio(a: int, b: int) -> float | None:
    return a / b if b > 0 else None


def aggregate_counts(counts: list[MaskCounts]) -> dict[str, float | None]:
    """Pooled and per-image scores of a list of per-image counts (see the module docstring). None = undefined."""
    tp = sum(c.tp for c in counts)
    fp = sum(c.fp for c in counts)
    fn = sum(c.fn for c in counts)
    tn = sum(c.tn for c in counts)
    ious = [c.iou for c in counts if c.gt_pos > 0]
    return {
        "iou": _ratio(tp, tp + fp + fn),
        "iou_mean": float(np.mean([i for i in ious if i is not None])) if ious else None,
        "recall": _ratio(tp, tp + fn),
        "precision": _ratio(tp, tp + fp),
        "fp_rate": _ratio(fp, fp + tn),
        "num_images": float(len(counts)),
        "num_with_transients": float(sum(c.gt_pos > 0 for c in counts)),
        "rejected": float(sum(c.rejected for c in counts)),
    }


def resize_mask(mask: np.ndarray, height: int, width: int) -> np.ndarray:
    """Bool mask [h, w] -> [height, width]: area average, then >= 0.5 (identity at the same size)."""
    if mask.shape == (height, width):
        return mask.astype(bool)
    t = torch.from_numpy(mask.astype(np.float32))[None, None]
    return (F.interpolate(t, size=(height, width), mode="area")[0, 0] >= 0.5).numpy()


def load_gt_mask(path: Path, height: int, width: int) -> np.ndarray:
    """masks_gt PNG (255 = transient) as bool [height, width]."""
    m = np.asarray(Image.open(path).convert("L")) >= 128
    return resize_mask(m, height, width)


def training_view(train_dataset, idx: int, extra: np.ndarray | None = None):
    """(camera [1], image uint8 [H, W, 3], extra [H, W] bool or None) of training image `idx` as training sees it.

    nerfstudio's FullImageDatamanager undistorts perspective images with nonzero distortion (OpenCV, optimal new
    camera matrix with alpha 0, then a crop to the valid ROI) and updates the camera's intrinsics and size: the
    same is done here to the image and `extra` (a GT mask at the image's size) together, starting from the
    dataparser's original camera (the dataset's own cameras may already have been modified in place).
    """
    data = train_dataset.get_data(idx, image_type="uint8")
    image = data["image"][..., :3].numpy()
    orig = train_dataset._dataparser_outputs.cameras
    cam = copy.deepcopy(orig[idx : idx + 1])
    if train_dataset.scale_factor != 1.0:
        cam.rescale_output_resolution(train_dataset.scale_factor)
    dist = None if cam.distortion_params is None else cam.distortion_params[0].numpy()
    if dist is None or not np.any(dist):
        return cam, image, extra
    import cv2
    from nerfstudio.cameras.cameras import CameraType

    if int(cam.camera_type[0]) != CameraType.PERSPECTIVE.value:
        raise NotImplementedError("mask_eval: undistortion of non-perspective cameras is not implemented")
    if dist[3] != 0:
        raise ValueError("nerfstudio only undistorts k1, k2, k3, p1, p2 (the 4th radial term must be 0)")
    K = cam.get_intrinsics_matrices()[0].numpy()  # float32 like nerfstudio's: bit-identical undistortion
    cv_dist = np.array([dist[0], dist[1], dist[4], dist[5], dist[2], dist[3], 0, 0])  # OpenCV order
    K[0, 2] -= 0.5  # nerfstudio's principal point counts pixel centres at +0.5, OpenCV's at integer coordinates
    K[1, 2] -= 0.5
    newK, roi = cv2.getOptimalNewCameraMatrix(K, cv_dist, (image.shape[1], image.shape[0]), 0)
    x, y, w, h = roi
    image = cv2.undistort(image, K, cv_dist, None, newK)[y : y + h, x : x + w]
    out_extra = None
    if extra is not None:  # bilinear warp of the 0/255 mask, then one half: the mask follows the image's pixels
        warped = cv2.undistort(extra.astype(np.uint8) * 255, K, cv_dist, None, newK)[y : y + h, x : x + w]
        out_extra = warped >= 128
    cam.fx[0, 0] = float(newK[0, 0])
    cam.fy[0, 0] = float(newK[1, 1])
    cam.cx[0, 0] = float(newK[0, 2] - x + 0.5)
    cam.cy[0, 0] = float(newK[1, 2] - y + 0.5)
    cam.width[0, 0] = image.shape[1]
    cam.height[0, 0] = image.shape[0]
    return cam, np.ascontiguousarray(image), out_extra


@torch.no_grad()
def teacher_render(model, camera, image: Tensor, image_idx: int) -> Tensor:
    """The EMA teacher's render [H, W, 3] of `camera` for the training image `image` [H, W, 3] in [0, 1].

    Through training's functions: the teacher's latent (VAE mean of the image, or its embedding row;
    willags_ns/mask/step.py), its colours on the student's current Gaussians (appearance/color_path.py), the camera
    after the camera optimiser, the teacher's own rasterisation (`model.render_teacher`) and the composite.
    Background: the teacher's sky behind every pixel when the model has one, else the model's fixed colour (training
    draws a random one per step, which only shows where alpha < 1). Without a teacher (teacher disabled) the
    student's networks are used.
    """
    from willags_ns.appearance.color_path import teacher_colors
    from willags_ns.appearance.sky import background, composite, pixel_directions
    from willags_ns.mask.step import teacher_latent

    nets = model.teacher if model.teacher is not None else model.appearance_nets
    z = teacher_latent(nets, image.permute(2, 0, 1).float().to(model.device), image_idx)
    view = _training_camera_view(model, camera, image_idx)
    c2w, K = view.c2w, view.K
    gp = model.gauss_params
    colors = teacher_colors(nets, z, gp, view.center, model.color_context(), None)
    dirs = pixel_directions(c2w[0], K[0], view.width, view.height) if nets.sky is not None else None
    bg = background(nets.sky, z, dirs, model.background_color.to(model.device))
    render, alpha = model.render_teacher(gp, colors, view)
    return composite(render, alpha, bg).squeeze(0)


def _training_camera_view(model, camera, image_idx: int) -> View:
    """The View of training camera `image_idx` as a training step renders it (after the camera optimiser)."""
    cam = camera.to(model.device)
    cam.metadata = dict(cam.metadata or {})
    cam.metadata["cam_idx"] = image_idx
    c2w = model.camera_optimizer.apply_to_camera(cam)
    K = cam.get_intrinsics_matrices().to(model.device)
    return View(c2w, viewmat_from_c2w(c2w), K, int(cam.width.item()), int(cam.height.item()))


def expected_render(model, camera, image_idx: int) -> Tensor | None:
    """The scene's expected residual [H, W] on training camera `image_idx` (willags_ns/mask/expected.py: the
    Gaussians' levels rendered), which the rule subtracts; None for a model without levels."""
    if LEVEL not in model.gauss_params:
        return None
    gp = model.gauss_params
    render, _ = model.render_teacher(gp, gp[LEVEL].detach(), _training_camera_view(model, camera, image_idx))
    return render[0, ..., 0]


@torch.no_grad()
def rule_mask(model, camera, image: Tensor, image_idx: int, threshold: float | None = None):
    """The mask's rule on training image `image_idx` (`image` [H, W, 3] in [0, 1]) against the teacher's render of
    `camera`, with the scene's expected residual where the model has one: compare_to_teacher's (transient [H, W],
    rejected, D) at the model's step (`threshold`: the bar instead of the step's)."""
    render = teacher_render(model, camera, image, image_idx)
    expected = expected_render(model, camera, image_idx)
    return compare_to_teacher(
        model.config.mask, model.step, image, render, model.perceptual, threshold=threshold, expected=expected
    )


def trained_mask(model):
    """The mask settings (MaskConfig) of a model that trains with the transient mask; None for one without: a model
    without willags' appearance (splatfacto), one with no mask config at all (the peer's adapter,
    benchmarks/peer.PeerForProtocol), with the mask off, or one whose mask's start rule kept it off (mask.start_rule)."""
    cfg = model.config
    mask = getattr(cfg, "mask", None)
    if getattr(cfg, "appearance", "sh") != "willags" or mask is None or not mask.enabled:
        return None
    step = getattr(model, "mask_step", None)
    if step is not None and step.declined:
        return None
    return mask


@torch.no_grad()
def kept_pixels(model, camera, image: Tensor, image_idx: int, threshold: float | None = None) -> Tensor | None:
    """bool [H, W]: the pixels of training image `image_idx` (`image` [H, W, 3] in [0, 1], seen by `camera` as
    training sees it) that the training loss keeps under the model's mask at its current step: the rule's mask
    against the teacher's render (a rejected mask keeps every pixel), then the SfM support. None for a model without
    the mask (:func:`trained_mask`), or before the mask's warm-up. `threshold`: the bar instead of the step's
    (:func:`step_threshold`)."""
    mask = trained_mask(model)
    if mask is None:
        return None
    if mask.distance == "vgg" and model.perceptual is None:
        return None
    if threshold is None and not model.mask_step.active(model.step):
        return None
    transient, _, _ = rule_mask(model, camera, image, image_idx, threshold)
    H, W = transient.shape
    return apply_support(~transient, model.static_support(image_idx, H, W))


def mask_scores(
    model,
    train_dataset,
    masks_gt_dir: Path | None,
    max_images: int = -1,
    threshold: float | None = None,
    keep_per_image: bool = False,
) -> dict:
    """Scores of the model's transient mask against `masks_gt_dir/<stem>.png` over the training images.

    `masks_gt_dir` None counts every pixel of every training image as static: ``fp_rate`` is then the share of all
    pixels the mask drops (a scene without ground truth).

    `threshold` overrides the threshold the model would use at its current step (mask_threshold(step, ...)).
    Returns the dict of :func:`aggregate_counts` plus ``threshold``, ``d_median_transient`` /
    ``d_median_clean``, ``status`` ("ok" or why nothing was measured) and, with keep_per_image, ``per_image``.
    """
    mask = trained_mask(model)
    if mask is None or model.perceptual is None:
        return {"status": "no perceptual mask in this model"}
    masks_gt_dir = None if masks_gt_dir is None else Path(masks_gt_dir)
    residual = mask.distance == "residual"
    thr = step_threshold(mask, model.step) if threshold is None else threshold  # "residual": its bar's floor
    was_training = model.training
    model.eval()
    counts: list[MaskCounts] = []
    counts_fixed: list[MaskCounts] = []
    d_pos: list[Tensor] = []
    d_neg: list[Tensor] = []
    per_image = []
    try:
        for i, fname in enumerate(train_dataset.image_filenames):
            if 0 <= max_images <= len(counts):
                break
            gt_mask = None
            if masks_gt_dir is not None:
                gt_path = masks_gt_dir / f"{Path(fname).stem}.png"
                if not gt_path.is_file():
                    continue
                raw = train_dataset.get_data(i, image_type="uint8")["image"]
                gt_mask = load_gt_mask(gt_path, raw.shape[0], raw.shape[1])
            cam, image, gt_mask = training_view(train_dataset, i, gt_mask)
            img = torch.from_numpy(image).float().div(255.0).to(model.device)
            pred, rejected_t, d = rule_mask(model, cam, img, i, thr)
            rejected = bool(rejected_t)
            if gt_mask is None:  # no ground truth: every pixel static
                gt_t = torch.zeros_like(pred, dtype=torch.bool)
            else:
                gt_t = torch.from_numpy(gt_mask).to(pred.device)
            c = count_pixels(pred, gt_t, rejected)
            counts.append(c)
            # the paper's fixed rule on the same D, for comparison
            fixed, fixed_rej = transient_mask(d, thr, "fixed", max_masked_fraction=mask.max_masked_fraction)
            counts_fixed.append(count_pixels(fixed, gt_t, bool(fixed_rej)))
            d_cpu = d.float().cpu()
            gt_cpu = gt_t.cpu()
            # subsample D for the medians: 4096 pixels per class and image is plenty
            for sel, sink in ((gt_cpu, d_pos), (~gt_cpu, d_neg)):
                v = d_cpu[sel]
                if v.numel() > 4096:
                    v = v[torch.linspace(0, v.numel() - 1, 4096).long()]
                sink.append(v)
            if keep_per_image:
                per_image.append(
                    {"image": Path(fname).name, "iou": c.iou, "tp": c.tp, "fp": c.fp, "fn": c.fn, "rejected": rejected}
                )
    finally:
        model.train(was_training)
    if not counts:
        return {"status": f"no training image has a mask in {masks_gt_dir}" if masks_gt_dir else "no training image"}
    out: dict = dict(aggregate_counts(counts))
    out["threshold"] = float(thr)
    out["rule"] = "residual" if residual else mask.threshold_rule
    fixed_agg = aggregate_counts(counts_fixed)
    for key in ("iou", "recall", "fp_rate", "rejected"):
        out[f"fixed_{key}"] = fixed_agg[key]
    pos, neg = torch.cat(d_pos), torch.cat(d_neg)
    out["d_median_transient"] = float(pos.median()) if pos.numel() else None
    out["d_median_clean"] = float(neg.median()) if neg.numel() else None
    out["status"] = "ok"
    if keep_per_image:
        out["per_image"] = per_image
    return out
