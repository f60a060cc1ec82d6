"""MAP baseline (conditional GPDM): log joint vs a dense reference, optimisation, bad input."""

from __future__ import annotations

import math

import pytest
import torch
from scipy.optimize import minimize

from hgpdm_torch.datasets import styled_movements, targeted_movements
from hgpdm_torch.inference.map import MAPInference
from hgpdm_torch.models import GPDM, HGPDM


@pytest.fixture(scope="module")
def data():
    return styled_movements(2, 2, 12, 5, seed=4)


@pytest.fixture(scope="module")
def hgpdm(data):
    model = HGPDM(data.sequences, data.labels, 2, alpha=(0.9, 1.0, 0.1, 0.01))
    model.fit(5, warn=False)  # a short fit: the oracle comparison holds at any parameters
    return model


def _reference_log_joint(model, z, x, code):
    """Term by term with GPPosterior.predict (gpytorch kernels) and torch.distributions."""
    h, f = model.measurement_posterior(), model.transition_posterior()
    lat = model.latent.detach()
    m1, S1 = lat.mean(0), torch.cov(lat.T) + 1e-6 * torch.eye(2)
    total = torch.distributions.MultivariateNormal(m1, S1).log_prob(x[0])
    inp = x[:-1] if code is None else torch.cat([x[:-1], torch.full((len(x) - 1, 1), code)], -1)
    mx, vx = f.predict(inp, include_noise=True)
    total = total + torch.distributions.Normal(mx, vx.sqrt()).log_prob(x[1:]).sum()
    mz, vz = h.predict(x, include_noise=True)
    obs = ~torch.isnan(z).all(-1)
    lz = torch.distributions.Normal(mz, vz.sqrt()).log_prob(torch.nan_to_num(z)).sum(-1)
    return total + lz[obs].sum()


def test_log_joint_matches_reference(hgpdm, data, generator):
    inf = MAPInference(hgpdm)
    z = data.sequences[1][2:6].clone()
    z[1] = float("nan")
    x = torch.randn(2, 4, 2, generator=generator)
    lj = inf.log_joint(z, x)
    for k in range(2):
        torch.testing.assert_close(lj[k], _reference_log_joint(hgpdm, z, x[k], float(k)))
    gpdm = GPDM(data.sequences, 2, alpha=(0.9, 1.0, 0.1, 0.01))
    inf = MAPInference(gpdm)
    lj = inf.log_joint(z, x[:1])
    torch.testing.assert_close(lj[0], _reference_log_joint(gpdm, z, x[0], None))
    # a process noise per latent dim: the reference's predict scales the variances itself
    scaled = GPDM(data.sequences, 2, alpha=(0.9, 1.0, 0.1, 0.01), scale_transitions=True)
    scaled.transition_scales = torch.tensor([0.4, 3.0])
    lj = MAPInference(scaled).log_joint(z, x[:1])
    torch.testing.assert_close(lj[0], _reference_log_joint(scaled, z, x[0], None))
    assert not torch.allclose(lj[0], MAPInference(gpdm).log_joint(z, x[:1])[0])


def test_infer_maximises_and_forecasts(hgpdm, data):
    inf = MAPInference(hgpdm)
    z = torch.stack([s[3:7] for s in data.sequences])
    mean, var, res = inf.forecast(z, steps=30)
    assert mean.shape == (4, 5) and (var > 0).all()
    assert res.latent.shape == (4, 2, 5, 2) and res.history[-1] <= res.history[0]
    window = torch.cat([z, torch.full((4, 1, 5), math.nan)], 1)
    start = inf.initial_guess(window, inf.values, "nearest")[0]
    assert torch.all(res.log_joint >= inf.log_joint(window, start) - 1e-9)
    torch.testing.assert_close(res.posterior.sum(-1), torch.ones(4))


def test_levenberg_marquardt_reaches_a_stationary_point_like_scipy(hgpdm, data):
    """The batched Levenberg-Marquardt MAP states are stationary (scipy's L-BFGS-B gains
    < 0.01 nats from them) and at least as good as L-BFGS-B run from the same start."""
    inf = MAPInference(hgpdm)
    z = data.sequences[2][4:9]
    res = inf.infer(z, steps=100)
    start = inf.initial_guess(z, inf.values, "nearest")[0]
    for k in range(2):

        def fun(v, k=k):
            x = torch.tensor(v, requires_grad=True)
            nlj = -inf.log_joint(z, x.reshape(1, 5, 2), values=[k])[0]
            (g,) = torch.autograd.grad(nlj, x)
            return float(nlj.detach()), g.numpy()

        ref = minimize(fun, start[k].flatten().numpy(), jac=True, method="L-BFGS-B",
                       options={"maxiter": 5000, "gtol": 1e-10, "ftol": 1e-15})  # fmt: skip
        assert float(res.log_joint[k]) >= -ref.fun - 1e-4 * max(1.0, abs(ref.fun))
        # stationary up to the stopping tolerance (1e-3 nats per step): scipy gains ~nothing
        polish = minimize(fun, res.latent[k].flatten().numpy(), jac=True, method="L-BFGS-B",
                          options={"maxiter": 5000, "gtol": 1e-10, "ftol": 1e-15})  # fmt: skip
        assert float(res.log_joint[k]) >= -polish.fun - 1e-2


def test_bad_input(hgpdm, data):
    inf = MAPInference(hgpdm)
    with pytest.raises(ValueError, match="at least 2 time steps"):
        inf.infer(data.sequences[0][:1])
    with pytest.raises(ValueError, match="every row is missing"):
        inf.infer(torch.full((3, 5), math.nan))
    seqs = targeted_movements(3, 6, 4, seed=0)
    model = HGPDM(seqs.sequences, seqs.labels, 2, intention="continuous")
    with pytest.raises(ValueError, match="continuous"):
        MAPInference(model)
