"""The image cache of willags' datamanager (willags_ns/data/datamanager.py): collections of over 500 training photos
train on a CPU, whose cache nerfstudio would pin (which needs CUDA)."""

from pathlib import Path

import pytest
import torch

from tests._scenes import small_scene

MANY = 501
"""Past nerfstudio's 500-image bound, where it moves the image cache to pinned host memory."""


@pytest.fixture(scope="module")
def many_photos(tmp_path_factory) -> Path:
    """MANY training photos of 32x24 px (and 2 test photos): a collection past the bound that caches in no time."""
    return small_scene(
        tmp_path_factory.mktemp("many") / "scene", 0.5, 0.0, num_train=MANY, width=32, height=24, num_points=400
    )


def _cpu_config(tmp_path: Path, data: Path, steps: int):
    from willags_ns.method_configs import willags_config

    config = willags_config()
    config.machine.device_type = "cpu"
    config.pipeline.datamanager.data = data
    config.max_num_iterations = config.steps_per_save = steps
    config.vis = "tensorboard"
    config.output_dir, config.experiment_name, config.timestamp = tmp_path, "many", "t"
    config.pipeline.model.num_downscales = 0
    config.set_timestamp()
    config.save_config()
    return config


@pytest.mark.slow
def test_over_500_training_photos_train_on_the_cpu(tmp_path, many_photos):
    from tests.test_train import train_recording

    trainer, losses = train_recording(_cpu_config(tmp_path, many_photos, steps=2))
    assert len(losses) == 2 and all(torch.isfinite(torch.tensor(v)) for v, _ in losses)
    dm = trainer.pipeline.datamanager
    assert len(dm.train_dataset) == MANY
    image = dm.cached_train[0]["image"]
    assert image.device.type == "cpu" and image.dtype == torch.uint8  # a quarter of float32's memory
    if torch.cuda.is_available():  # without CUDA, asking whether memory is pinned raises itself
        assert not image.is_pinned()  # page-locked memory buys nothing when training on the CPU


def test_nerfstudios_own_datamanager_config_caches_past_500_photos_on_the_cpu(many_photos):
    """A config.yml that names nerfstudio's FullImageDatamanagerConfig (what the method configs held before) is built
    as willags' datamanager by the pipeline: a run trained on a GPU loads on a CPU."""
    from nerfstudio.data.datamanagers.full_images_datamanager import FullImageDatamanagerConfig

    from willags_ns.data.datamanager import WillagsDatamanager, use_willags_datamanager
    from willags_ns.data.dataparser import WillagsDataParserConfig

    config = FullImageDatamanagerConfig(dataparser=WillagsDataParserConfig(data=many_photos), cache_images_type="uint8")
    use_willags_datamanager(config)
    dm = config.setup(device="cpu")
    assert isinstance(dm, WillagsDatamanager)
    assert dm.config.cache_images == "cpu"  # nerfstudio's bound moved the cache to the host ...
    camera, batch = dm.next_train(0)  # ... where it caches without pinning
    assert batch["image"].shape == (24, 32, 3) and batch["image"].dtype == torch.uint8
    assert len(dm.cached_train) == MANY


def test_only_a_cuda_device_pins_the_host_cache():
    from willags_ns.data.datamanager import pins_memory

    assert not pins_memory("cpu") and not pins_memory(torch.device("cpu"))
    assert pins_memory("cuda:0") == torch.cuda.is_available()
