"""Held-out halves: the right halves of a few training photos kept out of the loss and scored while the run trains.

A photo whose right half is held out trains on its left half alone, its latent included, which is how the NeRF-W
protocol treats a test photo (the latent fitted on the left half, the right half scored). Rendering that photo with
its own latent and scoring its right half therefore estimates, from the training photos only, what the protocol
will measure, at every step it is asked. A run keeps a copy of the model at the step that scored best and, when the
last step scores worse by more than a margin, ends with that copy: a collection whose test score falls with length
(crowds or sky learned into the scene late in a run) stops where it was best, and one that gains keeps its last
step. What it costs: the right halves of `photos` training photos never reach the loss.

With the beta-VAE latent the encoder sees the whole photo, so the held-out half reaches the latent: the estimate is
then optimistic. The model wires it (`WillagsModel`: the loss mask, the scoring callback and `finish_training`); this
module holds the rule.
"""

from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field

import torch
from torch import Tensor, nn

from willags_ns.eval.protocol import psnr, render_with_latent, split_halves, unit_float


@dataclass
class HoldoutConfig:
    """Which training photos lend their right half, when the halves are scored and when the run ends with its best
    step instead of its last (--pipeline.model.holdout.*)."""

    photos: int = 0
    """How many training photos lend their right half to the score (evenly spaced through the training photos; at
    most a quarter of them, none with fewer than 4). 0: off, every pixel trains."""
    every: int = 1000
    """Steps between two scorings of the held-out halves (and the last step, always)."""
    start: int = 3000
    """The first step scored: earlier copies are not kept (the Gaussians are still growing towards the photos)."""
    margin: float = 0.1
    """dB by which the best scoring must beat the last step's for the run to end with the best step's copy."""


def holdout_indices(num_train: int, photos: int) -> tuple[int, ...]:
    """The training photos (indices) whose right half is held out: `photos` evenly spaced ones, at most a quarter of
    `num_train`; none below 4 training photos or with `photos` 0."""
    k = min(photos, num_train // 4)
    if k <= 0:
        return ()
    return tuple(sorted({int((i + 0.5) * num_train / k) for i in range(k)}))


def left_half_weight(height: int, width: int, device: torch.device | str | None = None) -> Tensor:
    """[H, W] loss weight of a held-out photo: 1 on its left half (protocol.split_halves), 0 on its right."""
    left, _ = split_halves(width)
    w = torch.zeros(height, width, device=device)
    w[:, left] = 1.0
    return w


def is_scoring_step(step: int, cfg: HoldoutConfig, last_step: int) -> bool:
    """Whether `step` scores the held-out halves: from cfg.start every cfg.every steps, and the last step."""
    if step < cfg.start:
        return False
    return (step - cfg.start) % cfg.every == 0 or step == last_step


@torch.no_grad()
def holdout_psnr(model, cameras, images: Sequence[Tensor], indices: Sequence[int], latents: Tensor | None) -> float:
    """Mean PSNR (dB) of the held-out right halves: training photo i rendered with its own latent (`latents[i]`, None
    for a model without latents), in eval mode, scored on the columns the protocol scores."""
    was_training = model.training
    model.eval()
    try:
        scores = []
        for i in indices:
            pred = render_with_latent(
                model, cameras[i : i + 1].to(model.device), None if latents is None else latents[i]
            )
            gt = unit_float(images[i][..., :3].to(model.device))
            _, right = split_halves(gt.shape[1])
            scores.append(psnr(pred[:, right], gt[:, right]))
    finally:
        model.train(was_training)
    return sum(scores) / len(scores)


@dataclass
class BestStep:
    """The scorings of a run and a copy of the model at its best one (plain state: the model owns it)."""

    margin: float
    history: list[tuple[int, float]] = field(default_factory=list)
    best_step: int = -1
    best_psnr: float = float("-inf")
    copy: dict[str, Tensor] | None = None

    def observe(self, step: int, score: float, take_copy: Callable[[], dict[str, Tensor]]) -> None:
        """Record a scoring; a new best takes a copy of the model (`take_copy`)."""
        self.history.append((step, score))
        if score > self.best_psnr:
            self.best_step, self.best_psnr, self.copy = step, score, take_copy()

    def to_restore(self) -> dict[str, Tensor] | None:
        """The best step's copy when the last scoring is below the best by more than the margin, else None."""
        if not self.history or self.copy is None:
            return None
        last_step, last = self.history[-1]
        if last_step == self.best_step or self.best_psnr - last <= self.margin:
            return None
        return self.copy

    def summary(self) -> dict:
        """What the checkpoint keeps of it (the copy is not kept)."""
        return {"history": list(self.history), "best_step": self.best_step, "best_psnr": self.best_psnr}


COPY_SKIPS = ("perceptual.", "_lpips.")
"""State-dict prefixes a copy leaves out: fixed feature networks that training never changes."""


def copy_state(model: nn.Module) -> dict[str, Tensor]:
    """Every tensor of `model`'s state dict, detached and cloned, but the fixed networks of COPY_SKIPS."""
    return {
        k: v.detach().clone()
        for k, v in model.state_dict().items()
        if torch.is_tensor(v) and not k.startswith(COPY_SKIPS)
    }


def restore_state(
    model: nn.Module, gauss_params: Mapping[str, nn.Parameter], optimizers: Mapping, state: dict[str, Tensor]
) -> None:
    """Put a copy (copy_state) back into `model`: the Gaussians (`gauss_params`, named as in the state dict under
    "gauss_params.") resized in place, since the optimisers hold these Parameter objects; their moments in
    `optimizers` (name -> torch optimiser) dropped, as their shapes may no longer match (Adam starts them again);
    every other tensor copied."""
    n = state["gauss_params.means"].shape[0]
    for name, param in gauss_params.items():
        param.data = torch.zeros((n,) + param.shape[1:], device=param.device, dtype=param.dtype)
        opt = optimizers.get(name)
        if opt is not None:
            opt.state[param] = {}
    nn.Module.load_state_dict(model, state, strict=False)
