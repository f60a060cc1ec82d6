"""The MAP objective apart from the model (issue 53, item 5): :class:`MAPObjective` computes
``model.loss()`` (the same computation, bit for bit), a hand-written torch loop over it lowers
it, and :func:`fit` runs the toolkit's loop for a (model, objective, optimizer)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from hgpdm_torch.fitting import FitResult
from hgpdm_torch.models import GPDM, HGPDM, IDDM
from hgpdm_torch.models.objective import MAPObjective, fit


def _data(seed: int = 0, lengths=(5, 7, 6, 8), dz: int = 4):
    rng = np.random.default_rng(seed)
    return [torch.as_tensor(rng.normal(size=(n, dz)).cumsum(0) * 0.3) for n in lengths]


BUILDERS = {
    "gpdm": lambda s: GPDM(s, 2),
    "gpdm-learned-noise-bc": lambda s: GPDM(s, 2, learn_noise=True, back_constraint="kernel"),
    "gpdm-scaled": lambda s: GPDM(s, 2, scale_transitions=True, learn_alpha=True),
    "hgpdm": lambda s: HGPDM(s, [0, 1, 0, 2], 2, num_values=3),
    "hgpdm-noise-per-value": lambda s: HGPDM(s, [0, 1, 0, 1], 2, noise_per_value=True),
    "hgpdm-continuous": lambda s: HGPDM(s, [-0.5, 0.2, 0.9, 0.1], 2, intention="continuous"),
    "iddm": lambda s: IDDM(s, [0, 1, 1, 0], 2, sharing=0.7),
    "iddm-continuous": lambda s: IDDM(
        s, [0.3, -0.8, 0.5, 0.0], 2, intention="continuous", measurement="linear"
    ),
}


@pytest.mark.parametrize("name", list(BUILDERS))
def test_objective_equals_model_loss(name):
    model = BUILDERS[name](_data())
    if model.latent_map is None:
        with torch.no_grad():  # off the PCA values, so every term is exercised
            model.latent.add_(
                0.1 * torch.sin(torch.arange(model.latent.numel())).view_as(model.latent)
            )
    objective = MAPObjective(model)
    assert type(model.objective()) is MAPObjective and model.objective().model is model
    terms = objective.terms()
    assert list(terms) == ["measurement", "transition", "prior"]
    total = objective()
    assert total.item() == model.loss().item()
    assert total.item() == (terms["measurement"] + terms["transition"] + terms["prior"]).item()
    assert terms["measurement"].item() == model.measurement_nll().item()
    assert terms["transition"].item() == model.transition_nll().item()
    assert terms["prior"].item() == model.prior_nll().item()
    # the objective's parameters are the model's, as with gpytorch's marginal log likelihood
    assert {id(p) for p in objective.parameters()} == {id(p) for p in model.parameters()}


def test_hand_written_torch_loop_lowers_the_objective():
    model = HGPDM(_data(), [0, 1, 0, 1], 2)
    objective = model.objective()
    start = float(objective().detach())
    opt = torch.optim.Adam(model.parameters(), lr=0.01)
    for _ in range(20):
        opt.zero_grad()
        loss = objective()
        loss.backward()
        opt.step()
    assert float(objective().detach()) < start


def test_fit_function_equals_model_fit():
    """``fit(model, objective, optimizer)`` is what ``model.fit`` runs: same history, same
    parameters, bit for bit."""
    a, b = GPDM(_data(), 2), GPDM(_data(), 2)
    ra = a.fit(4, warn=False)
    rb = fit(b, MAPObjective(b), "lbfgs", 4, warn=False)
    assert isinstance(rb, FitResult) and rb.history == ra.history
    assert all(torch.equal(p, q) for p, q in zip(a.parameters(), b.parameters(), strict=True))
    assert b.fit_result is rb and not b.training


def test_fit_with_an_optimizer_and_a_custom_objective():
    model = IDDM(_data(), [0, 1, 1, 0], 2)
    opt = torch.optim.Adam(model.parameters(), lr=0.02)
    result = fit(model, model.objective(), opt, steps=5, warn=False)
    assert result.history[-1] < result.history[0]

    class Tempered(MAPObjective):
        """A subclass adding a term: the way to change the objective of a model class."""

        def terms(self):
            return {**super().terms(), "extra": self.model.latent.pow(2).sum()}

    tempered = Tempered(model)
    with torch.no_grad():
        want = model.loss() + model.latent.pow(2).sum()
        assert float(tempered()) == pytest.approx(float(want), rel=1e-12)
    result = fit(model, tempered, "adam", 3, lr=0.01, warn=False)
    assert len(result.history) >= 2

    class TemperedIDDM(IDDM):
        objective_class = Tempered

    sub = TemperedIDDM(_data(), [0, 1, 1, 0], 2)
    with torch.no_grad():
        assert float(sub.loss()) == float(Tempered(sub)()) != float(MAPObjective(sub)())


def test_fit_rejects_bad_arguments():
    model, other = GPDM(_data(), 2), GPDM(_data(), 2)
    with pytest.raises(ValueError, match="another model"):
        fit(model, MAPObjective(other), steps=1)
    with pytest.raises(ValueError, match="unknown fit option"):
        fit(model, steps=1, tolerance=1e-3)
    with pytest.raises(TypeError, match="callable"):
        fit(model, 3.0, steps=1)
