"""Inference must not depend on torch's default dtype: every tensor the library creates takes
its dtype from the model or the inputs. Run with the default set to float32 against a float64
model, the results must equal (bit for bit) those with the usual float64 default."""

from __future__ import annotations

import pytest
import torch

from hgpdm_torch.datasets import styled_movements
from hgpdm_torch.inference import OnlineIntentionFilter, VariationalInference, infer_intention
from hgpdm_torch.models import IDDM


@pytest.fixture(scope="module")
def models():
    data = styled_movements(3, 4, 12, 5, noise=0.05, seed=2)
    torch.manual_seed(0)
    discrete = IDDM(
        list(data.sequences), data.labels, 2, intention="discrete", measurement="linear",
        alpha=(0.9, 0.3, 0.1, 1e-2),
    )  # fmt: skip
    discrete.fit(5, warn=False)
    continuous = IDDM(
        list(data.sequences), data.labels.double() / 2, 2, intention="continuous",
        measurement="rbf", alpha=(0.9, 0.3, 0.1, 1e-2),
    )  # fmt: skip
    continuous.fit(5, warn=False)
    return discrete, continuous, torch.stack(list(data.sequences[:3]))


def _results(models) -> dict[str, torch.Tensor]:
    discrete, continuous, z = models
    out = {}
    for name, model, options in (
        ("online", continuous, {}),
        ("online bound gaussian", continuous, {"evidence": "bound", "mixing": "gaussian"}),
        ("online class prior", discrete, {"state_prior": "class", "temperature": 2.0}),
    ):
        f = OnlineIntentionFilter(model, batch_size=3, **options)
        out[name] = torch.stack([f.update(z[:, t]).log_prob for t in range(4)])
    out["batch"] = infer_intention(discrete, z, window=3, state_prior="class").log_prob
    out["vb"] = VariationalInference(discrete).infer(z[:, :4]).log_evidence
    return out


def test_results_do_not_depend_on_the_default_dtype(models):
    expected = _results(models)
    before = torch.get_default_dtype()
    torch.set_default_dtype(torch.float32)
    try:
        got = _results(models)
    finally:
        torch.set_default_dtype(before)
    for name, value in expected.items():
        assert got[name].dtype == torch.float64, name
        assert torch.equal(got[name], value), name
