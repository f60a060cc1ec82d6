"""Back-constrained latent states X = f(Z): loss against the dense reference, gradients, starts."""

from __future__ import annotations

import pytest
import torch

from hgpdm_torch.models import GPDM, HGPDM, IDDM, ModelFileError, load_model
from hgpdm_torch.models.back_constraints import KernelBackConstraint, MLPBackConstraint

from .test_loss import _data, _perturb, dense_negative_log_posterior

CASES = [
    ("gpdm-kernel", lambda s, bc: GPDM(s, 2, back_constraint=bc)),
    ("hgpdm-discrete", lambda s, bc: HGPDM(s, [0, 1, 0, 2], 2, num_values=3, back_constraint=bc)),
    (
        "iddm-continuous",
        lambda s, bc: IDDM(
            s, [0.3, -0.8, 0.5, 0.0], 2, intention="continuous", measurement="linear",
            back_constraint=bc,
        ),
    ),
]  # fmt: skip


@pytest.mark.parametrize("bc", ["kernel", "mlp"])
@pytest.mark.parametrize("name,build", CASES, ids=[c[0] for c in CASES])
def test_loss_matches_dense_reference_at_the_mapped_latents(name, build, bc):
    model = build(_data(), bc)
    assert "latent" not in dict(model.named_parameters())
    _perturb(model)  # moves the map's parameters (and hyperparameters)
    x = model.latent.detach()
    assert x.shape == (sum(len(s) for s in _data()), 2)
    # The latent states are the map of the standardised observations ...
    z = model.observations
    std = (z - z.mean(0)) / z.std(0)
    torch.testing.assert_close(model.latent_map(std).detach(), x, rtol=0, atol=0)
    # ... and the objective is Eq. 6 evaluated there.
    got = float(model.loss().detach())
    assert got == pytest.approx(dense_negative_log_posterior(model), rel=1e-10)


@pytest.mark.parametrize("bc", ["kernel", "mlp"])
def test_gradcheck_through_the_map(bc):
    model = HGPDM(_data(lengths=(4, 5, 3, 4), dz=3), [0, 1, 0, 1], 2, back_constraint=bc)
    model.transition_noise = 0.05
    model.measurement_noise = 0.1
    _perturb(model)
    names = [n for n, p in model.named_parameters() if p.requires_grad]
    assert any(n.startswith("latent_map.") for n in names)
    values = tuple(
        p.detach().clone().requires_grad_(True) for p in model.parameters() if p.requires_grad
    )

    def loss_of(*vals):
        return torch.func.functional_call(model, dict(zip(names, vals, strict=True)), ())

    assert torch.autograd.gradcheck(loss_of, values, eps=1e-6, atol=1e-5, rtol=1e-4)


def test_maps_start_near_the_free_model_and_fit():
    data = _data(lengths=(12, 10, 14, 11), dz=5)
    free = GPDM(data, 2)
    for bc, tol in (("kernel", 0.01), ("mlp", 0.2)):
        model = GPDM(data, 2, back_constraint=bc)
        dev = (model.latent - free.latent).abs().max() / free.latent.abs().max()
        assert float(dev) < tol, (bc, float(dev))
        result = model.fit(15, warn=False)
        assert result.final_loss < result.history[0]


def test_save_load_round_trip_and_custom_module(tmp_path):
    data = _data()
    model = HGPDM(data, [0, 1, 0, 1], 2, back_constraint="kernel")
    _perturb(model)
    model.save(tmp_path / "m.pt")
    again = load_model(tmp_path / "m.pt")
    assert float(again.loss()) == pytest.approx(float(model.loss()), rel=1e-12)
    custom = MLPBackConstraint(4, 2, hidden=5, seed=3)
    model = GPDM(data, 2, back_constraint=custom)
    assert model.latent_map is custom
    model.save(tmp_path / "c.pt")  # the map's parameters are in the state; the module is not
    with pytest.raises(ModelFileError, match=r"back_constraint \(a MLPBackConstraint\)"):
        load_model(tmp_path / "c.pt")
    user_built = GPDM(data, 2, back_constraint=MLPBackConstraint(4, 2, hidden=5, seed=4))
    again = load_model(tmp_path / "c.pt", model=user_built)
    assert torch.equal(again.latent, model.latent) and torch.equal(again.loss(), model.loss())


def test_bad_back_constraints_raise():
    data = _data()
    with pytest.raises(ValueError, match="back_constraint"):
        GPDM(data, 2, back_constraint="rbf")
    with pytest.raises(TypeError, match="back_constraint"):
        GPDM(data, 2, back_constraint=torch.nn.Linear(4, 2))
    with pytest.raises(ValueError, match="lengthscale"):
        KernelBackConstraint(torch.randn(5, 3), 2, lengthscale=-1.0)
    with pytest.raises(ValueError, match="hidden"):
        MLPBackConstraint(3, 2, hidden=0)
