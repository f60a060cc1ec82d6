"""MAP fitting (hgpdm_torch.fitting): no silent stall, convergence criteria, rollback, restarts."""

from __future__ import annotations

import warnings

import numpy as np
import pytest
import torch

from hgpdm_torch.datasets import styled_movements
from hgpdm_torch.fitting import ConvergenceWarning, FitResult, fit_map
from hgpdm_torch.linalg import CholeskyError
from hgpdm_torch.models import GPDM


class Rosenbrock(torch.nn.Module):
    """``(1 - a)^2 + 100 (b - a^2)^2``: minimum 0 at (1, 1) (the oracle)."""

    def __init__(self, start=(-1.2, 1.0), wall: float | None = None) -> None:
        super().__init__()
        self.x = torch.nn.Parameter(torch.tensor(start, dtype=torch.float64))
        self.wall = wall

    def loss(self) -> torch.Tensor:
        a, b = self.x
        if self.wall is not None and float(a) > self.wall:
            # Like a kernel matrix that is not positive definite: the loss cannot be evaluated.
            raise CholeskyError("outside the domain")
        return (1 - a) ** 2 + 100 * (b - a * a) ** 2


def _old_lbfgs_fit(model: torch.nn.Module, steps: int) -> list[float]:
    """The former ``fit``: LBFGS(max_iter=1) without max_eval, one step per call."""
    params = [p for p in model.parameters() if p.requires_grad]
    opt = torch.optim.LBFGS(
        params, lr=1, max_iter=1, history_size=50, line_search_fn="strong_wolfe"
    )

    def closure():
        opt.zero_grad()
        value = model.loss()
        value.backward()
        return value

    return [float(opt.step(closure).detach()) for _ in range(steps)]


@pytest.fixture(scope="module")
def small_gpdm_data():
    return styled_movements(3, 3, 30, 10, seed=3).sequences


def test_old_lbfgs_stalls_and_fit_does_not(small_gpdm_data):
    """The stall of the issue: with one evaluation per step the line search cannot back off and
    repeats a rejected trial (loss flat, gradient large). ``fit`` keeps descending."""
    old = GPDM(small_gpdm_data, 3, learn_noise=False)
    hist = _old_lbfgs_fit(old, 14)
    assert hist[-1] == hist[-2] == hist[-3]  # flat ...
    old.zero_grad()
    old.loss().backward()
    assert float(old.latent.grad.abs().max()) > 100  # ... far from a stationary point
    new = GPDM(small_gpdm_data, 3, learn_noise=False)
    result = new.fit(14, warn=False)
    h = np.array(result.history)
    assert (np.diff(h) < 0).all()  # every accepted step lowers the loss
    assert result.final_loss < hist[-1] - 1e4  # and it gets far past the stalled value
    assert result.steps == 14 and not result.converged and "step limit" in result.reason


def test_converges_to_the_rosenbrock_minimum():
    model = Rosenbrock()
    result = fit_map(model, 500)
    assert isinstance(result, FitResult) and result.converged, result.reason
    assert torch.allclose(model.x.detach(), torch.ones(2, dtype=torch.float64), atol=1e-5)
    assert result.final_loss == pytest.approx(float(model.loss().detach()), abs=0)
    assert result.evaluations >= result.steps and result.grad_norm < 1e-3
    # A second fit from the converged state hardly moves.
    again = fit_map(model, 50)
    assert abs(again.final_loss - result.final_loss) <= 1e-6 * max(1.0, abs(result.final_loss))


def test_failed_trial_points_are_backed_off():
    """Trial points where the loss cannot be evaluated (CholeskyError) only shrink the step."""
    model = Rosenbrock(start=(0.0, 0.0), wall=1.02)
    result = fit_map(model, 500)
    assert result.converged, result.reason
    assert torch.allclose(model.x.detach(), torch.ones(2, dtype=torch.float64), atol=1e-4)


def test_divergence_rolls_back_to_the_best_state(small_gpdm_data):
    model = GPDM(small_gpdm_data[:3], 2)
    start = float(model.loss())
    with pytest.warns(ConvergenceWarning, match="rolled back"):
        result = model.fit(40, optimizer="adam", lr=50.0)
    assert result.rolled_back and not result.converged
    assert "learning rate" in result.reason
    assert result.final_loss <= start
    assert float(model.loss()) == pytest.approx(result.final_loss, rel=1e-12)


def test_not_converged_warns_and_says_why(small_gpdm_data):
    model = GPDM(small_gpdm_data[:3], 2)
    with pytest.warns(ConvergenceWarning, match="step limit"):
        result = model.fit(2)
    assert not result.converged and result.steps == 2
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        model.fit(1, warn=False)


def test_restarts_keep_the_best():
    model = Rosenbrock(start=(-1.5, 2.0))
    result = fit_map(model, 300, restarts=2, seed=1)
    assert len(result.restarts) == 3
    assert result.final_loss == pytest.approx(min(result.restarts), abs=1e-12)
    assert float(model.loss()) == pytest.approx(result.final_loss, abs=1e-12)


def test_user_optimizer_and_factory():
    model = Rosenbrock()
    opt = torch.optim.SGD(model.parameters(), lr=1e-4)
    result = fit_map(model, 20, optimizer=opt, warn=False)
    assert result.final_loss < result.history[0]
    result = fit_map(Rosenbrock(), 20, optimizer=lambda p: torch.optim.Adam(p, lr=1e-2), warn=False)
    assert result.final_loss < result.history[0]


@pytest.mark.parametrize(
    "kwargs, match",
    [
        ({"steps": -1}, "steps"),
        ({"steps": 2.5}, "steps"),
        ({"ftol": 0.0}, "ftol"),
        ({"gtol": -1.0}, "gtol"),
        ({"patience": 0}, "patience"),
        ({"max_eval": 1}, "max_eval"),
        ({"restarts": -1}, "restarts"),
        ({"lr": float("nan")}, "lr"),
        ({"optimizer": "sgd"}, "optimizer"),
    ],
)
def test_bad_arguments_raise(kwargs, match):
    kwargs = {"steps": 5, **kwargs}
    with pytest.raises(ValueError, match=match):
        fit_map(Rosenbrock(), **kwargs)


def test_model_fit_rejects_unknown_options(small_gpdm_data):
    model = GPDM(small_gpdm_data[:2], 2)
    with pytest.raises(ValueError, match="unknown fit option"):
        model.fit(3, tolerance=1e-3)


def test_unevaluable_start_raises_with_advice():
    model = Rosenbrock(start=(2.0, 0.0), wall=1.5)
    with pytest.raises(FloatingPointError, match="starting parameters"):
        fit_map(model, 3)


@pytest.mark.slow
def test_a_converged_gpdm_stays_put_on_a_second_fit():
    """Acceptance of issue 13 on a model: converge by the criteria, then a second fit moves the
    loss by < 1e-6 relative (about 20-60 s; the Rosenbrock test covers it in the fast tier)."""
    model = GPDM(styled_movements(1, 2, 15, 5, seed=3).sequences, 2)
    first = model.fit(2000)
    assert first.converged, first.reason
    again = model.fit(50)
    assert abs(again.final_loss - first.final_loss) <= 1e-6 * abs(first.final_loss)


def test_an_optimizer_over_other_tensors_is_refused(small_gpdm_data):
    """An optimizer that holds none of the model's parameters would leave the model as it is
    and the fit would report a stall ("call fit again"): it is refused up front."""
    stray = torch.zeros(2, requires_grad=True)
    model = Rosenbrock()
    start = model.x.detach().clone()
    for optimizer in (torch.optim.Adam([stray]), lambda params: torch.optim.SGD([stray], lr=0.1)):
        with pytest.raises(ValueError, match=r"none of the model's trainable parameters.*"
                                             r"model\.parameters\(\)"):  # fmt: skip
            fit_map(model, 5, optimizer=optimizer)
    assert torch.equal(model.x.detach(), start) and model.x.grad is None
    gpdm = GPDM(small_gpdm_data[:2], 2)  # a model's fit goes through fit_map
    with pytest.raises(ValueError, match=r"build it over model\.parameters\(\)"):
        gpdm.fit(3, optimizer=torch.optim.Adam([stray]))
    # an optimizer over a part of the model's parameters is the user's choice
    part = [p for p in gpdm.parameters() if p.requires_grad][:1]
    result = gpdm.fit(2, optimizer=torch.optim.Adam(part, lr=1e-3), warn=False)
    assert result.steps == 2
