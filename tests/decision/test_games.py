"""Normal-form games, baselines and finite-stage trees (thesis Sec. 5.2, 5.3)."""

from __future__ import annotations

import itertools

import numpy as np
import pytest
import torch

from hgpdm_torch.decision.games import (
    RPS_REWARD,
    TABLE_TENNIS_REWARD,
    FiniteStageGame,
    as_rng,
    best_response,
    check_strategy,
    expected_reward,
    fictitious_play,
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


def test_thesis_minimax_numbers() -> None:
    pi, value = minimax_strategy(RPS_REWARD)
    np.testing.assert_allclose(pi, np.full(3, 1 / 3), atol=1e-8)
    assert abs(value) < 1e-9
    # Sec. 5.4.2: [0.2088 forehand, 0.7912 middle, 0 backhand] from the unrounded matrix; the
    # two-digit Table 5.3 gives [0.2027, 0.7973, 0].
    pi, _ = minimax_strategy(TABLE_TENNIS_REWARD)
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
    with pytest.raises(ValueError, match="one strategy per state"):
        two_stage_rps().values([np.full(3, 1 / 3)], [np.full(3, 1 / 3)])
