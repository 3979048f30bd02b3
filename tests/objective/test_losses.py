import pytest
import torch
from torchmetrics.functional.image import structural_similarity_index_measure

from willags_ns.objective.losses import masked_dssim, masked_l1, reconstruction_loss, total_loss


def _pair(seed=0, b=2, h=24, w=32):
    g = torch.Generator().manual_seed(seed)
    pred = torch.rand(b, 3, h, w, generator=g).requires_grad_(True)
    gt = torch.rand(b, 3, h, w, generator=g)
    return pred, gt


def test_l1_known_value():
    pred = torch.zeros(1, 3, 2, 2)
    gt = torch.zeros(1, 3, 2, 2)
    gt[0, 0, 0, 0] = 0.3
    gt[0, :, 1, 1] = 1.0  # a large error on an excluded pixel
    mask = torch.tensor([[[True, False], [False, False]]])
    assert masked_l1(pred, gt, mask).item() == pytest.approx(0.1)


def test_all_true_mask_equals_plain_losses():
    pred, gt = _pair()
    ones = torch.ones(2, 24, 32, dtype=torch.bool)
    torch.testing.assert_close(masked_l1(pred, gt, ones), (pred - gt).abs().mean())
    torch.testing.assert_close(masked_l1(pred, gt, None), (pred - gt).abs().mean())
    ssim = structural_similarity_index_measure(pred, gt, data_range=1.0)
    assert isinstance(ssim, torch.Tensor)
    torch.testing.assert_close(masked_dssim(pred, gt, ones), 1 - ssim)
    expected = 0.8 * (pred - gt).abs().mean() + 0.2 * (1 - ssim)
    torch.testing.assert_close(reconstruction_loss(pred, gt, ones), expected)
    torch.testing.assert_close(reconstruction_loss(pred, gt, ones.unsqueeze(1).float()), expected)


def test_all_masked_is_finite_zero_with_zero_gradients():
    pred, gt = _pair()
    none = torch.zeros(2, 24, 32, dtype=torch.bool)
    for fn in (masked_l1, masked_dssim, reconstruction_loss):
        pred.grad = None
        loss = fn(pred, gt, none)
        assert torch.isfinite(loss) and loss.item() == pytest.approx(0.0, abs=1e-6)
        loss.backward()
        assert pred.grad is not None and torch.isfinite(pred.grad).all() and pred.grad.abs().max() == 0


def test_masked_pixels_receive_no_gradient():
    pred, gt = _pair()
    mask = torch.ones(2, 24, 32, dtype=torch.bool)
    mask[:, 8:16, 10:20] = False  # a transient
    for fn in (masked_l1, masked_dssim, reconstruction_loss):
        pred.grad = None
        fn(pred, gt, mask).backward()
        assert pred.grad is not None
        g = pred.grad.abs().sum(1)  # [B, H, W]
        assert g[~mask].max() == 0, fn.__name__
        assert (g[mask] > 0).float().mean() > 0.9, fn.__name__


def test_masked_loss_ignores_transient_content():
    pred, gt = _pair()
    mask = torch.ones(2, 24, 32, dtype=torch.bool)
    mask[:, 8:16, 10:20] = False
    gt2 = gt.clone()
    gt2[:, :, 8:16, 10:20] = torch.rand(2, 3, 8, 10)  # change only the excluded pixels
    for fn in (masked_l1, masked_dssim):
        torch.testing.assert_close(fn(pred, gt, mask), fn(pred, gt2, mask))
    # and the normalisation is over kept pixels: a uniform error gives the same L1 whatever the mask covers
    e = torch.full((2, 3, 24, 32), 0.25)
    torch.testing.assert_close(masked_l1(e, torch.zeros_like(e), mask), torch.tensor(0.25))


def test_total_loss_composition():
    pred, gt = _pair()
    mask = torch.rand(2, 24, 32) > 0.3
    l_vae = torch.tensor(3.0, requires_grad=True)
    total, terms = total_loss(pred, gt, mask, l_vae)
    assert set(terms) == {"rgb_loss", "vae_loss"}
    torch.testing.assert_close(terms["rgb_loss"], reconstruction_loss(pred, gt, mask))
    torch.testing.assert_close(terms["vae_loss"], torch.tensor(0.03))
    torch.testing.assert_close(total, terms["rgb_loss"] + terms["vae_loss"])
    total.backward()
    assert l_vae.grad is not None and l_vae.grad.item() == pytest.approx(0.01)
    total2, terms2 = total_loss(pred, gt, mask)
    assert set(terms2) == {"rgb_loss"}


def test_shape_errors():
    pred, gt = _pair()
    with pytest.raises(ValueError):
        masked_l1(pred, gt[:, :, :-1], None)
    with pytest.raises(ValueError):
        masked_l1(pred, gt, torch.ones(2, 24, 31, dtype=torch.bool))
    with pytest.raises(ValueError):
        masked_l1(pred.permute(0, 2, 3, 1), gt.permute(0, 2, 3, 1), None)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA GPU")
def test_cuda_matches_cpu():
    pred, gt = _pair()
    mask = torch.rand(2, 24, 32, generator=torch.Generator().manual_seed(1)) > 0.3
    ref = reconstruction_loss(pred, gt, mask)
    out = reconstruction_loss(pred.detach().cuda(), gt.cuda(), mask.cuda())
    torch.testing.assert_close(out.cpu(), ref.detach(), atol=1e-5, rtol=1e-4)


@pytest.mark.parametrize("h,w", [(24, 32), (7, 9), (3, 5), (2, 2), (64, 48)])
def test_separable_ssim_map_equals_torchmetrics_map_and_gradients(h, w):
    """ssim_map (two 1D window passes) is torchmetrics' full SSIM map (one 2D window), values and gradients, at
    3DGS's window and at the smaller windows of tiny images (ssim_window)."""
    from willags_ns.objective.losses import ssim_map, ssim_window

    g = torch.Generator().manual_seed(h * 100 + w)
    x = torch.rand(2, 3, h, w, generator=g, dtype=torch.float64, requires_grad=True)
    y = torch.rand(2, 3, h, w, generator=g, dtype=torch.float64)
    k, sigma = ssim_window(h, w)
    _, want = structural_similarity_index_measure(
        x, y, data_range=1.0, return_full_image=True, reduction="none", kernel_size=k, sigma=sigma
    )
    got = ssim_map(x, y, sigma)
    assert got.shape == want.shape == x.shape
    torch.testing.assert_close(got, want, atol=1e-12, rtol=1e-10)
    wts = torch.rand(got.shape, generator=g, dtype=torch.float64)
    (ga,) = torch.autograd.grad((got * wts).sum(), [x])
    (gb,) = torch.autograd.grad((want * wts).sum(), [x])
    torch.testing.assert_close(ga, gb, atol=1e-12, rtol=1e-10)


def test_masked_dssim_without_mask_equals_all_true_mask():
    pred, gt = _pair(seed=4)
    ones = torch.ones(2, 24, 32, dtype=torch.bool)
    a, b = masked_dssim(pred, gt, None), masked_dssim(pred, gt, ones)
    torch.testing.assert_close(a, b)
    ga = torch.autograd.grad(a, [pred])[0]
    gb = torch.autograd.grad(b, [pred])[0]
    torch.testing.assert_close(ga, gb)
