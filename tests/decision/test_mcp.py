"""Monte-Carlo planning (Algorithms 4.2-4.3) on a small fitted IDDM.

Oracles: the online filter itself (the batched particle update must equal it stream by stream,
and a per-particle loop of single-stream updates valued by the LinearQ formula must reproduce
every projected reward), the filter's predictive distribution of the next observation (read
off its evidence; the sampled observations must follow it), the literal sampling chain of
Algorithm 4.2 (moments of the sampled observations), a Student-t interval computed with scipy
(early termination must stop exactly where it excludes the best stopping value), and the
decision with all particles (early termination must agree in >= 99% of states).
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from scipy import stats
from torch.utils.flop_counter import FlopCounterMode

from hgpdm_torch import settings
from hgpdm_torch.decision.basis import RadialBasis
from hgpdm_torch.decision.lspi import LinearQ, lspi
from hgpdm_torch.decision.mcp import Belief, MonteCarloPlanner
from hgpdm_torch.decision.stopping import StoppingProblem, belief_vector
from hgpdm_torch.inference.intention import OnlineIntentionFilter
from hgpdm_torch.models import IDDM

GRID = torch.linspace(-0.9, 0.9, 7)[:, None]
EPS = torch.finfo(torch.float64).eps
LENGTH, FIRST = 8, 3  # observations per movement; decisions after observations 3 .. 7


@pytest.fixture(scope="module")
def model(continuous_iddm) -> IDDM:
    return continuous_iddm


@pytest.fixture(params=[True, False], ids=["compiled", "torch"])
def kernels(request):
    """The compiled kernels on (the particles drawn and updated in C where they run) or off
    (every step in torch) for the test."""
    with settings.native_kernels(request.param):
        yield request.param


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


def _assert_filter_close(got, want, rounding: float) -> None:
    """The planner's particle update against the online filter, to rounding.

    The planner conditions on a precomputed gain for a batch of particles, the filter per
    stream: other algebra and BLAS shapes, both fed by moments that solve with the transition
    GP's ``K + noise I``; so they agree to ``rounding`` (``gp_rounding``: N EPS times its
    condition number, ~3e-8) times each quantity's scale, for one step (measured: up to a
    twentieth of it). ``rtol`` covers large entries, ``atol`` the small ones of the same tensor
    (an off-diagonal covariance carries the error of the whole matrix)."""
    for name, a, b in zip(("log_prob", "mean", "cov"), got, want, strict=True):
        scale = float(b.abs().max())
        torch.testing.assert_close(a, b, rtol=rounding, atol=rounding * scale, msg=name)


@pytest.mark.parametrize("temperature", [1.0, 3.0])
def test_batched_particle_update_equals_the_online_filter(
    model, pipeline, generator, temperature, gp_rounding
):
    f, basis, q, states = pipeline
    if temperature != 1.0:  # the planner follows its filter's evidence temperature
        f = OnlineIntentionFilter(model, GRID, forgetting=0.1, temperature=temperature)
    planner = MonteCarloPlanner(model, f, q, basis)
    belief = _belief(states, 3, 1)
    z = model.measurement_posterior().predict(belief.mean[None])[0] + 0.2 * torch.randn(
        40, model.obs_dim, generator=generator
    )
    mean, cov, log_prob, rejected = planner.step(belief, z)
    assert not bool(rejected.any())
    ref = _filter_in(model, belief, 40, temperature=temperature)
    out = ref.update(z)
    rounding = gp_rounding(f.posterior)
    _assert_filter_close((log_prob, mean, cov), (out.log_prob, ref.mean, ref.cov), rounding)


def test_planner_is_the_same_on_both_moment_paths(model, pipeline, gp_rounding):
    """The fused and the materialised psi2 paths (settings.moment_path) give the same particle
    updates and projected values, to the rounding of the shared transition moments."""
    f, basis, q, states = pipeline
    belief = _belief(states, 5, 2)
    z = model.measurement_posterior().predict(belief.mean[None])[0].expand(8, -1)
    out = {}
    for path in ("materialised", "fused"):
        with settings.moment_path(path):
            planner = MonteCarloPlanner(model, f, q, basis, num_particles=60, chunk_size=30)
            values = planner.project(belief, generator=torch.Generator().manual_seed(3))
            out[path] = (*planner.step(belief, z)[:3], values)
    rounding = gp_rounding(f.posterior)
    _assert_filter_close(out["fused"][:3], out["materialised"][:3], rounding)
    # the values read the particles' beliefs through the features: the same rounding
    torch.testing.assert_close(out["fused"][3], out["materialised"][3], rtol=0.0, atol=rounding)


def _filter_in(model, belief, num, **options):
    """An online filter of ``num`` streams, all in ``belief``."""
    ref = OnlineIntentionFilter(model, GRID, forgetting=0.1, batch_size=num, **options)
    ref.update(torch.zeros(num, model.obs_dim))  # start the streams, then overwrite the state
    ref.mean[:] = belief.mean
    ref.cov[:] = belief.cov
    ref.log_belief[:] = belief.log_prob
    return ref


def test_bad_particle_observations_are_missing_like_in_the_filter(
    model, pipeline, generator, gp_rounding
):
    """Rows with inf, partial NaN or implausible values are prediction-only steps for their
    particle only, flagged, and equal to what the filter does with them (and with NaN rows);
    a strict filter makes the planner raise, naming the row and channel."""
    f, basis, q, states = pipeline
    planner = MonteCarloPlanner(model, f, q, basis)
    belief = _belief(states, 3, 1)
    num = 8
    z = model.measurement_posterior().predict(belief.mean[None])[0] + 0.2 * torch.randn(
        num, model.obs_dim, generator=generator
    )
    z[1, 0] = math.inf
    z[2, 3] = math.nan
    z[4] = 1e200
    z[5, 1] = -1e6  # finite, but ~1e6 training standard deviations out
    z[6] = math.nan  # missing: not a rejection
    mean, cov, log_prob, rejected = planner.step(belief, z)
    assert rejected.tolist() == [False, True, True, False, True, True, False, False]
    ref = _filter_in(model, belief, num)
    out = ref.update(z)
    assert out.rejected.tolist() == rejected.tolist()
    rounding = gp_rounding(f.posterior)
    _assert_filter_close((log_prob, mean, cov), (out.log_prob, ref.mean, ref.cov), rounding)
    # a rejected row equals a missing one exactly (rows of one call, both the predicted moments)
    for i in (1, 2, 4, 5):
        torch.testing.assert_close(log_prob[i], log_prob[6], rtol=0, atol=0)
        torch.testing.assert_close(mean[i], mean[6], rtol=0, atol=0)
    # the clean rows are untouched by the bad ones, bit for bit: the same call with plausible
    # rows in their place has the same shapes, so the same kernels and rounding for every row
    plausible = z.clone()
    plausible[[1, 2, 4, 5, 6]] = z[0]
    clean = planner.step(belief, plausible)
    assert not bool(clean.rejected.any())
    for a, b in zip(clean[:3], (mean, cov, log_prob), strict=True):
        assert torch.equal(a[[0, 3, 7]], b[[0, 3, 7]])
    # the missing step only forgets: B = (1 - eps) B_{t-1}, normalised
    forget = 0.9 * belief.log_prob
    torch.testing.assert_close(log_prob[6], forget - torch.logsumexp(forget, -1))

    strict_filter = OnlineIntentionFilter(model, GRID, forgetting=0.1, strict=True)
    strict = MonteCarloPlanner(model, strict_filter, q, basis)
    with pytest.raises(ValueError, match=r"z\[1\] \(particle 1\).*channel 0 is inf"):
        strict.step(belief, z)
    with pytest.raises(ValueError, match=r"z\[0\] \(particle 0\).*channel 1 = -1e\+06 is impl"):
        strict.step(belief, z[5:])
    assert not bool(strict.step(belief, z[6:]).rejected.any())


def test_moment_sampling_matches_the_literal_chain(model, pipeline):
    """With a linear measurement kernel the mean and covariance of z_{t+1} depend only on the first
    two moments of x_{t+1}, which moment matching gets exactly: both samplers agree in them (the
    torch samplers; the compiled kernel's draws are tested against the filter's predictive
    distribution in test_projection_estimates_the_value_of_waiting)."""
    f, basis, q, states = pipeline
    belief = _belief(states, 5, 0)
    fast = MonteCarloPlanner(model, f, q, basis)
    slow = MonteCarloPlanner(model, f, q, basis, sampling="points")
    with settings.native_kernels(False):
        shared = fast._shared(belief)
    n = 20000
    za = fast._sample_observations(shared, n, torch.Generator().manual_seed(1))
    zb = slow._sample_observations(shared, n, torch.Generator().manual_seed(2))
    se = torch.sqrt(za.var(0) / n + zb.var(0) / n)
    assert ((za.mean(0) - zb.mean(0)).abs() < 4.5 * se).all()
    ca, cb = torch.cov(za.T), torch.cov(zb.T)
    scale = torch.sqrt(ca.diagonal()[:, None] * ca.diagonal()[None, :])
    assert ((ca - cb).abs() / scale).max() < 0.06  # ~ 4 SE of a correlation at n = 20000


def _record_draws(planner, monkeypatch):
    """The observations each batch of particles saw, ``[I, Dz]`` per batch, whichever path drew
    them: the torch sampler's output or, for the compiled kernel's draws, the observations its
    particles return for the same arguments (those of its values too)."""
    calls = []
    sample = planner._sample_observations

    def torch_path(*args, **kwargs):
        out = sample(*args, **kwargs)
        calls.append(out)
        return out

    monkeypatch.setattr(planner, "_sample_observations", torch_path)
    if planner._compiled is not None:
        draw = planner._compiled_args

        def compiled(*args, **kwargs):
            out = draw(*args, **kwargs)
            calls.append(planner._compiled.particles(out)[3])
            return out

        monkeypatch.setattr(planner, "_compiled_args", compiled)
    return calls


def _stop_value(basis, q, vectors):
    """``max_{a != 0} phi(theta)^T w_a`` written out from the LinearQ definition."""
    return (basis(vectors) @ q.weights[1:].T).max(-1).values


def test_projection_values_each_particle_with_the_online_filter(
    model, pipeline, kernels, monkeypatch
):
    """Algorithm 4.2 particle by particle: each sampled observation, filtered by a single-stream
    OnlineIntentionFilter and valued by the stopping values, gives that particle's reward, and
    the mean over the same particles is the planner's Q(theta, wait); with the compiled kernels
    (particles drawn and updated in C where they run) and without (all in torch)."""
    f, basis, q, states = pipeline
    planner = MonteCarloPlanner(model, f, q, basis, num_particles=150, chunk_size=64)
    belief = _belief(states, 2, 1)
    drawn = _record_draws(planner, monkeypatch)
    r = planner.project(belief, generator=torch.Generator().manual_seed(5))
    z = torch.cat(drawn)
    assert [len(c) for c in drawn] == [150] and r.shape == (150,)  # one batch: no interval

    ref = OnlineIntentionFilter(model, GRID, forgetting=0.1, batch_size=1)
    ref.update(torch.zeros(model.obs_dim))  # start the stream, then set its state per particle
    expected, continued = [], []
    for zi in z:
        ref.mean[0], ref.cov[0], ref.log_belief[0] = belief.mean, belief.cov, belief.log_prob
        ref.update(zi)
        vector = belief_vector(ref.mean[0], ref.cov[0], ref.log_belief[0].exp())
        expected.append(float(_stop_value(basis, q, vector)))
        continued.append(float((basis(vector) @ q.weights.T).max(-1).values))  # waiting too
    expected, continued = torch.tensor(expected), torch.tensor(continued)
    assert expected.std() > 0.01  # the particles really differ
    # a filter of one stream has the planner's shapes, so the same transition moments; only the
    # conditioning algebra differs (a precomputed gain): a few eps of |z| |gain|, through the
    # features (measured: 1e-12)
    torch.testing.assert_close(r, expected, rtol=1e-9, atol=1e-9)
    # where the next step may wait too, the default values a particle by all its LSPI values
    # (wait_value="lspi"); the thesis's "stop" keeps the stopping values
    gen = torch.Generator().manual_seed(5)
    torch.testing.assert_close(
        planner.project(belief, generator=gen, can_wait_next=True), continued, rtol=1e-9, atol=1e-9
    )
    assert float((continued - expected).max()) > 1e-2  # waiting is worth more somewhere (0.1)
    thesis = MonteCarloPlanner(model, f, q, basis, num_particles=150, chunk_size=64,
                               wait_value="stop")  # fmt: skip
    gen = torch.Generator().manual_seed(5)
    torch.testing.assert_close(
        thesis.project(belief, generator=gen, can_wait_next=True), expected, rtol=1e-9, atol=1e-9
    )
    drawn.clear()

    # decide() averages the same particles (same generator stream) into Q(theta, wait)
    drawn.clear()
    d = planner.decide(belief, early_stop=False, generator=torch.Generator().manual_seed(5))
    torch.testing.assert_close(torch.cat(drawn), z, rtol=0, atol=0)  # the same draws
    assert d.particles == 150
    assert d.q_wait == pytest.approx(float(expected.mean()), rel=1e-9, abs=1e-12)
    q_stop = basis(belief.vector()) @ q.weights[1:].T
    torch.testing.assert_close(d.q_stop, q_stop)
    assert d.action == (0 if d.q_wait > float(q_stop.max()) else int(q_stop.argmax()) + 1)


def _predictive(f, belief):
    """The filter's predictive distribution of the next observation, p(z | z_1:t) =
    sum_g p(g | z_1:t) N(z | m_g, S_g), read off the filter's own evidence log q(z | g): it is
    quadratic in z, so S_g = -H^-1 and m_g = S_g grad at z = 0."""
    mean, cov, _ = f.transition.moments(belief.mean[None], belief.cov[None])
    z0 = torch.zeros(f.obs_dim, dtype=mean.dtype)
    ms, Ss = [], []
    for k in range(f.num_values):

        def evidence(z, k=k):
            return f.measure(mean[0, k], cov[0, k], z)[2]

        H = torch.autograd.functional.hessian(evidence, z0)
        S = -torch.linalg.inv(H)
        ms.append(S @ torch.autograd.functional.jacobian(evidence, z0))
        Ss.append((S + S.T) / 2)
    prob = torch.softmax(belief.log_prob, -1)
    return prob.numpy(), torch.stack(ms).numpy(), torch.stack(Ss).numpy()


def test_projection_estimates_the_value_of_waiting(model, pipeline, kernels, monkeypatch):
    """The sampled observations follow the filter's predictive mixture (KS test of the
    probability integral transform along several directions, and its covariance), and the
    planner's Q(theta, wait)
    agrees within Monte-Carlo error with the value of waiting over observations drawn
    independently from that mixture."""
    f, basis, q, states = pipeline
    planner = MonteCarloPlanner(model, f, q, basis, chunk_size=4096)
    belief = _belief(states, 2, 1)
    prob, m, S = _predictive(f, belief)
    n = 20000
    drawn = _record_draws(planner, monkeypatch)
    r = planner.project(belief, n, generator=torch.Generator().manual_seed(7))
    z = torch.cat(drawn).numpy()
    rng = np.random.default_rng(3)
    dz = z.shape[1]
    directions = np.concatenate([np.eye(dz), rng.standard_normal((2, dz))])
    for a in directions:
        loc, scale = m @ a, np.sqrt(np.einsum("i,kij,j->k", a, S, a))
        u = (prob * stats.norm.cdf((z @ a)[:, None], loc, scale)).sum(1)
        assert stats.kstest(u, "uniform").pvalue > 1e-3
    # the mixture's covariance sum_g p_g (S_g + m_g m_g^T) - mbar mbar^T, relative to its scale
    mbar = prob @ m
    cov = np.einsum("k,kij->ij", prob, S + m[:, :, None] * m[:, None, :]) - np.outer(mbar, mbar)
    scale = np.sqrt(np.outer(cov.diagonal(), cov.diagonal()))
    assert (np.abs(np.cov(z.T) - cov) / scale).max() < 0.045  # over 30 seeds: at most 0.03

    # the value of waiting over independent draws from the mixture, updated and valued
    g = rng.choice(len(prob), n, p=prob)
    eps = rng.standard_normal((n, dz))
    z_ref = m[g] + np.einsum("nij,nj->ni", np.linalg.cholesky(S)[g], eps)
    mean, cov, log_prob, _ = planner.step(belief, torch.from_numpy(z_ref))
    r_ref = _stop_value(basis, q, belief_vector(mean, cov, log_prob.exp()))
    se = math.sqrt(r.var() / n + r_ref.var() / n)
    assert r.std() > 0.01
    assert abs(float(r.mean() - r_ref.mean())) < 4 * se


def _with_stop_shift(basis, q, current, shift):
    """Features and Q with one extra feature that is 1 only at the current belief vector, whose
    weight adds ``shift`` to every stopping value there: it moves max_a Q(theta_t, a) without
    changing any projected reward (particles sit at other beliefs)."""

    def features(v):
        at_current = ((v - current).abs().amax(-1) < 1e-9).to(v.dtype)
        return torch.cat([basis(v), at_current[..., None]], -1)

    column = torch.full((q.weights.shape[0], 1), float(shift), dtype=q.weights.dtype)
    column[0] = 0.0
    return features, LinearQ(torch.cat([q.weights, column], 1))


@pytest.mark.parametrize("n_check", [60, 150])
@pytest.mark.parametrize("side", [1.0, -1.0])
def test_early_termination_uses_the_student_t_interval(model, pipeline, n_check, side):
    """Algorithm 4.3: sampling stops at the first checkpoint n whose interval
    mean +- t_{(1+c)/2, n-1} s / sqrt(n) (s: sample std) excludes the best stopping value. The
    best stopping value is put at 1 +- 1e-6 half-widths (computed here with scipy) from
    the mean at checkpoint n: the planner must stop there in the first case only."""
    f, basis, q, states = pipeline
    belief = _belief(states, 4, 1)
    current = belief.vector()
    confidence = 0.9
    kwargs = dict(num_particles=300, confidence=confidence, min_particles=n_check, chunk_size=30)
    planner = MonteCarloPlanner(model, f, q, basis, **kwargs)
    # the rewards the early-terminating decision draws: chunks of 30 from the same generator
    shared = planner._shared(planner._check_belief(belief))
    gen = torch.Generator().manual_seed(3)
    r = torch.cat([planner._project(shared, 30, gen, False) for _ in range(n_check // 30)])
    r = r.numpy()
    half = stats.t.ppf((1 + confidence) / 2, n_check - 1) * r.std(ddof=1) / math.sqrt(n_check)
    best = float(_stop_value(basis, q, current))
    for factor, stops in ((1 + 1e-6, True), (1 - 1e-6, False)):
        target = r.mean() - side * factor * half  # side 1: waiting is better, -1: stopping is
        features, q_shifted = _with_stop_shift(basis, q, current, target - best)
        shifted = MonteCarloPlanner(model, f, q_shifted, features, **kwargs)
        d = shifted.decide(belief, generator=torch.Generator().manual_seed(3))
        # a dot product of 31 features with the weights (sum |phi w| ~ 6), plus the shift:
        # ~32 eps * 6 ~ 4e-14
        assert float(d.q_stop.max()) == pytest.approx(target, abs=1e-12)
        assert (d.particles == n_check) == stops
        if stops:
            # the mean of the same n rewards, summed in another order: n eps max |r|
            bound = n_check * EPS * float(abs(r).max())
            assert d.q_wait == pytest.approx(r.mean(), rel=1e-12, abs=bound)
            assert (d.action == 0) == (side > 0)
        else:
            assert d.particles > n_check


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
    with pytest.raises(ValueError, match="wait_value"):
        MonteCarloPlanner(model, f, q, basis, wait_value="forever")
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
    with pytest.raises(ValueError, match=r"\[I, Dz\]"):
        planner.step(belief, torch.zeros(2, 3, model.obs_dim))
    with pytest.raises(ValueError, match="num"):
        planner.project(belief, 0)
    assert isinstance(q, LinearQ)


def test_planner_does_not_depend_on_the_default_dtype(model, pipeline):
    """Every tensor of a decision takes its dtype from the model: with torch's default dtype
    set to float32 the particle update and the decision are bit-identical."""
    f, basis, q, states = pipeline
    planner = MonteCarloPlanner(model, f, q, basis)
    belief = _belief(states, 3, 1)
    z = model.measurement_posterior().predict(belief.mean[None])[0].expand(8, -1)

    def run():
        update = planner.step(belief, z)
        d = planner.decide(belief, early_stop=False, generator=torch.Generator().manual_seed(5))
        return [*update, d.q_stop, torch.tensor(d.q_wait, dtype=torch.float64)]

    expected = run()
    before = torch.get_default_dtype()
    torch.set_default_dtype(torch.float32)
    try:
        got = run()
    finally:
        torch.set_default_dtype(before)
    for a, b in zip(expected, got, strict=True):
        assert a.dtype == b.dtype and torch.equal(a, b)


def test_operation_count_covers_the_particles_products(model, pipeline):
    """The floor's per-particle count (``operations``, less the features and the values) of the
    torch path against the multiply-adds of the particles' matrix products
    (``torch.utils.flop_counter``: the drawn observation, the gains, the quadratic forms and the
    covariances), most of their work; an overcount, such as all Dz^2 pair products counted,
    fails the upper bound. (The compiled path's count against its algebra written out in torch:
    test_mcp_compiled.)"""
    f, basis, q, states = pipeline
    planner = MonteCarloPlanner(model, f, q, basis)
    n = 400
    k, dx, dz = f.num_values, f.mu0.shape[0], f.obs_dim
    pairs = dz * (dz + 1) // 2

    def particle():
        one = planner.operations(n + 1).madds - planner.operations(n).madds
        return one - basis.operations(1).madds - q.weights.numel()

    with settings.native_kernels(False):
        shared = planner._shared(planner._check_belief(_belief(states, 2, 1)))
        with FlopCounterMode(display=False) as counter:
            planner._particles(shared, n, torch.Generator().manual_seed(0))
        torch_path = particle()
    products = counter.get_total_flops() / 2 / n
    # what the counter does not see: the pair products y_a y_b and the mixture's elementwise
    # sums (the mean and the spread), exactly
    assert products == torch_path - (pairs + k * dx * dx + k * dx)
    assert products > 0.75 * torch_path
