"""The appearance networks of one model: what the EMA teacher copies and the optimiser's "appearance" groups hold.

latent source (per-image embedding table, or beta-VAE encoder: latent.kind) -> z [D]
z, normalised means -> tri-plane field -> f_d [N, F]                  (absent with use_field=False)
colour: the SH colour modulated by z (color_mode='modulated'), or the paper's T_color(f_d, f_s, dirs) ('decoder')
z, pixel directions -> sky                                            (absent without a sky)

Per-Gaussian tensors (means, SH, f_s) live in the model's gauss_params, so densification never touches this module.
"""

from typing import Any, Protocol

import torch
from torch import Tensor, nn

from willags_ns.appearance.decoder import ColorDecoder, ColorDecoderConfig
from willags_ns.appearance.modulation import ColorModulation, ColorModulationConfig
from willags_ns.appearance.sky import SkyConfig, SkyModel
from willags_ns.appearance.triplane import TriplaneConfig, TriplaneHyperField
from willags_ns.appearance.vae import AppearanceVAE
from willags_ns.render.sh import sh_color


class LatentSettings(Protocol):
    """The latent group of the model's config (config.LatentConfig)."""

    kind: str
    dim: int
    embedding_init_std: float
    vae: Any


class NetworksConfig(Protocol):
    """The fields of WillagsModelConfig the networks are built from (the model's config satisfies it; declared
    here so this module does not import the model's config)."""

    color_mode: str
    latent: LatentSettings
    use_field: bool
    intrinsic_dim: int
    triplane: TriplaneConfig
    decoder: ColorDecoderConfig
    modulation: ColorModulationConfig
    sky: SkyConfig


class AppearanceNetworks(nn.Module):
    """Every network the EMA teacher copies: VAE (or embedding table), tri-plane field, colour decoder.

    Per-Gaussian tensors (means, f_s) live in the model's gauss_params, so densification never touches this.
    """

    def __init__(self, cfg: "NetworksConfig", num_train: int, with_sky: bool | None = None):
        """`with_sky`: build the sky (default: cfg.sky.enabled; the model passes what the scene allows,
        appearance/sky.sky_for_scene)."""
        super().__init__()
        lat = cfg.latent
        d = lat.dim
        self.latent_dim = d
        self.color_mode = cfg.color_mode
        if cfg.color_mode == "modulated" and cfg.use_field and not cfg.modulation.local:
            raise ValueError(
                "willags: use_field=True with color_mode='modulated' needs modulation.local=True (the tri-plane "
                "feature feeds the per-Gaussian residual); set --pipeline.model.use-field False or "
                "--pipeline.model.modulation.local True"
            )
        if lat.kind not in ("embedding", "vae"):
            raise ValueError(f"willags: latent.kind must be 'embedding' or 'vae', got {lat.kind!r}")
        self.vae = (
            AppearanceVAE(latent_dim=d, image_size=lat.vae.image_size, channels=tuple(lat.vae.channels))
            if lat.kind == "vae"
            else None
        )
        self.embeddings = None
        if lat.kind == "embedding":
            self.embeddings = nn.Embedding(max(num_train, 1), d)
            nn.init.normal_(self.embeddings.weight, std=lat.embedding_init_std)
        tp = cfg.triplane
        self.field = (
            TriplaneHyperField(
                latent_dim=d,
                resolution=tp.resolution,
                channels=tp.channels,
                hyper_hidden=tuple(tp.hyper_hidden),
                feature_dim=tp.feature_dim,
                mlp_hidden=tp.mlp_hidden,
            )
            if cfg.use_field
            else None
        )
        self.sky = SkyModel(d, cfg.sky) if (cfg.sky.enabled if with_sky is None else with_sky) else None
        self.color: ColorDecoder | None = None
        self.modulation: ColorModulation | None = None
        if cfg.color_mode == "decoder":
            self.color = ColorDecoder(
                dynamic_dim=tp.feature_dim if cfg.use_field else 0,
                intrinsic_dim=cfg.intrinsic_dim + (0 if cfg.use_field else d),
                hidden=cfg.decoder.hidden,
                dir_sh_degree=cfg.decoder.dir_sh_degree,
            )
        else:
            self.modulation = ColorModulation(
                latent_dim=d,
                intrinsic_dim=cfg.intrinsic_dim if cfg.modulation.local else 0,
                dynamic_dim=tp.feature_dim if cfg.use_field else 0,
                cfg=cfg.modulation,
            )

    def param_groups(self) -> dict[str, list[nn.Parameter]]:
        """Optimiser groups: "appearance" (the shared networks) and, for an embedding table, "appearance_embed": a
        table row is updated only when its image is drawn (once per epoch), so it needs a far higher learning rate
        than the shared networks."""
        emb = self.embeddings
        own = {id(p) for p in emb.parameters()} if emb is not None else set()
        groups = {"appearance": [p for p in self.parameters() if id(p) not in own]}
        if emb is not None:
            groups["appearance_embed"] = list(emb.parameters())
        return groups

    def latent_stats(self, image_chw: Tensor | None, image_idx: int | None) -> tuple[Tensor, Tensor | None]:
        """(mu [D], logvar [D] or None) of one training image: the VAE posterior, or the embedding row."""
        if self.vae is not None:
            assert image_chw is not None
            mu, logvar = self.vae.encode(image_chw[None])
            return mu[0], logvar[0]
        assert self.embeddings is not None and image_idx is not None
        # the row by a Python index: an index tensor built on the device is a blocking host -> device copy per step;
        # the same row and the same (dense) gradient as the module's lookup
        n = self.embeddings.num_embeddings
        if not 0 <= image_idx < n:
            raise IndexError(f"willags: training image index {image_idx} outside the appearance table's {n} rows")
        return self.embeddings.weight[image_idx], None

    def dynamic_features(self, z: Tensor, xyz_norm: Tensor) -> Tensor | None:
        """f_d [N, F] for latent z [D] at normalised means [N, 3]; None without the field."""
        if self.field is None:
            return None
        return self.field(z, xyz_norm)

    def gaussian_rgb(
        self,
        z: Tensor,
        f_d: Tensor | None,
        f_s: Tensor | None,
        dirs: Tensor,
        sh: Tensor | None = None,
        sh_degree: int = 0,
        residual: Tensor | None = None,
        base: Tensor | None = None,
    ) -> Tensor:
        """Per-Gaussian RGB [N, 3] from f_d [N, F] (or None), f_s [N, Fs] (or None), view directions [N, 3] and,
        for color_mode='modulated', the Gaussians' SH coefficients sh [N, K, 3] evaluated up to sh_degree
        (``residual``: a precomputed local residual, see ColorModulation.forward; ``base``: the SH colours
        already evaluated, which then replace sh)."""
        if self.modulation is not None:
            if base is None:
                if sh is None:
                    raise ValueError("color_mode='modulated' needs the Gaussians' SH coefficients (sh=...)")
                base = sh_color(sh_degree, dirs, sh)  # gsplat's SH colour
            # clamped like gsplat clamps SH colours, so the exact render and the SH bake agree
            return self.modulation(z, base, f_s, f_d, residual=residual).clamp_min(0.0)
        assert self.color is not None and f_s is not None
        if self.field is None:
            f_s = torch.cat([f_s, z.expand(f_s.shape[0], -1)], dim=-1)  # the "w/o field" ablation
        return self.color(f_d, f_s, dirs)
