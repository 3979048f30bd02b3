"""Where the appearance latent z [D] of a forward pass comes from.

Training: this step's image through the VAE encoder (reparameterised), or its row of the per-image embedding table;
each visit records the image's mean latent (the appearances users pick later).

Rendering (viewer, ns-render, eval), first that applies:

1. the camera's metadata `appearance_latent` (the NeRF-W protocol's fitted latent);
2. the camera's `cam_idx` (`ns-render --camera-idx N`: that training image's appearance), unless an appearance was
   chosen or the viewer's panel is open;
3. the chosen appearance: `render_latent`, else $WILLAGS_APPEARANCE (a SPEC), else
4. the default: the mean of the training images' latents.

Latents handed out for rendering are memoised by what they are computed from (:class:`AppearanceLatents`), so a
renderer that asks every frame pays no host sync, and their cache key (:meth:`AppearanceLatents.key_of`) costs none.

The model's latent methods (`current_latent`, `render_latent`, `image_latents`, `encode_image`, ...: what the viewer,
the CLIs, the NeRF-W protocol and the benchmarks call; willags_ns/model.py) hand its networks and buffers to the
functions here.
"""

import os
import warnings
from collections.abc import Callable
from typing import TYPE_CHECKING, NamedTuple, Protocol

import torch
from torch import Tensor

from willags_ns.appearance.networks import AppearanceNetworks
from willags_ns.appearance.vae import AppearanceVAE, reparameterize, vae_loss
from willags_ns.tensor_constants import constant

if TYPE_CHECKING:
    pass


APPEARANCE_ENV = "WILLAGS_APPEARANCE"
"""Environment variable read by the model when no appearance was chosen in code: lets nerfstudio's own
`ns-render`, `ns-export gaussian-splat` and `ns-viewer` use a chosen appearance (they take no model options)."""

MAX_LATENT_NORM = 100.0
"""Latents with a larger norm are scaled down to it (with a warning). Encoder latents and N(0, I) samples have a
norm near sqrt(D) (about 6 for D = 32); 100 is far outside anything training saw, and beyond it the colour field
only saturates (or, for a file with garbage in it, produces noise)."""


class AppearanceSpecError(ValueError):
    """A SPEC that cannot be parsed or resolved; the message names the bad part."""


def checked_latent(z: Tensor, source: str, max_norm: float = MAX_LATENT_NORM) -> Tensor:
    """z unchanged if finite with norm <= max_norm; scaled to max_norm with a warning if larger; an error naming
    `source` if it holds NaN or Inf (a NaN latent would make every pixel NaN)."""
    if not torch.isfinite(z).all():
        raise AppearanceSpecError(f"{source}: the latent holds NaN or Inf values")
    norm = float(z.norm())
    if norm > max_norm:
        warnings.warn(
            f"{source}: latent norm {norm:.3g} is far outside the training latents; scaled down to {max_norm:g}",
            stacklevel=2,
        )
        z = z * (max_norm / norm)
    return z


def mean_latent(model) -> Tensor:
    """The mean of the training images' latents (what the model renders when nothing is chosen)."""
    lat, seen = model.image_latents()
    if bool(seen.any()):
        return lat[seen].mean(0)
    return torch.zeros(lat.shape[1], device=lat.device)


def image_as_float(image: Tensor) -> Tensor:
    """A datamanager's cached image (uint8 or float, [H, W, C]) as float in [0, 1]."""
    return image.float() / 255.0 if image.dtype == torch.uint8 else image.float()


def image_chw(image: Tensor, device) -> Tensor:
    """An image [H, W, C] (uint8 or float) as the encoder's input [3, H, W] in [0, 1] on `device`."""
    return image_as_float(image)[..., :3].permute(2, 0, 1).to(device)


def versions(tensors: list[Tensor]) -> tuple:
    """(storage pointer, version counter) of each tensor: changes when a tensor is replaced or edited in place
    (optimiser steps, load_state_dict, buffer writes), never otherwise."""
    return tuple((t.data_ptr(), t._version) for t in tensors)


def keeps_latent_memo(nets: AppearanceNetworks) -> bool:
    """Whether the training images' latents are remembered in the model's buffers (`train_latents`,
    `train_latent_seen`): with the VAE, the encoder's mean at each image's last visit; an embedding table is its own
    record, and writing a flag into a device tensor from the host every step would cost a synchronisation."""
    return nets.embeddings is None


def stored_latents(nets: AppearanceNetworks, train_latents: Tensor, train_latent_seen: Tensor) -> tuple[Tensor, Tensor]:
    """(latents [num_train, D], known [num_train] bool) of the training images, detached.

    An embedding table's rows are the latents (current values; every row exists from the start). With the VAE,
    the encoder's mean recorded at each image's last training visit (`train_latents`), known once the image was
    drawn (`train_latent_seen`)."""
    if not keeps_latent_memo(nets):
        lat = nets.embeddings.weight.detach()
        return lat, torch.ones(lat.shape[0], dtype=torch.bool, device=lat.device)
    return train_latents, train_latent_seen


class TrainingLatent(NamedTuple):
    """The latent of a training step's image, and what its loss and the EMA teacher read."""

    z: Tensor
    """[D] the posterior sample (VAE) or the table's row (embedding)."""
    mu: Tensor
    """[D] the posterior mean (VAE) or the row."""
    logvar: Tensor | None
    """[D] the posterior log-variance (VAE), None for the table."""
    vae_in: Tensor | None
    """[3, H, W] the encoder's input (VAE), None for the table."""
    image_idx: int
    """The training image's index."""


def training_latent(
    nets: AppearanceNetworks,
    batch: dict | None,
    metadata: dict,
    device,
    train_latents: Tensor,
    train_latent_seen: Tensor,
) -> TrainingLatent:
    """The latent of this training step's image: the VAE posterior sample (or the embedding row). Writes the image's
    mean latent into `train_latents` / `train_latent_seen` (in place: they are the model's buffers)."""
    if batch is None:
        raise RuntimeError(
            "willags: the model got no training image; train it through WillagsPipeline (method configs "
            "'willags*' do) or call model.set_train_batch(batch) before model(camera)"
        )
    idx = int(batch["image_idx"]) if "image_idx" in batch else int(metadata.get("cam_idx", 0))
    img = image_chw(batch["image"], device) if nets.vae is not None else None  # the encoder's input; a table has none
    mu, logvar = nets.latent_stats(img, idx)
    z = reparameterize(mu[None], logvar[None])[0] if logvar is not None else mu
    if keeps_latent_memo(nets) and idx < train_latents.shape[0]:
        train_latents[idx] = mu.detach()
        train_latent_seen[idx] = True
    return TrainingLatent(z, mu, logvar, img if logvar is not None else None, idx)


class AppearancePanel(Protocol):
    """A user interface that chooses the appearance while it is shown (the viewer's panel, willags_ns/viewer.py)."""

    def is_open(self) -> bool: ...


class AppearanceLatents:
    """The chosen appearance and the memo of the latents handed out for rendering.

    Holds no tensors of the model: the training images' latents are passed in by the caller (they are the model's
    buffers, replaced when the model moves between devices).
    """

    def __init__(self) -> None:
        self.render_latent: Tensor | None = None
        """Appearance override for eval / viewer / export ([D]); None: $WILLAGS_APPEARANCE, else the default."""
        self.panel: AppearancePanel | None = None
        """The viewer's panel, when one is attached: while it is open, its choice (the mean included) is shown."""
        self._memo: dict[str, tuple[tuple, Tensor]] = {}

    def memo(self, name: str, key: tuple, make: Callable[[], Tensor]) -> Tensor:
        """`make()`, recomputed only when `key` changes. A rendered frame needs its latent twice (to choose it, then
        to key the per-appearance caches); recomputing it each frame costs host syncs (boolean indexing, value
        checks, a copy to the host for the cache key) that stall a renderer otherwise bound by kernel launches."""
        hit = self._memo.get(name)
        if hit is not None and hit[0] == key:
            return hit[1]
        z = make()
        self._memo[name] = (key, z)
        return z

    def key_of(self, z: Tensor) -> tuple:
        """Cache key of latent z: its memo key when z came from :meth:`memo` (no host sync), else its bytes."""
        for name, (key, t) in self._memo.items():
            if t is z:
                return (name, *key)
        return ("value", z.detach().cpu().numpy().tobytes())

    def default(
        self, nets: AppearanceNetworks, train_latents: Tensor, train_latent_seen: Tensor, mean: Callable[[], Tensor]
    ) -> Tensor:
        """The appearance used when none is chosen: `mean()` (the mean of the training images' latents), recomputed
        only when the latents it is computed from change."""
        src = [train_latents, train_latent_seen] if keeps_latent_memo(nets) else [nets.embeddings.weight]
        return self.memo("default", versions(src), mean)

    def chosen(self, device, from_env: Callable[[str], Tensor | None], default: Callable[[], Tensor]) -> Tensor:
        """The chosen appearance: `render_latent` if set, else `from_env($WILLAGS_APPEARANCE)` if set, else
        `default()`."""
        if self.render_latent is not None:
            chosen = self.render_latent

            def checked() -> Tensor:
                self.render_latent = checked_latent(chosen, "render_latent")  # no NaN pixels, ever
                return self.render_latent.to(device)

            # keyed by the chosen tensor itself (kept alive by the key, so its id cannot be reused) and its version
            # counter (bumped by any in-place edit): a new or edited latent is checked again
            return self.memo("render", (id(chosen), chosen._version, chosen), checked)
        spec = os.environ.get(APPEARANCE_ENV)
        if spec:
            z = from_env(spec)
            if z is not None:
                self.render_latent = z
                return z.to(device)
        return default()

    def for_camera(self, cam_idx, stored: Callable[[], tuple[Tensor, Tensor]], device) -> Tensor | None:
        """Training image `cam_idx`'s latent when nothing else chose the appearance: `ns-render camera-path
        --camera-idx N` (nerfstudio's convention: that image's appearance). Not while the viewer is open: its cameras
        carry cam_idx too (0, or the last training frustum clicked) and the panel's choice, the mean included, is
        what it shows."""
        if cam_idx is None or self.render_latent is not None or os.environ.get(APPEARANCE_ENV):
            return None
        if self.panel is not None and self.panel.is_open():
            return None
        lat, known = stored()
        i = int(cam_idx)
        if not (0 <= i < lat.shape[0]) or not bool(known[i]):
            return None
        return lat[i].to(device)

    def for_render(
        self, metadata: dict, device, stored: Callable[[], tuple[Tensor, Tensor]], chosen: Callable[[], Tensor]
    ) -> Tensor:
        """z [D] of a forward pass outside training: the camera's metadata, its training image, or `chosen()`."""
        if "appearance_latent" in metadata:
            return torch.as_tensor(metadata["appearance_latent"], device=device).reshape(-1).float()
        z = self.for_camera(metadata.get("cam_idx"), stored, device)
        return z if z is not None else chosen()


def latent_prior(z: Tensor, center: Tensor) -> Tensor:
    """0.5 * ||z - center||^2: the negative log-density (up to a constant) of a unit Gaussian prior around `center`
    ([D] each; the embedding table's row of the step and the rows' mean, held fixed by the caller), whose gradient
    z - center pulls the row towards the others (latent.prior_weight)."""
    # mse_loss's sum: sum((z - center)^2) in one operator and one backward node instead of three
    return constant(0.5, z) * torch.nn.functional.mse_loss(z, center, reduction="sum")


def latent_loss(
    vae: AppearanceVAE, z: Tensor, mu: Tensor, logvar: Tensor, vae_in: Tensor, beta: float, recon_reduction: str
) -> tuple[Tensor, dict, Tensor]:
    """L_VAE of this training step (L1 reconstruction of the encoder's input `vae_in` [3, H, W] from z + beta KL of
    the posterior (mu, logvar); appearance/vae.py): (loss, its parts, the reconstruction [1, 3, S, S] detached)."""
    recon = vae.decode(z[None])
    target = vae.prepare(vae_in[None])
    l_vae, parts = vae_loss(recon, target, mu[None], logvar[None], beta=beta, recon_reduction=recon_reduction)
    return l_vae, parts, recon.detach()
