"""An H-GPDM with kernels of the user's choosing, end to end: a Matern-5/2 transition kernel over
``[x, g]`` and a periodic-plus-RBF measurement kernel, neither with closed-form Gaussian-input
expectations (hgpdm_torch.quadrature integrates them).

Oracles: Monte Carlo of the GP predictions at sampled inputs for the moment-matched predictions
(within the rule's documented error plus Monte-Carlo error); the training intentions for the
online filter's beliefs; the model before saving for the one loaded into a model rebuilt by the
user's code.
"""

from __future__ import annotations

import math

import pytest
import torch
from gpytorch.kernels import MaternKernel, PeriodicKernel, RBFKernel, ScaleKernel

from hgpdm_torch.datasets import targeted_movements
from hgpdm_torch.decision.basis import RadialBasis
from hgpdm_torch.decision.lspi import lspi
from hgpdm_torch.decision.mcp import Belief, MonteCarloPlanner
from hgpdm_torch.decision.stopping import StoppingProblem, belief_vector
from hgpdm_torch.inference.intention import OnlineIntentionFilter, infer_intention
from hgpdm_torch.inference.variational import VariationalInference
from hgpdm_torch.models import HGPDM, load_model
from hgpdm_torch.models.persistence import ModelFileError

GRID = torch.linspace(-1.0, 1.0, 9)[:, None]


def _kernels():
    transition = ScaleKernel(MaternKernel(nu=2.5))
    transition.base_kernel.lengthscale = 1.0
    measurement = ScaleKernel(PeriodicKernel()) + ScaleKernel(RBFKernel())
    return transition, measurement


def _build(data):
    transition, measurement = _kernels()
    return HGPDM(
        data.sequences, data.labels, 2, intention="continuous",
        transition_kernel=transition, measurement_kernel=measurement,
    )  # fmt: skip


@pytest.fixture(scope="module")
def data():
    return targeted_movements(10, 8, 6, noise=0.02, seed=3)


@pytest.fixture(scope="module")
def model(data):
    torch.manual_seed(0)
    m = _build(data)
    m.fit(20, warn=False)
    return m


def test_the_kernels_are_the_users_and_the_fit_lowers_the_loss(data):
    m = _build(data)
    assert isinstance(m.transition_kernel.base_kernel, MaternKernel)
    with torch.no_grad():
        before = float(m.loss())
    m.fit(5, warn=False)
    with torch.no_grad():
        assert float(m.loss()) < before
    with pytest.raises(ValueError, match="measurement= or measurement_kernel="):
        HGPDM(data.sequences, data.labels, 2, intention="continuous",
              measurement="linear", measurement_kernel=RBFKernel())  # fmt: skip
    with pytest.raises(TypeError, match="transition_kernel must be a gpytorch Kernel"):
        HGPDM(data.sequences, data.labels, 2, intention="continuous", transition_kernel="rbf")


def _mc_prediction(post, mu, Sigma, g=None, m=100_000):
    """Moments of the GP output (noise included) at x ~ N(mu, Sigma), by sampling x."""
    gen = torch.Generator().manual_seed(1)
    x = mu + torch.randn(m, mu.shape[-1], generator=gen) @ torch.linalg.cholesky(Sigma).T
    inputs = x if g is None else torch.cat([x, g.expand(m, -1)], -1)
    mean, var = post.predict(inputs, include_noise=True)
    total = mean.mean(0), torch.cov(mean.T) + torch.diag(var.mean(0))
    return total, mean.std(0) / math.sqrt(m)


def test_gaussian_input_moments_agree_with_monte_carlo(model):
    """Both GPs' moment-matched predictions at a Gaussian around a training state against Monte
    Carlo of their point predictions. The input's sd is 0.1 of the shortest effective length
    scale (the periodic kernel's ``l p / (2 pi)``; 0.084 after the fit), where the rule's
    documented error is below 1e-5 of the kernel's scale: the means agree within 5 Monte-Carlo
    standard errors plus 1e-4 of the output's scale, the covariances within 2% (the sample
    covariance of 1e5 draws is good to ~0.5%) plus 1e-3 of the largest variance."""
    periodic = model.measurement_kernel.kernels[0].base_kernel
    effective = float((periodic.lengthscale * periodic.period_length).detach()) / (2 * math.pi)
    x = torch.cat(model.latent_sequences()).detach()
    mu, Sigma = x[3], (0.1 * effective) ** 2 * torch.eye(x.shape[1])
    g = model.intentions[0]
    for post, extra in ((model.transition_posterior(), g), (model.measurement_posterior(), None)):
        with torch.no_grad():
            args = {"g": extra} if extra is not None else {}
            mean, cov, _ = post.predict_gaussian(mu, Sigma, include_noise=True, **args)
        (mc_mean, mc_cov), se = _mc_prediction(post, mu, Sigma, extra)
        scale = float(mc_cov.diagonal().max())
        assert bool(((mean - mc_mean).abs() <= 5 * se + 1e-4 * scale**0.5).all())
        torch.testing.assert_close(cov, mc_cov, rtol=0.02, atol=1e-3 * scale)


def test_it_filters_online_runs_vb_and_plans(model, data):
    """The online filter recognises the training targets (belief means within 0.25 of the
    labels on average, chance is ~0.7), VB gives finite evidence, batch inference (GP-ADF and
    RTS smoothing) puts its mean within 0.5 of each label, MCP decides."""
    z = torch.stack(data.sequences)
    f = OnlineIntentionFilter(model, GRID, forgetting=0.1, batch_size=z.shape[0])
    means, covs, logs = [], [], []
    for t in range(z.shape[1]):
        out = f.update(z[:, t])
        assert not bool(out.reset_streams.any())
        if t >= 2:
            means.append(f.mean.clone())
            covs.append(f.cov.clone())
            logs.append(f.log_belief.clone())
    assert float((out.mean[:, 0] - data.labels.reshape(-1)).abs().mean()) < 0.25

    res = VariationalInference(model).infer(z[:2, :5], steps=5)
    assert bool(torch.isfinite(res.log_evidence).all())
    # batch inference: GP-ADF filtering and RTS smoothing under every grid value (Alg. 3.1)
    batch = infer_intention(model, z[:3], GRID)
    assert float((batch.mean[:, 0] - data.labels.reshape(-1)[:3]).abs().max()) < 0.5

    mean, cov, log_prob = (torch.stack(v, 1) for v in (means, covs, logs))
    beliefs = belief_vector(mean, cov, log_prob.exp())
    T = beliefs.shape[1]
    region = torch.bucketize(data.labels.reshape(-1), torch.tensor([-1 / 3, 1 / 3]))
    right = torch.arange(3)[None, :, None] == region[:, None, None]
    rewards = torch.where(right, torch.linspace(1.0, 0.2, T), torch.tensor(-1.0))
    problem = StoppingProblem(beliefs, rewards.expand(z.shape[0], 3, T))
    basis = RadialBasis(20, seed=0).fit(beliefs.reshape(-1, beliefs.shape[-1]))
    q = lspi(problem.transitions(problem.enumerate_episodes(), unique=True), features=basis).q
    planner = MonteCarloPlanner(model, f, q, basis, num_particles=200)
    decision = planner.decide(
        Belief(mean[0, 1], cov[0, 1], log_prob[0, 1]), generator=torch.Generator().manual_seed(0)
    )
    assert decision.action in range(4) and math.isfinite(decision.q_wait)


def test_saves_and_loads_into_the_users_model(model, data, tmp_path):
    path = tmp_path / "custom.pt"
    model.save(path)
    with pytest.raises(ModelFileError, match="transition_kernel"):
        load_model(path)
    loaded = load_model(path, model=_build(data))
    x = torch.cat(model.latent_sequences()).detach()[:5]
    with torch.no_grad():
        for name in ("transition_posterior", "measurement_posterior"):
            a, b = getattr(model, name)(), getattr(loaded, name)()
            inputs = x if name == "measurement_posterior" else torch.cat(
                [x, model.intentions[:1].expand(5, -1)], -1
            )  # fmt: skip
            torch.testing.assert_close(b.predict(inputs)[0], a.predict(inputs)[0])
