"""willags_ns/mask/health.py: the warning when the transient mask feeds on itself."""

import warnings

import pytest
import torch

from willags_ns.mask.health import MaskHealth, MaskHealthConfig, WindowMeans, feedback_loop

# the paper preset on south-building, seed 42, one H200 (the mask diagnosis record in benchmarks/records/gpu_runs/):
# means over 250 steps from the mask's start (step 500) to step 2000, where its test PSNR fell 18.45 -> 15.57
MEASURED_LOOP = [
    (500, 0.0768, 21.0),
    (750, 0.0872, 20.2),
    (1000, 0.0906, 21.2),
    (1250, 0.125, 19.9),
    (1500, 0.127, 19.6),
]


def _windows(rows):
    return [WindowMeans(s, f, p) for s, f, p in rows]


def test_the_measured_loop_is_found_at_the_window_where_share_and_psnr_part():
    cfg = MaskHealthConfig()
    history = _windows(MEASURED_LOOP)
    for k in range(1, len(history)):
        assert feedback_loop(history[:k], cfg) is None, f"not yet at window {history[k - 1].start}"
    best, latest = feedback_loop(history, cfg)
    assert (best.start, latest.start) == (1000, 1500)


@pytest.mark.parametrize(
    "rows",
    [
        # a scene with real transients: the share moves by a few hundredths, the PSNR climbs
        [(500, 0.15, 18.0), (750, 0.17, 18.6), (1000, 0.14, 19.1), (1250, 0.18, 19.4), (1500, 0.16, 19.7)],
        # the mask finds more transients while the fit improves (share up, PSNR up)
        [(500, 0.05, 18.0), (750, 0.10, 18.5), (1000, 0.15, 19.0)],
        # harder photos in a window (PSNR down) with a steady share
        [(500, 0.08, 21.0), (750, 0.09, 18.0)],
    ],
)
def test_no_warning_unless_share_rises_and_psnr_falls_together(rows):
    assert feedback_loop(_windows(rows), MaskHealthConfig()) is None


def _feed(health, steps, share, psnr, regime=None):
    out = []
    for step in steps:
        out.append(health.observe(step, torch.tensor(share(step)), torch.tensor(psnr(step)), regime))
    return [m for m in out if m is not None]


def test_observe_warns_once_naming_the_numbers_and_the_switches():
    health = MaskHealth(MaskHealthConfig(window=10))
    warnings_ = _feed(health, range(0, 100), lambda s: 0.05 + 0.002 * s, lambda s: 22.0 - 0.05 * s)
    assert len(warnings_) == 1
    msg = warnings_[0]
    assert "feeding on itself" in msg and "mask.safeguard.enabled True" in msg and "mask.enabled False" in msg
    assert health.warned and _feed(health, range(100, 200), lambda s: 0.9, lambda s: 5.0) == []


def test_a_new_regime_starts_the_comparison_over():
    cfg = MaskHealthConfig(window=10)
    health = MaskHealth(cfg)
    # a good first regime, then a sharper resolution: lower PSNR, higher share, each by itself a step change
    assert _feed(health, range(0, 50), lambda s: 0.05, lambda s: 24.0, regime=(4, 0)) == []
    assert _feed(health, range(50, 100), lambda s: 0.11, lambda s: 21.0, regime=(2, 0)) == []
    assert [w.start for w in health.history] == [50, 60, 70, 80, 90]


def test_disabled_watches_nothing():
    health = MaskHealth(MaskHealthConfig(enabled=False, window=10))
    assert _feed(health, range(0, 100), lambda s: 0.05 + 0.002 * s, lambda s: 22.0 - 0.05 * s) == []
    assert health.history == []


def test_a_training_step_with_the_mask_feeds_the_watch_and_its_warning_reaches_the_console(monkeypatch):
    import willags_ns.model as model_module
    from tests.test_model import _tiny_model
    from tests.test_reliability_numerics import _image, train_step

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        model = _tiny_model()
    model.train()
    # every window compared, any change counts: the wiring, not the thresholds, is under test
    model.mask_health = MaskHealth(MaskHealthConfig(window=1, min_fraction_rise=-1.0, min_psnr_drop=-100.0))
    logged = []
    monkeypatch.setattr(model_module.CONSOLE, "log", lambda *a, **k: logged.append(" ".join(map(str, a))))
    for i in range(3):
        train_step(model, _image(seed=i))
    assert len(model.mask_health.history) >= 2
    ours = [m for m in logged if "feeding on itself" in m]
    assert len(ours) == 1
