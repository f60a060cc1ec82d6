"""Model API: fitting, a user's own optimisation loop, style discovery, bad input, persistence."""

from __future__ import annotations

import warnings

import numpy as np
import pytest
import torch

from hgpdm_torch.datasets import styled_movements, targeted_movements
from hgpdm_torch.experiments.style_discovery import style_purity
from hgpdm_torch.models import GPDM, HGPDM, IDDM, LinearIDDM, load_model


@pytest.fixture(scope="module")
def styles():
    return styled_movements(3, 3, 30, 10, seed=3)


def test_fit_lowers_loss_and_posteriors_reconstruct(styles):
    model = HGPDM(styles.sequences, styles.labels, 3)
    before = float(model.loss().detach())
    result = model.fit(25, warn=False)
    history = result.history
    assert history[0] == pytest.approx(before) and history[-1] < before
    assert len(history) == result.steps + 1 or result.converged
    assert all(np.diff(history) < 0)  # accepted L-BFGS steps always lower the loss
    z_hat, z_var = model.measurement_posterior().predict(model.latent.detach())
    resid = (z_hat - model.observations).pow(2).mean() / model.observations.var(0).mean()
    assert resid < 0.05
    assert (z_var > 0).all()


def test_user_loop_over_parameters_matches_fit_api(styles):
    model = GPDM(styles.sequences[:4], 2)
    opt = torch.optim.Adam(model.parameters(), lr=0.01)
    first = float(model.loss().detach())
    for _ in range(30):
        opt.zero_grad()
        loss = model.loss()
        loss.backward()
        opt.step()
    assert float(model.loss().detach()) < first
    # alpha stays fixed: no gradient reaches it
    assert all(p.grad is None for n, p in model.named_parameters() if n.startswith("transition"))


def test_discover_recovers_planted_styles(styles):
    model = HGPDM.discover(styles.sequences, 3, iterations=4, steps=20, seed=0)
    assert style_purity(styles.labels, model.intention_codes()) >= 0.9
    hist = model.discovery_history
    assert len(hist) >= 1 and np.isfinite(hist).all()


def test_continuous_models_fit_and_rollout():
    data = targeted_movements(8, 20, 8, seed=1)
    for cls in (HGPDM, IDDM):
        model = cls(data.sequences, data.labels, 3, intention="continuous", measurement="linear")
        h = model.fit(10, warn=False).history
        assert h[-1] < h[0]
        path = model.rollout(model.latent_sequences()[0][0], 5, g=data.labels[0])
        assert path.shape == (6, 3) and torch.isfinite(path).all()


def test_shared_dynamics_couple_the_styles(styles):
    """With sharing the transition GP of one style predicts from the others' transitions too."""
    seqs, codes = styles.sequences[:4], [0, 0, 0, 1]
    alpha = (0.9, 1.0, 0.1, 1e-2)  # a local RBF, so that far-off transitions do not explain x
    block = HGPDM(seqs, codes, 2, alpha=alpha)
    shared = HGPDM(seqs, codes, 2, alpha=alpha, sharing=0.5)
    assert len(block.transition_blocks()) == 2 and len(shared.transition_blocks()) == 1
    # states of style 0's first sequence, asked as style 1: the block model's style 1 ignores
    # style 0's transitions, the shared one borrows from them
    x = block.latent.detach()[:3]
    xin = torch.cat([x, torch.ones(3, 1, dtype=x.dtype)], -1)
    var_b = block.transition_posterior().predict(xin)[1]
    var_s = shared.transition_posterior().predict(xin)[1]
    assert bool((var_s < 0.9 * var_b).all())


def test_transitions_do_not_cross_sequence_boundaries():
    seqs = [torch.randn(4, 3), torch.randn(6, 3)]
    model = GPDM(seqs, 2)
    assert model.src_index.tolist() == [0, 1, 2, 4, 5, 6, 7, 8]
    assert model.transition_inputs(model.latent).shape == (8, 2)


def test_save_load_round_trip(tmp_path, styles):
    for model in (
        HGPDM(styles.sequences[:5], [0, 1, 2, 0, 1], 2),
        HGPDM(styles.sequences[:5], [0, 1, 2, 0, 1], 2, sharing=0.6, learn_alpha=True),
        IDDM(
            styles.sequences[:4],
            [0.1, -0.3, 0.7, 0.2],
            2,
            intention="continuous",
            measurement="linear",
            learn_alpha=True,
        ),
    ):
        model.fit(3, warn=False)  # a few steps: the round trip holds at any parameters
        path = tmp_path / "model.pt"
        model.save(path)
        again = load_model(path)
        assert type(again) is type(model)
        assert again.learn_alpha == model.learn_alpha
        assert getattr(again, "sharing", None) == getattr(model, "sharing", None)
        assert float(again.loss().detach()) == float(model.loss().detach())
        x = torch.randn(3, 2)
        for post, post2 in ((model.measurement_posterior(), again.measurement_posterior()),):
            torch.testing.assert_close(post.predict(x), post2.predict(x), rtol=0, atol=0)
        xin = model.transition_posterior().train_inputs[:3]
        torch.testing.assert_close(
            model.transition_posterior().predict(xin),
            again.transition_posterior().predict(xin),
            rtol=0,
            atol=0,
        )


SEQS = [torch.randn(5, 3), torch.randn(6, 3)]


@pytest.mark.parametrize(
    "build,error,match",
    [
        (lambda: GPDM([], 2), ValueError, "at least one sequence"),
        (lambda: GPDM([torch.randn(1, 3)], 2), ValueError, "at least 2 frames"),
        (lambda: GPDM([torch.randn(5, 3), torch.randn(5, 4)], 2), ValueError, "observed dims"),
        (lambda: GPDM([torch.randn(5)], 2), ValueError, "dimensions"),
        (lambda: GPDM([torch.tensor([[0.0, float("nan")]] * 3)], 1), ValueError, "NaN or inf"),
        (lambda: GPDM([torch.tensor([[0.0, float("inf")]] * 3)], 1), ValueError, "NaN or inf"),
        (lambda: GPDM(SEQS, 0), ValueError, "latent_dim"),
        (lambda: GPDM(SEQS, 2, measurement="poly"), ValueError, "unknown measurement"),
        (lambda: GPDM("abc", 2), TypeError, "sequences"),
        (lambda: LinearIDDM().fit([], []), ValueError, "at least one sequence"),
        (lambda: LinearIDDM().fit(np.zeros((2, 5)), [0, 1]), ValueError, r"\[J, T, Dz\]"),
        (
            lambda: LinearIDDM().fit([torch.randn(5, 3), torch.randn(5, 4)], [0, 1]),
            ValueError,
            "observed dims",
        ),
        (lambda: GPDM(SEQS, 2, alpha=(1, 2, 3)), ValueError, "alpha"),
        (lambda: HGPDM(SEQS, [0], 2), ValueError, "one per sequence"),
        (lambda: HGPDM(SEQS, [0, 3], 2, num_values=2), ValueError, r"\[0, 1\]"),
        (lambda: HGPDM(SEQS, [0, -1], 2), ValueError, "lie in"),
        (lambda: HGPDM(SEQS, [0.5, 1.0], 2), ValueError, "ints"),
        (lambda: HGPDM(SEQS, [0, 1], 2, intention="ordinal"), ValueError, "unknown intention"),
        (lambda: HGPDM(SEQS, [0, 1], 2, sharing=1.0), ValueError, "sharing"),
        (lambda: HGPDM(SEQS, [0, 1], 2, sharing="half"), TypeError, "sharing"),
        (
            lambda: HGPDM(SEQS, [0.1, 0.2], 2, intention="continuous", sharing=0.5),
            ValueError,
            "discrete intention only",
        ),
        (lambda: HGPDM(SEQS, [0.1, float("nan")], 2, intention="continuous"), ValueError, "NaN"),
        (lambda: GPDM(SEQS, 2, init=torch.randn(3, 2)), ValueError, "init"),
        (lambda: GPDM(SEQS, 2).fit(5, optimizer="sgd"), ValueError, "unknown optimizer"),
        (lambda: HGPDM.discover(SEQS, 3), ValueError, "num_styles"),
        (lambda: HGPDM(SEQS, ["a", "b"], 2), TypeError, "intentions"),
        (lambda: HGPDM(SEQS, [0, 1], 2).rollout(torch.zeros(2), 3, g=0.5), ValueError, "integer"),
        (
            lambda: HGPDM(SEQS, [0, 1], 2).rollout(torch.zeros(2), 3, g=float("nan")),
            ValueError,
            "g",
        ),
        (lambda: GPDM(SEQS, 2).rollout(torch.zeros(2), -1), ValueError, "steps"),
        (
            lambda: GPDM([torch.ones(4, 2) * torch.tensor([1.0, 2.0])] * 2, 1),
            ValueError,
            "constant",
        ),
        # issue 54: the arguments are named, with what is expected
        (lambda: GPDM(SEQS, 2, alpha=1.0), TypeError, "alpha must be a sequence of 4 positive"),
        (lambda: GPDM(SEQS, 2, alpha=(1, 1, float("inf"), 1)), ValueError, "alpha .*finite"),
        (lambda: GPDM(SEQS, 2, alpha=(1, 1, 0, 1)), ValueError, "alpha .*positive"),
        (
            lambda: HGPDM(SEQS, [0.1, 0.2], 2, intention="continuous", alpha_g=(1.0, -1.0)),
            ValueError,
            "alpha_g must be a sequence of 2 positive",
        ),
        (lambda: HGPDM(SEQS, [0, 1], 2, alpha_g=0.5), TypeError, "alpha_g"),
        (lambda: GPDM(SEQS, 2, dtype=torch.int64), TypeError, "dtype must be torch.float32 or"),
        (lambda: GPDM(SEQS, 2, dtype=torch.float16), TypeError, "dtype must be torch.float32"),
        (lambda: GPDM(SEQS, 2, dtype="float64"), TypeError, r"dtype .*pass torch.float64"),
        (lambda: HGPDM(SEQS, [0, 1], 2, dtype=torch.int64), TypeError, "dtype must be torch"),
        (
            lambda: HGPDM(SEQS, [0, 100_000], 2),
            ValueError,
            r"only 2 of them are used \(\[0, 100000\]\); recode .* num_values=100001",
        ),
        (lambda: GPDM([s * 1e200 for s in SEQS], 2), ValueError, r"sequences hold .*e\+200"),
        (lambda: GPDM([s * 1e-200 for s in SEQS], 2), ValueError, r"sequences hold .*e-200"),
        (lambda: GPDM([s * 1e20 for s in SEQS], 2, dtype=torch.float32), ValueError, "float32"),
    ],
)
def test_bad_input_raises(build, error, match):
    with pytest.raises(error, match=match):
        build()


def test_codes_and_magnitudes_at_the_limits_are_accepted():
    # a few unused codes (a subject without training trials) stay codes of the belief
    assert HGPDM(SEQS, [1, 2], 2).num_values == 3
    # sparse codes are kept when K is given: the caller asked for them
    assert HGPDM(SEQS, [0, 100_000], 2, num_values=100_001).num_values == 100_001
    # data in large or small units within the dtype's range fit as before
    for scale in (1e100, 1e-100):
        assert np.isfinite(float(GPDM([s.double() * scale for s in SEQS], 2).loss().detach()))
    assert GPDM(SEQS, 2, dtype=torch.float32).latent.dtype == torch.float32


def test_every_model_takes_sequences_as_a_list_a_tensor_or_an_array():
    """One checker (``validation.check_sequences``) for all models: a [J, T, Dz] NumPy array is
    the same training data as the list of its rows."""
    seqs = torch.randn(2, 6, 3, dtype=torch.float64)
    from_list = GPDM(list(seqs), 2, init=torch.zeros(12, 2, dtype=torch.float64))
    from_array = GPDM(seqs.numpy(), 2, init=torch.zeros(12, 2, dtype=torch.float64))
    torch.testing.assert_close(from_array.observations, from_list.observations, rtol=0, atol=0)
    linear = LinearIDDM(phase=False, coef_precision=1.0, noise_prior=0.1, noise="diagonal")
    a = linear.fit(seqs.numpy(), [0.0, 1.0]).coef.clone()
    b = linear.fit(list(seqs), [0.0, 1.0]).coef
    torch.testing.assert_close(a, b, rtol=0, atol=0)


def test_continuous_intentions_far_narrower_than_the_g_kernel_warn():
    from hgpdm_torch.datasets import targeted_movements
    from hgpdm_torch.models import IDDM

    data = targeted_movements(6, 8, 5, seed=0)
    g = torch.as_tensor(data.labels, dtype=torch.float64)
    with pytest.warns(UserWarning, match="standard deviation of .* below 0.1 of the transition"):
        IDDM(data.sequences, 0.001 * g, 2, intention="continuous")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        IDDM(data.sequences, g, 2, intention="continuous")  # unit scale: quiet
        IDDM(data.sequences, 0.001 * g, 2, intention="continuous", alpha_g=(1e8, 0.1))
