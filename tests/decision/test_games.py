"""Normal-form games, baselines and finite-stage trees (thesis Sec. 5.2, 5.3)."""

from __future__ import annotations

import itertools

import numpy as np
import pytest
import torch
from scipy.optimize import linprog

from hgpdm_torch.decision.games import (
    RPS_REWARD,
    TABLE_TENNIS_REWARD,
    FiniteStageGame,
    as_rng,
    best_response,
    check_strategy,
    expected_reward,
    fictitious_play,
    minimax_equilibrium,
    minimax_strategy,
    sample_counts,
    two_stage_rps,
)


def test_expected_reward_matches_monte_carlo() -> None:
    rng = np.random.default_rng(0)
    pi_i, pi_j = np.array([0.2, 0.5, 0.3]), np.array([0.6, 0.2, 0.2])
    n = 200_000
    a_i = rng.choice(3, size=n, p=pi_i)
    a_j = rng.choice(3, size=n, p=pi_j)
    samples = RPS_REWARD[a_i, a_j]
    se = samples.std() / np.sqrt(n)
    assert abs(expected_reward(RPS_REWARD, pi_i, pi_j) - samples.mean()) < 4 * se


@pytest.mark.parametrize("reward", [RPS_REWARD, TABLE_TENNIS_REWARD, np.array([[3.0, -1.0]])])
def test_minimax_against_brute_force_grid(reward: np.ndarray) -> None:
    pi, value = minimax_strategy(reward)
    assert np.isclose(pi.sum(), 1.0) and (pi >= 0).all()
    assert np.isclose((reward.T @ pi).min(), value)
    # no strategy on a fine grid guarantees more
    n_i = reward.shape[0]
    steps = 60
    best = -np.inf
    for k in itertools.product(range(steps + 1), repeat=n_i - 1):
        if sum(k) <= steps:
            grid_pi = np.array([*k, steps - sum(k)]) / steps
            best = max(best, (reward.T @ grid_pi).min())
    assert best <= value + 1e-9
    assert best >= value - 2 * np.abs(reward).max() / steps
    # the opponent's minimax strategy holds Player i to the same value (minimax theorem)
    q, neg_value = minimax_strategy(-reward.T)
    assert np.isclose((reward @ q).max(), value, atol=1e-7)
    assert np.isclose(-neg_value, value, atol=1e-7)


def test_minimax_equilibrium_brackets_the_value() -> None:
    # primal and dual of one LP: each player's guarantee, equal up to floating point
    rng = np.random.default_rng(8)
    for _ in range(30):
        reward = rng.normal(size=tuple(rng.integers(1, 7, size=2)))
        pi, q = minimax_equilibrium(reward)
        assert (pi >= 0).all() and (q >= 0).all()
        assert np.isclose(pi.sum(), 1.0) and np.isclose(q.sum(), 1.0)
        lower, upper = (reward.T @ pi).min(), (reward @ q).max()
        assert -1e-12 <= upper - lower <= 1e-9
        # the opponent's strategy solves the opponent's own LP
        assert (reward @ minimax_strategy(-reward.T)[0]).max() == pytest.approx(upper, abs=1e-9)


@pytest.mark.parametrize("scale", [1e300, 1e-300, 1e-12, 1e12])
def test_minimax_at_any_scale(scale: float) -> None:
    """Issue 54: rewards near 1e300 made HiGHS fail ("Model error") and rewards near 1e-300
    all looked alike (RPS gave a pure strategy). Oracle: the 2x2 closed form without a saddle
    point, ``p = (d - c) / (a - b - c + d)``, value ``(a d - b c) / (a - b - c + d)``, and RPS
    (uniform, value 0); the strategy is invariant to the scale and the value scales with it."""
    a, b, c, d = 3.0, -1.0, -2.0, 4.0
    pi, value = minimax_strategy(scale * np.array([[a, b], [c, d]]))
    p = (d - c) / (a - b - c + d)
    np.testing.assert_allclose(pi, [p, 1 - p], atol=1e-9)
    assert value == pytest.approx(scale * (a * d - b * c) / (a - b - c + d), rel=1e-9)
    pi, q = minimax_equilibrium(scale * RPS_REWARD)
    np.testing.assert_allclose(pi, np.full(3, 1 / 3), atol=1e-9)
    np.testing.assert_allclose(q, np.full(3, 1 / 3), atol=1e-9)
    pi, value = minimax_strategy(scale * RPS_REWARD)
    assert abs(value) <= 1e-9 * scale


def test_thesis_minimax_numbers() -> None:
    pi, value = minimax_strategy(RPS_REWARD)
    np.testing.assert_allclose(pi, np.full(3, 1 / 3), atol=1e-8)
    assert abs(value) < 1e-9
    pi, value = minimax_strategy(TABLE_TENNIS_REWARD)
    # Oracle: the classic reformulation min 1^T x s.t. (R + k)^T x >= 1, x >= 0 (pi = x / 1^T x,
    # value = 1 / 1^T x - k) solved by scipy's interior-point HiGHS, not the simplex of the code.
    k = 1.0 - TABLE_TENNIS_REWARD.min()
    res = linprog(
        np.ones(3),
        A_ub=-(TABLE_TENNIS_REWARD + k).T,
        b_ub=-np.ones(3),
        bounds=[(0, None)] * 3,
        method="highs-ipm",
    )
    assert res.status == 0
    np.testing.assert_allclose(pi, res.x / res.x.sum(), atol=1e-6)
    assert value == pytest.approx(1.0 / res.x.sum() - k, abs=1e-6)
    # By hand: the forehand and backhand-side columns equalise at p_forehand = 0.15 / 0.74.
    np.testing.assert_allclose(pi, [15 / 74, 59 / 74, 0.0], atol=1e-6)
    # Sec. 5.4.2 prints [0.2088, 0.7912, 0]: computed from the unrounded success rates, so the
    # two-digit Table 5.3 can only match it loosely.
    np.testing.assert_allclose(pi, [0.2088, 0.7912, 0.0], atol=0.01)


def test_best_response_and_fictitious_play() -> None:
    np.testing.assert_allclose(best_response(RPS_REWARD, [0.6, 0.2, 0.2]), [0, 1, 0])
    np.testing.assert_allclose(best_response(RPS_REWARD, np.full(3, 1 / 3)), np.full(3, 1 / 3))
    np.testing.assert_allclose(fictitious_play(RPS_REWARD, [1, 7, 2]), [0, 0, 1])
    np.testing.assert_allclose(fictitious_play(RPS_REWARD, [0, 0, 0]), np.full(3, 1 / 3))
    br = best_response(TABLE_TENNIS_REWARD, [1 / 3] * 3)
    np.testing.assert_allclose(br, [0, 1, 0])  # the middle pose, as in Fig. 5.5


def test_sample_counts_multinomial(generator: torch.Generator) -> None:
    p = np.array([0.6, 0.2, 0.2])
    counts = np.array([sample_counts(p, 1000, 7 + s) for s in range(400)])
    assert (counts.sum(1) == 1000).all()
    se = np.sqrt(1000 * p * (1 - p) / 400)
    np.testing.assert_array_less(np.abs(counts.mean(0) - 1000 * p), 4 * se)
    big = sample_counts(p, 10**8, generator)
    assert big.sum() == 10**8
    np.testing.assert_allclose(big / 1e8, p, atol=5e-4)
    assert (sample_counts(p, 0, 1) == 0).all()
    np.testing.assert_array_equal(sample_counts(p, 50, 3), sample_counts(p, 50, 3))


def test_as_rng_accepts_seeds_and_generators(generator: torch.Generator) -> None:
    assert isinstance(as_rng(3), np.random.Generator)
    assert isinstance(as_rng(generator), np.random.Generator)
    g = np.random.default_rng(1)
    assert as_rng(g) is g
    with pytest.raises(TypeError, match="generator"):
        as_rng(1.5)  # type: ignore[arg-type]


def test_two_stage_values_against_enumeration() -> None:
    game = two_stage_rps()
    assert game.n_states == 10
    rng = np.random.default_rng(2)
    pis = [rng.dirichlet(np.ones(3)) for _ in range(10)]
    pjs = [rng.dirichlet(np.ones(3)) for _ in range(10)]
    total = 0.0
    for a_i, a_j, b_i, b_j in itertools.product(range(3), repeat=4):
        child = 1 + 3 * a_i + a_j
        prob = pis[0][a_i] * pjs[0][a_j] * pis[child][b_i] * pjs[child][b_j]
        total += prob * (RPS_REWARD[a_i, a_j] + 2 * RPS_REWARD[b_i, b_j])
    assert np.isclose(game.values(pis, pjs)[0], total)
    # backward induction beats every sampled profile and attains its own value
    br, v = game.best_response(pjs)
    assert np.isclose(game.values(br, pjs)[0], v[0])
    for _ in range(20):
        other = [rng.dirichlet(np.ones(3)) for _ in range(10)]
        assert game.values(other, pjs)[0] <= v[0] + 1e-12
    order = game.bottom_up()
    assert order[-1] == 0 and sorted(order) == list(range(10))


def test_finite_stage_game_stores_validated_arrays() -> None:
    # nested lists and None leaves are accepted and stored as float arrays
    rps = RPS_REWARD.tolist()
    game = FiniteStageGame(
        (rps, rps, rps),
        ([1, 2], [], []),
        (np.full((3, 3, 2), 0.5).tolist(), None, None),
    )
    assert all(isinstance(r, np.ndarray) and r.dtype == np.float64 for r in game.rewards)
    assert game.transitions[1].shape == (3, 3, 0)
    assert game.children == ((1, 2), (), ())
    pi = [1 / 3] * 3
    # uniform play: every stage has value 0 in RPS
    np.testing.assert_allclose(game.values([pi] * 3, [pi] * 3), 0.0, atol=1e-15)
    rock = [1.0, 0.0, 0.0]
    # R[paper, rock] = 1 at the root and in whichever leaf follows (each with probability 1/2)
    paper = [0.0, 1.0, 0.0]
    np.testing.assert_allclose(game.values([paper] * 3, [rock] * 3), [2.0, 1.0, 1.0])
    br, v = game.best_response([rock] * 3)
    np.testing.assert_allclose(v, [2.0, 1.0, 1.0])
    np.testing.assert_allclose(br[0], paper)


def test_bad_inputs_raise() -> None:
    with pytest.raises(ValueError, match="strategy_i"):
        expected_reward(RPS_REWARD, [0.5, 0.6, -0.1], [1 / 3] * 3)
    with pytest.raises(ValueError, match="strategy_j.*3 entries"):
        expected_reward(RPS_REWARD, [1 / 3] * 3, [0.5, 0.5])
    with pytest.raises(ValueError, match="reward.*2 dimensions"):
        minimax_strategy([1.0, 2.0])
    with pytest.raises(ValueError, match="NaN"):
        minimax_strategy([[np.nan, 1.0]])
    with pytest.raises(TypeError, match="reward"):
        minimax_strategy("abc")
    with pytest.raises(ValueError, match="counts.*integer"):
        fictitious_play(RPS_REWARD, [1.5, 0, 0])
    with pytest.raises(ValueError, match="counts.*3 entries"):
        fictitious_play(RPS_REWARD, [1, 0])
    with pytest.raises(ValueError, match="n_samples"):
        sample_counts([0.5, 0.5], -1, 0)
    with pytest.raises(ValueError, match="probability vector"):
        check_strategy([0.2, 0.2], 2, "pi")
    with pytest.raises(ValueError, match="transitions"):
        FiniteStageGame(
            (RPS_REWARD, RPS_REWARD), ((1,), ()), (np.ones((3, 3, 2)), np.zeros((3, 3, 0)))
        )
    with pytest.raises(ValueError, match="tree"):
        FiniteStageGame(
            (RPS_REWARD, RPS_REWARD), ((1,), (1,)), (np.ones((3, 3, 1)), np.ones((3, 3, 1)))
        )
    with pytest.raises(ValueError, match="transitions\\[1\\] must have 3 dimensions"):
        FiniteStageGame((RPS_REWARD, RPS_REWARD), ((1,), ()), (np.ones((3, 3, 1)), [[1.0]]))
    with pytest.raises(TypeError, match="transitions\\[0\\]"):
        FiniteStageGame((RPS_REWARD, RPS_REWARD), ((1,), ()), (None, None))
    with pytest.raises(TypeError, match="children\\[0\\].*integer"):
        FiniteStageGame((RPS_REWARD, RPS_REWARD), ((1.0,), ()), (np.ones((3, 3, 1)), None))
    with pytest.raises(ValueError, match="one strategy per state"):
        two_stage_rps().values([np.full(3, 1 / 3)], [np.full(3, 1 / 3)])
