"""The mask's start rule (mask.start_rule "transients"): at mask.warmup_steps the training photos' residual-blob share
starts the mask or keeps it off for the rest of the run."""

import pytest
import torch

from willags_ns.config import WillagsModelConfig
from willags_ns.eval.mask_eval import trained_mask
from willags_ns.mask.rule import MaskConfig, mask_start


def test_the_start_rule_starts_the_mask_only_at_or_above_its_bar():
    cfg = MaskConfig(start_rule="transients", start_share=0.10)
    start, reason = mask_start(0.062, cfg)
    assert not start and "6.2%" in reason and "below the mask's bar of 10.0%" in reason and "stays off" in reason
    start, reason = mask_start(0.10, cfg)  # at the bar: it starts
    assert start and "at or above" in reason and "starts" in reason
    assert mask_start(0.3, cfg)[0]
    with pytest.raises(ValueError, match="within"):
        mask_start(float("nan"), cfg)


def test_a_start_rule_or_bar_out_of_range_is_refused_in_one_line():
    cfg = WillagsModelConfig()
    cfg.mask.start_share = 1.5
    with pytest.raises(ValueError, match="start-share within \\[0, 1\\].*1.5"):
        cfg.check()
    cfg.mask.start_share = 0.1
    cfg.mask.start_rule = "sometimes"
    with pytest.raises(ValueError, match="'sometimes'"):
        cfg.check()


def _train_with_start_rule(tmp_path, start_share: float):
    from tests.test_train import _train

    overrides = {
        "mask.enabled": True,
        "mask.distance": "residual",
        "mask.warmup_steps": 6,
        "mask.every": 1,
        "mask.start_rule": "transients",
        "mask.start_share": start_share,
    }
    torch.manual_seed(0)
    return _train(tmp_path, "willags", steps=12, auto_config=False, device="cpu", **overrides)[1].pipeline.model


@pytest.mark.slow
def test_the_start_rule_decides_at_the_mask_warmup_and_a_checkpoint_keeps_it(tmp_path):
    """A bar above any share (1.0) keeps the mask off: after the last step before its warm-up ends no image gets a
    mask and the teacher stops following the student. A bar of 0 starts it: every step from the warm-up on masks.
    The decision travels in the checkpoint."""
    off = _train_with_start_rule(tmp_path / "off", start_share=1.0)
    d = off.mask_decision
    assert d is not None and d["step"] == 5 and 0.0 <= d["share"] < 1.0 and d["start"] is False
    assert off.mask_step.declined and not off.mask_step.active(11) and len(off.last_masks) == 0
    assert trained_mask(off) is None  # scored as what it trained: a model without the mask
    frozen = [p.detach().clone() for p in off.teacher.parameters()]
    off.update_teacher(12)  # the teacher no longer follows the student
    assert all(torch.equal(a, b) for a, b in zip(frozen, off.teacher.parameters(), strict=True))
    on = _train_with_start_rule(tmp_path / "on", start_share=0.0)
    assert on.mask_decision["start"] is True and on.mask_decision["step"] == 5
    assert not on.mask_step.declined and on.mask_step.active(11) and len(on.last_masks) > 0
    assert trained_mask(on) is on.config.mask
    on.set_extra_state(off.get_extra_state())  # as a resumed run loads it
    assert on.mask_decision == d and on.mask_step.declined and not on.mask_step.active(11)


def test_a_run_that_ends_before_its_mask_starts_says_so():
    """ns-train with --max-num-iterations under the mask's start gets one line naming both steps and the flag; a run
    past the start, a mask off, a model without the latent (no mask built) or a time budget (which fits the start
    into its plan) get none."""
    from willags_ns.engine.trainer import mask_after_the_end
    from willags_ns.mask.step import MaskStep

    step = MaskStep(WillagsModelConfig(), None)
    note = mask_after_the_end(step, 3000, budgeted=False)
    assert note is not None and "5,000" in note and "3,000" in note and "--pipeline.model.mask.warmup-steps" in note
    assert mask_after_the_end(step, 5000, budgeted=False) is not None  # the last step is 4,999: never on
    assert mask_after_the_end(step, 5001, budgeted=False) is None
    assert mask_after_the_end(step, 3000, budgeted=True) is None
    off = WillagsModelConfig()
    off.mask.enabled = False
    assert mask_after_the_end(MaskStep(off, None), 3000, budgeted=False) is None
    assert mask_after_the_end(MaskStep(WillagsModelConfig(appearance="sh"), None), 3000, budgeted=False) is None
    assert mask_after_the_end(None, 3000, budgeted=False) is None
