import pytest
import torch

from willags_ns.appearance.vae import (
    LOGVAR_MAX,
    LOGVAR_MIN,
    AppearanceVAE,
    VAEConfig,
    kl_divergence,
    reparameterize,
    vae_loss,
)


def test_kl_zero_at_prior_positive_elsewhere():
    mu = torch.zeros(3, 8)
    logvar = torch.zeros(3, 8)
    assert kl_divergence(mu, logvar).item() == pytest.approx(0.0, abs=1e-7)
    # One dim with mu = 1 (the rest at the prior): 0.5 * 1 = 0.5 per sample, batch mean 0.5.
    mu1 = mu.clone()
    mu1[:, 0] = 1.0
    assert kl_divergence(mu1, logvar).item() == pytest.approx(0.5, rel=1e-6)
    g = torch.Generator().manual_seed(0)
    for _ in range(5):
        m = torch.randn(2, 8, generator=g)
        lv = torch.randn(2, 8, generator=g)
        assert kl_divergence(m, lv).item() > 0.0
    # variance only (mu = 0): also positive
    assert kl_divergence(mu, torch.full((3, 8), 0.5)).item() > 0.0


def test_reparameterize_gradients_and_statistics():
    mu = torch.tensor([[1.0, -2.0]], requires_grad=True)
    logvar = torch.tensor([[0.0, 2.0]], requires_grad=True)
    z = reparameterize(mu.expand(20000, 2), logvar.expand(20000, 2), generator=torch.Generator().manual_seed(0))
    z.sum().backward()
    assert mu.grad is not None and torch.all(mu.grad != 0)
    assert logvar.grad is not None and torch.all(logvar.grad != 0)
    # the samples follow N(mu, exp(logvar))
    torch.testing.assert_close(z.mean(0), mu.detach()[0], atol=0.05, rtol=0)
    torch.testing.assert_close(z.std(0), torch.exp(0.5 * logvar.detach()[0]), atol=0.05, rtol=0.02)


def test_reparameterize_is_reproducible_with_generator():
    mu, logvar = torch.zeros(2, 4), torch.zeros(2, 4)
    a = reparameterize(mu, logvar, generator=torch.Generator().manual_seed(3))
    b = reparameterize(mu, logvar, generator=torch.Generator().manual_seed(3))
    torch.testing.assert_close(a, b)


def test_shapes_and_any_input_size():
    cfg = VAEConfig()
    vae = AppearanceVAE(64, cfg.image_size, cfg.channels)
    images = torch.rand(2, 3, 90, 130)
    mu, logvar = vae.encode(images)
    assert mu.shape == (2, 64) and logvar.shape == (2, 64)
    recon = vae.decode(mu)
    assert recon.shape == (2, 3, 64, 64)
    assert recon.min() > 0 and recon.max() < 1
    assert vae.prepare(images).shape == (2, 3, 64, 64)
    out = vae(images, sample=False)
    torch.testing.assert_close(out["z"], out["mu"])
    out = vae(images, sample=True, generator=torch.Generator().manual_seed(0))
    assert not torch.allclose(out["z"], out["mu"])


def test_logvar_is_clamped():
    vae = AppearanceVAE(latent_dim=4, image_size=16, channels=(8, 8))
    with torch.no_grad():
        vae.to_stats.bias[4:] = 1e4  # logvar half of the output
    _, logvar = vae.encode(torch.rand(1, 3, 16, 16))
    assert logvar.max().item() == LOGVAR_MAX
    with torch.no_grad():
        vae.to_stats.bias[4:] = -1e4
    _, logvar = vae.encode(torch.rand(1, 3, 16, 16))
    assert logvar.min().item() == LOGVAR_MIN
    assert torch.isfinite(kl_divergence(torch.zeros_like(logvar), logvar))


def test_bad_image_size_raises():
    with pytest.raises(ValueError):
        AppearanceVAE(image_size=60, channels=(8, 8, 8))


def _train_recon(beta, reduction, steps=30):
    torch.manual_seed(0)
    vae = AppearanceVAE(latent_dim=8, image_size=16, channels=(16, 32))
    # 4 tiny, distinct images: smooth colour gradients
    ys, xs = torch.meshgrid(torch.linspace(0, 1, 24), torch.linspace(0, 1, 24), indexing="ij")
    images = torch.stack(
        [
            torch.stack([xs, ys, 1 - xs]),
            torch.stack([ys, 1 - ys, xs]),
            torch.stack([1 - xs * ys, xs, ys]),
            torch.stack([0.2 + 0 * xs, 0.8 * ys, 0.5 + 0 * xs]),
        ]
    )
    opt = torch.optim.Adam(vae.parameters(), lr=1e-2)
    gen = torch.Generator().manual_seed(0)
    recons = []
    terms = {}
    for _ in range(steps):
        out = vae(images, sample=True, generator=gen)
        loss, terms = vae_loss(out["recon"], out["target"], out["mu"], out["logvar"], beta, reduction)
        opt.zero_grad()
        loss.backward()
        opt.step()
        recons.append(terms["vae_recon"].item())
        assert torch.isfinite(loss)
    return recons, terms["vae_kl"].item()


def test_recon_loss_decreases():
    # beta = 2 with the per-image-sum likelihood scale: the VAE learns and z carries information (KL > 0)
    recons, kl = _train_recon(2.0, "sum")
    assert recons[-1] < 0.6 * recons[0]
    assert kl > 1.0
    # per-pixel mean scale, KL off: the reconstruction path alone learns
    recons, _ = _train_recon(0.0, "mean")
    assert recons[-1] < 0.6 * recons[0]


def test_vae_loss_composition():
    recon = torch.full((1, 3, 4, 4), 0.5)
    target = torch.zeros(1, 3, 4, 4)
    mu = torch.ones(1, 2)
    logvar = torch.zeros(1, 2)
    loss, terms = vae_loss(recon, target, mu, logvar, beta=2.0)
    assert terms["vae_recon"].item() == pytest.approx(0.5)
    assert terms["vae_kl"].item() == pytest.approx(1.0)  # 2 dims x 0.5
    assert loss.item() == pytest.approx(0.5 + 2.0 * 1.0)
    loss_sum, terms_sum = vae_loss(recon, target, mu, logvar, beta=2.0, recon_reduction="sum")
    assert terms_sum["vae_recon"].item() == pytest.approx(0.5 * 48)
    with pytest.raises(ValueError):
        vae_loss(recon, target, mu, logvar, recon_reduction="max")  # pyright: ignore[reportArgumentType]


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA GPU")
def test_cuda_forward_and_sampling():
    vae = AppearanceVAE(latent_dim=8, image_size=16, channels=(8, 8)).cuda()
    out = vae(torch.rand(2, 3, 20, 30, device="cuda"), sample=True, generator=torch.Generator("cuda").manual_seed(0))
    assert out["z"].is_cuda and out["recon"].shape == (2, 3, 16, 16)
