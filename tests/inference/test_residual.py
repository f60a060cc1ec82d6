"""AR(1) deviation from the model's reconstruction (inference/residual.py)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from hgpdm_torch.datasets import styled_movements
from hgpdm_torch.inference.map import MAPInference
from hgpdm_torch.inference.residual import ar1_residual_forecast
from hgpdm_torch.inference.variational import VariationalInference
from hgpdm_torch.models import HGPDM


def test_recovers_a_known_ar1_coefficient():
    """Long windows of a simulated AR(1) deviation: rho within a few standard errors."""
    gen = torch.Generator().manual_seed(0)
    rho, T, dz, B = 0.7, 200, 10, 8
    e = torch.zeros(B, T, dz)
    for t in range(1, T):
        e[:, t] = rho * e[:, t - 1] + torch.randn(B, dz, generator=gen)
    rec = torch.randn(B, T, dz, generator=gen)
    _, _, est = ar1_residual_forecast(rec + e, rec, torch.zeros(B, dz), torch.zeros(B, dz))
    se = ((1 - rho**2) / (T * dz)) ** 0.5
    assert torch.all((est - rho).abs() < 4 * se), est


def test_formula_against_numpy_with_a_missing_row():
    rng = np.random.default_rng(1)
    z, rec = rng.normal(size=(6, 4)), rng.normal(size=(6, 4))
    z[2] = np.nan  # pairs (1,2) and (2,3) are not used
    mean, var = rng.normal(size=4), rng.uniform(size=4)
    got_m, got_v, got_rho = ar1_residual_forecast(
        *(torch.as_tensor(a) for a in (z, rec, mean, var)), steps=2
    )
    e = z - rec
    pairs = [
        (t, t - 1) for t in range(1, 6) if not np.isnan(z[t]).any() and not np.isnan(z[t - 1]).any()
    ]
    cur, prev = np.stack([e[t] for t, _ in pairs]), np.stack([e[s] for _, s in pairs])
    rho = np.clip((cur * prev).sum() / (prev**2).sum(), 0, 1)
    s2 = ((cur - rho * prev) ** 2).mean(0)
    assert float(got_rho) == pytest.approx(rho, rel=1e-12)
    np.testing.assert_allclose(got_m.numpy(), mean + rho**2 * e[-1], rtol=1e-12)
    np.testing.assert_allclose(got_v.numpy(), var + (1 + rho**2) * s2, rtol=1e-12)


def test_bad_inputs():
    z = torch.zeros(5, 3)
    with pytest.raises(ValueError, match="same shape"):
        ar1_residual_forecast(z, torch.zeros(4, 3), torch.zeros(3), torch.zeros(3))
    with pytest.raises(ValueError, match="steps"):
        ar1_residual_forecast(z, z, torch.zeros(3), torch.zeros(3), steps=0)
    holed = z.clone()
    holed[-1] = float("nan")
    with pytest.raises(ValueError, match="last row"):
        ar1_residual_forecast(holed, z, torch.zeros(3), torch.zeros(3))


@pytest.fixture(scope="module")
def fitted():
    train, test = styled_movements(2, 3, 30, 8, seed=4).split(0.34, seed=0)
    model = HGPDM(train.sequences, train.labels, 3)
    model.fit(40, warn=False)
    return test, model


@pytest.mark.parametrize("engine", [VariationalInference, MAPInference])
def test_a_persistent_offset_is_carried_into_the_forecast(fitted, engine):
    """Test windows shifted off the training manifold by a persistent offset (0.1 sd per
    channel, random signs): the AR(1) residual forecast removes most of the error the offset
    adds, the white-noise forecast cannot. (Offsets of several tenths of an sd are partly
    absorbed by q(x) instead; the module docstring says so.)"""
    test, model = fitted
    z = torch.stack([s[i : i + 6] for s in test.sequences for i in (0, 8, 16)])
    signs = torch.randn(z.shape[-1], generator=torch.Generator().manual_seed(0)).sign()
    offset = 0.1 * model.observations.std(0) * signs
    window, nxt = z[:, :5] + offset, z[:, 5] + offset
    inf = engine(model)
    plain, _, _ = inf.forecast(window)
    carried, var, res = inf.forecast(window, residual="ar1")
    clean, _, _ = inf.forecast(z[:, :5])
    err_plain = float((plain - nxt).pow(2).mean().sqrt())
    err_carried = float((carried - nxt).pow(2).mean().sqrt())
    err_clean = float((clean - z[:, 5]).pow(2).mean().sqrt())  # without the offset
    # more than half of the error the offset adds is removed
    assert err_carried - err_clean < 0.5 * (err_plain - err_clean), (
        err_carried, err_plain, err_clean,
    )  # fmt: skip
    assert torch.all(var > 0)
    with pytest.raises(ValueError, match="residual"):
        inf.forecast(window, residual="ar2")
