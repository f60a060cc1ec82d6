"""Delta-safe opponent modelling (thesis Sec. 5.2-5.3), each solver against an oracle."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from scipy.optimize import minimize
from scipy.stats import chi2_contingency

from hgpdm_torch.decision.games import (
    RPS_REWARD,
    TABLE_TENNIS_REWARD,
    best_response,
    minimax_strategy,
    sample_counts,
    two_stage_rps,
)
from hgpdm_torch.decision.opponent import (
    AdaptiveLearner,
    DeltaSafeResponder,
    KLBall,
    delta_safe_tree,
    kl_bound,
    kl_divergence,
    solve_delta_safe,
    two_sample_z_test,
)


def _random_problem(rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    n_i, n_j = rng.integers(2, 5, size=2)
    reward = rng.normal(size=(n_i, n_j))
    counts = rng.multinomial(int(10 ** rng.uniform(0, 5)), rng.dirichlet(np.ones(n_j)))
    return reward, counts


def _primal_worst_case(c: np.ndarray, p: np.ndarray, eps: float) -> float:
    """``min c^T q`` over the KL ball, straight from the primal with SLSQP: ``c^T q`` of the
    best of several SLSQP runs, each pulled strictly into the ball, so an upper bound on the
    minimum up to rounding.

    SLSQP meets the KL constraint only to its tolerance (~1e-9): the value of a point that far
    outside is below the minimum by the KL multiplier (~1 / sqrt(eps), 1e3 at eps = 1e-6) times
    that, and by how much depends on its BLAS path. Pulling ``q`` towards the centre ``p``,
    ``(1 - t) q + t p`` with ``t = 1 - eps / KL(p || q)``, makes it feasible, as KL(p || .) is
    convex and zero at ``p``; the value moves by about that same multiplier times the excess."""
    on = p > 0
    cons = [
        {"type": "eq", "fun": lambda q: q.sum() - 1.0},
        {"type": "ineq", "fun": lambda q: eps - np.sum(p[on] * np.log(p[on] / q[on]))},
    ]
    bounds = [(1e-12 if o else 0.0, 1.0) for o in on]
    best = math.inf
    # SLSQP can end on an infeasible point: keep the best feasible result of several starts.
    for w in (0.5, 0.9, 0.1):
        res = minimize(
            lambda q: c @ q,
            w * p + (1 - w) / p.size,
            method="SLSQP",
            bounds=bounds,
            constraints=cons,
            options={"ftol": 1e-14, "maxiter": 500},
        )
        q = np.clip(res.x, 1e-300, None)
        if abs(q.sum() - 1) >= 1e-9:
            continue
        q = q / q.sum()
        kl = np.sum(p[on] * np.log(p[on] / q[on]))
        if not kl <= eps + 1e-9:
            continue
        if kl > eps:
            t = 1.0 - eps / kl
            q = (1.0 - t) * q + t * p
        best = min(best, float(c @ q))
    assert math.isfinite(best), "the SLSQP reference found no feasible point"
    return best


def test_kl_bound_formula_and_coverage() -> None:
    assert kl_bound(0.1, 0, 3) == math.inf
    expected = (2 * math.log(101) - math.log(0.1)) / 100
    assert math.isclose(kl_bound(0.1, 100, 3), expected)
    assert math.isclose(
        kl_bound(0.1, 100, 3, n_states=10), (2 * math.log(101) - math.log(0.01)) / 100
    )
    # the true strategy lies in the ball in at least 1 - delta of the draws
    rng = np.random.default_rng(0)
    truth = np.array([0.6, 0.2, 0.2])
    for n, delta in [(5, 0.5), (50, 0.2), (500, 0.05)]:
        eps = kl_bound(delta, n, 3)
        inside = [kl_divergence(rng.multinomial(n, truth) / n, truth) <= eps for _ in range(2000)]
        assert np.mean(inside) >= 1 - delta


def test_kl_divergence_values() -> None:
    assert kl_divergence([0.5, 0.5], [0.5, 0.5]) == 0.0
    assert math.isclose(kl_divergence([1.0, 0.0], [0.5, 0.5]), math.log(2))
    assert kl_divergence([0.5, 0.5], [1.0, 0.0]) == math.inf


def test_worst_case_matches_primal_and_certifies_itself() -> None:
    rng = np.random.default_rng(1)
    for trial in range(40):
        n = int(rng.integers(2, 6))
        c = rng.normal(size=n)
        p = rng.dirichlet(np.ones(n))
        if trial % 3 == 0:  # an unobserved action, sometimes the cheapest one
            p[rng.integers(n)] = 0.0
            p /= p.sum()
        eps = float(10 ** rng.uniform(-6, 1))
        ball = KLBall(p, eps)
        value, q = ball.worst_case(c)
        # q is a member and attains the dual value: weak duality makes both optimal
        assert ball.contains(q, atol=1e-10)
        assert math.isclose(c @ q, value, abs_tol=1e-12)
        # the reference is a feasible value: ours is at most the rounding of its KL (a few eps
        # times n |ln(p / q)| <= 1) times the KL multiplier (<= |c| / sqrt(eps)) above it, plus
        # that of c^T q (n eps |c|); 64 eps for the few terms (measured: up to 2e-14)
        primal = _primal_worst_case(c, p, eps)
        scale = float(np.abs(c).max()) * (1.0 + 1.0 / math.sqrt(eps))
        assert value <= primal + 64 * np.finfo(float).eps * n * scale
        assert value >= primal - 1e-6  # SLSQP's accuracy


def test_worst_case_special_cases() -> None:
    c = np.array([1.0, 2.0, -1.0])
    # single observed action: q_a >= e^-eps, the rest on the cheapest action
    value, q = KLBall(np.array([0.0, 1.0, 0.0]), 0.5).worst_case(c)
    w = math.exp(-0.5)
    assert math.isclose(value, 2 * w - (1 - w))
    np.testing.assert_allclose(q, [0, w, 1 - w])
    assert KLBall(np.array([0.2, 0.3, 0.5]), 0.0).worst_case(c)[0] == pytest.approx(0.3)
    assert KLBall(np.array([0.2, 0.3, 0.5]), math.inf).worst_case(c)[0] == -1.0
    huge = KLBall(np.array([0.2, 0.3, 0.5]), 5000.0).worst_case(c)[0]  # no overflow
    assert huge == pytest.approx(-1.0, abs=1e-9)


def test_exact_solver_against_grid_search() -> None:
    rng = np.random.default_rng(2)
    steps = 80
    grid = (
        np.array([(a, b, steps - a - b) for a in range(steps + 1) for b in range(steps + 1 - a)])
        / steps
    )
    for _ in range(6):
        reward = rng.normal(size=(3, 3))
        counts = rng.multinomial(int(rng.integers(5, 500)), rng.dirichlet(np.ones(3)))
        res = solve_delta_safe(reward, counts, 0.1)
        assert res.upper_bound - res.value <= 1e-6
        ball = KLBall.from_counts(counts, 0.1)
        assert math.isclose(ball.worst_case(reward.T @ res.strategy)[0], res.value, abs_tol=1e-12)
        best = max(ball.worst_case(reward.T @ pi)[0] for pi in grid)
        assert best <= res.value + 1e-9
        assert best >= res.value - 2 * np.abs(reward).max() / steps


def test_subgradient_is_certified_to_tol_on_many_problems() -> None:
    # The responder's contract: upper_bound - value <= tol * range on every problem, so its
    # value is within that of the certified optimum (cutting planes to 1e-9).
    rng = np.random.default_rng(3)
    fallbacks = 0
    for _ in range(150):
        reward, counts = _random_problem(rng)
        tol = 1e-4 * np.ptp(reward)
        exact = solve_delta_safe(reward, counts, 0.1, tol=1e-9)
        res = DeltaSafeResponder(reward).respond(counts, 0.1)
        fallbacks += res.cutting_planes > 0
        assert res.upper_bound - res.value <= tol
        assert res.value <= exact.upper_bound + 1e-9  # never claims more than the optimum
        assert res.upper_bound >= exact.value - 1e-9  # the certificate is a real upper bound
        assert res.value >= exact.value - tol
        # the reported value is exact for the reported strategy
        ball = KLBall.from_counts(counts, 0.1)
        assert math.isclose(ball.worst_case(reward.T @ res.strategy)[0], res.value, abs_tol=1e-12)
    assert fallbacks > 0  # the sub-gradient steps alone stall on some of these problems


def test_subgradient_warm_start_along_a_stream() -> None:
    # warm start along a stream of observations, as the online learner uses it
    rng = np.random.default_rng(13)
    responder = DeltaSafeResponder(TABLE_TENNIS_REWARD)
    tol = 1e-4 * np.ptp(TABLE_TENNIS_REWARD)
    counts = np.zeros(3, dtype=int)
    for t in range(300):
        counts[rng.choice(3, p=[0.7, 0.2, 0.1])] += 1
        res = responder.respond(counts, 0.1)
        assert res.upper_bound - res.value <= tol
        if t % 30 == 29:
            exact = solve_delta_safe(TABLE_TENNIS_REWARD, counts, 0.1, tol=1e-9)
            assert exact.value - tol <= res.value <= exact.upper_bound + 1e-9


def test_certified_without_subgradient_steps() -> None:
    # max_iter=0: Newton steps from minimax, then the cutting planes wherever they stall
    rng = np.random.default_rng(14)
    planes = 0
    for _ in range(10):
        reward, counts = _random_problem(rng)
        res = DeltaSafeResponder(reward, max_iter=0).respond(counts, 0.1)
        planes += res.cutting_planes
        assert res.upper_bound - res.value <= 1e-4 * np.ptp(reward)
        exact = solve_delta_safe(reward, counts, 0.1, tol=1e-9)
        assert res.value >= exact.value - 1e-4 * np.ptp(reward)
    assert planes > 0


def test_small_delta_limit_is_minimax() -> None:
    # delta -> 0 grows the ball to the whole simplex; Problem (38) becomes the minimax LP
    for reward in (RPS_REWARD, TABLE_TENNIS_REWARD):
        pi_mm, v_mm = minimax_strategy(reward)
        counts = np.array([40, 5, 5])
        values = [solve_delta_safe(reward, counts, d).value for d in (1e-2, 1e-20, 1e-300)]
        assert values[0] >= values[1] >= values[2] >= v_mm - 1e-9  # monotone in delta
        assert values[2] == pytest.approx(v_mm, abs=1e-3)
        res = DeltaSafeResponder(reward).respond(np.zeros(3, dtype=int), 0.1)
        np.testing.assert_allclose(res.strategy, pi_mm)
        assert res.value == pytest.approx(v_mm)


def test_many_samples_converge_to_best_response() -> None:
    truth = np.array([0.6, 0.2, 0.2])
    br = best_response(RPS_REWARD, truth)
    optimum = br @ RPS_REWARD @ truth
    gaps = []
    for n in (10**2, 10**4, 10**8):
        counts = sample_counts(truth, n, 11)
        res = DeltaSafeResponder(RPS_REWARD).respond(counts, 0.1)
        gaps.append(optimum - res.strategy @ RPS_REWARD @ truth)
    assert gaps[0] >= gaps[1] >= gaps[2] >= -1e-12
    assert gaps[2] < 1e-3
    res = DeltaSafeResponder(RPS_REWARD).respond(sample_counts(truth, 10**8, 12), 0.1)
    np.testing.assert_allclose(res.strategy, br, atol=1e-6)


@pytest.mark.parametrize("delta", [0.05, 0.3])
def test_lower_bound_holds_in_one_minus_delta_of_runs(delta: float) -> None:
    rng = np.random.default_rng(4)
    truth = np.array([0.5, 0.3, 0.2])
    responder = DeltaSafeResponder(TABLE_TENNIS_REWARD)
    held = []
    for _ in range(300):
        counts = rng.multinomial(30, truth)
        res = responder.respond(counts, delta)
        held.append(res.strategy @ TABLE_TENNIS_REWARD @ truth >= res.value - 1e-12)
    assert np.mean(held) >= 1 - delta


def test_two_sample_z_test_against_chi_square() -> None:
    x, y = np.array([50, 30, 20]), np.array([20, 30, 50])
    z, passed = two_sample_z_test(x, y, alpha=0.05)
    assert not passed
    for k in range(3):
        table = np.array([[x[k], x.sum() - x[k]], [y[k], y.sum() - y[k]]])
        chi2 = chi2_contingency(table, correction=False)[0]
        assert z[k] ** 2 == pytest.approx(chi2)
    assert two_sample_z_test([40, 30, 30], [38, 33, 29])[1]
    z, passed = two_sample_z_test([5, 0, 0], [7, 0, 0])  # never-seen actions carry no evidence
    assert passed and (z == 0).all()
    # size of the test: false rejections of one action's test at about alpha
    rng = np.random.default_rng(5)
    rejections = [
        abs(
            two_sample_z_test(rng.multinomial(256, [0.5, 0.5]), rng.multinomial(256, [0.5, 0.5]))[
                0
            ][0]
        )
        > 1.959964
        for _ in range(2000)
    ]
    assert abs(np.mean(rejections) - 0.05) < 4 * math.sqrt(0.05 * 0.95 / 2000)


def _run(learner: AdaptiveLearner, strategies: list[np.ndarray], switch: int, n: int, seed: int):
    rng = np.random.default_rng(seed)
    for t in range(n):
        learner.observe(int(rng.choice(3, p=strategies[int(t >= switch)])))
    return learner


def test_adaptive_learner_detects_switch_and_rarely_false_alarms() -> None:
    before, after = np.array([0.8, 0.1, 0.1]), np.array([0.1, 0.1, 0.8])
    n_min, switch = 64, 640
    delays = []
    for seed in range(5):
        learner = _run(
            AdaptiveLearner(RPS_REWARD, n_min=n_min), [before, after], switch, 1000, seed
        )
        after_switch = [r for r in learner.resets if r >= switch]
        assert after_switch
        delays.append(after_switch[0] - switch)
        # after the reset it learns the new best response (rock against scissors)
        assert learner.strategy[0] > 0.5
    assert max(delays) <= 3 * n_min
    # without a switch, alarms are rare: at most a few of the tests
    alarms = tests = 0
    for seed in range(5):
        learner = _run(
            AdaptiveLearner(RPS_REWARD, n_min=n_min), [before, before], 10**9, 1000, seed
        )
        alarms += len(learner.resets)
        tests += (1000 - n_min) // n_min
    assert alarms / tests <= 0.1
    # the simplified version never resets and, misled by stale data, earns less after the switch
    for seed in range(3):
        stale = _run(
            AdaptiveLearner(RPS_REWARD, n_min=n_min, change_detection=False),
            [before, after],
            switch,
            1000,
            seed,
        )
        fresh = _run(AdaptiveLearner(RPS_REWARD, n_min=n_min), [before, after], switch, 1000, seed)
        assert not stale.resets
        assert stale.strategy @ RPS_REWARD @ after < fresh.strategy @ RPS_REWARD @ after - 0.1


def test_adaptive_learner_follows_algorithm_5_1() -> None:
    learner = AdaptiveLearner(RPS_REWARD, n_min=4, delta=lambda n: 1.0 / (n + 1))
    np.testing.assert_allclose(learner.strategy, np.full(3, 1 / 3))
    for _ in range(4):  # X phase: re-solved after every sample
        learner.observe(0)
    assert learner.counts.sum() == 4
    fixed = learner.strategy.copy()
    for _ in range(3):  # Y phase: the strategy stays fixed until the block is full
        learner.observe(0)
        np.testing.assert_array_equal(learner.strategy, fixed)
    learner.observe(0)
    assert learner.counts.sum() == 8  # the test passed, Y merged into X
    for _ in range(4):
        learner.observe(2)  # a very different block fails the test: reset to minimax
    assert learner.resets == [11] and learner.counts.sum() == 0
    np.testing.assert_allclose(learner.strategy, np.full(3, 1 / 3))


def test_adaptive_learner_act_draws_fresh_actions() -> None:
    learner = AdaptiveLearner(RPS_REWARD, generator=5)
    n = 3000
    actions = np.array([learner.act() for _ in range(n)])
    # minimax strategy of RPS: each action with probability 1/3, within 4 standard errors
    freq = np.bincount(actions, minlength=3) / n
    np.testing.assert_array_less(np.abs(freq - 1 / 3), 4 * math.sqrt(2 / 9 / n))
    # the same seed replays the same sequence
    again = AdaptiveLearner(RPS_REWARD, generator=5)
    np.testing.assert_array_equal([again.act() for _ in range(n)], actions)
    # a numpy generator is used, not copied
    rng = np.random.default_rng(6)
    AdaptiveLearner(RPS_REWARD, generator=rng).act()
    assert rng.bit_generator.state != np.random.default_rng(6).bit_generator.state
    with pytest.raises(ValueError, match="generator"):
        AdaptiveLearner(RPS_REWARD).act()
    with pytest.raises(TypeError, match="generator"):
        AdaptiveLearner(RPS_REWARD, generator=0.5)  # type: ignore[arg-type]


def test_delta_safe_tree_bounds_and_limits() -> None:
    game = two_stage_rps()
    opponents = (
        [np.array([0.6, 0.2, 0.2])] + [np.array([1 / 3] * 3)] * 4 + [np.array([0.2, 0.6, 0.2])] * 5
    )
    # no data anywhere: maximin backward induction, value 0 in RPS
    empty = [np.zeros(3, dtype=int)] * 10
    res = delta_safe_tree(game, empty, 0.1)
    assert res.values[0] == pytest.approx(0.0, abs=1e-9)
    # the root value lower-bounds the learned strategies' true return in >= 1 - delta of runs
    rng = np.random.default_rng(6)
    held = []
    for _ in range(40):
        counts = [rng.multinomial(200, p) for p in opponents]
        res = delta_safe_tree(game, counts, 0.2)
        held.append(game.values(res.strategies, opponents)[0] >= res.values[0] - 1e-9)
    assert np.mean(held) >= 0.8
    # subgradient and exact agree; huge samples reach the globally optimal return
    counts = [sample_counts(p, 10**7, 7) for p in opponents]
    sg = delta_safe_tree(game, counts, 0.1)
    ex = delta_safe_tree(game, counts, 0.1, method="exact")
    assert sg.values[0] == pytest.approx(ex.values[0], abs=5e-3)
    optimum = game.best_response(opponents)[1][0]
    assert game.values(sg.strategies, opponents)[0] == pytest.approx(optimum, abs=5e-3)


def test_bad_inputs_raise_clear_errors() -> None:
    with pytest.raises(ValueError, match="delta must lie in"):
        kl_bound(1.0, 10, 3)
    with pytest.raises(ValueError, match="delta must lie in"):
        DeltaSafeResponder(RPS_REWARD).respond([1, 2, 3], 0.0)
    with pytest.raises(TypeError, match="delta"):
        kl_bound("0.1", 10, 3)  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="n_samples"):
        kl_bound(0.1, -1, 3)
    with pytest.raises(ValueError, match="counts.*3 entries"):
        DeltaSafeResponder(RPS_REWARD).respond([1, 2], 0.1)
    with pytest.raises(ValueError, match="counts.*non-negative integer"):
        solve_delta_safe(RPS_REWARD, [1, -2, 3], 0.1)
    with pytest.raises(ValueError, match="tol"):
        solve_delta_safe(RPS_REWARD, [1, 2, 3], 0.1, tol=0.0)
    with pytest.raises(ValueError, match="max_iter"):
        solve_delta_safe(RPS_REWARD, [1, 2, 3], 0.1, max_iter=0)
    with pytest.raises(ValueError, match="center.*probability"):
        KLBall(np.array([0.5, 0.6]), 0.1)
    with pytest.raises(ValueError, match="payoff"):
        KLBall(np.array([0.5, 0.5]), 0.1).worst_case([1.0, 2.0, 3.0])
    with pytest.raises(ValueError, match="at least one observation"):
        two_sample_z_test([0, 0, 0], [1, 2, 3])
    with pytest.raises(ValueError, match="counts_y"):
        two_sample_z_test([1, 2, 3], [1, 2])
    with pytest.raises(ValueError, match="n_min"):
        AdaptiveLearner(RPS_REWARD, n_min=0)
    with pytest.raises(ValueError, match="action"):
        AdaptiveLearner(RPS_REWARD).observe(3)
    with pytest.raises(ValueError, match="one vector per state"):
        delta_safe_tree(two_stage_rps(), [np.zeros(3)], 0.1)
    with pytest.raises(ValueError, match="method"):
        delta_safe_tree(two_stage_rps(), [np.zeros(3)] * 10, 0.1, method="magic")


@pytest.mark.parametrize(
    "radius",
    [np.float32(0.25), np.float64(0.25), np.array(0.25), torch.tensor(0.25), 0.25, np.int64(0)],
    ids=["float32", "float64", "0-dim array", "0-dim tensor", "float", "int64"],
)
def test_kl_ball_accepts_any_real_scalar_radius(radius) -> None:
    ball = KLBall(np.array([0.5, 0.3, 0.2]), radius)
    assert type(ball.radius) is float and ball.radius == pytest.approx(float(radius))
    reference = KLBall(np.array([0.5, 0.3, 0.2]), float(radius))
    value, q = ball.worst_case([1.0, 0.0, -1.0])
    assert value == pytest.approx(reference.worst_case([1.0, 0.0, -1.0])[0], abs=1e-12)
    assert ball.contains(q, atol=1e-9)


@pytest.mark.parametrize(
    "radius,error,match",
    [
        (-0.1, ValueError, "radius must be a non-negative"),
        (np.float32(-1.0), ValueError, "radius must be a non-negative"),
        (math.nan, ValueError, "radius must be a non-negative"),
        (torch.tensor(float("nan")), ValueError, "radius must be a non-negative"),
        ("0.1", TypeError, "radius must be a real number"),
        (True, TypeError, "radius must be a real number"),
        (np.array([0.1, 0.2]), TypeError, r"radius must be a real number, got an array"),
        (torch.tensor([0.1]), TypeError, r"radius must be a real number, got an array"),
    ],
)
def test_kl_ball_rejects_bad_radius(radius, error, match) -> None:
    with pytest.raises(error, match=match):
        KLBall(np.array([0.5, 0.5]), radius)


def test_numpy_and_tensor_scalars_elsewhere() -> None:
    assert kl_bound(np.float32(0.1), np.int32(10), torch.tensor(3)) == pytest.approx(
        kl_bound(0.1, 10, 3), rel=1e-6
    )
    learner = AdaptiveLearner(RPS_REWARD, n_min=np.int64(4), alpha=np.float32(0.05))
    learner.observe(torch.tensor(1))
    learner.observe(np.int8(2))
    assert learner.counts.tolist() == [0, 1, 1]
    DeltaSafeResponder(RPS_REWARD, tol=np.float32(1e-3), max_iter=np.int64(50))
    with pytest.raises(TypeError, match="n_samples"):
        kl_bound(0.1, 2.5, 3)
    with pytest.raises(ValueError, match="tol"):
        DeltaSafeResponder(RPS_REWARD, tol=math.inf)
    with pytest.raises(ValueError, match="alpha"):
        two_sample_z_test([1, 2, 3], [3, 2, 1], alpha=np.float64(math.nan))
    with pytest.raises(ValueError, match="action"):
        AdaptiveLearner(RPS_REWARD).observe(torch.tensor(0.5))


def test_opponent_package_re_exports_each_concept_module() -> None:
    """``hgpdm_torch.decision.opponent`` re-exports exactly the public names of its modules."""
    import importlib
    import pkgutil

    import hgpdm_torch.decision.opponent as package

    names: dict[str, object] = {}
    for info in pkgutil.iter_modules(package.__path__):
        module = importlib.import_module(f"{package.__name__}.{info.name}")
        assert module.__doc__
        for name in getattr(module, "__all__", ()):
            assert name not in names
            names[name] = getattr(module, name)
    assert set(package.__all__) == set(names)
    assert all(getattr(package, name) is obj for name, obj in names.items())
