import math

import pytest
import torch

from willags_ns.splats.mcmc import (
    McmcDensification,
    add_sampled,
    covariance_times,
    covariances,
    position_noise,
    relocate_dead,
    relocation,
)


def _eq9(o: float, s: float, n: int) -> tuple[float, float]:
    """The paper's Eq. 9 as written (double sum), in Python floats."""
    o_new = 1.0 - (1.0 - o) ** (1.0 / n)
    denom = sum(
        math.comb(i - 1, k) * (-1.0) ** k / math.sqrt(k + 1) * o_new ** (k + 1)
        for i in range(1, n + 1)
        for k in range(i)
    )
    return o_new, s * o / denom


def test_relocation_matches_the_papers_double_sum():
    g = torch.Generator().manual_seed(0)
    o = torch.rand(64, generator=g, dtype=torch.float64) * 0.98 + 0.01
    s = torch.rand(64, 3, generator=g, dtype=torch.float64) + 0.1
    n = torch.randint(1, 12, (64,), generator=g)
    o_new, s_new = relocation(o, s, n)
    for i in range(64):
        want_o, want_s = _eq9(float(o[i]), float(s[i, 0]), int(n[i]))
        assert float(o_new[i]) == pytest.approx(want_o, rel=1e-9)
        assert float(s_new[i, 0]) == pytest.approx(want_s, rel=1e-6)


def test_one_copy_is_the_gaussian_itself_and_copies_share_its_opacity():
    o = torch.tensor([0.3, 0.9])
    s = torch.tensor([[1.0, 2.0, 3.0], [0.5, 0.5, 0.5]])
    o1, s1 = relocation(o, s, torch.tensor([1, 1]))
    assert torch.allclose(o1, o) and torch.allclose(s1, s)
    o4, _ = relocation(o, s, torch.tensor([4, 4]))
    # four copies of opacity o' stacked let through as much light as the one: (1 - o')^4 = 1 - o
    assert torch.allclose((1 - o4) ** 4, 1 - o, atol=1e-6)
    assert (o4 < o).all()


def test_covariances_are_rotated_squared_scales():
    q = torch.tensor([[1.0, 0.0, 0.0, 0.0], [math.cos(math.pi / 4), 0.0, 0.0, math.sin(math.pi / 4)]])
    s = torch.tensor([[1.0, 2.0, 3.0], [1.0, 2.0, 3.0]])
    c = covariances(q, s)
    assert torch.allclose(c[0], torch.diag(torch.tensor([1.0, 4.0, 9.0])))
    # 90 degrees about z swaps the x and y variances
    assert torch.allclose(c[1], torch.diag(torch.tensor([4.0, 1.0, 9.0])), atol=1e-6)


def test_the_covariance_applied_by_turning_into_each_gaussian_s_frame_is_the_covariance_matrix_s():
    """position_noise's Sigma v (two quaternion turns and the squared scales, never the 3x3 matrix) against the matrix,
    for unnormalised quaternions and scales over two orders of magnitude."""
    g = torch.Generator().manual_seed(3)
    q = torch.randn(4000, 4, generator=g, dtype=torch.float64) * 3.0
    log_s = torch.randn(4000, 3, generator=g, dtype=torch.float64) * 1.5
    v = torch.randn(4000, 3, generator=g, dtype=torch.float64)
    want = torch.einsum("bij,bj->bi", covariances(q, torch.exp(log_s)), v)
    assert torch.allclose(covariance_times(q, log_s, v), want, rtol=1e-12, atol=1e-12)
    # 90 degrees about z: a step along x is scaled by the y variance
    quarter = torch.tensor([[math.cos(math.pi / 4), 0.0, 0.0, math.sin(math.pi / 4)]])
    scaled = covariance_times(quarter, torch.log(torch.tensor([[1.0, 2.0, 3.0]])), torch.tensor([[1.0, 0.0, 0.0]]))
    assert torch.allclose(scaled, torch.tensor([[4.0, 0.0, 0.0]]), atol=1e-6)
    # at the extremes, float32: a zero quaternion (no rotation, as the matrix has it), scales from 1e-8 to 1e8
    q32 = torch.tensor([[0.0, 0.0, 0.0, 0.0], [1e-20, 1e-20, 0.0, 1e-20], [1e8, -1e8, 1e8, 1.0]])
    log_s32 = torch.log(torch.tensor([[1e-8, 1.0, 1e8], [1e-4, 1e-4, 1e-4], [1e4, 1.0, 1e-4]]))
    v32 = torch.ones(3, 3)
    got = covariance_times(q32, log_s32, v32)
    want = torch.einsum("bij,bj->bi", covariances(q32, torch.exp(log_s32)), v32)
    assert torch.isfinite(got).all() and torch.allclose(got, want, rtol=1e-5, atol=1e-12)


def _params(n=200, seed=0):
    g = torch.Generator().manual_seed(seed)
    params = torch.nn.ParameterDict(
        {
            "means": torch.nn.Parameter(torch.randn(n, 3, generator=g)),
            "scales": torch.nn.Parameter(torch.randn(n, 3, generator=g) - 3),
            "quats": torch.nn.Parameter(torch.randn(n, 4, generator=g)),
            "opacities": torch.nn.Parameter(torch.randn(n, 1, generator=g)),
            "features_dc": torch.nn.Parameter(torch.randn(n, 3, generator=g)),
        }
    )
    optimizers = {k: torch.optim.Adam([p], lr=1e-3) for k, p in params.items()}
    loss = sum((p**2).sum() for p in params.values())
    loss.backward()
    for o in optimizers.values():
        o.step()
    return params, optimizers


def test_dead_gaussians_move_onto_live_ones_and_the_count_stays():
    params, optimizers = _params()
    with torch.no_grad():
        params["opacities"][:50] = -10.0  # dead
    before = {k: v.detach().clone() for k, v in params.items()}
    moved = relocate_dead(params, optimizers, min_opacity=0.005)
    assert moved == 50
    assert len(params["means"]) == 200
    assert (torch.sigmoid(params["opacities"]) > 0.005).all()
    # each moved Gaussian sits on a live one's mean
    live_means = before["means"][50:]
    d = (
        torch.cdist(params["means"][:50].detach(), live_means, compute_mode="donot_use_mm_for_euclid_dist")
        .min(dim=1)
        .values
    )
    assert (d == 0).all()
    # the optimisers follow the new tensors, with the moved ones' moments cleared
    for k, p in params.items():
        state = optimizers[k].state[p]
        assert state["exp_avg"].shape == p.shape
        assert (state["exp_avg"][:50] == 0).all()


def test_growth_adds_copies_that_split_their_source():
    params, optimizers = _params()
    n0 = len(params["means"])
    add_sampled(params, optimizers, 20, min_opacity=0.005)
    assert len(params["means"]) == n0 + 20
    for k, p in params.items():
        assert optimizers[k].state[p]["exp_avg_sq"].shape == p.shape
        assert optimizers[k].param_groups[0]["params"][0] is p
    # a new Gaussian is a copy: its mean equals an old one's
    d = (
        torch.cdist(
            params["means"][n0:].detach(), params["means"][:n0].detach(), compute_mode="donot_use_mm_for_euclid_dist"
        )
        .min(dim=1)
        .values
    )
    assert (d == 0).all()


def test_noise_moves_only_nearly_transparent_gaussians():
    params, _ = _params()
    with torch.no_grad():
        params["opacities"][:100] = 5.0  # opaque
        params["opacities"][100:] = -10.0  # transparent
    before = params["means"].detach().clone()
    position_noise(params, scaler=1.0)
    moved = (params["means"].detach() - before).norm(dim=1)
    assert (moved[:100] < 1e-6).all()
    assert (moved[100:] > 0).all()


def test_strategy_grows_to_its_cap_within_the_window_and_never_resets_opacity():
    params, optimizers = _params(n=100)
    s = McmcDensification(cap_max=130, refine_start_iter=0, refine_stop_iter=1000, refine_every=10, noise_lr=0.0)
    for step in range(1, 200):
        s.step_post_backward(params, optimizers, {}, step, {}, lr=1e-4)
    assert len(params["means"]) == 130
    assert s.reset_every == 0
    s2 = McmcDensification(cap_max=10_000, refine_start_iter=50, refine_stop_iter=60, refine_every=5, noise_lr=0.0)
    p2, o2 = _params(n=100)
    for step in range(1, 200):
        s2.step_post_backward(p2, o2, {}, step, {}, lr=1e-4)
    assert len(p2["means"]) == int(1.05 * 100)  # one refinement step (55) inside (50, 60)


def test_a_model_trains_with_mcmc_up_to_its_cap_and_pays_the_penalties(tmp_path, monkeypatch):
    import willags_ns.model as model_module
    from tests.test_train import _train

    seen: list[set[str]] = []
    terms_of = model_module.regularization_terms

    def spy(*args):
        out = terms_of(*args)
        seen.append(set(out[0]))
        return out

    monkeypatch.setattr(model_module, "regularization_terms", spy)
    torch.manual_seed(0)
    _, trainer, losses = _train(tmp_path, "willags", steps=30, **{"densification": "mcmc", "mcmc.cap_max": 8400})
    model = trainer.pipeline.model
    assert isinstance(model.strategy, McmcDensification)
    assert model.num_points == 8400  # the built-in scene's 8000 points grown by 5 % per refinement to the cap
    assert all(math.isfinite(v) for v, _ in losses)
    assert seen and all("mcmc_reg" in keys for keys in seen)


def test_auto_densifies_by_mcmc_on_a_gpu_and_as_splatfacto_on_the_cpu():
    from willags_ns.splats.mcmc import uses_mcmc

    assert uses_mcmc("auto", "cuda") and uses_mcmc("auto", torch.device("cuda", 1))
    assert not uses_mcmc("auto", "cpu")
    assert uses_mcmc("mcmc", "cpu") and not uses_mcmc("splatfacto", "cuda")
    with pytest.raises(ValueError, match="auto, mcmc or splatfacto"):
        uses_mcmc("default", "cpu")


def test_the_default_model_on_the_cpu_densifies_as_splatfacto(tmp_path):
    from tests.test_train import _train
    from willags_ns.splats.splitclone import BudgetedDefaultStrategy

    _, trainer, _ = _train(tmp_path, "willags", steps=2, device="cpu")
    model = trainer.pipeline.model
    assert model.config.densification == "auto" and not model.mcmc_on
    assert type(model.strategy) is BudgetedDefaultStrategy  # gsplat's DefaultStrategy with a budget
    assert model.strategy.cap_max == model.config.splitclone_cap > 0


def test_the_cap_reason_names_the_larger_cap_only_below_it():
    from willags_ns.splats.mcmc import MORE_GAUSSIANS, McmcConfig, cap_and_reason, scene_cap

    cap, reason = cap_and_reason(McmcConfig(), 5.0)
    assert cap == 300_000 and f"cap-max {MORE_GAUSSIANS})" in reason and "not crowded ones" in reason
    cap, reason = cap_and_reason(McmcConfig(cap_max=MORE_GAUSSIANS), 5.0)
    assert cap == MORE_GAUSSIANS and "cap-max" not in reason  # already there: nothing more to offer
    pixels = McmcConfig(cap_rule="pixels")
    cap, reason = cap_and_reason(pixels, 5.0)
    assert (cap, reason) == scene_cap(5.0, pixels) and "cap-max" not in reason  # the pixels rule's own reason


def test_the_transients_rule_raises_the_cap_only_below_its_bar():
    from willags_ns.splats.mcmc import McmcConfig, cap_and_reason, transient_cap

    cfg = McmcConfig(cap_rule="transients", cap_max=300_000, cap_ceiling=1_000_000, clean_share=0.02)
    cap, reason = transient_cap(0.011, cfg)
    assert cap == 1_000_000 and "1.1%" in reason and "below the bar of 2.0%" in reason and "clean" in reason
    cap, reason = transient_cap(0.02, cfg)  # at the bar: crowded
    assert cap == 300_000 and "at or above" in reason and "crowded" in reason
    assert transient_cap(0.3, cfg)[0] == 300_000
    assert transient_cap(0.0, McmcConfig(cap_max=2_000_000, clean_share=0.02))[0] == 2_000_000  # never lowers it
    with pytest.raises(ValueError, match="within"):
        transient_cap(float("nan"), cfg)
    cap, reason = cap_and_reason(cfg, 5.0)  # before the cap is filled: as set, and what happens then
    assert cap == 300_000 and "until MCMC fills them" in reason and "rises to 1,000,000" in reason


def _train_with_transients_rule(tmp_path, clean_share: float):
    from tests.test_train import _train

    overrides = {
        "densification": "mcmc",
        "mcmc.cap_rule": "transients",
        "mcmc.cap_max": 8100,
        "mcmc.cap_ceiling": 8400,
        "mcmc.clean_share": clean_share,
    }
    torch.manual_seed(0)
    return _train(tmp_path, "willags", steps=30, device="cpu", **overrides)[1].pipeline.model


def test_the_transients_rule_decides_the_cap_while_training_and_a_checkpoint_keeps_it(tmp_path):
    """When MCMC first fills its cap (the built-in scene's 8000 points grown 5 % at step 10, the first refinement) the
    model renders its training photos, measures their transient share and sets the cap: a bar above any share (1.0)
    takes the collection for clean and the Gaussians grow past cap_max to the ceiling; a bar of 0 takes it for
    crowded and they stop at cap_max. The decision travels in the checkpoint."""
    clean = _train_with_transients_rule(tmp_path / "clean", clean_share=1.0)
    d = clean.cap_decision
    assert d is not None and d["step"] == 10 and 0.0 <= d["share"] < 1.0 and d["cap"] == 8400
    assert clean.strategy.cap_max == 8400 and clean.num_points == 8400
    crowded = _train_with_transients_rule(tmp_path / "crowded", clean_share=0.0)
    assert crowded.cap_decision["cap"] == 8100 and crowded.num_points == 8100
    state = clean.get_extra_state()
    crowded.set_extra_state(state)  # as a resumed run loads it
    assert crowded.strategy.cap_max == 8400 and crowded.cap_decision == d
