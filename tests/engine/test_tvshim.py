"""The torchvision shim: defines the op schemas only for a CPU torch, and makes torchvision importable."""

import subprocess
import sys

import torch

from willags_ns.engine import tvshim


def test_torchvision_imports_in_a_fresh_interpreter():
    # a fresh process: the installed .pth must act before anything else imports torchvision
    code = "import torchvision, torch; print(torchvision.__version__, torch.ops.torchvision.nms is not None)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=600)
    assert out.returncode == 0, out.stderr[-2000:]
    assert "True" in out.stdout


def test_nms_kernel_matches_greedy_definition():
    boxes = torch.tensor([[0, 0, 10, 10], [1, 1, 11, 11], [50, 50, 60, 60], [0, 0, 10, 9.0]])
    scores = torch.tensor([0.9, 0.8, 0.7, 0.95])
    keep = tvshim._nms_cpu(boxes, scores, 0.5)
    # box 3 (0.95) suppresses 0 and 1 (IoU > 0.5); box 2 is far away
    assert keep.tolist() == [3, 2]
    assert tvshim._nms_cpu(torch.zeros(0, 4), torch.zeros(0), 0.5).numel() == 0


def test_shim_is_inactive_with_a_cuda_torch(monkeypatch):
    monkeypatch.setattr(tvshim, "_DONE", False)
    monkeypatch.setattr(torch.version, "cuda", "12.4")
    assert tvshim.define_missing_ops() is False


def test_disabled_by_environment(monkeypatch):
    monkeypatch.setenv("WILLAGS_TVSHIM", "0")
    before = list(sys.meta_path)
    tvshim.activate()
    assert sys.meta_path == before
