import pytest
import torch

from willags_ns.appearance.triplane import (
    MIN_EXTENT,
    TriplaneConfig,
    TriplaneHyperField,
    normalize_points,
    robust_bounds,
)


def _small_field(**kw):
    args: dict = dict(latent_dim=8, resolution=8, channels=4, hyper_hidden=(16, 4), feature_dim=6, mlp_hidden=16)
    args.update(kw)
    return TriplaneHyperField(**args)


def test_robust_bounds_quantiles_and_margin():
    x = torch.linspace(0, 10, 10001)
    pts = torch.stack([x, 2 * x, -x], dim=-1)
    lo, hi = robust_bounds(pts, quantile=0.02, margin=0.1)
    # x: [0.2, 9.8] -> extent 9.6 -> [-0.76, 10.76]
    torch.testing.assert_close(lo, torch.tensor([-0.76, -1.52, -10.76]), atol=1e-3, rtol=0)
    torch.testing.assert_close(hi, torch.tensor([10.76, 21.52, 0.76]), atol=1e-3, rtol=0)


def test_robust_bounds_ignore_outliers_and_nonfinite():
    g = torch.Generator().manual_seed(0)
    pts = torch.rand(1000, 3, generator=g)
    pts[:5] = 1e6  # 0.5% far-away outliers (stray SfM points)
    pts[5] = float("nan")
    lo, hi = robust_bounds(pts)
    assert torch.isfinite(lo).all() and torch.isfinite(hi).all()
    assert (hi < 2.0).all() and (lo > -1.0).all()


def test_normalize_clamps_outside_points():
    lo, hi = torch.zeros(3), torch.ones(3)
    pts = torch.tensor([[0.5, 0.5, 0.5], [0.0, 1.0, 0.25], [-5.0, 3.0, 0.5], [100.0, -100.0, 2.0]])
    n = normalize_points(pts, lo, hi)
    torch.testing.assert_close(n[0], torch.zeros(3))
    torch.testing.assert_close(n[1], torch.tensor([-1.0, 1.0, -0.5]))
    torch.testing.assert_close(n[2], torch.tensor([-1.0, 1.0, 0.0]))
    torch.testing.assert_close(n[3], torch.tensor([1.0, -1.0, 1.0]))


def test_degenerate_bounds_no_nan():
    pts = torch.tensor([[1.0, 2.0, 3.0]]).repeat(50, 1)  # all identical
    pts[:, 0] = torch.linspace(-1, 1, 50)  # x varies, y and z degenerate
    lo, hi = robust_bounds(pts)
    extent = hi - lo
    assert extent[0] > 2.0 and torch.allclose(extent[1:], 0.01 * extent[0].expand(2))
    torch.testing.assert_close((lo + hi)[1:] / 2, torch.tensor([2.0, 3.0]))
    n = normalize_points(pts, lo, hi)
    assert torch.isfinite(n).all()
    torch.testing.assert_close(n[:, 1:], torch.zeros(50, 2), atol=1e-3, rtol=0)
    # explicit zero-extent bounds passed in: still finite
    n = normalize_points(pts, torch.zeros(3), torch.zeros(3))
    assert torch.isfinite(n).all()
    lo, hi = robust_bounds(torch.empty(0, 3))
    assert torch.isfinite(lo).all() and (hi > lo).all()
    lo, hi = robust_bounds(torch.ones(10, 3))  # a single point: every axis degenerate
    assert ((hi - lo) >= MIN_EXTENT * 0.99).all()
    assert torch.isfinite(normalize_points(torch.ones(10, 3), lo, hi)).all()


def test_shapes_and_defaults():
    cfg = TriplaneConfig()
    field = TriplaneHyperField(64, cfg.resolution, cfg.channels, cfg.hyper_hidden, cfg.feature_dim, cfg.mlp_hidden)
    z = torch.randn(64)
    planes = field.planes(z)
    assert planes.shape == (3, 32, 64, 64)
    # planes ~ unit variance at init; z only modulates them slightly
    assert 0.8 < planes.std().item() < 1.2
    delta = planes - field.mean_planes
    assert delta.abs().max().item() < 0.1
    f = field(z, torch.rand(100, 3) * 2 - 1)
    assert f.shape == (100, 32)
    # f_d starts near a constant
    assert f.std(0).max().item() < 0.05
    # no dense 100M-param layer
    n_params = sum(p.numel() for p in field.parameters())
    assert n_params < 14_000_000
    assert field(z, torch.zeros(0, 3)).shape == (0, 32)
    assert field.planes(z[None]).shape == (3, 32, 64, 64)
    with pytest.raises(ValueError):
        field.planes(torch.randn(63))


def test_query_matches_plane_values_at_texel_centres():
    field = _small_field()
    planes = torch.randn(3, 4, 8, 8)
    # corner (-1, -1, -1) -> texel (0, 0) of every plane; (+1, -1, -1) -> XY: x=+1 -> col 7, XZ: col 7, YZ: col 0
    calls = []
    field.mlp = torch.nn.Sequential(torch.nn.Identity())
    field.mlp.register_forward_hook(lambda m, i, o: calls.append(i[0]))
    field.query(planes, torch.tensor([[-1.0, -1.0, -1.0], [1.0, -1.0, -1.0]]))
    feats = calls[0].view(2, 3, 4)
    torch.testing.assert_close(feats[0], planes[:, :, 0, 0])
    torch.testing.assert_close(feats[1, 0], planes[0, :, 0, 7])
    torch.testing.assert_close(feats[1, 1], planes[1, :, 0, 7])
    torch.testing.assert_close(feats[1, 2], planes[2, :, 0, 0])


def test_gradients_reach_z_hypernetwork_and_points():
    torch.manual_seed(0)
    field = _small_field()
    z = torch.randn(8, requires_grad=True)
    means = (torch.rand(32, 3) * 4 - 2).requires_grad_(True)
    lo, hi = torch.full((3,), -3.0), torch.full((3,), 3.0)
    f = field(z, normalize_points(means, lo, hi))
    (f**2).sum().backward()
    assert z.grad is not None and z.grad.abs().sum() > 0
    assert means.grad is not None and means.grad.abs().sum() > 0
    for name, p in field.named_parameters():
        assert p.grad is not None and p.grad.abs().sum() > 0, name


def test_different_latents_give_different_features_after_training_signal():
    # the basis is small at init but not zero: two latents give (slightly) different planes
    field = _small_field()
    a = field.planes(torch.randn(8))
    b = field.planes(torch.randn(8))
    assert not torch.allclose(a, b)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA GPU")
def test_cuda_matches_cpu():
    torch.manual_seed(0)
    field = _small_field()
    z = torch.randn(8)
    pts = torch.rand(64, 3) * 6 - 3
    lo, hi = robust_bounds(pts)
    ref = field(z, normalize_points(pts, lo, hi))
    field_c = field.cuda()
    lo_c, hi_c = robust_bounds(pts.cuda())
    assert lo_c.is_cuda
    out = field_c(z.cuda(), normalize_points(pts.cuda(), lo_c, hi_c))
    torch.testing.assert_close(out.cpu(), ref, atol=1e-5, rtol=1e-4)
