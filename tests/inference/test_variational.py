"""VB inference (Sec. 2.3): closed-form free energy vs Pyro Monte Carlo, gradients, prediction,
batched L-BFGS, bad input."""

from __future__ import annotations

import math

import numpy as np
import pyro
import pyro.poutine as poutine
import pytest
import torch
from scipy.optimize import minimize

from hgpdm_torch.datasets import styled_movements, targeted_movements
from hgpdm_torch.experiments.style_recognition import forecast_windows
from hgpdm_torch.inference.map import MAP_STEPS, MAPInference
from hgpdm_torch.inference.variational import (
    MeanFieldGuide,
    VariationalInference,
    batched_lbfgs,
    condition_gaussian,
    prediction,
    window_mask,
)
from hgpdm_torch.inference.variational.laplace import laplace
from hgpdm_torch.inference.variational.prediction import candidate_forecasts
from hgpdm_torch.models import GPDM, HGPDM

# A nonlinear transition (alpha_2 = 1: length scale 1) and a noise large enough for a sharp
# Monte-Carlo check; the formulas do not depend on the hyperparameter values.
ALPHA = (0.9, 1.0, 0.1, 0.01)


@pytest.fixture(scope="module")
def styles():
    return styled_movements(2, 2, 12, 5, seed=4)


@pytest.fixture(scope="module")
def hgpdm(styles):
    model = HGPDM(styles.sequences, styles.labels, 2, alpha=ALPHA)
    model.fit(5, warn=False)  # a short fit: the oracle comparison holds at any parameters
    return model


@pytest.fixture(scope="module")
def shared(styles):
    """An H-GPDM whose styles share half of their dynamics (a kernel that is not block-diagonal)."""
    model = HGPDM(styles.sequences, styles.labels, 2, alpha=ALPHA, sharing=0.5)
    model.fit(5, warn=False)  # a short fit: the oracle comparison holds at any parameters
    return model


@pytest.fixture(scope="module")
def scaled(styles):
    """An H-GPDM with an output scale per latent dim of its transition GP, set far apart."""
    model = HGPDM(styles.sequences, styles.labels, 2, alpha=ALPHA, scale_transitions=True)
    model.fit(5, warn=False)
    model.transition_scales = torch.tensor([0.5, 2.0])
    return model


@pytest.fixture(scope="module")
def iddm():
    data = targeted_movements(4, 10, 4, seed=2)
    model = HGPDM(
        data.sequences, data.labels, 2, intention="continuous", measurement="linear", alpha=ALPHA
    )
    model.fit(5, warn=False)  # a short fit: the oracle comparison holds at any parameters
    return model, data


def _window(seq: torch.Tensor, start: int, length: int, missing: tuple[int, ...] = ()):
    z = seq[start : start + length].clone()
    for t in missing:
        z[t] = float("nan")
    return z


def _random_guide(model, T, K, gen, spread=0.05, g_dim=0):
    lat = model.latent.detach()
    idx = torch.randint(0, lat.shape[0] - T, (K,), generator=gen)
    loc = torch.stack([lat[i : i + T] for i in idx]) + 0.1 * torch.randn(
        K, T, model.latent_dim, generator=gen
    )
    a = torch.randn(K, T, model.latent_dim, model.latent_dim, generator=gen)
    cov = spread * (a @ a.mT / model.latent_dim + 0.5 * torch.eye(model.latent_dim))
    if not g_dim:
        return MeanFieldGuide(loc, cov)
    return MeanFieldGuide(loc, cov, torch.tensor([0.2]), torch.tensor([[0.05]]))


def _mc_elbo(vb, z, guide, values, M):
    """Per-particle ``log p~(x, z) - log q(x)`` drawn through the guide with Pyro."""
    pyro.clear_param_store()
    nb = guide.loc.dim() - 2
    with pyro.plate("particles", M, dim=-(nb + 1)):
        gtr = poutine.trace(guide).get_trace()
        mtr = poutine.trace(poutine.replay(vb.pyro_model, trace=gtr)).get_trace(
            z, guide, values=values
        )
    gtr.compute_log_prob()
    mtr.compute_log_prob()
    total = 0.0
    for tr, sign in ((mtr, 1.0), (gtr, -1.0)):
        for site in tr.nodes.values():
            if site["type"] == "sample":
                total = total + sign * site["log_prob"]
    return total  # [M, K]


def _check_mc(F, samples):
    mean = samples.mean(0)
    se = samples.std(0) / math.sqrt(samples.shape[0])
    assert torch.all(se < 0.05 * F.abs().clamp_min(1.0)), "Monte-Carlo error too large to judge"
    assert torch.all((mean - F).abs() < 4.0 * se + 1e-8), (F, mean, se)


@pytest.mark.parametrize("name", ["hgpdm", "shared", "scaled"])
def test_free_energy_matches_pyro_monte_carlo_discrete(name, styles, request):
    model = request.getfixturevalue(name)
    torch.manual_seed(0)
    gen = torch.Generator().manual_seed(1)
    vb = VariationalInference(model)
    z = _window(styles.sequences[1], 2, 4, missing=(2,))
    guide = _random_guide(model, 4, 2, gen)
    F = vb.guide_free_energy(z, guide).detach()
    assert F.shape == (2,)
    _check_mc(F, _mc_elbo(vb, z, guide, None, 20000).detach())


def test_free_energy_matches_pyro_monte_carlo_gpdm_and_continuous(hgpdm, styles, iddm):
    torch.manual_seed(0)
    gen = torch.Generator().manual_seed(2)
    gpdm = GPDM(styles.sequences, 2, alpha=ALPHA, measurement="linear")
    vb = VariationalInference(gpdm)
    z = _window(styles.sequences[0], 0, 3)
    guide = _random_guide(gpdm, 3, 1, gen)
    F = vb.guide_free_energy(z, guide).detach()
    _check_mc(F, _mc_elbo(vb, z, guide, None, 20000).detach())

    model, data = iddm
    vb = VariationalInference(model)
    z = _window(data.sequences[0], 3, 4, missing=(0,))
    guide = _random_guide(model, 4, 1, gen, g_dim=1)
    F = vb.guide_free_energy(z, guide).detach()
    _check_mc(F, _mc_elbo(vb, z, guide, None, 20000).detach())


def test_free_energy_gradcheck(hgpdm, shared, styles, iddm):
    gen = torch.Generator().manual_seed(3)
    for model in (hgpdm, shared):
        vb = VariationalInference(model)
        z = _window(styles.sequences[2], 1, 3, missing=(1,))
        guide = _random_guide(model, 3, 2, gen)
        loc = guide.loc.detach().requires_grad_(True)
        tril = guide.scale_tril.detach().requires_grad_(True)
        fun = lambda a, b, vb=vb, z=z: vb.free_energy(z, a, b)  # noqa: E731
        assert torch.autograd.gradcheck(fun, (loc, tril))
    model, data = iddm
    vb = VariationalInference(model)
    z = _window(data.sequences[1], 0, 3)
    guide = _random_guide(model, 3, 1, gen, g_dim=1)
    args = [
        t.detach().requires_grad_(True)
        for t in (guide.loc, guide.scale_tril, guide.g_loc, guide.g_scale_tril)
    ]
    fun = lambda a, b, c, d: vb.free_energy(z, a, b, g_loc=c, g_scale_tril=d)  # noqa: E731
    assert torch.autograd.gradcheck(fun, tuple(args))


@pytest.mark.parametrize("name", ["hgpdm", "shared"])
def test_point_predictions_equal_gp_posterior(name, generator, request):
    vb = VariationalInference(request.getfixturevalue(name))
    x = torch.randn(7, 2, generator=generator)
    m, v = vb.window.h.predict_point(x)
    ref_m, ref_v = vb.measurement.predict(x, include_noise=True)
    torch.testing.assert_close(m + vb.measurement.offset, ref_m)
    torch.testing.assert_close(v[:, None] * vb.measurement.scale.pow(2), ref_v)
    codes = torch.tensor([0, 1])
    f = vb.window.transition_gp(codes)
    mf, vf = f.predict_point(x[:, None, None, :].expand(7, 2, 1, 2))
    ref = vb.transition.predict(
        torch.cat([x[:, None, :].expand(7, 2, 2), codes[:, None].expand(7, 2, 1).to(x.dtype)], -1),
        include_noise=True,
    )
    torch.testing.assert_close(mf[:, :, 0], ref[0])
    torch.testing.assert_close(vf[:, :, 0, None].expand(7, 2, 2), ref[1])


def test_observation_cross_covariance_matches_monte_carlo(hgpdm, generator):
    """App. 2.B: Cov[z_s, z_t] = scale^2 E[k(x_s, x_t) - k_s^T K^-1 k_t] for independent x."""
    vb = VariationalInference(hgpdm)
    gen = torch.Generator().manual_seed(5)
    guide = _random_guide(hgpdm, 3, 1, gen, spread=0.1)
    mean, cov = guide.loc.detach()[0], guide.cov.detach()[0]
    m, S = vb.observation_joint(mean, cov)
    dz = hgpdm.obs_dim
    S = S.reshape(3, dz, 3, dz)
    M = 200000
    xs = mean + (torch.linalg.cholesky(cov) @ torch.randn(M, 3, 2, 1, generator=gen))[..., 0]
    post = vb.measurement
    k = post.kernel(xs.reshape(-1, 2), post.train_inputs).to_dense().reshape(M, 3, -1)
    kk = post.kernel(xs[:, 0], xs[:, 2], diag=True)
    samples = kk - ((k[:, 0] @ post.kinv) * k[:, 2]).sum(-1)  # posterior cov of f(x_1), f(x_3)
    samples = samples.detach()
    se = float(samples.std() / math.sqrt(M))
    expect = samples.mean() * post.scale.pow(2)
    assert torch.allclose(
        S[0, :, 2, :].diagonal(), expect, atol=4 * se * float(post.scale.max() ** 2)
    )
    assert torch.allclose(S[0, :, 2, :] - torch.diag(S[0, :, 2, :].diagonal()), torch.zeros(dz, dz))
    # diagonal blocks are the moment-matched marginals; the whole matrix is a covariance
    _, Sm = vb.observation_marginals(mean, cov)
    torch.testing.assert_close(S[1, :, 1, :], Sm[1])
    assert torch.linalg.eigvalsh(S.reshape(3 * dz, 3 * dz)).min() > 0


def test_condition_gaussian_matches_dense_reference(generator):
    n = 6
    a = torch.randn(2, n, n, generator=generator)
    cov = a @ a.mT + 0.1 * torch.eye(n)
    mean = torch.randn(2, n, generator=generator)
    values = torch.randn(2, n, generator=generator)
    obs = torch.tensor([[1, 0, 1, 1, 0, 0], [0, 1, 1, 0, 1, 1]], dtype=torch.bool)
    cm, cS = condition_gaussian(mean, cov, obs, values)
    for b in range(2):
        o, u = obs[b].numpy(), ~obs[b].numpy()
        C, m, v = cov[b].numpy(), mean[b].numpy(), values[b].numpy()
        gain = C[np.ix_(u, o)] @ np.linalg.inv(C[np.ix_(o, o)])
        np.testing.assert_allclose(cm[b].numpy()[u], m[u] + gain @ (v[o] - m[o]), rtol=1e-10)
        np.testing.assert_allclose(cm[b].numpy()[o], v[o])
        ref = C[np.ix_(u, u)] - gain @ C[np.ix_(o, u)]
        np.testing.assert_allclose(cS[b].numpy()[np.ix_(u, u)], ref, rtol=1e-9, atol=1e-12)
        assert np.abs(cS[b].numpy()[o]).max() == 0


def test_batched_lbfgs_solves_independent_problems(generator):
    B, P = 5, 4
    a = torch.randn(B, P, P, generator=generator)
    H = a @ a.mT + torch.diag_embed(torch.logspace(-2, 2, P).expand(B, P))
    b = torch.randn(B, P, generator=generator)

    def fun(x, rows=slice(None)):  # quadratic plus the Rosenbrock valley in two coordinates
        quad = 0.5 * (x[:, None, :] @ H[rows] @ x[:, :, None])[:, 0, 0] - (b[rows] * x).sum(-1)
        return quad + (1 - x[:, 0]).pow(2) + 10 * (x[:, 1] - x[:, 0].pow(2)).pow(2)

    x, hist = batched_lbfgs(fun, torch.zeros(B, P), max_iter=200, tol_grad=1e-9)
    for i in range(B):
        ref = minimize(
            lambda v, i=i: float(fun(torch.tensor(v)[None], slice(i, i + 1))[0]),
            np.zeros(P),
            method="Nelder-Mead",
            options={"xatol": 1e-10, "fatol": 1e-14, "maxiter": 20000},
        )
        assert float(fun(x[i : i + 1], slice(i, i + 1))[0]) <= ref.fun + 1e-8
        np.testing.assert_allclose(x[i].numpy(), ref.x, atol=1e-4)
    assert np.all(np.diff(hist) <= 1e-12)  # monotone (Armijo)


def test_infer_increases_free_energy_and_svi_can_fit_the_guide(hgpdm, styles):
    vb = VariationalInference(hgpdm)
    z = _window(styles.sequences[3], 4, 5, missing=(4,))
    res = vb.infer(z, steps=30, newton_steps=0, init="prior")
    assert res.history[-1] < res.history[0]
    assert res.log_evidence.shape == (2,) and res.mean.shape == (2, 5, 2)
    torch.testing.assert_close(res.posterior.sum(-1), torch.tensor(1.0))
    # the guide works with pyro.infer: SVI on the same objective raises F from the prior start
    pyro.clear_param_store()
    torch.manual_seed(0)
    loc, cov, _, _ = vb.initial_guess(z, vb.values, "prior")
    guide = MeanFieldGuide(loc, cov)
    before = vb.guide_free_energy(z, guide).sum().item()
    svi = pyro.infer.SVI(
        vb.pyro_model,
        guide,
        pyro.optim.Adam({"lr": 0.02}),
        pyro.infer.Trace_ELBO(num_particles=8, vectorize_particles=True),
    )
    for _ in range(60):
        svi.step(z, guide)
    assert vb.guide_free_energy(z, guide).sum().item() > before + 1.0


def test_forecast_and_gap_shapes_batched(hgpdm, styles):
    vb = VariationalInference(hgpdm)
    z = torch.stack([styles.sequences[j][3:7] for j in range(4)])
    mean, var, res = vb.forecast(z, steps=20)
    assert mean.shape == (4, 5) and (var > 0).all()
    assert res.mean.shape == (4, 2, 5, 2)
    gap = z.clone()
    gap[:, 1:3] = float("nan")
    res = vb.infer(gap, steps=20)
    rec, rv = vb.predict_observations(gap, res)
    torch.testing.assert_close(rec[:, 0], z[:, 0])
    assert (rv[:, 1:3] > 0).all() and torch.all(rv[:, 0] == 0)
    oracle = vb.infer(gap, values=styles.labels[:4, None], steps=10)
    assert oracle.log_evidence.shape == (4, 1)


def test_joint_prediction_in_chunks_matches_one_batch(hgpdm, styles, monkeypatch):
    """The joint q(z) is conditioned in chunks of windows (``_JOINT_ENTRIES``): one window at a
    time gives what one batch gives, for windows whose missing rows differ (so a chunk takes
    the gathered path where the whole batch takes the masked one). Tolerance: the same
    conditioning of O(1) values on at most 25 entries, by Cholesky with or without identity padding
    (1e-10)."""
    vb = VariationalInference(hgpdm)
    z = torch.stack([styles.sequences[j][2:7] for j in range(4)])
    z[0, 4] = z[1, 2:4] = z[2, 0] = float("nan")  # window 3 is complete
    res = vb.infer(z, steps=20)
    whole = vb.predict_observations(z, res)
    monkeypatch.setattr(prediction, "_JOINT_ENTRIES", 1.0)  # one window and candidate per chunk
    for got, want in zip(vb.predict_observations(z, res), whole, strict=True):
        assert got.shape == want.shape == (4, 5, 5)
        torch.testing.assert_close(got, want, rtol=0, atol=1e-10)


def test_candidate_forecasts_match_separate_inferences(hgpdm, styles):
    """One posterior over all g gives the ML g's forecast (plain and AR(1)) of
    ``VariationalInference.forecast``, the oracle's (a separate inference with the true g),
    their Bayesian average, and the MAP baseline's at the Laplace start's states. Tolerances:
    the same algebra batched over K candidates (1e-9 on O(1) forecasts: reductions in another
    order); a separate inference stops at the optimiser's tolerance (1e-6)."""
    vb = VariationalInference(hgpdm)
    z = torch.stack([styles.sequences[j][3:8] for j in range(4)])
    cf = candidate_forecasts(vb, z, prune=None)
    assert cf.mean.shape == cf.ar1_mean.shape == (4, 2, 5)
    for residual in (None, "ar1"):
        mean, _, res = vb.forecast(z, residual=residual, prune=None)
        got = cf.pick(res.g_ml, ar1=residual is not None)
        torch.testing.assert_close(got, mean, rtol=0, atol=1e-9)
    truth = styles.labels[:4]
    oracle, _, _ = vb.forecast(z, values=truth[:, None], prune=None)
    index = (vb.values[None] == truth[:, None]).long().argmax(-1)
    torch.testing.assert_close(cf.pick(index), oracle, rtol=0, atol=1e-6)
    # the MAP baseline's forecast at the Laplace start's states (30 iterations, no pruning)
    map_oracle, _, _ = MAPInference(hgpdm).forecast(z, values=truth[:, None], steps=30)
    torch.testing.assert_close(cf.pick(index, map_states=True), map_oracle, rtol=0, atol=1e-6)
    with pytest.raises(ValueError, match="AR"):
        cf.pick(index, ar1=True, map_states=True)
    # the per-step reconstruction under the ML g is VB's unconditioned (FIC marginal) prediction
    # of every row of the window with the forecast row appended
    assert cf.reconstruction.shape == (4, 2, 6, 5)
    with_row = torch.cat([z, torch.full_like(z[:, :1], float("nan"))], 1)
    marginal = vb.predict_observations(with_row, cf.result, joint=False)[0]
    rec_ml = cf.reconstruction[torch.arange(4), cf.result.g_ml]
    torch.testing.assert_close(rec_ml, marginal, rtol=0, atol=1e-9)
    post = cf.result.posterior
    want = post[:, 0, None] * cf.mean[:, 0] + post[:, 1, None] * cf.mean[:, 1]
    torch.testing.assert_close(cf.averaged(), want, rtol=0, atol=1e-12)
    # a GPDM has one candidate: the average is its forecast
    gp = GPDM(styles.sequences, 2)
    gp.fit(5, warn=False)
    one = candidate_forecasts(VariationalInference(gp), z, newton_steps=MAP_STEPS)
    torch.testing.assert_close(one.averaged(), one.pick(one.result.g_ml), rtol=0, atol=1e-12)
    map_gp, _, _ = MAPInference(gp).forecast(z)
    torch.testing.assert_close(
        one.pick(one.result.g_ml, map_states=True), map_gp, rtol=0, atol=1e-6
    )


def test_sparse_measurement_gp(hgpdm, styles):
    """``measurement_points`` routes the measurement GP through the latents of evenly spaced
    training frames (DTC on all the data): the exact GP when ``points >= N``, else
    ``GPPosterior.sparse`` on those latents; VB runs on it and forecasts close to the exact GP
    (within 10% of the forecast's scale with half the frames as pseudo-inputs)."""
    n = hgpdm.latent.shape[0]
    full, same = hgpdm.measurement_posterior(), hgpdm.measurement_posterior(n + 5)
    torch.testing.assert_close(same.weights, full.weights, rtol=0, atol=0)
    sub = hgpdm.measurement_posterior(n // 2)
    rows = torch.linspace(0, n - 1, n // 2).round().long()
    assert rows[0] == 0 and rows[-1] == n - 1 and sub.train_inputs.shape[0] == n // 2
    want = full.sparse(hgpdm.latent.detach()[rows])
    torch.testing.assert_close(sub.weights, want.weights, rtol=0, atol=0)
    vb, exact = VariationalInference(hgpdm, measurement_points=n // 2), VariationalInference(hgpdm)
    assert vb.measurement.train_inputs.shape[0] == n // 2
    z = torch.stack([styles.sequences[j][3:7] for j in range(4)])
    mean, var, _ = vb.forecast(z)
    ref = exact.forecast(z)[0]
    assert bool((var > 0).all())
    assert float((mean - ref).abs().max()) < 0.1 * float(ref.abs().max())
    for bad in (1, 2.5, True):
        with pytest.raises(ValueError, match="points"):
            hgpdm.measurement_posterior(bad)


def test_bad_input(hgpdm, styles):
    vb = VariationalInference(hgpdm)
    z = styles.sequences[0][:4]
    with pytest.raises(ValueError, match="at least 2 time steps"):
        vb.infer(z[:1])
    with pytest.raises(ValueError, match="Dz = 5"):
        vb.infer(z[:, :3])
    with pytest.raises(ValueError, match="every row is missing"):
        vb.infer(torch.full_like(z, float("nan")))
    part = z.clone()
    part[1, 0] = float("nan")
    with pytest.raises(ValueError, match="partially observed"):
        vb.infer(part)
    inf = z.clone()
    inf[0, 0] = float("inf")
    with pytest.raises(ValueError, match="inf"):
        vb.infer(inf)
    with pytest.raises(ValueError, match="codes in"):
        vb.infer(z, values=[0, 5])
    with pytest.raises(ValueError, match="init"):
        vb.infer(z, init="random")
    with pytest.raises(TypeError, match="GPDM"):
        VariationalInference("model")
    with pytest.raises(ValueError, match="g_prior"):
        VariationalInference(hgpdm, g_prior=[0.2, 0.2])
    k = hgpdm.num_values
    with pytest.raises(ValueError, match="positive"):  # a zero prior would give -inf evidence
        VariationalInference(hgpdm, g_prior=[1.0] + [0.0] * (k - 1))


@pytest.mark.parametrize("name", ["hgpdm", "scaled"])
def test_precision_blocks_equal_fisher_information_of_the_terms(name, styles, request):
    """Fisher precision against autograd's Jacobian of an augmented residual vector built from
    GPPosterior.predict (gpytorch kernels, which scale the transition variance per latent dim
    for ``scaled``): the residuals whitened by variances frozen at the expansion point (the
    Gauss-Newton part) and, per Gaussian term of D outputs, ``sqrt(D / 2) log sigma^2(x)`` with
    the live variance, whose outer product is the variance's Fisher information ``D / 2 grad
    log sigma^2 grad log sigma^2^T``. Dense J^T J of sums of O(10) products of O(1-100) numbers:
    agreement to 1e-10 relative, the Fisher part is O(1) of the total (checked)."""
    model = request.getfixturevalue(name)
    vb = VariationalInference(model)
    z = _window(styles.sequences[1], 3, 4, missing=(2,))
    observed = ~torch.isnan(z).all(-1)
    x0 = model.latent.detach()[5:9] + 0.05
    h, f = vb.measurement, vb.transition
    code = torch.ones(3, 1)
    vz = h.predict(x0, include_noise=True)[1]
    vx = f.predict(torch.cat([x0[:-1], code], -1), include_noise=True)[1]
    L1, m1 = torch.linalg.cholesky(vb.window.x1_cov), vb.window.x1_mean
    dx, dz = model.latent_dim, model.obs_dim

    def residuals(x, variance):
        r1 = torch.linalg.solve_triangular(L1, (x[0] - m1)[:, None], upper=False)[:, 0]
        fx = f.predict(torch.cat([x[:-1], code], -1), include_noise=True)
        hz = h.predict(x, include_noise=True)
        rx = (x[1:] - fx[0]) / vx.sqrt()
        rz = (torch.nan_to_num(z) - hz[0]) / vz.sqrt()
        out = [r1, rx.flatten(), rz[observed].flatten()]
        if variance:  # one shared variance per term: its log in any output column
            out += [(dx / 2) ** 0.5 * fx[1][:, 0].log(), (dz / 2) ** 0.5 * hz[1][observed, 0].log()]
        return torch.cat(out)

    J = torch.autograd.functional.jacobian(lambda x: residuals(x, True), x0).reshape(-1, 8)
    diag, off = vb.window.precision_blocks(observed, x0[None], torch.tensor([1]), None)
    fisher = vb.window.dense(diag, off)[0]
    torch.testing.assert_close(fisher, J.T @ J, rtol=1e-10, atol=1e-10)
    Jgn = torch.autograd.functional.jacobian(lambda x: residuals(x, False), x0).reshape(-1, 8)
    assert float((fisher - Jgn.T @ Jgn).abs().max()) > 1e-2 * float(fisher.abs().max())


def test_laplace_start_is_near_the_optimum_of_the_free_energy(hgpdm, styles):
    """F at the mean-field Laplace start is within 0.05 nats of scipy's L-BFGS-B optimum of F
    (run from there)."""
    vb = VariationalInference(hgpdm)
    z = _window(styles.sequences[0], 2, 5)
    res = vb.infer(z)
    k = int(res.g_ml)
    loc, cov = res.mean[k], res.cov[k]
    tril = torch.linalg.cholesky(cov)
    n = loc.numel()

    def fun(v):
        v = torch.tensor(v, requires_grad=True)
        lt = torch.tril(v[n:].reshape(tril.shape))
        F = vb.free_energy(z, v[:n].reshape(1, *loc.shape), lt[None], values=[k])[0]
        (g,) = torch.autograd.grad(-F, v)
        return float(-F.detach()), g.numpy()

    ref = minimize(fun, torch.cat([loc.flatten(), tril.flatten()]).numpy(), jac=True,
                   method="L-BFGS-B", options={"maxiter": 5000, "ftol": 1e-15})  # fmt: skip
    assert -ref.fun >= float(res.log_evidence[k]) - 1e-9
    assert -ref.fun - float(res.log_evidence[k]) < 0.05


# ---------------------------------------------------------------- acceptance (issue 4)


@pytest.fixture(scope="module")
def planted():
    """Three planted styles; train/test split of ONE generated set (same observation map)."""
    train, test = styled_movements(3, 4, 30, 12, seed=0).split(0.25, seed=0)
    model = HGPDM(train.sequences, train.labels, 3)
    model.fit(60, warn=False)  # a step budget: recognition needs no converged fit
    return train, test, model


def _forecast_windows(test, length, stride):
    return forecast_windows(test.sequences, test.labels, length, stride)


def test_acceptance_vb_recognises_planted_styles_and_beats_map(planted):
    _, test, model = planted
    z, nxt, y = _forecast_windows(test, 5, 3)
    mean, _, res = VariationalInference(model).forecast(z)
    assert float((res.g_ml == y).double().mean()) >= 0.95
    rmse_vb = float((mean - nxt).pow(2).mean().sqrt())
    map_mean, _, _ = MAPInference(model).forecast(z)
    rmse_map = float((map_mean - nxt).pow(2).mean().sqrt())
    assert rmse_vb < rmse_map, (rmse_vb, rmse_map)


def test_pruning_hopeless_candidates_keeps_the_posterior(planted):
    """Pruned LM (the default) against LM refining every candidate to convergence: the same ML
    style, the same F for it (up to LM's stopping tolerance, 1e-3 nats; roundoff in differently
    composed batches can move a stop by one step) and the same posterior."""
    _, test, model = planted
    z, _, _ = _forecast_windows(test, 5, 4)
    vb = VariationalInference(model)
    full = vb.infer(z, prune=None)
    pruned = vb.infer(z)
    assert torch.equal(pruned.g_ml, full.g_ml)
    best = full.g_ml[:, None]
    torch.testing.assert_close(
        pruned.log_evidence.gather(-1, best), full.log_evidence.gather(-1, best), rtol=0,
        atol=1e-3,
    )  # fmt: skip
    assert float((pruned.posterior - full.posterior).abs().max()) < 1e-3
    with pytest.raises(ValueError, match="prune"):
        vb.infer(z[0], prune=-1.0)


@pytest.mark.xfail(
    strict=True,
    reason="known defect: with the fully fitted model the optimistic bound (3x the first-order "
    "gain) of a far-off best candidate trails the others by > prune nats, so it is pruned",
)
def test_pruning_keeps_a_candidate_that_starts_far_off(planted):
    """The best candidate started far from its optimum (thousands of nats behind the others) has
    a large predicted gain, so it is refined, not pruned, and reaches the unpruned optimum."""
    _, test, model = planted
    vb = VariationalInference(model)
    z, observed = window_mask(test.sequences[0][:8], vb.obs_dim, vb.window.x1_mean)
    values = vb.values
    x0 = vb.initial_guess(z, values)[0]
    start, _ = laplace(vb.window, z, observed, x0, values, prune=None)  # the others start converged
    k = int((-vb.window.log_joint(z, observed, start, values)).argmin())  # the best candidate ...
    start[k] = x0[k] + 2.0  # ... starts far off
    f0 = -vb.window.log_joint(z, observed, start, values)
    assert float(f0[k]) > float(f0.min()) + 1000.0
    ref, _ = laplace(vb.window, z, observed, start, values, prune=None)
    out, _ = laplace(vb.window, z, observed, start, values, prune=50.0)
    torch.testing.assert_close(out[k], ref[k], rtol=0, atol=1e-4)


def test_transition_gp_per_code_parts_equal_padded_blocks(planted):
    """Codes along one batch axis (K candidates; one code per row, repeated) are computed per
    code on unpadded views of their blocks: the same predictions, Jacobians and mean moments
    as the padded per-entry blocks (codes varying along two axes)."""
    from hgpdm_torch.inference.variational.gaussian_input import GaussianInputGP

    train, _, _ = planted
    # one code more than the styles present: a code without training points (as a subject
    # missing from Four Walkers' folds), whose part keeps one padding row
    model = HGPDM(train.sequences, train.labels, 3, num_values=4)
    with torch.no_grad():
        model.transition_noise = 0.1  # a well-conditioned K_x: see the tolerance below
    vb = VariationalInference(model)
    post, K = vb.window.transition, model.num_values
    # Each output sums N kernel-weighted terms (weights K^-1 Y, or K^-1 itself in the
    # variance) of unit-scale kernels; another summation order moves such a sum by at most
    # N eps sum|terms|. With these bounds on the weights that is below 261 * 2.2e-16 * 3e3
    # * (a few) ~ 1e-9, while a wrong block or code moves an output by O(0.01-1).
    N = post.train_inputs.shape[-2]
    assert float(post.weights.abs().sum(-2).max()) < 3e3
    assert N * float(post.kinv.abs().max()) < 3e3
    tol = {"rtol": 1e-9, "atol": 1e-9}
    gen = torch.Generator().manual_seed(3)
    mu = torch.randn(2, K, 4, 3, generator=gen, dtype=torch.float64)
    a = torch.randn(2, K, 4, 3, 3, generator=gen, dtype=torch.float64)
    Sigma = 0.01 * a @ a.mT
    codes = torch.arange(K)
    padded = GaussianInputGP(post, codes.expand(2, K)[..., None])  # two varying axes
    parts = GaussianInputGP(post, codes[:, None])
    assert parts.parts and not padded.parts
    points = [gp.predict_point(mu, jacobian=True) for gp in (parts, padded)]
    for got, ref in zip(*points, strict=True):
        torch.testing.assert_close(got, ref, **tol)
    for got, ref in zip(parts.mean_moments(mu, Sigma), padded.mean_moments(mu, Sigma), strict=True):
        torch.testing.assert_close(got, ref, **tol)
    rows = torch.tensor([2, 0, 2, 1, 0])[:, None, None] % K  # one code per row, repeated
    per_row = GaussianInputGP(post, rows)
    x = mu[0, 0, :2].expand(5, 1, 2, 3)  # [rows, K = 1, T, Dx]
    padded_rows = GaussianInputGP(post, rows.expand(5, 2, 1))
    ref = padded_rows.predict_point(x.expand(5, 2, 2, 3), jacobian=True)
    for got, r in zip(per_row.predict_point(x, jacobian=True), ref, strict=True):
        torch.testing.assert_close(got, r[:, :1], **tol)


def test_lm_broadcasts_windows_and_refuses_bad_prune(planted):
    """Windows broadcast against one set of initial states and each equals its own solve; a
    bad prune is refused."""
    _, test, model = planted
    vb = VariationalInference(model)
    z, observed = window_mask(
        torch.stack([s[:6] for s in test.sequences[:3]]), 12, vb.window.x1_mean
    )
    x0 = vb.initial_guess(z[0], vb.values)[0]  # [K, T, Dx], broadcast over the 3 windows
    rows, _ = laplace(vb.window, z, observed, x0, vb.values, prune=50.0)
    assert rows.shape == (3, *x0.shape)
    one, _ = laplace(vb.window, z[1], observed[1], x0, vb.values, prune=50.0)
    # equal up to LM's stopping tolerance (roundoff in other batch shapes can move a stop by a
    # step below 1e-3 nats)
    lj = [vb.window.log_joint(z[1], observed[1], x, vb.values) for x in (rows[1], one)]
    torch.testing.assert_close(lj[1], lj[0], rtol=0, atol=1e-3)
    with pytest.raises(ValueError, match="prune"):
        laplace(vb.window, z, observed, x0, vb.values, prune=-1.0)


def test_batched_windows_equal_one_window_at_a_time(planted):
    """Windows solved in one call (problems compacted as they converge) equal separate calls."""
    _, test, model = planted
    z, _, _ = _forecast_windows(test, 5, 7)
    vb = VariationalInference(model)
    batched = vb.infer(z[:6])
    for i in range(6):
        one = vb.infer(z[i])
        # equal up to LM's stopping tolerance, 1e-3 nats: rounding in another batch shape can
        # move a window's stop by a step that gains less than that (measured: up to 1.6e-4)
        torch.testing.assert_close(batched.log_evidence[i], one.log_evidence, rtol=0, atol=1e-3)
        assert torch.equal(batched.g_ml[i], one.g_ml)


def test_laplace_start_avoids_the_stall_of_lbfgs_alone(planted):
    """With the thesis's stiff alpha-bar (alpha_4 = 1e-4), L-BFGS on F from the GP-RTSS smoother
    stalls far below the Laplace start for the true style (the cause of the 38% recognition)."""
    _, test, model = planted
    vb = VariationalInference(model)
    z = test.sequences[2][:5]
    good = vb.infer(z, values=[2])
    plain = vb.infer(z, values=[2], newton_steps=0, steps=20, init="smoother")
    assert float(plain.log_evidence[0]) < float(good.log_evidence[0]) - 20.0


def test_acceptance_gap_recovery_hgpdm_beats_gpdm():
    """3-frame gaps in 10-frame windows of two planted styles: the VB H-GPDM recovers them
    better than the GPDM (RMSE 0.023 against 0.053). It failed (0.165) while the Laplace start
    used Gauss-Newton without the variances' curvature, which left the H-GPDM's states far from
    their maximum (issue 30)."""
    train, test = styled_movements(2, 4, 30, 12, seed=3).split(0.25, seed=0)
    errors = {}
    for name, model in (
        ("hgpdm", HGPDM(train.sequences, train.labels, 3)),
        ("gpdm", GPDM(train.sequences, 3)),
    ):
        model.fit(60, warn=False)  # a step budget, as the experiments use
        z = torch.stack([s[i : i + 10] for s in test.sequences for i in range(0, 20, 4)])
        gap = z.clone()
        gap[:, 4:7] = float("nan")
        vb = VariationalInference(model)
        rec, var = vb.predict_observations(gap, vb.infer(gap))
        assert torch.all(var[:, 4:7] > 0)
        errors[name] = float((rec[:, 4:7] - z[:, 4:7]).pow(2).mean().sqrt())
    assert errors["hgpdm"] < errors["gpdm"], errors
