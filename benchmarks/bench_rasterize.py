"""Rasterizer benchmark: forward and forward+backward time of `willags_ns.render.rasterize` per backend.

Scene (a stand-in for a trained 3DGS scene seen from one camera): N Gaussians placed uniformly in the view frustum
(pixel position uniform over the image, camera depth uniform in [2, 6]), per-axis scales log-uniform in
[0.005, 0.05] world units, random rotations, opacities uniform in [0.05, 1], RGB colours; one pinhole camera with
fx = fy = image width (about 53 degrees field of view), principal point at the centre. A Gaussian of scale 0.02
at depth 4 then covers about 0.6 px sigma at 128 px (plus gsplat's 0.3 px^2 blur), i.e. a few pixels, as in
trained scenes. The loss for the backward is a fixed random weighting of render and alpha.

Prints a markdown table for N in {5k, 20k, 100k} x {64^2, 128^2, 256^2}: median time of the forward and of
forward+backward, and the number of Gaussian-pixel pairs composited (torch backend). gsplat is timed only when
CUDA is available. CPU threads are fixed to 2 (the project's CPU budget; `--threads` changes it). On a shared
machine, other processes' load inflates the median of a 2-thread run (a descheduled OpenMP thread stalls every
parallel op); the min column is the less disturbed figure.

Usage:
    python -m benchmarks rasterize            # full grid
    python -m benchmarks rasterize --quick    # fewer repeats, skips the 100k x 256^2 cell
    python -m benchmarks rasterize --profile  # torch.profiler table for 20k @ 128^2 (torch backend)
"""

import argparse
import math
import statistics
import time

import torch

from willags_ns.render import rasterize


def make_scene(n: int, size: int, device: str = "cpu", seed: int = 0):
    """The benchmark scene above: (means, quats, scales, opacities, colors, viewmats, Ks)."""
    g = torch.Generator().manual_seed(seed)
    f = float(size)
    z = 2.0 + 4.0 * torch.rand(n, generator=g)
    u = torch.rand(n, generator=g) * size
    v = torch.rand(n, generator=g) * size
    means = torch.stack([(u - size / 2) * z / f, (v - size / 2) * z / f, z], dim=-1)
    quats = torch.randn(n, 4, generator=g)
    scales = torch.exp(math.log(0.005) + (math.log(0.05) - math.log(0.005)) * torch.rand(n, 3, generator=g))
    opacities = 0.05 + 0.95 * torch.rand(n, generator=g)
    colors = torch.rand(n, 3, generator=g)
    viewmats = torch.eye(4)[None]
    Ks = torch.tensor([[f, 0.0, size / 2], [0.0, f, size / 2], [0.0, 0.0, 1.0]])[None]
    out = [means, quats, scales, opacities, colors, viewmats, Ks]
    return [t.to(device) for t in out]


def _sync(device: str) -> None:
    if device == "cuda":
        torch.cuda.synchronize()


def time_backend(backend: str, n: int, size: int, repeats: int, device: str) -> dict:
    """Median forward and forward+backward seconds, and the pair count (torch backend)."""
    means, quats, scales, opacities, colors, viewmats, Ks = make_scene(n, size, device)
    params = [means, quats, scales, opacities, colors]
    for p in params:
        p.requires_grad_(True)
    g = torch.Generator().manual_seed(1)
    w_render = torch.randn(1, size, size, 3, generator=g).to(device)
    w_alpha = torch.randn(1, size, size, 1, generator=g).to(device)

    def forward():
        return rasterize(means, quats, scales, opacities, colors, viewmats, Ks, size, size, backend=backend)

    fwd, fwd_bwd, pairs = [], [], None
    for i in range(repeats + 1):  # first run is a warm-up
        _sync(device)
        t0 = time.perf_counter()
        render, alpha, meta = forward()
        _sync(device)
        t1 = time.perf_counter()
        loss = (render * w_render).sum() + (alpha * w_alpha).sum()
        loss.backward()
        _sync(device)
        t2 = time.perf_counter()
        for p in params:
            p.grad = None
        if i > 0:
            fwd.append(t1 - t0)
            fwd_bwd.append(t2 - t0)
        pairs = meta.get("n_pairs")
    return {
        "fwd": statistics.median(fwd),
        "fwd_bwd": statistics.median(fwd_bwd),
        "fwd_min": min(fwd),
        "fwd_bwd_min": min(fwd_bwd),
        "pairs": pairs,
    }


def profile(n: int = 20_000, size: int = 128) -> None:
    """torch.profiler table (self CPU time) of one torch-backend forward+backward."""
    from torch.profiler import ProfilerActivity
    from torch.profiler import profile as tprofile

    means, quats, scales, opacities, colors, viewmats, Ks = make_scene(n, size)
    for t in (means, quats, scales, opacities, colors):
        t.requires_grad_(True)
    args = (means, quats, scales, opacities, colors, viewmats, Ks, size, size)
    for _ in range(2):
        render, alpha, _ = rasterize(*args, backend="torch")
        (render.sum() + alpha.sum()).backward()
    with tprofile(activities=[ProfilerActivity.CPU]) as prof:
        render, alpha, _ = rasterize(*args, backend="torch")
        (render.sum() + alpha.sum()).backward()
    print(prof.key_averages().table(sort_by="self_cpu_time_total", row_limit=30))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--quick", action="store_true", help="fewer repeats, skip 100k @ 256^2")
    parser.add_argument("--profile", action="store_true", help="profile the torch backend at 20k @ 128^2")
    parser.add_argument("--threads", type=int, default=2)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    if args.profile:
        profile()
        return
    backends = [("torch", "cpu")] + ([("gsplat", "cuda")] if torch.cuda.is_available() else [])
    repeats = 3 if args.quick else 7
    print(f"torch {torch.__version__}, {torch.get_num_threads()} CPU threads, repeats={repeats} (median)\n")
    print("| N | image | backend | pairs | forward ms, median (min) | forward+backward ms, median (min) |")
    print("|---:|---:|---|---:|---:|---:|")
    for n in (5_000, 20_000, 100_000):
        for size in (64, 128, 256):
            if args.quick and n == 100_000 and size == 256:
                continue
            for backend, device in backends:
                r = time_backend(backend, n, size, repeats, device)
                pairs = f"{r['pairs']:,}" if r["pairs"] is not None else "-"
                fwd = f"{1e3 * r['fwd']:.1f} ({1e3 * r['fwd_min']:.1f})"
                fwd_bwd = f"{1e3 * r['fwd_bwd']:.1f} ({1e3 * r['fwd_bwd_min']:.1f})"
                print(f"| {n:,} | {size}x{size} | {backend} | {pairs} | {fwd} | {fwd_bwd} |", flush=True)


if __name__ == "__main__":
    main()
