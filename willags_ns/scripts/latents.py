"""`willags-latents`: every training image's appearance latent, with its file name, in one .npz.

    willags-latents --load-config run/config.yml --output latents.npz

The file holds `latents` [N, D] (float32, the VAE encoder's mean of each training image as last refreshed during
training, or the embedding rows of an embedding-table model), `names` [N] (file names, dataset order) and `seen`
[N] (False: never visited in training, its row is meaningless). One row saved with numpy is a `latent:FILE.npy`
SPEC: `np.save("z.npy", np.load("latents.npz")["latents"][3])`.
"""

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import tyro

from willags_ns.engine.checkpoints import write_file_atomic


@dataclass
class ExportLatents:
    """Write every training image's appearance latent with its file name."""

    load_config: Path
    """Path to the run's config.yml."""
    output: Path = Path("latents.npz")
    """The .npz to write."""


def training_latents(model) -> tuple[np.ndarray, list[str], np.ndarray]:
    """(latents [N, D] float32, names [N], seen [N] bool) of a WillagsModel's training images."""
    if getattr(model.config, "appearance", None) != "willags" or model.appearance_nets is None:
        raise SystemExit("error: this checkpoint has no appearance model (willags-3dgs): no latents")
    lat, seen = model.image_latents()  # embedding-table models: the rows (every row is trained)
    names = list(model.image_names)[: lat.shape[0]]
    return lat.detach().cpu().float().numpy(), names, seen.cpu().numpy().astype(bool)


def write_latents(path: Path, latents: np.ndarray, names: list[str], seen: np.ndarray) -> Path:
    """The .npz at exactly `path` (numpy would add ".npz" to a name without it), written through a partial file
    renamed over it: a full disk or a kill leaves the previous file whole and no partial one. A failed write is one
    WillagsIOError naming the file."""
    return write_file_atomic(
        path, lambda f: np.savez(f, latents=latents, names=np.array(names), seen=seen), latents.nbytes
    )


def main(cfg: ExportLatents) -> Path:
    from nerfstudio.utils.eval_utils import eval_setup
    from nerfstudio.utils.rich_utils import CONSOLE

    _, pipeline, _, _ = eval_setup(cfg.load_config, test_mode="inference")
    lat, names, seen = training_latents(pipeline.model)
    cfg.output.parent.mkdir(parents=True, exist_ok=True)
    write_latents(cfg.output, lat, names, seen)
    CONSOLE.print(f"{lat.shape[0]} latents of size {lat.shape[1]} ({int(seen.sum())} seen in training): {cfg.output}")
    return cfg.output


def entrypoint() -> None:
    """Entrypoint for use with pyproject scripts."""
    tyro.extras.set_accent_color("bright_yellow")
    main(tyro.cli(ExportLatents))


if __name__ == "__main__":
    entrypoint()
