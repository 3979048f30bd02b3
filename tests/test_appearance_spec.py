"""Appearance SPECs (willags_ns/appearance_spec.py): parsing, resolving on a tiny model, errors naming the bad part."""

import os
from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image

from tests.test_mask_eval import _camera
from tests.test_model import _tiny_model
from willags_ns.appearance_spec import (
    APPEARANCE_ENV,
    MAX_LATENT_NORM,
    AppearanceSpecError,
    ImageSpec,
    InterpSpec,
    MeanSpec,
    PhotoSpec,
    RefineOptions,
    SampleSpec,
    checked_latent,
    interpolate_latents,
    parse_spec,
    resolve_latent,
    sample_latent,
)
from willags_ns.viewer import appearance_controls


def _model():
    """The tiny model with a latent-dependent field, distinct training latents and file names."""
    model = _tiny_model()
    model.eval()
    with torch.no_grad():
        g = torch.Generator().manual_seed(6)
        for p in model.appearance_nets.field.parameters():  # at initialisation the planes barely depend on z
            p.add_(0.5 * torch.randn(p.shape, generator=g))
        model.train_latents.copy_(torch.randn(model.train_latents.shape, generator=torch.Generator().manual_seed(5)))
        model.train_latent_seen.fill_(True)
    model.set_train_image_names(["a.png", "b.png"])
    return model


def test_parse_each_kind_and_round_trip():
    cases = {
        "mean": MeanSpec(),
        "image:a.png": ImageSpec("a.png"),
        "sample:7": SampleSpec(7),
        "photo:/x/y.jpg": PhotoSpec(Path("/x/y.jpg")),
        "interp:0,1": InterpSpec(ImageSpec("0"), ImageSpec("1"), None),
        "interp:image:a,sample:2,0.25": InterpSpec(ImageSpec("a"), SampleSpec(2), 0.25),
    }
    for text, spec in cases.items():
        assert parse_spec(text) == spec, text
        assert parse_spec(str(spec)) == spec, text  # str() writes a SPEC back
    # a photo path with a comma: split where the second SPEC starts
    s = parse_spec("interp:photo:a,b.jpg,sample:1")
    assert s == InterpSpec(PhotoSpec(Path("a,b.jpg")), SampleSpec(1), None)


@pytest.mark.parametrize(
    "text,match",
    [
        ("sample:x", "seed must be an integer, got 'x'"),
        ("bogus:1", "unknown appearance kind 'bogus'"),
        ("interp:a,b,2", "T must be in \\[0, 1\\], got 2"),
        ("interp:a", "interp needs two appearances"),
        ("image:", "needs a training image"),
        ("photo:", "needs a file path"),
    ],
)
def test_parse_errors_name_the_bad_part(text, match):
    with pytest.raises(AppearanceSpecError, match=match):
        parse_spec(text, "--appearance")
    with pytest.raises(ValueError, match="--appearance"):  # the context names where the SPEC came from
        parse_spec(text, "--appearance")


def test_interpolation_endpoints_and_seeded_samples():
    a, b = torch.zeros(4), torch.arange(4.0)
    assert torch.equal(interpolate_latents(a, b, 0.0), a) and torch.equal(interpolate_latents(a, b, 1.0), b)
    torch.testing.assert_close(interpolate_latents(a, b, 0.25), 0.25 * b)
    assert torch.equal(sample_latent(8, 3), sample_latent(8, 3))
    assert not torch.equal(sample_latent(8, 3), sample_latent(8, 4))


def test_resolve_each_kind_on_a_model(tmp_path):
    model = _model()
    lat = model.train_latents
    d = lat.shape[1]
    torch.testing.assert_close(resolve_latent("mean", model), lat.mean(0))
    for key in ("b.png", "b", "1"):  # file name, stem, index
        assert torch.equal(resolve_latent(f"image:{key}", model), lat[1])
    assert torch.equal(resolve_latent("sample:4", model), sample_latent(d, 4))
    z = np.linspace(-1, 1, d).astype(np.float32)
    np.save(tmp_path / "z.npy", z)
    np.save(tmp_path / "z2.npy", z[None])
    assert torch.equal(resolve_latent(f"latent:{tmp_path / 'z.npy'}", model), torch.from_numpy(z))
    assert torch.equal(resolve_latent(f"latent:{tmp_path / 'z2.npy'}", model), torch.from_numpy(z))
    torch.testing.assert_close(resolve_latent("interp:a,b,0.25", model), 0.75 * lat[0] + 0.25 * lat[1])
    torch.testing.assert_close(resolve_latent("interp:a.png,sample:4", model, t=1.0), sample_latent(d, 4))
    with pytest.raises(AppearanceSpecError, match="a still image needs interp:A,B,T"):
        resolve_latent("interp:a,b", model)
    # photo: through the encoder, the same latent as encoding the pixels directly
    img = (np.random.default_rng(0).random((24, 40, 3)) * 255).astype(np.uint8)
    Image.fromarray(img).save(tmp_path / "p.png")
    z_photo = resolve_latent(f"photo:{tmp_path / 'p.png'}", model)
    torch.testing.assert_close(z_photo, model.encode_image(torch.from_numpy(img)))


def test_resolve_errors_name_the_bad_part(tmp_path):
    model = _model()
    with pytest.raises(AppearanceSpecError, match="unknown training image 'zzz'"):
        resolve_latent("image:zzz", model)
    with pytest.raises(AppearanceSpecError, match="unknown training image 'zzz'"):
        resolve_latent("interp:a.png,zzz,0.5", model)
    model.train_latent_seen[1] = False
    with pytest.raises(AppearanceSpecError, match="'b.png' was never encoded"):
        resolve_latent("image:b.png", model)
    with pytest.raises(AppearanceSpecError, match="missing.jpg.*no such file"):
        resolve_latent(f"photo:{tmp_path / 'missing.jpg'}", model)
    (tmp_path / "junk.jpg").write_bytes(b"not an image")
    with pytest.raises(AppearanceSpecError, match="junk.jpg' as an image"):
        resolve_latent(f"photo:{tmp_path / 'junk.jpg'}", model)
    d = model.train_latents.shape[1]
    z = np.zeros(d, np.float32)
    z[2] = np.nan
    np.save(tmp_path / "nan.npy", z)
    with pytest.raises(AppearanceSpecError, match="nan.npy' holds NaN or Inf"):
        resolve_latent(f"latent:{tmp_path / 'nan.npy'}", model)
    np.save(tmp_path / "short.npy", np.zeros(d + 1, np.float32))
    with pytest.raises(AppearanceSpecError, match=f"short.npy' has shape \\({d + 1},\\); this model needs \\[{d}\\]"):
        resolve_latent(f"latent:{tmp_path / 'short.npy'}", model)


def test_a_test_photo_named_as_a_training_image_says_so_and_gives_the_photo_spec_that_fits(tmp_path):
    """image:NAME of a photo held out of training: an error saying it is a test photo, whose photo:PATH SPEC
    resolves; a name or stem wins over an index (image:0001 is 0001.png, not the training image at index 1)."""
    import re

    model = _model()
    model.set_train_image_names(["0001.png", "0000.png"])
    img = (np.random.default_rng(1).random((24, 40, 3)) * 255).astype(np.uint8)
    held_out = tmp_path / "images" / "0007.png"
    held_out.parent.mkdir()
    Image.fromarray(img).save(held_out)
    model.set_test_photos([str(held_out)])
    for key in ("0007.png", "0007"):
        with pytest.raises(AppearanceSpecError, match="test photo") as info:
            resolve_latent(f"image:{key}", model)
        (spec,) = re.findall(r"photo:\S+", str(info.value))
        assert spec == f"photo:{held_out}"
        assert torch.isfinite(resolve_latent(spec, model)).all()
    assert torch.equal(resolve_latent("image:0001", model), model.train_latents[0])
    assert torch.equal(resolve_latent("image:1", model), model.train_latents[1])
    with pytest.raises(AppearanceSpecError, match="unknown training image '0009'"):
        resolve_latent("image:0009", model)


def test_huge_latents_are_clamped_with_a_warning_and_never_render_nan(tmp_path):
    model = _model()
    d = model.train_latents.shape[1]
    np.save(tmp_path / "big.npy", np.full(d, 1e3, np.float32))
    with pytest.warns(UserWarning, match="scaled down to 100"):
        z = resolve_latent(f"latent:{tmp_path / 'big.npy'}", model)
    assert float(z.norm()) == pytest.approx(MAX_LATENT_NORM, rel=1e-5)
    model.render_latent = torch.full((d,), 1e3)  # set in code: the model checks it too
    with pytest.warns(UserWarning, match="render_latent: latent norm"):
        z = model.current_latent()
    assert float(z.norm()) == pytest.approx(MAX_LATENT_NORM, rel=1e-5)
    with torch.no_grad():
        assert torch.isfinite(model.get_outputs(_camera(24, 16))["rgb"]).all()
    with pytest.raises(AppearanceSpecError, match="render_latent: the latent holds NaN"):
        checked_latent(torch.tensor([0.0, float("nan")]), "render_latent")


def test_environment_variable_uses_the_same_parser(monkeypatch):
    model = _model()
    monkeypatch.setenv(APPEARANCE_ENV, "image:b")
    assert torch.equal(model.current_latent(), model.train_latents[1])
    model.render_latent = None
    monkeypatch.setenv(APPEARANCE_ENV, "sample:x")
    with pytest.raises(ValueError, match=f"{APPEARANCE_ENV}: sample seed must be an integer, got 'x'"):
        model.current_latent()
    monkeypatch.setenv(APPEARANCE_ENV, "mean")
    torch.testing.assert_close(model.current_latent(), model.train_latents.mean(0))
    assert os.environ[APPEARANCE_ENV] == "mean"


def test_photo_refinement_lowers_the_loss_on_the_photo():
    """photo: with refinement fits the latent to the photo seen from a training camera (the scene stays frozen)."""
    from willags_ns.appearance_spec import _render_at, refine_photo_latent

    model = _model()
    cam = _camera(32, 24)
    target = sample_latent(model.train_latents.shape[1], 11)
    with torch.no_grad():
        c = cam.to(model.device)
        c.metadata = {"appearance_latent": target}
        photo = model.get_outputs(c)["rgb"].clone()  # a "photo" of this view under another appearance
    z0 = model.encode_image(photo)
    before = {k: v.detach().clone() for k, v in model.gauss_params.items()}

    z = refine_photo_latent(model, photo, z0, cam, RefineOptions(steps=25, lr=0.05, view="0"))
    with torch.no_grad():
        err0 = float((_render_at(model, cam, z0, 128) - photo).abs().mean())
        err1 = float((_render_at(model, cam, z, 128) - photo).abs().mean())
    assert err1 < 0.8 * err0, (err0, err1)
    for k, v in model.gauss_params.items():
        assert torch.equal(v, before[k]), k


def test_photo_refinement_finds_the_photos_view():
    """Without --refine-view, the training view whose render looks most like the photo is the one refined on."""
    from nerfstudio.cameras.cameras import Cameras

    from willags_ns.appearance_spec import nearest_view

    model = _model()
    views = []
    for dx in (-0.6, 0.0, 0.6):
        c = _camera(32, 24)
        c.camera_to_worlds[0, 0, 3] += dx
        views.append(c)
    cams = Cameras(
        camera_to_worlds=torch.cat([c.camera_to_worlds for c in views]),
        fx=torch.cat([c.fx for c in views]),
        fy=torch.cat([c.fy for c in views]),
        cx=torch.cat([c.cx for c in views]),
        cy=torch.cat([c.cy for c in views]),
        width=torch.cat([c.width for c in views]),
        height=torch.cat([c.height for c in views]),
    )
    z = model.train_latents[0]
    for i in range(3):
        with torch.no_grad():
            c = cams[i : i + 1]
            c.metadata = {"appearance_latent": sample_latent(z.shape[0], 2)}
            photo = model.get_outputs(c)["rgb"]
        assert nearest_view(model, photo, model.encode_image(photo), cams) == i


def test_embedding_model_latents_are_the_table_rows_and_samples_follow_their_spread():
    """An embedding-table model (the default): image:/mean read the table's current rows (not the value recorded
    at the image's last visit), and sample: draws from the rows' own Gaussian, not N(0, I)."""
    from tests.test_mask_eval import _tiny_model as tiny

    model = tiny(use_vae=False)
    model.eval()
    model.set_train_image_names(["a.png", "b.png"])
    emb = model.appearance_nets.embeddings.weight
    with torch.no_grad():  # trained rows far from N(0, I); train_latents keeps its stale zeros
        emb.copy_(
            3.0 + torch.tensor([[0.5], [-0.5]]) * torch.randn(emb.shape[1], generator=torch.Generator().manual_seed(1))
        )
    assert torch.equal(resolve_latent("image:b", model), emb[1].detach())
    torch.testing.assert_close(resolve_latent("mean", model), emb.mean(0).detach())
    s = torch.stack([resolve_latent(f"sample:{k}", model) for k in range(64)])
    assert torch.equal(s[3], resolve_latent("sample:3", model))  # reproducible
    # every sample lies on the line through the two rows (their covariance has rank 1), near their mean
    mid, half = emb.mean(0).detach(), (emb[1] - emb[0]).detach() / 2
    t = ((s - mid) @ half) / (half @ half)
    torch.testing.assert_close(s, mid + t[:, None] * half, atol=1e-3, rtol=1e-3)
    assert 0.3 < float(t.abs().mean()) < 3.0


def test_embedding_table_has_its_own_optimiser_group():
    from tests.test_mask_eval import _tiny_model as tiny
    from willags_ns.method_configs import willags_config

    model = tiny(use_vae=False)
    groups = model.get_param_groups()
    emb = model.appearance_nets.embeddings.weight
    assert [p is emb for p in groups["appearance_embed"]] == [True]
    assert all(p is not emb for p in groups["appearance"])
    assert willags_config().optimizers["appearance_embed"]["optimizer"].lr == 0.02
    assert "appearance_embed" not in tiny(use_vae=True).get_param_groups()


def test_ns_render_camera_idx_renders_that_training_images_appearance(monkeypatch):
    """nerfstudio's `ns-render camera-path --camera-idx N` puts cam_idx N in the cameras' metadata: the render
    takes training image N's latent, unless an appearance was chosen (render_latent, $WILLAGS_APPEARANCE) or the
    viewer is open (its cameras carry cam_idx too; its panel decides)."""
    from tests.test_mask_eval import _tiny_model as tiny

    monkeypatch.delenv(APPEARANCE_ENV, raising=False)
    model = tiny(use_vae=False)
    model.eval()
    model.set_train_image_names(["a.png", "b.png"])
    with torch.no_grad():
        model.appearance_nets.modulation.global_mlp[-1].weight.normal_(0.0, 0.5)
        model.appearance_nets.embeddings.weight.normal_(0.0, 2.0)
    lat = model.image_latents()[0]

    @torch.no_grad()
    def render(**md):
        c = _camera(48, 32)
        c.metadata = md
        return model.get_outputs(c)["rgb"]

    torch.testing.assert_close(render(cam_idx=1), render(appearance_latent=lat[1]))
    assert not torch.allclose(render(cam_idx=1), render(cam_idx=0), atol=1e-3)
    mean = render()
    model.render_latent = lat[0].clone()  # a chosen appearance wins
    torch.testing.assert_close(render(cam_idx=1), render(appearance_latent=lat[0]))
    model.render_latent = None
    appearance_controls(model).p01_a.gui_handle = object()  # the viewer is open: the panel (here: the mean) decides
    torch.testing.assert_close(render(cam_idx=1), mean)


def test_photo_on_an_embedding_model_is_fitted_without_refine_steps(tmp_path):
    """No encoder: photo:P fits the latent to the photo (PHOTO_FIT_STEPS) instead of failing; it needs the
    training cameras, and says so without them."""
    from tests.test_mask_eval import _tiny_model as tiny
    from willags_ns.appearance_spec import PHOTO_FIT_STEPS

    model = tiny(use_vae=False)
    model.eval()
    model.set_train_image_names(["a.png", "b.png"])
    with torch.no_grad():
        model.appearance_nets.modulation.global_mlp[-1].weight.normal_(0.0, 0.3)
    c = _camera(48, 32)
    c.metadata = {"appearance_latent": torch.full((8,), 1.5)}
    with torch.no_grad():
        photo = (model.get_outputs(c)["rgb"].clamp(0, 1) * 255).to(torch.uint8).numpy()
    Image.fromarray(photo).save(tmp_path / "p.png")
    spec = f"photo:{tmp_path / 'p.png'}"
    with pytest.raises(AppearanceSpecError, match="needs the training cameras"):
        resolve_latent(spec, model)
    z = resolve_latent(spec, model, cameras=_camera(48, 32))
    z_ref = resolve_latent(spec, model, refine=RefineOptions(steps=PHOTO_FIT_STEPS), cameras=_camera(48, 32))
    torch.testing.assert_close(z, z_ref)  # the same fit as --refine-steps PHOTO_FIT_STEPS
    assert not torch.allclose(z, model.image_latents()[0].mean(0))


def test_photo_fit_starts_from_the_training_latent_whose_render_is_closest():
    """A photo whose appearance is a far training row's: the fit starts from that row (RefineOptions.start_candidates)
    rather than the mean, so a short fit lands on it; with no candidates it starts from the mean and stays far."""
    from tests.test_mask_eval import _tiny_model as tiny
    from willags_ns.appearance_spec import _render_at, refine_photo_latent

    model = tiny(use_vae=False)
    model.eval()
    model.set_train_image_names(["a.png", "b.png", "c.png"][: model.train_latents.shape[0]])
    with torch.no_grad():
        model.appearance_nets.modulation.global_mlp[-1].weight.normal_(0.0, 0.3)
        model.appearance_nets.embeddings.weight.normal_(0.0, 0.1)
        model.appearance_nets.embeddings.weight[1] = 2.0  # one photo far from the rest
    lat = model.image_latents()[0]
    cam = _camera(48, 32)
    with torch.no_grad():
        photo = _render_at(model, cam, lat[1], 128).clone()
    mean = lat.mean(0)
    z_far = refine_photo_latent(model, photo, mean, cam, RefineOptions(steps=1, lr=1e-3, view="0"))
    z_mean = refine_photo_latent(model, photo, mean, cam, RefineOptions(steps=1, lr=1e-3, view="0", start_candidates=0))
    assert float((z_far - lat[1]).norm()) < 0.05
    assert float((z_mean - lat[1]).norm()) > 1.0
    with torch.no_grad():
        err_far = float((_render_at(model, cam, z_far, 128) - photo).abs().mean())
        err_mean = float((_render_at(model, cam, z_mean, 128) - photo).abs().mean())
    assert err_far < 0.5 * err_mean, (err_far, err_mean)
