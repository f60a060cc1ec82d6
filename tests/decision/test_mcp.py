"""Monte-Carlo planning (Algorithms 4.2-4.3) on a small fitted IDDM.

Oracles: the online filter itself (the batched particle update must equal it stream by stream),
the literal sampling chain of Algorithm 4.2 (moments of the sampled observations), and the
decision with all particles (early termination must agree in >= 99% of states).
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from hgpdm_torch.decision.basis import RadialBasis
from hgpdm_torch.decision.lspi import LinearQ, lspi
from hgpdm_torch.decision.mcp import Belief, MonteCarloPlanner
from hgpdm_torch.decision.stopping import StoppingProblem, belief_vector
from hgpdm_torch.inference.intention import OnlineIntentionFilter
from hgpdm_torch.models import IDDM

GRID = torch.linspace(-0.9, 0.9, 7)[:, None]
LENGTH, FIRST = 8, 3  # observations per movement; decisions after observations 3 .. 7


@pytest.fixture(scope="module")
def model(continuous_iddm) -> IDDM:
    return continuous_iddm


def _movements(model, num, gen):
    """Movements drawn from the IDDM with g uniform on the grid."""
    trans, meas = model.transition_posterior(), model.measurement_posterior()
    first = torch.stack([s[0] for s in model.latent_sequences()])
    k = torch.randint(len(GRID), (num,), generator=gen)
    x = first.mean(0) + 0.1 * torch.randn(num, first.shape[1], generator=gen)
    zs = []
    for _ in range(LENGTH):
        m, v = meas.predict(x, include_noise=True)
        zs.append(m + v.sqrt() * torch.randn(m.shape, generator=gen))
        m, v = trans.predict(torch.cat([x, GRID[k]], -1), include_noise=True)
        x = m + v.sqrt() * torch.randn(m.shape, generator=gen)
    return torch.stack(zs, 1), k


def _filtered(model, z):
    """Beliefs after each observation from FIRST on: mean [n, T, Dx], cov, log_prob [n, T, K]."""
    f = OnlineIntentionFilter(model, GRID, forgetting=0.1, batch_size=z.shape[0])
    means, covs, logs = [], [], []
    for t in range(z.shape[1]):
        f.update(z[:, t])
        if t + 1 >= FIRST:
            means.append(f.mean.clone())
            covs.append(f.cov.clone())
            logs.append(f.log_belief.clone())
    return f, torch.stack(means, 1), torch.stack(covs, 1), torch.stack(logs, 1)


def _rewards(k, T, gen):
    """Three movements for the regions g < -0.3, |g| <= 0.3, g > 0.3 of the grid; the right one
    succeeds with probability falling from 0.95 to 0.5, a wrong one with 0.1."""
    region = torch.bucketize(GRID[k, 0], torch.tensor([-0.3, 0.3]))
    p_right = torch.linspace(0.95, 0.5, T)
    right = torch.arange(3)[None, :, None] == region[:, None, None]
    p = torch.where(right, p_right, torch.tensor(0.1))
    return torch.where(torch.rand(p.shape, generator=gen) < p, 1.0, -1.0)


@pytest.fixture(scope="module")
def pipeline(model):
    gen = torch.Generator().manual_seed(11)
    z, k = _movements(model, 160, gen)
    f, mean, cov, log_prob = _filtered(model, z)
    T = mean.shape[1]
    beliefs = belief_vector(mean, cov, log_prob.exp())
    problem = StoppingProblem(beliefs, _rewards(k, T, gen))
    basis = RadialBasis(30, seed=0, bias=True).fit(beliefs.reshape(-1, beliefs.shape[-1]))
    tr = problem.transitions(problem.enumerate_episodes(), unique=True)
    q = lspi(tr, features=basis, ridge=1e-3).q
    return f, basis, q, (mean, cov, log_prob)


def _belief(states, i, t):
    mean, cov, log_prob = states
    return Belief(mean[i, t], cov[i, t], log_prob[i, t])


def test_batched_particle_update_equals_the_online_filter(model, pipeline, generator):
    f, basis, q, states = pipeline
    planner = MonteCarloPlanner(model, f, q, basis)
    belief = _belief(states, 3, 1)
    z = model.measurement_posterior().predict(belief.mean[None])[0] + 0.2 * torch.randn(
        40, model.obs_dim, generator=generator
    )
    mean, cov, log_prob = planner.step(belief, z)
    ref = OnlineIntentionFilter(model, GRID, forgetting=0.1, batch_size=40)
    ref.update(torch.zeros(40, model.obs_dim))  # start the streams, then overwrite the state
    ref.mean[:] = belief.mean
    ref.cov[:] = belief.cov
    ref.log_belief[:] = belief.log_prob
    out = ref.update(z)
    torch.testing.assert_close(log_prob, out.log_prob, rtol=1e-9, atol=1e-9)
    torch.testing.assert_close(mean, ref.mean, rtol=1e-9, atol=1e-10)
    torch.testing.assert_close(cov, ref.cov, rtol=1e-9, atol=1e-10)


def test_moment_sampling_matches_the_literal_chain(model, pipeline):
    """With a linear measurement kernel the mean and covariance of z_{t+1} depend only on the first
    two moments of x_{t+1}, which moment matching gets exactly: both samplers agree in them."""
    f, basis, q, states = pipeline
    belief = _belief(states, 5, 0)
    fast = MonteCarloPlanner(model, f, q, basis)
    slow = MonteCarloPlanner(model, f, q, basis, sampling="points")
    shared = fast._shared(belief)
    n = 20000
    za = fast._sample_observations(shared, n, torch.Generator().manual_seed(1))
    zb = slow._sample_observations(shared, n, torch.Generator().manual_seed(2))
    se = torch.sqrt(za.var(0) / n + zb.var(0) / n)
    assert ((za.mean(0) - zb.mean(0)).abs() < 4.5 * se).all()
    ca, cb = torch.cov(za.T), torch.cov(zb.T)
    scale = torch.sqrt(ca.diagonal()[:, None] * ca.diagonal()[None, :])
    assert ((ca - cb).abs() / scale).max() < 0.06  # ~ 4 SE of a correlation at n = 20000


def test_projection_estimates_the_value_of_waiting(model, pipeline, generator):
    """The projected rewards are the stop values of genuinely updated beliefs, and their mean
    over independent runs agrees within the Monte-Carlo standard error."""
    f, basis, q, states = pipeline
    planner = MonteCarloPlanner(model, f, q, basis, chunk_size=64)
    belief = _belief(states, 2, 1)
    r1 = planner.project(belief, 1000, generator=generator)
    r2 = planner.project(belief, 1000, generator=generator)
    assert r1.shape == (1000,) and r1.std() > 0
    se = math.sqrt(r1.var() / 1000 + r2.var() / 1000)
    assert abs(float(r1.mean() - r2.mean())) < 4 * se
    # every projected reward is the best stop value of some reachable belief
    stop_now = q.values(basis(belief.vector()))[1:]
    assert float(r1.min()) > float(stop_now.max()) - 10.0


def test_early_termination_agrees_with_all_particles(model, pipeline):
    f, basis, q, states = pipeline
    planner = MonteCarloPlanner(
        model, f, q, basis, num_particles=500
    )  # confidence 0.99, chunks of 100
    mean = states[0]
    n, T = mean.shape[0], mean.shape[1]
    agree, total, used, waits = 0, 0, 0, 0
    for i in range(0, n, 2):
        for t in range(T - 1):
            belief = _belief(states, i, t)
            seed = 1000 * i + t
            early = planner.decide(belief, generator=torch.Generator().manual_seed(seed))
            full = planner.decide(
                belief, early_stop=False, generator=torch.Generator().manual_seed(seed)
            )
            agree += early.action == full.action
            total += 1
            used += early.particles
            waits += full.action == 0
    assert total >= 300
    assert agree / total >= 0.99
    assert used / total < 0.4 * 500  # and it saves most of the particles
    assert 0.1 < waits / total < 0.9  # both decisions occur: the test is not trivial


def test_last_step_stops_without_sampling(model, pipeline):
    f, basis, q, states = pipeline
    planner = MonteCarloPlanner(model, f, q, basis)
    d = planner.decide(_belief(states, 0, 0), can_wait=False)
    assert d.action in (1, 2, 3) and d.particles == 0 and math.isnan(d.q_wait)
    assert d.action == int(d.q_stop.argmax()) + 1


def test_unnormalised_belief_is_normalised_once(model, pipeline):
    f, basis, q, states = pipeline
    planner = MonteCarloPlanner(model, f, q, basis, confidence=np.float64(0.99))
    belief = _belief(states, 0, 1)
    shifted = type(belief)(belief.mean, belief.cov, belief.log_prob + 3.0)
    a = planner.decide(belief, generator=torch.Generator().manual_seed(0))
    b = planner.decide(shifted, generator=torch.Generator().manual_seed(0))
    assert a.action == b.action
    torch.testing.assert_close(a.q_stop, b.q_stop)


def test_bad_input(model, pipeline):
    f, basis, q, states = pipeline
    with pytest.raises(TypeError, match="OnlineIntentionFilter"):
        MonteCarloPlanner(model, "filter", q, basis)
    with pytest.raises(ValueError, match="predictive"):
        MonteCarloPlanner(model, OnlineIntentionFilter(model, GRID, evidence="bound"), q, basis)
    with pytest.raises(TypeError, match="LinearQ"):
        MonteCarloPlanner(model, f, torch.zeros(4, 3), basis)
    with pytest.raises(ValueError, match="num_particles"):
        MonteCarloPlanner(model, f, q, basis, num_particles=1)
    with pytest.raises(ValueError, match="confidence"):
        MonteCarloPlanner(model, f, q, basis, confidence=1.5)
    with pytest.raises(ValueError, match="sampling"):
        MonteCarloPlanner(model, f, q, basis, sampling="exact")
    with pytest.raises(TypeError, match="IDDM"):
        MonteCarloPlanner("model", f, q, basis)
    planner = MonteCarloPlanner(model, f, q, basis)
    belief = _belief(states, 0, 0)
    with pytest.raises(TypeError, match="Belief"):
        planner.decide(belief.vector())
    with pytest.raises(ValueError, match="log_prob"):
        planner.decide(Belief(belief.mean, belief.cov, belief.log_prob[:3]))
    with pytest.raises(ValueError, match="NaN"):
        planner.decide(Belief(belief.mean * math.nan, belief.cov, belief.log_prob))
    with pytest.raises(ValueError, match="Dz"):
        planner.step(belief, torch.zeros(3, 2))
    with pytest.raises(ValueError, match="num"):
        planner.project(belief, 0)
    assert isinstance(q, LinearQ)
