"""The latent-conditioned colour transform (willags_ns/appearance/modulation.py)."""

import pytest
import torch

from willags_ns.appearance.modulation import ColorModulation, ColorModulationConfig, local_penalty


def _randomised(latent, intrinsic, dynamic):
    torch.manual_seed(0)
    m = ColorModulation(latent, intrinsic, dynamic, ColorModulationConfig())
    with torch.no_grad():
        for p in m.parameters():
            p.normal_(0.0, 0.3)  # a trained transform, not the zero-initialised identity
    return m


@pytest.mark.parametrize("intrinsic,dynamic", [(16, 0), (0, 0), (8, 32)])
def test_local_residual_is_the_mlp_over_the_concatenated_features(intrinsic, dynamic):
    """The split first layer (z's share added as one bias) gives exactly the MLP of the formula, and the same
    gradients to every input and weight."""
    m = _randomised(12, intrinsic, dynamic)
    n = 50
    z = torch.randn(12, requires_grad=True)
    f_s = torch.randn(n, intrinsic, requires_grad=True) if intrinsic else None
    f_d = torch.randn(n, dynamic, requires_grad=True) if dynamic else None
    got = m.local_residual(z, f_s, f_d, n)
    parts = ([f_s] if intrinsic else []) + [m.latent_proj(z).expand(n, -1)] + ([f_d] if dynamic else [])
    want = m.local_mlp(torch.cat(parts, -1))
    assert got.shape == (n, 6)
    torch.testing.assert_close(got, want, atol=1e-5, rtol=1e-5)
    inputs = [t for t in (z, f_s, f_d) if t is not None] + list(m.parameters())
    _assert_same_grads(got.square().sum(), want.square().sum(), inputs, tol=1e-4)


def _assert_same_grads(loss_got, loss_want, inputs, tol):
    """Both losses give the same gradient to every input (an input one of them does not reach: zero or None)."""
    g_got = torch.autograd.grad(loss_got, inputs, allow_unused=True)
    g_want = torch.autograd.grad(loss_want, inputs, allow_unused=True)
    for a, b in zip(g_got, g_want, strict=True):
        if b is None:
            assert a is None or a.abs().max() == 0
        else:
            torch.testing.assert_close(a, b, atol=tol, rtol=tol)


@pytest.mark.parametrize("chunk", [0, 16])
def test_a_residual_without_the_latent_projection_is_the_same_for_every_latent(chunk):
    """latent_proj 0: the per-Gaussian residual sees only the Gaussian's own features (a static colour scale and
    offset), while the global transform still follows z."""
    torch.manual_seed(0)
    m = ColorModulation(8, 4, 0, ColorModulationConfig(latent_proj=0, residual_chunk=chunk))
    with torch.no_grad():
        for p in m.parameters():
            p.normal_(0.0, 0.3)
    f_s, base = torch.randn(30, 4), torch.rand(30, 3)
    z1, z2 = torch.randn(8), torch.randn(8)
    torch.testing.assert_close(m.local_residual(z1, f_s, None, 30), m.local_residual(z2, f_s, None, 30))
    assert not torch.allclose(m(z1, base, f_s), m(z2, base, f_s))


@pytest.mark.parametrize("proj,rank", [(2, 2), (16, 8), (64, 8)])
def test_the_residual_follows_as_many_directions_of_the_latent_as_its_projection_keeps(proj, rank):
    """latent_proj sets how many directions of z move the per-Gaussian residual: the Jacobian of every Gaussian's
    (s, o) with respect to an 8-d z has rank min(8, latent_proj), at the same per-Gaussian cost (the projection is
    one vector added to the hidden layer)."""
    torch.manual_seed(0)
    m = ColorModulation(8, 4, 0, ColorModulationConfig(latent_proj=proj, local_hidden=64))
    with torch.no_grad():
        for p in m.parameters():
            p.normal_(0.0, 0.3)
    f_s, z = torch.randn(40, 4, dtype=torch.float64), torch.randn(8, dtype=torch.float64)
    m = m.double()
    jac = torch.autograd.functional.jacobian(lambda v: m.local_residual(v, f_s, None, 40), z)  # [40, 6, 8]
    assert int(torch.linalg.matrix_rank(jac.reshape(-1, 8))) == rank


def test_identity_at_initialisation_and_the_penalty():
    m = ColorModulation(8, 4, 0, ColorModulationConfig())
    base = torch.rand(20, 3)
    out = m(torch.randn(8), base, torch.randn(20, 4))
    torch.testing.assert_close(out, base)  # a fresh model is plain 3DGS
    assert local_penalty(torch.zeros(0, 6)) is None and local_penalty(None) is None
    assert float(local_penalty(torch.ones(3, 6))) == pytest.approx(6.0)


def test_wrong_feature_sizes_are_named():
    m = ColorModulation(8, 4, 2, ColorModulationConfig())
    with pytest.raises(ValueError, match=r"f_s must be \[N, 4\]"):
        m.local_residual(torch.zeros(8), torch.zeros(5, 3), torch.zeros(5, 2), 5)
    with pytest.raises(ValueError, match=r"f_d must be \[N, 2\]"):
        m.local_residual(torch.zeros(8), torch.zeros(5, 4), None, 5)


@pytest.mark.parametrize("chunk", [7, 50, 1000])
def test_chunked_residual_equals_plain_autograd(chunk):
    """The local residual's own backward (recomputing the hidden layer chunk by chunk, nothing [N, hidden] kept)
    gives the plain MLP's values and gradients, whatever the chunk size against N (uneven last chunk, one chunk)."""
    m = _randomised(12, 16, 0)
    n = 50
    z = torch.randn(12, requires_grad=True)
    f_s = torch.randn(n, 16, requires_grad=True)
    m.residual_chunk = chunk
    got = m.local_residual(z, f_s, None, n)
    m.residual_chunk = 0
    want = m.local_residual(z, f_s, None, n)
    assert got.grad_fn is not None and "LocalResidualMLP" in type(got.grad_fn).__name__
    assert "LocalResidualMLP" not in type(want.grad_fn).__name__
    torch.testing.assert_close(got, want, atol=1e-6, rtol=1e-6)
    w = torch.randn(n, 6)  # a loss that weighs every output differently
    _assert_same_grads((got * w).sum(), (want * w).sum(), [z, f_s, *m.parameters()], tol=1e-5)


def test_chunked_residual_gradcheck_float64():
    """torch's numerical gradient check of the chunked function (float64, three chunks)."""
    from willags_ns.appearance.modulation import LocalResidualMLP

    torch.manual_seed(1)
    f = torch.randn(11, 4, dtype=torch.float64, requires_grad=True)
    w1 = torch.randn(8, 4, dtype=torch.float64, requires_grad=True)
    h0 = torch.randn(8, dtype=torch.float64, requires_grad=True)
    w2 = torch.randn(6, 8, dtype=torch.float64, requires_grad=True)
    b2 = torch.randn(6, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda *a: LocalResidualMLP.apply(*a, 4), (f, w1, h0, w2, b2))


def test_chunked_residual_without_grad_and_frozen_inputs():
    """No grad (teacher, bake) and inputs that need none (a frozen f_s) take the same path without error."""
    m = _randomised(12, 16, 0)
    f_s = torch.randn(30, 16)
    with torch.no_grad():
        a = m.local_residual(torch.randn(12), f_s, None, 30)
    assert a.shape == (30, 6) and not a.requires_grad
    z = torch.randn(12, requires_grad=True)
    out = m.local_residual(z, f_s, None, 30)
    (gz,) = torch.autograd.grad(out.sum(), [z])
    assert torch.isfinite(gz).all() and gz.abs().sum() > 0


def test_chunked_residual_under_autocast_stays_float32():
    """Under (CPU) bf16 autocast the chunked function computes in float32 and returns float32 values and gradients
    (the per-chunk writes need one dtype), close to the call without autocast (only z's share of the bias, computed
    outside it, runs in bf16)."""
    m = _randomised(12, 16, 0)
    z = torch.randn(12, requires_grad=True)
    f_s = torch.randn(40, 16, requires_grad=True)
    m.residual_chunk = 16
    with torch.autocast("cpu", dtype=torch.bfloat16):
        got = m.local_residual(z, f_s, None, 40)
    want = m.local_residual(z, f_s, None, 40)
    assert got.dtype == torch.float32
    torch.testing.assert_close(got, want, atol=2e-2, rtol=2e-2)
    (g,) = torch.autograd.grad(got.sum(), [f_s])
    assert g.dtype == torch.float32 and torch.isfinite(g).all()


def test_gamma_starts_at_one_and_applies_a_per_channel_power_before_the_transform():
    """With ``gamma`` on, a fresh model is still plain 3DGS (g = 1); a trained g(z) raises each channel of the base
    colour to its own power before the 3x3 transform: c = A base^g + b."""
    from willags_ns.appearance.modulation import GAMMA_FLOOR

    m = ColorModulation(8, 4, 0, ColorModulationConfig(gamma=True))
    assert m.global_mlp[-1].out_features == 15
    assert ColorModulation(8, 4, 0, ColorModulationConfig()).gamma_of(torch.zeros(8)) is None
    base = GAMMA_FLOOR + torch.rand(20, 3)
    z, f_s = torch.randn(8), torch.randn(20, 4)
    torch.testing.assert_close(m.gamma_of(z), torch.ones(3))
    torch.testing.assert_close(m(z, base, f_s), base)
    with torch.no_grad():
        for p in m.global_mlp.parameters():
            p.normal_(0.0, 0.3)
    g = m.gamma_of(z)
    assert not torch.allclose(g, torch.ones(3), atol=1e-2)
    A, b = m.global_transform(z)
    residual = m.local_residual(z, f_s, None, 20)
    want = (base.pow(g) @ A.T + b) * (1 + residual[:, :3]) + residual[:, 3:]
    torch.testing.assert_close(m(z, base, f_s), want)


@pytest.mark.parametrize("h", [-1e4, -3.0, 0.0, 3.0, 1e4])
def test_gamma_stays_in_its_range_with_finite_gradients_at_black_and_at_the_extremes(h):
    """g(z) in [1/3, 3] whatever the MLP outputs, and black base colours (0, where x^g has no finite slope for
    g < 1) give finite gradients to the base and the networks."""
    m = ColorModulation(8, 0, 0, ColorModulationConfig(gamma=True, local=False))
    with torch.no_grad():
        m.global_mlp[-1].bias[12:].fill_(h)
    z = torch.randn(8, requires_grad=True)
    g = m.gamma_of(z)
    assert ((g >= 1 / 3 - 1e-6) & (g <= 3 + 1e-5)).all(), g
    base = torch.tensor([[0.0, 0.0, 0.0], [1e-8, 0.5, 1.0], [2.0, 1e-3, 0.25]], requires_grad=True)
    out = m(z, base)
    grads = torch.autograd.grad(out.sum(), [base, z, *m.parameters()], allow_unused=True)
    assert torch.isfinite(out).all()
    assert all(gr is None or torch.isfinite(gr).all() for gr in grads)


@pytest.mark.parametrize("chunk", [0, 16])
def test_a_render_anchor_fixes_the_residuals_latent_outside_training_only(chunk):
    """residual_latent "mean": outside training the local residual reads the anchor the model gives (the training
    latents' mean) whatever the latent, while the global transform still follows it; while training, and with
    residual_latent "own", the residual follows the latent."""
    torch.manual_seed(0)
    m = ColorModulation(8, 4, 0, ColorModulationConfig(residual_latent="mean", residual_chunk=chunk))
    with torch.no_grad():
        for p in m.parameters():
            p.normal_(0.0, 0.3)
    f_s, base = torch.randn(30, 4), torch.rand(30, 3)
    z1, z2, anchor = torch.randn(8), torch.randn(8), torch.randn(8)
    assert m.anchors_render()
    m.set_render_anchor(anchor)
    m.eval()
    at_anchor = m.local_residual(anchor, f_s, None, 30)
    torch.testing.assert_close(m.local_residual(z1, f_s, None, 30), at_anchor)
    torch.testing.assert_close(m.local_residual(z2, f_s, None, 30), at_anchor)
    assert not torch.allclose(m(z1, base, f_s), m(z2, base, f_s))  # the global transform follows z
    A, b = m.global_transform(z1)
    scale, offset = at_anchor.split(3, dim=-1)
    torch.testing.assert_close(m(z1, base, f_s), (base @ A.mT + b) * (1 + scale) + offset)
    m.train()
    assert not torch.allclose(m.local_residual(z1, f_s, None, 30), at_anchor)
    m.eval()
    m.set_render_anchor(None)  # what the model gives while it trains
    assert not torch.allclose(m.local_residual(z1, f_s, None, 30), at_anchor)

    own = ColorModulation(8, 4, 0, ColorModulationConfig(residual_chunk=chunk))
    own.load_state_dict(m.state_dict())
    assert not own.anchors_render()
    own.set_render_anchor(anchor)  # ignored: the residual reads the latent it is given
    own.eval()
    assert not torch.allclose(own.local_residual(z1, f_s, None, 30), at_anchor)
    static = ColorModulation(8, 4, 0, ColorModulationConfig(residual_latent="mean", latent_proj=0))
    assert not static.anchors_render()  # a residual that does not read z has nothing to anchor
