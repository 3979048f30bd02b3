"""willags / --pipeline.model.auto-config: the inspector's recommendation sets the model's switches before the
model is built, is logged (console, tensorboard, auto_config.json) and is what config.yml reloads."""

import json

import pytest
import torch
import yaml

from tests._scenes import small_scene
from willags_ns.method_configs import willags_config, willags_model_config
from willags_ns.tools.autoconfig import (
    AUTO_CONFIG_FILE,
    apply_auto_config,
    format_summary,
    overrides_from_recommendation,
    tensorboard_entries,
)


@pytest.fixture(scope="module")
def scenes(tmp_path_factory):
    root = tmp_path_factory.mktemp("auto_scenes")
    out = {}
    for name, app, tr in (("static", 0.0, 0.0), ("appearance", 1.0, 0.0), ("wild", 1.0, 0.6)):
        out[name] = small_scene(root / name, app, tr)
    return out


def _rec(preset: str, latent: bool, mask: bool, dim: int) -> dict:
    on = lambda v: {"on": v, "reason": "r"}  # noqa: E731
    return {
        "appearance_latent": on(latent),
        "mask": on(mask),
        "teacher": on(mask),
        "triplane_field": on(False),
        "latent_dim": {"value": dim, "reason": "r"},
        "preset": {"value": preset, "flags": [], "reason": "r"},
    }


def test_overrides_map_each_recommendation():
    assert overrides_from_recommendation(_rec("willags-3dgs", False, False, 0)) == {
        "appearance": "sh",
        "mask.enabled": False,
        "use_field": False,
    }
    assert overrides_from_recommendation(_rec("willags", True, False, 64)) == {
        "appearance": "willags",
        "mask.enabled": False,
        "use_field": False,
        "latent.dim": 64,
    }
    assert overrides_from_recommendation(_rec("willags", False, True, 8))["mask.enabled"] is True


def test_apply_follows_the_scene(scenes):
    static, appearance, wild = (willags_model_config() for _ in range(3))
    s = apply_auto_config(static, scenes["static"])
    assert s["applied"] and static.appearance == "sh" and not static.mask.enabled
    assert s["changes"]["appearance"] == ["willags", "sh"]
    a = apply_auto_config(appearance, scenes["appearance"])
    assert appearance.appearance == "willags" and appearance.mask.enabled is False
    assert appearance.latent.dim == 32  # 20 training images: the smaller latent
    assert a["changes"]["mask.enabled"] == [True, False] and "threshold" in a["reasons"]["mask"]
    w = apply_auto_config(wild, scenes["wild"])
    assert wild.appearance == "willags" and wild.mask.enabled is True and not wild.use_field
    assert w["switches"] == {"appearance_latent": True, "mask": True, "teacher": True, "triplane_field": False}
    text, scalars = tensorboard_entries(w)
    assert scalars["auto_config/mask"] == 1.0 and scalars["auto_config/latent_dim"] == 32.0
    assert "mask: ON" in text["auto_config"] and "appearance_latent: ON" in text["auto_config"]


def test_uninspectable_scene_keeps_the_method(tmp_path):
    cfg = willags_model_config()
    before = (cfg.appearance, cfg.mask.enabled, cfg.latent.dim)
    s = apply_auto_config(cfg, tmp_path / "nope")
    assert not s["applied"] and str(tmp_path / "nope") in s["error"]
    assert (cfg.appearance, cfg.mask.enabled, cfg.latent.dim) == before
    assert "not applied" in format_summary(s)


def test_the_inspecting_method_is_willags_under_one_name():
    from nerfstudio.plugins.registry import discover_methods

    methods, _ = discover_methods()
    assert methods["willags"].pipeline.model.auto_config is True
    assert [m for m in methods if m.startswith("willags") and methods[m].pipeline.model.auto_config] == ["willags"]
    assert willags_config().pipeline.model.mask.enabled is True  # before inspection: the full model


def test_the_default_inspects_first_and_willags_full_does_not():
    """`willags` is the full model with auto_config (docs/design.md); `willags-full` is the same model without
    inspection."""
    from nerfstudio.plugins.registry import discover_methods

    from willags_ns.engine.time_budget import preset_defaults
    from willags_ns.method_configs import willags_config, willags_full_config

    methods, _ = discover_methods()
    default, full = methods["willags"], methods["willags-full"]
    assert default.pipeline.model.auto_config is True and full.pipeline.model.auto_config is False
    assert (default.method_name, full.method_name) == ("willags", "willags-full")
    # the same model apart from the inspection: every field but auto_config equal, the schedule equal
    d, f = vars(willags_config().pipeline.model), vars(willags_full_config().pipeline.model)
    assert {k for k in d if d[k] != f[k]} == {"auto_config"}
    assert f == vars(willags_model_config())
    assert willags_config().max_num_iterations == willags_full_config().max_num_iterations == 30000
    # the preset a user's switches are told from (time_budget.preset_defaults) is the method's own
    assert preset_defaults("willags")[0].auto_config is True
    assert preset_defaults("willags-full")[0].auto_config is False


@pytest.mark.slow
def test_training_applies_logs_and_reloads(tmp_path, scenes, monkeypatch):
    """ns-train willags on a scene with appearance change and no transients: no mask, no teacher; the choice
    goes to tensorboard and auto_config.json; config.yml reloads the trained model without inspecting again."""
    from nerfstudio.utils import writer

    from tests.test_train import _train

    logged = []
    orig = writer.put_config
    monkeypatch.setattr(
        writer,
        "put_config",
        lambda name, config_dict, step: (logged.append((name, config_dict)), orig(name, config_dict, step)),
    )
    config, trainer, losses = _train(tmp_path, "willags", steps=6, data=scenes["appearance"], auto_config=True)
    model = trainer.pipeline.model
    assert model.teacher is None and not model.config.mask.enabled
    assert model.appearance_nets.latent_dim == 32
    assert not any("masked_fraction" in m for _, m in losses)
    ours = [c for n, c in logged if n == "auto_config"]  # nerfstudio logs its own "config" too
    assert len(ours) == 1 and "mask: off" in ours[0]["auto_config"]

    run_dir = config.get_base_dir()
    saved = json.loads((run_dir / AUTO_CONFIG_FILE).read_text())
    assert saved["applied"] and saved["settings"]["mask.enabled"] is False
    assert saved["report"]["evidence"]["transient_score"] < 0.2
    text = (run_dir / "config.yml").read_text()
    reloaded = yaml.load(text, Loader=yaml.Loader)
    assert reloaded.pipeline.model.auto_config is False and reloaded.pipeline.model.mask.enabled is False

    from nerfstudio.utils.eval_utils import eval_setup

    import willags_ns.tools.autoconfig as ac

    monkeypatch.setattr(ac, "inspect_scene", lambda *a, **k: pytest.fail("reload must not inspect again"))
    _, pipeline, _, _ = eval_setup(run_dir / "config.yml", test_mode="test")
    assert pipeline.model.num_points == model.num_points and pipeline.model.teacher is None
    cam = pipeline.datamanager.eval_dataset.cameras[0:1]
    with torch.no_grad():
        assert torch.isfinite(pipeline.model.get_outputs_for_camera(cam)["rgb"]).all()


# --------------------------------------------------------------------------------------------------------------------
# the sky (inspector's evidence 4)


def _rec_sky(preset: str, sky: bool, measured: bool = True) -> dict:
    rec = _rec(preset, preset != "willags-3dgs", False, 64 if preset != "willags-3dgs" else 0)
    rec["sky"] = {"on": sky, "measured": measured, "reason": "r"}
    return rec


def test_overrides_map_the_sky():
    on = overrides_from_recommendation(_rec_sky("willags", True))
    assert on["sky.enabled"] is True and on["sky.alpha_penalty"] == 0.0 and on["sky.region"] == "open"
    surround = _rec_sky("willags", True)
    surround["sky"]["mode"] = "surround"
    over = overrides_from_recommendation(surround)
    assert (over["sky.enabled"], over["sky.region"], over["sky.alpha_penalty"]) == (True, "everywhere", 0.1)
    off = overrides_from_recommendation(_rec_sky("willags", False))
    assert off["sky.enabled"] is False and off["sky.alpha_penalty"] == 0.0
    # not measured (no SfM points): the method's own sky stays
    assert not any(k.startswith("sky.") for k in overrides_from_recommendation(_rec_sky("willags", True, False)))
    # plain 3DGS: appearance='sh' builds no sky, nothing to set
    assert overrides_from_recommendation(_rec_sky("willags-3dgs", False)) == {
        "appearance": "sh",
        "mask.enabled": False,
        "use_field": False,
    }


@pytest.fixture(scope="module")
def plane_scenes(tmp_path_factory):
    from tests.tools.test_inspect import write_plane_scene

    root = tmp_path_factory.mktemp("auto_plane")
    return {"lower": write_plane_scene(root / "lower", True), "full": write_plane_scene(root / "full", False)}


def test_apply_sets_the_sky_from_the_scene(plane_scenes):
    cfg = willags_model_config()
    cfg.sky.enabled, cfg.sky.alpha_penalty = False, 0.0
    s = apply_auto_config(cfg, plane_scenes["lower"])  # the upper half of every image has no SfM point
    assert cfg.sky.enabled is True and cfg.sky.alpha_penalty == 0.0 and s["sky"] is True
    assert s["changes"]["sky.enabled"] == [False, True] and "threshold" in s["reasons"]["sky"]
    text, scalars = tensorboard_entries(s)
    assert scalars["auto_config/sky"] == 1.0 and "sky: ON" in text["auto_config"]

    cfg = willags_model_config()
    cfg.sky.enabled, cfg.sky.alpha_penalty = True, 0.1  # a sky with its penalty, switched off by the scene
    s = apply_auto_config(cfg, plane_scenes["full"])  # points everywhere: no open background
    assert cfg.sky.enabled is False and cfg.sky.alpha_penalty == 0.0 and s["sky"] is False
    assert s["changes"]["sky.enabled"] == [True, False]
    text, scalars = tensorboard_entries(s)
    assert scalars["auto_config/sky"] == 0.0 and "sky: off" in format_summary(s)


def test_scene_without_points_keeps_the_methods_sky(scenes, tmp_path):
    src = scenes["appearance"]
    meta = json.loads((src / "transforms.json").read_text())
    meta.pop("ply_file_path")
    meta["frames"] = [{**f, "file_path": str(src / f["file_path"])} for f in meta["frames"]]
    (tmp_path / "transforms.json").write_text(json.dumps(meta))
    for own in (True, False):
        cfg = willags_model_config()
        cfg.sky.enabled, cfg.sky.alpha_penalty = own, 0.05
        s = apply_auto_config(cfg, tmp_path)
        assert s["applied"] and cfg.sky.enabled is own and cfg.sky.alpha_penalty == 0.05
        assert not any(k.startswith("sky") for k in s["changes"]) and s["sky"] is own
        assert "not measured" in s["reasons"]["sky"] and "method's own setting" in s["reasons"]["sky"]


def test_the_inspectors_default_sky_is_the_willags_presets():
    """inspect.WILLAGS_SKY names the default preset's sky (the recommended command lists only what differs)."""
    from willags_ns.tools.inspection import WILLAGS_SKY

    cfg = willags_model_config()
    own = {"sky.enabled": cfg.sky.enabled, "sky.region": cfg.sky.region, "sky.alpha_penalty": cfg.sky.alpha_penalty}
    assert own == WILLAGS_SKY


def test_a_subject_against_the_sky_sets_the_surround_sky_unless_the_user_named_the_region(tmp_path):
    from tests.tools.test_inspect import write_plane_scene

    scene = write_plane_scene(tmp_path / "column", lower_only=False, column=True)
    cfg = willags_model_config()
    s = apply_auto_config(cfg, scene)
    assert (cfg.sky.enabled, cfg.sky.region, cfg.sky.alpha_penalty) == (True, "everywhere", 0.1)
    assert s["changes"]["sky.region"] == ["open", "everywhere"] and "surround" in format_summary(s)
    cfg = willags_model_config()
    s = apply_auto_config(cfg, scene, keep=("sky.region",))
    assert cfg.sky.region == "open" and cfg.sky.alpha_penalty == 0.1 and s["kept"] == {"sky.region": "open"}


# --------------------------------------------------------------------------------------------------------------------
# the user's own switches win over the inspector


def test_user_switches_are_flags_named_or_values_changed_from_the_preset():
    from willags_ns.tools.autoconfig import user_switches

    cfg, preset = willags_model_config(), willags_model_config()
    assert user_switches(cfg, preset, []) == ()
    cfg.use_field, cfg.sky.alpha_penalty = True, 0.1
    assert user_switches(cfg, preset, []) == ("use_field", "sky.alpha_penalty")
    # a flag repeating the preset's value is only seen on the command line (both spellings of tyro's flags)
    argv = ["--data", "x", "--pipeline.model.mask.enabled", "True", "--pipeline.model.sky.enabled=True"]
    assert user_switches(cfg, preset, argv) == ("mask.enabled", "use_field", "sky.enabled", "sky.alpha_penalty")
    assert user_switches(cfg, None, ["--pipeline.model.mask.enabled", "True"]) == ("mask.enabled",)  # preset unknown


def test_kept_switches_are_left_reported_and_printed(scenes):
    """The 'appearance' scene has no transients: the inspector turns the mask off, unless the user set it."""
    cfg = willags_model_config()
    s = apply_auto_config(cfg, scenes["appearance"], keep=("mask.enabled",))
    assert cfg.mask.enabled is True and "mask.enabled" not in s["settings"] and s["kept"] == {"mask.enabled": True}
    assert s["switches"]["mask"] is True and s["switches"]["teacher"] is True
    assert "kept as you set it: mask.enabled=True" in s["reasons"]["mask"]
    assert "kept (your flags win): mask.enabled=True" in format_summary(s)
    plain = willags_model_config()
    s = apply_auto_config(plain, scenes["appearance"])
    assert plain.mask.enabled is False and s["kept"] == {} and s["switches"]["mask"] is False


def test_a_mask_under_the_start_rule_says_when_and_where_it_starts(scenes):
    """A mask that is on under mask.start_rule "transients" is decided again at its warm-up's end: the summary says
    so; a mask that is off says nothing of it."""
    cfg = willags_model_config()
    cfg.mask.start_rule, cfg.mask.warmup_steps, cfg.mask.start_share = "transients", 5000, 0.1
    s = apply_auto_config(cfg, scenes["appearance"], keep=("mask.enabled",))
    assert "starts at step 5,000 only where the training photos' own renders then leave at least 10%" in format_summary(
        s
    )
    off = willags_model_config()
    off.mask.start_rule = "transients"
    s = apply_auto_config(off, scenes["appearance"])
    assert s["switches"]["mask"] is False and "start_rule" not in s["reasons"]["mask"]


def test_training_keeps_a_switch_the_user_changed_from_the_preset(tmp_path, scenes):
    from tests.test_train import _train

    config, trainer, _ = _train(
        tmp_path, "willags", steps=2, data=scenes["appearance"], auto_config=True, use_field=True
    )
    model = trainer.pipeline.model
    assert config.pipeline.auto_config_keep == ("use_field",)
    assert model.appearance_nets.field is not None and not model.config.mask.enabled  # the field kept, the mask decided
    assert trainer.pipeline.auto_config_summary["kept"] == {"use_field": True}


def test_on_liberty_the_default_resolves_to_the_measured_surround_sky_without_mask(shared_data):
    """The default's model on liberty, after inspection, is exactly the measured `willags-skyalpha-nomask`'s: the
    full model without the mask, with the sky behind every pixel and its alpha penalty."""
    import dataclasses

    from benchmarks.methods import set_nested

    resolved = willags_model_config()
    summary = apply_auto_config(resolved, shared_data / "liberty")
    assert summary["applied"] and summary["changes"] == {
        "mask.enabled": [True, False],
        "sky.region": ["open", "everywhere"],
        "sky.alpha_penalty": [0.0, 0.1],
    }
    measured = willags_model_config()
    skyalpha_nomask = (("sky.enabled", True), ("sky.region", "everywhere"), ("sky.alpha_penalty", 0.1))
    for key, value in (*skyalpha_nomask, ("mask.enabled", False)):
        set_nested(measured, key, value)
    assert dataclasses.asdict(resolved) == dataclasses.asdict(measured)


def test_the_pixels_rule_sets_mcmcs_cap_from_the_training_photos_unless_the_user_set_it(scenes):
    from willags_ns.splats.mcmc import McmcConfig, scene_cap

    cfg = willags_model_config()
    assert cfg.mcmc.cap_rule == "fixed"
    fixed = apply_auto_config(cfg, scenes["appearance"])
    assert cfg.mcmc.cap_max == McmcConfig().cap_max  # the default: as set, and said why, with the other rule's cap
    mpx = fixed["report"]["facts"]["train_megapixels"]
    assert mpx == pytest.approx(20 * 96 * 72 / 1e6, abs=0.01)  # 20 training photos of 96 x 72 px
    assert fixed["reasons"]["capacity"].startswith(f"at most {McmcConfig().cap_max:,} Gaussians (rule fixed")
    assert f"cap-rule pixels would allow {scene_cap(mpx, cfg.mcmc)[0]:,} for these" in fixed["reasons"]["capacity"]
    assert "capacity (MCMC's cap, rule fixed; where MCMC densifies" in format_summary(fixed)

    ruled = willags_model_config()
    ruled.mcmc.cap_rule = "pixels"
    ruled.mcmc.cap_min = 1000
    s = apply_auto_config(ruled, scenes["appearance"])
    want, _ = scene_cap(mpx, ruled.mcmc)
    assert ruled.mcmc.cap_max == want == round(12_500 * mpx / 1000) * 1000
    assert s["settings"]["mcmc.cap_max"] == want and "Mpx of training photos" in s["reasons"]["capacity"]
    assert "capacity (MCMC's cap, rule pixels; " in format_summary(s)

    mine = willags_model_config()
    mine.mcmc.cap_rule, mine.mcmc.cap_max = "pixels", 123_000
    s = apply_auto_config(mine, scenes["appearance"], keep=("mcmc.cap_max",))
    assert mine.mcmc.cap_max == 123_000 and s["reasons"]["capacity"].endswith("kept as you set it")

    trained = willags_model_config()  # the transients rule decides while training: the cap starts as set
    trained.mcmc.cap_rule = "transients"
    t = apply_auto_config(trained, scenes["appearance"])
    assert trained.mcmc.cap_max == McmcConfig().cap_max and "mcmc.cap_max" not in t["changes"]
    assert "until MCMC fills them (rule transients)" in t["reasons"]["capacity"]
    assert "capacity (MCMC's cap, rule transients; " in format_summary(t)


def test_scene_cap_scales_with_megapixels_within_its_bounds():
    from willags_ns.splats.mcmc import McmcConfig, scene_cap

    cfg = McmcConfig(gaussians_per_megapixel=10_000, cap_min=50_000, cap_ceiling=1_000_000)
    assert scene_cap(20.0, cfg)[0] == 200_000
    assert scene_cap(40.0, cfg)[0] == 2 * scene_cap(20.0, cfg)[0]
    assert scene_cap(1.0, cfg)[0] == 50_000 and "within [50,000, 1,000,000]" in scene_cap(1.0, cfg)[1]
    assert scene_cap(500.0, cfg)[0] == 1_000_000
    with pytest.raises(ValueError, match="megapixels"):
        scene_cap(float("nan"), cfg)
