"""willags_ns/engine/compat.py: the shims between nerfstudio 1.1.5 and current torch keep nerfstudio's behaviour."""

import inspect

import pytest

pytest.importorskip("nerfstudio")

from nerfstudio.configs import external_methods  # noqa: E402

from willags_ns.engine.compat import quick_external_method_check  # noqa: E402


def test_external_methods_listed_without_reading_the_stack(monkeypatch):
    quick_external_method_check()
    quick_external_method_check()  # applied once: a second call does not wrap the wrapper

    def no_stack(*args, **kwargs):
        raise AssertionError("inspect.stack() called while nerfstudio lists its external methods")

    monkeypatch.setattr(inspect, "stack", no_stack)
    configs, descriptions = external_methods.get_external_methods()
    assert len(configs) > 10 and set(configs) == set(descriptions)
    assert all(isinstance(c, external_methods.ExternalMethodDummyTrainerConfig) for c in configs.values())


def test_external_method_built_elsewhere_still_offers_its_install(monkeypatch):
    """A dummy built outside get_external_methods (the CLI picked a method that is not installed) goes through
    nerfstudio's own __post_init__: it prints the instructions, asks whether to install, and exits."""
    quick_external_method_check()
    asked = []
    monkeypatch.setattr(external_methods.Confirm, "ask", lambda *a, **k: asked.append(a) or False)
    method = external_methods.external_methods[0]
    with pytest.raises(SystemExit) as stop:
        external_methods.ExternalMethodDummyTrainerConfig(method_name="x", method=method)
    assert stop.value.code == 0
    assert asked or not method.pip_package


def test_a_config_yml_naming_the_modules_before_the_rooms_loads_as_today():
    import yaml

    from willags_ns import method_configs as mc
    from willags_ns.engine.compat import CONFIG_YML_CLASSES

    config = mc.willags_config()
    text = yaml.dump(config)
    older = text
    for old, new in CONFIG_YML_CLASSES.items():
        if old.rpartition(".")[2] == new.rpartition(".")[2]:
            older = older.replace(f":{new}", f":{old}")
    assert "willags_ns.trainer.WillagsTrainerConfig" in older and "willags_ns.pipeline.WillagsPipeline ''" in older
    assert "willags_ns.transient.MaskConfig" in older and "willags_ns.engine." not in older
    assert "willags_ns.model.WillagsModelConfig" in older  # the model's settings were declared in model.py
    loaded = yaml.load(older, Loader=yaml.Loader)
    assert type(loaded) is type(config) and loaded == config


def test_a_config_yml_naming_the_mask_settings_in_transient_loads_them_from_the_rule():
    import yaml

    from willags_ns import method_configs as mc
    from willags_ns.mask.rule import MaskConfig

    config = mc.willags_config()
    text = yaml.dump(config)
    assert "!!python/object:willags_ns.mask.rule.MaskConfig" in text
    loaded = yaml.load(text.replace("mask.rule.MaskConfig", "mask.transient.MaskConfig"), Loader=yaml.Loader)
    assert type(loaded.pipeline.model.mask) is MaskConfig and loaded == config


def test_an_unknown_module_in_a_config_yml_still_fails():
    import yaml

    with pytest.raises(yaml.constructor.ConstructorError, match="willags_ns.nowhere"):
        yaml.load("!!python/object:willags_ns.nowhere.Config {}", Loader=yaml.Loader)


def test_willags_own_warnings_print_as_one_line_and_library_noise_is_hidden():
    import warnings

    import willags_ns  # noqa: F401 - installs both

    own = warnings.formatwarning("willags: the weights are missing; run this", RuntimeWarning, "/x/t.py", 3, "code")
    assert own == "willags: the weights are missing; run this\n"
    other = warnings.formatwarning("something else", UserWarning, "/x/t.py", 3, "code")
    assert "/x/t.py:3" in other  # everything else keeps Python's format
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("default")
        from willags_ns.engine.compat import silence_library_noise

        silence_library_noise()
        warnings.warn("`torch.cuda.amp.GradScaler(args...)` is deprecated. Please use x", FutureWarning, stacklevel=2)
        copy = "To copy construct from a tensor, it is recommended to use sourceTensor.detach().clone() or x"
        warnings.warn(copy, UserWarning, stacklevel=2)  # nerfstudio's interpolated camera path (willags-render)
        warnings.warn("a warning a user can act on", FutureWarning, stacklevel=2)
    assert [str(w.message) for w in caught] == ["a warning a user can act on"]
