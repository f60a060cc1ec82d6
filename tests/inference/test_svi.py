"""VB through Pyro (inference/variational/svi.py): SVI with the closed-form loss reaches the
closed-form optimum; Pyro's Trace_ELBO estimates the closed-form F; bad options."""

from __future__ import annotations

import math

import pyro
import pytest
import torch

from hgpdm_torch.datasets import styled_movements
from hgpdm_torch.inference.variational import MeanFieldGuide, SVIOptions, VariationalInference
from hgpdm_torch.models import HGPDM

ALPHA = (0.9, 1.0, 0.1, 0.01)


@pytest.fixture(scope="module")
def setup():
    styles = styled_movements(2, 2, 12, 5, seed=4)
    model = HGPDM(styles.sequences, styles.labels, 2, alpha=ALPHA)
    model.fit(5, warn=False)
    z = styles.sequences[3][4:8].clone()
    z[2] = float("nan")
    return VariationalInference(model), z, int(styles.labels[3])


def test_svi_with_the_closed_form_loss_reaches_the_closed_form_optimum(setup):
    """Same window, same Laplace start: L-BFGS on F (the default) and pyro.infer.SVI (Adam) with
    -F as its loss end at the same q and F."""
    vb, z, code = setup
    start = vb.infer(z, values=[code])
    closed = vb.infer(z, values=[code], steps=200)
    pyro.set_rng_seed(0)
    svi = vb.infer(z, values=[code], method="svi", steps=300)
    gap = float(closed.log_evidence - start.log_evidence)
    assert gap > 0.1  # the Laplace start is not the optimum: SVI has work to do
    torch.testing.assert_close(svi.log_evidence, closed.log_evidence, rtol=1e-5, atol=1e-4)
    torch.testing.assert_close(svi.mean, closed.mean, rtol=0, atol=1e-2)
    torch.testing.assert_close(svi.cov, closed.cov, rtol=0, atol=1e-3)
    assert svi.history[-1] < svi.history[0]  # the SVI loss, -F
    assert math.isclose(svi.history[-1], -float(svi.log_evidence), abs_tol=1e-3)


def test_svi_leaves_the_global_param_store_alone(setup):
    vb, z, code = setup
    pyro.clear_param_store()
    pyro.param("unrelated", torch.ones(2, dtype=torch.float64))
    vb.infer(z, values=[code], method="svi", steps=2)
    assert list(pyro.get_param_store().keys()) == ["unrelated"]


def test_trace_elbo_estimates_the_closed_form_free_energy(setup):
    """At a fixed guide, Pyro's Trace_ELBO of the Pyro model (GP means at sampled states, no
    kernel expectations) agrees with F in expectation: |mean - F| < 4 standard errors."""
    vb, z, _ = setup
    res = vb.infer(z)  # a guide [K = 2, T, Dx] near the optimum of F; widen q to test more
    guide = MeanFieldGuide(res.mean, 4.0 * res.cov)
    F = float(vb.guide_free_energy(z, guide).detach().sum())
    elbo = pyro.infer.Trace_ELBO(num_particles=2000, vectorize_particles=True)
    pyro.set_rng_seed(1)
    with pyro.get_param_store().scope():
        batches = torch.tensor(
            [-elbo.loss(vb.pyro_model, guide, z, guide) for _ in range(20)], dtype=torch.float64
        )
    se = float(batches.std() / math.sqrt(len(batches)))
    assert se < 0.05 * abs(F), "Monte-Carlo error too large to judge"
    assert abs(float(batches.mean()) - F) < 4.0 * se + 1e-8, (F, batches.mean(), se)


def test_svi_with_trace_elbo_raises_the_free_energy(setup):
    vb, z, code = setup
    pyro.set_rng_seed(2)
    start = vb.infer(z, values=[code], init="prior", newton_steps=0, steps=1, method="svi")
    options = SVIOptions(loss="trace_elbo", lr=0.02, num_particles=8)
    res = vb.infer(
        z, values=[code], init="prior", newton_steps=0, steps=60, method="svi", svi=options
    )
    assert float(res.log_evidence) > float(start.log_evidence) + 1.0


def test_bad_options(setup):
    vb, z, _ = setup
    with pytest.raises(ValueError, match="method"):
        vb.infer(z, method="mcmc")
    with pytest.raises(ValueError, match="steps > 0"):
        vb.infer(z, method="svi")
    with pytest.raises(ValueError, match="method='svi'"):
        vb.infer(z, svi=SVIOptions())
    with pytest.raises(ValueError, match="loss"):
        SVIOptions(loss="elbo")
    with pytest.raises(ValueError, match="lr"):
        SVIOptions(lr=0.0)
    with pytest.raises(ValueError, match="num_particles"):
        SVIOptions(num_particles=0)
