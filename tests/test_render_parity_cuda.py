"""Parity of the pure-torch rasterizer (run on CPU) with gsplat 1.4.0's CUDA `rasterization()`.

Skipped without CUDA. Forward: max |torch - gsplat| / max |gsplat| <= 1e-4 for render and alpha; gradients of a
fixed random weighting of render and alpha w.r.t. means, quats, scales, opacities, colors (and the 2D means that
densification reads) <= 1e-3 in the same normalised max norm. Both sides compute in float32.

The worst cases print with:
    python tests/test_render_parity_cuda.py
"""

import math
from typing import Any

import pytest
import torch
import torch.nn.functional as F

from willags_ns.render import rasterize

FWD_TOL = 1e-4
GRAD_TOL = 1e-3
PARAMS = ("means", "quats", "scales", "opacities", "colors")


def _look_at_viewmats(C: int, radius: float = 5.0) -> torch.Tensor:
    mats = []
    for i in range(C):
        ang = 0.5 * i
        eye = torch.tensor([radius * math.sin(ang), 0.4 * i, -radius * math.cos(ang)])
        fwd = F.normalize(-eye, dim=0)
        right = F.normalize(torch.linalg.cross(torch.tensor([0.0, 1.0, 0.0]), fwd), dim=0)
        up = torch.linalg.cross(fwd, right)
        R = torch.stack([right, up, fwd])
        V = torch.eye(4)
        V[:3, :3] = R
        V[:3, 3] = -R @ eye
        mats.append(V)
    return torch.stack(mats)


def _intrinsics(C: int, W: int, H: int, f: float) -> torch.Tensor:
    K = torch.tensor([[f, 0.0, W / 2 + 0.3], [0.0, f * 1.05, H / 2 - 0.7], [0.0, 0.0, 1.0]])
    return K.repeat(C, 1, 1)


def make_case(name: str, seed: int = 0) -> dict:
    """Inputs (float32, CPU) and rasterize kwargs of one parity case."""
    g = torch.Generator().manual_seed(seed)

    def rand(*shape):
        return torch.rand(*shape, generator=g)

    W, H, C, N = 96, 72, 1, 3000
    kw: dict = {}
    spread, scale_lo, scale_hi, opa = 1.5, 0.005, 0.1, (0.05, 1.0)
    if name == "multi_cam_antialiased_ed":
        C, kw = 2, dict(rasterize_mode="antialiased", render_mode="RGB+ED")
    elif name == "sh3_per_camera_bg":
        C, kw = 2, dict(sh_degree=3)
    elif name == "dense_opaque":
        N, spread, scale_lo, scale_hi, opa = 6000, 0.8, 0.02, 0.2, (0.5, 1.0)
    means = (rand(N, 3) - 0.5) * 2 * spread
    quats = torch.randn(N, 4, generator=g)
    scales = torch.exp(math.log(scale_lo) + (math.log(scale_hi) - math.log(scale_lo)) * rand(N, 3))
    opacities = opa[0] + (opa[1] - opa[0]) * rand(N)
    colors = rand(N, 3)
    if name == "multi_cam_antialiased_ed":
        colors = rand(C, N, 3)
    if name == "sh3_per_camera_bg":
        colors = 0.4 * torch.randn(N, 16, 3, generator=g)
        kw["backgrounds"] = rand(C, 3)
    if name == "extremes":
        # the camera sits at z = -5 looking along +z (depth = z + 5)
        N = 8
        means = torch.tensor(
            [
                [0.0, 0.0, 0.0],  # tiny (scale 1e-6)
                [0.3, 0.1, 0.5],  # huge (scale 1e3)
                [0.0, 0.0, -9.0],  # behind the camera
                [0.0, 0.0, -5.0],  # at the camera centre
                [0.1, 0.0, -4.98],  # just past the near plane
                [40.0, 0.0, 0.0],  # off-screen
                [0.2, -0.1, -4.5],  # very close
                [-0.2, 0.1, 1e3],  # far
            ]
        )
        scales = torch.tensor([[1e-6] * 3, [1e3] * 3] + [[0.05, 0.02, 0.1]] * (N - 2))
        quats, opacities, colors = torch.randn(N, 4, generator=g), 0.2 + 0.79 * rand(N), rand(N, 3)
    viewmats = _look_at_viewmats(C)
    Ks = _intrinsics(C, W, H, f=0.9 * W)
    return dict(
        params=dict(means=means, quats=quats, scales=scales, opacities=opacities, colors=colors),
        viewmats=viewmats,
        Ks=Ks,
        width=W,
        height=H,
        kwargs=kw,
    )


CASES = ("random_rgb", "multi_cam_antialiased_ed", "sh3_per_camera_bg", "dense_opaque", "extremes")


def _run(case: dict, backend: str, device: str):
    params = {k: v.to(device).clone().requires_grad_(True) for k, v in case["params"].items()}
    kw: dict[str, Any] = {k: (v.to(device) if torch.is_tensor(v) else v) for k, v in case["kwargs"].items()}
    render, alpha, meta = rasterize(
        **params,
        viewmats=case["viewmats"].to(device),
        Ks=case["Ks"].to(device),
        width=case["width"],
        height=case["height"],
        backend=backend,
        packed=False,
        **kw,
    )
    meta["means2d"].retain_grad()
    g = torch.Generator().manual_seed(123)
    w_r = torch.randn(render.shape, generator=g).to(device)
    w_a = torch.randn(alpha.shape, generator=g).to(device)
    ((render * w_r).sum() + (alpha * w_a).sum()).backward()
    grads = {k: p.grad.detach().cpu() for k, p in params.items()}
    grads["means2d"] = meta["means2d"].grad.detach().cpu()
    return render.detach().cpu(), alpha.detach().cpu(), meta, grads


def _rel(a: torch.Tensor, b: torch.Tensor) -> float:
    """max |a - b| / max |b| over finite entries (0 when b vanishes everywhere)."""
    scale = b.abs().max().item() if b.numel() else 0.0
    return (a - b).abs().max().item() / scale if scale > 0 else float((a - b).abs().max().item() if a.numel() else 0.0)


def parity_report(cases=CASES, seed: int = 0, torch_device: str = "cpu") -> dict:
    """Worst-case relative errors, torch backend (on `torch_device`) vs gsplat (CUDA), per case:
    {case: {"render", "alpha", "means2d", "radii_mismatch", "grad_<param>", "pixels_off_1e-3", "n_pairs"}}."""
    out = {}
    for name in cases:
        case = make_case(name, seed)
        r_t, a_t, m_t, g_t = _run(case, "torch", torch_device)
        r_g, a_g, m_g, g_g = _run(case, "gsplat", "cuda")
        radii_t, radii_g = m_t["radii"].cpu(), m_g["radii"].cpu()
        vis = (radii_t > 0) & (radii_g > 0)
        rep = {
            "render": _rel(r_t, r_g),
            "alpha": _rel(a_t, a_g),
            "pixels_off_1e-3": int(((r_t - r_g).abs().amax(-1) > 1e-3).sum()),
            "radii_mismatch": int((radii_t != radii_g).sum()),
            "means2d": _rel(m_t["means2d"].detach().cpu()[vis], m_g["means2d"].detach().cpu()[vis]),
            "n_pairs": m_t["n_pairs"],
            "n_visible": int(vis.sum()),
        }
        for k in list(PARAMS) + ["means2d"]:
            gt, gg = g_t[k], g_g[k]
            if k == "means2d":
                gt, gg = gt[vis], gg[vis]
            rep[f"grad_{k}"] = _rel(gt, gg)
        out[name] = rep
    return out


@pytest.mark.cuda
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA for gsplat's rasterizer")
@pytest.mark.parametrize("name", CASES)
def test_torch_backend_matches_gsplat(name):
    rep = parity_report(cases=(name,))[name]
    assert rep["radii_mismatch"] == 0, rep
    assert rep["render"] <= FWD_TOL and rep["alpha"] <= FWD_TOL, rep
    assert rep["means2d"] <= FWD_TOL, rep
    for k in list(PARAMS) + ["means2d"]:
        assert math.isfinite(rep[f"grad_{k}"]) and rep[f"grad_{k}"] <= GRAD_TOL, (k, rep)


@pytest.mark.cuda
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_torch_backend_runs_on_cuda_tensors():
    """The torch backend is device-agnostic: on CUDA tensors it gives the CPU result."""
    case = make_case("random_rgb")
    r_cpu, a_cpu, _, g_cpu = _run(case, "torch", "cpu")
    r_gpu, a_gpu, _, g_gpu = _run(case, "torch", "cuda")
    assert _rel(r_gpu, r_cpu) <= FWD_TOL and _rel(a_gpu, a_cpu) <= FWD_TOL
    for k in PARAMS:
        assert _rel(g_gpu[k], g_cpu[k]) <= GRAD_TOL, k


if __name__ == "__main__":
    import json

    print(json.dumps(parity_report(), indent=1))


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA (gsplat's fused SH kernel)")
@pytest.mark.parametrize("degree", [0, 1, 2, 3])
def test_sh_cuda_dispatch_matches_torch_sh(degree):
    """willags_ns.render.sh.spherical_harmonics on CUDA float32 runs gsplat's fused kernel: same colours and
    gradients (coefficients and directions) as the torch version, directions not unit length."""
    from willags_ns.render import sh as sh_mod

    g = torch.Generator().manual_seed(degree)
    dirs = (torch.randn(4096, 3, generator=g) * 3.0).double()
    coeffs = torch.randn(4096, 16, 3, generator=g).double()
    w = torch.randn(4096, 3, generator=g).double()
    ref_d, ref_c = dirs.clone().requires_grad_(), coeffs.clone().requires_grad_()
    ref = sh_mod.spherical_harmonics(degree, ref_d, ref_c)  # float64: the torch path
    (ref * w).sum().backward()
    d = dirs.float().cuda().requires_grad_()
    c = coeffs.float().cuda().requires_grad_()
    out = sh_mod.spherical_harmonics(degree, d, c)
    assert sh_mod._gsplat_sh() is not None
    (out * w.float().cuda()).sum().backward()
    assert torch.allclose(out.double().cpu(), ref.detach(), atol=1e-4, rtol=1e-4)
    assert torch.allclose(c.grad.double().cpu(), ref_c.grad, atol=1e-4, rtol=1e-4)
    if degree > 0:
        assert torch.allclose(d.grad.double().cpu(), ref_d.grad, atol=1e-3, rtol=1e-3)
