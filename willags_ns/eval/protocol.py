"""The NeRF-W evaluation protocol for appearance-conditioned models.

A test image's appearance (exposure, weather, camera) is unknown to the model, so NeRF-W fits it on the image's
*left half* and scores the *right half*. Here, for each test image:

1. freeze the scene (every Gaussian parameter and network weight);
2. initialise the latent from the VAE encoder's mean of the left half (models without a VAE: the mean training
   embedding; with `start_candidates` K: whichever of it and K training latents spread over the table renders the
   left half with the lowest loss), then optimise only the latent with Adam on the left half (0.8 L1 + 0.2 D-SSIM,
   the training loss);
3. score the right half: PSNR, SSIM, and LPIPS when its weights can be loaded (else reported as unavailable).

Also reported, so each number's meaning is visible: the encoder latent without optimisation (right half) and
full-image scores. Defaults: 128 Adam steps at lr 0.01, the same budget as the peer table in ../shared/gpu/README.

Cost: every Adam step renders the image and back-propagates, so the fit is the protocol's time. With `fit_max_side`
the fit runs on a k-times smaller image (k an integer: the camera's intrinsics divided by k, the ground truth
averaged over k x k blocks, so every low-resolution pixel of the left half lies in the full-resolution left half);
the right half is still scored at full resolution. ns-eval fits at most CPU_FIT_MAX_SIDE px on the CPU
(`fit_max_side` -1) and shows its progress per image and Adam step (`progress`).
"""

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import torch
from torch import Tensor

from willags_ns.eval.mask_eval import kept_pixels
from willags_ns.mask.residual import ResidualConfig, outlier_share
from willags_ns.objective.losses import reconstruction_loss


@dataclass
class EvalProtocolConfig:
    """NeRF-W protocol settings."""

    steps: int = 128
    """Adam steps fitting the latent on the left half of each test image (0 = encoder latent only)."""
    lr: float = 0.01
    """Adam learning rate for the latent."""
    max_images: int = -1
    """Evaluate at most this many test images (-1 = all)."""
    oracle: bool = False
    """Also fit the latent on the *whole* test image and score its right half (`oracle_*`): the gap to the
    headline number is what inferring the appearance from half an image costs (a diagnosis, not the protocol)."""
    start_candidates: int = 0
    """Training latents also tried as the fit's start (0 = the encoder's or the mean latent alone). K > 0: K of the
    training images' latents, picked spread over the table (farthest first from the usual start: `spread_picks`),
    each rendered once at the fit's resolution; the fit starts from whichever, the usual start included, has the
    lowest loss on the left half (`best_start`: only the left half is seen, as the fit sees it). A photo whose
    appearance lies far from the training mean (night, a storm) then starts near the training photo most like it
    instead of 128 Adam steps away; the cost is K renders without gradients per test photo."""
    fit_max_side: int = 0
    """Longest side (px) of the image the latent is fitted on (the right half is always scored at full resolution):
    0 = full resolution; N > 0 = downscaled by the smallest integer that brings it to N px or less; -1 = automatic,
    CPU_FIT_MAX_SIDE px on the CPU and full resolution on a GPU (each Adam step renders and back-propagates the image:
    on a CPU a full-resolution fit of 800 px images takes about half an hour per two images, docs/reliability.md).
    willags' pipeline (ns-eval) uses -1."""


CPU_FIT_MAX_SIDE = 320
"""Largest side of the latent fit on the CPU under `fit_max_side` -1."""


def resolve_fit_max_side(fit_max_side: int, device: Any) -> int:
    """The fit's largest side (0 = full resolution) for `fit_max_side` on `device` (see EvalProtocolConfig)."""
    if fit_max_side >= 0:
        return int(fit_max_side)
    return CPU_FIT_MAX_SIDE if torch.device(device).type == "cpu" else 0


def describe_protocol(cfg: EvalProtocolConfig, cameras, model) -> str:
    """What evaluate_model will do with `cfg` on `cameras` (printed by ns-eval before it starts)."""
    n = len(cameras) if cfg.max_images < 0 else min(cfg.max_images, len(cameras))
    appearance = getattr(model.config, "appearance", "sh") == "willags"
    if not appearance or cfg.steps <= 0:
        return f"ns-eval: {n} test images, each rendered once and scored (PSNR, SSIM, LPIPS)"
    max_side = resolve_fit_max_side(cfg.fit_max_side, model.device)
    sizes = sorted({(int(cameras.width[i]), int(cameras.height[i])) for i in range(n)}, reverse=True)
    fits = [(w, h, fit_factor(w, h, max_side)) for w, h in sizes]
    if all(k == 1 for _, _, k in fits):
        where = "at full resolution (" + ", ".join(f"{w}x{h}" for w, h, _ in fits[:3]) + " px)"
    else:
        shown = ", ".join(f"{w}x{h} -> {w // k}x{h // k}" for w, h, k in fits[:3]) + (" ..." if len(fits) > 3 else "")
        where = (
            f"downscaled to at most {max_side} px ({shown}; `fit_max_side: 0` under `eval_protocol` in config.yml, "
            "or --pipeline.eval-protocol.fit-max-side 0 when training, fits at full resolution)"
        )
    oracle = " plus the oracle fit on the whole image," if cfg.oracle else ""
    return (
        f"ns-eval: NeRF-W protocol on {n} test images: per image, {cfg.steps} Adam steps fit the appearance latent "
        f"to its left half {where},{oracle} then the right half is scored at full resolution (PSNR, SSIM, LPIPS); "
        "each Adam step renders the image once: the steps are most of the time"
    )


def fit_factor(width: int, height: int, max_side: int) -> int:
    """The integer downscale k of the latent fit: 1 for max_side <= 0 or an image that fits, else the smallest k with
    max(width, height) / k <= max_side."""
    side = max(int(width), int(height))
    if max_side <= 0 or side <= max_side:
        return 1
    return math.ceil(side / max_side)


def downscale_camera(cam, k: int):
    """One camera [1] rendering a k-times smaller image: width // k by height // k, intrinsics divided by k (pixel j's
    centre falls on the centre of full-resolution block [jk, jk + k))."""
    if k == 1:
        return cam
    from nerfstudio.cameras.cameras import Cameras

    return Cameras(
        camera_to_worlds=cam.camera_to_worlds,
        fx=cam.fx / k,
        fy=cam.fy / k,
        cx=cam.cx / k,
        cy=cam.cy / k,
        width=torch.div(cam.width, k, rounding_mode="floor"),
        height=torch.div(cam.height, k, rounding_mode="floor"),
        distortion_params=cam.distortion_params,
        camera_type=cam.camera_type,
        times=cam.times,
        metadata=cam.metadata,
    )


def block_mean(img: Tensor, k: int) -> Tensor:
    """[H, W, C] -> [H // k, W // k, C]: the mean of each k x k block (the remainder rows / columns dropped)."""
    if k == 1:
        return img
    h, w = img.shape[0] // k, img.shape[1] // k
    x = img[: h * k, : w * k].permute(2, 0, 1)[None]
    return torch.nn.functional.avg_pool2d(x, k)[0].permute(1, 2, 0)


def split_halves(width: int) -> tuple[slice, slice]:
    """Column slices (left, right) of an image `width` pixels wide: disjoint, covering, left = floor(W/2)."""
    if width < 2:
        raise ValueError(f"the NeRF-W protocol needs images at least 2 pixels wide, got width={width}")
    half = width // 2
    return slice(0, half), slice(half, width)


def psnr(pred: Tensor, gt: Tensor) -> float:
    """PSNR in dB of images in [0, 1] (any matching shapes)."""
    mse = torch.mean((pred.float() - gt.float()) ** 2).clamp_min(1e-12)
    return float(-10.0 * torch.log10(mse))


def ssim(pred: Tensor, gt: Tensor) -> float:
    """SSIM of [H, W, 3] images in [0, 1] (torchmetrics' Gaussian-window SSIM)."""
    from torchmetrics.functional.image import structural_similarity_index_measure

    p, g = pred.permute(2, 0, 1)[None].float(), gt.permute(2, 0, 1)[None].float()
    return float(structural_similarity_index_measure(p, g, data_range=1.0))


def image_scores(pred: Tensor, gt: Tensor, lpips_fn: Callable | None = None) -> dict[str, float]:
    """PSNR, SSIM (and LPIPS if a metric is given) of [H, W, 3] images."""
    out = {"psnr": psnr(pred, gt), "ssim": ssim(pred, gt)}
    if lpips_fn is not None:
        out["lpips"] = float(lpips_fn(pred.permute(2, 0, 1)[None].clamp(0, 1), gt.permute(2, 0, 1)[None]))
    return out


def fit_latent(
    render_fn: Callable[[Tensor], Tensor],
    gt: Tensor,
    z0: Tensor,
    cols: slice,
    steps: int,
    lr: float,
    on_step: Callable[[], None] | None = None,
) -> tuple[Tensor, list[float]]:
    """Optimise a latent so `render_fn(z)` [H, W, 3] matches `gt` on the columns `cols`.

    Only z receives updates (the caller freezes the scene). Returns (z, per-step loss history; the first entry is
    the loss at z0). `on_step()` is called after each Adam step (progress).
    """
    z = z0.detach().clone().requires_grad_(True)
    opt = torch.optim.Adam([z], lr=lr)
    target = gt[:, cols].permute(2, 0, 1)[None]
    history: list[float] = []
    for _ in range(steps):
        opt.zero_grad(set_to_none=True)
        pred = render_fn(z)[:, cols].permute(2, 0, 1)[None]
        loss = reconstruction_loss(pred, target, None)
        loss.backward()
        history.append(float(loss.detach()))
        opt.step()
        if on_step is not None:
            on_step()
    with torch.no_grad():
        history.append(float(reconstruction_loss(render_fn(z)[:, cols].permute(2, 0, 1)[None], target, None)))
    return z.detach(), history


def spread_picks(latents: Tensor, first: Tensor, k: int) -> Tensor:
    """[1 + min(k, N), D]: `first` [D], then `k` rows of `latents` [N, D] picked farthest-first (each the row
    farthest from every pick so far; ties to the lower index): candidates that cover the table's spread, the far
    appearances first. All N rows (in that order) when k >= N."""
    picks = [first.detach()]
    if k <= 0 or latents.shape[0] == 0:
        return picks[0][None]
    lat = latents.detach().to(first.device, first.dtype)
    dist = (lat - picks[0]).norm(dim=1)
    taken = torch.zeros(lat.shape[0], dtype=torch.bool, device=lat.device)
    for _ in range(min(k, lat.shape[0])):
        i = int(torch.where(taken, torch.full_like(dist, -1.0), dist).argmax())
        taken[i] = True
        picks.append(lat[i])
        dist = torch.minimum(dist, (lat - lat[i]).norm(dim=1))
    return torch.stack(picks)


@torch.no_grad()
def best_start(
    render_fn: Callable[[Tensor], Tensor], gt: Tensor, cols: slice, candidates: Tensor
) -> tuple[Tensor, int, list[float]]:
    """(z, index, losses): of the `candidates` [M, D], the one whose render matches `gt` on the columns `cols` best
    (the fit's own loss), its index (0: the first, the usual start, also on ties) and every candidate's loss."""
    target = gt[:, cols].permute(2, 0, 1)[None]
    losses = [
        float(reconstruction_loss(render_fn(z)[:, cols].permute(2, 0, 1)[None], target, None)) for z in candidates
    ]
    best = min(range(len(losses)), key=lambda i: (losses[i], i))
    return candidates[best].clone(), best, losses


def training_start(
    model, render_fn: Callable[[Tensor], Tensor], gt: Tensor, cols: slice, z0: Tensor, k: int
) -> tuple[Tensor, int | None]:
    """(z, index): the fit's start, `z0` or whichever of it and `k` of `model`'s training latents (spread over its
    table, `spread_picks`) renders `gt`'s columns `cols` best (`best_start`); index None where no choice was made
    (`k` is 0, or the model keeps no training latents)."""
    if k <= 0 or not hasattr(model, "image_latents"):
        return z0, None
    lat, known = model.image_latents()
    z, picked, _ = best_start(render_fn, gt, cols, spread_picks(lat[known], z0, k))
    return z, picked


class frozen:
    """Context manager: parameters of `module` get requires_grad=False inside, restored on exit."""

    def __init__(self, module: torch.nn.Module):
        self.params = list(module.parameters())
        self.flags: list[bool] = []

    def __enter__(self):
        self.flags = [p.requires_grad for p in self.params]
        for p in self.params:
            p.requires_grad_(False)
        return self

    def __exit__(self, *exc):
        for p, f in zip(self.params, self.flags, strict=True):
            p.requires_grad_(f)
        return False


def unit_float(image: Tensor) -> Tensor:
    """An image as float in [0, 1]: uint8 divided by 255 (what the training loss sees: splatfacto's `get_gt_img`),
    float as it is."""
    return image.float() / 255.0 if image.dtype == torch.uint8 else image.float()


def eval_split_images(datamanager) -> list[Tensor]:
    """Eval-split GT images [H, W, C] as the datamanager caches them (uint8, or float in [0, 1]), exactly as the eval
    cameras see them. The protocol turns each into floats when it scores it (:func:`unit_float`): the whole split
    as floats would hold four times the cache's memory.

    nerfstudio's full-image datamanager undistorts (and crops) images when it caches them and rewrites the eval
    cameras' intrinsics and sizes in place, so the dataset's raw files no longer match the cameras: use its cache.
    """
    cache = getattr(datamanager, "cached_eval", None)
    if cache is None:
        ds = datamanager.eval_dataset
        return [ds.get_image_float32(i) for i in range(len(ds))]
    return [d["image"] for d in cache]


def render_with_latent(model, cam, z: Tensor | None) -> Tensor:
    """[H, W, 3] render of one camera with latent z passed in the camera metadata (the exact colour path)."""
    c = cam
    if z is not None:
        c = cam.to(model.device)
        c.metadata = dict(c.metadata or {})
        c.metadata["appearance_latent"] = z
    return model.get_outputs(c)["rgb"]


def spaced_indices(n: int, max_images: int) -> list[int]:
    """Up to `max_images` (all when negative) evenly spaced indices of `n` images, the first and the last among them."""
    k = n if max_images < 0 else min(max_images, n)
    return sorted({round(i * (n - 1) / max(1, k - 1)) for i in range(k)})


def own_renders(model, cameras, images: list[Tensor], max_images: int):
    """(index, camera, render, photo in [0, 1]) of up to `max_images` evenly spaced training photos (`images` uint8 or
    float), each rendered with its own latent (the mean latent it had when last visited); the caller sets the model's
    mode."""
    latents = model.image_latents()[0] if getattr(model.config, "appearance", "sh") == "willags" else None
    for i in spaced_indices(len(images), max_images):
        cam = cameras[i : i + 1].to(model.device)
        pred = render_with_latent(model, cam, None if latents is None else latents[i])
        yield i, cam, pred, unit_float(images[i][..., :3].to(model.device))


@torch.no_grad()
def training_outlier_share(model, cameras, images: list[Tensor], max_images: int = 8) -> float:
    """The mean share of pixels the colour-residual rule (mask/residual.outlier_share, its defaults) marks transient in
    up to `max_images` evenly spaced training photos, each rendered with its own latent: `train_view_scores`'
    `train_outlier_share`, measured while training (the "transients" cap rule), the model left in its mode."""
    if not images:
        raise ValueError("willags: no training photos to measure a transient share on")
    was_training = model.training
    model.eval()
    try:
        rule = ResidualConfig()
        shares = [
            float(outlier_share(gt, pred, rule)) for _, _, pred, gt in own_renders(model, cameras, images, max_images)
        ]
    finally:
        model.train(was_training)
    return sum(shares) / len(shares)


@torch.no_grad()
def train_view_scores(model, cameras, images: list[Tensor], max_images: int = 8) -> dict[str, float]:
    """Fitting capacity: PSNR / SSIM of training views rendered with their *own* latents (the mean latent each image
    had when last visited; no test-time inference), over up to `max_images` evenly spaced training images (`images`
    uint8, or float in [0, 1]).

    With the mask on, also `train_psnr_kept`: the PSNR over the pixels the training loss keeps (mask_eval.kept_pixels
    at the model's step), and `train_kept_share`, their share. The whole photo's PSNR counts the pixels the mask
    leaves unfit on purpose, so only the kept pixels' fit compares across mask settings.

    `train_outlier_share`, whatever the mask: the share of pixels the colour-residual rule (mask/residual.py, its
    defaults) marks transient against this render, the blobs the model leaves unfit in its own photos (people it
    did not learn): a diagnosis of how crowded a collection is, measured by training, mask on or off."""
    model.eval()
    n = len(images)
    if n == 0:
        return {}
    appearance = getattr(model.config, "appearance", "sh") == "willags"
    scores, kept, shares, outliers = [], [], [], []
    rule = ResidualConfig()
    for i, cam, pred, gt in own_renders(model, cameras, images, max_images):
        scores.append(image_scores(pred, gt))
        outliers.append(float(outlier_share(gt, pred, rule)))
        keep = kept_pixels(model, cam, gt, i) if appearance else None
        if keep is not None and bool(keep.any()):
            kept.append(psnr(pred[keep], gt[keep]))
            shares.append(float(keep.float().mean()))
    out = {f"train_{k}": float(sum(s[k] for s in scores) / len(scores)) for k in scores[0]}
    out["train_num_images"] = float(len(scores))
    out["train_outlier_share"] = float(sum(outliers) / len(outliers))
    if kept:
        out["train_psnr_kept"] = float(sum(kept) / len(kept))
        out["train_kept_share"] = float(sum(shares) / len(shares))
    return out


def evaluate_model(
    model,
    cameras,
    images: list[Tensor],
    cfg: EvalProtocolConfig,
    names: list[str] | None = None,
    on_prediction: Callable[[int, Tensor, Tensor], None] | None = None,
    progress: Any = None,
):
    """Run the protocol over test `cameras` (nerfstudio Cameras, one per image) and GT `images` [H, W, 3] (uint8,
    or float in [0, 1]: :func:`unit_float`).

    Returns (aggregate dict, per-image list). Keys: `psnr`/`ssim`/`lpips` (right half, fitted latent: the
    headline numbers), `encoder_*` (right half, encoder latent, no optimisation), `full_*` (whole image, fitted
    latent), `left_loss_before` / `left_loss_after`, `fit_shift` (how far the fit moved the latent: the norm of
    fitted minus initial), `fit_scale` (the fit's downscale k), `start_pick` (with `start_candidates`: which
    candidate the fit started from, 0 the usual start). `on_prediction(i, pred,
    gt)` sees each scored render (whole image, fitted latent) and its ground truth, e.g. to save pictures.
    `progress`: a rich-style progress (``add_task`` / ``advance``, e.g. willags_ns.tools.progress.Progress) given one task
    per image, advanced at each Adam step, and one for all images (its time left is the whole protocol's).
    """
    model.eval()
    lpips_fn = model.lpips_metric() if hasattr(model, "lpips_metric") else None
    appearance = getattr(model.config, "appearance", "sh") == "willags"
    n = len(images) if cfg.max_images < 0 else min(cfg.max_images, len(images))
    max_side = resolve_fit_max_side(cfg.fit_max_side, model.device)
    fitting = appearance and cfg.steps > 0
    units = cfg.steps * (2 if cfg.oracle else 1) if fitting else 1  # progress units of one image
    tasks: dict[str, Any] = {}  # progress tasks: "all" (from the first unit of work on), "image" (this image's)
    per_image = []
    with frozen(model):
        for i in range(n):
            gt = unit_float(images[i][..., :3].to(model.device))
            cam = cameras[i : i + 1].to(model.device)
            h, w = int(cam.height.item()), int(cam.width.item())
            if gt.shape[:2] != (h, w):
                raise ValueError(
                    f"test image {names[i] if names else i}: ground truth is {gt.shape[1]}x{gt.shape[0]} but its "
                    f"camera renders {w}x{h} (were the images undistorted/cropped? use eval_split_images())"
                )
            left, right = split_halves(w)
            scale = fit_factor(w, h, max_side)
            fit_cam, fit_gt = downscale_camera(cam, scale), block_mean(gt, scale)
            fit_left, _ = split_halves(fit_gt.shape[1])

            def render_fn(z: Tensor | None, cam=cam) -> Tensor:
                return render_with_latent(model, cam, z)

            def render_fit(z: Tensor | None, cam=fit_cam) -> Tensor:
                return render_with_latent(model, cam, z)

            label = f"image {i + 1}/{n}" + (f" {names[i]}" if names else "")
            what = f"latent fit, left half at {fit_gt.shape[1]}x{fit_gt.shape[0]} px" if fitting else "render"

            def start(label=label, what=what) -> None:
                """Start this image's progress task (and at the first image, the overall one) at the work it counts,
                so that the first rate, and the time left printed with it, is that of this work alone."""
                if progress is None:
                    return
                if n > 1 and "all" not in tasks:
                    tasks["all"] = progress.add_task(f"all {n} test images", total=n * units)
                tasks["image"] = progress.add_task(f"{label} ({what})", total=units)

            def advance() -> None:
                for key in ("image", "all"):
                    if key in tasks:
                        progress.advance(tasks[key])

            rec: dict[str, float] = {"fit_scale": float(scale)}
            if appearance:
                if model.appearance_nets.vae is not None:
                    z0 = model.encode_image(gt[:, left])
                else:
                    z0 = model.default_latent()
                with torch.no_grad():
                    enc = render_fn(z0)
                rec.update({f"encoder_{k}": v for k, v in image_scores(enc[:, right], gt[:, right], lpips_fn).items()})
                z0, picked = training_start(model, render_fit, fit_gt, fit_left, z0, cfg.start_candidates)
                if picked is not None:
                    rec["start_pick"] = float(picked)
                if fitting:
                    start()
                with torch.enable_grad():
                    z, hist = fit_latent(render_fit, fit_gt, z0, fit_left, cfg.steps, cfg.lr, advance)
                rec["left_loss_before"], rec["left_loss_after"] = hist[0], hist[-1]
                rec["fit_shift"] = float((z - z0).norm())
                if cfg.oracle:
                    with torch.enable_grad():
                        z_o, _ = fit_latent(render_fit, fit_gt, z0, slice(None), cfg.steps, cfg.lr, advance)
                    with torch.no_grad():
                        pred_o = render_fn(z_o)
                    rec.update({f"oracle_{k}": v for k, v in image_scores(pred_o[:, right], gt[:, right]).items()})
            else:  # no appearance model: nothing to fit
                z = None
            if not fitting:
                start()
            with torch.no_grad():
                pred = render_fn(z)
            if not fitting:
                advance()
            if on_prediction is not None:
                on_prediction(i, pred.detach(), gt)
            rec.update(image_scores(pred[:, right], gt[:, right], lpips_fn))
            rec.update({f"full_{k}": v for k, v in image_scores(pred, gt, lpips_fn).items()})
            if names is not None:
                rec["image"] = names[i]  # type: ignore[assignment]
            per_image.append(rec)
    keys = [k for k in per_image[0] if k != "image"] if per_image else []
    agg = {k: float(sum(r[k] for r in per_image) / len(per_image)) for k in keys}
    agg["num_images"] = float(len(per_image))
    if lpips_fn is None:
        agg["lpips_status"] = "unavailable (no LPIPS weights on this machine)"  # type: ignore[assignment]
    return agg, per_image
