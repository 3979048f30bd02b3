"""EMA teacher of the appearance networks (encoder, tri-plane hypernetwork field, colour decoder).

After each optimiser step ``W_T <- tau * W_T + (1 - tau) * W_S`` for every parameter; buffers are copied. The
teacher renders the training view with the *current* per-Gaussian tensors of the student (means, scales,
opacities, intrinsic features f_s, detached), so it follows densification and pruning for free: only the
fixed-shape appearance networks live in the teacher. Its render is what the perceptual transient mask compares
the ground truth against (``willags_ns.mask.transient``): a slowly moving average does not chase an occluder the
student has just started to fit, so the occluder keeps standing out.

State is explicit: the teacher is a plain ``nn.Module`` returned by :func:`make_teacher`, updated in place by
the pure :func:`ema_update_`; the model owns it and decides when to call the update.
"""

import copy
from dataclasses import dataclass

import torch
from torch import nn


@dataclass
class TeacherConfig:
    """EMA teacher settings."""

    tau: float = 0.99
    """EMA decay per optimiser step. The teacher averages over about 1 / (1 - tau) = 100 steps: short enough to
    track a 30k-step run (and a 2k-step CPU run, where 100 steps is 5% of training) without lagging the scene,
    long enough that an occluder fitted by the student over a handful of visits to one image is smoothed out.
    tau = 0.999 (1000 steps) would lag far behind a short run; tau = 0.9 (10 steps) follows the student's
    transient overfitting."""
    enabled: bool = True
    """Build and update a teacher; when False the student's own render is used for the mask (ablation)."""
    fused: bool = True
    """Render the teacher's colours as 3 extra channels of the student's rasterisation (same Gaussians, same
    camera) instead of a second rasterisation. Identical pseudo-GT and identical student gradients (the teacher
    channels are detached, so their share of every geometry gradient is zero); saves the teacher's projection,
    sorting and compositing (measured: docs/design.md, the model)."""


def make_teacher(student: nn.Module) -> nn.Module:
    """A frozen copy of ``student``: ``deepcopy``, ``requires_grad = False``, eval mode."""
    teacher = copy.deepcopy(student)
    teacher.requires_grad_(False)
    teacher.eval()
    return teacher


@torch.no_grad()
def ema_update_(teacher: nn.Module, student: nn.Module, tau: float) -> None:
    """In place: ``p_T <- tau * p_T + (1 - tau) * p_S`` for all parameters; buffers are copied from the student.

    ``tau = 0`` copies the student exactly, ``tau = 1`` leaves the teacher unchanged. Raises ``ValueError`` when
    the two modules' parameter or buffer names or shapes differ, or ``tau`` is outside [0, 1].
    Example: p_T = 0, p_S = 1, tau = 0.99 -> p_T = 0.01.
    """
    if not 0.0 <= tau <= 1.0:
        raise ValueError(f"tau must be in [0, 1], got {tau}")
    t_params = dict(teacher.named_parameters())
    s_params = dict(student.named_parameters())
    t_bufs = dict(teacher.named_buffers())
    s_bufs = dict(student.named_buffers())
    for kind, t, s in (("parameter", t_params, s_params), ("buffer", t_bufs, s_bufs)):
        if t.keys() != s.keys():
            raise ValueError(
                f"teacher/student {kind} names differ: only in teacher {sorted(t.keys() - s.keys())}, "
                f"only in student {sorted(s.keys() - t.keys())}"
            )
        for name in t:
            if t[name].shape != s[name].shape:
                raise ValueError(f"{kind} {name!r}: teacher {tuple(t[name].shape)} vs student {tuple(s[name].shape)}")
    if tau < 1.0:
        # lerp(T, S, w) = T + w * (S - T) = tau * T + (1 - tau) * S with w = 1 - tau (w = 1 copies). One fused
        # multi-tensor kernel per (device, dtype) instead of one launch per parameter: this runs after every step.
        groups: dict[tuple, tuple[list[torch.Tensor], list[torch.Tensor]]] = {}
        for name, p_t in t_params.items():
            g = groups.setdefault((p_t.device, p_t.dtype), ([], []))
            g[0].append(p_t)
            g[1].append(s_params[name].detach().to(p_t.dtype))
        for ts, ss in groups.values():
            torch._foreach_lerp_(ts, ss, 1.0 - tau)
    for name, b_t in t_bufs.items():
        b_t.copy_(s_bufs[name])
