"""The colour model contract (appearance/color_model.py): a new colour model is one ColorModel subclass, and the
Gaussians, the colour path, the loss and the SH bake follow from it."""

import torch
from torch import nn

from willags_ns.appearance import networks
from willags_ns.appearance.color_model import ColorModel, GaussianLayout
from willags_ns.appearance.decoder import ColorDecoder
from willags_ns.appearance.modulation import ColorModulation


class TintedFeatures(ColorModel):
    """A toy model: colour = sigmoid(first 3 entries of f_s) x a tint of z; no SH; a penalty on the tint."""

    def __init__(self, latent_dim: int):
        super().__init__()
        self.tint = nn.Linear(latent_dim, 3)

    @classmethod
    def build(cls, cfg, latent_dim, field_dim):
        return cls(latent_dim)

    @classmethod
    def layout(cls, cfg):
        return GaussianLayout(sh=False, intrinsic_dim=5)

    def prepare(self, z, f_s, f_d, n):
        return torch.sigmoid(self.tint(z))

    def rgb(self, z, base, f_s, f_d, dirs, prepared):
        assert base is None  # it reads no SH
        return torch.sigmoid(f_s[:, :3]) * prepared

    def penalty(self, prepared):
        return 0.5 * prepared.square().mean()


def test_the_two_models_state_their_layouts():
    from willags_ns.method_configs import willags_model_config

    cfg = willags_model_config()
    assert networks.gaussian_layout(cfg) == GaussianLayout(sh=True, intrinsic_dim=cfg.intrinsic_dim)
    cfg.modulation.local = False
    assert networks.gaussian_layout(cfg) == GaussianLayout(sh=True, intrinsic_dim=0)
    cfg.color_mode = "decoder"
    assert networks.gaussian_layout(cfg).seed_color_in_features and not networks.gaussian_layout(cfg).sh
    cfg.appearance = "sh"
    assert networks.gaussian_layout(cfg) == GaussianLayout(sh=True, intrinsic_dim=0)
    assert issubclass(ColorModulation, ColorModel) and issubclass(ColorDecoder, ColorModel)


def test_a_new_colour_model_is_one_subclass_and_trains(tmp_path, monkeypatch):
    from tests.test_train import _train

    monkeypatch.setitem(networks.COLOR_MODELS, "tinted", ("tinted", TintedFeatures))
    _, trainer, _ = _train(tmp_path, "willags", steps=3, **{"color_mode": "tinted", "sky.enabled": False})
    model = trainer.pipeline.model
    nets = model.appearance_nets
    assert isinstance(nets.color_model, TintedFeatures) and nets.modulation is None and nets.color is None
    gp = model.gauss_params
    assert "features_dc" not in gp and gp["features"].shape[1] == 5  # its layout: f_s of 5, no SH
    assert "appearance_nets.tinted.tint.weight" in model.state_dict()
    assert nets.tinted.tint.weight.grad is not None  # trained through the colour path

    model.train()
    camera = trainer.pipeline.datamanager.train_dataset.cameras[0:1].to(model.device)
    batch = {"image": trainer.pipeline.datamanager.cached_train[0]["image"], "image_idx": 0}
    model.set_train_batch(batch)
    outputs = model.get_outputs(camera)
    want = nets.color_model.penalty(torch.sigmoid(nets.tinted.tint(outputs["latent"])))
    torch.testing.assert_close(outputs["color_penalty"], want)
    assert model.get_loss_dict(outputs, batch)["appearance_local"] == outputs["color_penalty"]

    # no exact SH: a fixed appearance is baked by least squares and renders close to the model's own colours
    model.eval()
    z = model.default_latent()
    with torch.no_grad():
        sh = model.color_path.baked_sh(nets, z, gp["means"], gp["features"], 0, model.color_context(), None)
        direct = model.appearance_colors(z, gp["means"], gp["features"], torch.zeros(3, device=model.device)).rgb
    torch.testing.assert_close(sh[:, 0] * 0.28209479177387814 + 0.5, direct, atol=1e-5, rtol=1e-5)
