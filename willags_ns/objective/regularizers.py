"""The terms a training step adds to the reconstruction loss, each weighted by the model's config.

    loss = reconstruction (losses.py, masked by the transient mask)
         + latent.vae.weight * L_VAE        the beta-VAE of the step's photo        appearance/latents.py, vae.py
         + latent.prior_weight * prior      the table row of the step's photo       appearance/latents.py
         + sky.alpha_penalty * mean alpha   where the sky alone explains the photo  appearance/sky.py
         + the colour model's penalty (the modulation's: local_penalty * mean(s^2 + o^2))  appearance/color_model.py
         + splatfacto's scale penalty (every 10th step)                              losses.py
         + mcmc.opacity_reg * mean opacity + mcmc.scale_reg * mean scale (MCMC)     splats/mcmc.py

Each term is computed where its component lives; this module only says when a term applies and how much it
weighs. It sits above `losses.py`, which the NeRF-W protocol (and through it the SPEC parser) imports: the pure
loss terms never import the appearance networks, so the latents can use the protocol without an import cycle.
"""

from jaxtyping import Float
from torch import Tensor

from willags_ns.appearance.latents import latent_loss, latent_prior
from willags_ns.appearance.sky import background_alpha_penalty
from willags_ns.appearance.vae import AppearanceVAE
from willags_ns.objective.losses import scale_regularization
from willags_ns.splats.mcmc import mcmc_penalty
from willags_ns.tensor_constants import constant


def regularization_terms(
    cfg,
    vae: AppearanceVAE | None,
    outputs: dict,
    gt_img: Float[Tensor, "H W 3"],
    mask: Float[Tensor, "H W"] | None,
    log_scales: Float[Tensor, "N 3"],
    logit_opacities: Float[Tensor, "N 1"],
    mcmc: bool,
    step: int,
    training: bool,
) -> tuple[dict[str, Tensor], dict[str, Tensor], Tensor | None]:
    """The weighted terms a step adds to the reconstruction loss, their metrics, and the VAE's reconstruction of the
    photo for the logs (or None): ``(terms, metrics, recon)``.

    ``cfg``: the model's config (WillagsModelConfig); ``outputs``: the step's render with its intermediates
    (``latent``, ``latent_mu``, ``latent_logvar``, ``vae_in`` of a VAE latent, ``latent_center`` of a table with a
    prior, ``color_penalty``: WillagsModel's
    get_outputs). In the order the trainer sums them (the order of a float sum sets its last bits):

    - ``vae_loss``: latent.vae.weight * L_VAE of the step's photo (training with the VAE; metrics ``vae_kl``, ``vae_recon``);
    - ``latent_prior``: latent.prior_weight * the Gaussian prior of the step's table row around the rows' mean
      (``latent_center``; training with an embedding table and a prior);
    - ``sky_alpha``: sky.alpha_penalty * the mean alpha over pixels the sky alone reproduces (training with a sky);
    - ``appearance_local``: the colour model's weighted penalty of the step (ColorModel.penalty: the modulation's
      local_penalty * mean(s^2 + o^2) of its per-Gaussian residual; training);
    - ``scale_reg``: splatfacto's needle penalty on every 10th step (use_scale_regularization, training or not);
    - ``mcmc_reg``: MCMC densification's opacity and scale penalties (``mcmc``: the model densifies by MCMC; training).
    """
    terms: dict[str, Tensor] = {}
    metrics: dict[str, Tensor] = {}
    recon = None
    if training and outputs.get("latent_logvar") is not None:  # only the VAE has a log-variance
        assert vae is not None
        vcfg, o = cfg.latent.vae, outputs
        args = (o["latent"], o["latent_mu"], o["latent_logvar"], o["vae_in"], vcfg.beta, vcfg.recon_reduction)
        l_vae, parts, recon = latent_loss(vae, *args)
        terms["vae_loss"] = constant(vcfg.weight, l_vae) * l_vae
        metrics["vae_kl"] = parts["vae_kl"].detach()
        metrics["vae_recon"] = parts["vae_recon"].detach()
    if training and cfg.latent.prior_weight > 0 and outputs.get("latent_center") is not None:
        prior = latent_prior(outputs["latent"], outputs["latent_center"])
        terms["latent_prior"] = constant(cfg.latent.prior_weight, prior) * prior
    if training and cfg.sky.enabled and cfg.sky.alpha_penalty > 0 and outputs["background"].dim() == 3:
        acc, bg = outputs["accumulation"], outputs["background"]
        pen_sky = background_alpha_penalty(acc, gt_img, bg, cfg.sky.alpha_tol, mask)
        if pen_sky is not None:
            terms["sky_alpha"] = constant(cfg.sky.alpha_penalty, pen_sky) * pen_sky
    if training and outputs.get("color_penalty") is not None:  # the colour model's own term (ColorModel.penalty)
        terms["appearance_local"] = outputs["color_penalty"]
    if cfg.use_scale_regularization and step % 10 == 0:
        terms["scale_reg"] = scale_regularization(log_scales, cfg.max_gauss_ratio)
    if training and mcmc:
        terms["mcmc_reg"] = mcmc_penalty(cfg, logit_opacities, log_scales)
    return terms, metrics, recon
