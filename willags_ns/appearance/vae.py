"""beta-VAE appearance encoder: a training image -> a Gaussian posterior over the appearance latent z.

WilLaGS conditions the scene's colours on one latent per image. The encoder sees the whole image at a small,
fixed size and outputs ``N(mu, sigma^2)`` over ``z in R^D`` (D = 64); a decoder reconstructs the small image, and

    L_VAE = L1(recon, target) + beta * KL(q(z | I) || N(0, I)),        beta = 2.

During training ``z`` is sampled with the reparameterisation trick (:func:`reparameterize`); at evaluation the
posterior mean ``mu`` is used. The KL term keeps the latent space smooth (nearby z = similar appearance), which is
what makes latent interpolation and test-time latent fitting well posed.

Why 64x64 input: the latent should capture *global* appearance (exposure, white balance, tone curve,
low-frequency shading such as sun vs overcast), not geometry or transient content. At 64x64 those survive
(they are low-frequency by nature) while most high-frequency detail, including small occluders, is averaged away
by the antialiased downsampling. It also keeps the encoder cheap: four stride-2 convolutions on 64x64 cost a few
MFLOPs, negligible next to rasterisation even on a CPU. Non-square images are squashed to a square; the aspect
change does not matter for a global descriptor.

Numerical safety: ``logvar`` is clamped to [LOGVAR_MIN, LOGVAR_MAX] = [-10, 10] (sigma in [6.7e-3, 148]), so
``exp(logvar)`` in the KL and in the sampler can neither overflow nor underflow to a zero-variance posterior that
would make the KL blow up (``-logvar`` term).
"""

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Literal

import torch
import torch.nn.functional as F
from jaxtyping import Float
from torch import Tensor, nn

LOGVAR_MIN = -10.0
"""Lower clamp of the encoder's log-variance (sigma >= 6.7e-3)."""
LOGVAR_MAX = 10.0
"""Upper clamp of the encoder's log-variance (sigma <= 148)."""


@dataclass
class VAEConfig:
    """Hyper-parameters of the appearance beta-VAE (latent.kind="vae"; its code size is latent.dim)."""

    image_size: int = 64
    """Side S of the square image the encoder sees and the decoder reconstructs. Must be divisible by
    2 ** len(channels). 64 keeps global appearance (exposure, white balance, low-frequency shading) and drops
    most detail; it is cheap on a CPU."""
    beta: float = 2.0
    """Weight of the KL term in L_VAE = L1 + beta * KL (beta-VAE; the paper's 2)."""
    recon_reduction: Literal["mean", "sum"] = "sum"
    """Scale of the L1 reconstruction term: "sum" over pixels and channels per image (the textbook beta-VAE
    likelihood scale, against which beta=2 on a KL summed over latent dims is meaningful) or "mean". With
    "mean" the KL dominates and the posterior collapses to the prior (z carries no appearance: docs/design.md,
    "The VAE's reconstruction scale"), so the model uses "sum"."""
    channels: tuple[int, ...] = (32, 64, 128, 128)
    """Output channels of the encoder's stride-2 convolutions (the decoder mirrors them). Four stages take
    64x64 down to 4x4."""
    weight: float = 0.01
    """Weight of L_VAE = L1 recon + beta * KL in the total loss."""


def _resize(images: Tensor, size: int) -> Tensor:
    """Antialiased bilinear resize to ``size x size`` (antialias matters when downsampling 8x or more)."""
    if images.shape[-2:] == (size, size):
        return images
    return F.interpolate(images, size=(size, size), mode="bilinear", align_corners=False, antialias=True)


class AppearanceVAE(nn.Module):
    """Convolutional beta-VAE over downsampled training images.

    Encoder: ``len(channels)`` blocks of (3x3 conv stride 2, SiLU) then a linear layer to ``(mu, logvar)``.
    Decoder: a linear layer to the smallest feature map, then mirrored blocks of (2x nearest upsample,
    3x3 conv, SiLU) and a final 3x3 conv + sigmoid. No normalisation layers: training feeds one image per step,
    where BatchNorm statistics are meaningless.
    """

    def __init__(self, latent_dim: int = 64, image_size: int = 64, channels: Sequence[int] = (32, 64, 128, 128)):
        super().__init__()
        channels = tuple(int(c) for c in channels)
        if len(channels) == 0:
            raise ValueError("channels must not be empty")
        factor = 2 ** len(channels)
        if image_size % factor != 0:
            raise ValueError(f"image_size={image_size} must be divisible by 2**len(channels)={factor}")
        self.latent_dim = latent_dim
        self.image_size = image_size
        self.channels = channels
        self.bottom = image_size // factor  # side of the smallest feature map
        flat = channels[-1] * self.bottom * self.bottom

        enc = []
        c_in = 3
        for c in channels:
            enc += [nn.Conv2d(c_in, c, 3, stride=2, padding=1), nn.SiLU()]
            c_in = c
        self.encoder = nn.Sequential(*enc)
        self.to_stats = nn.Linear(flat, 2 * latent_dim)
        # Start with a near-prior posterior (mu ~ 0, logvar ~ 0): the KL starts small and z starts informative-free.
        nn.init.normal_(self.to_stats.weight, std=1e-3)
        nn.init.zeros_(self.to_stats.bias)

        self.from_latent = nn.Linear(latent_dim, flat)
        dec = []
        rev = list(reversed(channels))
        for c_in, c_out in zip(rev, rev[1:] + [rev[-1]], strict=True):
            dec += [nn.Upsample(scale_factor=2, mode="nearest"), nn.Conv2d(c_in, c_out, 3, padding=1), nn.SiLU()]
        dec += [nn.Conv2d(rev[-1], 3, 3, padding=1)]
        self.decoder = nn.Sequential(*dec)

    def prepare(self, images: Float[Tensor, "B 3 H W"]) -> Float[Tensor, "B 3 S S"]:
        """The encoder's input and the reconstruction target: ``images`` resized to ``image_size``."""
        if images.dim() != 4 or images.shape[1] != 3:
            raise ValueError(f"expected images [B, 3, H, W], got {tuple(images.shape)}")
        return _resize(images, self.image_size)

    def encode(self, images: Float[Tensor, "B 3 H W"]) -> tuple[Float[Tensor, "B D"], Float[Tensor, "B D"]]:
        """Posterior parameters ``(mu, logvar)``; ``images`` in [0, 1] at any size (resized internally)."""
        x = self.prepare(images) * 2.0 - 1.0  # [B, 3, S, S], zero-centred input
        h = self.encoder(x).flatten(1)  # [B, C * s * s]
        mu, logvar = self.to_stats(h).chunk(2, dim=-1)  # [B, D] each
        return mu, logvar.clamp(LOGVAR_MIN, LOGVAR_MAX)

    def decode(self, z: Float[Tensor, "B D"]) -> Float[Tensor, "B 3 S S"]:
        """Reconstruction of the downsampled image, in (0, 1)."""
        h = self.from_latent(z).view(z.shape[0], self.channels[-1], self.bottom, self.bottom)
        return torch.sigmoid(self.decoder(h))

    def forward(
        self,
        images: Float[Tensor, "B 3 H W"],
        sample: bool | None = None,
        generator: torch.Generator | None = None,
    ) -> dict[str, Tensor]:
        """Encode, pick z (a sample when ``sample`` else mu; default: sample iff training), decode.

        Returns ``{"mu", "logvar", "z", "recon", "target"}``.
        """
        mu, logvar = self.encode(images)
        if sample is None:
            sample = self.training
        z = reparameterize(mu, logvar, generator=generator) if sample else mu
        return {"mu": mu, "logvar": logvar, "z": z, "recon": self.decode(z), "target": self.prepare(images)}


def reparameterize(
    mu: Float[Tensor, "B D"], logvar: Float[Tensor, "B D"], generator: torch.Generator | None = None
) -> Float[Tensor, "B D"]:
    """``z = mu + exp(logvar / 2) * eps``, ``eps ~ N(0, I)``: a sample whose gradient reaches mu and logvar."""
    eps = torch.randn(mu.shape, generator=generator, device=mu.device, dtype=mu.dtype)
    return mu + torch.exp(0.5 * logvar) * eps


def kl_divergence(mu: Float[Tensor, "B D"], logvar: Float[Tensor, "B D"]) -> Tensor:
    """``KL(N(mu, exp(logvar)) || N(0, I))``, summed over latent dims, averaged over the batch.

    Per dim: ``0.5 * (mu^2 + exp(logvar) - 1 - logvar)``; 0 exactly at (mu, logvar) = (0, 0), positive elsewhere.
    Example: mu = 1, logvar = 0 in one dim gives 0.5.
    """
    kl = 0.5 * (mu.pow(2) + logvar.exp() - 1.0 - logvar)  # [B, D]
    return kl.sum(dim=-1).mean()


def vae_loss(
    recon: Float[Tensor, "B 3 S S"],
    target: Float[Tensor, "B 3 S S"],
    mu: Float[Tensor, "B D"],
    logvar: Float[Tensor, "B D"],
    beta: float = 2.0,
    recon_reduction: Literal["mean", "sum"] = "mean",
) -> tuple[Tensor, dict[str, Tensor]]:
    """``L_VAE = L1(recon, target) + beta * KL``; returns ``(loss, {"vae_recon", "vae_kl"})``.

    The KL is a per-image sum over the D latent dims (batch mean). ``recon_reduction`` sets the L1 scale:
    "mean" (default) = mean over pixels and channels, so L_VAE is on the scale of the rendering loss and the
    paper's 0.01 weight stays meaningful; "sum" = sum over pixels and channels per image (batch mean), the
    textbook VAE likelihood scale. With "mean" and beta = 2 the VAE alone collapses to the prior (one nat of KL costs
    as much as 0.5 of mean L1); in WilLaGS the rendering loss also reaches the encoder through z, and "sum" makes
    the VAE informative on its own (docs/design.md, "The VAE's reconstruction scale").
    """
    if recon.shape != target.shape:
        raise ValueError(f"recon {tuple(recon.shape)} and target {tuple(target.shape)} differ")
    err = (recon - target).abs()
    if recon_reduction == "mean":
        recon_l1 = err.mean()
    elif recon_reduction == "sum":
        recon_l1 = err.flatten(1).sum(dim=1).mean()
    else:
        raise ValueError(f"recon_reduction must be 'mean' or 'sum', got {recon_reduction!r}")
    kl = kl_divergence(mu, logvar)
    return recon_l1 + beta * kl, {"vae_recon": recon_l1, "vae_kl": kl}
