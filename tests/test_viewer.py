"""The viewer's appearance panel without a server (the elements hold their values; callbacks are called directly).
The real-browser test is tests/test_viewer_browser.py."""

import numpy as np
import torch
from PIL import Image

from tests.test_appearance_spec import _model
from tests.test_mask_eval import _camera
from willags_ns.appearance_spec import sample_latent
from willags_ns.viewer import MEAN, PHOTO, SAMPLE, appearance_controls, filter_names, spec_from_choices


def test_spec_from_choices_and_search():
    assert spec_from_choices(MEAN, "b.png", 0.0, "", 0) == "mean"
    assert spec_from_choices("a.png", "b.png", 1.0, "", 0) == "image:b.png"
    assert spec_from_choices("a.png", SAMPLE, 0.25, "", 3) == "interp:image:a.png,sample:3,0.25"
    assert spec_from_choices(PHOTO, "a.png", 0.0, " /p.jpg ", 0) == "photo:/p.jpg"
    names = [f"IMG_{i:04d}.jpg" for i in range(1200)]
    assert filter_names(names, "img_11") == [f"IMG_{i:04d}.jpg" for i in range(1100, 1200)]
    assert len(filter_names(names, "")) == 500  # a long list is narrowed by the search field


def test_panel_sets_the_render_latent_and_changes_the_render(tmp_path):
    model = _model()
    d = model.train_latents.shape[1]
    ctl = appearance_controls(model)
    names = ["a.png", "b.png"]
    assert ctl.p01_a.options[3:] == names and ctl.p02_b.options[3:] == names  # every training image is listed

    ctl.p01_a.value = "b.png"
    ctl.p01_a.cb_hook(ctl.p01_a)
    assert torch.equal(model.render_latent, model.train_latents[1]) and ctl.p09_spec.value == "image:b.png"
    assert ctl.p10_norm.value == f"{float(model.train_latents[1].norm()):.4f}"
    with torch.no_grad():
        rgb_b = model.get_outputs(_camera(48, 32))["rgb"]

    ctl.p01_a.value, ctl.p02_b.value, ctl.p04_t.value = "a.png", "b.png", 0.25
    ctl.p04_t.cb_hook(ctl.p04_t)
    torch.testing.assert_close(model.render_latent, 0.75 * model.train_latents[0] + 0.25 * model.train_latents[1])

    ctl.p07_seed.value = 7
    ctl.p08_random.cb_hook(ctl.p08_random)  # the "Random appearance" button: next seed, shown as A
    assert ctl.p01_a.value == SAMPLE and int(ctl.p07_seed.value) == 8 and ctl.spec == "sample:8"
    assert torch.equal(model.render_latent, sample_latent(d, 8))
    with torch.no_grad():
        rgb_s = model.get_outputs(_camera(48, 32))["rgb"]
    assert not torch.allclose(rgb_b, rgb_s, atol=1e-3), "a different appearance must render different colours"

    img = (np.random.default_rng(1).random((20, 30, 3)) * 255).astype(np.uint8)
    Image.fromarray(img).save(tmp_path / "new.jpg")
    ctl.p05_photo.value = str(tmp_path / "new.jpg")
    ctl.p06_use_photo.cb_hook(ctl.p06_use_photo)  # "Use photo"
    assert ctl.p01_a.value == PHOTO and ctl.spec == f"photo:{tmp_path / 'new.jpg'}"
    torch.testing.assert_close(
        model.render_latent, model.encode_image(torch.from_numpy(np.asarray(Image.open(tmp_path / "new.jpg"))))
    )

    # a bad SPEC typed into the spec field: the error names it, the appearance stays
    kept = model.render_latent.clone()
    ctl.p09_spec.value = "image:nope"
    ctl.p09_spec.cb_hook(ctl.p09_spec)
    assert "unknown training image 'nope'" in ctl.p11_status.content and torch.equal(model.render_latent, kept)
    ctl.p09_spec.value = "interp:a,b,0.5"
    ctl.p09_spec.cb_hook(ctl.p09_spec)
    torch.testing.assert_close(model.render_latent, 0.5 * (model.train_latents[0] + model.train_latents[1]))
    assert ctl.p11_status.content == ""

    ctl.p01_a.value, ctl.p04_t.value = MEAN, 0.0
    ctl.p01_a.cb_hook(ctl.p01_a)
    assert model.render_latent is None  # back to the model's default, the mean of the training latents
    torch.testing.assert_close(model.current_latent(), model.train_latents.mean(0))


def test_search_narrows_both_lists_and_keeps_the_choice():
    model = _model()
    ctl = appearance_controls(model)
    ctl.set_image_names([f"IMG_{i}.jpg" for i in range(30)])
    ctl.p01_a.value = "IMG_3.jpg"
    ctl.p03_search.value = "IMG_2"
    ctl.p03_search.cb_hook(ctl.p03_search)
    listed = ctl.p01_a.options[3:]
    assert "IMG_2.jpg" in listed and "IMG_21.jpg" in listed and "IMG_5.jpg" not in listed
    assert "IMG_3.jpg" in listed  # the chosen entry stays selectable
    assert "IMG_3.jpg" not in ctl.p02_b.options[3:]


def test_use_photo_fits_the_latent_on_an_embedding_table_model(tmp_path):
    """The default model has no encoder: "Use photo" fits the photo's latent (as --refine-steps does) from the
    training cameras the pipeline gives the panel, instead of failing."""
    from types import SimpleNamespace

    from tests.test_mask_eval import _tiny_model as tiny
    from willags_ns.viewer import AppearanceControls

    model = tiny(use_vae=False)
    model.eval()
    model.set_train_image_names(["a.png", "b.png"])
    with torch.no_grad():
        model.appearance_nets.modulation.global_mlp[-1].weight.normal_(0.0, 0.3)  # colours depend on z
    ctl = AppearanceControls(model, ["a.png", "b.png"])
    ctl.set_train_dataset(SimpleNamespace(cameras=_camera(48, 32)))
    c = _camera(48, 32)
    c.metadata = {"appearance_latent": torch.full((8,), 1.5)}
    with torch.no_grad():  # the "photo": the model's own render under a latent far from the mean
        photo = (model.get_outputs(c)["rgb"].clamp(0, 1) * 255).to(torch.uint8).numpy()
    Image.fromarray(photo).save(tmp_path / "p.png")
    ctl.p05_photo.value = str(tmp_path / "p.png")
    ctl.p06_use_photo.cb_hook(ctl.p06_use_photo)
    assert ctl.p11_status.content == "" and ctl.spec == f"photo:{tmp_path / 'p.png'}"
    mean = model.image_latents()[0].mean(0)

    @torch.no_grad()
    def err(z):
        return float((model.get_outputs(_with(z))["rgb"] - torch.from_numpy(photo) / 255.0).abs().mean())

    assert err(model.render_latent) < 0.7 * err(mean)


def _with(z):
    c = _camera(48, 32)
    c.metadata = {"appearance_latent": z}
    return c


def test_ns_viewer_of_a_willags_checkpoint_listens_on_localhost_unless_asked(monkeypatch):
    """ns-viewer swaps the run's saved host for its own default 0.0.0.0; the guard a willags pipeline installs in
    test mode keeps the viewer on 127.0.0.1 unless $WILLAGS_VIEWER_HOST or an explicit other host says otherwise."""
    from nerfstudio.configs.base_config import ViewerConfig
    from nerfstudio.viewer import viewer as ns_viewer

    from willags_ns.viewer import VIEWER_HOST_ENV, guard_viewer_host

    seen = []
    monkeypatch.setattr(ns_viewer.Viewer, "__init__", lambda self, config, *a, **k: seen.append(config.websocket_host))
    monkeypatch.delenv(VIEWER_HOST_ENV, raising=False)
    guard_viewer_host()
    guard_viewer_host()  # installed once
    for host in ("0.0.0.0", "192.168.1.7"):
        ns_viewer.Viewer(ViewerConfig(websocket_host=host), None, None, None)
    monkeypatch.setenv(VIEWER_HOST_ENV, "0.0.0.0")
    ns_viewer.Viewer(ViewerConfig(websocket_host="0.0.0.0"), None, None, None)
    assert seen == ["127.0.0.1", "192.168.1.7", "0.0.0.0"]
