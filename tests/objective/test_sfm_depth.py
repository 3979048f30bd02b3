"""objective/sfm_depth.py: the render's expected depth held to the depths of the photo's SfM points."""

import math

import pytest
import torch

from willags_ns.objective.sfm_depth import SfmDepthConfig, sample_at, select_observations, sfm_depth_loss


def _centre(i: int, size: int) -> float:
    return (i + 0.5) / size


def test_samples_at_pixel_centres_are_the_pixels_and_between_them_are_blends():
    img = torch.arange(12.0).reshape(3, 4, 1)  # H 3, W 4
    uv = torch.tensor([[_centre(0, 4), _centre(0, 3)], [_centre(3, 4), _centre(2, 3)], [_centre(1, 4), _centre(1, 3)]])
    assert torch.allclose(sample_at(img, uv)[:, 0], torch.tensor([0.0, 11.0, 5.0]), atol=1e-5)
    mid = torch.tensor([[(_centre(1, 4) + _centre(2, 4)) / 2, _centre(1, 3)]])
    assert torch.allclose(sample_at(img, mid)[:, 0], torch.tensor([5.5]))


def test_only_points_inside_the_photo_matched_often_enough_with_a_known_positive_depth_are_kept():
    obs = torch.tensor(
        [
            [0.5, 0.5, 3.0],  # kept
            [0.5, 0.5, 2.0],  # a two-photo track
            [1.2, 0.5, 5.0],  # outside
            [0.2, 0.7, 4.0],  # unknown depth
            [0.2, 0.7, 4.0],  # behind the camera
            [0.1, 0.1, 9.0],  # kept
        ]
    )
    target = torch.tensor([2.0, 2.0, 2.0, float("nan"), -1.0, 5.0])
    uv, t = select_observations(obs, target, SfmDepthConfig(weight=1.0, min_track=3))
    assert torch.equal(t, torch.tensor([2.0, 5.0])) and torch.equal(uv, obs[[0, 5], :2])


def test_the_loss_is_the_mean_absolute_log_ratio_where_the_render_is_opaque():
    cfg = SfmDepthConfig(weight=1.0, min_alpha=0.5)
    depth = torch.full((4, 4, 1), 2.0)
    alpha = torch.ones(4, 4, 1)
    uv = torch.tensor([[_centre(1, 4), _centre(1, 4)], [_centre(2, 4), _centre(3, 4)]])
    loss, used = sfm_depth_loss(depth, alpha, uv, torch.tensor([2.0, 2.0]), cfg)
    assert float(loss) == 0.0 and int(used) == 2
    loss, _ = sfm_depth_loss(depth, alpha, uv, torch.tensor([2.0 * math.e, 2.0 / math.e]), cfg)
    assert math.isclose(float(loss), 1.0, rel_tol=1e-5)  # a factor e either way costs 1
    alpha[1, 1] = 0.2  # the first point's pixel is too transparent: only the second counts
    loss, used = sfm_depth_loss(depth, alpha, uv, torch.tensor([20.0, 2.0 * math.e]), cfg)
    assert int(used) == 1 and math.isclose(float(loss), 1.0, rel_tol=1e-5)
    loss, used = sfm_depth_loss(depth, torch.zeros(4, 4, 1), uv, torch.tensor([2.0, 2.0]), cfg)
    assert int(used) == 0 and float(loss) == 0.0 and torch.isfinite(loss)


def test_descending_the_loss_moves_the_rendered_depth_to_the_points_and_leaves_alpha_alone():
    cfg = SfmDepthConfig(weight=1.0)
    depth = torch.full((6, 6, 1), 1.0, requires_grad=True)
    alpha = torch.full((6, 6, 1), 0.9, requires_grad=True)
    uv = torch.tensor([[_centre(2, 6), _centre(3, 6)]])
    opt = torch.optim.Adam([depth], lr=0.05)
    for _ in range(200):
        opt.zero_grad()
        loss, _ = sfm_depth_loss(depth, alpha, uv, torch.tensor([3.0]), cfg)
        loss.backward()
        opt.step()
    assert abs(float(depth[3, 2, 0]) - 3.0) < 0.1
    assert alpha.grad is None or float(alpha.grad.abs().sum()) == 0.0


@pytest.mark.parametrize(
    "field, value, shown",
    [("weight", -0.1, "weight -0.1"), ("weight", float("nan"), "weight nan"), ("min_track", 1, "min-track 1"),
     ("min_alpha", 1.0, "min-alpha 1.0")],
)  # fmt: skip
def test_a_bad_sfm_depth_setting_is_refused_naming_it(field, value, shown):
    from willags_ns.config import WillagsModelConfig

    with pytest.raises(ValueError, match=rf"sfm-depth\.\*.*{shown}"):
        WillagsModelConfig(sfm_depth=SfmDepthConfig(**{field: value}))
