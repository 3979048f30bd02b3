import warnings

import pytest
import torch
import torch.nn.functional as F
from torch import nn

from willags_ns.mask import rule, transient
from willags_ns.mask.rule import (
    MaskConfig,
    mask_active,
    mask_threshold,
    robust_threshold,
    static_mask,
    transient_mask,
    transient_threshold,
)
from willags_ns.mask.transient import (
    PerceptualFeatures,
    build_seeded_vgg16_features,
    load_vgg16_features,
    perceptual_error,
)


@pytest.fixture
def fresh_warning(monkeypatch):
    """Reset the warn-once flag (other tests may already have triggered the fallback warning)."""
    monkeypatch.setattr(transient, "_FALLBACK_WARNED", False)


@pytest.fixture(scope="module")
def seeded_features():
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        pf = PerceptualFeatures("seeded")
        pf(torch.rand(1, 3, 16, 16))
    return pf


def _blur(x):
    k = torch.tensor([0.25, 0.5, 0.25])
    k2 = (k[:, None] * k[None]).view(1, 1, 3, 3).repeat(3, 1, 1, 1)
    return F.conv2d(F.pad(x, (1, 1, 1, 1), mode="replicate"), k2, groups=3)


def _textured_scene(seed=0):
    """96x128 scene: 1/f colour texture with a photo-like fine-scale energy, plus flat patches (sharp edges)."""
    g = torch.Generator().manual_seed(100 + seed)
    img = _blur(_blur(transient._pink_noise(1, 128, g)[:, :, :96]))
    for _ in range(8):
        y0 = int(torch.randint(0, 80, (1,), generator=g))
        x0 = int(torch.randint(0, 110, (1,), generator=g))
        patch = img[0, :, y0 : y0 + 16, x0 : x0 + 18]
        img[0, :, y0 : y0 + 16, x0 : x0 + 18] = 0.5 * patch + 0.5 * torch.rand(3, 1, 1, generator=g)
    return img


def test_occluder_is_masked_and_clean_pixels_kept(seeded_features):
    clean = _textured_scene()
    g = torch.Generator().manual_seed(7)
    # an imperfect teacher render: slightly blurred, 2% colour shift, a little noise
    teacher = _blur(clean) * torch.tensor([1.02, 1.0, 0.98]).view(1, 3, 1, 1)
    teacher = (teacher + 0.01 * torch.randn(teacher.shape, generator=g)).clamp(0, 1)
    gt = clean.clone()
    occ = torch.zeros(96, 128, dtype=torch.bool)
    occ[30:62, 50:90] = True
    gt[0, :, 30:62, 50:90] = torch.tensor([0.9, 0.2, 0.1]).view(3, 1, 1)  # flat-coloured occluder

    D = perceptual_error(seeded_features(gt), seeded_features(teacher), (96, 128))
    assert D.shape == (1, 96, 128)
    D = D[0]
    keep = static_mask(D[None], 0.85)[0]
    recall = (~keep & occ).float().sum() / occ.sum()
    false_pos = (~keep & ~occ).float().sum() / (~occ).sum()
    far = torch.ones_like(occ)
    far[22:70, 42:98] = False  # more than 8 px away from the occluder
    assert recall > 0.95, recall
    assert false_pos < 0.12, false_pos  # only a thin ring around the occluder (receptive field of relu3_3)
    assert (~keep & far).float().mean() < 0.01
    assert D[occ].median() > 2 * 0.85 and D[far].median() < 0.5 * 0.85
    # the same scene against itself: nothing masked
    same = perceptual_error(seeded_features(clean), seeded_features(clean), (96, 128))
    assert same.abs().max() < 1e-5 and static_mask(same, 0.85).all()


def test_seeded_fallback_is_deterministic_and_calibrated():
    a = build_seeded_vgg16_features()
    b = build_seeded_vgg16_features()
    for p, q in zip(a.parameters(), b.parameters(), strict=True):
        assert torch.equal(p, q)
    # calibration holds on unrelated images it was not fitted on: mean D ~ FALLBACK_UNRELATED_D
    g = torch.Generator().manual_seed(123)
    imgs = transient._imagenet_normalize(transient._pink_noise(8, 64, g))
    feats = transient._tap_outputs(a, imgs)
    d = perceptual_error([f[:4] for f in feats], [f[4:] for f in feats], (64, 64)).mean().item()
    assert d == pytest.approx(transient.FALLBACK_UNRELATED_D, rel=0.1)


def test_layout_matches_torchvision_indices():
    net = transient._vgg16_features_layers()
    assert len(net) == 16
    assert [i for i, m in enumerate(net) if isinstance(m, nn.Conv2d)] == [0, 2, 5, 7, 10, 12, 14]
    assert [i for i, m in enumerate(net) if isinstance(m, nn.MaxPool2d)] == [4, 9]
    assert all(isinstance(net[i], nn.ReLU) for i in transient.TAPS)


def test_path_loader_round_trip(tmp_path, fresh_warning):
    ref = transient._vgg16_features_layers()
    # torchvision's full-model layout: "features.N.weight" (plus classifier keys, ignored)
    sd = {f"features.{k}": v for k, v in ref.state_dict().items()}
    sd["classifier.0.weight"] = torch.zeros(2, 2)
    file = tmp_path / "vgg16.pth"
    torch.save(sd, file)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # no fallback warning on a successful load
        net, source = load_vgg16_features("path", file)
        net_auto, source_auto = load_vgg16_features("auto", file)
    assert source == f"path:{file}" and source_auto == source
    for (n, p), q in zip(net.state_dict().items(), ref.state_dict().values(), strict=True):
        assert torch.equal(p, q), n
    assert all(not p.requires_grad for p in net.parameters()) and not net.training
    # a features-only state dict ("N.weight") works too
    file2 = tmp_path / "features.pth"
    torch.save(ref.state_dict(), file2)
    assert load_vgg16_features("path", file2)[1] == f"path:{file2}"


def test_path_loader_errors(tmp_path):
    with pytest.raises(FileNotFoundError):
        load_vgg16_features("path", tmp_path / "missing.pth")
    with pytest.raises(ValueError):
        load_vgg16_features("path", None)
    bad = tmp_path / "bad.pth"
    torch.save({"features.0.weight": torch.zeros(64, 3, 3, 3)}, bad)
    with pytest.raises(ValueError):
        load_vgg16_features("path", bad)


def test_auto_reads_the_hub_cache(tmp_path, monkeypatch):
    monkeypatch.setenv("TORCH_HOME", str(tmp_path))
    ref = transient._vgg16_features_layers()
    file = transient.hub_weights_file()
    assert file == tmp_path / "hub" / "checkpoints" / "vgg16-397923af.pth"
    file.parent.mkdir(parents=True)
    torch.save({f"features.{k}": v for k, v in ref.state_dict().items()}, file)
    net, source = load_vgg16_features("auto")
    assert source == f"torch_hub:{file}"
    torch.testing.assert_close(net[14].weight, ref[14].weight)


def test_fallback_warns_once_and_reports_source(tmp_path, monkeypatch, fresh_warning):
    monkeypatch.setenv("TORCH_HOME", str(tmp_path))  # an empty hub cache
    with pytest.warns(RuntimeWarning, match="VGG16 ImageNet weights not found") as rec:
        _, source = load_vgg16_features("auto")
    assert source.startswith("seeded")
    assert str(transient.hub_weights_file()) in str(rec[0].message)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        _, source2 = load_vgg16_features("auto")  # second time: silent
        pf = PerceptualFeatures("seeded")
        pf(torch.rand(1, 3, 8, 8))
    assert source2 == source and pf.source == source


def test_perceptual_features_module(seeded_features):
    pf = PerceptualFeatures("seeded", max_resolution=32)
    assert pf.source is None
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        feats = pf(torch.rand(2, 3, 48, 64))
    assert pf.source is not None and pf.source.startswith("seeded")
    # computed at max_resolution (longest side 32 -> 24x32), three taps at 1, 1/2, 1/4
    assert [tuple(f.shape) for f in feats] == [(2, 64, 24, 32), (2, 128, 12, 16), (2, 256, 6, 8)]
    # the frozen network is not part of the module's parameters / state dict
    assert len(list(pf.parameters())) == 0 and len(pf.state_dict()) == 0
    assert all(not f.requires_grad for f in feats)


def test_perceptual_error_is_sum_of_upsampled_channel_means():
    a = [torch.zeros(1, 2, 2, 2), torch.zeros(1, 4, 1, 1)]
    b = [torch.ones(1, 2, 2, 2) * torch.tensor([1.0, 3.0]).view(1, 2, 1, 1), torch.full((1, 4, 1, 1), 0.5)]
    D = perceptual_error(a, b, (4, 4))
    # layer 1: mean over channels of (1, 3) = 2 everywhere; layer 2: 0.5 -> D = 2.5
    torch.testing.assert_close(D, torch.full((1, 4, 4), 2.5))
    with pytest.raises(ValueError):
        perceptual_error(a, b[:1], (4, 4))


def test_static_mask_threshold_is_strict():
    D = torch.tensor([[[0.0, 0.84, 0.85, 2.0]]])
    assert static_mask(D, 0.85).tolist() == [[[True, True, False, False]]]


def test_robust_threshold_equals_fixed_on_a_well_explained_image():
    g = torch.Generator().manual_seed(0)
    D = 0.1 + 0.05 * torch.randn(2, 32, 32, generator=g).abs()  # a teacher that explains the image
    D[0, :8, :8] = 3.0  # an occluder
    thr = robust_threshold(D, 0.85, 2.0)
    assert thr.shape == (2, 1, 1)
    torch.testing.assert_close(thr, torch.full((2, 1, 1), 0.85))
    assert torch.equal(static_mask(D, thr), static_mask(D, 0.85))


def test_robust_threshold_keeps_texture_and_flags_the_occluder():
    """Textured static pixels with D around 0.7 +- 0.3 (a blurry teacher): the fixed 0.85 drops ~30% of them,
    the robust bar keeps nearly all of them and still flags an occluder at D = 2.5."""
    g = torch.Generator().manual_seed(1)
    D = (0.7 + 0.3 * torch.randn(1, 64, 64, generator=g)).clamp_min(0)
    occ = torch.zeros(1, 64, 64, dtype=torch.bool)
    occ[0, 10:26, 30:50] = True
    D[occ] = 2.5 + 0.2 * torch.rand(int(occ.sum()), generator=g)
    fixed_fp = (~static_mask(D, 0.85) & ~occ).float().sum() / (~occ).sum()
    thr = robust_threshold(D, 0.85, 2.0)
    robust_fp = (~static_mask(D, thr) & ~occ).float().sum() / (~occ).sum()
    assert fixed_fp > 0.25 and robust_fp < 0.05, (fixed_fp, robust_fp)
    assert bool((~static_mask(D, thr))[occ].all())  # every occluder pixel still flagged
    assert 0.85 < float(thr) < 2.5


def test_transient_threshold_rules():
    D = torch.rand(1, 8, 8)
    assert transient_threshold(D, 0.85, "fixed") == 0.85
    assert transient_threshold(D, float("inf"), "robust") == float("inf")  # warming up: nothing masked
    assert transient_threshold(D, 0.85, "robust").shape == (1, 1, 1)
    with pytest.raises(ValueError, match="unknown mask threshold rule"):
        transient_threshold(D, 0.85, "bogus")


def test_transient_mask_flags_above_threshold_and_rejects_a_mostly_flagged_image():
    D = torch.zeros(10, 10)
    D[:3] = 2.0  # 30% of the image
    transient, rejected = transient_mask(D, 0.85, max_masked_fraction=0.5)
    assert not rejected and torch.equal(transient, D >= 0.85)
    transient, rejected = transient_mask(D, 0.85, max_masked_fraction=0.25)
    assert rejected and not transient.any()  # rejected: nothing is transient, every pixel is supervised
    transient, rejected = transient_mask(D, float("inf"), "robust")  # warming up
    assert not rejected and not transient.any()


def test_schedule_boundaries():
    assert not mask_active(0, 500)
    assert not mask_active(499, 500)
    assert mask_active(500, 500)
    assert mask_active(0, 0)
    assert mask_threshold(499, 0.85, 500) == float("inf")
    assert mask_threshold(500, 0.85, 500) == 0.85
    assert mask_threshold(499, 0.85, 500, 100) == float("inf")
    assert mask_threshold(500, 0.85, 500, 100) == pytest.approx(0.85 * rule.RAMP_START_FACTOR)
    assert mask_threshold(550, 0.85, 500, 100) == pytest.approx(0.85 * (rule.RAMP_START_FACTOR + 1) / 2)
    assert mask_threshold(600, 0.85, 500, 100) == pytest.approx(0.85)
    assert mask_threshold(10_000, 0.85, 500, 100) == pytest.approx(0.85)


def test_config_defaults():
    cfg = MaskConfig()
    assert cfg.threshold == 0.85 and cfg.vgg_weights == "auto"
    assert cfg.threshold_rule == "robust" and cfg.robust_k == 2.0
    # the default's mask starts at step 5000 and only where the renders then leave transients
    assert cfg.warmup_steps == 5000 and cfg.start_rule == "transients" and cfg.start_share == 0.10


def test_the_paper_and_fast_presets_start_their_mask_early_and_always():
    from willags_ns.method_configs import willags_lite_config, willags_paper_config

    paper = willags_paper_config().pipeline.model.mask
    lite = willags_lite_config().pipeline.model.mask
    assert (paper.warmup_steps, paper.start_rule) == (500, "always")
    assert (lite.warmup_steps, lite.start_rule) == (300, "always")


def test_modules_do_not_import_torchvision_eagerly():
    import subprocess
    import sys

    code = (
        "import sys, willags_ns.mask.transient, willags_ns.objective.losses, willags_ns.mask.teacher, willags_ns.appearance.vae, "
        "willags_ns.appearance.triplane, willags_ns.appearance.decoder; print('torchvision' in sys.modules)"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "False"


def _fake_torchvision(vgg16_fn):
    """A stand-in ``torchvision`` module (no import of the real one, no network)."""
    import types

    tv = types.ModuleType("torchvision")
    models = types.SimpleNamespace(vgg16=vgg16_fn, VGG16_Weights=types.SimpleNamespace(IMAGENET1K_V1="v1"))
    setattr(tv, "models", models)  # noqa: B010 (a plain attribute assignment upsets the type checker)
    return tv


def test_torchvision_loader_success_and_offline_fallback(monkeypatch, fresh_warning):
    import sys
    import types

    ref = transient._vgg16_features_layers()
    full = types.SimpleNamespace(features=nn.Sequential(*ref, nn.MaxPool2d(2)))  # the full net has more layers
    monkeypatch.setitem(sys.modules, "torchvision", _fake_torchvision(lambda weights: full))
    net, source = load_vgg16_features("torchvision")
    assert source == "torchvision:IMAGENET1K_V1"
    torch.testing.assert_close(net[12].weight, ref[12].weight)

    def offline(weights):
        raise RuntimeError("<urlopen error [Errno -3] Temporary failure in name resolution>")

    monkeypatch.setitem(sys.modules, "torchvision", _fake_torchvision(offline))
    with pytest.warns(RuntimeWarning, match="name resolution"):
        _, source = load_vgg16_features("torchvision")
    assert source.startswith("seeded")


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA GPU")
def test_cuda_features_match_cpu(seeded_features):
    x = torch.rand(1, 3, 40, 56, generator=torch.Generator().manual_seed(0))
    y = x.flip(-1)
    ref = perceptual_error(seeded_features(x), seeded_features(y), (40, 56))
    pf = PerceptualFeatures("seeded")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        out = perceptual_error(pf(x.cuda()), pf(y.cuda()), (40, 56))
    assert out.is_cuda
    torch.testing.assert_close(out.cpu(), ref, atol=1e-3, rtol=1e-3)


def test_image_distance_is_one_batched_pass_equal_to_two_single_passes(seeded_features):
    """Training and the mask evaluation take D from one VGG pass over the photo and the teacher's render together;
    it equals the two separate passes (per-image network, no batch statistics), with the normalisation constants
    kept per device and dtype."""
    from willags_ns.mask.transient import image_distance

    g = torch.Generator().manual_seed(5)
    photo = torch.rand(40, 56, 3, generator=g)
    render = (photo + 0.2 * torch.rand(40, 56, 3, generator=g)).clamp(0, 1)
    d = image_distance(seeded_features, photo, render)
    single = perceptual_error(
        seeded_features(photo.permute(2, 0, 1)[None]), seeded_features(render.permute(2, 0, 1)[None]), (40, 56)
    )[0]
    assert d.shape == (40, 56)
    torch.testing.assert_close(d, single, atol=1e-5, rtol=1e-5)
    assert float(d.mean()) > 0
    torch.testing.assert_close(image_distance(seeded_features, photo, photo), torch.zeros(40, 56), atol=1e-6, rtol=0)
    # float64 inputs get float64 constants (cached per dtype), not the float32 ones cached above
    d64 = image_distance(seeded_features, photo.double(), render.double())
    assert d64.dtype == torch.float64
    torch.testing.assert_close(d64.float(), d, atol=1e-4, rtol=1e-4)
