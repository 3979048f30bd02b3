"""Make PyPI's torchvision importable next to a CPU-only torch.

Why: PyPI's torchvision 0.28.0 wheel is a CUDA build. Next to the CPU torch wheel its C++ extension
(`torchvision/_C.so`) cannot load, so the ops it would define (``torchvision::nms``...) do not exist, and
``import torchvision`` dies in ``torchvision/_meta_registrations.py``, which unconditionally calls
``torch.library.register_fake("torchvision::nms")`` (and ``qnms``) at import time::

    RuntimeError: operator torchvision::nms does not exist

nerfstudio's pipeline imports torchvision, so nothing of nerfstudio runs. The cure is to *define* the two op
schemas before torchvision's module body runs (``nms`` also gets a pure-torch CPU kernel, reachable as
``torch.ops.torchvision.nms``; ``torchvision.ops.*`` still refuse, since torchvision checks its extension
first). Everything nerfstudio uses of torchvision (models, transforms, utils) is pure Python.

How it is activated: ``python -m willags_ns.engine.tvshim install`` (run by ``make``) writes two files into the
environment's site-packages: ``_willags_tvshim.py`` (a copy of this file: it must not import willags_ns, whose
import may happen later or not at all) and ``willags-tvshim.pth``. The ``.pth`` only registers a tiny
``sys.meta_path`` finder, so interpreter start-up stays fast; the finder acts the first time ``torchvision``
is imported, and only when ``torch.version.cuda is None`` (a CPU torch) and torchvision's extension did not
load. With a CUDA torch (a GPU user's install) it does nothing. ``python -m willags_ns.engine.tvshim uninstall``
removes the two files.
"""

import importlib.abc
import os
import sys
import sysconfig
from pathlib import Path

_SCHEMAS = {
    "nms": "nms(Tensor dets, Tensor scores, float iou_threshold) -> Tensor",
    "qnms": "qnms(Tensor dets, Tensor scores, float iou_threshold) -> Tensor",
}
_LIB = None  # keeps the torch.library.Library alive: dropping it would unregister the schemas
_DONE = False


def _nms_cpu(dets, scores, iou_threshold):
    """Greedy non-maximum suppression, the same result as torchvision's C++ kernel. dets [N,4] xyxy, scores [N]."""
    import torch

    if dets.numel() == 0:
        return torch.empty(0, dtype=torch.long, device=dets.device)
    order = scores.argsort(descending=True)
    x1, y1, x2, y2 = dets.unbind(1)
    areas = (x2 - x1) * (y2 - y1)
    suppressed = torch.zeros(dets.shape[0], dtype=torch.bool)
    keep = []
    for i in order.tolist():
        if suppressed[i]:
            continue
        keep.append(i)
        xx1 = torch.maximum(x1[i], x1)
        yy1 = torch.maximum(y1[i], y1)
        xx2 = torch.minimum(x2[i], x2)
        yy2 = torch.minimum(y2[i], y2)
        inter = (xx2 - xx1).clamp(min=0) * (yy2 - yy1).clamp(min=0)
        iou = inter / (areas[i] + areas - inter)
        suppressed |= iou > iou_threshold
    return torch.tensor(keep, dtype=torch.long, device=dets.device)


def define_missing_ops() -> bool:
    """Define torchvision's missing op schemas when torch is a CPU build. Returns True when it defined them."""
    global _LIB, _DONE
    if _DONE:
        return _LIB is not None
    _DONE = True
    import torch

    if torch.version.cuda is not None:
        return False  # a CUDA torch loads torchvision's real extension: never interfere
    if hasattr(torch.ops, "torchvision") and _op_exists("nms"):
        return False  # a matching CPU torchvision already defined them
    lib = torch.library.Library("torchvision", "FRAGMENT")
    for name, schema in _SCHEMAS.items():
        if not _op_exists(name):
            lib.define(schema)
    lib.impl("nms", _nms_cpu, "CPU")
    _LIB = lib
    return True


def _op_exists(name: str) -> bool:
    import torch

    try:
        return torch._C._dispatch_has_kernel_for_dispatch_key(f"torchvision::{name}", "Meta") or bool(
            torch._C._get_operation_overload(f"torchvision::{name}", "")  # type: ignore[attr-defined]
        )
    except Exception:
        return False


class _Finder(importlib.abc.MetaPathFinder):
    """Runs define_missing_ops() the first time `torchvision` is imported, then steps aside."""

    def find_spec(self, fullname, path=None, target=None):
        if fullname == "torchvision":
            sys.meta_path[:] = [f for f in sys.meta_path if f is not self]
            try:
                define_missing_ops()
            except Exception as e:  # never break an unrelated program's start-up
                print(f"willags tvshim: could not define torchvision ops: {e}", file=sys.stderr)
        return None  # let the normal finders import torchvision


def activate() -> None:
    """Called by the installed .pth line at interpreter start-up (cheap: no torch import here)."""
    if os.environ.get("WILLAGS_TVSHIM", "1") == "0":
        return
    if "torchvision" in sys.modules:
        return
    sys.meta_path.insert(0, _Finder())


_PTH_NAME = "willags-tvshim.pth"
_MOD_NAME = "_willags_tvshim.py"


def _site_dir() -> Path:
    return Path(sysconfig.get_paths()["purelib"])


def install() -> Path:
    site = _site_dir()
    (site / _MOD_NAME).write_text(Path(__file__).read_text())
    (site / _PTH_NAME).write_text("import _willags_tvshim; _willags_tvshim.activate()\n")
    return site


def uninstall() -> None:
    for name in (_PTH_NAME, _MOD_NAME):
        (_site_dir() / name).unlink(missing_ok=True)


if __name__ == "__main__":
    cmd = sys.argv[1] if len(sys.argv) > 1 else "install"
    if cmd == "install":
        print(f"willags tvshim installed in {install()}")
    elif cmd == "uninstall":
        uninstall()
        print("willags tvshim removed")
    else:
        raise SystemExit(f"usage: python -m willags_ns.engine.tvshim [install|uninstall], got {cmd!r}")
