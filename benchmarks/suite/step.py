"""The GPU suite's ``--step`` and ``--memory`` sections: train-step time per variant, peak VRAM, host syncs,
and the per-component profile (event regions) and kernel table (torch.profiler) that say where a step goes."""

import contextlib
import gc
import statistics
import time
import traceback
from collections import defaultdict

import torch

from benchmarks import _synthetic_gaussians as syn
from benchmarks.suite.models import STEP0, VARIANTS, build_model, make_camera, train_step
from benchmarks.suite.timing import RegionTimer, Stamp, count_host_syncs, log, short_exc, sync


def install_profile(model, timer: RegionTimer, is_willags: bool) -> list:
    """Wrap the model's components with event regions (instance attributes; returns an undo list)."""
    undo = []

    def wrap(obj, name, label, on_enter=None, on_exit=None):
        orig = getattr(obj, name)

        def f(*a, **k):
            with timer.region(label):
                if on_enter:
                    on_enter()
                try:
                    return orig(*a, **k)
                finally:
                    if on_exit:
                        on_exit()

        setattr(obj, name, f)
        undo.append((obj, name))

    wrap(model, "get_outputs", "get_outputs (incl.)")
    wrap(model, "get_loss_dict", "get_loss_dict (incl.)")
    if is_willags:
        nets = model.appearance_nets
        wrap(model, "_rasterize", "rasterize")
        if nets is not None:
            if nets.vae is not None:
                wrap(nets.vae, "encode", "VAE encode")
                wrap(nets.vae, "decode", "VAE decode (loss)")
            if nets.field is not None:
                wrap(nets.field, "planes", "hypernetwork planes")
                wrap(nets.field, "query", "tri-plane query (incl.)")
                wrap(nets.field.mlp, "forward", "field MLP")
            if nets.color is not None:
                wrap(nets.color, "forward", "decoder MLP")
            if nets.modulation is not None:  # SH evaluation + local residual + colour transform of the student
                wrap(model, "appearance_colors", "appearance colours (SH + modulation)")
        if model.teacher is not None:

            def enter():
                timer.suspended = True

            def leave():
                timer.suspended = False

            # the label's region opens before `enter` and closes after `leave`: it is recorded, its inside is not
            wrap(model, "render_teacher", "teacher render", enter, leave)
        if model.perceptual is not None:
            wrap(model, "step_static_mask", "VGG + mask")
    else:
        from nerfstudio.models import splatfacto as sf

        orig = sf.rasterization

        def timed(*a, **k):
            with timer.region("rasterize"):
                return orig(*a, **k)

        sf.rasterization = timed
        undo.append((sf, "rasterization", orig))
        if hasattr(model, "_rasterize"):
            wrap(model, "_rasterize", "rasterize")
    return undo


def _allocator_counts(cuda: bool) -> dict[str, int]:
    """The caching allocator's device allocations, frees and retries so far (CUDA; empty elsewhere)."""
    if not cuda:
        return {}
    st = torch.cuda.memory_stats()
    keys = ("num_device_alloc", "num_device_free", "num_alloc_retries", "num_sync_all_streams")
    return {k: int(st.get(k, 0)) for k in keys}


def kernel_profile(run_step, iters: int, top: int = 25) -> dict:
    """torch.profiler over `iters` calls of run_step(): device (kernel + copy) time per step, the kernels that take
    it (ms and launches per step) and the busy share of the wall time. Busy well below the wall time means the
    step waits on the host (launch-bound); the kernel list says where device time goes."""
    from torch.profiler import ProfilerActivity, profile

    torch.cuda.synchronize()
    with profile(activities=[ProfilerActivity.CPU, ProfilerActivity.CUDA]) as prof:
        t0 = time.perf_counter()
        for _ in range(iters):
            run_step()
        torch.cuda.synchronize()
        wall = (time.perf_counter() - t0) * 1e3 / iters
    rows = []
    for e in prof.key_averages():
        if e.device_type != torch.autograd.DeviceType.CUDA:
            continue
        us = getattr(e, "self_device_time_total", None)
        us = e.self_cuda_time_total if us is None else us
        rows.append((e.key[:120], us / 1e3 / iters, e.count / iters))
    rows.sort(key=lambda r: -r[1])
    busy = sum(r[1] for r in rows)
    return {
        "iters": iters,
        "device_busy_ms_per_step": busy,
        "wall_ms_per_step_profiled": wall,
        "launches_per_step": sum(r[2] for r in rows),
        "top_kernels": [(k, round(ms, 4), round(n, 2)) for k, ms, n in rows[:top]],
    }


def remove_profile(undo: list) -> None:
    for item in reversed(undo):
        if len(item) == 3:
            setattr(item[0], item[1], item[2])
        else:
            obj, name = item
            with contextlib.suppress(AttributeError):
                delattr(obj, name)  # back to the class attribute


def profile_table(totals: dict, steps: int, step_ms: float) -> list[tuple[str, float]]:
    """Exclusive ms per step per component, 'other' = the rest of the step."""
    t = {k: v / steps for k, v in totals.items()}
    rows = []
    for k in ("VAE encode", "hypernetwork planes"):
        if k in t:
            rows.append((k, t[k]))
    if "tri-plane query (incl.)" in t:
        rows.append(("tri-plane sampling (grid_sample)", t["tri-plane query (incl.)"] - t.get("field MLP", 0.0)))
        rows.append(("field MLP (planes -> f_d)", t.get("field MLP", 0.0)))
    for k in ("decoder MLP", "appearance colours (SH + modulation)", "rasterize", "teacher render"):
        if k in t:
            rows.append((k, t[k]))
    fwd_known = sum(
        t.get(k, 0.0)
        for k in (
            "VAE encode",
            "hypernetwork planes",
            "tri-plane query (incl.)",
            "decoder MLP",
            "appearance colours (SH + modulation)",
            "rasterize",
            "teacher render",
        )
    )
    rows.append(("forward, rest", t.get("get_outputs (incl.)", 0.0) - fwd_known))
    if "VGG + mask" in t:
        rows.append(("VGG + mask", t["VGG + mask"]))
    if "VAE decode (loss)" in t:
        rows.append(("VAE decode (loss)", t["VAE decode (loss)"]))
    rows.append(
        (
            "loss (L1 + SSIM + rest)",
            t.get("get_loss_dict (incl.)", 0.0) - t.get("VGG + mask", 0) - t.get("VAE decode (loss)", 0),
        )
    )
    for k in ("metrics", "backward", "optimizer", "strategy (grad stats)", "teacher EMA"):
        if k in t:
            rows.append((k, t[k]))
    rows.append(("other (host gaps, glue)", step_ms - sum(v for _, v in rows)))
    return rows


def section_step(args, cuda: bool, dev, backend: str, variants: list[str], memory: bool, timing: bool) -> dict:
    n, size = args.n_gaussians, args.size
    seeds = syn.seed_points(n, seed=0)
    image = syn.smooth_image(size, size, seed=1).to(dev)  # uint8 [H, W, 3], as the datamanager caches it
    batch = {"image": image, "image_idx": 0}
    camera = make_camera(size, dev)
    results: dict[str, dict] = {}
    step = STEP0
    n_it = args.iters if timing else 4
    log(f"\n## train step: N={n:,} Gaussians, {size}x{size} px, backend {backend}")
    for v in variants:
        r: dict = {}
        results[v] = r
        need = 150.0 if "compile" in VARIANTS[v][2] and cuda else 0.0  # a compile is ~1-2 min and cannot be cut
        if time.perf_counter() + need > args.step_deadline:
            r["error"] = "skipped: time budget spent"
            log(f"{v}: skipped (time budget)")
            continue
        model = opts = None
        try:
            gc.collect()
            base = 0
            if cuda:
                torch.cuda.empty_cache()
                base = torch.cuda.memory_allocated()
            t0 = time.perf_counter()
            model, opts, is_w = build_model(v, seeds, args.n_train, dev, backend)
            r["build_s"] = time.perf_counter() - t0
            r["n_gaussians"] = int(model.num_points)
            t0 = time.perf_counter()
            for _ in range(args.warmup):  # also builds the lazy VGG, the Adam states, compiled graphs
                train_step(model, opts, camera, batch, step, is_w)
                step += 1
            sync(cuda)
            r["warmup_s"] = time.perf_counter() - t0
            if cuda:
                gc.collect()
                torch.cuda.reset_peak_memory_stats()
                r["static_gb"] = (torch.cuda.memory_allocated() - base) / 2**30  # params, Adam, caches
            # The mean, not the median, is the headline: with mask.every=k one step in k also renders the teacher
            # and runs VGG (iters is a multiple of 4), and the mean is what a training run pays per step. The peak
            # VRAM is taken over the same steps, so it includes a teacher step.
            spans = []
            host = []
            alloc0 = _allocator_counts(cuda)
            t0 = time.perf_counter()
            for _ in range(n_it):
                s = Stamp(cuda)
                h0 = time.perf_counter()
                train_step(model, opts, camera, batch, step, is_w)
                host.append((time.perf_counter() - h0) * 1e3)
                spans.append((s, Stamp(cuda)))
                step += 1
            sync(cuda)
            wall = (time.perf_counter() - t0) * 1e3 / n_it
            # host ms: the CPU's time in the step (launches, Python, and its waits at host syncs); cudaMalloc /
            # cudaFree calls of the caching allocator (a cudaFree waits for the device) per step
            r["host_ms_median"] = statistics.median(host)
            alloc1 = _allocator_counts(cuda)
            r["allocator_per_step"] = {k: (alloc1[k] - alloc0[k]) / n_it for k in alloc1}
            if timing:
                ms = [s.ms_until(e) for s, e in spans]
                r.update(step_ms=statistics.fmean(ms), step_ms_median=statistics.median(ms), step_ms_wall=wall)
                r.update(step_ms_min=min(ms), step_ms_max=max(ms))
            if memory and cuda:
                r["peak_gb"] = (torch.cuda.max_memory_allocated() - base) / 2**30
            if cuda and timing:
                sites: list[str] = []
                with count_host_syncs(cuda, sites):
                    for _ in range(4):
                        train_step(model, opts, camera, batch, step, is_w)
                        step += 1
                r["host_syncs_per_step"] = len(sites) / 4
                top: dict[str, int] = defaultdict(int)
                for s_ in sites:
                    top[s_] += 1
                r["host_sync_sites"] = [(k, c / 4) for k, c in sorted(top.items(), key=lambda kv: -kv[1])[:8]]
            # (compiled variants are not profiled: the event wrappers would enter the traced graph)
            if timing and args.profile and v in args.profile_variants and "compile" not in VARIANTS[v][2]:
                timer = RegionTimer(cuda)
                undo = install_profile(model, timer, is_w)
                try:
                    for _ in range(args.profile_iters):
                        train_step(model, opts, camera, batch, step, is_w, timer)
                        step += 1
                    totals = timer.collect()
                finally:
                    remove_profile(undo)
                r["profile_ms"] = profile_table(totals, args.profile_iters, r["step_ms"])
            if cuda and timing and v in args.kernel_variants:
                at = [step]

                def one_step(m=model, o=opts, w=is_w, at=at):
                    train_step(m, o, camera, batch, at[0], w)
                    at[0] += 1

                r["kernels"] = kernel_profile(one_step, 8)  # two mask steps of four at mask.every=4
                step = at[0]
            msg = f"{v}: " + ", ".join(
                f"{k}={r[k]:.2f}"
                for k in ("step_ms", "step_ms_median", "step_ms_wall", "host_ms_median", "peak_gb", "static_gb")
                if k in r
            )
            if "host_syncs_per_step" in r:
                msg += f", host syncs/step={r['host_syncs_per_step']:.2f}"
            if r.get("allocator_per_step"):
                msg += ", allocator/step " + " ".join(f"{k}={v:g}" for k, v in r["allocator_per_step"].items())
            log(msg + f" (build {r['build_s']:.1f}s, warm-up {r['warmup_s']:.1f}s)")
        except Exception as e:
            r["error"] = short_exc(e)
            r["traceback"] = traceback.format_exc()[-2000:]
            log(f"{v}: ERROR {r['error']}")
        finally:
            del model, opts
            gc.collect()
            if cuda:
                torch.cuda.empty_cache()
    # tables
    base_name = _baseline_name(results, "step_ms")
    if timing:
        log(f"\n| variant | step ms (mean) | median | wall ms/step | ratio vs {base_name} | host syncs/step |")
        log("|---|---|---|---|---|---|")
        for v, r in results.items():
            if "step_ms" not in r:
                log(f"| {v} | {r.get('error', 'n/a')} | | | | |")
                continue
            ratio = r["step_ms"] / results[base_name]["step_ms"] if base_name else float("nan")
            r["step_ratio_vs_baseline"] = ratio
            syncs = r.get("host_syncs_per_step")
            log(
                f"| {v} | {r['step_ms']:.2f} | {r['step_ms_median']:.2f} | {r['step_ms_wall']:.2f} | {ratio:.2f} "
                f"| {'-' if syncs is None else f'{syncs:.2f}'} |"
            )
        for v, r in results.items():
            if "profile_ms" in r:
                log(f"\n### profile {v} (mean ms per step, device events, {args.profile_iters} steps)")
                log("| component | ms | share |")
                log("|---|---|---|")
                for k, ms in r["profile_ms"]:
                    log(f"| {k} | {ms:.2f} | {100 * ms / r['step_ms']:.0f}% |")
            if "kernels" in r:
                kp = r["kernels"]
                log(
                    f"\n### kernels {v} (torch.profiler, {kp['iters']} steps): device busy "
                    f"{kp['device_busy_ms_per_step']:.2f} ms/step of {kp['wall_ms_per_step_profiled']:.2f} wall "
                    f"(profiled), {kp['launches_per_step']:.0f} device ops/step"
                )
                for k, ms, n in kp["top_kernels"]:
                    log(f"| {k} | {ms:.3f} ms | x{n:g} |")
            if r.get("host_sync_sites"):
                log(f"host-sync sites {v} (per step): " + "; ".join(f"{s} x{c:g}" for s, c in r["host_sync_sites"]))
    if memory and cuda:
        mb = _baseline_name(results, "peak_gb")
        log(f"\n| variant | static GB (params, Adam, caches) | peak GB ({n_it} train steps) | extra vs {mb} |")
        log("|---|---|---|---|")
        for v, r in results.items():
            if "peak_gb" in r:
                r["extra_vram_gb"] = r["peak_gb"] - results[mb]["peak_gb"] if mb else float("nan")
                log(f"| {v} | {r['static_gb']:.3f} | {r['peak_gb']:.3f} | {r['extra_vram_gb']:+.3f} |")
    return {"baseline": base_name, "variants": results}


def _baseline_name(results: dict, key: str) -> str | None:
    for name in ("splatfacto", "willags-3dgs"):
        if key in results.get(name, {}):
            return name
    return None
