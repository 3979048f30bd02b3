"""`make demo`: train willags on the embedded default scene on CPU, then render test views next to their photos
(each tile labelled: the photo on the left, the render on the right) and a labelled appearance grid: one test view under training images' appearances, a new photo's (a test image the
model never trained on: its latent fitted to the photo, or through the encoder of a VAE-latent model), two sampled
appearances and an interpolation. Each tile is labelled with the SPEC that renders it
(`willags-render ... --appearance SPEC`). The test views render with the mean appearance, or with the test image's
own through the encoder of a VAE-latent model.

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
    """Options of the demo (the defaults take about 5 minutes on 2 CPU cores: README.md)."""

    output_dir: Path = Path("demo_outputs")
    """Where the run (checkpoint, config.yml, tensorboard) and the PNGs go."""
    method: str = "willags"
    """Method to train (willags, willags-lite, willags-3dgs)."""
    steps: int = 500
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


def _font(size: int):
    from PIL import ImageFont

    try:
        return ImageFont.load_default(size=size)  # Pillow >= 10.1 with FreeType: a scalable font
    except TypeError:
        return ImageFont.load_default()


def labelled_grid(rows: list[tuple[str, list[tuple[str, np.ndarray]]]], scale: int = 2, pad: int = 6) -> np.ndarray:
    """Rows of labelled tiles: (row title, [(label, image [H, W, 3] uint8)]). Tiles are upscaled `scale` times
    (nearest) so colour differences are visible; the label sits under each tile, the title above each row."""
    from PIL import ImageDraw

    h, w = (int(x) * scale for x in rows[0][1][0][1].shape[:2])
    label_h, title_h = 20, 24
    ncol = max(len(tiles) for _, tiles in rows)
    width = pad + ncol * (w + pad)
    height = pad + sum(title_h + h + label_h + pad for _ in rows)
    canvas = Image.new("RGB", (width, height), (255, 255, 255))
    draw = ImageDraw.Draw(canvas)
    font, title_font = _font(13), _font(16)
    y = pad
    for title, tiles in rows:
        draw.text((pad, y + 2), title, fill=(0, 0, 0), font=title_font)
        y += title_h
        for j, (label, img) in enumerate(tiles):
            x = pad + j * (w + pad)
            canvas.paste(Image.fromarray(img).resize((w, h), Image.Resampling.NEAREST), (x, y))
            while draw.textlength(label, font=font) > w and len(label) > 4:  # long paths: keep the end
                label = "..." + label[4:]
            draw.text((x, y + h + 3), label, fill=(40, 40, 40), font=font)
        y += h + label_h + pad
    return np.asarray(canvas)


PHOTO_REFINE_STEPS = 50
"""Adam steps fitting the new photo's latent when the model has no encoder (an embedding table)."""


def appearance_grid(pipeline, out_dir: Path, n_train: int = 4, n_interp: int = 5) -> np.ndarray:
    """The labelled appearance grid of the demo (see the module docstring); every latent comes from a SPEC."""
    from willags_ns.appearance_spec import RefineOptions, resolve_latent

    model = pipeline.model
    test = pipeline.datamanager.eval_dataset
    cam = test.cameras[0:1]
    names = list(model.image_names)
    seen = torch.nonzero(model.image_latents()[1]).flatten().tolist()  # training images with a known latent
    picks = [seen[int(k)] for k in np.linspace(0, len(seen) - 1, min(n_train, len(seen)))] if seen else []

    def tile(spec: str) -> tuple[str, np.ndarray]:
        return spec, to_uint8(render(pipeline, cam, resolve_latent(spec, model, context="demo")))

    rows = []
    if picks:
        train = pipeline.datamanager.train_dataset
        photos = [(names[i], to_uint8(train.get_image_float32(i)[..., :3])) for i in picks]
        rows.append(("training photos (their own views)", photos))
        rows.append(("their appearances, on test view 0", [tile(f"image:{names[i]}") for i in picks]))
    row = []
    if len(test) > 1:
        # a photo the model never trained on: another test image, through the encoder or, for an embedding-table
        # model, fitted to the photo (what `willags-render --appearance photo:P --refine-steps N` does)
        photo = out_dir / "new_photo.png"
        Image.fromarray(to_uint8(test.get_image_float32(1)[..., :3])).save(photo)
        refine = None if model.appearance_nets.vae is not None else RefineOptions(steps=PHOTO_REFINE_STEPS)
        cams = pipeline.datamanager.train_dataset.cameras
        z = resolve_latent(f"photo:{photo}", model, refine=refine, cameras=cams, context="demo")
        label = f"photo:{photo.name}" + (f" (--refine-steps {PHOTO_REFINE_STEPS})" if refine else "")
        row += [("the new photo (not trained on)", to_uint8(test.get_image_float32(1)[..., :3]))]
        row += [(label, to_uint8(render(pipeline, cam, z)))]
    row += [tile("sample:0"), tile("sample:1")]
    rows.append(("a new photo's appearance; two sampled appearances", row))
    if len(picks) >= 2:
        a, b = names[picks[0]], names[picks[-1]]
        interp = [(f"T = {t:.2f}", tile(f"interp:{a},{b},{t:.2f}")[1]) for t in np.linspace(0, 1, n_interp)]
        rows.append((f"interp:{a},{b},T", interp))
    return labelled_grid(rows)


@torch.no_grad()
def render(pipeline, camera, latent: torch.Tensor | None = None) -> torch.Tensor:
    cam = camera.to(pipeline.model.device)
    if latent is not None:
        cam.metadata = dict(cam.metadata or {})
        cam.metadata["appearance_latent"] = latent
    return pipeline.model.get_outputs_for_camera(cam)["rgb"]


def views_rows(pipeline, n_views: int = 4) -> list[tuple[str, list[tuple[str, np.ndarray]]]]:
    """The rows of views_gt_vs_render.png, for :func:`labelled_grid`: per test view (never trained on), the photo
    on the left and the render on the right, each labelled, with the appearance the render used."""
    model = pipeline.model
    test = pipeline.datamanager.eval_dataset
    encoder = model.config.appearance == "willags" and model.appearance_nets.vae is not None
    how = "the photo's appearance" if encoder else "mean appearance"
    rows = []
    for i in range(min(n_views, len(test))):
        cam = test.cameras[i : i + 1]
        gt = test.get_image_float32(i)[..., :3]
        latent = model.encode_image(gt) if encoder else None  # the test image's appearance, through the encoder
        name = Path(test.image_filenames[i]).name
        tiles = [("the photo", to_uint8(gt)), (f"the render, {how}", to_uint8(render(pipeline, cam, latent)))]
        rows.append((f"test view {i}: {name} (not trained on)", tiles))
    return rows


def render_outputs(run_dir: Path, out_dir: Path) -> dict[str, Path]:
    from nerfstudio.utils.eval_utils import eval_setup

    _, pipeline, _, _ = eval_setup(run_dir / "config.yml", test_mode="test")
    model = pipeline.model
    model.eval()
    paths = {"views": out_dir / "views_gt_vs_render.png"}
    Image.fromarray(labelled_grid(views_rows(pipeline))).save(paths["views"])

    if model.config.appearance == "willags":
        paths["appearances"] = out_dir / "appearance_grid.png"
        Image.fromarray(appearance_grid(pipeline, out_dir)).save(paths["appearances"])
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
