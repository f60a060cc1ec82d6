"""An output scale per latent dim of the transition GP (``scale_transitions=True``): a process
noise ``alpha_4 / v_d^2`` per latent dim.

Oracles: the moments at a Gaussian input against Monte Carlo of an unscaled GP whose variances
are divided by ``v_d^2`` by hand, and (with a phase) against Gauss-Hermite quadrature; the
online filter's first prediction against GP-ADF; the IDDM's shared fast path against the generic
path; save and load. The loss is checked against the dense SciPy reference in
``tests/models/test_loss.py``, the window objectives (MAP log joint, VB free energy,
Gauss-Newton precision) in ``test_map.py`` / ``test_variational.py``.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch
from gpytorch.priors import NormalPrior

from hgpdm_torch.datasets import targeted_movements
from hgpdm_torch.gp import GPPosterior
from hgpdm_torch.inference.filtering import filter_sequence
from hgpdm_torch.inference.intention import (
    GenericTransition,
    OnlineIntentionFilter,
    SharedTransition,
    transition_moments,
)
from hgpdm_torch.models import GPDM, IDDM, load_model

GRID = torch.linspace(-0.9, 0.9, 5)
ALPHA = (0.9, 0.3, 0.1, 1e-2)
SCALES = torch.tensor([0.5, 3.0], dtype=torch.float64)


@pytest.fixture(scope="module")
def data():
    return targeted_movements(8, 6, 4, noise=0.02, seed=5)


def _model(data, phase_width=None, scaled=True) -> IDDM:
    torch.manual_seed(0)
    model = IDDM(
        data.sequences, data.labels, 2, intention="continuous", measurement="linear",
        alpha=ALPHA, phase_width=phase_width, scale_transitions=scaled,
    )  # fmt: skip
    model.fit(8, warn=False)
    if scaled:
        model.transition_scales = SCALES
    return model


def test_moments_match_monte_carlo_of_the_unscaled_gp(data):
    model = _model(data, phase_width=1.0)
    post = model.transition_posterior()
    torch.testing.assert_close(post.scale, 1.0 / SCALES)
    # the same GP without the scale: the oracle divides its variances by v_d^2 itself
    plain = GPPosterior(post.kernel, post.train_inputs, post.train_targets, post.noise)
    mean, cov, _ = transition_moments(post, GRID[:, None].double(), phase=True).moments(
        model.latent.detach()[[2, 11]],
        0.05 * torch.eye(2, dtype=torch.float64).expand(2, 2, 2),
        torch.tensor([1.0, 2.0], dtype=torch.float64),
    )
    gen = torch.Generator().manual_seed(3)
    n = 200_000
    for b, (row, phase) in enumerate(((2, 1.0), (11, 2.0))):
        x = model.latent.detach()[row] + 0.05**0.5 * torch.randn(n, 2, generator=gen,
                                                                 dtype=torch.float64)  # fmt: skip
        for k in (0, 4):
            known = x.new_tensor([float(GRID[k]), phase]).expand(n, 2)
            m, v = plain.predict(torch.cat([x, known], -1))
            # total variance: Var[E f | x] + (E[Var f | x] + alpha_4) / v_d^2
            mc_cov = torch.cov(m.T) + torch.diag_embed((v.mean(0) + plain.noise) / SCALES**2)
            sd = m.std(0) / n**0.5
            assert ((mean[b, k] - m.mean(0)).abs() < 5 * sd + 1e-12).all()
            # MC relative error of a variance with 2e5 samples is ~0.3%: rtol 2% holds
            torch.testing.assert_close(cov[b, k], mc_cov, rtol=0.02, atol=2e-3 * float(
                mc_cov.diagonal().max()))  # fmt: skip


def test_shared_fast_path_takes_the_scales_like_the_generic_path(data):
    model = _model(data)
    post, values = model.transition_posterior(), GRID[:, None].double()
    shared = transition_moments(post, values)
    assert isinstance(shared, SharedTransition)
    generic = GenericTransition(post, values)
    mu = model.latent.detach()[[0, 7, 13]]
    Sigma = 0.02 * torch.eye(2, dtype=mu.dtype).expand(3, 2, 2)
    for a, b in zip(shared.moments(mu, Sigma), generic.moments(mu, Sigma), strict=True):
        # two summation orders of O(1) moments from N = 40 training points
        torch.testing.assert_close(a, b, rtol=1e-9, atol=1e-10)
    z = torch.stack([data.sequences[0][:4], data.sequences[5][:4]])
    f = OnlineIntentionFilter(model, GRID, batch_size=2)
    g = OnlineIntentionFilter(model, GRID, batch_size=2, transition="generic")
    unscaled = _model(data, scaled=False)
    with torch.no_grad():
        for name, p in unscaled.named_parameters():
            p.copy_(model.get_parameter(name))
    u = OnlineIntentionFilter(unscaled, GRID, batch_size=2)
    for t in range(4):
        got, want, other = f.update(z[:, t]), g.update(z[:, t]), u.update(z[:, t])
        torch.testing.assert_close(got.log_prob, want.log_prob, rtol=1e-8, atol=1e-8)
    assert (got.log_prob - other.log_prob).abs().max() > 1e-3  # the scales change the beliefs


def test_scales_are_learned_saved_and_checked(data, tmp_path):
    model = _model(data, phase_width=0.5)
    path = tmp_path / "m.pt"
    model.save(path)
    back = load_model(path)
    assert back.scale_transitions and back.config()["scale_transitions"]
    torch.testing.assert_close(back.transition_scales, SCALES)
    torch.testing.assert_close(back.loss(), model.loss())
    # the MAP fit moves them off their start (ones)
    torch.manual_seed(0)
    fresh = IDDM(data.sequences, data.labels, 2, intention="continuous", measurement="linear",
                 alpha=ALPHA, scale_transitions=True)  # fmt: skip
    torch.testing.assert_close(fresh.transition_scales, torch.ones(2, dtype=torch.float64))
    fresh.fit(5, warn=False)
    assert (fresh.transition_scales - 1).abs().max() > 1e-3
    plain = GPDM(data.sequences, 2)
    assert "raw_transition_scales" not in dict(plain.named_parameters())
    torch.testing.assert_close(plain.transition_scales, torch.ones(2, dtype=torch.float64))
    assert plain.transition_posterior_scale() is None
    with pytest.raises(ValueError, match="scale_transitions=True"):
        plain.transition_scales = 2.0
    # a prior of the user's own is the one in the loss
    tight = GPDM(data.sequences, 2, scale_transitions=True,
                 priors={"transition_scales": NormalPrior(0.0, 0.5)})  # fmt: skip
    tight.transition_scales = torch.tensor([2.0, 0.5], dtype=torch.float64)
    want = -NormalPrior(0.0, 0.5).log_prob(tight.transition_scales.log()).sum()
    default = GPDM(data.sequences, 2, scale_transitions=True)
    default.transition_scales = torch.tensor([2.0, 0.5], dtype=torch.float64)
    got = tight.prior_nll() - default.prior_nll()
    torch.testing.assert_close(got, want + NormalPrior(0.0, 1.0).log_prob(
        default.transition_scales.log()).sum())  # fmt: skip
    with pytest.raises(TypeError, match="scale_transitions must be a bool"):
        GPDM(data.sequences, 2, scale_transitions="yes")
    with pytest.raises(ValueError, match="transition_scales must be finite"):
        model.transition_scales = torch.tensor([1.0, -1.0])


def test_phase_moments_match_gauss_hermite_quadrature(data):
    """Moments of ``x_{t+1}`` at ``x ~ N(mu, Sigma)`` (known g and phase) for the phase-aware
    IDDM with transition scales: the closed-form kernel expectations against tensor Gauss-Hermite
    quadrature of the GP's predictive mean and variance (60 x 60 nodes; the integrands are smooth
    with length scale 1.8, about 8 sd of the input: the rule converges far below 1e-6)."""
    model = _model(data, phase_width=0.7)
    post = model.transition_posterior()
    mu = model.latent.detach()[5]
    A = torch.tensor([[0.08, 0.02], [0.02, 0.05]], dtype=torch.float64)
    g, phase = 0.4, 2.0
    mean, cov, cross = GenericTransition(post, torch.tensor([[g]], dtype=torch.float64),
                                         phase=True).moments(
        mu[None], A[None], torch.tensor([phase], dtype=torch.float64))  # fmt: skip
    nodes, weights = np.polynomial.hermite_e.hermegauss(60)  # for N(0, 1)
    w = torch.as_tensor(np.outer(weights, weights).ravel() / (2 * np.pi))
    u = torch.as_tensor(np.stack(np.meshgrid(nodes, nodes, indexing="ij"), -1).reshape(-1, 2))
    x = mu + u @ torch.linalg.cholesky(A).T
    known = x.new_tensor([g, phase]).expand(len(x), 2)
    m, v = post.predict(torch.cat([x, known], -1), include_noise=True)
    q_mean = w @ m
    q_cov = (w[:, None] * m).T @ m - torch.outer(q_mean, q_mean) + torch.diag(w @ v)
    q_cross = (w[:, None] * (x - mu)).T @ (m - q_mean)
    # rtol 1e-6 of each quantity's scale: the quadrature's error and the closed form's rounding
    # (N = 40 training points, sums of O(1) terms) are both far below it
    for got, want in ((mean[0, 0], q_mean), (cov[0, 0], q_cov), (cross[0, 0], q_cross)):
        torch.testing.assert_close(got, want, rtol=1e-6, atol=1e-6 * float(want.abs().max()))


def test_online_first_prediction_equals_gp_adf(data, gp_rounding):
    """The online filter's belief after two observations of a phase-aware IDDM with transition
    scales is the softmax of GP-ADF's log-likelihoods (``filter_sequence``) with g and the
    first frame's phase (0) known: z_1's evidence is the same for every g."""
    model = _model(data, phase_width=0.5)
    trans, meas = model.transition_posterior(), model.measurement_posterior()
    f = OnlineIntentionFilter(model, GRID, forgetting=0.0, batch_size=3)
    z = torch.stack([s[:2] for s in data.sequences[:3]])
    f.update(z[:, 0])
    belief = f.update(z[:, 1])
    known = torch.stack([GRID.double(), torch.zeros(len(GRID), dtype=torch.float64)], -1)
    ll = filter_sequence(trans, meas, z, f.mu0, f.Sigma0, g=known[:, None, :]).log_likelihood
    # two filter steps by other code: the log-likelihoods agree to 2 gp_rounding of their
    # scale, as in test_value_noise.py
    rel = 2 * gp_rounding(trans, meas) * max(1.0, float(ll.abs().max()))
    torch.testing.assert_close(belief.prob, torch.softmax(ll.T, -1), rtol=rel, atol=rel)
