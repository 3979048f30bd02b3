"""Splatfacto's densification (gsplat's DefaultStrategy: split, clone, prune, opacity resets) with a budget.

gsplat's rule grows every Gaussian whose mean screen-space gradient since the last refinement passes a threshold
(and, early on, every one that covers too much of the screen), with no limit on how many: on some collections it
keeps growing at every refinement (docs/design.md, "Capacity"), until a CPU's memory or time runs out. Here a
refinement grows at most `cap_max - N` Gaussians: when more are eligible, those with the largest gradients grow and
the rest wait for the next refinement (their statistics are reset with everyone's). Below the budget the strategy
is gsplat's, step for step. MCMC (splats/mcmc.py) has its own cap.

Pure function :func:`keep_growth_within` (what a refinement may grow), and :class:`BudgetedDefaultStrategy`, which
applies it before gsplat's growth."""

from dataclasses import dataclass
from typing import Any

import torch
from gsplat.strategy import DefaultStrategy


def keep_growth_within(
    state: dict[str, Any], n: int, cap: int, grow_grad2d: float, grow_scale2d: float, scale2d: bool
) -> int:
    """Make at most `cap - n` of the `n` Gaussians eligible for the coming growth, in place on gsplat's strategy
    `state`: a Gaussian is eligible when its mean gradient (`grad2d / count`) passes `grow_grad2d` or, with `scale2d`
    (before `refine_scale2d_stop_iter`), its screen radius (`radii`) passes `grow_scale2d`. When more are eligible,
    the largest gradients keep their statistics and the others' are zeroed (gsplat resets them after the refinement
    anyway). Returns how many were made ineligible (0: the growth fits the budget, nothing changed)."""
    budget = max(cap - n, 0)
    grads = state["grad2d"] / state["count"].clamp_min(1)
    eligible = grads > grow_grad2d
    if scale2d and state.get("radii") is not None:
        eligible = eligible | (state["radii"] > grow_scale2d)
    n_eligible = int(eligible.sum())  # a host read at refinement steps only
    if n_eligible <= budget:
        return 0
    score = torch.where(eligible, grads, torch.full_like(grads, -1.0))
    keep = torch.zeros_like(eligible)
    if budget > 0:
        keep[torch.topk(score, budget).indices] = True
    drop = eligible & ~keep
    state["grad2d"][drop] = 0.0
    if state.get("radii") is not None:
        state["radii"][drop] = 0.0
    return n_eligible - budget


@dataclass
class BudgetedDefaultStrategy(DefaultStrategy):
    """gsplat's DefaultStrategy whose refinements grow no Gaussian past `cap_max` (:func:`keep_growth_within`)."""

    cap_max: int = 0
    """The most Gaussians a refinement grows to (0: no budget, gsplat's strategy as it is)."""

    def _grow_gs(self, params, optimizers, state, step):  # type: ignore[override]
        if self.cap_max > 0:
            scale2d = step < self.refine_scale2d_stop_iter
            n = params["means"].shape[0]
            keep_growth_within(state, n, self.cap_max, self.grow_grad2d, self.grow_scale2d, scale2d)
        return super()._grow_gs(params, optimizers, state, step)
