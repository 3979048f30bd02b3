"""Train methods on one scene in-process (nerfstudio's Trainer, as ns-train does) and score them under the NeRF-W
protocol. A trimmed harness: one process, one JIT, several runs; prints a table, writes JSON.

    python -m benchmarks train-eval --scene ../shared/data/fox-wild --methods willags willags-3dgs --steps 5000

Methods: willags, willags-lite, willags-3dgs, willags-novae, willags-nofield, willags-nomask. Schedules are the
methods' own defaults (the paper's / splatfacto's), only the iteration count is set.
"""

import argparse
import json
import platform
import time
from pathlib import Path

import torch

ABLATIONS = {
    "willags-novae": {"latent.kind": "embedding"},
    "willags-nofield": {"use_field": False},
    "willags-nomask": {"mask.enabled": False},
}


def build_config(method: str, scene: Path | None, steps: int, out: Path, protocol_steps: int):
    from willags_ns import method_configs as mc

    base = {"willags-lite": mc.willags_lite_config, "willags-3dgs": mc.willags_3dgs_config}.get(
        method, mc.willags_config
    )
    config = base()
    config.method_name = method if method in ("willags", "willags-lite", "willags-3dgs") else "willags"
    config.max_num_iterations = steps
    config.steps_per_save = steps
    config.vis = "tensorboard"
    config.output_dir = out
    config.experiment_name = (scene.name if scene else "default") + "-" + method
    config.timestamp = "run"
    config.machine.device_type = "cuda" if torch.cuda.is_available() else "cpu"
    if scene is not None:
        config.pipeline.datamanager.data = scene
    config.pipeline.eval_protocol.steps = protocol_steps
    for k, v in ABLATIONS.get(method, {}).items():
        setattr(config.pipeline.model, k, v)
    return config


def run_one(method: str, scene: Path | None, steps: int, out: Path, protocol_steps: int) -> dict:
    from willags_ns.eval.protocol import EvalProtocolConfig, eval_split_images, evaluate_model

    config = build_config(method, scene, steps, out, protocol_steps)
    config.set_timestamp()
    config.save_config()
    trainer = config.setup(local_rank=0, world_size=1)
    trainer.setup()
    if torch.cuda.is_available():
        torch.cuda.synchronize()
        torch.cuda.reset_peak_memory_stats()
    t0 = time.time()
    trainer.train()
    if torch.cuda.is_available():
        torch.cuda.synchronize()
    train_s = time.time() - t0
    pipeline = trainer.pipeline
    model = pipeline.model
    ds = pipeline.datamanager.eval_dataset
    images = eval_split_images(pipeline.datamanager)
    agg, _ = evaluate_model(model, ds.cameras, images, EvalProtocolConfig(steps=protocol_steps))
    # render speed at a fixed latent (eval, no grad): the f_d cache makes only the decoder + rasteriser run
    cam = ds.cameras[0:1].to(model.device)
    with torch.no_grad():
        for _ in range(3):
            model.get_outputs(cam)
        if torch.cuda.is_available():
            torch.cuda.synchronize()
        t1, n = time.time(), 20
        for _ in range(n):
            model.get_outputs(cam)
        if torch.cuda.is_available():
            torch.cuda.synchronize()
        fps = n / (time.time() - t1)
    rec = {
        "scene": scene.name if scene else "default",
        "method": method,
        "device": torch.cuda.get_device_name()
        if torch.cuda.is_available()
        else f"cpu ({platform.processor() or 'x86_64'})",
        "steps": steps,
        "train_s": round(train_s, 1),
        "num_gaussians": int(model.num_points),
        "fps": round(fps, 1),
        "peak_mem_gb": round(torch.cuda.max_memory_allocated() / 2**30, 3) if torch.cuda.is_available() else None,
        "protocol_steps": protocol_steps,
    }
    rec.update({k: (round(v, 4) if isinstance(v, float) else v) for k, v in agg.items()})
    if "lpips" not in rec:
        rec["lpips"] = None
    del trainer, pipeline, model
    if torch.cuda.is_available():
        torch.cuda.empty_cache()
    return rec


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scene", type=Path, default=None, help="scene directory (default: the embedded scene)")
    ap.add_argument("--methods", nargs="+", default=["willags", "willags-3dgs"])
    ap.add_argument("--steps", type=int, nargs="+", default=[5000], help="one per method, or one for all")
    ap.add_argument("--protocol-steps", type=int, default=128)
    ap.add_argument("--out", type=Path, default=Path("outputs/train_eval"))
    ap.add_argument("--json-out", type=Path, default=None)
    args = ap.parse_args()
    steps = args.steps * len(args.methods) if len(args.steps) == 1 else args.steps
    records = []
    for method, n in zip(args.methods, steps, strict=True):
        try:
            rec = run_one(method, args.scene, n, args.out, args.protocol_steps)
        except Exception as e:  # one failed run must not lose the others
            import traceback

            traceback.print_exc()
            rec = {"scene": str(args.scene), "method": method, "steps": n, "error": f"{type(e).__name__}: {e}"}
        records.append(rec)
        print("RESULT", json.dumps(rec), flush=True)
        if args.json_out:
            args.json_out.write_text(json.dumps(records, indent=1))
    keys = [
        "scene",
        "method",
        "steps",
        "psnr",
        "ssim",
        "encoder_psnr",
        "full_psnr",
        "train_s",
        "fps",
        "num_gaussians",
        "peak_mem_gb",
    ]
    print("| " + " | ".join(keys) + " |\n|" + "---|" * len(keys))
    for r in records:
        print("| " + " | ".join(str(r.get(k, "")) for k in keys) + " |")


if __name__ == "__main__":
    main()
