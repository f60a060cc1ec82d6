"""Episodic NAC: the score-function identity, the natural gradient against its exact value, and
improvement over the uniform exploration policy on a small stopping problem."""

from __future__ import annotations

import pytest
import torch

from hgpdm_torch.decision.basis import RadialBasis
from hgpdm_torch.decision.nac import SoftmaxPolicy, _episode_scores, nac, natural_gradient
from hgpdm_torch.decision.stopping import EXPLORATION, StoppingProblem

T, G = 3, 3


def _problem(n: int, gen: torch.Generator) -> StoppingProblem:
    """Belief: a noisy one-hot of the intended movement that sharpens with t, plus t; stopping
    with the intended movement succeeds with probability 0.9, 0.8, 0.6 at t = 0, 1, 2."""
    g = torch.randint(G, (n,), generator=gen)
    noise = torch.tensor([1.0, 0.5, 0.1])[None, :, None]
    hint = torch.nn.functional.one_hot(g, G)[:, None, :] + noise * torch.randn(
        n, T, G, generator=gen
    )
    beliefs = torch.cat([hint, torch.arange(T, dtype=hint.dtype).expand(n, T)[..., None]], -1)
    right = torch.arange(G)[None, :, None] == g[:, None, None]
    p = torch.where(right, torch.tensor([0.9, 0.8, 0.6]), torch.tensor(0.1)).expand(n, G, T)
    rewards = torch.where(torch.rand(n, G, T, generator=gen) < p, 1.0, -1.0)
    return StoppingProblem(beliefs, rewards)


def _allowed(problem):
    return torch.stack([problem.allowed(t) for t in range(problem.horizon)])


@pytest.fixture(scope="module")
def setting():
    gen = torch.Generator().manual_seed(3)
    train, test = _problem(300, gen), _problem(300, gen)
    basis = RadialBasis(6, bias=True, seed=0).fit(train.beliefs.reshape(-1, G + 1))
    return train, test, basis


def _exact_gradient(problem, phi, theta):
    theta = theta.clone().requires_grad_(True)
    probs = SoftmaxPolicy(theta).probs(phi, _allowed(problem))
    problem.expected_reward(probs).mean().backward()
    return theta.grad.reshape(-1)


def _enumerated(problem, phi, theta):
    """All episodes with their probabilities under the policy, and their summed scores."""
    probs = SoftmaxPolicy(theta).probs(phi, _allowed(problem))
    ep = problem.enumerate_episodes()
    wait = probs[ep.trial, :, 0]  # [E, T]
    steps = torch.arange(problem.horizon)
    reach = torch.where(steps[None] < ep.stop_step[:, None], wait, 1.0).prod(1)
    prob = reach * probs[ep.trial, ep.stop_step, ep.stop_action]
    scores = _episode_scores(ep, phi, probs).reshape(len(ep), -1)
    return ep, prob, scores


def test_score_function_identity_gives_the_exact_gradient(setting):
    """sum_episodes P(e) psi_e R_e / n equals autograd's gradient of the exact expected return."""
    train, _, basis = setting
    phi = basis(train.beliefs)
    theta = 0.3 * torch.randn(4, phi.shape[-1], generator=torch.Generator().manual_seed(0))
    ep, prob, scores = _enumerated(train, phi, theta)
    torch.testing.assert_close(prob.view(len(train), -1).sum(1), torch.ones(len(train)))
    lr = (prob[:, None] * scores * ep.reward[:, None]).sum(0) / len(train)
    torch.testing.assert_close(lr, _exact_gradient(train, phi, theta), rtol=1e-9, atol=1e-12)


def test_sampled_natural_gradient_matches_the_exact_one(setting):
    """The critic's regression on sampled episodes converges to F^-1 grad J with the exact Fisher
    F = E[psi psi^T] of the episode distribution."""
    train, _, basis = setting
    phi = basis(train.beliefs)
    theta = 0.3 * torch.randn(4, phi.shape[-1], generator=torch.Generator().manual_seed(0))
    ep, prob, scores = _enumerated(train, phi, theta)
    fisher = (prob[:, None, None] * scores[:, :, None] * scores[:, None, :]).sum(0) / len(train)
    grad = _exact_gradient(train, phi, theta)
    # softmax scores sum to zero over actions: F is singular along that direction; project out
    exact = torch.linalg.lstsq(fisher, grad[:, None]).solution[:, 0]
    probs = SoftmaxPolicy(theta).probs(phi, _allowed(train))
    sampled = train.sample_episodes(100, probs=probs, generator=torch.Generator().manual_seed(1))
    s = _episode_scores(sampled, phi, probs).reshape(len(sampled), -1)
    w, baseline = natural_gradient(s, sampled.reward, ridge=1e-9)
    proj = fisher @ w  # compare in the identifiable subspace
    cos = torch.nn.functional.cosine_similarity(proj, fisher @ exact, dim=0)
    assert cos > 0.95
    assert abs(float(baseline) - float(train.expected_reward(probs).mean())) < 0.05
    assert float(w @ grad) > 0


def test_natural_gradient_recovers_a_linear_model(generator):
    scores = torch.randn(500, 4, generator=generator)
    w_true = torch.tensor([1.0, -2.0, 0.5, 0.0])
    w, j = natural_gradient(scores, scores @ w_true + 0.7, ridge=1e-12)
    torch.testing.assert_close(w, w_true, rtol=0, atol=1e-8)
    assert float(j) == pytest.approx(0.7, abs=1e-8)


def test_nac_improves_on_the_uniform_policy(setting):
    train, test, basis = setting
    result = nac(
        train,
        basis(train.beliefs),
        iterations=60,
        step_size=0.5,
        generator=torch.Generator().manual_seed(2),
    )
    probs = result.policy.probs(basis(test.beliefs), _allowed(test))
    learned = test.expected_reward(probs).mean()
    uniform = test.expected_reward(torch.tensor(EXPLORATION).expand(len(test), T, 4)).mean()
    start = test.expected_reward(
        SoftmaxPolicy(torch.zeros(4, basis.num_features)).probs(basis(test.beliefs), _allowed(test))
    ).mean()
    assert learned > uniform + 0.4 and learned > start + 0.4
    assert result.returns[-10:].mean() > result.returns[:5].mean() + 0.3


def test_bad_input(setting):
    train, _, basis = setting
    phi = basis(train.beliefs)
    with pytest.raises(TypeError, match="StoppingProblem"):
        nac("problem", phi)
    with pytest.raises(ValueError, match="phi must have shape"):
        nac(train, phi[:5])
    with pytest.raises(ValueError, match="iterations"):
        nac(train, phi, iterations=0)
    with pytest.raises(ValueError, match="step_size"):
        nac(train, phi, step_size=-1.0)
    with pytest.raises(ValueError, match="ridge"):
        nac(train, phi, ridge=0)
    with pytest.raises(ValueError, match="at least one action"):
        SoftmaxPolicy(torch.zeros(4, 2)).probs(torch.ones(2), torch.zeros(4, dtype=torch.bool))
