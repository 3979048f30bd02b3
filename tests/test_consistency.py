"""willags_ns/data/consistency.py: the colour-fit test of a photo against the SfM points it should show."""

import numpy as np

from willags_ns.data.consistency import colour_fit_r2


def _observations(n_img=6, n_pts=400, seed=0):
    """Point colours seen by every image through its own affine colour transform, plus a little noise."""
    rng = np.random.default_rng(seed)
    ref = rng.random((n_pts, 3)).astype(np.float32)
    obs = []
    for _ in range(n_img):
        A = np.eye(3) * rng.uniform(0.4, 1.2) + 0.05 * rng.standard_normal((3, 3))
        obs.append(ref @ A.T + rng.uniform(-0.2, 0.2, 3) + 0.02 * rng.standard_normal((n_pts, 3)))
    return np.stack(obs).astype(np.float32)


def test_a_photo_of_another_place_has_no_colour_fit_and_real_ones_do():
    obs = _observations()
    obs[2] = np.random.default_rng(9).random(obs[2].shape)  # unrelated colours at the projections
    obs[4, :150] = np.nan  # partly unseen: still judged on the rest
    r2 = colour_fit_r2(obs)
    assert r2[2] < 0.05
    assert all(r2[i] > 0.9 for i in (0, 1, 3, 4, 5)), r2


def test_flat_or_barely_seen_images_are_not_judged():
    obs = _observations()
    obs[1] = 0.0  # an all-black photo: nothing to judge
    obs[3, 20:] = np.nan  # 20 points seen: too few
    r2 = colour_fit_r2(obs)
    assert np.isnan(r2[1]) and np.isnan(r2[3]) and np.isfinite(r2[0])
