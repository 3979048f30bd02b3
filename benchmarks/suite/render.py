"""The GPU suite's ``--render`` section: FPS of ``get_outputs`` with a fixed latent against the same Gaussians
through the rasteriser with colours precomputed, and against stock splatfacto."""

import gc
import time
import traceback

import torch

from benchmarks import _synthetic_gaussians as syn
from benchmarks.suite.models import STEP0, build_model, make_camera
from benchmarks.suite.timing import count_host_syncs, log, short_exc, sync


def section_render(args, cuda: bool, dev, backend: str) -> dict:
    from willags_ns.render import rasterize

    n, size, frames = args.n_gaussians, args.size, args.frames
    seeds = syn.seed_points(n, seed=0)
    c2ws = syn.orbit_c2ws(8)
    cams = [make_camera(size, dev, c) for c in c2ws]
    out: dict = {"frames": frames, "render_mode": "RGB+ED (what get_outputs renders in eval)"}
    log(f"\n## render: N={n:,}, {size}x{size} px, {frames} frames over 8 orbit views, fixed latent, no grad")

    def fps_of(render_one) -> float:
        with torch.no_grad():
            for i in range(3):
                render_one(i)
            sync(cuda)
            t0 = time.perf_counter()
            for i in range(frames):
                render_one(i)
            sync(cuda)
        return frames / (time.perf_counter() - t0)

    holder: list = []  # the model, dropped in `finally` so the baselines below get the memory back
    try:
        holder.append(build_model("willags", seeds, args.n_train, dev, backend)[0])
        model = holder[0]
        model.eval()
        nets = model.appearance_nets
        g = torch.Generator().manual_seed(3)
        model.render_latent = (0.5 * torch.randn(nets.latent_dim, generator=g)).to(dev)
        calls = {"planes": 0}
        if nets.field is not None:  # the default has no tri-plane field
            orig_planes = nets.field.planes

            def counted(*a, **k):
                calls["planes"] += 1
                return orig_planes(*a, **k)

            nets.field.planes = counted
        out["willags_fps"] = fps_of(lambda i: model.get_outputs(cams[i % 8]))
        out["hypernetwork_calls"] = calls["planes"]  # 1 when the f_d cache holds across frames
        # the decoder every frame (render_sh_degree=-1) vs the per-appearance SH bake (default), and the bake's cost
        deg = model.config.render_sh_degree
        model.config.render_sh_degree = -1
        out["willags_exact_fps"] = fps_of(lambda i: model.get_outputs(cams[i % 8]))
        model.config.render_sh_degree = deg
        if deg >= 0:
            model.color_path.sh_cache = None
            sync(cuda)
            t_b = time.perf_counter()
            with torch.no_grad():
                model.get_outputs(cams[0])
            sync(cuda)
            out["sh_bake_ms"] = 1e3 * (time.perf_counter() - t_b)
        sites: list[str] = []
        with count_host_syncs(cuda, sites), torch.no_grad():
            model.get_outputs(cams[0])
        out["host_syncs_per_frame"] = len(sites)

        # the same Gaussians through gsplat, colours precomputed once (what an exported splat viewer does)
        with torch.no_grad():
            z = model.render_latent
            cam0 = cams[0]
            c2w0 = cam0.camera_to_worlds
            colors = model.appearance_colors(z, model.means, model.intrinsic_features, c2w0[0, :3, 3]).rgb.contiguous()
            means, quats = model.means.contiguous(), model.quats.contiguous()
            scales = torch.exp(model.scales).contiguous()
            opac = torch.sigmoid(model.opacities).squeeze(-1).contiguous()
            from willags_ns.render.camera import viewmat_from_c2w

            vms = [viewmat_from_c2w(c.camera_to_worlds) for c in cams]
            Ks = [c.get_intrinsics_matrices().to(dev) for c in cams]
        for mode in ("RGB+ED", "RGB"):
            out[f"precomputed_fps_{mode}"] = fps_of(
                lambda i, mode=mode: rasterize(
                    means,
                    quats,
                    scales,
                    opac,
                    colors,
                    vms[i % 8],
                    Ks[i % 8],
                    size,
                    size,
                    render_mode=mode,
                    backend=backend,
                )
            )
        # per-frame appearance work alone (f_d cached): what render_sh_degree=-1 pays every frame
        f_s = model.intrinsic_features
        centers = [c.camera_to_worlds[0, :3, 3] for c in cams]
        out["decoder_only_ms"] = 1e3 / fps_of(
            lambda i: model.appearance_colors(z, model.means, f_s, centers[i % 8], cacheable=True)
        )
        out["render_fps_ratio_vs_gsplat"] = out["willags_fps"] / out["precomputed_fps_RGB+ED"]
        out["baseline_backend"] = backend
    except Exception as e:
        out["error"] = short_exc(e)
        out["traceback"] = traceback.format_exc()[-2000:]
    finally:
        holder.clear()
        gc.collect()
        if cuda:
            torch.cuda.empty_cache()
    for v in ("willags-3dgs", "splatfacto"):
        m = None
        try:
            m, _, _ = build_model(v, seeds, args.n_train, dev, backend)
            m.eval()
            m.step = STEP0  # SH degree 3
            out[f"{v}_fps"] = fps_of(lambda i, m=m: m.get_outputs(cams[i % 8]))
        except Exception as e:
            out[f"{v}_error"] = short_exc(e)
        finally:
            del m
            gc.collect()
            if cuda:
                torch.cuda.empty_cache()
    if "willags_fps" in out and "splatfacto_fps" in out:
        out["render_fps_ratio_vs_splatfacto"] = out["willags_fps"] / out["splatfacto_fps"]
    log("| renderer | FPS | note |")
    log("|---|---|---|")
    for k, note in (
        (
            "willags_fps",
            f"get_outputs, fixed latent (hypernetwork calls: {out.get('hypernetwork_calls', '?')}); decoder baked to SH once per appearance ({out.get('sh_bake_ms', float('nan')):.0f} ms)",
        ),
        ("willags_exact_fps", "get_outputs, fixed latent, decoder every frame (render_sh_degree=-1)"),
        ("precomputed_fps_RGB+ED", f"rasterize ({backend}), same Gaussians, colours precomputed: the baseline"),
        ("precomputed_fps_RGB", "same, RGB only"),
        ("willags-3dgs_fps", "get_outputs with SH degree 3 (same code path)"),
        ("splatfacto_fps", "stock splatfacto get_outputs"),
    ):
        if k in out:
            log(f"| {k} | {out[k]:.1f} | {note} |")
    if "decoder_only_ms" in out:
        log(
            f"decoder per frame: {out['decoder_only_ms']:.2f} ms; host syncs per frame: {out.get('host_syncs_per_frame')}"
        )
    if "render_fps_ratio_vs_gsplat" in out:
        log(f"render_fps_ratio_vs_gsplat = {out['render_fps_ratio_vs_gsplat']:.3f} (goal >= 0.9)")
    for k in [k for k in out if k.endswith("error")]:
        log(f"{k}: {out[k]}")
    return out
