"""Appearance controls of the viewer and the latent helpers (no viewer server needed: the elements hold values)."""

import torch

from tests.test_mask_eval import _camera
from tests.test_model import _tiny_model
from willags_ns.viewer import MODES, interpolate_latents, sample_latent


def test_interpolation_endpoints_and_seeded_samples():
    a, b = torch.zeros(4), torch.arange(4.0)
    assert torch.equal(interpolate_latents(a, b, 0.0), a) and torch.equal(interpolate_latents(a, b, 1.0), b)
    torch.testing.assert_close(interpolate_latents(a, b, 0.25), 0.25 * b)
    assert torch.equal(sample_latent(8, 3), sample_latent(8, 3))
    assert not torch.equal(sample_latent(8, 3), sample_latent(8, 4))


def test_controls_set_the_render_latent_and_change_the_render():
    model = _tiny_model()
    model.eval()
    d = model.train_latents.shape[1]
    with torch.no_grad():
        g = torch.Generator().manual_seed(6)
        for p in model.appearance_nets.field.parameters():  # at initialisation the planes barely depend on z
            p.add_(0.5 * torch.randn(p.shape, generator=g))
        model.train_latents.copy_(torch.randn(model.train_latents.shape, generator=torch.Generator().manual_seed(5)))
        model.train_latent_seen.fill_(True)
    names = ["a.png", "b.png"]
    model.set_train_image_names(names)
    ctl = model.viewer_controls

    ctl.mode.value, ctl.image_a.value = MODES[1], "b.png"
    ctl.apply()
    assert torch.equal(model.render_latent, model.train_latents[1])
    with torch.no_grad():
        rgb_b = model.get_outputs(_camera(48, 32))["rgb"]

    ctl.mode.value, ctl.image_a.value, ctl.image_b.value, ctl.t.value = MODES[2], "a.png", "b.png", 0.25
    ctl.apply()
    torch.testing.assert_close(model.render_latent, 0.75 * model.train_latents[0] + 0.25 * model.train_latents[1])

    ctl.mode.value, ctl.seed.value = MODES[0], 7
    ctl.resample.cb_hook(ctl.resample)  # the "New random appearance" button
    assert ctl.mode.value == MODES[3] and int(ctl.seed.value) == 8
    assert torch.equal(model.render_latent, sample_latent(d, 8))
    with torch.no_grad():
        rgb_s = model.get_outputs(_camera(48, 32))["rgb"]
    assert not torch.allclose(rgb_b, rgb_s, atol=1e-3), "a different appearance must render different colours"

    ctl.mode.value = MODES[0]
    ctl.apply()
    assert model.render_latent is None  # back to the mean of the training latents
    torch.testing.assert_close(model.current_latent(), model.train_latents.mean(0))
