"""Property test of the torch rasteriser (docs/reliability.md): over random Gaussians, cameras and image sizes, the
render is finite, alpha stays in [0, 1] and every gradient is finite. Extremes are drawn on purpose: Gaussians
behind the camera, at the near plane, tiny (1e-4) and huge (1e2) scales, needle-thin anisotropy, opacities 0 and
1, unnormalised quaternions, 1-pixel images, focal lengths from 1 to 1e4 px."""

import math

import pytest
import torch
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from willags_ns.render import rasterize

_floats = dict(allow_nan=False, allow_infinity=False, width=32)


@st.composite
def scenes(draw):
    n = draw(st.integers(0, 24))
    w = draw(st.integers(1, 40))
    h = draw(st.integers(1, 40))
    seed = draw(st.integers(0, 2**31 - 1))
    g = torch.Generator().manual_seed(seed)
    spread = draw(st.sampled_from([1e-3, 1.0, 10.0]))
    means = (torch.rand(n, 3, generator=g) - 0.5) * 2 * spread
    means[:, 2] += draw(st.floats(-1.0, 5.0, **_floats))  # some behind the camera, some at the near plane
    quats = torch.randn(n, 4, generator=g) * draw(st.sampled_from([1e-3, 1.0, 1e3]))  # unnormalised
    log_s = torch.empty(n, 3).uniform_(math.log(1e-4), math.log(1e2), generator=g)
    if draw(st.booleans()):  # needle-thin: one axis 1e4 times the others
        log_s[:, 0] = log_s[:, 1] + math.log(1e4)
    scales = log_s.exp()
    opac = torch.rand(n, generator=g)
    opac[: n // 3] = draw(st.sampled_from([0.0, 1.0, 0.999999]))
    colors = torch.rand(n, 3, generator=g) * draw(st.sampled_from([1.0, 10.0]))
    f = draw(st.floats(1.0, 1e4, **_floats))
    K = torch.tensor(
        [[f, 0.0, draw(st.floats(0, w, **_floats))], [0.0, f, draw(st.floats(0, h, **_floats))], [0, 0, 1]]
    )
    # a random rigid camera near the origin, world -> camera
    q = torch.randn(4, generator=g)
    q = q / q.norm()
    a, b, c, d = q.tolist()
    R = torch.tensor(
        [
            [1 - 2 * (c * c + d * d), 2 * (b * c - a * d), 2 * (b * d + a * c)],
            [2 * (b * c + a * d), 1 - 2 * (b * b + d * d), 2 * (c * d - a * b)],
            [2 * (b * d - a * c), 2 * (c * d + a * b), 1 - 2 * (b * b + c * c)],
        ]
    )
    view = torch.eye(4)
    if draw(st.booleans()):
        view[:3, :3] = R
    view[:3, 3] = torch.randn(3, generator=g) * 0.1
    mode = draw(st.sampled_from(["RGB", "RGB+ED", "D"]))
    return means, quats, scales, opac, colors, view[None], K[None], w, h, mode


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow], derandomize=True)
@given(scenes())
def test_torch_rasteriser_outputs_finite_alpha_in_unit_interval_gradients_finite(scene):
    means, quats, scales, opac, colors, viewmats, Ks, w, h, mode = scene
    leaves = [t.clone().requires_grad_(True) for t in (means, quats, scales, opac, colors)]
    render, alpha, meta = rasterize(*leaves, viewmats, Ks, w, h, render_mode=mode, backend="torch")
    assert render.shape[:3] == (1, h, w) and alpha.shape == (1, h, w, 1)
    assert torch.isfinite(render).all(), "non-finite render"
    assert torch.isfinite(alpha).all() and alpha.min() >= 0.0 and alpha.max() <= 1.0
    loss = render.square().mean() + alpha.mean()
    if loss.requires_grad:
        grads = torch.autograd.grad(loss, leaves, allow_unused=True)
        for name, gr in zip(("means", "quats", "scales", "opacities", "colors"), grads, strict=True):
            assert gr is None or torch.isfinite(gr).all(), f"non-finite gradient of {name}"


@pytest.mark.parametrize("n", [0, 1])
def test_empty_and_single_gaussian_scenes_give_the_background(n):
    means = torch.tensor([[0.0, 0.0, 2.0]])[:n]
    ones = torch.ones(n)
    render, alpha, _ = rasterize(
        means,
        torch.tensor([[1.0, 0, 0, 0]])[:n],
        torch.full((n, 3), 0.2),
        ones * 0.5,
        torch.ones(n, 3),
        torch.eye(4)[None],
        torch.tensor([[[10.0, 0, 4.5], [0, 10.0, 4.5], [0, 0, 1]]]),  # pixel (4, 4) centred on the mean
        8,
        8,
        backgrounds=torch.tensor([[0.1, 0.2, 0.3]]),
        backend="torch",
    )
    assert torch.isfinite(render).all() and alpha.min() >= 0 and alpha.max() <= 1
    if n == 0:
        assert torch.equal(alpha, torch.zeros_like(alpha))
        assert torch.allclose(render, torch.tensor([0.1, 0.2, 0.3]).expand_as(render))
    else:
        assert alpha[0, 4, 4, 0] == pytest.approx(0.5, abs=1e-3)  # opacity at the centre
