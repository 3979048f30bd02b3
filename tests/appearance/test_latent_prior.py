"""The Gaussian prior on the embedding table's rows (latent.prior_weight): its term, its gradient, and that it is
only there when asked for."""

import torch

from tests.test_mask_eval import _camera, _tiny_model
from willags_ns.appearance.latents import latent_prior


def test_the_prior_pulls_a_row_straight_towards_the_centre():
    z = torch.tensor([1.0, -2.0, 0.5], requires_grad=True)
    center = torch.tensor([0.0, 1.0, 0.5])
    loss = latent_prior(z, center)
    assert float(loss) == 0.5 * (1.0 + 9.0 + 0.0)
    (g,) = torch.autograd.grad(loss, z)
    assert torch.equal(g, z.detach() - center)


def _step_terms(weight: float):
    model = _tiny_model(use_vae=False)
    model.config.latent.prior_weight = weight
    model.config.mask.enabled = False
    model.optimizers = {}  # only read by densification, which one step's loss does not reach
    model.train()
    cam = _camera(24, 16)
    image = (torch.rand(16, 24, 3, generator=torch.Generator().manual_seed(1)) * 255).to(torch.uint8)
    with torch.no_grad():  # rows apart from each other, as after training
        model.appearance_nets.embeddings.weight.normal_(0.0, 1.0, generator=torch.Generator().manual_seed(2))
    batch = {"image": image, "image_idx": 1}
    model.set_train_batch(batch)
    out = model.get_outputs(cam)
    return model, model.get_loss_dict(out, batch, {})


def test_a_training_step_adds_the_prior_of_its_own_row_and_moves_no_other_row():
    model, losses = _step_terms(0.5)
    table = model.appearance_nets.embeddings.weight
    center = table.detach().mean(0)
    assert torch.allclose(losses["latent_prior"], 0.5 * 0.5 * (table[1].detach() - center).square().sum())
    (g,) = torch.autograd.grad(losses["latent_prior"], table)
    assert torch.allclose(g[1], 0.5 * (table[1].detach() - center)) and not g[0].any()


def test_without_a_prior_weight_no_term_and_no_centre():
    _, losses = _step_terms(0.0)
    assert "latent_prior" not in losses


def test_an_extreme_weight_stays_finite_and_a_lone_row_feels_no_pull():
    """At a weight a million times the default's the term and its gradient stay finite; a table of one photo is its
    own mean, so the prior adds nothing there."""
    model, losses = _step_terms(2000.0)
    table = model.appearance_nets.embeddings.weight
    (g,) = torch.autograd.grad(losses["latent_prior"], table)
    assert torch.isfinite(losses["latent_prior"]) and torch.isfinite(g).all() and g.abs().max() > 0
    row = torch.randn(1, 5, requires_grad=True)
    assert float(latent_prior(row[0], row.detach().mean(0))) == 0.0
