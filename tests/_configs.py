"""Model settings of the component tests: every component built (the tri-plane field, the mask with its teacher at
every step, VGG at 512 px), no sky, no safeguard, classic rasterisation, no inspection. The tests of the model's
parts are written against these, whatever the `willags` defaults (WillagsModelConfig's) are."""

from typing import Any

from willags_ns.appearance.sky import SkyConfig
from willags_ns.config import LatentConfig
from willags_ns.mask.rule import MaskConfig
from willags_ns.mask.static_support import StaticSupportConfig


def mask(**fields: Any) -> MaskConfig:
    """The mask at every step from step 500 whatever the renders leave (the paper's), VGG at 512 px, no safeguard;
    `fields` on top."""
    return MaskConfig(
        **{
            "every": 1,
            "max_resolution": 512,
            "warmup_steps": 500,
            "start_rule": "always",
            "safeguard": StaticSupportConfig(enabled=False),
            **fields,
        }
    )


def latent(use_vae: bool = True, **fields: Any) -> LatentConfig:
    """The beta-VAE latent (`use_vae`) or the embedding table; `fields` on top."""
    return LatentConfig(kind="vae" if use_vae else "embedding", **fields)


def all_components(use_vae: bool = True, **fields: Any) -> dict[str, Any]:
    """WillagsModelConfig keyword arguments: every component; `fields` on top."""
    return {
        "latent": latent(use_vae),
        "use_field": True,
        "intrinsic_dim": 32,
        "mask": mask(),
        "sky": SkyConfig(enabled=False, region="everywhere"),
        "rasterize_mode": "classic",
        "auto_config": False,
        **fields,
    }
