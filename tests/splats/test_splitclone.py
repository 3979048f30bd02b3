"""splats/splitclone.py: splatfacto's densification with a budget of Gaussians."""

import torch
from gsplat.strategy import DefaultStrategy

from willags_ns.splats.splitclone import BudgetedDefaultStrategy, keep_growth_within


def _state(grads, radii=None):
    """gsplat's strategy state with these mean gradients (one visit each)."""
    g = torch.tensor(grads, dtype=torch.float32)
    r = torch.zeros_like(g) if radii is None else torch.tensor(radii, dtype=torch.float32)
    return {"grad2d": g.clone(), "count": torch.ones_like(g), "radii": r, "scene_scale": 1.0}


def test_a_growth_within_the_budget_is_left_as_it_is():
    state = _state([0.5, 0.0, 0.3, 0.0])
    assert keep_growth_within(state, n=4, cap=6, grow_grad2d=0.1, grow_scale2d=0.05, scale2d=True) == 0
    assert torch.equal(state["grad2d"], torch.tensor([0.5, 0.0, 0.3, 0.0]))


def test_past_the_budget_only_the_largest_gradients_stay_eligible():
    """Six Gaussians, four above the threshold and one large on screen, room for two more: the two largest
    gradients stay eligible, the others' statistics are zeroed; the screen-size rule counts only with scale2d."""
    state = _state([0.5, 0.05, 0.3, 0.9, 0.2, 0.0], radii=[0.0, 0.0, 0.0, 0.0, 0.0, 0.2])
    dropped = keep_growth_within(state, n=6, cap=8, grow_grad2d=0.1, grow_scale2d=0.05, scale2d=True)
    assert dropped == 3  # five eligible, two kept
    eligible = (state["grad2d"] > 0.1) | (state["radii"] > 0.05)
    assert eligible.tolist() == [True, False, False, True, False, False]
    state = _state([0.5, 0.05, 0.3, 0.9, 0.2, 0.0], radii=[0.0, 0.0, 0.0, 0.0, 0.0, 0.2])
    assert keep_growth_within(state, n=6, cap=8, grow_grad2d=0.1, grow_scale2d=0.05, scale2d=False) == 2
    assert (state["grad2d"] > 0.1).tolist() == [True, False, False, True, False, False]
    state = _state([0.5, 0.3])  # at the cap already: nothing grows
    assert keep_growth_within(state, n=10, cap=10, grow_grad2d=0.1, grow_scale2d=0.05, scale2d=False) == 2
    assert state["grad2d"].tolist() == [0.0, 0.0]


def _params(n):
    torch.manual_seed(0)
    p = {
        "means": torch.randn(n, 3),
        "scales": torch.full((n, 3), -5.0),  # small: eligible ones are duplicated
        "quats": torch.nn.functional.normalize(torch.randn(n, 4), dim=-1),
        "opacities": torch.zeros(n),
    }
    params = torch.nn.ParameterDict({k: torch.nn.Parameter(v) for k, v in p.items()})
    optimizers = {k: torch.optim.Adam([params[k]], lr=1e-3) for k in params}
    return params, optimizers


def test_a_refinement_grows_no_gaussian_past_the_cap_and_none_fewer_below_it():
    """gsplat's growth of 100 Gaussians that all pass the gradient threshold: without a budget it doubles them; with
    a cap of 130 it grows 30 (the largest gradients); with a cap above 200 it is gsplat's own growth."""
    grads = torch.linspace(0.01, 1.0, 100).tolist()
    for strategy, want in (
        (DefaultStrategy(grow_grad2d=0.001), 200),
        (BudgetedDefaultStrategy(grow_grad2d=0.001, cap_max=130), 130),
        (BudgetedDefaultStrategy(grow_grad2d=0.001, cap_max=1000), 200),
        (BudgetedDefaultStrategy(grow_grad2d=0.001, cap_max=0), 200),
    ):
        params, optimizers = _params(100)
        state = strategy.initialize_state(scene_scale=1.0)
        state.update(_state(grads))
        strategy._grow_gs(params, optimizers, state, step=600)
        assert params["means"].shape[0] == want, type(strategy).__name__
    params, optimizers = _params(100)
    strategy = BudgetedDefaultStrategy(grow_grad2d=0.001, cap_max=130)
    state = strategy.initialize_state(scene_scale=1.0)
    state.update(_state(grads))
    strategy._grow_gs(params, optimizers, state, step=600)
    # the duplicated ones are the 30 largest gradients: their copies sit at the end with the same means
    assert torch.equal(params["means"][100:], params["means"][70:100])
