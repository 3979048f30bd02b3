"""CPU tests of `willags_ns.render.rasterize` with the pure-torch backend.

Categories (kornia's): known answers computed by hand, an independent dense twin of gsplat's kernel (forward and
gradients), float64 gradcheck, exceptions, extremes, and gsplat's DefaultStrategy driven by our meta.
"""

import math
from typing import Any

import pytest
import torch
import torch.nn.functional as F

from willags_ns.render import rasterize
from willags_ns.splats.mcmc import covariances as mcmc_covariances

# ----------------------------------------------------------------------------------------------- helpers


def pinhole(width: int, height: int, f: float, C: int = 1, dtype=torch.float32):
    """C identity-pose cameras (looking down +z) with focal f and the principal point at the image centre."""
    K = torch.tensor([[f, 0.0, width / 2], [0.0, f, height / 2], [0.0, 0.0, 1.0]], dtype=dtype)
    return torch.eye(4, dtype=dtype).repeat(C, 1, 1), K.repeat(C, 1, 1)


def orbit_viewmats(C: int, radius: float = 4.0, dtype=torch.float32):
    """C world-to-camera matrices on a circle around the origin, all looking at it."""
    mats = []
    for i in range(C):
        a = 0.4 * i
        eye = torch.tensor([radius * math.sin(a), 0.3 * i, -radius * math.cos(a)], dtype=dtype)
        fwd = F.normalize(-eye, dim=0)
        right = F.normalize(torch.linalg.cross(torch.tensor([0.0, 1.0, 0.0], dtype=dtype), fwd), dim=0)
        up = torch.linalg.cross(fwd, right)
        R = torch.stack([right, up, fwd])  # rows: camera axes in world
        V = torch.eye(4, dtype=dtype)
        V[:3, :3] = R
        V[:3, 3] = -R @ eye
        mats.append(V)
    return torch.stack(mats)


def random_scene(
    N: int, seed: int, dtype=torch.float32, spread: float = 1.0, scale=(0.02, 0.3), opacity=(0.05, 0.95), D: int = 3
):
    g = torch.Generator().manual_seed(seed)
    means = (torch.rand(N, 3, generator=g, dtype=dtype) - 0.5) * 2 * spread
    quats = torch.randn(N, 4, generator=g, dtype=dtype)
    lo, hi = math.log(scale[0]), math.log(scale[1])
    scales = torch.exp(lo + (hi - lo) * torch.rand(N, 3, generator=g, dtype=dtype))
    opacities = opacity[0] + (opacity[1] - opacity[0]) * torch.rand(N, generator=g, dtype=dtype)
    colors = torch.rand(N, D, generator=g, dtype=dtype)
    return means, quats, scales, opacities, colors


def test_quaternion_to_matrix_is_a_rotation_and_normalises():
    from willags_ns.render.rotation import quaternion_to_matrix

    q = torch.randn(50, 4, dtype=torch.float64)
    R = quaternion_to_matrix(q)
    torch.testing.assert_close(R @ R.transpose(-1, -2), torch.eye(3, dtype=torch.float64).expand(50, 3, 3))
    torch.testing.assert_close(torch.linalg.det(R), torch.ones(50, dtype=torch.float64))
    torch.testing.assert_close(quaternion_to_matrix(3.0 * q), R)  # the norm does not matter
    half = torch.tensor([0.5**0.5, 0.0, 0.0, 0.5**0.5])  # 90 degrees about z: x -> y
    torch.testing.assert_close(
        quaternion_to_matrix(half) @ torch.tensor([1.0, 0.0, 0.0]), torch.tensor([0.0, 1.0, 0.0])
    )


def rasterize_p(params, viewmats, Ks, width, height, **kwargs: Any):
    """`rasterize` with the five Gaussian tensors given as one sequence."""
    means, quats, scales, opacities, colors = params
    return rasterize(means, quats, scales, opacities, colors, viewmats, Ks, width, height, **kwargs)


def dense_reference(
    params,
    viewmats,
    Ks,
    width,
    height,
    *,
    tile_size=16,
    eps2d=0.3,
    backgrounds=None,
    antialiased=False,
    sh_degree=None,
    depth_channel=False,
):
    """An independent, slow twin of gsplat's pipeline: gsplat's own pure-torch projection, then its CUDA
    compositing kernel replayed literally, one Gaussian at a time (front to back) over all pixels at once:
    tile membership, alpha = min(0.999, o exp(-sigma)), skip alpha < 1/255 or sigma < 0, stop at next_T <= 1e-4.
    Differentiable by autograd. Returns render [C, H, W, D], alpha [C, H, W, 1], means2d [C, N, 2] and the number
    of pixels where the cut-off stopped compositing."""
    from gsplat.cuda._torch_impl import _fully_fused_projection, _spherical_harmonics

    means, quats, scales, opacities, colors = params
    C, N = viewmats.shape[0], means.shape[0]
    radii, means2d, depths, conics, comp = _fully_fused_projection(
        means, mcmc_covariances(quats, scales), viewmats, Ks, width, height, eps2d=eps2d, calc_compensations=antialiased
    )
    opac = opacities[None].expand(C, N) * (comp if antialiased else 1.0)
    if sh_degree is not None:
        campos = torch.linalg.inv(viewmats)[:, :3, 3]
        dirs = means[None] - campos[:, None]
        shs = colors.expand(C, -1, -1, -1) if colors.dim() == 3 else colors
        feats = torch.clamp_min(_spherical_harmonics(sh_degree, dirs, shs) + 0.5, 0.0)
    else:
        feats = colors.expand(C, -1, -1) if colors.dim() == 2 else colors
    if depth_channel:
        feats = torch.cat([feats, depths[..., None]], dim=-1)
    ys, xs = torch.meshgrid(torch.arange(height), torch.arange(width), indexing="ij")
    px, py = xs.reshape(-1).to(means.dtype) + 0.5, ys.reshape(-1).to(means.dtype) + 0.5
    tx, ty = xs.reshape(-1) // tile_size, ys.reshape(-1) // tile_size
    tw, th = math.ceil(width / tile_size), math.ceil(height / tile_size)
    renders, alphas, n_stopped = [], [], 0
    for c in range(C):
        T = torch.ones(height * width, dtype=means.dtype)
        done = torch.zeros(height * width, dtype=torch.bool)
        out = torch.zeros(height * width, feats.shape[-1], dtype=means.dtype)
        order = sorted(range(N), key=lambda i: (float(depths[c, i]), i))
        for i in order:
            r = float(radii[c, i])
            if r <= 0:
                continue
            mx, my = means2d[c, i]
            x0 = min(max(math.floor((float(mx) - r) / tile_size), 0), tw)
            x1 = min(max(math.ceil((float(mx) + r) / tile_size), 0), tw)
            y0 = min(max(math.floor((float(my) - r) / tile_size), 0), th)
            y1 = min(max(math.ceil((float(my) + r) / tile_size), 0), th)
            in_tile = (tx >= x0) & (tx < x1) & (ty >= y0) & (ty < y1)
            a, b, cc = conics[c, i]
            dx, dy = mx - px, my - py
            sigma = 0.5 * (a * dx * dx + cc * dy * dy) + b * dx * dy
            alpha = torch.clamp_max(opac[c, i] * torch.exp(-sigma), 0.999)
            ok = in_tile & ~done & (sigma >= 0) & (alpha >= 1 / 255)
            next_T = T * (1 - alpha)
            stop = ok & (next_T <= 1e-4)
            done = done | stop
            ok = ok & ~stop
            out = out + torch.where(ok, alpha * T, torch.zeros_like(T))[:, None] * feats[c, i]
            T = torch.where(ok, next_T, T)
        if backgrounds is not None:  # the depth channel's background is 0, as in gsplat
            bg = F.pad(backgrounds[c], (0, out.shape[-1] - backgrounds.shape[-1]))
            out = out + T[:, None] * bg
        n_stopped += int(done.sum())
        renders.append(out.reshape(height, width, -1))
        alphas.append((1 - T).reshape(height, width, 1))
    return torch.stack(renders), torch.stack(alphas), means2d, n_stopped


def rel_err(a: torch.Tensor, b: torch.Tensor) -> float:
    """max |a - b| / max |b| (0 when both vanish)."""
    scale = b.abs().max().item()
    return (a - b).abs().max().item() / max(scale, 1e-30)


# ----------------------------------------------------------------------------------------------- known answers


def test_single_gaussian_alpha_at_centre_and_falloff():
    W, H, f, z, s, o = 16, 16, 20.0, 2.0, 0.1, 0.8
    viewmats, Ks = pinhole(W, H, f)
    # the mean projects to (8.5, 7.5): exactly the centre of pixel (x=8, y=7)
    means = torch.tensor([[0.5 * z / f, -0.5 * z / f, z]])
    quats = torch.tensor([[1.0, 0.0, 0.0, 0.0]])
    scales = torch.full((1, 3), s)
    color = torch.tensor([[0.2, 0.5, 1.0]])
    render, alpha, meta = rasterize(means, quats, scales, torch.tensor([o]), color, viewmats, Ks, W, H)
    assert render.shape == (1, H, W, 3) and alpha.shape == (1, H, W, 1)
    assert meta["backend"] == "torch"  # "auto" on CPU tensors
    assert torch.allclose(meta["means2d"][0, 0], torch.tensor([8.5, 7.5]))
    torch.testing.assert_close(alpha[0, 7, 8, 0], torch.tensor(o))
    torch.testing.assert_close(render[0, 7, 8], o * color[0])
    # one pixel to the right: variance (f s / z)^2 + eps2d (the mean is on the optical axis, so J is diagonal;
    # its x offset from the axis is tiny and the tx term vanishes to first order)
    var = (f * s / z) ** 2 + 0.3
    expect = o * math.exp(-0.5 / var)
    torch.testing.assert_close(alpha[0, 7, 9, 0], torch.tensor(expect), rtol=1e-3, atol=1e-5)
    # gsplat's radius: ceil(3 sqrt(largest eigenvalue)); here both eigenvalues are var (up to the tiny tx term)
    assert int(meta["radii"][0, 0]) == math.ceil(3 * math.sqrt(var))
    # far pixels (alpha < 1/255) are untouched
    assert alpha[0, 0, 0, 0] == 0


def _two_layer(depth_red: float, depth_green: float):
    W = H = 12
    viewmats, Ks = pinhole(W, H, 15.0)
    means = torch.tensor([[0.0, 0.0, depth_red], [0.0, 0.0, depth_green]])
    quats = torch.tensor([[1.0, 0, 0, 0], [1.0, 0, 0, 0]])
    scales = torch.tensor([[0.5, 0.5, 0.5], [0.5, 0.5, 0.5]])
    opac = torch.tensor([0.999, 0.999])
    colors = torch.tensor([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
    render, alpha, _ = rasterize(means, quats, scales, opac, colors, viewmats, Ks, W, H)
    return render[0, H // 2, W // 2]


def test_occlusion_order():
    front_red = _two_layer(2.0, 3.0)
    assert front_red[0] > 0.95 and front_red[1] < 0.05
    front_green = _two_layer(3.0, 2.0)
    assert front_green[1] > 0.95 and front_green[0] < 0.05


@pytest.mark.parametrize("case", ["behind", "empty"])
def test_empty_scene_gives_background(case):
    W, H = 10, 8
    viewmats, Ks = pinhole(W, H, 10.0, C=2)
    bg = torch.tensor([[0.1, 0.2, 0.3], [0.7, 0.6, 0.5]])
    if case == "behind":
        means = torch.tensor([[0.0, 0.0, -2.0], [0.1, 0.0, 0.0], [0.0, 0.1, 0.005]], requires_grad=True)
    else:
        means = torch.zeros(0, 3, requires_grad=True)
    N = means.shape[0]
    quats = torch.tensor([[1.0, 0, 0, 0]]).repeat(N, 1)
    scales = torch.full((N, 3), 0.3)
    colors = torch.rand(N, 3)
    render, alpha, meta = rasterize(
        means, quats, scales, torch.full((N,), 0.9), colors, viewmats, Ks, W, H, backgrounds=bg
    )
    assert torch.equal(alpha, torch.zeros(2, H, W, 1))
    assert torch.equal(render, bg[:, None, None, :].expand(2, H, W, 3))
    assert meta["n_pairs"] == 0 and (meta["radii"] == 0).all() and meta["radii"].shape == (2, N)
    render.sum().backward()  # still a graph; gradients are zero, not NaN
    assert means.grad is not None and torch.equal(means.grad, torch.zeros_like(means))


def test_transmittance_cutoff_is_exclusive():
    """Four stacked Gaussians of opacity 0.95: T = 0.05, 0.0025, 1.25e-4 after three; the fourth would give
    6.25e-6 <= 1e-4, so gsplat stops *before* it: it contributes nothing and alpha = 1 - 0.05^3."""
    W = H = 9
    viewmats, Ks = pinhole(W, H, 10.0)
    means = torch.tensor([[0.0, 0.0, 2.0], [0.0, 0.0, 3.0], [0.0, 0.0, 4.0], [0.0, 0.0, 5.0]])
    quats = torch.tensor([[1.0, 0, 0, 0]]).repeat(4, 1)
    scales = means[:, 2:3].expand(4, 3) * 0.2  # same pixel footprint for all four
    opac = torch.full((4,), 0.95)
    colors = torch.tensor([[1.0, 0, 0], [1.0, 0, 0], [1.0, 0, 0], [0.0, 0.0, 1.0]])
    # centre pixel (4, 4): mean at (4.5, 4.5) -> sigma = 0
    render, alpha, _ = rasterize(means, quats, scales, opac, colors, viewmats, Ks, W, H)
    torch.testing.assert_close(alpha[0, 4, 4, 0], torch.tensor(1 - 0.05**3))
    assert render[0, 4, 4, 2] == 0.0  # the blue fourth Gaussian is cut off
    torch.testing.assert_close(render[0, 4, 4, 0], torch.tensor(1 - 0.05**3))
    # a pixel where the stack is thinner keeps all four (the cut-off is per pixel)
    assert render[0, 4, 6, 2] > 0


def test_expected_depth_of_single_opaque_gaussian():
    W = H = 12
    viewmats, Ks = pinhole(W, H, 12.0)
    z = 3.7
    means = torch.tensor([[0.0, 0.0, z]])
    args = (means, torch.tensor([[1.0, 0, 0, 0]]), torch.full((1, 3), 0.4), torch.tensor([0.9]), torch.rand(1, 3))
    render, alpha, _ = rasterize_p(args, viewmats, Ks, W, H, render_mode="RGB+ED")
    covered = alpha[0, ..., 0] > 0
    assert covered.sum() > 10
    torch.testing.assert_close(render[0][covered][:, 3], torch.full((int(covered.sum()),), z))
    assert torch.equal(render[0][~covered][:, 3], torch.zeros(int((~covered).sum())))
    acc_depth, alpha_d, _ = rasterize_p(args, viewmats, Ks, W, H, render_mode="D")
    torch.testing.assert_close(acc_depth, alpha_d * z)
    ed, _, _ = rasterize_p(args, viewmats, Ks, W, H, render_mode="ED")
    torch.testing.assert_close(ed[..., 0], render[..., 3])


# ----------------------------------------------------------------------------------------------- dense twin


@pytest.mark.parametrize(
    "C, tile_size, antialiased, sh_degree, per_camera_colors, render_mode",
    [
        (1, 16, False, None, False, "RGB"),
        (2, 8, True, None, True, "RGB+ED"),
        (2, 4, False, 3, False, "RGB+D"),
        (2, 16, False, 2, True, "RGB"),  # per-camera SH coefficients [C, N, K, 3], partial degree
    ],
)
def test_matches_dense_gsplat_twin(C, tile_size, antialiased, sh_degree, per_camera_colors, render_mode):
    dtype = torch.float64
    W, H, N = 23, 19, 80
    # dense and fairly opaque, so that many pixels reach gsplat's T cut-off
    means, quats, scales, opac, colors = random_scene(
        N, seed=C + tile_size, dtype=dtype, spread=0.5, scale=(0.02, 0.4), opacity=(0.5, 0.99)
    )
    viewmats = orbit_viewmats(C, dtype=dtype)
    _, Ks = pinhole(W, H, 30.0, C=C, dtype=dtype)
    if sh_degree is not None:
        shape = (C, N, 16, 3) if per_camera_colors else (N, 16, 3)
        colors = 0.3 * torch.randn(*shape, dtype=dtype, generator=torch.Generator().manual_seed(3))
    elif per_camera_colors:
        colors = torch.rand(C, N, 3, dtype=dtype)
    bg = torch.rand(C, 3, dtype=dtype)
    params = [means, quats, scales, opac, colors]
    for p in params:
        p.requires_grad_(True)
    render, alpha, meta = rasterize_p(
        params,
        viewmats,
        Ks,
        W,
        H,
        tile_size=tile_size,
        backgrounds=bg,
        sh_degree=sh_degree,
        rasterize_mode="antialiased" if antialiased else "classic",
        render_mode=render_mode,
    )
    ref_r, ref_a, ref_m2, n_stopped = dense_reference(
        params,
        viewmats,
        Ks,
        W,
        H,
        tile_size=tile_size,
        eps2d=0.3,
        backgrounds=bg,
        antialiased=antialiased,
        sh_degree=sh_degree,
        depth_channel=render_mode != "RGB",
    )
    if render_mode == "RGB+ED":
        ref_r = torch.cat([ref_r[..., :3], ref_r[..., 3:] / ref_a.clamp(min=1e-10)], dim=-1)
    assert meta["n_pairs"] > 500
    assert n_stopped > 20 or antialiased  # the T cut-off is exercised (compensation lowers opacities too much)
    assert rel_err(render, ref_r) < 1e-10 and rel_err(alpha, ref_a) < 1e-10
    vis = meta["radii"] > 0
    assert vis.sum() > N // 2
    assert rel_err(meta["means2d"][vis], ref_m2[vis]) < 1e-12

    g = torch.Generator().manual_seed(0)
    wr, wa = torch.randn(render.shape, generator=g, dtype=dtype), torch.randn(alpha.shape, generator=g, dtype=dtype)
    meta["means2d"].retain_grad()
    ref_m2.retain_grad()
    ours = torch.autograd.grad((render * wr).sum() + (alpha * wa).sum(), params + [meta["means2d"]])
    ref = torch.autograd.grad((ref_r * wr).sum() + (ref_a * wa).sum(), params + [ref_m2])
    for name, a, b in zip(["means", "quats", "scales", "opacities", "colors", "means2d"], ours, ref, strict=True):
        assert torch.isfinite(a).all(), name
        assert rel_err(a, b) < 1e-8, (name, rel_err(a, b))


def test_chunked_early_termination_matches_dense_twin(monkeypatch):
    """Dense scenes are binned front to back in chunks and skip pixels already cut off; force tiny chunks here."""
    import willags_ns.render._torch as rt

    monkeypatch.setattr(rt, "LAYERS_PER_CHUNK", 1)
    dtype = torch.float64
    W, H, N, C = 17, 13, 80, 2
    means, quats, scales, opac, colors = random_scene(
        N, seed=11, dtype=dtype, spread=0.5, scale=(0.05, 0.5), opacity=(0.6, 0.99)
    )
    viewmats = orbit_viewmats(C, dtype=dtype)
    _, Ks = pinhole(W, H, 25.0, C=C, dtype=dtype)
    params = [means, quats, scales, opac.requires_grad_(True), colors.requires_grad_(True)]
    render, alpha, meta = rasterize_p(params, viewmats, Ks, W, H, tile_size=8)
    ref_r, ref_a, _, n_stopped = dense_reference(params, viewmats, Ks, W, H, tile_size=8)
    assert n_stopped > 50
    assert meta["n_candidates"] < 0.9 * _count_candidates_without_chunks(params, viewmats, Ks, W, H, monkeypatch)
    assert rel_err(render, ref_r) < 1e-10 and rel_err(alpha, ref_a) < 1e-10
    ours = torch.autograd.grad(render.square().sum() + alpha.sum(), params[3:])
    ref = torch.autograd.grad(ref_r.square().sum() + ref_a.sum(), params[3:])
    for a, b in zip(ours, ref, strict=True):
        assert rel_err(a, b) < 1e-8


def _count_candidates_without_chunks(params, viewmats, Ks, W, H, monkeypatch):
    import willags_ns.render._torch as rt

    monkeypatch.setattr(rt, "LAYERS_PER_CHUNK", 10**6)
    with torch.no_grad():
        return rasterize_p(params, viewmats, Ks, W, H, tile_size=8)[2]["n_candidates"]


def test_packed_matches_unpacked():
    W, H, N, C = 20, 16, 30, 2
    means, quats, scales, opac, colors = random_scene(N, seed=5)
    viewmats = orbit_viewmats(C)
    _, Ks = pinhole(W, H, 16.0, C=C)
    r0, a0, m0 = rasterize(means, quats, scales, opac, colors, viewmats, Ks, W, H, packed=False)
    r1, a1, m1 = rasterize(means, quats, scales, opac, colors, viewmats, Ks, W, H, packed=True)
    torch.testing.assert_close(r0, r1)
    torch.testing.assert_close(a0, a1)
    sel = m0["radii"] > 0
    nnz = int(sel.sum())
    assert m1["means2d"].shape == (nnz, 2) and m1["radii"].shape == (nnz,)
    assert torch.equal(m1["camera_ids"], torch.where(sel)[0]) and torch.equal(m1["gaussian_ids"], torch.where(sel)[1])
    torch.testing.assert_close(m1["means2d"], m0["means2d"][sel])


def test_sh_matches_gsplat_torch_twin():
    from gsplat.cuda._torch_impl import _spherical_harmonics

    from willags_ns.render.sh import spherical_harmonics

    dirs = torch.randn(50, 3, dtype=torch.float64)
    coeffs = torch.randn(50, 25, 3, dtype=torch.float64)
    for degree in range(5):
        torch.testing.assert_close(
            spherical_harmonics(degree, dirs, coeffs),
            _spherical_harmonics(degree, dirs, coeffs[:, : (degree + 1) ** 2]),
        )


# ----------------------------------------------------------------------------------------------- gradcheck


def test_gradcheck_float64():
    """Three large soft Gaussians over an 8x8 image (one 16-px tile): every pixel has alpha well above 1/255,
    far below the 0.999 clamp and far from the T cut-off, so the pair set is locally constant."""
    dtype = torch.float64
    W = H = 8
    viewmats, Ks = pinhole(W, H, 8.0, dtype=dtype)
    means = torch.tensor([[0.1, -0.05, 2.0], [-0.2, 0.1, 2.5], [0.05, 0.15, 3.0]], dtype=dtype)
    quats = torch.tensor([[1.0, 0.1, -0.2, 0.05], [0.9, -0.3, 0.1, 0.2], [0.8, 0.2, 0.3, -0.1]], dtype=dtype)
    scales = torch.tensor([[0.9, 0.7, 0.8], [1.0, 1.1, 0.9], [1.2, 1.0, 1.3]], dtype=dtype)
    opac = torch.tensor([0.4, 0.5, 0.6], dtype=dtype)
    colors = torch.tensor([[0.9, 0.1, 0.2], [0.2, 0.8, 0.3], [0.1, 0.3, 0.9]], dtype=dtype)
    inputs = [t.clone().requires_grad_(True) for t in (means, quats, scales, opac, colors)]

    def fn(*p):
        render, alpha, meta = rasterize_p(p, viewmats, Ks, W, H, render_mode="RGB+ED")
        assert meta["n_pairs"] == 3 * W * H
        return render, alpha

    assert torch.autograd.gradcheck(fn, inputs, eps=1e-6, atol=1e-6, rtol=1e-5)


# ----------------------------------------------------------------------------------------------- exceptions


def _valid_args(N=4, C=1) -> dict[str, Any]:
    means, quats, scales, opac, colors = random_scene(N, seed=0)
    means = means + torch.tensor([0.0, 0.0, 3.0])
    viewmats, Ks = pinhole(8, 8, 8.0, C=C)
    return dict(
        means=means,
        quats=quats,
        scales=scales,
        opacities=opac,
        colors=colors,
        viewmats=viewmats,
        Ks=Ks,
        width=8,
        height=8,
    )


@pytest.mark.parametrize(
    "override, match",
    [
        (dict(means=torch.zeros(4, 2)), "means"),
        (dict(means=torch.zeros(4)), "means"),
        (dict(quats=torch.zeros(3, 4)), "quats"),
        (dict(scales=torch.zeros(4, 3, 1)), "scales"),
        (dict(opacities=torch.zeros(4, 1)), "opacities"),
        (dict(colors=torch.zeros(5, 3)), "colors"),
        (dict(colors=torch.zeros(4, 16, 3)), "colors"),  # SH-shaped without sh_degree
        (dict(colors=torch.zeros(4, 3), sh_degree=1), "SH"),
        (dict(colors=torch.zeros(4, 2, 3), sh_degree=1), "K >= 4"),
        (dict(colors=torch.zeros(4, 25, 3), sh_degree=5), "sh_degree"),
        (dict(viewmats=torch.eye(4)), "viewmats"),
        (dict(Ks=torch.eye(3).repeat(2, 1, 1)), "Ks"),
        (dict(width=0), "width"),
        (dict(height=7.5), "width and height"),
        (dict(backgrounds=torch.zeros(1, 4)), "backgrounds"),
        (dict(render_mode="RGBD"), "render_mode"),
        (dict(backend="cuda"), "backend"),
        (dict(rasterize_mode="mip"), "rasterize_mode"),
        (dict(backend="gsplat"), "CUDA"),
        (dict(absgrad=True), "absgrad"),
        (dict(absgrad=True, backend="torch"), "gsplat's CUDA backward"),
    ],
)
def test_bad_inputs_raise(override, match):
    args = _valid_args()
    args.update(override)
    with pytest.raises(ValueError, match=match):
        rasterize(**args)


# ----------------------------------------------------------------------------------------------- extremes


def test_extremes_are_finite():
    """Tiny (1e-6) and huge (1e3) scales, Gaussians behind the camera, at z = 0, at and just past the near plane,
    at a grazing angle outside the clipped field of view, fully opaque: no NaN/inf in outputs or gradients."""
    W = H = 16
    viewmats, Ks = pinhole(W, H, 16.0)
    means = torch.tensor(
        [
            [0.0, 0.0, 2.0],  # tiny
            [0.3, 0.1, 3.0],  # huge
            [0.0, 0.0, -1.0],  # behind
            [0.0, 0.0, 0.0],  # at the camera centre
            [0.0, 0.0, 0.01],  # exactly at the near plane (kept by gsplat)
            [0.0, 0.0, 0.0100001],  # just past it
            [50.0, 0.0, 1.0],  # far outside the field of view
            [0.1, -0.1, 1e4],  # very far
        ]
    )
    N = means.shape[0]
    scales = torch.tensor([[1e-6] * 3, [1e3] * 3] + [[0.05, 0.02, 0.1]] * (N - 2))
    quats = torch.randn(N, 4, generator=torch.Generator().manual_seed(0))
    opac = torch.tensor([0.9, 0.5, 0.9, 0.9, 0.999, 0.9, 0.9, 0.9])
    colors = torch.rand(N, 3, generator=torch.Generator().manual_seed(1))
    for mode in ("classic", "antialiased"):
        params = [t.clone().requires_grad_(True) for t in (means, quats, scales, opac, colors)]
        render, alpha, meta = rasterize_p(params, viewmats, Ks, W, H, render_mode="RGB+ED", rasterize_mode=mode)
        assert torch.isfinite(render).all() and torch.isfinite(alpha).all()
        assert meta["radii"][0, 2] == 0 and meta["radii"][0, 3] == 0  # behind / at the camera: culled
        assert meta["radii"][0, 1] > 0 and meta["radii"][0, 4] > 0
        assert meta["n_pairs"] > 0
        meta["means2d"].retain_grad()
        (render.square().sum() + alpha.sum()).backward()
        grads = [p.grad for p in params] + [meta["means2d"].grad]
        for name, g in zip(["means", "quats", "scales", "opacities", "colors", "means2d"], grads, strict=True):
            assert g is not None and torch.isfinite(g).all(), (mode, name)
        assert grads[0] is not None and grads[0][1].abs().sum() > 0  # the huge Gaussian gets a gradient


# ----------------------------------------------------------------------------------------------- densification


def test_default_strategy_accepts_meta():
    """gsplat's DefaultStrategy, driven exactly like splatfacto (packed=False): grad2d / count accumulate for the
    visible Gaussians only, then a refine step duplicates the small ones and splits the large ones."""
    from gsplat.strategy import DefaultStrategy

    torch.manual_seed(0)
    N, W, H = 60, 24, 24
    means, quats, scales, opac, colors = random_scene(N, seed=7, scale=(0.01, 0.3))
    means[:, 2] += 3.0
    means[0] = torch.tensor([0.0, 0.0, -3.0])  # behind the camera: never visible
    params = torch.nn.ParameterDict(
        {
            "means": means,
            "scales": torch.log(scales),
            "quats": quats,
            "opacities": torch.logit(opac),
            "colors": colors,
        }
    )
    optimizers: dict[str, torch.optim.Optimizer] = {
        k: torch.optim.Adam([{"params": p, "lr": 1e-3, "name": k}]) for k, p in params.items()
    }
    strategy = DefaultStrategy(
        refine_start_iter=0, refine_every=2, grow_grad2d=1e-12, grow_scale3d=0.08, prune_opa=0.0, reset_every=10_000
    )
    strategy.check_sanity(params, optimizers)
    state = strategy.initialize_state(scene_scale=1.0)
    viewmats, Ks = pinhole(W, H, 24.0)
    target = torch.rand(1, H, W, 3)
    for step in (1, 2):
        render, alpha, info = rasterize(
            params["means"],
            params["quats"],
            torch.exp(params["scales"]),
            torch.sigmoid(params["opacities"]),
            params["colors"],
            viewmats,
            Ks,
            W,
            H,
            packed=False,
        )
        strategy.step_pre_backward(params, optimizers, state, step, info)
        (render - target).square().mean().backward()
        grad2d = info["means2d"].grad
        assert grad2d is not None and grad2d.shape == (1, N, 2)
        visible = info["radii"][0] > 0
        if step == 1:
            strategy.step_post_backward(params, optimizers, state, step, info, packed=False)
            assert visible.sum() > N // 2 and not visible[0]
            torch.testing.assert_close(state["count"], visible.float())
            assert (state["grad2d"][visible] > 0).all() and (state["grad2d"][~visible] == 0).all()
            for opt in optimizers.values():
                opt.step()
                opt.zero_grad()
        else:
            is_small = torch.exp(params["scales"]).max(-1).values <= 0.08
            n_dupli = int((visible & is_small).sum())
            n_split = int((visible & ~is_small).sum())
            assert n_dupli > 0 and n_split > 0
            strategy.step_post_backward(params, optimizers, state, step, info, packed=False)
            # a duplicate adds one Gaussian, a split replaces one by two
            assert params["means"].shape[0] == N + n_dupli + n_split
            assert all(p.shape[0] == N + n_dupli + n_split for p in params.values())


def test_homogeneous_monomials_span_the_sh_basis():
    """The monomials of degree L and L-1 are what their exponents say, and a fixed matrix maps them onto the SH
    basis on the unit sphere (float64: to rounding)."""
    from willags_ns.render.sh import _monomial_exponents, eval_sh_bases, homogeneous_monomials, monomial_to_sh

    d = torch.nn.functional.normalize(torch.randn(300, 3, dtype=torch.float64), dim=-1)
    for degree in range(5):
        m = homogeneous_monomials(degree, d)
        exps = torch.tensor(_monomial_exponents(degree), dtype=torch.float64)
        assert m.shape == (300, (degree + 1) ** 2) and len(set(_monomial_exponents(degree))) == m.shape[1]
        torch.testing.assert_close(m, (d[:, None, :] ** exps).prod(-1))
        torch.testing.assert_close(m @ monomial_to_sh(degree), eval_sh_bases(degree, d), atol=1e-12, rtol=0)
    with pytest.raises(ValueError, match="sh_degree must be in"):
        homogeneous_monomials(5, d)
