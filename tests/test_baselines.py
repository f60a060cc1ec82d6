"""Window baselines: features, GPR against scikit-learn, classifiers on separable styles;
next-frame forecasters against a simulated VAR(2) and the ridge normal equations."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from sklearn.gaussian_process import GaussianProcessRegressor
from sklearn.gaussian_process.kernels import RBF, ConstantKernel, WhiteKernel

from hgpdm_torch.baselines import (
    GRUForecaster,
    HMMClassifier,
    LastFrameForecaster,
    MedianPredictor,
    RidgeAR,
    WindowGPC,
    WindowGPR,
    WindowRidge,
    WindowSVM,
    window_features,
)
from hgpdm_torch.datasets import styled_movements


def test_window_features_stack_past_frames():
    z = torch.arange(12.0).reshape(1, 4, 3)
    f = window_features(z, 2)
    assert f.shape == (1, 4, 6)
    torch.testing.assert_close(f[0, 0], torch.tensor([0.0, 1, 2, 0, 1, 2]))  # padded
    torch.testing.assert_close(f[0, 3], torch.tensor([6.0, 7, 8, 9, 10, 11]))
    with pytest.raises(ValueError, match="window"):
        window_features(z, 0)


def velocity_sequences(num: int, gen: torch.Generator):
    """The target is the speed of a drifting point: one frame cannot tell it, two can."""
    targets = torch.rand(num, generator=gen) * 2 - 1
    start = 3 * torch.randn(num, 1, 2, generator=gen)
    steps = torch.arange(6.0)[None, :, None]
    z = start + targets[:, None, None] * steps * torch.tensor([1.0, 0.5])
    z = z + 0.01 * torch.randn(z.shape, generator=gen)
    return list(z), targets


def test_gpr_chooses_the_informative_window_and_matches_sklearn(generator):
    seqs, y = velocity_sequences(40, generator)
    gpr = WindowGPR(windows=(1, 2), steps=120).fit(seqs, y)
    assert gpr.window == 2
    assert gpr.validation_mae[2] < 0.75 * gpr.validation_mae[1]
    test, y_test = velocity_sequences(10, generator)
    mean, std = gpr.predict(torch.stack(test))
    assert mean.shape == std.shape == (10, 6)
    median_mae = float((y_test - y.median()).abs().mean())
    assert float((mean[:, 1:] - y_test[:, None]).abs().mean()) < 0.5 * median_mae
    # the same GP with the learned hyperparameters in scikit-learn (no re-optimisation)
    k = gpr.model.covar_module
    ls = k.base_kernel.lengthscale.detach().numpy().ravel()
    c = float(gpr.model.mean_module.constant.detach())
    kernel = ConstantKernel(float(k.outputscale.detach()), "fixed") * RBF(
        ls, "fixed"
    ) + WhiteKernel(float(gpr.likelihood.noise.detach()), "fixed")
    x_train = gpr.scaler.transform(torch.cat([window_features(s, 2) for s in seqs]).numpy())
    y_train = np.repeat(y.numpy(), 6) - c
    ref = GaussianProcessRegressor(kernel, optimizer=None).fit(x_train, y_train)
    x_test = gpr.scaler.transform(window_features(torch.stack(test), 2).reshape(-1, 4).numpy())
    np.testing.assert_allclose(mean.reshape(-1).numpy(), ref.predict(x_test) + c, atol=1e-5)


def test_ridge_chooses_the_informative_window_and_solves_the_normal_equations(generator):
    seqs, y = velocity_sequences(40, generator)
    ridge = WindowRidge(windows=(1, 2)).fit(seqs, y)
    assert ridge.window == 2
    assert ridge.validation_mae[2] < 0.5 * ridge.validation_mae[1]
    test, y_test = velocity_sequences(10, generator)
    pred = ridge.predict(torch.stack(test))
    assert pred.shape == (10, 6)
    # frames after the first show the speed exactly (up to the noise): a linear read-out
    assert float((pred[:, 1:] - y_test[:, None]).abs().mean()) < 0.05
    # the same ridge solution from the normal equations on the standardised windows
    x = ridge.scaler.transform(torch.cat([window_features(s, 2) for s in seqs]).numpy())
    t = np.repeat(y.numpy(), 6)
    xc, tc = x - x.mean(0), t - t.mean()
    alpha = ridge.model.alpha_
    coef = np.linalg.solve(xc.T @ xc + alpha * np.eye(x.shape[1]), xc.T @ tc)
    np.testing.assert_allclose(ridge.model.coef_, coef, rtol=1e-6, atol=1e-9)
    with pytest.raises(ValueError, match="alphas"):
        WindowRidge(alphas=(0.0,))
    with pytest.raises(ValueError, match="one target per sequence"):
        WindowRidge().fit(seqs, y[:-1])


def test_median_predictor():
    pred = MedianPredictor().fit(None, torch.tensor([3.0, -1.0, 2.0, 10.0, 0.0]))
    torch.testing.assert_close(pred.predict(torch.zeros(2, 4, 3)), torch.full((2, 4), 2.0))


@pytest.fixture(scope="module")
def styles():
    return styled_movements(3, 6, 20, 6, noise=0.02, seed=2).split(0.34, seed=0)


@pytest.mark.parametrize(
    "make",
    [
        lambda: WindowSVM(window=5),
        lambda: WindowGPC(window=5, steps=60),
        lambda: pytest.importorskip("hmmlearn") and HMMClassifier(states=3, window=8),
    ],
    ids=["svm", "gpc", "hmm"],
)
def test_classifiers_recognise_styles(styles, make):
    train, test = styles
    clf = make().fit(train.sequences, train.labels)
    pred = clf.predict(torch.stack(test.sequences))
    assert pred.shape == (len(test), 20)
    acc = float((pred[:, 8:] == test.labels[:, None]).double().mean())
    assert acc > 0.8
    if hasattr(clf, "predict_proba"):
        p = clf.predict_proba(torch.stack(test.sequences))
        torch.testing.assert_close(p.sum(-1), torch.ones(len(test), 20))
        assert bool((p.argmax(-1) == pred).all())


def test_bad_inputs_raise(styles):
    train, _ = styles
    with pytest.raises(ValueError, match="windows"):
        WindowGPR(windows=())
    with pytest.raises(ValueError, match="labels"):
        WindowSVM().fit(train.sequences, torch.zeros(len(train)))
    with pytest.raises(ValueError, match="one per sequence"):
        WindowSVM().fit(train.sequences, train.labels[:-1])
    clf = WindowSVM(window=2).fit(train.sequences, train.labels)
    with pytest.raises(ValueError, match="Dz"):
        clf.predict(torch.zeros(1, 5, 3))
    with pytest.raises(ValueError, match="sequences"):
        WindowSVM().fit([], [])


@pytest.mark.parametrize(
    "build,match",
    [
        (lambda: HMMClassifier(0), r"states .* int >= 1, got 0"),
        (lambda: HMMClassifier(-2), r"states .* int >= 1, got -2"),
        (lambda: HMMClassifier(2.5), r"states"),
        (lambda: HMMClassifier(2, window=0), r"window must be an int >= 1"),
        (lambda: HMMClassifier(2, iterations=0), r"iterations"),
        (lambda: WindowSVM(window=0), r"window"),
        (lambda: WindowGPC(samples=0), r"samples"),
        (lambda: WindowGPR(windows=2), r"windows must be a non-empty sequence"),
        (lambda: WindowRidge(windows=(1, True)), r"windows"),
    ],
)
def test_bad_settings_are_refused_when_built(build, match):
    """Issue 54: HMMClassifier(0) and (-2) failed only in fit, with ZeroDivisionError and a
    NumPy error; WindowGPR(windows=2) with "object of type 'int' has no len()"."""
    with pytest.raises(ValueError, match=match):
        build()


@pytest.mark.parametrize(
    "make,call",
    [
        (WindowGPR, "fit(sequences, targets)"),
        (WindowRidge, "fit(sequences, targets)"),
        (MedianPredictor, "fit(sequences, targets)"),
        (WindowSVM, "fit(sequences, labels)"),
        (WindowGPC, "fit(sequences, labels)"),
        (lambda: pytest.importorskip("hmmlearn") and HMMClassifier(), "fit(sequences, labels)"),
    ],
)
def test_predict_before_fit_says_so(make, call):
    """Issue 54: a window baseline used before fit raised AttributeError."""
    model = make()
    with pytest.raises(RuntimeError, match=rf"{type(model).__name__} is not fitted yet") as err:
        model.predict(torch.zeros(5, 2))
    assert f"call {call}" in str(err.value)
    for name in ("predict_proba", "log_likelihood"):
        if hasattr(model, name):
            with pytest.raises(RuntimeError, match="not fitted yet"):
                getattr(model, name)(torch.zeros(5, 2))


def test_hmm_classifier_names_a_class_without_sequences():
    pytest.importorskip("hmmlearn")
    seqs = [torch.randn(12, 2, generator=torch.Generator().manual_seed(j)) for j in range(4)]
    with pytest.raises(ValueError, match="class 1 has no training sequence"):
        HMMClassifier(2, iterations=2).fit(seqs, [0, 0, 2, 2])


# ------------------------------------------------------------------------------------------
# Next-frame forecasters
# ------------------------------------------------------------------------------------------

A1 = np.array([[0.6, 0.2, 0.0], [-0.1, 0.5, 0.1], [0.0, 0.3, 0.4]])
A2 = np.array([[-0.3, 0.0, 0.1], [0.0, -0.2, 0.0], [0.1, 0.0, -0.25]])
C = np.array([0.1, -0.2, 0.05])
NOISE = 0.1


def var2(num: int, length: int, rng: np.random.Generator) -> np.ndarray:
    """``[num, length, 3]`` draws of z_t = A1 z_{t-1} + A2 z_{t-2} + c + noise (after burn-in)."""
    z = np.zeros((num, length + 50, 3))
    for t in range(2, length + 50):
        z[:, t] = z[:, t - 1] @ A1.T + z[:, t - 2] @ A2.T + C
        z[:, t] += NOISE * rng.standard_normal((num, 3))
    return z[:, 50:]


def ridge_normal_equations(x: np.ndarray, y: np.ndarray, alpha: float):
    """Ridge with an unpenalised intercept: centre, then solve (Xc'Xc + alpha I) W = Xc'Yc."""
    xm, ym = x.mean(0), y.mean(0)
    w = np.linalg.solve((x - xm).T @ (x - xm) + alpha * np.eye(x.shape[1]), (x - xm).T @ (y - ym))
    return w, ym - xm @ w


def lag_rows(seqs, order: int, start: int):
    """Rows [z_{t-order}, ..., z_{t-1}] -> z_t for t >= start, written out with a loop."""
    xs, ys = [], []
    for s in seqs:
        for t in range(start, len(s)):
            xs.append(np.concatenate([s[t - order + i] for i in range(order)]))
            ys.append(s[t])
    return np.array(xs), np.array(ys)


def test_last_frame_forecaster():
    windows = torch.randn(4, 6, 3)
    f = LastFrameForecaster().fit([torch.randn(10, 3), torch.randn(7, 3)])
    torch.testing.assert_close(f.predict(windows), windows[:, -1])
    assert f.predict(windows[:, :1]).shape == (4, 3)
    with pytest.raises(ValueError, match="windows"):
        f.predict(torch.zeros(4, 6, 2))
    with pytest.raises(ValueError, match="windows"):
        f.predict(torch.zeros(4, 0, 3))


def test_ridge_ar_recovers_a_var2_process():
    rng = np.random.default_rng(0)
    train = var2(20, 250, rng)
    ar = RidgeAR().fit(list(torch.as_tensor(train)))
    assert ar.order_ == 2 and ar.cv_mse_.shape == (5, 13)
    # coefficient blocks: oldest frame first
    np.testing.assert_allclose(ar.coef_[:, 3:].numpy(), A1, atol=0.03)
    np.testing.assert_allclose(ar.coef_[:, :3].numpy(), A2, atol=0.03)
    test = var2(200, 6, rng)
    windows, target = torch.as_tensor(test[:, :5]), test[:, 5]
    pred = ar.predict(windows).numpy()
    mean = test[:, 4] @ A1.T + test[:, 3] @ A2.T + C  # the true conditional mean
    assert np.sqrt(np.mean((pred - mean) ** 2)) < 0.1 * NOISE
    mse = np.mean((pred - target) ** 2)
    assert 0.8 * NOISE**2 < mse < 1.2 * NOISE**2
    assert mse < 0.8 * np.mean((LastFrameForecaster().predict(windows).numpy() - target) ** 2)
    # any leading batch dims
    assert ar.predict(windows.reshape(4, 50, 5, 3)).shape == (4, 50, 3)


def test_ridge_ar_solves_the_normal_equations():
    rng = np.random.default_rng(1)
    seqs = [np.cumsum(rng.standard_normal((n, 2)), 0) for n in (12, 9, 15)]
    ar = RidgeAR().fit([torch.as_tensor(s) for s in seqs], orders=(2,), alphas=(0.7,))
    assert ar.order_ == 2 and ar.alpha_ == 0.7 and ar.cv_mse_ is None
    w, b = ridge_normal_equations(*lag_rows(seqs, 2, 2), 0.7)
    np.testing.assert_allclose(ar.coef_.numpy(), w.T, rtol=1e-8, atol=1e-10)
    windows = rng.standard_normal((4, 5, 2))
    expected = np.concatenate([windows[:, -2], windows[:, -1]], 1) @ w + b
    np.testing.assert_allclose(ar.predict(torch.as_tensor(windows)).numpy(), expected, rtol=1e-8)
    with pytest.raises(ValueError, match="windows"):
        ar.predict(torch.as_tensor(windows[:, :1]))


def test_ridge_ar_cross_validation_is_leave_one_sequence_out():
    """With folds >= sequences the validation errors are those of leaving each sequence out,
    every candidate scored on the targets t >= max(orders)."""
    rng = np.random.default_rng(2)
    seqs = [np.cumsum(rng.standard_normal((n, 2)), 0) * 0.3 for n in (15, 11, 14, 18)]
    orders, alphas = (1, 3), (0.1, 10.0)
    ar = RidgeAR().fit(
        [torch.as_tensor(s) for s in seqs], orders, alphas, folds=10, one_standard_error=False
    )
    expected = np.zeros((2, 2))
    for i, k in enumerate(orders):
        for j, alpha in enumerate(alphas):
            for held in range(len(seqs)):
                rest = [s for h, s in enumerate(seqs) if h != held]
                w, b = ridge_normal_equations(*lag_rows(rest, k, 3), alpha)
                x, y = lag_rows([seqs[held]], k, 3)
                expected[i, j] += np.mean((x @ w + b - y) ** 2) / len(seqs)
    np.testing.assert_allclose(ar.cv_mse_, expected, rtol=1e-8)
    assert ar.cv_se_ is None
    i, j = np.unravel_index(np.argmin(expected), expected.shape)
    assert (ar.order_, ar.alpha_) == (orders[i], alphas[j])


def test_ridge_ar_bad_inputs():
    seqs = [torch.randn(20, 2), torch.randn(15, 2)]
    for orders in [(), (0,), (1.5,), (True,)]:
        with pytest.raises(ValueError, match="orders"):
            RidgeAR().fit(seqs, orders=orders)
    for alphas in [(), (0.0,), (-1.0,), (np.nan,)]:
        with pytest.raises(ValueError, match="alphas"):
            RidgeAR().fit(seqs, alphas=alphas)
    with pytest.raises(ValueError, match="folds"):
        RidgeAR().fit(seqs, folds=1)
    with pytest.raises(ValueError, match="sequences"):
        RidgeAR().fit(seqs[:1])  # nothing to cross-validate over
    with pytest.raises(ValueError, match="sequences"):
        RidgeAR().fit([torch.randn(3, 2)], orders=(3,), alphas=(1.0,))
    with pytest.raises(ValueError, match="sequences"):
        RidgeAR().fit([torch.randn(20, 2), torch.randn(20, 3)])
    ar = RidgeAR().fit(seqs, orders=(2,), alphas=(1.0,))
    with pytest.raises(ValueError, match="Dz = 2"):
        ar.predict(torch.zeros(3, 4, 3))
    with pytest.raises(ValueError, match="windows"):
        ar.predict(torch.zeros(4))


def test_gru_learns_a_var2_process_and_chooses_its_size_by_grouped_cv():
    """On a VAR(2) the GRU, trained on windows of 5, forecasts near the noise floor (MSE within
    1.35 x the noise variance, below 0.8 x the persistence forecast's, as ridge AR); its choice
    comes from grouped CV curves, and refitting is deterministic for a seed."""
    rng = np.random.default_rng(1)
    train = list(torch.as_tensor(var2(8, 120, rng)))
    gru = GRUForecaster(hidden_sizes=(4, 16), max_epochs=150, folds=4).fit(train, 5)
    assert gru.cv_mse_.shape == (2, 150) and gru.hidden_ in (4, 16)
    assert 1 <= gru.epochs_ <= 150
    i = (4, 16).index(gru.hidden_)
    assert gru.cv_mse_[i, gru.epochs_ - 1] == gru.cv_mse_.min()
    test = var2(200, 6, rng)
    windows, target = torch.as_tensor(test[:, :5]), test[:, 5]
    pred = gru.predict(windows).numpy()
    assert pred.dtype == np.float64 and gru.predict(windows.reshape(4, 50, 5, 3)).shape == (
        4,
        50,
        3,
    )
    mse = np.mean((pred - target) ** 2)
    last = np.mean((LastFrameForecaster().predict(windows).numpy() - target) ** 2)
    assert mse < 1.35 * NOISE**2 and mse < 0.8 * last
    again = GRUForecaster(hidden_sizes=(4, 16), max_epochs=150, folds=4).fit(train, 5)
    np.testing.assert_array_equal(again.predict(windows).numpy(), pred)


def test_gru_bad_inputs():
    seqs = [torch.randn(12, 2), torch.randn(12, 2)]
    for kwargs, match in (
        ({"hidden_sizes": ()}, "hidden_sizes"),
        ({"hidden_sizes": (0,)}, "hidden_sizes"),
        ({"max_epochs": 0}, "max_epochs"),
        ({"folds": 1}, "folds"),
        ({"lr": 0.0}, "lr"),
    ):
        with pytest.raises(ValueError, match=match):
            GRUForecaster(**kwargs)
    with pytest.raises(ValueError, match="window"):
        GRUForecaster().fit(seqs, 0)
    with pytest.raises(ValueError, match="longer than the window"):
        GRUForecaster().fit(seqs, 12)
    with pytest.raises(ValueError, match="at least 2 sequences"):
        GRUForecaster().fit([torch.randn(12, 2), torch.randn(3, 2)], 5)
    gru = GRUForecaster(hidden_sizes=(2,), max_epochs=2).fit(seqs, 3)
    with pytest.raises(ValueError, match="Dz = 2"):
        gru.predict(torch.zeros(4, 3, 5))
    with pytest.raises(ValueError, match="order_ = 3"):
        gru.predict(torch.zeros(4, 2, 2))
