"""Timing tools of the GPU suite: device-timeline stamps, per-label region timers, a median-of-calls bench, the
host-sync counter, the environment description and the device's copy / matmul ceilings."""

import contextlib
import platform
import statistics
import time
import warnings
from collections import defaultdict
from pathlib import Path

import torch

REPO = Path(__file__).resolve().parents[2]


def log(*a) -> None:
    print(*a, flush=True)


def short_exc(e: BaseException) -> str:
    return f"{type(e).__name__}: {e}".strip()[:400]


# ------------------------------------------------------------------------------------------------- timing tools
class Stamp:
    """A point in time on the device's timeline: a CUDA event (no host sync when taken), else perf_counter."""

    def __init__(self, cuda: bool):
        self.cuda = cuda
        if cuda:
            self.ev = torch.cuda.Event(enable_timing=True)
            self.ev.record()
        else:
            self.t = time.perf_counter()

    def ms_until(self, other: "Stamp") -> float:
        return self.ev.elapsed_time(other.ev) if self.cuda else 1e3 * (other.t - self.t)


def sync(cuda: bool) -> None:
    if cuda:
        torch.cuda.synchronize()


class RegionTimer:
    """Accumulates device time per label; regions are closed lazily (one sync at `collect`)."""

    def __init__(self, cuda: bool):
        self.cuda = cuda
        self.pending: list[tuple[str, Stamp, Stamp]] = []
        self.totals: dict[str, float] = defaultdict(float)
        self.suspended = False  # True inside the teacher render: its inner calls belong to it

    @contextlib.contextmanager
    def region(self, label: str):
        if self.suspended:
            yield
            return
        s = Stamp(self.cuda)
        try:
            yield
        finally:
            self.pending.append((label, s, Stamp(self.cuda)))

    def collect(self) -> dict[str, float]:
        sync(self.cuda)
        for label, s, e in self.pending:
            self.totals[label] += s.ms_until(e)
        self.pending.clear()
        return dict(self.totals)


def bench_fn(fn, cuda: bool, warmup: int, iters: int) -> float:
    """Median ms of `fn()` (device events around each call, after `warmup` calls)."""
    for _ in range(warmup):
        fn()
    sync(cuda)
    spans = []
    for _ in range(iters):
        s = Stamp(cuda)
        fn()
        spans.append((s, Stamp(cuda)))
    sync(cuda)
    return statistics.median(s.ms_until(e) for s, e in spans)


@contextlib.contextmanager
def count_host_syncs(cuda: bool, sink: list):
    """Record (file:line) of every synchronising CUDA call made inside (torch's sync debug mode)."""
    if not cuda or not hasattr(torch.cuda, "set_sync_debug_mode"):
        yield
        return
    with warnings.catch_warnings(record=True) as rec:
        warnings.simplefilter("always")
        torch.cuda.set_sync_debug_mode("warn")
        try:
            yield
        finally:
            torch.cuda.set_sync_debug_mode(0)
    for w in rec:
        if "synchroniz" in str(w.message):
            f = str(w.filename)
            f = f[len(str(REPO)) + 1 :] if f.startswith(str(REPO)) else "/".join(Path(f).parts[-3:])
            sink.append(f"{f}:{w.lineno}")


# --------------------------------------------------------------------------------------------- environment info
def environment(cuda: bool) -> dict:
    info = {
        "device": torch.cuda.get_device_name(0) if cuda else f"cpu ({platform.processor() or platform.machine()})",
        "torch": torch.__version__,
        "python": platform.python_version(),
        "cuda": torch.version.cuda if cuda else None,
    }
    try:
        import gsplat

        info["gsplat"] = gsplat.__version__
    except Exception as e:
        info["gsplat"] = f"unavailable ({short_exc(e)})"
    try:
        from importlib.metadata import version

        import nerfstudio  # noqa: F401

        info["nerfstudio"] = version("nerfstudio")
    except Exception as e:
        info["nerfstudio"] = f"unavailable ({short_exc(e)})"
    if cuda:
        info["tf32_matmul"] = torch.backends.cuda.matmul.allow_tf32
        info["tf32_cudnn"] = torch.backends.cudnn.allow_tf32
    return info


def measure_ceilings(cuda: bool) -> dict:
    """Device-to-device copy bandwidth and matmul rates (fp32 as the trainer runs it, bf16), METHOD.md style."""
    if not cuda:
        return {}
    out = {}
    n = 256 * 2**20  # 1 GiB of float32
    src = torch.randn(n, device="cuda")
    dst = torch.empty_like(src)
    ms = bench_fn(lambda: dst.copy_(src), True, 3, 10)
    out["copy_GBps"] = 2 * n * 4 / ms / 1e6  # bytes read + bytes written
    for dt, name in ((torch.float32, "fp32"), (torch.bfloat16, "bf16")):
        m = 8192 if dt == torch.bfloat16 else 4096
        x = torch.randn(m, m, device="cuda", dtype=dt)  # random data: zeros run faster (METHOD.md)
        y = torch.randn(m, m, device="cuda", dtype=dt)
        ms = bench_fn(lambda x=x, y=y: x @ y, True, 3, 10)
        out[f"matmul_{name}_TFLOPs"] = 2 * m**3 / ms / 1e9
    return out
