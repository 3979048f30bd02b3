"""nerfstudio method specifications: `willags` (the default: SH colours transformed by the appearance latent, the
scene inspected first and only what it needs trained), `willags-full` (every component, no inspection),
`willags-paper` (the paper's exact configuration: colour decoder + tri-plane field), `willags-lite` (fast preset for
short CPU budgets), `willags-3dgs` (plain 3DGS through the same code: the CPU stand-in for splatfacto in benchmarks). Each preset sets
only fields that act in it. Why each default is set as it is: docs/design.md.

Without CUDA the methods default to the CPU (`--machine.device-type cpu` is not needed) and to our torch
rasteriser; with CUDA, to gsplat.
"""

from dataclasses import dataclass

import torch
from nerfstudio.configs.base_config import MachineConfig, ViewerConfig
from nerfstudio.engine.optimizers import AdamOptimizerConfig
from nerfstudio.engine.schedulers import ExponentialDecaySchedulerConfig
from nerfstudio.plugins.types import MethodSpecification

from willags_ns.appearance.sky import SkyConfig
from willags_ns.appearance.vae import VAEConfig
from willags_ns.config import LatentConfig, WillagsModelConfig
from willags_ns.data.datamanager import WillagsDatamanagerConfig
from willags_ns.data.dataparser import WillagsDataParserConfig
from willags_ns.engine.compat import quick_external_method_check
from willags_ns.engine.pipeline import WillagsPipelineConfig
from willags_ns.engine.time_budget import PRESET_CONFIGS
from willags_ns.engine.trainer import WillagsTrainerConfig
from willags_ns.mask.rule import MaskConfig
from willags_ns.mask.static_support import StaticSupportConfig

quick_external_method_check()  # nerfstudio loads these configs before it lists its installable methods


def default_device_type() -> str:
    return "cuda" if torch.cuda.is_available() else "cpu"


@dataclass
class FusedAdamOptimizerConfig(AdamOptimizerConfig):
    """Adam as splatfacto configures it, but on CUDA through torch's fused implementation (``fused=True``): one
    kernel per parameter group instead of one per foreach operation, the same update to float rounding. A willags
    step launches hundreds of device operations and its GPU waits on the host for part of the step, so launches
    count (docs/design.md); on the CPU, torch's default implementation."""

    def setup(self, params) -> torch.optim.Optimizer:
        params = list(params)
        kwargs = vars(self).copy()
        kwargs.pop("_target")
        kwargs.pop("max_norm")
        if params and all(isinstance(p, torch.Tensor) and p.is_cuda for p in params):
            kwargs["fused"] = True
        return self._target(params, **kwargs)


def _optimizers(max_steps: int) -> dict[str, dict]:
    """Splatfacto's per-group Adam settings, plus f_s ('features') and the appearance networks."""

    def adam(lr: float, sched=None):
        return {"optimizer": FusedAdamOptimizerConfig(lr=lr, eps=1e-15), "scheduler": sched}

    return {
        "means": adam(1.6e-4, ExponentialDecaySchedulerConfig(lr_final=1.6e-6, max_steps=max_steps)),
        "scales": adam(0.005),
        "quats": adam(0.001),
        "opacities": adam(0.05),
        "features_dc": adam(0.0025),
        "features_rest": adam(0.0025 / 20),
        "features": adam(0.0025),
        "residual_level": adam(0.005),  # each Gaussian's expected residual (mask.residual.expected): mask/expected.py
        "appearance": {
            "optimizer": FusedAdamOptimizerConfig(lr=1e-3, eps=1e-15),
            "scheduler": ExponentialDecaySchedulerConfig(lr_final=1e-4, max_steps=max_steps, warmup_steps=100),
        },
        # per-image embedding table (latent.kind "embedding"): each row sees one gradient per epoch
        "appearance_embed": adam(0.02, ExponentialDecaySchedulerConfig(lr_final=2e-3, max_steps=max_steps)),
        "camera_opt": adam(
            1e-4, ExponentialDecaySchedulerConfig(lr_final=5e-7, max_steps=max_steps, warmup_steps=1000)
        ),
    }


def _trainer(name: str, model: WillagsModelConfig, steps: int) -> WillagsTrainerConfig:
    return WillagsTrainerConfig(
        method_name=name,
        steps_per_eval_image=500,
        steps_per_eval_batch=0,
        steps_per_save=2000,
        steps_per_eval_all_images=100000,
        max_num_iterations=steps,
        mixed_precision=False,
        machine=MachineConfig(device_type=default_device_type()),  # type: ignore[arg-type]
        pipeline=WillagsPipelineConfig(
            datamanager=WillagsDatamanagerConfig(dataparser=WillagsDataParserConfig(), cache_images_type="uint8"),
            model=model,
        ),
        optimizers=_optimizers(steps),
        # the viewer listens on this machine only (LAN: --viewer.websocket-host 0.0.0.0); ns-train ends when training
        # does, unless --viewer.quit-on-train-completion False keeps the viewer (WillagsTrainer, "after training")
        viewer=ViewerConfig(num_rays_per_chunk=1 << 15, websocket_host="127.0.0.1", quit_on_train_completion=True),
        vis="viewer+tensorboard",
    )


def willags_model_config() -> WillagsModelConfig:
    """The full `willags` model without inspecting the scene: WillagsModelConfig's defaults (each choice and the
    measurement behind it: docs/design.md) with auto_config off.

    - appearance latent: a 64-d per-image embedding table (lr 0.02), not the paper's beta-VAE encoder, its rows
      pulled towards their mean by a small Gaussian prior (latent.prior_weight) so that they stay within reach of a
      new photo's fit. A new photo's appearance is fitted to it (`willags-render --appearance photo:P
      --refine-steps N`); `--pipeline.model.latent.kind vae` brings the encoder back;
    - the EMA teacher and the perceptual mask of the paper, the mask refreshed on every 4th visit of an image with
      VGG at 256 px (the paper: every step at full size), for a fraction of the step time; it starts at step 5000,
      and only where the training photos' own renders then leave at least 10 % of their pixels as residual blobs
      (mask.start_rule "transients"): where they leave fewer, what the mask drops is mostly scene;
    - colour: each Gaussian's SH colour under a global colour transform of z plus a penalised per-Gaussian
      residual (16-d f_s), no tri-plane field;
    - gsplat's antialiased rasterisation, which keeps renders consistent across the resolution schedule (a
      5000-step run trains at 1/4 and 1/2 resolution and is scored at full);
    - the appearance-conditioned sky, trained only above each photo's SfM skyline (sky.region "open"), and the
      mask's SfM-track safeguard (mask.safeguard). Both need COLMAP's keypoints: on a scene without them (a
      transforms.json scene) the model trains as without both (tests/test_train.py)."""
    return WillagsModelConfig(auto_config=False)


def willags_config() -> WillagsTrainerConfig:
    """The default method: the full model (willags_model_config) with `auto_config`, 30k steps. Before the model is
    built, willags-inspect's evidence switches off what the scene does not need: the mask and its teacher where no
    transients are measured, the latent where no appearance change is, the sky where no photo has open background
    (willags_ns/tools/autoconfig.py, docs/inspect.md). Dropping what a scene does not need loses nothing measurable there
    and makes the step cheaper (docs/design.md). `willags-full` keeps every component without inspecting; a switch
    named on the command line wins."""
    return _trainer("willags", WillagsModelConfig(), 30000)


def willags_full_config() -> WillagsTrainerConfig:
    """Every component of the default on every scene, no inspection: the latent, the EMA teacher and the mask, the
    sky above the SfM skyline and the mask's safeguard, 30k steps (willags_model_config without `auto_config`)."""
    return _trainer("willags-full", willags_model_config(), 30000)


def willags_paper_model_config() -> WillagsModelConfig:
    """The paper's exact model: beta-VAE latent, colour decoder T_color(f_d, f_s, view dir), 64x64x32 tri-planes,
    32-d f_s, the mask at every step with VGG at 512 px, classic rasterisation, 3DGS' densification (split / clone /
    prune); no sky, no safeguard."""
    return WillagsModelConfig(
        color_mode="decoder",
        latent=LatentConfig(kind="vae"),
        use_field=True,
        intrinsic_dim=32,
        mask=MaskConfig(
            every=1,
            max_resolution=512,
            warmup_steps=500,
            start_rule="always",
            safeguard=StaticSupportConfig(enabled=False),
        ),
        sky=SkyConfig(enabled=False),
        rasterize_mode="classic",
        densification="splatfacto",
        auto_config=False,
    )


def willags_paper_config() -> WillagsTrainerConfig:
    """The paper's configuration: 64-d latent, 64x64x32 planes, colour decoder, mask every step, 30k steps."""
    return _trainer("willags-paper", willags_paper_model_config(), 30000)


def willags_lite_config() -> WillagsTrainerConfig:
    """Fast preset: a 32-d beta-VAE latent (of the photo at 32 px), the modulated SH colours without a tri-plane field
    (as `willags`), the mask after a 300-step warm-up, refreshed every 4th visit of an image, no sky, no safeguard,
    splatfacto's densification (split / clone / prune) every 100 steps until step 5000, 7k steps.

    Cheaper than `willags` per step on a small CPU, which is where the time budget picks it
    (willags_ns/engine/time_budget.py); splatfacto's densification on every device (MCMC's gradual growth suits long
    runs). A tri-plane field made its CPU step slower for no measured gain
    (docs/design.md, "The fast preset without a tri-plane field"); `--pipeline.model.use-field True` adds it. On the
    GPU it is neither better nor faster than `willags`: it runs the beta-VAE encoder on every step's photo and VGG at
    512 px (docs/design.md).
    """
    model = WillagsModelConfig(
        latent=LatentConfig(kind="vae", dim=32, vae=VAEConfig(image_size=32)),
        mask=MaskConfig(
            warmup_steps=300, start_rule="always", max_resolution=512, safeguard=StaticSupportConfig(enabled=False)
        ),
        sky=SkyConfig(enabled=False),
        refine_every=100,
        warmup_length=300,
        stop_split_at=5000,
        densification="splatfacto",
        auto_config=False,
    )
    return _trainer("willags-lite", model, 7000)


def willags_3dgs_config() -> WillagsTrainerConfig:
    """Plain 3DGS (splatfacto's colours, losses and densification) through our rasteriser: no appearance
    model, no mask. Use it as the splatfacto baseline where splatfacto's CUDA-only code cannot run."""
    model = WillagsModelConfig(appearance="sh", rasterize_mode="classic", densification="splatfacto", auto_config=False)
    return _trainer("willags-3dgs", model, 30000)


# every method's factory (willags_ns/engine/trainer.py): the presets the time budget chooses between, and the method's own
# preset that tells a user's auto_config switches from its defaults
PRESET_CONFIGS.update(
    {
        "willags": willags_config,
        "willags-full": willags_full_config,
        "willags-lite": willags_lite_config,
        "willags-paper": willags_paper_config,
        "willags-3dgs": willags_3dgs_config,
    }
)

willags_method = MethodSpecification(
    config=willags_config(),
    description="WilLaGS (Gaussian splatting in the wild): per-image appearance latent transforming each Gaussian's "
    "SH colour, EMA teacher + perceptual transient mask, sky; the photos are inspected first and only what the scene "
    "needs is trained (logged with the reasons). Trains on CPU or CUDA. willags-full: every component, no "
    "inspection; willags-paper: the paper's exact configuration (beta-VAE, tri-plane field).",
)
willags_full_method = MethodSpecification(
    config=willags_full_config(),
    description="WilLaGS with every component on every scene (latent, EMA teacher, transient mask, sky, the mask's "
    "SfM safeguard), no inspection.",
)
willags_paper_method = MethodSpecification(
    config=willags_paper_config(),
    description="WilLaGS exactly as in the paper: colour decoder over tri-plane hypernetwork features + intrinsic "
    "features, beta-VAE latent, EMA teacher, perceptual transient mask.",
)
willags_lite_method = MethodSpecification(
    config=willags_lite_config(),
    description="WilLaGS fast preset for short CPU budgets (32-d VAE latent, no tri-plane field, cheaper mask, 7k steps).",
)
willags_3dgs_method = MethodSpecification(
    config=willags_3dgs_config(),
    description="Plain 3DGS (splatfacto's model) through willags' CPU/CUDA rasteriser: the benchmark baseline.",
)
