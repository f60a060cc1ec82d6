"""Calibration of intention posteriors: the coverage/ECE measures by hand, the fitted evidence
temperature against sampling and a dense grid, and the tempered batch and online inference
against the untempered algebra."""

from __future__ import annotations

import math

import pytest
import torch

from hgpdm_torch.datasets import styled_movements
from hgpdm_torch.inference import (
    OnlineIntentionFilter,
    calibration,
    fit_temperature,
    grid_index,
    infer_intention,
    temper,
)
from hgpdm_torch.models import IDDM


def test_calibration_against_hand_computed_values():
    truth = torch.tensor([0, 1, 1, 0])
    onehot = torch.nn.functional.one_hot(truth, 2).double()
    assert calibration(onehot, truth) == {
        "coverage": 1.0, "set_size": 1.0, "ece": 0.0, "nll": 0.0,
    }  # fmt: skip
    # Confident and wrong on one window of four: the 90% set misses it once.
    post = onehot.clone()
    post[3] = torch.tensor([0.0, 1.0])
    cal = calibration(post, truth)
    assert cal["coverage"] == 0.75 and cal["ece"] == pytest.approx(0.25)
    assert cal["nll"] == math.inf
    # 0.8 on the top class, right 3 times in 4: the 90% set needs both classes; ECE |0.75-0.8|.
    post = torch.tensor([[0.8, 0.2], [0.2, 0.8], [0.2, 0.8], [0.2, 0.8]])
    cal = calibration(post, truth)
    assert cal["coverage"] == 1.0 and cal["set_size"] == 2.0
    assert cal["ece"] == pytest.approx(0.05)
    assert cal["nll"] == pytest.approx(-(math.log(0.8) * 3 + math.log(0.2)) / 4)


def _sampled(temperature: float, n: int, k: int = 5, seed: int = 0):
    """Posteriors that are calibrated after tempering by ``temperature``: truths drawn from
    ``softmax(logits / temperature)``, the posteriors reported at ``T = 1``."""
    gen = torch.Generator().manual_seed(seed)
    logits = 3.0 * torch.randn(n, k, generator=gen, dtype=torch.float64)
    truth = torch.multinomial(torch.softmax(logits / temperature, -1), 1, generator=gen)[:, 0]
    return torch.log_softmax(logits, -1), truth


@pytest.mark.parametrize("true_t", [0.5, 1.0, 3.0])
def test_fitted_temperature_recovers_the_sampling_temperature(true_t):
    log_prob, truth = _sampled(true_t, 20000)
    t = fit_temperature(log_prob, truth)
    # the MLE of 1/T from 20000 draws: relative error a few percent
    assert t == pytest.approx(true_t, rel=0.06)
    # against a dense grid of the same objective
    grid = torch.logspace(-1, 1, 2001, dtype=torch.float64)
    nll = torch.stack([-temper(log_prob, float(g)).gather(-1, truth[:, None]).mean() for g in grid])
    assert t == pytest.approx(float(grid[nll.argmin()]), rel=3e-3)
    # tempering at the fitted T calibrates the 90% sets: they hold the truth as often as the
    # mass they claim on average (>= 0.9: a set is the smallest reaching 0.9)
    prob = temper(log_prob, t).exp()
    p, _ = prob.sort(-1, descending=True)
    claimed = (p * ((p.cumsum(-1) - p) < 0.9)).sum(-1).mean()
    assert calibration(prob, truth)["coverage"] == pytest.approx(float(claimed), abs=0.01)


def test_temper_algebra_and_prior():
    log_prob = torch.log(torch.tensor([[0.7, 0.2, 0.1], [0.1, 0.1, 0.8]], dtype=torch.float64))
    torch.testing.assert_close(temper(log_prob, 1.0), log_prob)
    flat = temper(log_prob, 1e9)
    torch.testing.assert_close(flat.exp(), torch.full((2, 3), 1 / 3.0, dtype=torch.float64))
    prior = torch.tensor([0.5, 0.3, 0.2], dtype=torch.float64)
    # with a prior, an infinite temperature falls back to the prior, not to uniform
    torch.testing.assert_close(temper(log_prob, 1e9, prior=prior).exp()[0], prior)
    # T = 2: square root of the likelihood ratio, times the prior
    lik = log_prob.exp() / prior
    expected = prior * lik.sqrt()
    expected = expected / expected.sum(-1, keepdim=True)
    torch.testing.assert_close(temper(log_prob, 2.0, prior=prior).exp(), expected)


def test_uninformative_posteriors_hit_the_upper_bound():
    gen = torch.Generator().manual_seed(1)
    log_prob = torch.log_softmax(torch.randn(2000, 3, generator=gen, dtype=torch.float64), -1)
    truth = torch.randint(0, 3, (2000,), generator=gen)
    assert fit_temperature(log_prob, truth, bounds=(0.1, 50.0)) > 10.0


@pytest.mark.parametrize(
    ("kwargs", "error", "match"),
    [
        ({"truth": torch.tensor([0.0, 1.0])}, TypeError, "integer"),
        ({"truth": torch.tensor([0, 3])}, ValueError, "class indices"),
        ({"truth": torch.tensor([0])}, ValueError, "leading shape"),
        ({"log_prob": torch.tensor([[0.0, math.nan], [0.0, 0.0]])}, ValueError, "NaN"),
        ({"log_prob": torch.zeros(2, 1)}, ValueError, "K >= 2"),
        ({"bounds": (2.0, 1.0)}, ValueError, "bounds"),
        ({"prior": [0.5, 0.6]}, ValueError, "prior"),
    ],
)
def test_bad_inputs_are_named(kwargs, error, match):
    args = {"log_prob": torch.zeros(2, 2), "truth": torch.tensor([0, 1])}
    args.update(kwargs)
    with pytest.raises(error, match=match):
        fit_temperature(**args)


@pytest.mark.parametrize("bad", [0.0, -1.0, math.inf, math.nan])
def test_bad_temperatures_are_refused(bad):
    with pytest.raises(ValueError, match="temperature"):
        temper(torch.zeros(1, 2), bad)
    with pytest.raises(TypeError, match="temperature"):
        temper(torch.zeros(1, 2), "2")


@pytest.fixture(scope="module")
def fitted():
    data = styled_movements(3, 6, 12, 5, noise=0.05, seed=2)
    train = [i for i in range(len(data.sequences)) if i % 3 != 2]
    test = [i for i in range(len(data.sequences)) if i % 3 == 2]
    torch.manual_seed(0)
    model = IDDM(
        [data.sequences[i] for i in train], data.labels[train], 2, intention="discrete",
        measurement="linear", alpha=(0.9, 0.3, 0.1, 1e-2),
    )  # fmt: skip
    assert model.num_values == 3
    model.fit(15, warn=False)
    return model, torch.stack([data.sequences[i] for i in test])


@pytest.mark.parametrize("state_prior", ["marginal", "class"])
def test_batch_temperature_divides_the_bound(fitted, state_prior):
    """``infer_intention(temperature=T)`` is the tempered ``T = 1`` posterior (any prior)."""
    model, z = fitted
    prior = torch.tensor([0.2, 0.3, 0.5], dtype=torch.float64)
    base = infer_intention(model, z, window=4, prior=prior, state_prior=state_prior)
    hot = infer_intention(model, z, window=4, prior=prior, state_prior=state_prior, temperature=2.5)
    torch.testing.assert_close(
        hot.log_prob, temper(base.log_prob, 2.5, prior=prior), rtol=1e-10, atol=1e-10
    )
    with pytest.raises(ValueError, match="temperature"):
        infer_intention(model, z, temperature=0)


@pytest.mark.parametrize("state_prior", ["marginal", "class"])
def test_online_temperature_scales_each_steps_evidence(fitted, state_prior):
    """From the same state, one step of the tempered filter adds ``E_t(g) / T`` where the
    untempered one adds ``E_t(g)`` (recovered from its belief; normalisers cancel)."""
    model, z = fitted
    eps, T = 0.2, 3.0
    cold = OnlineIntentionFilter(
        model, forgetting=eps, batch_size=z.shape[0], state_prior=state_prior
    )
    hot = OnlineIntentionFilter(
        model, forgetting=eps, batch_size=z.shape[0], state_prior=state_prior, temperature=T
    )
    prior = cold.log_belief.clone()
    first_cold, first_hot = cold.update(z[:, 0]), hot.update(z[:, 0])
    # first step: the class prior scores log q(z_1 | g) / T; the marginal prior leaves the prior
    torch.testing.assert_close(
        first_hot.log_prob, temper(first_cold.log_prob, T), rtol=1e-10, atol=1e-10
    )
    # second step from the same state (copy the cold filter's state into the hot one)
    for name in ("mean", "cov", "log_belief"):
        getattr(hot, name).copy_(getattr(cold, name))
    before = cold.log_belief.clone()
    after_cold, after_hot = cold.update(z[:, 1]), hot.update(z[:, 1])
    evidence = after_cold.log_prob - (1 - eps) * before
    expected = (1 - eps) * before + evidence / T
    expected = expected - torch.logsumexp(expected, -1, keepdim=True)
    torch.testing.assert_close(after_hot.log_prob, expected, rtol=1e-9, atol=1e-10)
    assert not torch.allclose(after_hot.log_prob, after_cold.log_prob)
    # T = 1 is the thesis's recursion, bit for bit
    same = OnlineIntentionFilter(
        model, forgetting=eps, batch_size=z.shape[0], state_prior=state_prior, temperature=1.0
    )
    ref = OnlineIntentionFilter(
        model, forgetting=eps, batch_size=z.shape[0], state_prior=state_prior
    )
    for t in range(3):
        assert torch.equal(same.update(z[:, t]).log_prob, ref.update(z[:, t]).log_prob)
    assert prior.shape == (z.shape[0], 3)


def test_calibration_refuses_what_is_not_a_probability():
    truth = torch.tensor([1])
    for bad in ([[-0.2, 1.2]], [[0.5, 0.5, 2.0]], [[math.nan, 1.0]]):
        with pytest.raises(ValueError, match="prob"):
            calibration(torch.tensor(bad), truth)
    with pytest.raises(ValueError, match="level"):
        calibration(torch.tensor([[0.5, 0.5]]), truth, level=1.0)


def test_grid_index_is_the_nearest_value():
    grid = torch.linspace(-1.0, 1.0, 5)  # -1, -0.5, 0, 0.5, 1
    y = torch.tensor([-2.0, -0.7, -0.2, 0.1, 0.74, 3.0])
    assert grid_index(y, grid).tolist() == [0, 1, 2, 2, 3, 4]
    with pytest.raises(ValueError, match="targets"):
        grid_index(torch.tensor([0.1, float("nan")]), grid)
    with pytest.raises(ValueError, match="grid"):
        grid_index(y, grid[None])
