"""Shared fixtures: the device under test, the ../shared data (skipped when absent), a scratch cache."""

import os
from pathlib import Path

import pytest
import torch

REPO = Path(__file__).resolve().parents[1]
SHARED_DATA = REPO.parent / "shared" / "data"

# keep the suite's generated scenes away from the user's cache, and quiet
os.environ.setdefault("WILLAGS_CACHE", str(REPO / ".pytest_cache" / "willags-scenes"))
torch.set_num_threads(max(1, min(2, os.cpu_count() or 1)))


@pytest.fixture(params=["cpu"] + (["cuda"] if torch.cuda.is_available() else []))
def device(request) -> torch.device:
    return torch.device(request.param)


@pytest.fixture
def shared_data() -> Path:
    if not SHARED_DATA.is_dir():
        pytest.skip(f"{SHARED_DATA} is absent (the benchmark scenes live in ../shared/data)")
    return SHARED_DATA


cuda = pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA GPU")


@pytest.fixture(scope="session")
def appearance_run(tmp_path_factory):
    """A 6-step willags run (through nerfstudio's trainer) whose colours depend on the latent (at 6 steps the colour
    transform is still ~the identity): (config.yml, training image names, indices of encoded training images)."""
    from tests.test_train import _look_trained, _train

    tmp = tmp_path_factory.mktemp("appearance_run")
    config, trainer, _ = _train(tmp, "willags", steps=6)
    model = trainer.pipeline.model
    _look_trained(trainer)  # a latent-dependent colour transform, as after training; saves the checkpoint
    seen = model.image_latents()[1].nonzero().flatten().tolist()  # the training images with a known latent
    assert len(seen) >= 2, "the fixture needs two encoded training images"
    return config.get_base_dir() / "config.yml", list(model.image_names), seen
