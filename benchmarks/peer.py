"""The peer plugin Splatfacto-W (its light preset and its full method), trained and scored beside ours under the same
NeRF-W protocol.

Its source is not part of this project (measured, never copied): fetch the public repository KevinXu02/splatfacto-w
and put its `splatfactow` package in a folder named by $WILLAGS_PEER_SRC (default `.gpu-peer/` at the repository
root, ignored by git), e.g.

    git -C <mirror of KevinXu02/splatfacto-w> archive HEAD splatfactow | tar x -C .gpu-peer

The run uses the peer's own `splatfacto-w-light` or `splatfacto-w` TrainerConfig unchanged except for what every
benchmark run shares: our data parser (COLMAP + NeRF-W tsv split, the same test views), the step budget, no evaluation while
training. Its appearance embedding is fitted by the protocol exactly like our latent (:class:`PeerForProtocol`).
"""

import copy
import os
import sys
from pathlib import Path
from types import SimpleNamespace

import torch
from torch import Tensor, nn

REPO = Path(__file__).resolve().parents[1]
PEER_ENV = "WILLAGS_PEER_SRC"


def peer_source() -> Path:
    """The folder holding the peer's `splatfactow` package; a clear error when it is missing."""
    src = Path(os.environ.get(PEER_ENV, REPO / ".gpu-peer")).expanduser()
    if not (src / "splatfactow" / "splatfactow_model.py").is_file():
        raise FileNotFoundError(
            f"the peer's source is not at {src}/splatfactow: fetch KevinXu02/splatfacto-w and unpack its "
            f"`splatfactow` package there (or set ${PEER_ENV}); see benchmarks/peer.py"
        )
    return src


def _peer_on_path() -> None:
    """Make the peer's `splatfactow` package importable."""
    src = str(peer_source())
    if src not in sys.path:
        sys.path.insert(0, src)


def peer_trainer_config(full: bool = False):
    """The peer's TrainerConfig with our data parser (the same splits as every other run): `splatfacto-w-light`, or
    with ``full`` its `splatfacto-w` (background model, alpha loss, robust mask). The full method's own data manager
    reads its NeRF-W parser's split and, with `eval_right_half`, trains on the left halves of the test photos, which
    the protocol forbids: it gets nerfstudio's FullImageDatamanager over our parser (as the light preset has) and
    `eval_right_half` off; nothing else of its config changes."""
    from nerfstudio.data.datamanagers.full_images_datamanager import FullImageDatamanagerConfig

    from willags_ns.data.dataparser import WillagsDataParserConfig

    _peer_on_path()
    if full:
        from splatfactow.splatfactow_config import splatfactow_config  # type: ignore[import-not-found]

        config = copy.deepcopy(splatfactow_config.config)
        config.pipeline.datamanager = FullImageDatamanagerConfig(
            dataparser=WillagsDataParserConfig(), cache_images_type="uint8"
        )
        config.pipeline.model.eval_right_half = False
        return config
    from splatfactow.splatfactow_config import splatfactow_light_config  # type: ignore[import-not-found]

    config = copy.deepcopy(splatfactow_light_config.config)
    config.pipeline.datamanager.dataparser = WillagsDataParserConfig()
    return config


def patch_peer() -> list[str]:
    """Offline, like stock splatfacto here: no LPIPS download (the protocol computes its own metrics), and its
    torch.compile'd viewmat replaced by the same maths. Call before the peer's model is built."""
    from willags_ns.render.camera import viewmat_from_c2w

    _peer_on_path()
    import splatfactow.splatfactow_model as pm  # type: ignore[import-not-found]

    pm.get_viewmat = viewmat_from_c2w
    return ["peer: get_viewmat without torch.compile"]


class _FixedEmbedding(nn.Module):
    """Stands in for the peer's nn.Embedding while the protocol fits a latent: every lookup and the table's mean
    are the latent being fitted (so gradients reach it)."""

    def __init__(self, z: Tensor):
        super().__init__()
        self.z = z

    @property
    def weight(self) -> Tensor:
        return self.z[None]

    def forward(self, idx: Tensor) -> Tensor:
        return self.z


class PeerForProtocol(nn.Module):
    """The interface willags_ns.eval.protocol reads (appearance latent in the camera metadata, default latent =
    the mean training embedding, no encoder) around a trained peer model."""

    def __init__(self, model: nn.Module):
        super().__init__()
        self.model = model
        self.config = SimpleNamespace(appearance="willags")
        self.appearance_nets = SimpleNamespace(vae=None)

    @property
    def device(self):
        return self.model.device

    def default_latent(self) -> Tensor:
        return self.model.appearance_embeds.weight.detach().mean(0)

    def image_latents(self) -> tuple[Tensor, Tensor]:
        w = self.model.appearance_embeds.weight.detach()
        return w, torch.ones(w.shape[0], dtype=torch.bool, device=w.device)

    def lpips_metric(self):
        return None

    def get_outputs(self, camera):
        md = dict(camera.metadata or {})
        z = md.pop("appearance_latent", None)
        if z is None:
            return self.model.get_outputs(camera)
        md.pop("cam_idx", None)  # the peer would look its own table up by index
        camera.metadata = md
        table, avg = self.model.appearance_embeds, self.model.config.use_avg_appearance
        self.model.appearance_embeds = _FixedEmbedding(torch.as_tensor(z, device=self.device))
        self.model.config.use_avg_appearance = True
        try:
            return self.model.get_outputs(camera)
        finally:
            self.model.appearance_embeds = table
            self.model.config.use_avg_appearance = avg
