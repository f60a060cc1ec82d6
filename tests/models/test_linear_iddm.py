"""LinearIDDM: the conjugate predictive against marginal-likelihood ratios, beliefs against a
brute-force loop, recovery of g on phase-dependent linear systems, and bad input."""

from __future__ import annotations

import math
import warnings

import numpy as np
import pytest
import torch
from scipy import integrate, stats
from scipy.special import gammaln, logsumexp, multigammaln

from hgpdm_torch.models import LinearIDDM
from hgpdm_torch.models.linear_iddm import (
    AUTO_COEF_PRECISION,
    AUTO_NOISE_PRIOR,
    FORGETTING_CANDIDATES,
)


def _log_marginal(u: np.ndarray, y: np.ndarray, noise: str, lam: float, psi: float) -> float:
    """log p(Y | U) of the conjugate model, from its closed form (not from the predictive)."""
    n, d = y.shape
    p = u.shape[1]
    prec = u.T @ u + lam * np.eye(p)
    coef = np.linalg.solve(prec, u.T @ y)
    resid = y.T @ y - coef.T @ prec @ coef  # Y^T (I + U U^T / lam)^-1 Y
    logdet_ratio = p * math.log(lam) - np.linalg.slogdet(prec)[1]  # log |Lambda_0| / |Lambda_n|
    if noise == "isotropic":  # sigma^2 ~ IG(2, psi)
        a0, b0 = 2.0, psi
        an, bn = a0 + n * d / 2, b0 + 0.5 * np.trace(resid)
        gauss = -n * d / 2 * math.log(2 * math.pi) + d / 2 * logdet_ratio
        return float(gauss + a0 * math.log(b0) - an * math.log(bn) + gammaln(an) - gammaln(a0))
    if noise == "diagonal":  # each dim its own D = 1 model
        return sum(_log_marginal(u, y[:, [k]], "full", lam, psi) for k in range(d))
    nu0 = d + 2.0
    psi0, psin = psi * np.eye(d), psi * np.eye(d) + resid
    return float(
        -n * d / 2 * math.log(math.pi) + d / 2 * logdet_ratio
        + nu0 / 2 * np.linalg.slogdet(psi0)[1] - (nu0 + n) / 2 * np.linalg.slogdet(psin)[1]
        + multigammaln((nu0 + n) / 2, d) - multigammaln(nu0 / 2, d)
    )  # fmt: skip


def _sampled_log_marginal(u: np.ndarray, y: np.ndarray, noise: str, lam: float, psi: float):
    """log p(Y | U) by integrating the noise out numerically: quadrature over sigma^2 for
    isotropic and per-dimension noise, Monte Carlo over inverse-Wishart draws for full noise.
    Given the noise, Y ~ MN(0, A, Sigma) with A = I + U U^T / lambda (W integrated out)."""
    n, d = y.shape
    a = np.eye(n) + u @ u.T / lam
    a_inv, logdet_a = np.linalg.inv(a), np.linalg.slogdet(a)[1]

    def gauss(q: float, var: float, dims: int) -> float:  # log N(y; 0, var A), dims columns
        return -0.5 * (dims * (n * math.log(2 * math.pi * var) + logdet_a) + q / var)

    def integral(q: float, dims: int, shape: float, scale: float) -> float:
        # int N(.; 0, v A) IG(v; shape, scale) dv, over t = log v; the integrand's peak set
        # to 1 (by its log at the mode v = (q/2 + scale) / (n dims / 2 + shape + 1))
        def log_f(t: float) -> float:
            return (
                gauss(q, math.exp(t), dims)
                + stats.invgamma.logpdf(math.exp(t), shape, scale=scale)
                + t
            )

        mode = math.log((q / 2 + scale) / (n * dims / 2 + shape + 1))
        peak = log_f(mode)
        value, _ = integrate.quad(lambda t: math.exp(log_f(t) - peak), mode - 30, mode + 30,
                                  points=[mode], limit=200)  # fmt: skip
        return peak + math.log(value)

    quad = np.einsum("id,ij,jd->d", y, a_inv, y)  # y_d^T A^-1 y_d per column
    if noise == "isotropic":
        return integral(float(quad.sum()), d, 2.0, psi)
    if noise == "diagonal":  # IW(psi, 3) in one dimension is IG(3/2, psi/2)
        return sum(integral(float(q), 1, 1.5, psi / 2) for q in quad)
    sigmas = stats.invwishart(df=d + 2, scale=psi * np.eye(d)).rvs(100_000, random_state=3)
    s_inv = np.linalg.inv(sigmas)
    logs = (-0.5 * n * d * math.log(2 * math.pi) - 0.5 * d * logdet_a
            - 0.5 * n * np.linalg.slogdet(sigmas)[1]
            - 0.5 * np.einsum("kij,ji->k", s_inv, y.T @ a_inv @ y))  # fmt: skip
    return float(logsumexp(logs) - math.log(len(logs)))


def _phase_system(n: int, generator: torch.Generator, discrete: bool = False, T: int = 6):
    """Sequences of z_{t+1} = A_t z_t + b_t phi(g) + e_t whose dependence on g flips sign with
    the phase (a stationary model averages it away), full noise covariance."""
    d = 3
    if discrete:
        g = torch.randint(0, 3, (n,), generator=generator).double()
        phi = torch.nn.functional.one_hot(g.long(), 3).double() - 1 / 3
    else:
        g = 2 * torch.rand(n, generator=generator) - 1
        phi = g[:, None]
    a = 0.6 * torch.eye(d)
    b = torch.randn(phi.shape[1], d, generator=generator)
    mix = torch.tensor([[1.0, 0.0, 0.0], [0.9, 0.3, 0.0], [0.2, -0.5, 0.4]])
    z = [torch.randn(n, d, generator=generator)]
    for t in range(T - 1):
        sign = 1.0 if t % 2 == 0 else -1.0
        noise = 0.3 * torch.randn(n, d, generator=generator) @ mix.T
        z.append(z[-1] @ a.T + sign * phi @ b + noise)
    return torch.stack(z, 1), g


@pytest.mark.parametrize("noise", ["full", "diagonal", "isotropic"])
def test_predictive_is_the_ratio_of_marginal_likelihoods(noise, generator):
    # log p(z_new | u_new, data) = log p(Y + new | U + u_new) - log p(Y | U): the closed-form
    # marginal likelihoods are an independent derivation of the Student-t predictive
    obs, g = _phase_system(12, generator, T=4)
    model = LinearIDDM(noise=noise, phase=False).fit(obs, g)  # the prior by its evidence
    lam, psi = model.prior
    fixed = LinearIDDM(noise=noise, phase=False, coef_precision=0.7, noise_prior=0.4).fit(obs, g)
    assert fixed.prior == (0.7, 0.4)
    frames = obs.reshape(-1, 3).numpy()
    mean, std = frames.mean(0), frames.std(0, ddof=1)
    z = (obs.numpy() - mean) / std
    u = np.concatenate(
        [z[:, :-1], np.broadcast_to(g.numpy()[:, None, None], (12, 3, 1)), np.ones((12, 3, 1))], -1
    ).reshape(-1, 5)
    y = z[:, 1:].reshape(-1, 3)
    a, b = torch.randn(2, 3, generator=generator).double() + torch.tensor(mean)
    for gv in (-0.8, 0.3):
        u_new = np.concatenate([(a.numpy() - mean) / std, [gv, 1.0]])[None]
        y_new = ((b.numpy() - mean) / std)[None]
        oracle = _log_marginal(np.vstack([u, u_new]), np.vstack([y, y_new]), noise, lam, psi)
        oracle -= _log_marginal(u, y, noise, lam, psi) + np.log(std).sum()  # raw-z density
        got = model.log_predictive(a, b, torch.tensor([gv]))
        assert got.shape == (1,)
        assert abs(float(got[0]) - oracle) < 1e-9
        oracle = _log_marginal(np.vstack([u, u_new]), np.vstack([y, y_new]), noise, 0.7, 0.4)
        oracle -= _log_marginal(u, y, noise, 0.7, 0.4) + np.log(std).sum()
        assert abs(float(fixed.log_predictive(a, b, torch.tensor([gv]))[0]) - oracle) < 1e-9


@pytest.mark.parametrize("noise", ["full", "diagonal", "isotropic"])
def test_evidence_and_the_auto_prior(noise, generator):
    obs, g = _phase_system(15, generator, T=4)
    frames = obs.reshape(-1, 3).numpy()
    z = (obs.numpy() - frames.mean(0)) / frames.std(0, ddof=1)
    phases = [(np.column_stack([z[:, s], g.numpy(), np.ones(15)]), z[:, s + 1]) for s in range(3)]
    model = LinearIDDM(noise=noise, coef_precision=0.5, noise_prior=0.2).fit(obs, g)
    oracle = sum(_log_marginal(u, y, noise, 0.5, 0.2) for u, y in phases)
    assert abs(model.log_marginal_likelihood() - oracle) < 1e-8
    # "auto" (the default) takes the candidates' evidence maximum
    auto = LinearIDDM(noise=noise).fit(obs, g)
    best = max(
        ((lam, psi) for lam in AUTO_COEF_PRECISION for psi in AUTO_NOISE_PRIOR),
        key=lambda pr: sum(_log_marginal(u, y, noise, *pr) for u, y in phases),
    )
    assert auto.prior == pytest.approx(best)
    psi = AUTO_NOISE_PRIOR[2]  # only lambda searched: a sub-grid, never a better evidence
    half = LinearIDDM(noise=noise, noise_prior=psi).fit(obs, g)
    assert half.prior[1] == psi and half.prior[0] in AUTO_COEF_PRECISION
    assert half.log_marginal_likelihood() <= auto.log_marginal_likelihood() + 1e-9


@pytest.mark.parametrize("noise", ["full", "diagonal", "isotropic"])
def test_closed_forms_against_numerical_integration(noise, generator):
    # the closed-form evidence (used by the test oracle above and by "auto") against the noise
    # integrated out by quadrature or Monte Carlo
    u = np.column_stack([torch.randn(5, 2, generator=generator).numpy(), np.ones(5)])
    y = torch.randn(5, 2, generator=generator).numpy() + u[:, :2] @ np.array([[0.5, 0], [0, 1]])
    closed = _log_marginal(u, y, noise, 0.8, 0.6)
    tol = 0.02 if noise == "full" else 1e-6  # Monte Carlo with 1e5 draws, or quadrature
    assert abs(closed - _sampled_log_marginal(u, y, noise, 0.8, 0.6)) < tol


@pytest.mark.parametrize("noise", ["full", "diagonal", "isotropic"])
def test_each_phase_predicts_with_its_own_posterior(noise, generator):
    # phase=True: the predictive at step s is the ratio of phase s's evidences
    obs, g = _phase_system(10, generator, T=4)
    model = LinearIDDM(noise=noise, coef_precision=0.7, noise_prior=0.4).fit(obs, g)
    frames = obs.reshape(-1, 3).numpy()
    mean, std = frames.mean(0), frames.std(0, ddof=1)
    z = (obs.numpy() - mean) / std
    a, b = torch.randn(2, 3, generator=generator).double() + torch.tensor(mean)
    for step in range(3):
        u = np.column_stack([z[:, step], g.numpy(), np.ones(10)])
        u_new = np.concatenate([(a.numpy() - mean) / std, [0.4, 1.0]])[None]
        y, y_new = z[:, step + 1], ((b.numpy() - mean) / std)[None]
        oracle = _log_marginal(np.vstack([u, u_new]), np.vstack([y, y_new]), noise, 0.7, 0.4)
        oracle -= _log_marginal(u, y, noise, 0.7, 0.4) + np.log(std).sum()
        got = model.log_predictive(a, b, torch.tensor([0.4]), step=np.int64(step))
        assert abs(float(got[0]) - oracle) < 1e-9


def test_auto_noise_takes_the_kind_of_largest_evidence(generator):
    obs, g = _phase_system(40, generator)
    auto = LinearIDDM(coef_precision=1.0, noise_prior=0.1).fit(obs, g)
    fixed = {
        kind: LinearIDDM(noise=kind, coef_precision=1.0, noise_prior=0.1).fit(obs, g)
        for kind in ("full", "diagonal", "isotropic")
    }
    best = max(fixed, key=lambda k: fixed[k].log_marginal_likelihood())
    assert auto.noise_kind == best == "full"  # the simulated noise is correlated
    assert auto.log_marginal_likelihood() == fixed[best].log_marginal_likelihood()


def test_float32_tracks_float64(generator):
    # nearly deterministic dynamics: the residual scatter is ~1e-5 of Y^T Y, so computing it as
    # Y^T Y - M^T Lambda M would cancel to noise in float32
    n, T, d = 60, 30, 4
    g = 2 * torch.rand(n, generator=generator) - 1
    rot = torch.linalg.matrix_exp(torch.tensor([[0, .3, 0, 0], [-.3, 0, .2, 0], [0, -.2, 0, .1],
                                                [0, 0, -.1, 0]]))  # fmt: skip
    z = [torch.randn(n, d, generator=generator)]
    for _ in range(T - 1):
        z.append(z[-1] @ rot.T + 0.1 * g[:, None] + 3e-3 * torch.randn(n, d, generator=generator))
    obs = torch.stack(z, 1)
    options = {"noise": "full", "phase": False, "coef_precision": 0.1, "noise_prior": 1e-4}
    b64 = LinearIDDM(**options).fit(obs[:40], g[:40])
    b32 = LinearIDDM(**options, dtype=torch.float32).fit(obs[:40].float(), g[:40])
    rel = (b32.scatter.double() - b64.scatter).abs().max() / b64.scatter.abs().max()
    assert rel < 1e-3
    grid = torch.linspace(-1, 1, 21)
    p64 = b64.beliefs(obs[40:, :4], grid).prob
    p32 = b32.beliefs(obs[40:, :4], grid).prob
    assert p32.dtype == torch.float32 and (p32.double() - p64).abs().max() < 1e-2


def test_a_failed_refit_keeps_the_fitted_model(generator):
    obs, g = _phase_system(20, generator)
    model = LinearIDDM().fit(obs, g)
    before = model.beliefs(obs[:3]).prob
    with pytest.raises(ValueError, match="intentions"):
        model.fit(obs[:, :, :2], g[:5])
    assert model.obs_dim == 3 and torch.equal(model.beliefs(obs[:3]).prob, before)
    again = LinearIDDM().fit(obs.numpy(), g.numpy())  # NumPy input
    assert torch.allclose(again.beliefs(obs[:3]).prob, before)


def test_beliefs_match_a_brute_force_loop_and_are_causal(generator):
    obs, g = _phase_system(40, generator)
    model = LinearIDDM().fit(obs[:30], g[:30])
    grid = torch.linspace(-1, 1, 7)
    belief = model.beliefs(obs[30:], grid)
    assert belief.prob.shape == (10, 6, 7) and belief.mean.shape == (10, 6, 1)
    for i in range(10):
        for t in range(6):
            log_w = torch.zeros(7)
            for s in range(t):
                log_w += model.log_predictive(obs[30 + i, s], obs[30 + i, s + 1], grid, step=s)
            expected = torch.softmax(log_w, 0)
            assert torch.allclose(belief.prob[i, t], expected, atol=1e-12)
    # frame 0 has seen no transition: the uniform prior; a later frame never changes the past
    assert torch.allclose(belief.prob[:, 0], torch.full((10, 7), 1 / 7))
    changed = obs[30:].clone()
    changed[:, 4:] += 5.0
    again = model.beliefs(changed, grid)
    assert torch.allclose(again.prob[:, :4], belief.prob[:, :4], atol=1e-14)
    assert not torch.allclose(again.prob[:, 4:], belief.prob[:, 4:])
    # a prior over the grid multiplies the belief
    prior = torch.linspace(-1.0, 1.0, 7)
    tilted = model.beliefs(obs[30:], grid, log_prior=prior)
    assert torch.allclose(tilted.prob, torch.softmax(belief.log_prob + prior, -1), atol=1e-12)


def test_recovers_g_of_a_phase_dependent_system(generator):
    obs, g = _phase_system(260, generator)
    train, test = slice(0, 200), slice(200, 260)
    grid = torch.linspace(-1, 1, 41)
    errors = {}
    for phase in (True, False):
        model = LinearIDDM(phase=phase).fit(obs[train], g[train])
        mean = model.beliefs(obs[test], grid).mean[:, -1, 0]
        errors[phase] = float((mean - g[test]).abs().mean())
    # g's effect flips sign with the phase: the shared transition averages it away
    assert errors[True] < 0.1 and errors[False] > 3 * errors[True]
    # the error falls as frames arrive
    model = LinearIDDM().fit(obs[train], g[train])
    err = (model.beliefs(obs[test], grid).mean[..., 0] - g[test, None]).abs().mean(0)
    assert float(err[-1]) < float(err[1]) < float(err[0])


def test_discrete_intentions(generator):
    obs, g = _phase_system(200, generator, discrete=True)
    with pytest.warns(UserWarning, match="edge of its candidates"):  # lambda at its smallest
        model = LinearIDDM(intention="discrete").fit(list(obs[:150]), g[:150].long())
    belief = model.beliefs(obs[150:])
    assert belief.values.tolist() == [[0.0], [1.0], [2.0]] and belief.mean is None
    accuracy = (belief.prob[:, -1].argmax(-1) == g[150:].long()).double().mean()
    assert accuracy > 0.9


def test_too_few_transitions_per_phase_warn(generator):
    obs, g = _phase_system(5, generator)  # 5 transitions per phase for 5 coefficients: fine
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        LinearIDDM(coef_precision=1.0, noise_prior=0.1).fit(obs, g)
    with pytest.warns(UserWarning, match="4 training transitions for 5 coefficients"):
        LinearIDDM(coef_precision=1.0, noise_prior=0.1).fit(obs[:4], g[:4])


def test_sequences_of_different_lengths(generator):
    obs, g = _phase_system(30, generator)
    seqs = [obs[j, : 3 + j % 4] for j in range(30)]  # 3..6 frames
    model = LinearIDDM().fit(seqs, g)
    assert model.num_phases == 5
    out = model.log_evidence(obs[0])  # one [T, Dz] stream
    assert out.shape == (6, 25) and bool((out[0] == 0).all())
    with pytest.raises(ValueError, match="step 5 has no transition"):
        model.log_evidence(torch.cat([obs[0], obs[0, :1]]))
    shared = LinearIDDM(phase=False).fit(seqs, g)
    assert shared.num_phases == 1 and shared.log_evidence(torch.cat([obs[0]] * 2)).shape == (12, 25)


def test_rejects_bad_input(generator):
    obs, g = _phase_system(10, generator)
    with pytest.raises(RuntimeError, match="not fitted"):
        LinearIDDM().beliefs(obs)
    with pytest.raises(ValueError, match="noise"):
        LinearIDDM(noise="spherical")
    with pytest.raises(ValueError, match="coef_precision"):
        LinearIDDM(coef_precision=0.0)
    with pytest.raises(ValueError, match="coef_precision"):
        LinearIDDM(coef_precision="best")
    with pytest.raises(ValueError, match="noise_prior"):
        LinearIDDM(noise_prior=float("nan"))
    with pytest.raises(TypeError, match="phase"):
        LinearIDDM(phase=1)
    with pytest.raises(ValueError, match="select"):
        LinearIDDM(select="likelihood")
    with pytest.raises(ValueError, match="num_values"):
        LinearIDDM(num_values=3)
    with pytest.raises(ValueError, match="intentions"):
        LinearIDDM().fit(obs, g[:5])
    with pytest.raises(ValueError, match="at least 2 frames"):
        LinearIDDM().fit([obs[0, :1]], g[:1])
    with pytest.raises(ValueError, match="codes"):
        LinearIDDM(intention="discrete").fit(obs, g)
    model = LinearIDDM().fit(obs, g)
    with pytest.raises(ValueError, match="Dz = 3"):
        model.beliefs(obs[..., :2])
    bad = obs.clone()
    bad[1, 2, 0] = float("nan")
    with pytest.raises(ValueError, match="obs"):
        model.beliefs(bad)
    with pytest.raises(ValueError, match="grid"):
        model.beliefs(obs, torch.zeros(3, 2))
    with pytest.raises(ValueError, match="log_prior"):
        model.beliefs(obs, torch.zeros(3), log_prior=torch.zeros(4))
    with pytest.raises(ValueError, match="step"):
        model.log_predictive(obs[0, 0], obs[0, 1], step=-1)
    with pytest.raises(ValueError, match="B, T >= 1"):
        model.beliefs(obs[:, :0])
    with pytest.raises(ValueError, match="B, T >= 1"):
        model.beliefs(obs[:0])
    with pytest.raises(ValueError, match="num"):
        model.grid(num=0)
    with pytest.raises(ValueError, match="noise"):
        LinearIDDM(noise="spherical")


@pytest.mark.filterwarnings("ignore:LinearIDDM. the evidence chose")
def test_stream_shared_phase_discrete_and_inf_rows(generator):
    obs, g = _phase_system(60, generator, discrete=True)
    for phase in (True, False):
        model = LinearIDDM(intention="discrete", phase=phase).fit(obs[:50], g[:50].long())
        prior = torch.tensor([0.0, -math.inf, 0.5])  # -inf excludes code 1
        batch = model.beliefs(obs[50:], log_prior=prior)
        assert bool((batch.prob[..., 1] == 0).all())
        bad = obs[50:].clone()
        bad[4, 0, 0] = float("inf")  # stream 4 misses frame 0: no transition 0 -> 1
        stream = model.stream(10, log_prior=prior)
        for t in range(6):
            b = stream.update(bad[:, t])
        keep = [i for i in range(10) if i != 4]
        assert torch.allclose(b.prob[keep], batch.prob[keep, -1], atol=1e-12)
        log_w = prior.clone()
        for s in range(1, 5):
            log_w += model.log_predictive(obs[54, s], obs[54, s + 1], step=s)
        assert torch.allclose(b.prob[4], torch.softmax(log_w, 0), atol=1e-12)
    with pytest.raises(ValueError, match="log_prior"):
        model.stream(log_prior=torch.tensor([0.0, math.nan, 0.0]))
    with pytest.raises(ValueError, match="log_prior"):
        model.beliefs(obs[50:], log_prior=torch.full((3,), -math.inf))


def test_no_tensor_lands_on_the_default_device(generator):
    # with torch's default device set to "meta", a tensor made without device= lands there
    # and mixing it with the model's CPU tensors fails
    obs, g = _phase_system(30, generator)
    expected = LinearIDDM().fit(obs[:20], g[:20]).beliefs(obs[20:]).prob
    torch.set_default_device("meta")
    try:
        model = LinearIDDM().fit(obs[:20], g[:20])
        prob = model.beliefs(obs[20:], log_prior=torch.zeros(25, device="cpu")).prob
        cv = LinearIDDM(temperature="cv", forgetting="cv").fit(obs[:20], g[:20])
        stream = model.stream(10, log_prior=[0.0] * 25)
        for t in range(6):
            online = stream.update(obs[20:, t]).prob
    finally:
        torch.set_default_device(None)
    assert torch.allclose(prob, expected, atol=1e-12)
    assert torch.allclose(online, expected[:, -1], atol=1e-12)
    on_cpu = LinearIDDM(temperature="cv", forgetting="cv").fit(obs[:20], g[:20])
    assert (cv.temperature, cv.forgetting) == (on_cpu.temperature, on_cpu.forgetting)


def test_runs_on_the_device_of_its_data(device, generator):
    obs, g = _phase_system(30, generator)
    cpu = LinearIDDM().fit(obs[:20], g[:20]).beliefs(obs[20:]).prob
    model = LinearIDDM().fit(obs[:20].to(device), g[:20].to(device))
    assert model.coef.device.type == device.type
    prob = model.beliefs(obs[20:])  # streams given on the CPU move to the model's device
    assert prob.prob.device.type == device.type
    assert torch.allclose(prob.prob.cpu(), cpu, atol=1e-10)


def test_stream_matches_beliefs_and_isolates_bad_rows(generator):
    obs, g = _phase_system(40, generator)
    model = LinearIDDM().fit(obs[:30], g[:30])
    grid = torch.linspace(-1, 1, 9)
    prior = torch.linspace(0.0, 1.0, 9)
    batch = model.beliefs(obs[30:], grid, log_prior=prior)
    stream = model.stream(10, grid, log_prior=prior)
    for t in range(6):
        b = stream.update(obs[30:, t])
        assert torch.allclose(b.prob, batch.prob[:, t], atol=1e-12)
        assert not bool(b.rejected.any())
    # a NaN row in stream 2 at frame 3: the others are untouched; stream 2 loses the
    # transitions 2 -> 3 and 3 -> 4 and keeps the rest
    bad = obs[30:].clone()
    bad[2, 3, 1] = float("nan")
    stream.reset()
    for t in range(6):
        b = stream.update(bad[:, t])
        assert bool(b.rejected[2]) == (t == 3) and int(b.rejected.sum()) == (t == 3)
    assert stream.rejected_count.tolist() == [int(i == 2) for i in range(10)]
    others = [i for i in range(10) if i != 2]
    assert torch.allclose(b.prob[others], batch.prob[others, -1], atol=1e-12)
    log_w = prior.clone()
    for s in (0, 1, 4):
        log_w += model.log_predictive(obs[32, s], obs[32, s + 1], grid, step=s)
    assert torch.allclose(b.prob[2], torch.softmax(log_w, 0), atol=1e-12)
    # one stream takes [Dz] rows and answers [K]; past the trained phases it refuses any frame
    single = model.stream(grid=grid, log_prior=prior)
    for t in range(6):
        one = single.update(obs[30, t])
        assert one.prob.shape == (9,) and one.rejected.shape == ()
        assert torch.allclose(one.prob, batch.prob[0, t], atol=1e-12)
    with pytest.raises(ValueError, match="frame 6 has no transition"):
        single.update(torch.full((3,), float("nan")))
    assert single.frames == 6
    stream.reset()
    with pytest.raises(ValueError, match=r"\[B, Dz\] = \[10, 3\]"):
        stream.update(obs[30:35, 0])
    with pytest.raises(ValueError, match="batch_size"):
        model.stream(0)


def _coverage(model: LinearIDDM, obs: torch.Tensor, g: torch.Tensor) -> float:
    """How often the 90% credible set of the held-out beliefs (every frame after the first)
    holds the grid value nearest to the true g."""
    from hgpdm_torch.calibration import credible_set

    values = model.grid()
    truth = (g[:, None] - values[:, 0]).abs().argmin(-1)
    inside = credible_set(model.beliefs(obs, values).prob[:, 1:], 0.9)
    return float(inside.gather(-1, truth[:, None, None].expand(-1, inside.shape[1], 1)).double()
                 .mean())  # fmt: skip


def test_temperature_tempers_the_evidence_in_batch_and_stream(generator):
    from hgpdm_torch.calibration import temper

    obs, g = _phase_system(40, generator)
    prior = torch.softmax(torch.linspace(0.0, 1.0, 25, dtype=torch.float64), 0)
    exact = LinearIDDM(noise="full", coef_precision=1.0, noise_prior=0.1).fit(obs[:30], g[:30])
    hot = LinearIDDM(noise="full", coef_precision=1.0, noise_prior=0.1, temperature=2.5)
    hot.fit(obs[:30], g[:30])
    assert exact.temperature == 1.0 and hot.temperature == 2.5
    base = exact.beliefs(obs[30:], log_prior=prior.log())
    tempered = hot.beliefs(obs[30:], log_prior=prior.log())
    # the calibration module's tempering of the exact posterior (prior kept, evidence / T)
    expected = temper(base.log_prob, 2.5, prior=prior).exp()
    assert torch.allclose(tempered.prob, expected, atol=1e-12)
    assert not torch.allclose(tempered.prob, base.prob, atol=1e-3)
    stream = hot.stream(10, log_prior=prior.log())
    for t in range(6):
        assert torch.allclose(stream.update(obs[30:, t]).prob, tempered.prob[:, t], atol=1e-12)
    with pytest.raises(ValueError, match="temperature"):
        LinearIDDM(temperature=0.0)
    with pytest.raises(TypeError, match="temperature"):
        LinearIDDM(temperature="hot")
    with pytest.raises(ValueError, match="cv_folds"):
        LinearIDDM(cv_folds=1)
    for bad in (1.0, -0.1, "some", True):
        with pytest.raises(ValueError, match="forgetting"):
            LinearIDDM(forgetting=bad)
    assert LinearIDDM(forgetting=np.float32(0.25)).forgetting == 0.25
    with pytest.raises(ValueError, match="two sequences"), warnings.catch_warnings():
        warnings.simplefilter("ignore")  # one sequence: too few transitions per phase
        LinearIDDM(temperature="cv").fit(obs[:1], g[:1])


def _sequence_offsets(n: int, generator: torch.Generator, shared: float):
    """Continuous-g sequences of z_{t+1} = 0.6 z_t + b g + e_t + c, whose noise has a part ``c``
    drawn once per sequence with sd ``shared`` (0: independent transitions, as the model
    assumes; > 0: the transitions of a sequence are correlated and their evidence overlaps)."""
    d, steps = 3, 8
    g = 2 * torch.rand(n, generator=generator) - 1
    b = torch.tensor([[0.5, -0.3, 0.2]])
    offset = shared * torch.randn(n, d, generator=generator)
    z = [torch.randn(n, d, generator=generator)]
    for _ in range(steps - 1):
        e = 0.3 * torch.randn(n, d, generator=generator)
        z.append(0.6 * z[-1] + g[:, None] @ b + e + offset)
    return torch.stack(z, 1).double(), g.double()


def test_cv_temperature_is_one_for_the_model_and_calibrates_correlated_noise(generator):
    # independent Gaussian transitions (the model's own assumption): T ~ 1 and the exact
    # beliefs are calibrated already; a noise part shared by a sequence's transitions makes
    # T = 1 over-confident, and the cross-validated T widens the sets
    obs, g = _sequence_offsets(400, generator, shared=0.0)
    model = LinearIDDM(phase=False, temperature="cv").fit(obs[:200], g[:200])
    assert 0.75 < model.temperature < 1.33
    assert 0.85 < _coverage(model, obs[200:], g[200:]) < 0.95
    # exact Bayes is what the model's own data calls for: no forgetting either
    both = LinearIDDM(phase=False, temperature="cv", forgetting="cv").fit(obs[:200], g[:200])
    assert both.forgetting == 0.0 and both.temperature == model.temperature
    obs, g = _sequence_offsets(400, generator, shared=0.5)
    exact = LinearIDDM(phase=False).fit(obs[:200], g[:200])
    model = LinearIDDM(phase=False, temperature="cv").fit(obs[:200], g[:200])
    assert model.temperature > 1.5
    # correlated transitions: the cross-validation lets the latest ones outweigh the earlier
    both = LinearIDDM(phase=False, temperature="cv", forgetting="cv").fit(obs[:200], g[:200])
    assert both.forgetting > 0.0 and both.temperature > 1.2
    assert _coverage(both, obs[200:], g[200:]) > 0.85
    before, after = _coverage(exact, obs[200:], g[200:]), _coverage(model, obs[200:], g[200:])
    assert after > max(before + 0.05, 0.85)
    # and the held-out truth is more likely (what the fitted T maximises on the folds)
    truth = (g[200:, None] - exact.grid()[:, 0]).abs().argmin(-1)[:, None].expand(-1, 7)
    nll = [-m.beliefs(obs[200:]).log_prob[:, 1:].gather(-1, truth[..., None]).mean()
           for m in (exact, model)]  # fmt: skip
    assert nll[1] < nll[0]


@pytest.mark.filterwarnings("ignore:LinearIDDM. a phase has")
@pytest.mark.filterwarnings("ignore:LinearIDDM. the evidence chose")
@pytest.mark.parametrize("rank", [0, 1])
def test_cv_calibration_against_a_hand_made_fold_loop(rank, generator):
    # per phase, sequences of 2 to 6 frames, 3 folds: j is held out in fold j mod 3, the others
    # refit with the chosen noise kind and prior, every held-out frame after the first scored
    # on the default 25-value grid at the value nearest its g
    from hgpdm_torch.calibration import fit_temperature

    obs, g = _phase_system(60, generator)
    seqs = [s[: 2 + (2 * j) % 5] for j, s in enumerate(obs)]  # lengths vary within each fold
    model = LinearIDDM(temperature="cv", cv_folds=3, interaction_rank=rank).fit(seqs, g)
    joint = LinearIDDM(temperature="cv", forgetting="cv", cv_folds=3, interaction_rank=rank)
    joint.fit(seqs, g)
    values = torch.linspace(float(g.min()), float(g.max()), 25, dtype=torch.float64)
    steps, truth = _held_out_steps(seqs, g, values, noise=model.noise_kind,
                                   coef_precision=model.prior[0], noise_prior=model.prior[1],
                                   interaction_rank=rank)  # fmt: skip
    assert model.temperature == pytest.approx(fit_temperature(_forgetful(steps, 0.0), truth),
                                              rel=1e-9)  # fmt: skip
    assert 0.1 < model.temperature < 10  # informative held-out beliefs: T off its bounds
    # the joint choice: for each candidate eps the forgetful beliefs B_t = (1 - eps) B_{t-1}
    # + E_t, their own T, and the pair under which the truths are most likely
    scores = []
    for eps in FORGETTING_CANDIDATES:
        rows = _forgetful(steps, eps)
        t = fit_temperature(rows, truth)
        nll = -torch.log_softmax(rows / t, -1).gather(-1, truth[:, None]).mean()
        scores.append((float(nll), t, eps))
    _, t, eps = min(scores)
    assert joint.forgetting == eps and joint.temperature == pytest.approx(t, rel=1e-9)


@pytest.mark.filterwarnings("ignore:LinearIDDM. a phase has")
@pytest.mark.filterwarnings("ignore:LinearIDDM. the cross-validation chose")
@pytest.mark.parametrize("rank", [0, 1])
def test_cv_selection_against_a_brute_force_search(rank, generator, monkeypatch):
    # select="cv": every candidate (noise kind, lambda) refitted through the public API on each
    # fold's other sequences, its held-out evidence steps forgotten and tempered as in
    # test_cv_calibration_against_a_hand_made_fold_loop; the fit must take the candidate, eps
    # and T of the smallest held-out negative log probability of the truths (first on ties)
    from hgpdm_torch.calibration import fit_temperature
    from hgpdm_torch.models.linear_iddm import NOISE_KINDS

    obs, g = _phase_system(45, generator, T=5)
    # lengths 2-5 that vary within each fold (the held-out sequences are batched by length)
    seqs = [s[: 2 + (2 * j) % 5] for j, s in enumerate(obs)]
    options = {"noise_prior": 0.3, "interaction_rank": rank, "cv_folds": 3}
    model = LinearIDDM(select="cv", temperature="cv", forgetting="cv", **options).fit(seqs, g)
    values = torch.linspace(float(g.min()), float(g.max()), 25, dtype=torch.float64)
    scores = []
    for lam in AUTO_COEF_PRECISION:
        for kind in NOISE_KINDS:
            steps, truth = _held_out_steps(seqs, g, values, noise=kind, coef_precision=lam,
                                           noise_prior=0.3, interaction_rank=rank)  # fmt: skip
            for eps in FORGETTING_CANDIDATES:
                rows = _forgetful(steps, eps)
                t = fit_temperature(rows, truth)
                nll = -torch.log_softmax(rows / t, -1).gather(-1, truth[:, None]).mean()
                scores.append((float(nll), kind, lam, eps, t))
    best = min(scores, key=lambda s: s[0])
    assert (model.noise_kind, model.prior, model.forgetting) == (best[1], (best[2], 0.3), best[3])
    assert model.temperature == pytest.approx(best[4], rel=1e-9)
    # the statistics are those of a plain fit with the chosen options; its evidence as reported
    plain = LinearIDDM(**model.config()).fit(seqs, g)
    for key, value in plain.state_dict().items():
        torch.testing.assert_close(model.state_dict()[key], value, rtol=1e-12, atol=1e-12)

    # with nothing to choose, select="cv" is the plain fit and runs no cross-validation
    def no_cv(*args, **kwargs):
        raise AssertionError("cross-validation ran with nothing to choose")

    monkeypatch.setattr(LinearIDDM, "_cross_validate", no_cv)
    fixed = LinearIDDM(select="cv", **model.config()).fit(seqs, g)
    for key, value in plain.state_dict().items():
        torch.testing.assert_close(fixed.state_dict()[key], value, rtol=0, atol=0)


def _held_out_steps(seqs, g, values, folds: int = 3, **options):
    """Per held-out sequence (j in fold j mod ``folds``), the ``[T_j - 1, K]`` evidence of each
    transition under a LinearIDDM with ``options`` fitted on the other folds through the public
    API, and the index of the grid value nearest each sequence's g, per transition."""
    steps, truth = [], []
    for fold in range(folds):
        rest = [j for j in range(len(seqs)) if j % folds != fold]
        sub = LinearIDDM(**options).fit([seqs[j] for j in rest], g[rest])
        for j in range(fold, len(seqs), folds):
            frames = min(len(seqs[j]), sub.num_phases + 1)
            steps.append(sub.log_evidence(seqs[j][:frames], values).diff(dim=0))
            truth.append((g[j] - values).abs().argmin().expand(frames - 1))
    return steps, torch.cat(truth)


def _forgetful(steps: list[torch.Tensor], eps: float) -> torch.Tensor:
    """Rows B_1 .. B_{T_j - 1} of every sequence's ``[T_j - 1, K]`` evidence steps, stacked."""
    rows = []
    for seq in steps:
        b = torch.zeros_like(seq[0])
        for e in seq:
            b = (1 - eps) * b + e
            rows.append(b)
    return torch.stack(rows)


@pytest.mark.filterwarnings("ignore:LinearIDDM. a phase has")
@pytest.mark.filterwarnings("ignore:LinearIDDM. the evidence chose")
def test_cv_on_separable_discrete_data_warns_at_the_temperature_bound(generator):
    obs, g = _phase_system(60, generator, discrete=True)
    with pytest.warns(UserWarning, match="temperature is at its bound"):
        model = LinearIDDM(intention="discrete", temperature="cv", cv_folds=3).fit(obs, g.long())
    assert model.temperature < 0.0011
    with pytest.raises(ValueError, match="at least 2 distinct values"):
        LinearIDDM(intention="discrete", temperature="cv").fit(obs, torch.zeros(60).long())


def test_forgetting_follows_algorithm_3_2_in_batch_and_stream(generator):
    # B_t = (1 - eps) B_{t-1} + log p(z_t | z_{t-1}, g) / T from B_0 = log p(g), by hand from
    # the one-step predictive
    obs, g = _phase_system(40, generator)
    model = LinearIDDM(noise="diagonal", coef_precision=1.0, noise_prior=0.1, temperature=1.5,
                       forgetting=0.3).fit(obs[:30], g[:30])  # fmt: skip
    assert model.forgetting == 0.3
    grid = torch.linspace(-1, 1, 7)
    prior = torch.log_softmax(torch.linspace(0.0, 2.0, 7, dtype=torch.float64), 0)
    batch = model.beliefs(obs[30:], grid, log_prior=prior)
    b = prior.expand(10, -1)
    assert torch.allclose(batch.log_prob[:, 0], torch.log_softmax(b, -1), atol=1e-12)
    for t in range(1, 6):
        b = 0.7 * b + model.log_predictive(obs[30:, t - 1], obs[30:, t], grid, step=t - 1) / 1.5
        assert torch.allclose(batch.log_prob[:, t], torch.log_softmax(b, -1), atol=1e-10)
    stream = model.stream(10, grid, log_prior=prior)
    for t in range(6):
        assert torch.allclose(stream.update(obs[30:, t]).prob, batch.prob[:, t], atol=1e-12)
    # a stream that misses frame 2 forgets at every frame but takes no evidence into or out of it
    bad = obs[30:].clone()
    bad[3, 2] = float("nan")
    stream.reset()
    for t in range(6):
        online = stream.update(bad[:, t])
    b = prior.clone()
    for t in range(1, 6):
        b = 0.7 * b
        if t not in (2, 3):
            b = b + model.log_predictive(obs[33, t - 1], obs[33, t], grid, step=t - 1) / 1.5
    assert torch.allclose(online.prob[3], torch.softmax(b, 0), atol=1e-10)
    # alone in its batch (no stream has a transition at frames 2 and 3), the same belief
    alone = model.stream(1, grid, log_prior=prior)
    for t in range(6):
        single = alone.update(bad[3, t])
    assert torch.allclose(single.prob, online.prob[3], atol=1e-12)


def _scaled_effect(n: int, generator: torch.Generator, T: int = 5):
    """Sequences where the intention's effect on the next frame scales with the current frame:
    z_{t+1} = 0.9 z_t + g (c^T z_t) b + e, no additive effect of g at all."""
    g = 2 * torch.rand(n, generator=generator, dtype=torch.float64) - 1
    c = torch.tensor([1.0, 0.5, 0.0], dtype=torch.float64)
    b = torch.tensor([0.0, 0.3, 0.8], dtype=torch.float64)
    z = [1.5 * torch.randn(n, 3, generator=generator, dtype=torch.float64)]  # centred: the
    for _ in range(T - 1):  # sign of g's effect follows the state's, so it averages to zero
        e = 0.1 * torch.randn(n, 3, generator=generator, dtype=torch.float64)
        z.append(0.9 * z[-1] + g[:, None] * (z[-1] @ c)[:, None] * b + e)
    return torch.stack(z, 1), g


@pytest.mark.filterwarnings("ignore:LinearIDDM. the evidence chose")
def test_interaction_inputs_predictive_and_recovery(generator):
    from sklearn.cross_decomposition import PLSRegression

    obs, g = _scaled_effect(300, generator)
    model = LinearIDDM(interaction_rank=1, noise="diagonal").fit(obs[:200], g[:200])
    # the directions: sklearn's PLS of each phase's standardised states on g
    z = ((obs[:200] - model.obs_mean) / model.obs_std).numpy()
    for s in range(4):
        pls = PLSRegression(1, scale=False).fit(z[:, s], g[:200, None].numpy())
        assert np.allclose(model.directions[s].numpy(), pls.x_rotations_, atol=1e-10)
    # the predictive is the ratio of marginal likelihoods with u = [z, g, 1, g V^T z]
    s, lam, psi = 2, *model.prior
    v = model.directions[s].numpy()

    def inputs(zs: np.ndarray, gv: np.ndarray) -> np.ndarray:
        return np.concatenate([zs, gv[:, None], np.ones((len(zs), 1)), gv[:, None] * (zs @ v)], 1)

    u, y = inputs(z[:, s], g[:200].numpy()), z[:, s + 1]
    a, b = obs[250, s], obs[250, s + 1]
    za = ((a - model.obs_mean) / model.obs_std).numpy()[None]
    zb = ((b - model.obs_mean) / model.obs_std).numpy()[None]
    for gv in (-0.6, 0.4):
        u_new = inputs(za, np.array([gv]))
        oracle = _log_marginal(np.vstack([u, u_new]), np.vstack([y, zb]), "diagonal", lam, psi)
        oracle -= _log_marginal(u, y, "diagonal", lam, psi) + np.log(model.obs_std.numpy()).sum()
        got = model.log_predictive(a, b, torch.tensor([gv]), step=s)
        assert abs(float(got[0]) - oracle) < 1e-9
    # g only scales the dynamics: without the interaction the belief is at chance (a uniform g
    # on [-1, 1] guessed at 0 errs by 0.5); with it, it finds g in part (the PLS direction is
    # only an estimate of c)
    grid = torch.linspace(-1, 1, 41)
    errors = []
    for rank in (0, 1):
        m = LinearIDDM(interaction_rank=rank).fit(obs[:200], g[:200])
        errors.append(float((m.beliefs(obs[200:], grid).mean[:, -1, 0] - g[200:]).abs().mean()))
    assert errors[0] > 0.45 and errors[1] < 0.65 * errors[0]


@pytest.mark.filterwarnings("ignore:LinearIDDM")
def test_interaction_discrete_shared_phase_stream_and_bad_rank(generator):
    obs, g = _phase_system(60, generator, discrete=True)
    model = LinearIDDM(intention="discrete", phase=False, interaction_rank=2)
    model.fit(obs[:50], g[:50].long())
    assert model.directions.shape == (1, 3, 2) and model.coef.shape == (1, 3 + 3 + 1 + 6, 3)
    batch = model.beliefs(obs[50:])
    stream = model.stream(10)
    for t in range(6):
        assert torch.allclose(stream.update(obs[50:, t]).prob, batch.prob[:, t], atol=1e-12)
    for bad in (-1, 1.5, True):
        with pytest.raises(ValueError, match="interaction_rank"):
            LinearIDDM(interaction_rank=bad)
    with pytest.raises(ValueError, match="exceeds Dz = 3"):
        LinearIDDM(interaction_rank=4).fit(obs[:50], g[:50])
    # the predictive with P = 3 one-hot features and r = 2 directions: the ratio of marginal
    # likelihoods with u = [z, phi, 1, phi (x) V^T z] flattened phi-major
    lam, psi = model.prior
    z = ((obs[:50] - model.obs_mean) / model.obs_std).numpy()
    v = model.directions[0].numpy()
    onehot = np.eye(3)[g[:50].long().numpy()]

    def inputs(zs: np.ndarray, phi: np.ndarray) -> np.ndarray:
        inter = (phi[:, :, None] * (zs @ v)[:, None, :]).reshape(len(zs), 6)
        return np.concatenate([zs, phi, np.ones((len(zs), 1)), inter], 1)

    u = inputs(z[:, :-1].reshape(-1, 3), np.repeat(onehot, 5, 0))
    y = z[:, 1:].reshape(-1, 3)
    a, b = obs[55, 1], obs[55, 2]
    za = ((a - model.obs_mean) / model.obs_std).numpy()[None]
    zb = ((b - model.obs_mean) / model.obs_std).numpy()[None]
    for code in range(3):
        u_new = inputs(za, np.eye(3)[[code]])
        oracle = _log_marginal(np.vstack([u, u_new]), np.vstack([y, zb]), model.noise_kind,
                               lam, psi)  # fmt: skip
        oracle -= _log_marginal(u, y, model.noise_kind, lam, psi)
        oracle -= np.log(model.obs_std.numpy()).sum()
        got = model.log_predictive(a, b, torch.tensor([float(code)]), step=1)
        assert abs(float(got[0]) - oracle) < 1e-9


@pytest.mark.filterwarnings("ignore:LinearIDDM. a phase has 1 training transitions for")
@pytest.mark.filterwarnings("ignore:LinearIDDM. a phase has 3 training transitions for")
@pytest.mark.filterwarnings("ignore:LinearIDDM. the evidence chose")
def test_interaction_with_short_phases_and_constant_intentions_warns(generator):
    obs, g = _phase_system(40, generator)
    seqs = [s if j == 0 else s[:5] for j, s in enumerate(obs)]  # one transition in phase 4
    with pytest.warns(UserWarning, match="cannot be estimated"):
        model = LinearIDDM(interaction_rank=1, temperature="cv", cv_folds=4).fit(seqs, g)
    assert bool((model.directions[4] == 0).all()) and bool((model.directions[0] != 0).any())
    assert math.isfinite(model.temperature)
    # only sequences of one intention reach the last phase: no direction there
    same = g.clone()
    same[:3] = 0.3
    seqs = [s if j < 3 else s[:5] for j, s in enumerate(obs)]
    with pytest.warns(UserWarning, match="intentions are all equal"):
        model = LinearIDDM(interaction_rank=1, coef_precision=1.0, noise_prior=0.1).fit(seqs, same)
    assert bool((model.directions[4] == 0).all()) and bool((model.directions[3] != 0).any())


# ------------------------------------------------------------------------------ bad data
def test_batch_refuses_implausible_and_overflowing_frames(generator):
    # a frame far out (1e160: its squares overflow float64) is a clear error naming its stream
    # and frame, as infer_intention's for a bad row; never a NaN belief
    obs, g = _phase_system(40, generator)
    model = LinearIDDM().fit(obs[:30], g[:30])
    bad = obs[30:].clone()
    bad[1, 2, 0] = 1e160
    for method in (model.beliefs, model.log_evidence):
        with pytest.raises(
            ValueError, match=r"obs\[1, 2\] cannot be used: channel 0 .* implausible"
        ):
            method(bad)
    with pytest.raises(ValueError, match=r"obs\[2\] cannot be used"):  # one [T, Dz] stream
        model.beliefs(bad[1])
    with pytest.raises(ValueError, match=r"z_next\[0\] cannot be used"):
        model.log_predictive(obs[30:32, 1], bad[1:3, 2])
    # the threshold is in training standard deviations of each dimension
    near = obs[30:].clone()
    near[0, 3] = model.obs_mean + 99.0 * model.obs_std
    assert bool(torch.isfinite(model.beliefs(near).prob).all())
    near[0, 3, 1] = model.obs_mean[1] + 101.0 * model.obs_std[1]
    with pytest.raises(ValueError, match=r"obs\[0, 3\] cannot be used: channel 1"):
        model.beliefs(near)
    # without the threshold a finite frame is taken, and one that overflows still raises
    loose = LinearIDDM(outlier_sd=None).fit(obs[:30], g[:30])
    assert loose.config()["outlier_sd"] is None and model.config()["outlier_sd"] == 100.0
    assert bool(torch.isfinite(loose.beliefs(near).prob).all())
    with pytest.raises(ValueError, match=r"obs\[1, 2\]: the density .* not finite.*rescale"):
        loose.beliefs(bad)
    with pytest.raises(ValueError, match=r"z_next\[0\]: the density .* not finite"):
        loose.log_predictive(obs[30:32, 1], bad[1:3, 2])


def test_outlier_sd_default_and_validation():
    import inspect

    from hgpdm_torch.inference.filtering import DEFAULT_OUTLIER_SD

    assert inspect.signature(LinearIDDM).parameters["outlier_sd"].default == DEFAULT_OUTLIER_SD
    for bad, err in ((0.0, ValueError), (-1.0, ValueError), ("100", TypeError)):
        with pytest.raises(err, match="outlier_sd"):
            LinearIDDM(outlier_sd=bad)


@pytest.mark.filterwarnings("ignore:LinearIDDM")
def test_fit_refuses_data_that_overflow_its_dtype(generator):
    obs, g = _phase_system(20, generator)
    with pytest.raises(ValueError, match=r"sequences overflow torch.float64.*rescale"):
        LinearIDDM().fit(obs * 1e200, g)
    with pytest.raises(ValueError, match=r"intentions overflow torch.float64.*rescale g"):
        LinearIDDM().fit(obs, g * 1e200)  # a continuous g enters the inputs as given
    with pytest.raises(ValueError, match="intentions overflow"):
        LinearIDDM(temperature="cv").fit(obs, g * 1e200)
    # large but representable data fit (standardised), and their beliefs are finite
    model = LinearIDDM().fit(obs * 1e100, g)
    assert bool(torch.isfinite(model.beliefs(obs[:3] * 1e100).prob).all())
    model = LinearIDDM(dtype=torch.float32).fit(obs * 1e30, g)  # squares beyond float32's range
    assert bool(torch.isfinite(model.beliefs(obs[:3] * 1e30).prob).all())


def test_fit_needs_two_distinct_intention_values(generator):
    obs, g = _phase_system(20, generator)
    match = "intentions must take at least 2 distinct values, got the single value 0.3 for all"
    with pytest.raises(ValueError, match=match + " 20 sequence"):
        LinearIDDM().fit(obs, torch.full((20,), 0.3))
    with pytest.raises(ValueError, match="at least two sequences"):
        LinearIDDM().fit(obs[:1], torch.tensor([0.3]))
    with pytest.raises(ValueError, match="single value 0"):
        LinearIDDM(intention="discrete", num_values=3).fit(obs, torch.zeros(20).long())
    with pytest.raises(ValueError, match="single value 0.5, -1"):
        LinearIDDM().fit(obs, torch.tensor([[0.5, -1.0]]).expand(20, 2))
    # two values, or a 2-D g that varies in one component, are enough to fit
    two = (torch.arange(20) % 2).double()
    assert LinearIDDM(coef_precision=1.0, noise_prior=0.1).fit(obs, two).grid().shape == (25, 1)
    LinearIDDM(coef_precision=1.0, noise_prior=0.1).fit(obs, torch.stack([two, 0 * two], 1))


def test_fit_warns_of_a_continuous_intention_far_below_unit_scale(generator):
    """g in small units: the coefficient prior, set for unit-scale inputs, hides its effect and
    the belief is near uniform (issue 54). The warning names g's spread and the scale."""
    obs, g = _phase_system(60, generator)  # g uniform on +-1: standard deviation about 0.58
    options = {"coef_precision": 1.0, "noise_prior": 0.1}
    with warnings.catch_warnings():
        warnings.filterwarnings("error", message="LinearIDDM: the intentions")
        sharp = LinearIDDM(**options).fit(obs, g).beliefs(obs[:10]).prob[:, -1]
    match = (r"standard deviation of [\d.e-]+, below 0.1, while the coefficient prior "
             r"\(coef_precision\) is set for inputs of unit scale.*standardise g")  # fmt: skip
    for scale in (0.01, 1e-12):
        with pytest.warns(UserWarning, match=match):
            model = LinearIDDM(**options).fit(obs, scale * g)
        flat = model.beliefs(obs[:10]).prob[:, -1]
        assert float(flat.max()) < 2 / 25 < float(sharp.max(-1).values.min())  # near uniform
    two = torch.stack([g, 0.01 * g, torch.zeros_like(g)], 1)  # a constant dimension: nothing
    with pytest.warns(UserWarning, match="in dimension 1, below 0.1"):
        LinearIDDM(**options).fit(obs, two)
