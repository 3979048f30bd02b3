"""The appearance networks of one model: what the EMA teacher copies and the optimiser's "appearance" groups hold.

latent source (per-image embedding table, or beta-VAE encoder: latent.kind) -> z [D]
z, normalised means -> tri-plane field -> f_d [N, F]                  (absent with use_field=False)
colour: the SH colour modulated by z (color_mode='modulated'), or the paper's T_color(f_d, f_s, dirs) ('decoder')
z, pixel directions -> sky                                            (absent without a sky)

Per-Gaussian tensors (means, SH, f_s) live in the model's gauss_params, so densification never touches this module.
"""

from typing import Any, Protocol

from torch import Tensor, nn

from willags_ns.appearance.color_model import ColorModel, GaussianLayout
from willags_ns.appearance.decoder import ColorDecoder, ColorDecoderConfig
from willags_ns.appearance.modulation import ColorModulation, ColorModulationConfig
from willags_ns.appearance.sky import SkyConfig, SkyModel
from willags_ns.appearance.triplane import TriplaneConfig, TriplaneHyperField
from willags_ns.appearance.vae import AppearanceVAE

COLOR_MODELS: dict[str, tuple[str, type[ColorModel]]] = {
    "modulated": ("modulation", ColorModulation),
    "decoder": ("color", ColorDecoder),
}
"""color_mode -> (the attribute of AppearanceNetworks that holds the model, its class): every colour model
(appearance/color_model.py). A new one is a module with its ColorModel subclass, a line here and its config group."""


def color_model_class(color_mode: str) -> type[ColorModel]:
    if color_mode not in COLOR_MODELS:
        raise ValueError(f"willags: color_mode must be one of {', '.join(COLOR_MODELS)}, got {color_mode!r}")
    return COLOR_MODELS[color_mode][1]


def gaussian_layout(cfg: Any) -> GaussianLayout:
    """The per-Gaussian tensors the model config `cfg` needs (splats/gaussians.initial_gauss_params builds them):
    its colour model's, or SH alone for plain 3DGS colours (appearance 'sh')."""
    if cfg.appearance == "sh":
        return GaussianLayout(sh=True, intrinsic_dim=0)
    return color_model_class(cfg.color_mode).layout(cfg)


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
        color_model_class(cfg.color_mode)  # an unknown colour model stops here, before any network is built
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
        name, model_cls = COLOR_MODELS[cfg.color_mode]
        # under its own attribute: the checkpoints' parameter names (appearance_nets.modulation.*, ...color.*)
        setattr(self, name, model_cls.build(cfg, d, tp.feature_dim if cfg.use_field else 0))
        self.color_model_name = name

    @property
    def color_model(self) -> ColorModel:
        """The colour model (appearance/color_model.py) of color_mode."""
        return getattr(self, self.color_model_name)

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
