"""The transient mask's two comparisons (mask.distance "vgg" and "residual") scored on one trained model.

    python benchmarks/mask_distance.py --scene ../shared/data/fox-wild --steps 1200 --downscale 2 \
        --max-images 24 --out benchmarks/records/cpu_runs/mask_distance_foxwild.json

Trains `willags-full` (every component, no inspection; the mask trains with --train-distance) on the CPU with the
short schedule (benchmarks/methods.py: apply_schedule), then computes every training image's mask at the last step
with each comparison against the same EMA teacher render (willags_ns/mask/step.py: compare_to_teacher) and scores:

- scenes with ``masks_gt/``: IoU, recall and the masked share of GT-static pixels (willags_ns/eval/mask_eval.py);
- COLMAP scenes: the share of observations of SfM points with a track of >= 5 training images that the mask flags
  (static observations masked, before the safeguard) and the mean masked share of the images;
- scenes with ``masks_subject/`` (liberty): the share of the subject's pixels masked.
"""

import argparse
import json
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
if str(REPO) not in sys.path:
    sys.path.insert(0, str(REPO))

DISTANCES = ("vgg", "residual")


def score_distances(model, train_dataset, data: Path, max_images: int = -1) -> dict:
    """Scores of each comparison (DISTANCES) on the same teacher render per image (see the module docstring)."""
    import numpy as np
    import torch
    from PIL import Image

    from willags_ns.eval.mask_eval import (
        aggregate_counts,
        count_pixels,
        load_gt_mask,
        resize_mask,
        teacher_render,
        training_view,
    )
    from willags_ns.mask.static_support import masked_share, observations_masked
    from willags_ns.mask.step import compare_to_teacher

    obs = model.sfm_observations
    acc = {d: {"counts": [], "pairs": [], "shares": [], "subj": [0, 0]} for d in DISTANCES}
    names = train_dataset.image_filenames
    n = len(names) if max_images < 0 else min(max_images, len(names))
    # evenly spread images when only some are scored
    for idx in np.unique(np.linspace(0, len(names) - 1, n).round().astype(int)).tolist():
        stem = Path(names[idx]).stem
        gt_path = data / "masks_gt" / f"{stem}.png"
        gt = None
        if gt_path.is_file():
            raw = train_dataset.get_data(idx, image_type="uint8")["image"]
            gt = load_gt_mask(gt_path, raw.shape[0], raw.shape[1])
        cam, image, gt = training_view(train_dataset, idx, gt)
        img = torch.from_numpy(image).float().div(255.0).to(model.device)
        subj_path = data / "masks_subject" / f"{stem}.png"
        with torch.no_grad():
            render = teacher_render(model, cam, img, idx)
            for distance in DISTANCES:
                model.config.mask.distance = distance
                transient, rejected, _ = compare_to_teacher(
                    model.config.mask, model.step, img, render, model.perceptual
                )
                a, t = acc[distance], transient.cpu()
                a["shares"].append(float(t.float().mean()))
                if gt is not None:
                    a["counts"].append(count_pixels(t, torch.from_numpy(gt), bool(rejected)))
                if obs is not None and idx < len(obs):
                    a["pairs"].append(observations_masked(~t, obs[idx], 5))
                if subj_path.is_file():
                    s = resize_mask(np.asarray(Image.open(subj_path).convert("L")) > 0, *t.shape)
                    a["subj"][0] += int((t.numpy() & s).sum())
                    a["subj"][1] += int(s.sum())
    out = {}
    for distance, a in acc.items():
        o: dict = {"images": len(a["shares"]), "image_masked_mean": float(np.mean(a["shares"]))}
        if a["counts"]:
            o.update(aggregate_counts(a["counts"]))
        if a["pairs"]:
            o["static_obs_masked"] = masked_share(a["pairs"])
        if a["subj"][1]:
            o["subject_masked"] = a["subj"][0] / a["subj"][1]
        out[distance] = o
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scene", type=Path, required=True)
    ap.add_argument("--steps", type=int, default=1200)
    ap.add_argument("--downscale", type=int, default=2)
    ap.add_argument("--train-distance", choices=DISTANCES, default="vgg", help="the mask's comparison while training")
    ap.add_argument("--max-images", type=int, default=-1, help="score this many training images (evenly spread)")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--seed", type=int, default=42)
    ap.add_argument("--work-dir", type=Path, default=Path("/tmp/willags-mask-distance"))
    ap.add_argument("--out", type=Path, required=True)
    args = ap.parse_args(argv)

    import random

    import numpy as np
    import torch

    from benchmarks.methods import build_config
    from benchmarks.runner import downscaled_scene

    torch.set_num_threads(args.threads)
    data = downscaled_scene(args.scene, args.downscale) if args.downscale > 1 else args.scene
    config = build_config("willags-full", args.steps, "cpu", data, args.downscale, "short", args.work_dir)
    config.machine.seed = args.seed
    config.pipeline.model.mask.distance = args.train_distance
    random.seed(args.seed)
    np.random.seed(args.seed)
    torch.manual_seed(args.seed)
    t0 = time.perf_counter()
    trainer = config.setup(local_rank=0, world_size=1)
    trainer.setup(test_mode="test")
    trainer.train()
    train_s = time.perf_counter() - t0
    model = trainer.pipeline.model
    ds = trainer.pipeline.datamanager.train_dataset
    rec = {
        "scene": args.scene.name,
        "method": "willags-full",
        "device": "cpu",
        "steps": args.steps,
        "downscale": args.downscale,
        "schedule": "short",
        "mask_warmup_steps": config.pipeline.model.mask.warmup_steps,
        "train_distance": args.train_distance,
        "seed": args.seed,
        "train_s": train_s,
    }
    t1 = time.perf_counter()
    rec["scores"] = score_distances(model, ds, args.scene, args.max_images)
    rec["score_s"] = time.perf_counter() - t1
    print(json.dumps(rec["scores"], indent=1), flush=True)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(rec, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
