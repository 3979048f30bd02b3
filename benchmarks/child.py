"""One benchmark run inside its child process: ``python -m benchmarks.child SPEC RESULT`` (started by
:mod:`benchmarks.grid`).

:func:`run_child` trains in-process exactly as ``ns-train`` does (``config.setup() -> trainer.setup() ->
trainer.train()``, vis tensorboard, no viewer, no evaluation during training), then measures on the test split and
returns the result record:

- the NeRF-W protocol (:func:`protocol_scores`, also what long runs score their milestones with): PSNR / SSIM /
  LPIPS of the right half with the latent fitted on the left half; ``encoder_*`` (encoder latent, no fit) and
  ``full_*`` (whole image); with ``$WILLAGS_BENCH_REGIONS`` the error maps and geometry of :mod:`benchmarks.regions`;
- render FPS: median wall time of ``model.get_outputs`` per test view (eval mode, no grad, one fixed latent);
- number of Gaussians, training wall time (``trainer.train()`` only: data loading is ``setup_s``), peak memory
  (CUDA: ``torch.cuda.max_memory_allocated`` during training; CPU: the child's peak RSS);
- the transient mask over the training photos (:func:`mask_record`): against ``masks_gt/`` where the scene has it,
  the share of the subject (``masks_subject/``) or of every pixel dropped elsewhere.

With ``$WILLAGS_BENCH_RENDERS`` set to a folder, a run also writes <scene>-<method>[-<tag>].png there: the right
halves of its test images (ground truth above, the protocol's render below, PSNR on each).
"""

import json
import os
import random
import resource
import statistics
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
import torch

from benchmarks.methods import METHODS, build_config, is_peer
from benchmarks.records import json_default
from benchmarks.regions import REFERENCE, REGIONS_ENV, RegionDump


def sync(device) -> None:
    """Wait for the work queued on ``device`` (nothing to wait for off CUDA): before a clock is read."""
    if str(device).startswith("cuda"):
        torch.cuda.synchronize()


def mask_record(model, train_dataset, max_images: int = -1) -> dict[str, Any]:
    """The transient mask of a trained model over its training photos, by what the scene folder holds: against
    ``masks_gt/`` (``mask_iou``, ``mask_recall``, ``mask_fp_rate``: static pixels dropped, ...); the share of the
    subject dropped where it has ``masks_subject/`` (``subject_masked``; ``mask_fp_rate`` then counts the rest of
    the photo); elsewhere the share of every pixel dropped (``mask_share``), at most what a static scene loses.
    Empty for a model without the mask; ``mask_status`` says why nothing was measured."""
    from willags_ns.eval.mask_eval import mask_scores, trained_mask

    if trained_mask(model) is None:
        return {}
    scene = Path(train_dataset.image_filenames[0]).parent.parent if train_dataset.image_filenames else None
    meta_dir = train_dataset.metadata.get("masks_gt_dir")
    gt_dir = Path(meta_dir) if meta_dir else (scene / "masks_gt" if scene else None)
    subject_dir = scene / "masks_subject" if scene else None
    if gt_dir is not None and gt_dir.is_dir():
        ms = mask_scores(model, train_dataset, gt_dir, max_images=max_images)
        return {"mask_status": ms.pop("status"), **{f"mask_{k}": v for k, v in ms.items()}}
    subject = subject_dir if subject_dir is not None and subject_dir.is_dir() else None
    ms = mask_scores(model, train_dataset, subject, max_images=max_images)
    if subject is not None:
        shares = {"subject_masked": ms.get("recall"), "mask_fp_rate": ms.get("fp_rate")}
    else:
        shares = {"mask_share": ms.get("fp_rate"), "mask_rejected": ms.get("rejected")}
    return {"mask_status": ms["status"], **shares, "mask_rule": ms.get("rule")}


def render_fps(model, cameras, n_views: int, repeats: int = 3) -> dict[str, float]:
    """Median ms per `model.get_outputs` over up to n_views test cameras (eval, no grad, one fixed latent)."""
    dev = str(model.device)
    model.eval()
    appearance = getattr(model.config, "appearance", "sh") == "willags"
    if appearance:
        model.render_latent = model.default_latent()
    times = []
    try:
        with torch.no_grad():
            for i in range(min(max(1, n_views), len(cameras))):
                cam = cameras[i : i + 1].to(model.device)
                model.get_outputs(cam)  # warm-up: allocations, f_d of the fixed latent
                for _ in range(repeats):
                    sync(dev)
                    t = time.perf_counter()
                    model.get_outputs(cam)
                    sync(dev)
                    times.append(time.perf_counter() - t)
    finally:
        if appearance:
            model.render_latent = None
    ms = 1e3 * statistics.median(times)
    return {"render_ms": ms, "fps": 1e3 / ms}


def patch_offline(base: str) -> list[str]:
    """Stock splatfacto and the peer (a ``base`` of benchmarks.methods) offline, before their model is built; the
    patches applied (none for our own methods). LPIPS would download AlexNet weights (unused here: the protocol scores
    LPIPS through the model's own metric, which splatfacto lacks); get_viewmat's torch.compile is replaced by the same
    maths (the peer's too: benchmarks.peer.patch_peer, which puts its package on the path)."""
    if base != "splatfacto" and not is_peer(base):
        return []
    import torchmetrics.image.lpip as tm_lpip
    from nerfstudio.models import splatfacto as sf

    from willags_ns.eval.lpips import lpips_weights_cached
    from willags_ns.render.camera import viewmat_from_c2w

    patches = []
    if not lpips_weights_cached():

        class _NoLPIPS(torch.nn.Module):
            def __init__(self, *a, **k):
                super().__init__()

        tm_lpip.LearnedPerceptualImagePatchSimilarity = _NoLPIPS
        patches.append("LPIPS stubbed (no AlexNet weights)")
    sf.get_viewmat = viewmat_from_c2w
    patches.append("get_viewmat without torch.compile")
    if is_peer(base):
        from benchmarks.peer import patch_peer

        patches += patch_peer()
    return patches


def protocol_scores(trainer, spec: dict[str, Any]) -> dict[str, Any]:
    """The NeRF-W protocol on the test split of a set-up trainer (spec: protocol_steps, protocol_lr,
    max_test_images, oracle, start_candidates, train_views): aggregate scores, per_image, eval_s and the train-view
    scores."""
    from willags_ns.eval.protocol import EvalProtocolConfig, evaluate_model

    dm = trainer.pipeline.datamanager
    model = trainer.pipeline.model
    if is_peer(METHODS[spec["method"]].base):
        from benchmarks.peer import PeerForProtocol

        model = PeerForProtocol(model)
    model.eval()
    # the test images as the model sees them: nerfstudio's cached (undistorted) images and updated cameras, as cached
    # (uint8): the protocol turns each into floats when it scores it
    images = [d["image"] for d in dm.cached_eval]
    names = [Path(p).name for p in dm.eval_dataset.image_filenames]
    t2 = time.perf_counter()
    proto = EvalProtocolConfig(
        steps=spec["protocol_steps"],
        lr=spec["protocol_lr"],
        max_images=spec["max_test_images"],
        oracle=bool(spec.get("oracle", False)),
        start_candidates=int(spec.get("start_candidates", 0)),
    )
    shown: list[tuple[Any, Any]] = []
    renders_dir, regions_dir = os.environ.get(RENDERS_ENV), os.environ.get(REGIONS_ENV)
    dump = RegionDump() if regions_dir and spec.get("regions", True) else None

    def seen(i, pred, gt):
        if renders_dir:
            w = pred.shape[1]
            shown.append((gt[:, w // 2 :].cpu(), pred[:, w // 2 :].cpu()))
        if dump is not None:
            dump.on_prediction(i, pred, gt)

    agg, per_image = evaluate_model(
        model, dm.eval_dataset.cameras, images, proto, names, on_prediction=seen if renders_dir or dump else None
    )
    if renders_dir and shown:
        save_right_halves(Path(renders_dir) / f"{_run_name(spec)}.png", shown, [r["psnr"] for r in per_image])
    if dump is not None:  # the reference geometry of the regions comes from willags' runs (benchmarks/regions.py)
        dump.save(Path(regions_dir) / f"{_run_name(spec)}.npz", names, trainer if spec["method"] == REFERENCE else None)
    rec: dict[str, Any] = {**agg, "per_image": per_image, "num_test_images": len(images)}
    rec["eval_s"] = time.perf_counter() - t2
    # the diagnoses below are extras: one that fails is written into the record and the log, and the protocol's
    # scores, which took the GPU a whole run, are kept
    for name, extra in (
        ("latent_spread", lambda: latent_spread(model)),
        ("train_views", lambda: _train_views(model, dm, int(spec.get("train_views", 0)))),
    ):
        try:
            rec.update(extra())
        except Exception as e:  # any failure of a diagnosis
            rec[f"{name}_error"] = f"{type(e).__name__}: {e}"
            print(
                f"benchmarks: the run's {name} failed and is left out of its record: {type(e).__name__}: {e}",
                file=sys.stderr,
            )
    return rec


def _train_views(model, dm, max_images: int) -> dict[str, float]:
    """train_view_scores over up to `max_images` of the cached training photos; none when 0."""
    from willags_ns.eval.protocol import train_view_scores

    if max_images == 0:
        return {}
    return train_view_scores(model, dm.train_dataset.cameras, [d["image"] for d in dm.cached_train], max_images)


def latent_spread(model) -> dict[str, float]:
    """How far the training images' latents lie from their mean (the protocol's starting latent without an
    encoder): `latent_spread` the mean distance, `latent_spread_max` the largest. Nothing for a model without an
    appearance latent."""
    if getattr(model.config, "appearance", "sh") != "willags":
        return {}
    lat, seen = model.image_latents()
    if not bool(seen.any()):
        return {}
    d = (lat[seen] - lat[seen].mean(0)).norm(dim=1)
    return {"latent_spread": float(d.mean()), "latent_spread_max": float(d.max())}


RENDERS_ENV = "WILLAGS_BENCH_RENDERS"
"""Folder where each run writes the picture of its test images' right halves (unset: none)."""


def _run_name(spec: dict[str, Any]) -> str:
    """<scene>-<method>[-<tag>]: how a run's pictures and region maps are named."""
    return f"{spec['scene_name']}-{spec['method']}{('-' + spec['tag']) if spec.get('tag') else ''}"


def save_right_halves(path: Path, pairs: list[tuple[Any, Any]], psnrs: list[float], height: int = 200) -> Path:
    """(ground truth, render) right halves [H, W, 3] in [0, 1]: one column per test image, each scaled to `height`
    pixels, ground truth above and the render below with its PSNR written on it."""
    from PIL import Image, ImageDraw

    def tile(t):
        im = Image.fromarray((t.clamp(0, 1).numpy() * 255).astype(np.uint8))
        return im.resize((max(1, round(im.width * height / im.height)), height), Image.Resampling.BILINEAR)

    tiles = [(tile(a), tile(b)) for a, b in pairs]
    sheet = Image.new("RGB", (sum(a.width for a, _ in tiles), 2 * height), "white")
    draw, x = ImageDraw.Draw(sheet), 0
    for (a, b), psnr in zip(tiles, psnrs, strict=True):
        sheet.paste(a, (x, 0))
        sheet.paste(b, (x, height))
        draw.text((x + 4, height + 4), f"{psnr:.2f} dB", fill=(255, 255, 0))
        x += a.width
    path.parent.mkdir(parents=True, exist_ok=True)
    sheet.save(path)
    return path


def run_child(spec: dict[str, Any]) -> dict[str, Any]:
    """Train and evaluate one run in this process; returns the result record (see the module docstring)."""
    threads = int(spec.get("threads") or 0)
    if threads > 0:
        torch.set_num_threads(threads)
    device = spec["device"]
    rec: dict[str, Any] = {}
    patches = patch_offline(METHODS[spec["method"]].base)
    data = Path(spec["data"]) if spec.get("data") else None
    config = build_config(
        spec["method"], spec["steps"], device, data, spec.get("downscale"), spec["schedule"], Path(spec["work_dir"])
    )
    config.machine.seed = int(spec.get("seed", config.machine.seed))
    config.save_config()
    random.seed(config.machine.seed)
    np.random.seed(config.machine.seed)
    torch.manual_seed(config.machine.seed)

    t0 = time.perf_counter()
    trainer = config.setup(local_rank=0, world_size=1)
    trainer.setup(test_mode="test")
    dm = trainer.pipeline.datamanager
    _ = dm.cached_train  # load + undistort now, not inside the timed loop
    setup_s = time.perf_counter() - t0
    auto = getattr(trainer.pipeline, "auto_config_summary", None)
    if auto is not None:  # what the inspector chose (its time is part of setup_s)
        rec["auto_config"] = {k: auto.get(k) for k in ("applied", "settings", "switches", "error")}
        rec["auto_inspect_s"] = (auto.get("report") or {}).get("wall_s")
    if device == "cuda":
        torch.cuda.reset_peak_memory_stats()
    sync(device)
    ru0 = resource.getrusage(resource.RUSAGE_SELF)
    load0 = os.getloadavg()[0]
    t1 = time.perf_counter()
    trainer.train()
    sync(device)
    train_s = time.perf_counter() - t1
    ru1 = resource.getrusage(resource.RUSAGE_SELF)
    # CPU seconds of this process while training, and the machine's load: wall time on a shared CPU machine is
    # only comparable between runs when the load was the same
    rec["train_cpu_s"] = (ru1.ru_utime - ru0.ru_utime) + (ru1.ru_stime - ru0.ru_stime)
    rec["load_avg_1m"] = [load0, os.getloadavg()[0]]
    if device == "cuda":
        rec["peak_mem_gb"] = torch.cuda.max_memory_allocated() / 1024**3
        rec["peak_mem_kind"] = "cuda max_memory_allocated (training)"

    model = trainer.pipeline.model
    rec.update(protocol_scores(trainer, spec))
    rec.update(render_fps(model, dm.eval_dataset.cameras, spec["fps_views"]))
    t3 = time.perf_counter()
    masks = mask_record(model, dm.train_dataset, spec["mask_max_images"])
    if masks:
        rec.update(masks)
        rec["mask_eval_s"] = time.perf_counter() - t3

    if device != "cuda":
        rec["peak_mem_gb"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024**2  # kilobytes on Linux
        rec["peak_mem_kind"] = "process max RSS (training + evaluation)"
    img0 = dm.cached_train[0]["image"]
    rec.update(
        num_gaussians=int(model.num_points),
        train_s=train_s,
        setup_s=setup_s,
        s_per_step=train_s / max(1, spec["steps"]),
        image_hw=[int(img0.shape[0]), int(img0.shape[1])],
        num_train_images=len(dm.train_dataset),
        patches=patches,
        threads=torch.get_num_threads(),
    )
    return rec


if __name__ == "__main__":
    if len(sys.argv) != 3:
        sys.exit("usage: python -m benchmarks.child SPEC.json RESULT.json (started by python -m benchmarks run)")
    result = run_child(json.loads(Path(sys.argv[1]).read_text()))
    Path(sys.argv[2]).write_text(json.dumps(result, default=json_default))
