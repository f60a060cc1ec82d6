"""LSPI (Algorithm 4.1) against exact dynamic programming on a small optimal-stopping problem.

The problem: an intention g in {1, 2, 3} (uniform); at decision step t the robot has seen t + 1
noisy symbols (the right one with probability 0.6); stopping with movement a at step t succeeds
with a probability that falls with t if a = g and is small otherwise (reward +1 / -1). The
belief is (posterior over g, t); its value is computed by backward induction over the counts.
"""

from __future__ import annotations

import itertools

import pytest
import torch

from hgpdm_torch.decision.basis import RadialBasis
from hgpdm_torch.decision.lspi import LinearQ, lspi, lstdq
from hgpdm_torch.decision.stopping import StoppingProblem

T, G = 4, 3
P_RIGHT = 0.6
SUCCESS_RIGHT = torch.tensor([0.95, 0.9, 0.8, 0.45])
SUCCESS_WRONG = 0.1


def _posterior(counts: tuple[int, ...]) -> torch.Tensor:
    n = sum(counts)
    logp = torch.tensor(
        [
            c * torch.log(torch.tensor(P_RIGHT)) + (n - c) * torch.log(torch.tensor(0.2))
            for c in counts
        ]
    )
    return torch.softmax(logp, 0)


def _expected_stop_rewards(t: int, post: torch.Tensor) -> torch.Tensor:
    """[G] expected reward of each movement: sum_g P(g) (2 P(success | a, g, t) - 1)."""
    right = 2 * SUCCESS_RIGHT[t] - 1
    wrong = 2 * SUCCESS_WRONG - 1
    return post * right + (1 - post) * wrong


def _true_dp() -> dict[tuple[int, tuple[int, ...]], torch.Tensor]:
    """Exact Q(state, a) for a = wait, 1..3 by backward induction over (t, counts)."""
    q: dict[tuple[int, tuple[int, ...]], torch.Tensor] = {}
    value: dict[tuple[int, tuple[int, ...]], float] = {}
    for t in range(T - 1, -1, -1):
        for counts in itertools.product(range(t + 2), repeat=G):
            if sum(counts) != t + 1:
                continue
            post = _posterior(counts)
            stop = _expected_stop_rewards(t, post)
            if t == T - 1:
                wait = torch.tensor(-torch.inf)
            else:
                p_obs = post * P_RIGHT + (1 - post) * 0.2  # P(next symbol = o)
                wait = sum(
                    float(p_obs[o])
                    * value[(t + 1, tuple(c + (i == o) for i, c in enumerate(counts)))]
                    for o in range(G)
                )
                wait = torch.tensor(wait)
            q[(t, counts)] = torch.cat([wait[None], stop])
            value[(t, counts)] = float(q[(t, counts)].max())
    return q


def _simulate(n: int, gen: torch.Generator):
    """Trials: beliefs [n, T, G + 1] = (posterior, t), rewards [n, G, T], and the count states."""
    g = torch.randint(G, (n,), generator=gen)
    right = torch.rand(n, T, generator=gen) < P_RIGHT
    other = (g[:, None] + torch.randint(1, G, (n, T), generator=gen)) % G
    symbols = torch.where(right, g[:, None], other)
    counts = torch.nn.functional.one_hot(symbols, G).cumsum(1)  # [n, T, G]
    beliefs = torch.zeros(n, T, G + 1)
    states = []
    for i in range(n):
        row = []
        for t in range(T):
            c = tuple(int(v) for v in counts[i, t])
            beliefs[i, t, :G] = _posterior(c)
            beliefs[i, t, G] = t
            row.append((t, c))
        states.append(row)
    p_success = torch.where(
        torch.arange(G)[None, :, None] == g[:, None, None], SUCCESS_RIGHT, SUCCESS_WRONG
    ).expand(n, G, T)
    rewards = torch.where(torch.rand(n, G, T, generator=gen) < p_success, 1.0, -1.0)
    return StoppingProblem(beliefs, rewards), states


def _empirical_dp(problem: StoppingProblem, states) -> dict:
    """Q of the certainty-equivalence MDP estimated from the trials (each (trial, step) once)."""
    keys = sorted({s for row in states for s in row}, key=lambda s: -s[0])
    q = {}
    for key in keys:
        t = key[0]
        cells = [(i, t) for i, row in enumerate(states) if row[t] == key]
        stop = torch.stack([problem.rewards[i, :, t] for i, _ in cells]).mean(0)
        if t == T - 1:
            wait = -torch.inf
        else:
            # the last step's wait entry is -inf, so max is over the allowed actions
            wait = sum(float(q[states[i][t + 1]].max()) for i, _ in cells) / len(cells)
        q[key] = torch.cat([torch.tensor([wait]), stop])
    return q


@pytest.fixture(scope="module")
def toy():
    gen = torch.Generator().manual_seed(7)
    problem, states = _simulate(3000, gen)
    transitions = problem.transitions(problem.enumerate_episodes(), unique=True)
    basis = RadialBasis(num_centres=200, eta=1e4, standardize=False).fit(
        problem.beliefs.reshape(-1, G + 1)
    )
    result = lspi(transitions, features=basis, ridge=1e-9)
    return problem, states, basis, result


def test_true_problem_is_a_real_stopping_problem():
    q = _true_dp()
    waits = [bool(v[0] > v[1:].max()) for (t, _), v in q.items() if t < T - 1]
    assert any(waits) and not all(waits)


def test_lspi_equals_dynamic_programming_on_the_sampled_mdp(toy):
    """Tabular features (one RBF per distinct belief, tiny width): LSPI's fixed point is the
    optimal Q of the MDP estimated from the samples, which backward induction computes exactly."""
    problem, states, basis, result = toy
    assert result.converged
    assert basis.centres.shape[0] == len({s for row in states for s in row})
    emp = _empirical_dp(problem, states)
    seen = {}
    for i, row in enumerate(states):
        for t, key in enumerate(row):
            seen.setdefault(key, problem.beliefs[i, t])
    for key, belief in seen.items():
        q = result.q.values(basis(belief))
        ref = emp[key]
        if key[0] == T - 1:
            torch.testing.assert_close(q[1:], ref[1:], atol=1e-5, rtol=0)
        else:
            torch.testing.assert_close(q, ref, atol=1e-5, rtol=0)


def test_lspi_recovers_the_optimal_policy(toy):
    """Against the exact optimum of the true model: the greedy action is optimal wherever the true
    gap exceeds 4 standard errors of the Monte-Carlo estimates, and the value lost is tiny."""
    problem, states, basis, result = toy
    q_true = _true_dp()
    visits: dict = {}
    belief_of = {}
    for i, row in enumerate(states):
        for t, key in enumerate(row):
            visits[key] = visits.get(key, 0) + 1
            belief_of.setdefault(key, problem.beliefs[i, t])
    checked = 0
    for key, n in visits.items():
        t = key[0]
        allowed = problem.allowed(t)
        a = int(result.q.greedy(basis(belief_of[key]), allowed))
        truth = q_true[key].masked_fill(~allowed, -torch.inf)
        best = truth.max()
        gap = best - truth.masked_fill(truth == best, -torch.inf).max()
        if gap > 4 * 2.0 / n**0.5:  # rewards in [-1, 1]: SE <= 1 / sqrt(n) per mean
            assert a == int(truth.argmax()), key
            checked += 1
    assert checked >= 10
    # expected return of the learned policy under the true model, from the initial beliefs
    value = _policy_value(result.q, basis, problem, states)
    optimum = sum(float(q_true[row[0]].max()) for row in states) / len(states)
    assert value >= optimum - 0.02


def _policy_value(q: LinearQ, basis, problem, states) -> float:
    """Exact expected return of the greedy policy on the true model, averaged over start states."""
    cache: dict = {}

    def v(key, belief):
        if key in cache:
            return cache[key]
        t, counts = key
        post = _posterior(counts)
        a = int(q.greedy(basis(belief), problem.allowed(t)))
        if a > 0:
            out = float(_expected_stop_rewards(t, post)[a - 1])
        else:
            p_obs = post * P_RIGHT + (1 - post) * 0.2
            out = 0.0
            for o in range(G):
                nxt = tuple(c + (i == o) for i, c in enumerate(counts))
                nb = torch.cat([_posterior(nxt), torch.tensor([t + 1.0])])
                out += float(p_obs[o]) * v((t + 1, nxt), nb)
        cache[key] = out
        return out

    return sum(v(row[0], problem.beliefs[i, 0]) for i, row in enumerate(states)) / len(states)


def test_lstdq_absorbing_stops_fit_mean_rewards():
    """One state feature: stop values are the mean rewards; wait bootstraps on the next value."""
    phi = torch.ones(6, 1)
    action = torch.tensor([1, 1, 2, 2, 0, 0])
    reward = torch.tensor([1.0, 0.0, -1.0, -1.0, 0.0, 0.0])
    next_phi = torch.ones(6, 1)
    next_action = torch.tensor([-1, -1, -1, -1, 1, 1])
    w = lstdq(phi, action, reward, next_phi, next_action, 3, ridge=1e-12)
    torch.testing.assert_close(w[:, 0], torch.tensor([0.5, 0.5, -1.0]), atol=1e-9, rtol=0)
    with pytest.raises(ValueError, match="next_action"):
        lstdq(phi, action, reward, next_phi, next_action + 3, 3)
    with pytest.raises(ValueError, match="action must be"):
        lstdq(phi, action + 2, reward, next_phi, next_action, 3)
    with pytest.raises(ValueError, match="ridge"):
        lstdq(phi, action, reward, next_phi, next_action, 3, ridge=0.0)


def test_lspi_iteration_cap_and_discount():
    gen = torch.Generator().manual_seed(1)
    problem, _ = _simulate(200, gen)
    tr = problem.transitions(problem.enumerate_episodes(), unique=True)
    basis = RadialBasis(10, seed=0).fit(problem.beliefs.reshape(-1, G + 1))
    capped = lspi(tr, features=basis, max_iter=1)
    assert capped.iterations == 1
    discounted = lspi(tr, features=basis, discount=0.5)
    full = lspi(tr, features=basis)
    phi = basis(problem.beliefs[:, 0])
    # discounting shrinks the value of waiting but not of stopping-only states' rewards
    assert not torch.allclose(discounted.q.values(phi)[:, 0], full.q.values(phi)[:, 0])


def test_lspi_bad_input():
    phi = torch.ones(4, 2)
    act = torch.tensor([0, 1, 1, 0])
    r = torch.zeros(4)
    allowed = torch.ones(4, 2, dtype=torch.bool)
    with pytest.raises(ValueError, match="ridge"):
        lspi(phi, act, r, phi, allowed, ridge=0.0)
    with pytest.raises(ValueError, match="discount"):
        lspi(phi, act, r, phi, allowed, discount=1.5)
    with pytest.raises(ValueError, match="max_iter"):
        lspi(phi, act, r, phi, allowed, max_iter=0)
    with pytest.raises(ValueError, match="action must be in"):
        lspi(phi, torch.tensor([0, 1, 2, 0]), r, phi, allowed)
    with pytest.raises(TypeError, match="action must hold integers"):
        lspi(phi, act.double(), r, phi, allowed)
    with pytest.raises(ValueError, match="next_phi"):
        lspi(phi, act, r, phi[:3], allowed)
    with pytest.raises(ValueError, match="NaN"):
        lspi(phi, act, torch.tensor([0.0, float("nan"), 0.0, 0.0]), phi, allowed)
    with pytest.raises(TypeError, match="next_allowed"):
        lspi(phi, act, r, phi, allowed.double())
    with pytest.raises(ValueError, match="features"):
        lspi(
            StoppingProblem(torch.zeros(2, 2, 1), torch.zeros(2, 3, 2)).transitions(
                StoppingProblem(torch.zeros(2, 2, 1), torch.zeros(2, 3, 2)).enumerate_episodes()
            )
        )
