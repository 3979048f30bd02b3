import math

import pytest
import torch

from willags_ns.appearance.decoder import ColorDecoder, ColorDecoderConfig, sh_basis


@pytest.mark.parametrize("degree", [0, 1, 2, 3])
def test_sh_basis_is_orthonormal(degree):
    g = torch.Generator().manual_seed(0)
    d = torch.randn(200_000, 3, generator=g, dtype=torch.float64)
    d = d / d.norm(dim=-1, keepdim=True)
    y = sh_basis(d, degree)
    assert y.shape == (200_000, (degree + 1) ** 2)
    gram = 4 * math.pi * (y.T @ y) / d.shape[0]  # Monte-Carlo integral over the sphere
    torch.testing.assert_close(gram, torch.eye(y.shape[1], dtype=torch.float64), atol=0.03, rtol=0)


@pytest.mark.parametrize("degree", [0, 1, 2, 3])
def test_sh_basis_is_the_rasterisers_basis_to_float_rounding(degree):
    """The decoder's encoding and the rasteriser's SH (render/sh.py's eval_sh_bases, gsplat's order) are one basis,
    evaluated in two orders: equal to float32 rounding."""
    from willags_ns.render.sh import eval_sh_bases

    d = torch.randn(10_000, 3, generator=torch.Generator().manual_seed(1))
    d = d / d.norm(dim=-1, keepdim=True)
    torch.testing.assert_close(sh_basis(d, degree), eval_sh_bases(degree, d), atol=2e-6, rtol=0)


def test_sh_basis_known_values():
    y = sh_basis(torch.tensor([[0.0, 0.0, 1.0]]), 1)
    torch.testing.assert_close(y, torch.tensor([[0.28209479, 0.0, 0.48860251, 0.0]]))
    with pytest.raises(ValueError):
        sh_basis(torch.zeros(1, 3), 4)


def test_output_range_and_shape():
    cfg = ColorDecoderConfig()
    dec = ColorDecoder(32, 32, cfg.hidden, cfg.dir_sh_degree)
    n = 500
    rgb = dec(torch.randn(n, 32) * 10, torch.randn(n, 32) * 10, torch.randn(n, 3) * 5)
    assert rgb.shape == (n, 3)
    assert (rgb > 0).all() and (rgb < 1).all()


def test_view_dirs_need_not_be_normalised():
    dec = ColorDecoder(4, 4, 16, 3)
    f_d, f_s, d = torch.randn(10, 4), torch.randn(10, 4), torch.randn(10, 3)
    torch.testing.assert_close(dec(f_d, f_s, d), dec(f_d, f_s, 7.5 * d))


def test_gradients_reach_all_inputs():
    torch.manual_seed(0)
    dec = ColorDecoder(8, 8, 16, 2)
    f_d = torch.randn(20, 8, requires_grad=True)
    f_s = torch.randn(20, 8, requires_grad=True)
    d = torch.randn(20, 3, requires_grad=True)
    dec(f_d, f_s, d).sum().backward()
    for t in (f_d, f_s, d):
        assert t.grad is not None and t.grad.abs().sum() > 0 and torch.isfinite(t.grad).all()


def test_empty_and_no_field_ablation():
    dec = ColorDecoder(8, 8, 16, 2)
    out = dec(torch.zeros(0, 8), torch.zeros(0, 8), torch.zeros(0, 3))
    assert out.shape == (0, 3)
    ablation = ColorDecoder(dynamic_dim=0, intrinsic_dim=8 + 64, hidden=16)
    rgb = ablation(None, torch.randn(5, 72), torch.randn(5, 3))
    assert rgb.shape == (5, 3)
    assert ablation(None, torch.zeros(0, 72), torch.zeros(0, 3)).shape == (0, 3)
    with pytest.raises(ValueError):
        dec(None, torch.randn(5, 8), torch.randn(5, 3))
    with pytest.raises(ValueError):
        dec(torch.randn(5, 8), torch.randn(5, 7), torch.randn(5, 3))


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA GPU")
def test_cuda_matches_cpu():
    torch.manual_seed(0)
    dec = ColorDecoder(8, 8, 16, 3)
    f_d, f_s, d = torch.randn(50, 8), torch.randn(50, 8), torch.randn(50, 3)
    ref = dec(f_d, f_s, d)
    out = dec.cuda()(f_d.cuda(), f_s.cuda(), d.cuda())
    torch.testing.assert_close(out.cpu(), ref, atol=1e-5, rtol=1e-4)
