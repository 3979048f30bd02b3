"""Row 19 of docs/reliability.md: train willags on a real scene with anomaly checks; every parameter and gradient
must stay finite. Too slow for CI on CPU (2k steps), so it is a script; its result goes into docs/reliability.md.

    python -m benchmarks stability --scene ../shared/data/fox-wild --steps 2000 --downscales 1 \
        --out /tmp/stability --json /tmp/stability.json

What it does: nerfstudio's Trainer exactly as `ns-train willags` sets it up (method defaults; only the step count,
the output folder and, for CPU time, a fixed training resolution 1/2**downscales changed), with
`torch.autograd.set_detect_anomaly(True)` (a NaN produced inside any backward op raises at that op) and, after every
optimiser step, a check that every model parameter and every gradient is finite. It stops at the first failure and
writes a JSON record: steps run, seconds, first failure (step, tensor name) or none, losses every 50 steps.
"""

import argparse
import json
import time
from pathlib import Path

import torch


def nonfinite(named) -> list[str]:
    """Names of tensors in ``named`` (name, tensor) that hold a NaN or an Inf."""
    return [n for n, t in named if t is not None and not torch.isfinite(t).all()]


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scene", type=Path, default=Path(__file__).resolve().parents[2] / "shared/data/fox-wild")
    ap.add_argument("--method", default="willags", choices=["willags", "willags-lite"])
    ap.add_argument("--steps", type=int, default=2000)
    ap.add_argument("--downscales", type=int, default=1, help="train at 1/2**k resolution throughout (CPU time)")
    ap.add_argument("--no-anomaly", action="store_true", help="skip torch's anomaly mode (about 2x faster)")
    ap.add_argument("--out", type=Path, default=Path("/tmp/willags-stability"))
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args()

    from nerfstudio.scripts.train import _set_random_seed

    from willags_ns import method_configs as mc

    config = (mc.willags_lite_config if args.method == "willags-lite" else mc.willags_config)()
    config.max_num_iterations = args.steps
    config.steps_per_save = args.steps
    config.steps_per_eval_image = 10**9
    config.vis = "tensorboard"
    config.output_dir = args.out
    config.experiment_name = f"stability-{args.scene.name}"
    config.timestamp = "run"
    config.machine.device_type = "cuda" if torch.cuda.is_available() else "cpu"
    config.pipeline.datamanager.data = args.scene
    m = config.pipeline.model
    m.num_downscales = args.downscales
    m.resolution_schedule = 10**9  # stay at 1/2**downscales (the schedule would otherwise reach full size)
    m.log_images_every = 0
    config.set_timestamp()
    config.save_config()
    _set_random_seed(config.machine.seed)
    trainer = config.setup(local_rank=0, world_size=1)
    trainer.setup()
    model = trainer.pipeline.model

    record: dict = {
        "scene": str(args.scene),
        "method": args.method,
        "steps_asked": args.steps,
        "downscales": args.downscales,
        "anomaly_mode": not args.no_anomaly,
        "failure": None,
        "losses": {},
        "steps_run": 0,
    }
    orig = trainer.train_iteration

    def checked(step: int):
        loss, loss_dict, metrics = orig(step)
        bad = nonfinite(model.named_parameters())
        bad += [f"{n}.grad" for n in nonfinite((n, p.grad) for n, p in model.named_parameters())]
        if not torch.isfinite(loss):
            bad.append("loss")
        record["steps_run"] = step + 1
        if step % 50 == 0:
            record["losses"][step] = float(loss)
            print(f"step {step}: loss {float(loss):.4f}, {model.num_points} Gaussians", flush=True)
            if args.json:  # partial record: a run cut short still says how far it got
                args.json.write_text(json.dumps(record, indent=1))
        if bad:
            record["failure"] = {"step": step, "tensors": bad[:20]}
            raise RuntimeError(f"non-finite at step {step}: {bad[:20]}")
        return loss, loss_dict, metrics

    trainer.train_iteration = checked
    t0 = time.time()
    try:
        with torch.autograd.set_detect_anomaly(not args.no_anomaly):
            trainer.train()
    except RuntimeError as e:  # anomaly mode raises RuntimeError naming the backward op
        if record["failure"] is None:
            record["failure"] = {"step": record["steps_run"], "error": str(e)[:2000]}
    record["seconds"] = round(time.time() - t0, 1)
    record["num_gaussians"] = int(model.num_points)
    print(json.dumps({k: v for k, v in record.items() if k != "losses"}, indent=1))
    if args.json:
        args.json.write_text(json.dumps(record, indent=1))
    return 1 if record["failure"] else 0


if __name__ == "__main__":
    raise SystemExit(main())
