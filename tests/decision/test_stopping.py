"""The optimal-stopping container: episodes, exploration policy, transitions, evaluation."""

from __future__ import annotations

import itertools

import numpy as np
import pytest
import torch
from scipy import stats

from hgpdm_torch.decision.stopping import (
    ACTIONS,
    EXPLORATION,
    WAIT,
    StoppingProblem,
    belief_vector,
)


def _problem(n=6, T=4, F=3, seed=0) -> StoppingProblem:
    gen = torch.Generator().manual_seed(seed)
    beliefs = torch.randn(n, T, F, generator=gen)
    rewards = torch.where(torch.rand(n, 3, T, generator=gen) < 0.5, 1.0, -1.0)
    return StoppingProblem(beliefs, rewards)


def test_enumerated_episodes_cover_every_start_and_movement():
    p = _problem()
    ep = p.enumerate_episodes()
    assert len(ep) == 6 * 4 * 3
    combos = set(
        zip(ep.trial.tolist(), ep.stop_step.tolist(), ep.stop_action.tolist(), strict=True)
    )
    assert combos == set(itertools.product(range(6), range(4), range(1, 4)))
    for i, t, a, r in zip(ep.trial, ep.stop_step, ep.stop_action, ep.reward, strict=True):
        assert r == p.rewards[i, a - 1, t]


def test_uniform_exploration_matches_its_distribution(generator):
    """Stop step: P(tau = t) = 2^-(t+1) for t < T-1 and 2^-(T-1) at T-1; movement uniform."""
    p = _problem(n=50, T=4)
    ep = p.sample_episodes(200, generator=generator)
    assert len(ep) == 50 * 200
    T = p.horizon
    expected = [0.5 ** (t + 1) for t in range(T - 1)] + [0.5 ** (T - 1)]
    counts = torch.bincount(ep.stop_step, minlength=T).numpy()
    assert stats.chisquare(counts, [e * len(ep) for e in expected]).pvalue > 1e-3
    moves = torch.bincount(ep.stop_action, minlength=4)[1:].numpy()
    assert stats.chisquare(moves).pvalue > 1e-3
    assert EXPLORATION[WAIT] == 0.5 and sum(EXPLORATION) == pytest.approx(1.0)


def test_sample_episodes_with_a_policy(generator):
    p = _problem(n=3, T=3)
    probs = torch.zeros(3, 3, 4)
    probs[:, :, WAIT] = 1.0
    probs[:, 2] = torch.tensor([0.0, 0.0, 0.0, 1.0])  # wait, wait, then backhand
    ep = p.sample_episodes(5, probs=probs, generator=generator)
    assert (ep.stop_step == 2).all() and (ep.stop_action == 3).all()
    assert torch.equal(ep.reward, p.rewards[ep.trial, 2, 2])


def test_expected_reward_equals_monte_carlo(generator):
    p = _problem(n=4, T=3)
    probs = torch.softmax(torch.randn(4, 3, 4, generator=generator), -1)
    exact = p.expected_reward(probs)
    ep = p.sample_episodes(20000, probs=probs, generator=generator)
    mc = ep.reward.view(4, -1)
    se = mc.std(1) / mc.shape[1] ** 0.5
    assert ((mc.mean(1) - exact).abs() < 4 * se).all()


def test_transitions_from_episodes():
    p = _problem(n=2, T=3)
    ep = p.episodes(torch.tensor([0, 0, 1]), torch.tensor([2, 1, 0]), torch.tensor([1, 2, 3]))
    tr = p.transitions(ep)
    # waits: episode 0 has 2, episode 1 has 1, episode 2 none; plus 3 stops
    assert len(tr) == 6
    waits = tr.action == WAIT
    assert waits.sum() == 3 and (tr.reward[waits] == 0).all()
    for s, t, i, ns in zip(
        tr.state[waits], tr.step[waits], tr.trial[waits], tr.next_state[waits], strict=True
    ):
        assert torch.equal(s, p.beliefs[i, t]) and torch.equal(ns, p.beliefs[i, t + 1])
    # the wait into the last step allows only stops; stops are absorbing
    last = waits & (tr.step == 1)
    assert (~tr.next_allowed[last, WAIT]).all() and tr.next_allowed[last, 1:].all()
    assert not tr.next_allowed[~waits].any()
    torch.testing.assert_close(tr.reward[~waits], ep.reward)
    unique = p.transitions(ep, unique=True)
    assert (unique.action == WAIT).sum() == 2  # trial 0's wait at step 0 kept once


def test_run_follows_the_policy_and_needs_a_stop_at_the_end():
    p = _problem(n=5, T=3)

    def policy(beliefs, t, idx):
        return torch.where(idx % 2 == 0, 0, 2) if t < 2 else torch.full_like(idx, 1)

    ep = p.run(policy)
    assert ep.stop_step.tolist() == [2, 0, 2, 0, 2]
    assert ep.stop_action.tolist() == [1, 2, 1, 2, 1]
    torch.testing.assert_close(
        ep.reward, p.rewards[torch.arange(5), ep.stop_action - 1, ep.stop_step]
    )
    with pytest.raises(ValueError, match="must stop at the last step"):
        p.run(lambda b, t, i: torch.zeros_like(i))
    with pytest.raises(ValueError, match="one action per trial"):
        p.run(lambda b, t, i: torch.zeros(1, dtype=torch.long))
    with pytest.raises(ValueError, match="outside"):
        p.run(lambda b, t, i: torch.full_like(i, 7))


def test_subset_and_allowed():
    p = _problem()
    s = p.subset(torch.tensor([1, 3]))
    assert len(s) == 2 and torch.equal(s.rewards[1], p.rewards[3])
    assert p.allowed(0).all() and not p.allowed(p.horizon - 1)[WAIT]
    assert p.actions == ACTIONS


def test_bad_input():
    with pytest.raises(ValueError, match="rewards must have shape"):
        StoppingProblem(torch.zeros(2, 3, 1), torch.zeros(2, 3, 4))
    with pytest.raises(ValueError, match="beliefs must have 3"):
        StoppingProblem(torch.zeros(2, 3), torch.zeros(2, 3, 3))
    with pytest.raises(ValueError, match="NaN"):
        StoppingProblem(torch.full((2, 3, 1), float("nan")), torch.zeros(2, 3, 3))
    with pytest.raises(ValueError, match="actions must name"):
        StoppingProblem(torch.zeros(2, 3, 1), torch.zeros(2, 2, 3))
    with pytest.raises(TypeError):
        StoppingProblem("beliefs", torch.zeros(2, 3, 3))
    p = _problem()
    with pytest.raises(ValueError, match="per_trial"):
        p.sample_episodes(0)
    with pytest.raises(ValueError, match="probs must have shape"):
        p.sample_episodes(1, probs=torch.ones(1, 1, 4))
    with pytest.raises(ValueError, match="probs must be non-negative"):
        p.sample_episodes(1, probs=torch.ones(6, 4, 4))
    with pytest.raises(ValueError, match="stop_action"):
        p.episodes(torch.tensor([0]), torch.tensor([0]), torch.tensor([0]))
    with pytest.raises(ValueError, match="stop_step"):
        p.episodes(torch.tensor([0]), torch.tensor([9]), torch.tensor([1]))
    with pytest.raises(TypeError, match="Episodes"):
        p.transitions("episodes")
    with pytest.raises(ValueError, match="probs must be a tensor"):
        p.expected_reward(torch.ones(2, 2, 2))


def test_episodes_index_checks():
    """episodes() takes 1-D whole-number indices of equal length and checks every range; before
    these checks an out-of-range trial raised IndexError, a negative one wrapped around to the
    last trial and 1.7 was truncated to 1."""
    p = _problem(n=3, T=4)
    # accepted: lists, NumPy integer arrays, int32 tensors and whole-number floats
    for args in (
        ([2, 0], [3, 1], [1, 3]),
        (np.array([2, 0]), np.array([3, 1], dtype=np.int32), np.array([1, 3])),
        (torch.tensor([2, 0], dtype=torch.int32), torch.tensor([3.0, 1.0]), (1.0, 3.0)),
    ):
        ep = p.episodes(*args)
        assert ep.trial.dtype == ep.stop_step.dtype == ep.stop_action.dtype == torch.long
        assert ep.trial.tolist() == [2, 0] and ep.stop_step.tolist() == [3, 1]
        assert ep.stop_action.tolist() == [1, 3]
        assert ep.reward.tolist() == [float(p.rewards[2, 0, 3]), float(p.rewards[0, 2, 1])]
    empty = p.episodes([], [], [])
    assert len(empty) == 0 and empty.reward.shape == (0,)
    ok = torch.tensor([0])
    for bad, pattern in (
        (torch.tensor([3]), r"trial must be in 0 \.\. 2, got 3"),
        (torch.tensor([-1]), r"trial must be in 0 \.\. 2, got -1"),
        (torch.tensor([1.5]), "trial must hold whole numbers"),
        (torch.tensor([float("nan")]), "trial must hold finite"),
        (torch.tensor([[0]]), "trial must be 1-D"),
        (torch.tensor(0), "trial must be 1-D"),
    ):
        with pytest.raises(ValueError, match=pattern):
            p.episodes(bad, ok, ok + 1)
    with pytest.raises(ValueError, match="stop_step must hold whole numbers"):
        p.episodes(ok, [1.7], ok + 1)
    with pytest.raises(ValueError, match="stop_action must hold whole numbers"):
        p.episodes(ok, ok, np.array([1.2]))
    with pytest.raises(ValueError, match=r"stop_step must be in 0 \.\. 3, got -1"):
        p.episodes(ok, [-1], ok + 1)
    with pytest.raises(ValueError, match="same length"):
        p.episodes([0, 1], [0, 1], [1])
    with pytest.raises(ValueError, match="same length"):
        p.episodes([0], [0, 1], [1, 1])
    with pytest.raises(TypeError, match="trial must hold integers"):
        p.episodes(torch.tensor([True]), ok, ok + 1)
    with pytest.raises(TypeError, match="stop_action"):
        p.episodes(ok, ok, "1")
    with pytest.raises(TypeError, match="stop_step"):
        p.episodes(ok, object(), ok + 1)


def test_belief_vector_layout():
    mean = torch.tensor([1.0, 2.0])
    cov = torch.tensor([[3.0, 4.0], [4.0, 5.0]])
    prob = torch.tensor([[0.25, 0.75], [0.5, 0.5]])
    v = belief_vector(mean, cov, prob)
    torch.testing.assert_close(
        v,
        torch.tensor([[1.0, 2.0, 3.0, 4.0, 5.0, 0.25, 0.75], [1.0, 2.0, 3.0, 4.0, 5.0, 0.5, 0.5]]),
    )
    with pytest.raises(ValueError, match="cov must have trailing shape"):
        belief_vector(mean, torch.eye(3), prob)


def test_subset_checks_its_index():
    problem = StoppingProblem(torch.randn(4, 3, 2), torch.ones(4, 3, 3))
    assert len(problem.subset([3, 1])) == 2
    assert len(problem.subset(torch.tensor([0.0, 2.0]))) == 2
    for bad, match in (([4], "index"), ([-1], "index"), ([0.5], "index"), ([[0, 1]], "index")):
        with pytest.raises(ValueError, match=match):
            problem.subset(bad)
