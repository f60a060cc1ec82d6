"""Window baselines: features, GPR against scikit-learn, classifiers on separable styles."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from sklearn.gaussian_process import GaussianProcessRegressor
from sklearn.gaussian_process.kernels import RBF, ConstantKernel, WhiteKernel

from hgpdm_torch.baselines import (
    HMMClassifier,
    MedianPredictor,
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
