"""The GPU suite's ``--components`` section: isolated forward + backward timings of the appearance path and the
rasteriser, next to their FLOP / byte floors from the measured device ceilings."""

import torch

from benchmarks import _synthetic_gaussians as syn
from benchmarks.suite.models import _patch_knn, make_camera
from benchmarks.suite.timing import bench_fn, log, short_exc


def _vgg_flops(h: int, w: int) -> float:
    """Multiply-adds x2 of VGG16 features[:16] (conv1_1 .. conv3_3) on one h x w image."""
    from willags_ns.mask.transient import VGG16_CFG

    flops, c_in = 0.0, 3
    for v in VGG16_CFG:
        if v == "M":
            h, w = h // 2, w // 2
        else:
            flops += 2.0 * h * w * int(v) * c_in * 9
            c_in = int(v)
    return flops


def section_components(args, cuda: bool, dev, backend: str, ceilings: dict) -> dict:
    """Isolated fwd+bwd timings of the appearance path at N Gaussians, with FLOP / byte floors."""
    from willags_ns.appearance.decoder import ColorDecoder, ColorDecoderConfig
    from willags_ns.appearance.triplane import TriplaneConfig, TriplaneHyperField
    from willags_ns.mask.transient import PerceptualFeatures
    from willags_ns.render import rasterize

    n, size = args.n_gaussians, args.size
    tp, dc, latent_dim = TriplaneConfig(), ColorDecoderConfig(), 64
    field = TriplaneHyperField(
        latent_dim, tp.resolution, tp.channels, tuple(tp.hyper_hidden), tp.feature_dim, tp.mlp_hidden
    ).to(dev)
    dec = ColorDecoder(tp.feature_dim, 32, dc.hidden, dc.dir_sh_degree).to(dev)
    g = torch.Generator().manual_seed(5)
    z = torch.randn(latent_dim, generator=g).to(dev).requires_grad_(True)
    xyz = (torch.rand(n, 3, generator=g) * 2 - 1).to(dev).requires_grad_(True)
    f_s = torch.randn(n, 32, generator=g).to(dev).requires_grad_(True)
    dirs = torch.randn(n, 3, generator=g).to(dev)
    planes = field.planes(z).detach().requires_grad_(True)
    f_d = (0.1 * torch.randn(n, tp.feature_dim, generator=g)).to(dev).requires_grad_(True)
    w_it, it = (2, 5) if args.quick else (3, 10)

    def fb(fn, autocast: bool = False):
        def run():
            with torch.autocast(dev.type, dtype=torch.bfloat16, enabled=autocast):
                y = fn()
            y.float().sum().backward()

        return run

    def fwd(fn, autocast: bool = False):
        def run():
            with torch.no_grad(), torch.autocast(dev.type, dtype=torch.bfloat16, enabled=autocast):
                fn()

        return run

    d_in = tp.feature_dim + 32 + (dc.dir_sh_degree + 1) ** 2
    dec_macs = d_in * dc.hidden + dc.hidden * dc.hidden + dc.hidden * 3
    q_macs = 3 * tp.channels * tp.mlp_hidden + tp.mlp_hidden * tp.feature_dim + 3 * tp.channels * 4  # + bilinear taps
    plane_out = 3 * tp.channels * tp.resolution**2
    hyper_macs = (
        latent_dim * tp.hyper_hidden[0] + tp.hyper_hidden[0] * tp.hyper_hidden[1] + tp.hyper_hidden[1] * plane_out
    )
    # fewest bytes: inputs read once, outputs written once (fwd), + output grads read, input grads written (bwd)
    dec_bytes_fb = 4 * n * (2 * (tp.feature_dim + 32) + 3 + 3 + 3)
    q_bytes_fb = 4 * n * (3 + tp.feature_dim + tp.feature_dim + 3) + 2 * 4 * plane_out
    items = [
        (
            "hypernetwork planes fwd+bwd",
            fb(lambda: field.planes(z)),
            6 * hyper_macs,
            4 * 3 * tp.hyper_hidden[1] * plane_out,
        ),
        ("tri-plane query fwd+bwd fp32", fb(lambda: field.query(planes, xyz)), 6 * n * q_macs, q_bytes_fb),
        ("tri-plane query fwd+bwd bf16", fb(lambda: field.query(planes, xyz), True), 6 * n * q_macs, q_bytes_fb // 2),
        ("decoder MLP fwd+bwd fp32", fb(lambda: dec(f_d, f_s, dirs)), 6 * n * dec_macs, dec_bytes_fb),
        ("decoder MLP fwd+bwd bf16", fb(lambda: dec(f_d, f_s, dirs), True), 6 * n * dec_macs, dec_bytes_fb // 2),
        (
            "query + decoder fwd (teacher)",
            fwd(lambda: dec(field.query(planes, xyz), f_s, dirs)),
            2 * n * (q_macs + dec_macs),
            4 * n * (3 + 32 + 3 + 3),
        ),
        (
            "decoder fwd (per render frame)",
            fwd(lambda: dec(f_d, f_s, dirs)),
            2 * n * dec_macs,
            4 * n * (tp.feature_dim + 32 + 3 + 3),
        ),
        (
            "decoder fwd bf16 (per frame)",
            fwd(lambda: dec(f_d, f_s, dirs), True),
            2 * n * dec_macs,
            2 * n * (tp.feature_dim + 32 + 3 + 3),
        ),
    ]
    rows = []
    peak32 = ceilings.get("matmul_fp32_TFLOPs")
    peak16 = ceilings.get("matmul_bf16_TFLOPs")
    bw = ceilings.get("copy_GBps")
    for name, fn, flops, nbytes in items:
        row = {"name": name, "flops": flops, "bytes": nbytes}
        try:
            row["ms"] = bench_fn(fn, cuda, w_it, it)
            if peak32 and bw:
                peak = peak16 if "bf16" in name else peak32
                row["floor_ms"] = max(flops / (peak * 1e9), nbytes / (bw * 1e6))
        except Exception as e:
            row["error"] = short_exc(e)
        rows.append(row)
        for t in (z, xyz, f_s, planes, f_d):
            t.grad = None
        field.zero_grad(set_to_none=True)
        dec.zero_grad(set_to_none=True)
    # VGG on GT + teacher render at the mask's resolution
    try:
        pf = PerceptualFeatures(max_resolution=512)
        imgs = torch.rand(1, 3, size, size, generator=g).to(dev)
        side = min(size, 512)
        ms = bench_fn(lambda: (pf(imgs), pf(imgs)), cuda, w_it, it)
        rows.append(
            {
                "name": f"VGG16 relu1_2..3_3 x2 at {side}px (no grad)",
                "ms": ms,
                "flops": 2 * _vgg_flops(side, side),
                "bytes": 0,
            }
        )
    except Exception as e:
        rows.append({"name": "VGG16 x2", "error": short_exc(e)})
    # gsplat (or torch) rasterisation of the benchmark scene: fwd+bwd, plain colours and SH degree 3
    try:
        from nerfstudio.models.splatfacto import SplatfactoModel

        _patch_knn()
        xyz0, rgb0 = syn.seed_points(n, seed=0)
        d, _ = SplatfactoModel.k_nearest_sklearn(None, xyz0, 3)
        scales = torch.log(torch.from_numpy(d).mean(-1, keepdim=True).repeat(1, 3)).to(dev)
        torch.manual_seed(0)
        means = xyz0.to(dev).requires_grad_(True)
        quats = torch.nn.functional.normalize(torch.randn(n, 4), dim=-1).to(dev).requires_grad_(True)
        log_s = scales.clone().requires_grad_(True)
        opa = torch.full((n,), -2.197, device=dev).requires_grad_(True)  # logit(0.1), splatfacto's init
        col = (rgb0.float() / 255).to(dev).requires_grad_(True)
        sh = torch.zeros(n, 16, 3, device=dev)
        sh[:, 0] = (col.detach() - 0.5) / 0.28209479177387814
        sh.requires_grad_(True)
        from willags_ns.render.camera import viewmat_from_c2w

        cam = make_camera(size, dev)
        vm = viewmat_from_c2w(cam.camera_to_worlds)
        K = cam.get_intrinsics_matrices().to(dev)

        def rast(colors, shd):
            def run():
                r, a, _ = rasterize(
                    means,
                    quats,
                    torch.exp(log_s),
                    torch.sigmoid(opa),
                    colors,
                    vm,
                    K,
                    size,
                    size,
                    sh_degree=shd,
                    backend=backend,
                )
                (r.sum() + a.sum()).backward()

            return run

        rows.append({"name": f"rasterize fwd+bwd RGB ({backend})", "ms": bench_fn(rast(col, None), cuda, w_it, it)})
        rows.append({"name": f"rasterize fwd+bwd SH3 ({backend})", "ms": bench_fn(rast(sh, 3), cuda, w_it, it)})
    except Exception as e:
        rows.append({"name": "rasterize", "error": short_exc(e)})
    log(
        f"\n## components at N={n:,} ({size}px for image-space ones); floors from measured ceilings {ceilings or '(none: CPU)'}"
    )
    log("| component | ms | floor ms | GFLOP | min MB |")
    log("|---|---|---|---|---|")
    for r in rows:
        if "error" in r:
            log(f"| {r['name']} | ERROR {r['error']} | | | |")
            continue
        fl = f"{r['floor_ms']:.3f}" if "floor_ms" in r else "-"
        log(f"| {r['name']} | {r['ms']:.3f} | {fl} | {r.get('flops', 0) / 1e9:.2f} | {r.get('bytes', 0) / 1e6:.0f} |")
    return {"rows": rows}
