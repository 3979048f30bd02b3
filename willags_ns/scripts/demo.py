"""`make demo`: train willags on the embedded default scene on CPU, then render test views next to ground truth
and an appearance strip (3 training appearances, an interpolation, 3 samples z ~ N(0, I)).

Training goes through nerfstudio's own `ns-train` (a subprocess, exactly what a user runs); rendering loads the
checkpoint through nerfstudio's `eval_setup`.
"""

import os
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
import tyro
from PIL import Image


@dataclass
class DemoConfig:
    """Options of the demo (defaults fit the 5-minute budget on 2 CPU cores)."""

    output_dir: Path = Path("demo_outputs")
    """Where the run (checkpoint, config.yml, tensorboard) and the PNGs go."""
    method: str = "willags"
    """Method to train (willags, willags-lite, willags-3dgs)."""
    steps: int = 600
    """Training iterations."""
    data: Path | None = None
    """Scene directory; None = the embedded synthetic in-the-wild scene."""
    skip_train: bool = False
    """Reuse the last run in output_dir (render only)."""


def train_args(cfg: DemoConfig) -> list[str]:
    """The ns-train command line of the demo: the short-run schedule (no downscaled warm-up, early refinement)."""
    steps = cfg.steps
    args = [
        sys.executable,
        "-m",
        "nerfstudio.scripts.train",
        cfg.method,
        "--max-num-iterations",
        str(steps),
        "--steps-per-save",
        str(steps),
        "--vis",
        "tensorboard",
        "--output-dir",
        str(cfg.output_dir),
        "--experiment-name",
        "demo",
        "--timestamp",
        "run",
        "--pipeline.model.num-downscales",
        "0",
        "--pipeline.model.warmup-length",
        str(max(50, steps // 6)),
        "--pipeline.model.refine-every",
        "50",
        "--pipeline.model.reset-alpha-every",
        "1000",
        "--pipeline.model.stop-split-at",
        str(int(steps * 0.8)),
        "--pipeline.model.log-images-every",
        str(max(1, steps // 3)),
    ]
    if cfg.method != "willags-3dgs":
        args += ["--pipeline.model.mask.warmup-steps", str(steps // 4)]
    if cfg.data is not None:
        args += ["--data", str(cfg.data)]
    return args


def to_uint8(img: torch.Tensor) -> np.ndarray:
    return (img.detach().clamp(0, 1).cpu().numpy() * 255).round().astype(np.uint8)


def grid(rows: list[list[np.ndarray]], pad: int = 2) -> np.ndarray:
    """Tile images (all the same size) into one array with white padding."""
    h, w = rows[0][0].shape[:2]
    ncol = max(len(r) for r in rows)
    out = np.full((len(rows) * (h + pad) + pad, ncol * (w + pad) + pad, 3), 255, np.uint8)
    for i, r in enumerate(rows):
        for j, im in enumerate(r):
            out[pad + i * (h + pad) : pad + i * (h + pad) + h, pad + j * (w + pad) : pad + j * (w + pad) + w] = im
    return out


@torch.no_grad()
def render(pipeline, camera, latent: torch.Tensor | None = None) -> torch.Tensor:
    cam = camera.to(pipeline.model.device)
    if latent is not None:
        cam.metadata = dict(cam.metadata or {})
        cam.metadata["appearance_latent"] = latent
    return pipeline.model.get_outputs_for_camera(cam)["rgb"]


def render_outputs(run_dir: Path, out_dir: Path) -> dict[str, Path]:
    from nerfstudio.utils.eval_utils import eval_setup

    from willags_ns.viewer import interpolate_latents, sample_latent

    _, pipeline, _, _ = eval_setup(run_dir / "config.yml", test_mode="test")
    model = pipeline.model
    model.eval()
    dm = pipeline.datamanager
    test = dm.eval_dataset
    n_views = min(4, len(test))
    rows = []
    for i in range(n_views):
        cam = test.cameras[i : i + 1]
        gt = test.get_image_float32(i)[..., :3]
        if model.config.appearance == "willags" and model.appearance_nets.vae is not None:
            latent = model.encode_image(gt)  # the test image's appearance, through the encoder
        else:
            latent = None
        rows.append([to_uint8(gt), to_uint8(render(pipeline, cam, latent))])
    paths = {"views": out_dir / "views_gt_vs_render.png"}
    Image.fromarray(grid(rows)).save(paths["views"])

    if model.config.appearance == "willags":
        cam = test.cameras[0:1]
        seen = torch.nonzero(model.train_latent_seen).flatten().tolist()
        picks = [seen[int(k)] for k in np.linspace(0, len(seen) - 1, 3)] if seen else []
        lat = model.train_latents
        row_train = [to_uint8(render(pipeline, cam, lat[i])) for i in picks]
        row_interp = []
        if len(picks) >= 2:
            za, zb = lat[picks[0]], lat[picks[-1]]
            row_interp = [to_uint8(render(pipeline, cam, interpolate_latents(za, zb, t))) for t in np.linspace(0, 1, 5)]
        row_sample = [to_uint8(render(pipeline, cam, sample_latent(lat.shape[1], s))) for s in range(3)]
        paths["appearances"] = out_dir / "appearance_strip.png"
        Image.fromarray(grid([r for r in (row_train, row_interp, row_sample) if r])).save(paths["appearances"])
    return paths


def main(cfg: DemoConfig) -> None:
    t0 = time.time()
    cfg.output_dir.mkdir(parents=True, exist_ok=True)
    run_dir = cfg.output_dir / "demo" / cfg.method / "run"
    if not cfg.skip_train:
        print("willags demo: training:", " ".join(train_args(cfg)[3:]), flush=True)
        env = dict(os.environ, PYTHONWARNINGS=os.environ.get("PYTHONWARNINGS", "ignore"))
        subprocess.run(train_args(cfg), check=True, env=env)
    t_train = time.time() - t0
    paths = render_outputs(run_dir, cfg.output_dir)
    total = time.time() - t0
    print(f"\nwillags demo done in {total:.0f} s (training {t_train:.0f} s).")
    print(f"  checkpoint + config: {run_dir}")
    for name, p in paths.items():
        print(f"  {name}: {p}")


def entrypoint() -> None:
    main(tyro.cli(DemoConfig))


if __name__ == "__main__":
    entrypoint()
