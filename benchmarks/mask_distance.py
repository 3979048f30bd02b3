"""The transient mask's two comparisons (mask.distance "vgg" and "residual") scored on one trained model.

    python benchmarks/mask_distance.py --scene ../shared/data/fox-wild --steps 1200 --downscale 2 \
        --out benchmarks/records/cpu_runs/mask_distance_foxwild_1200.json

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


def score_distance(model, train_dataset, data: Path) -> dict:
    """Scores of the model's mask with its current mask.distance (see the module docstring)."""
    import numpy as np
    import torch
    from PIL import Image

    from willags_ns.eval.mask_eval import mask_scores, resize_mask, teacher_render, training_view
    from willags_ns.mask.static_support import masked_share, observations_masked
    from willags_ns.mask.step import compare_to_teacher

    out: dict = {}
    if (data / "masks_gt").is_dir():
        ms = mask_scores(model, train_dataset, data / "masks_gt")
        out.update({k: ms.get(k) for k in ("iou", "iou_mean", "recall", "fp_rate", "rejected", "threshold")})
    obs = model.sfm_observations
    pairs, shares, subj_flag, subj_total = [], [], 0, 0
    for idx in range(len(train_dataset.image_filenames)):
        cam, image, _ = training_view(train_dataset, idx)
        img = torch.from_numpy(image).float().div(255.0).to(model.device)
        with torch.no_grad():
            render = teacher_render(model, cam, img, idx)
            transient, _, _ = compare_to_teacher(model.config.mask, model.step, img, render, model.perceptual)
        shares.append(float(transient.float().mean()))
        if obs is not None and idx < len(obs):
            pairs.append(observations_masked(~transient.cpu(), obs[idx], 5))
        subj = data / "masks_subject" / f"{Path(train_dataset.image_filenames[idx]).stem}.png"
        if subj.is_file():
            s = resize_mask(np.asarray(Image.open(subj).convert("L")) > 0, *transient.shape)
            subj_flag += int((transient.cpu().numpy() & s).sum())
            subj_total += int(s.sum())
    out["image_masked_mean"] = float(np.mean(shares))
    if pairs:
        out["static_obs_masked"] = masked_share(pairs)
    if subj_total:
        out["subject_masked"] = subj_flag / subj_total
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scene", type=Path, required=True)
    ap.add_argument("--steps", type=int, default=1200)
    ap.add_argument("--downscale", type=int, default=2)
    ap.add_argument("--train-distance", choices=DISTANCES, default="vgg", help="the mask's comparison while training")
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
        "scores": {},
    }
    for distance in DISTANCES:
        model.config.mask.distance = distance
        t1 = time.perf_counter()
        rec["scores"][distance] = score_distance(model, ds, args.scene)
        rec["scores"][distance]["score_s"] = time.perf_counter() - t1
        print(distance, json.dumps(rec["scores"][distance]), flush=True)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(rec, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
