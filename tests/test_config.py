"""The model's settings (willags_ns/config.py): the defaults are the method `willags`, fields that moved into a group
say where, config.yml files of the flat layout load into the groups, splatfacto's knobs that do nothing here are
refused, and building the model leaves its config as it was."""

import copy
import dataclasses
from pathlib import Path

import pytest
import yaml

from willags_ns import method_configs as mc
from willags_ns.config import INERT_KNOBS, RENAMED, WillagsModelConfig, check_settings

FLAT_LAYOUT = Path(__file__).parent / "data" / "model_config_flat_layout.yml"
"""`willags` and `willags-paper` model configs as config.yml stored them with use_vae, use_mask, mask_every,
max_masked_fraction, fuse_teacher_render, teacher, static_support, mask_health, vae.latent_dim and lambda_vae at the
top level."""


def test_the_dataclass_defaults_are_the_method_willags():
    assert WillagsModelConfig() == mc.willags_config().pipeline.model
    assert mc.willags_model_config() == dataclasses.replace(WillagsModelConfig(), auto_config=False)


def test_a_config_yml_of_the_flat_layout_loads_into_the_groups():
    old = yaml.load(FLAT_LAYOUT.read_text(), Loader=yaml.Loader)
    # a file written before the densification setting trained with splatfacto's, and loads with it; one written
    # before the mask's start rule started its mask at its warm-up's end (500 then), and loads so
    assert all(cfg.densification == "splatfacto" for cfg in old.values())
    assert all(cfg.mask.start_rule == "always" for cfg in old.values())
    now = mc.willags_config().pipeline.model
    early = dataclasses.replace(now.mask, warmup_steps=500, start_rule="always")
    assert old["willags"] == dataclasses.replace(now, densification="splatfacto", mask=early)
    paper_now = mc.willags_paper_config().pipeline.model
    assert not paper_now.sky.enabled  # the file's sky region ("everywhere", its default then) does nothing here
    assert old["willags-paper"] == dataclasses.replace(
        paper_now, sky=dataclasses.replace(paper_now.sky, region="everywhere")
    )
    paper = old["willags-paper"]
    assert paper.latent.kind == "vae" and paper.latent.dim == 64 and paper.mask.every == 1
    assert paper.mask.teacher.fused and not paper.mask.safeguard.enabled
    for cfg in old.values():  # no stray attribute of the flat layout survives
        assert not {"use_vae", "use_mask", "teacher", "static_support"} & set(vars(cfg))
        assert "latent_dim" not in vars(cfg.triplane) and "dynamic_dim" not in vars(cfg.decoder)
    # and what today's config.yml stores loads as itself, the default's start rule too
    again = yaml.load(yaml.dump(old["willags-paper"]), Loader=yaml.Loader)
    assert again == old["willags-paper"]
    again = yaml.load(yaml.dump(now), Loader=yaml.Loader)
    assert again == now and again.mask.start_rule == "transients"


@pytest.mark.parametrize("old,new", [(o, n) for o, n in RENAMED if "." not in o])
def test_a_moved_field_names_its_new_place(old, new):
    cfg = WillagsModelConfig()
    flag = "--pipeline.model." + new.replace("_", "-")
    with pytest.raises(AttributeError, match=flag.replace(".", r"\.")):
        getattr(cfg, old)
    with pytest.raises(AttributeError, match=new.replace(".", r"\.")):
        setattr(cfg, old, None)


@pytest.mark.parametrize("knob,value", [("n_split_samples", 3), ("use_bilateral_grid", True), ("prompt", "a fox")])
def test_splatfacto_knobs_that_do_nothing_here_are_refused(knob, value):
    assert knob in INERT_KNOBS
    flag = "--pipeline.model." + knob.replace("_", "-")
    with pytest.raises(ValueError, match=flag):
        WillagsModelConfig(**{knob: value})
    cfg = WillagsModelConfig()
    setattr(cfg, knob, value)  # a later edit is refused when the model is built (populate_modules runs this)
    with pytest.raises(ValueError, match=flag):
        check_settings(cfg)


def test_the_expected_residual_without_the_residual_distance_is_refused_by_name():
    """mask.residual.expected is the colour residual's level: with the VGG distance nothing would learn or use it, so
    the config says which switch it needs instead of training without it."""
    from willags_ns.mask.residual import ResidualConfig
    from willags_ns.mask.rule import MaskConfig

    with pytest.raises(
        ValueError, match=r"mask\.residual\.expected True needs --pipeline\.model\.mask\.distance residual"
    ):
        WillagsModelConfig(mask=MaskConfig(residual=ResidualConfig(expected=True)))
    cfg = WillagsModelConfig(mask=MaskConfig(distance="residual", residual=ResidualConfig(expected=True)))
    cfg.mask.distance = "vgg"  # a later edit is refused when the model is built
    with pytest.raises(ValueError, match="'vgg'"):
        check_settings(cfg)


def test_building_the_model_leaves_its_config_as_it_was():
    """A sky above the skyline on a scene without keypoints is not built, and the config still says what was asked
    (config.yml is what trains)."""
    from tests._configs import all_components
    from tests.test_mask_eval import _tiny_model
    from willags_ns.appearance.sky import SkyConfig

    sky = SkyConfig(enabled=True, region="open")
    before = WillagsModelConfig(**all_components(sky=sky))
    model = _tiny_model(use_vae=True, sky=copy.deepcopy(sky))
    assert model.appearance_nets.sky is None
    assert model.config.sky == before.sky and model.config.latent.dim == 8  # read, never written


def test_presets_set_only_fields_that_act():
    """willags-3dgs (appearance "sh": no latent, mask, sky or f_s) differs from the defaults only where it acts;
    willags-lite builds no tri-plane field, so it sets none of the field's settings."""
    from willags_ns.appearance.sky import SkyConfig
    from willags_ns.appearance.triplane import TriplaneConfig

    default = vars(WillagsModelConfig())
    plain = vars(mc.willags_3dgs_config().pipeline.model)
    diff = {k for k in default if default[k] != plain[k]}
    assert diff == {"appearance", "rasterize_mode", "densification", "auto_config"}
    assert plain["densification"] == "splatfacto"
    lite = mc.willags_lite_config().pipeline.model
    assert not lite.use_field and lite.triplane == TriplaneConfig() and lite.sky == SkyConfig(enabled=False)
