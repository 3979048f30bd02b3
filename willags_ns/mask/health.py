"""Watches the transient mask for a feedback loop and says so while training.

What the mask drops gets no loss, so it renders worse; the teacher (an EMA of the student) then differs more from
the photo there, and the next mask drops more: the masked share climbs while the training PSNR falls, and the test
PSNR with it (the paper preset does this on south-building: docs/design.md). The default's safeguards (the inspector
drops the mask on clean scenes, the SfM-track support keeps long-track pixels in the loss) are switches a user can
turn off, and the paper preset has neither, so the loop is watched for wherever the mask runs.

Means over windows of training steps (each step is one photo, so single steps are noise): once a window's masked
share has risen by ``min_fraction_rise`` over the lowest window's *and* its training PSNR has fallen
``min_psnr_drop`` dB under the best window's, both within one regime (the same training resolution, no opacity
reset between: both move the PSNR by themselves), :class:`MaskHealth` returns one warning naming the numbers and
what to try. It warns; it changes nothing in the training. Beside it, the warning that a step's mask was rejected
(:meth:`MaskHealth.rejected`), rate-limited: the pipeline reads the rejection flag one step late.
"""

import time
from dataclasses import dataclass

import torch
from torch import Tensor

REJECTED_WARN_EVERY_S = 60.0
"""At most one 'mask rejected' warning per this many seconds (it is normal early in training)."""


@dataclass
class MaskHealthConfig:
    """When the mask's feedback loop is reported (``WillagsModelConfig.mask.health``)."""

    enabled: bool = True
    """Watch the masked share and the training PSNR while the mask runs, and warn once on a feedback loop."""
    window: int = 250
    """Training steps per window: the share and the PSNR are compared as means over this many steps."""
    min_fraction_rise: float = 0.05
    """The masked share (0-1) must rise at least this much above its lowest window's mean: below what a feedback
    loop adds within a few windows, above the few hundredths by which the share moves between windows on a scene
    with real transients (docs/design.md)."""
    min_psnr_drop: float = 1.5
    """... while the training PSNR falls at least this many dB under its best window's mean. Both at once: a rising
    share alone is the mask finding transients, a falling PSNR alone is harder photos."""


@dataclass(frozen=True)
class WindowMeans:
    """Means of one window of training steps."""

    start: int
    """First step of the window."""
    masked_fraction: float
    psnr: float


def feedback_loop(history: list[WindowMeans], cfg: MaskHealthConfig) -> tuple[WindowMeans, WindowMeans] | None:
    """(best window, latest window) when the latest window's masked share is `min_fraction_rise` over the lowest
    earlier share and its PSNR `min_psnr_drop` under the best earlier PSNR; None otherwise (fewer than 2 windows)."""
    if len(history) < 2:
        return None
    latest, earlier = history[-1], history[:-1]
    best = max(earlier, key=lambda w: w.psnr)
    lowest_share = min(w.masked_fraction for w in earlier)
    if latest.masked_fraction - lowest_share >= cfg.min_fraction_rise and best.psnr - latest.psnr >= cfg.min_psnr_drop:
        return best, latest
    return None


def feedback_message(best: WindowMeans, latest: WindowMeans, cfg: MaskHealthConfig) -> str:
    """The warning for a feedback loop between window `best` and window `latest`."""
    return (
        f"willags warning: the transient mask looks like it is feeding on itself: over steps {best.start}-"
        f"{latest.start + cfg.window} the masked share of each photo rose to {latest.masked_fraction:.0%} while "
        f"the training PSNR fell from {best.psnr:.1f} to {latest.psnr:.1f} dB (means over {cfg.window} steps). What "
        "the mask drops gets no loss and renders worse, so it is dropped again. On COLMAP scenes "
        "--pipeline.model.mask.safeguard.enabled True keeps pixels near long SfM tracks in the loss; on a capture "
        "without transients --pipeline.model.mask.enabled False turns the mask off (`willags-inspect` tells which)."
    )


class MaskHealth:
    """Accumulates the masked share and the training PSNR of the steps where the mask ran (on their device: one
    host read per window, not per step) and returns the warning once (:meth:`observe`)."""

    def __init__(self, cfg: MaskHealthConfig):
        self.cfg = cfg
        self.history: list[WindowMeans] = []
        """Closed windows of the current regime."""
        self.warned = False
        self._sums: Tensor | None = None  # [masked share, PSNR] summed over the open window
        self._count = 0
        self._window_start: int | None = None
        self._regime: object = None
        self.clock = time.monotonic
        self._last_rejected_warning = -float("inf")

    def rejected(self, step: int, photo: str, max_masked_fraction: float) -> str | None:
        """The warning that `step`'s mask of `photo` was rejected (it would have dropped more than
        `max_masked_fraction` of it, so the photo was supervised everywhere), at most once per
        REJECTED_WARN_EVERY_S seconds (None in between): normal early in training, a sign when one photo keeps it
        up."""
        now = self.clock()
        if now - self._last_rejected_warning < REJECTED_WARN_EVERY_S:
            return None
        self._last_rejected_warning = now
        return (
            f"[bold yellow]willags warning:[/bold yellow] step {step}: the transient mask flagged more than "
            f"{max_masked_fraction} of {photo}; that image is supervised everywhere this step (normal early in "
            "training; if it persists for one image, that photo may not show this scene)"
        )

    def observe(self, step: int, masked_fraction: Tensor, psnr: Tensor, regime: object = None) -> str | None:
        """Add one training step (its masked share and PSNR, 0-d tensors; `regime` any key of what else moves the
        PSNR, e.g. (downscale factor, opacity resets so far)). Returns the warning the first time a closed window
        shows the loop, else None. A new regime starts the comparison over."""
        cfg = self.cfg
        if not cfg.enabled or self.warned:
            return None
        if regime != self._regime:
            self.history, self._sums, self._count, self._window_start, self._regime = [], None, 0, None, regime
        if self._window_start is None:
            self._window_start = step
        value = torch.stack([masked_fraction.detach().float().reshape(()), psnr.detach().float().reshape(())])
        self._sums = value if self._sums is None else self._sums + value
        self._count += 1
        if step - self._window_start + 1 < cfg.window:
            return None
        share, mean_psnr = (self._sums / self._count).tolist()
        self.history.append(WindowMeans(self._window_start, share, mean_psnr))
        self._sums, self._count, self._window_start = None, 0, None
        found = feedback_loop(self.history, cfg)
        if found is None:
            return None
        self.warned = True
        return feedback_message(*found, cfg)
