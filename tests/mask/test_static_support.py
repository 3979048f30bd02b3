"""The mask's safeguard (willags_ns/mask/static_support.py), the SfM observations it reads (willags_ns/data/sfm_tracks.py)
and the model's use of it: what long SfM tracks vouch for is never masked."""

import numpy as np
import pytest
import torch

from willags_ns.data.sfm_tracks import SFM_OBSERVATIONS_KEY, grid_shape, train_observations
from willags_ns.mask.static_support import (
    StaticSupportConfig,
    apply_support,
    masked_share,
    observations_masked,
    support_map,
)


def _cluster(u, v, n, track, spread=0.005, seed=0):
    rng = np.random.default_rng(seed)
    uv = np.stack([u + spread * rng.standard_normal(n), v + spread * rng.standard_normal(n)], 1)
    return np.concatenate([uv, np.full((n, 1), track)], 1).astype(np.float32)


def test_grid_follows_the_image_aspect():
    assert grid_shape(800, 600, 64) == (48, 64)
    assert grid_shape(600, 800, 64) == (64, 48)
    assert grid_shape(1000, 1, 64) == (1, 64)


def test_a_cluster_of_long_tracks_is_supported_and_an_isolated_keypoint_is_not():
    cfg = StaticSupportConfig(grid=32, min_track=5, min_observations=3, radius_cells=1)
    obs = np.concatenate([_cluster(0.25, 0.25, 20, 7), _cluster(0.8, 0.8, 1, 9, spread=0.0)])
    sup = support_map(obs, 320, 320, cfg)
    assert sup.shape == (32, 32)
    assert sup[8, 8]  # the cluster's cell
    assert not sup[25, 25]  # one keypoint alone does not unmask an occluder
    assert not sup[16, 16] and not sup[0, 31]
    # the support stays local: a few cells around the cluster, not the image
    assert 1 <= int(sup.sum()) <= 25


def test_short_tracks_vouch_for_nothing():
    cfg = StaticSupportConfig(grid=32, min_track=5)
    assert not support_map(_cluster(0.5, 0.5, 50, 4), 320, 320, cfg).any()
    assert support_map(_cluster(0.5, 0.5, 50, 5), 320, 320, cfg).any()
    assert not support_map(np.zeros((0, 3), np.float32), 320, 240, cfg).any()


def test_observations_outside_the_image_are_ignored():
    cfg = StaticSupportConfig(grid=16, min_observations=1, radius_cells=0)
    obs = np.array([[1.5, 0.5, 9], [-0.1, 0.5, 9], [0.5, 1.0, 9]], np.float32)
    assert not support_map(obs, 160, 160, cfg).any()


def test_supported_pixels_stay_in_the_loss_at_any_resolution():
    cfg = StaticSupportConfig(grid=32)
    sup = support_map(_cluster(0.25, 0.25, 30, 8), 320, 240, cfg)
    for h, w in ((240, 320), (60, 80), (480, 640)):
        static = torch.zeros(h, w, dtype=torch.bool)  # the perceptual mask flags everything
        out = apply_support(static, sup)
        assert out[int(0.25 * h), int(0.25 * w)]
        assert not out[int(0.75 * h), int(0.75 * w)]
    static = torch.rand(60, 80) > 0.5
    assert torch.equal(apply_support(static, None), static)
    assert torch.equal(apply_support(torch.ones(60, 80, dtype=torch.bool), sup), torch.ones(60, 80, dtype=torch.bool))


def test_observations_masked_counts_long_tracks_under_the_mask():
    static = torch.ones(100, 200, dtype=torch.bool)
    static[:, 100:] = False  # right half masked
    obs = np.array([[0.25, 0.5, 6], [0.75, 0.5, 6], [0.75, 0.2, 2], [0.9, 0.9, 5]], np.float32)
    assert observations_masked(static, obs, 5) == (2, 3)
    assert observations_masked(static, obs, 7) == (0, 0)
    assert masked_share([(2, 3), (0, 1)]) == 0.5
    assert masked_share([(0, 0)]) is None


def test_track_length_counts_training_images_only():
    obs = {
        "a.jpg": (np.array([[10.0, 20.0], [30.0, 40.0]]), np.array([1, 2]), (100, 50)),
        "b.jpg": (np.array([[50.0, 25.0]]), np.array([1]), (100, 50)),
        "test.jpg": (np.array([[5.0, 5.0], [6.0, 6.0]]), np.array([1, 2]), (100, 50)),
    }
    a, b, missing = train_observations(obs, ["a.jpg", "b.jpg", "gone.jpg"])
    np.testing.assert_allclose(a, [[0.1, 0.4, 2], [0.3, 0.8, 1]])  # point 2 is seen by the test photo only besides a
    np.testing.assert_allclose(b, [[0.5, 0.5, 2]])
    assert missing.shape == (0, 3)


def test_the_model_keeps_supported_pixels_its_perceptual_mask_flags():
    from tests.test_model import _tiny_model

    model = _tiny_model()
    model.config.mask.safeguard.enabled = True
    model.train()
    h, w = 32, 48
    model.sfm_observations = [_cluster(0.25, 0.3, 40, 9), np.zeros((0, 3), np.float32)]
    gt = torch.rand(h, w, 3)
    for idx in (0, 1):
        model.last_masks[idx] = torch.zeros(h, w, dtype=torch.bool)  # the perceptual mask: all transient
        mask = model.step_static_mask({"image_idx": idx}, gt).mask
        assert mask is not None
        if idx == 0:
            assert mask[int(0.3 * h), int(0.25 * w)] == 1.0
            assert mask[int(0.8 * h), int(0.8 * w)] == 0.0
        else:  # no tracks in this image: the perceptual mask alone
            assert mask.sum() == 0
    model.config.mask.safeguard.enabled = False
    model.mask_step.support_cache.clear()
    assert model.step_static_mask({"image_idx": 0}, gt).mask.sum() == 0


def test_colmap_scenes_carry_their_training_observations(shared_data):
    from willags_ns.data.dataparser import WillagsDataParserConfig

    parser = WillagsDataParserConfig(data=shared_data / "sacre-coeur-mini").setup()
    train = parser.get_dataparser_outputs("train")
    obs = train.metadata[SFM_OBSERVATIONS_KEY]
    assert len(obs) == len(train.image_filenames)
    allobs = np.concatenate(obs)
    assert len(allobs) > 1000
    assert (allobs[:, :2] >= 0).all() and (allobs[:, :2] <= 1).all()
    assert allobs[:, 2].min() >= 1 and allobs[:, 2].max() <= len(train.image_filenames)
    assert SFM_OBSERVATIONS_KEY not in parser.get_dataparser_outputs("test").metadata


@pytest.mark.parametrize("scene", ["fox-wild"])
def test_transforms_scenes_have_no_tracks(shared_data, scene):
    from willags_ns.data.dataparser import WillagsDataParserConfig

    train = WillagsDataParserConfig(data=shared_data / scene).setup().get_dataparser_outputs("train")
    assert SFM_OBSERVATIONS_KEY not in train.metadata


def test_open_background_is_what_hangs_above_the_skyline():
    from willags_ns.data.sfm_tracks import open_background_map

    rng = np.random.default_rng(0)
    # a "building" of keypoints filling rows 0.4-0.7 of the image across its width, nothing below or above
    uv = np.stack([rng.uniform(0, 1, 3000), rng.uniform(0.4, 0.7, 3000)], 1)
    obs = np.concatenate([uv, np.full((3000, 1), 6.0)], 1).astype(np.float32)
    m = open_background_map(obs, 320, 320, grid=32)
    assert m.shape == (32, 32)
    assert m[:11].all()  # above the building (rows < 0.4 * 32, less the one-cell dilation)
    assert not m[13:].any()  # the building and the plaza under it (no points there either) are not open
    # a column without keypoints takes the others' skyline, not the whole column
    obs2 = obs[(obs[:, 0] < 0.45) | (obs[:, 0] > 0.55)]
    m2 = open_background_map(obs2, 320, 320, grid=32)
    assert m2[:11, 16].all() and not m2[13:, 16].any()
    assert not open_background_map(np.zeros((0, 3), np.float32), 320, 240).any()
