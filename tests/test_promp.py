"""The ProMP baseline: its conditioning against a dense Gaussian oracle, its weight fit against
mp_pytorch's own, and what it recovers from prefixes (target, speed, class)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from scipy.stats import multivariate_normal

from hgpdm_torch.baselines import ProMP


def _movements(n: int, frames, seed: int = 0, noise: float = 0.02):
    """``n`` two-channel movements whose shape is set by a target ``g`` each, lasting
    ``frames`` (an int or a list), and the targets."""
    gen = torch.Generator().manual_seed(seed)
    g = torch.rand(n, generator=gen, dtype=torch.float64) * 2 - 1
    lengths = [frames] * n if isinstance(frames, int) else frames
    seqs = []
    for i, T in enumerate(lengths):
        s = torch.linspace(0, 1, T, dtype=torch.float64)
        y = torch.stack([g[i] * torch.sin(math.pi * s), s + 0.3 * g[i] * s**2], 1)
        seqs.append(y + noise * torch.randn(T, 2, generator=gen, dtype=torch.float64))
    return seqs, g


def _dense_oracle(model: ProMP, prefix: torch.Tensor, duration: float):
    """log p(Y | T_c) and p(e | Y, T_c) from the dense joint Gaussian of [Y, e]."""
    t, d = prefix.shape
    nb, n_w = model.num_basis, model.dim * model.num_basis
    phi = model.basis(t, torch.tensor([duration], dtype=torch.float64))[0].numpy()
    H = np.kron(np.eye(d), phi)  # rows (channel, frame), columns (channel, basis)
    A = np.zeros((t * d + model.num_extras, n_w + model.num_extras))
    A[: t * d, :n_w] = H
    A[t * d :, n_w:] = np.eye(model.num_extras)
    m, S = model.mean.numpy(), model.cov.numpy()
    R = np.diag(np.repeat(model.noise.numpy(), t))
    joint_mean = A @ m
    joint_cov = A @ S @ A.T
    joint_cov[: t * d, : t * d] += R
    y = prefix.T.reshape(-1).numpy()  # (channel, frame) order
    Syy, Sye = joint_cov[: t * d, : t * d], joint_cov[: t * d, t * d :]
    log_ev = multivariate_normal(joint_mean[: t * d], Syy).logpdf(y)
    gain = np.linalg.solve(Syy, Sye).T
    mean_e = joint_mean[t * d :] + gain @ (y - joint_mean[: t * d])
    cov_e = joint_cov[t * d :, t * d :] - gain @ Sye
    assert nb == model.num_basis
    return log_ev, mean_e, cov_e


def test_conditioning_matches_the_dense_gaussian():
    seqs, g = _movements(30, [9, 10, 11, 12] * 7 + [10, 10])
    model = ProMP(num_basis=5, speeds=(0.8, 1.0, 1.25), durations=3).fit(seqs, g)
    prefix = torch.stack([s[:6] for s in seqs[:4]])
    post = model.condition(prefix)
    for b in range(4):
        oracle = [_dense_oracle(model, prefix[b], float(T)) for T in model.durations]
        log_c = np.array([o[0] for o in oracle]) - math.log(len(oracle))
        total = np.logaddexp.reduce(log_c)
        w = np.exp(log_c - total)
        mean = sum(wc * o[1] for wc, o in zip(w, oracle, strict=True))
        second = sum(wc * (o[2] + np.outer(o[1], o[1])) for wc, o in zip(w, oracle, strict=True))
        # float64 with condition numbers ~1e6 (the basis Gram, the shrunk covariance): errors
        # ~1e-10 relative; the log evidence is O(10), the target O(1)
        assert post.log_evidence[b].item() == pytest.approx(total, rel=1e-8, abs=1e-7)
        np.testing.assert_allclose(post.duration_weights[b].numpy(), w, atol=1e-8)
        np.testing.assert_allclose(post.mean[b].numpy(), mean, rtol=1e-8, atol=1e-9)
        np.testing.assert_allclose(
            post.cov[b].numpy(), second - np.outer(mean, mean), rtol=1e-7, atol=1e-10
        )


def test_weights_match_mp_pytorch_learning():
    from mp_pytorch.basis_gn import NormalizedRBFBasisGenerator
    from mp_pytorch.mp import ProMP as LibraryProMP
    from mp_pytorch.phase_gn import LinearPhaseGenerator

    seqs, g = _movements(4, 12)
    model = ProMP(num_basis=6, reg=0.0).fit(seqs, g)
    kw = {"dtype": torch.float64}
    basis = NormalizedRBFBasisGenerator(LinearPhaseGenerator(**kw), num_basis=6, **kw)
    lib = LibraryProMP(basis, num_dof=2, **kw)
    times = torch.linspace(0, 1, 12, dtype=torch.float64).expand(4, -1)
    params = lib.learn_mp_params_from_trajs(times, torch.stack(seqs), reg=1e-12)["params"]
    ours = torch.stack([model._weights(s)[0] for s in seqs])
    # both solve the same 6 x 6 normal equations (reg 1e-12 against a Gram of O(1))
    torch.testing.assert_close(ours, params, rtol=1e-8, atol=1e-9)


def test_prefix_predicts_the_target_and_the_speed():
    seqs, g = _movements(60, 20, seed=1)
    model = ProMP(num_basis=8, speeds=(0.5, 1.0, 2.0)).fit(seqs, g)
    test, g_test = _movements(20, 20, seed=2)
    post = model.condition(torch.stack([s[:10] for s in test]))
    mae = (post.mean[:, 0] - g_test).abs().mean()
    assert mae < 0.1 * (g_test - g.median()).abs().mean()
    z = (post.mean[:, 0] - g_test) / post.cov[:, 0, 0].sqrt()
    assert z.abs().max() < 5  # calibrated, not overconfident
    # movements twice as fast (10 frames for the same path): the half-duration candidate wins
    fast, _ = _movements(5, 10, seed=3)
    post_fast = model.condition(torch.stack([s[:6] for s in fast]))
    assert model.durations[post_fast.duration_weights.argmax(1)].eq(10).all()
    assert model.durations[post.duration_weights.argmax(1)].eq(20).all()


def test_empty_prefix_is_the_prior():
    seqs, g = _movements(10, 8)
    model = ProMP(num_basis=4).fit(seqs, g)
    post = model.condition(torch.zeros(3, 0, 2, dtype=torch.float64))
    torch.testing.assert_close(post.mean, model.mean[-1:].expand(3, 1))
    assert post.log_evidence.eq(0).all()


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"num_basis": 0}, "num_basis"),
        ({"speeds": ()}, "speeds"),
        ({"speeds": (1.0, -1.0)}, "speeds"),
        ({"bandwidth": float("nan")}, "bandwidth"),
        ({"reg": -1.0}, "reg"),
    ],
)
def test_bad_options(kwargs, match):
    with pytest.raises(ValueError, match=match):
        ProMP(**kwargs)


def test_bad_inputs():
    seqs, g = _movements(5, 8)
    with pytest.raises(RuntimeError, match="fit"):
        ProMP().condition(torch.zeros(1, 2, 2))
    with pytest.raises(ValueError, match="at least 2 movements"):
        ProMP().fit(seqs[:1])
    with pytest.raises(ValueError, match="extras"):
        ProMP().fit(seqs, g[:3])
    model = ProMP(num_basis=4).fit(seqs, g)
    with pytest.raises(ValueError, match="prefix"):
        model.condition(torch.zeros(1, 2, 3))
    with pytest.raises(ValueError, match="prefix"):
        model.condition(torch.full((1, 2, 2), float("nan")))


def _classes(per_class: int, seed: int, frames=(18, 22)):
    """Three one-channel gestures (a rise, a dip, a wave) at random durations and amplitudes."""
    gen = torch.Generator().manual_seed(seed)
    seqs, labels = [], []
    for c in range(3):
        for _ in range(per_class):
            T = int(torch.randint(frames[0], frames[1] + 1, (1,), generator=gen))
            s = torch.linspace(0, 1, T, dtype=torch.float64)
            a = 1 + 0.2 * torch.randn(1, generator=gen, dtype=torch.float64)
            path = (s, -torch.sin(math.pi * s), torch.sin(2 * math.pi * s))[c]
            y = a * path + 0.05 * torch.randn(T, generator=gen, dtype=torch.float64)
            seqs.append(torch.stack([y, s * a], 1))
            labels.append(c)
    return seqs, torch.tensor(labels)


def test_classifier_recognises_gestures_from_prefixes():
    from hgpdm_torch.baselines import ProMPClassifier

    seqs, y = _classes(8, seed=0)
    clf = ProMPClassifier(grid={"num_basis": (3, 6)}, folds=3).fit(seqs, y)
    assert len(clf.scores) == 2 and clf.options["num_basis"] in (3, 6)
    test, y_test = _classes(5, seed=1, frames=(20, 20))
    z = torch.stack(test)
    log_p = clf.predict_log_proba(z)
    torch.testing.assert_close(log_p.exp().sum(-1), torch.ones(z.shape[:2], dtype=torch.float64))
    pred = clf.predict(z)
    assert pred[:, -1].eq(y_test).all()  # the whole gesture: no doubt
    assert pred[:, 10].eq(y_test).double().mean() > 0.8  # half of it
    # the posterior is each class's prefix likelihood under the training frequencies
    direct = torch.stack([m.log_likelihood(z[:, :7]) for m in clf.models], -1)
    torch.testing.assert_close(log_p[:, 6], direct.log_softmax(-1))
    torch.testing.assert_close(clf.window_log_proba(z), log_p[:, -1])
    # scored on whole movements, the CV counts the end decisions alone: the early frames,
    # where the gestures look alike, no longer count against any option
    grid = {"num_basis": (1, 6)}
    whole = ProMPClassifier(grid=grid, folds=3, online=False).fit(seqs, y)
    every = ProMPClassifier(grid=grid, folds=3).fit(seqs, y)
    assert all(w < e for w, e in zip(whole.scores, every.scores, strict=True))


def test_classifier_cv_survives_a_class_too_small_for_a_fold():
    from hgpdm_torch.baselines import ProMPClassifier

    seqs, y = _classes(4, seed=2)
    seqs, y = seqs[:10], y[:10]  # class 2 keeps 2 movements: one fold trains on 1 of them
    clf = ProMPClassifier(grid={"num_basis": (3, 4)}, folds=2).fit(seqs, y)
    assert len(clf.models) == 3 and all(m is not None for m in clf.models)
    with pytest.raises(ValueError, match="fewer than 2"):
        ProMPClassifier().fit(seqs[:9], y[:9])
    with pytest.raises(ValueError, match="labels"):
        ProMPClassifier().fit(seqs, y.double())
    with pytest.raises(RuntimeError, match="fit"):
        ProMPClassifier().predict(torch.zeros(1, 3, 2))


def test_regressor_chooses_by_cross_validation():
    from hgpdm_torch.baselines import ProMPRegressor

    seqs, g = _movements(20, 12, seed=4)
    reg = ProMPRegressor(grid={"num_basis": (1, 6)}, folds=4).fit(seqs, g)
    # one basis function (a constant) misses the shape of the movement: the CV error says so
    assert reg.options == {"num_basis": 6} and reg.scores[0] > reg.scores[1]
    mean, std = reg.predict(torch.stack(seqs[:3]))
    assert mean.shape == std.shape == (3, 12) and bool((std > 0).all())
    with pytest.raises(ValueError, match="grid"):
        ProMPRegressor(grid={"windows": (1,)})
    with pytest.raises(RuntimeError, match="fit"):
        ProMPRegressor().predict(torch.zeros(1, 3, 2))


def test_next_frame_draws_match_the_dense_predictive():
    seqs, g = _movements(25, 10, seed=5)
    model = ProMP(num_basis=5).fit(seqs, g)
    assert len(model.durations) == 1
    prefix = seqs[0][:4]
    # the dense joint of the prefix and frame 4 (rows (channel, frame)), conditioned
    d, nb, T = 2, 5, float(model.durations[0])
    phi = model.basis(5, torch.tensor([T], dtype=torch.float64))[0].numpy()
    H = np.kron(np.eye(d), phi)  # [(d, 5 frames), d nb]
    m, S = model.mean[: d * nb].numpy(), model.cov[: d * nb, : d * nb].numpy()
    cov = H @ S @ H.T + np.diag(np.repeat(model.noise.numpy(), 5))
    mean = H @ m
    seen = [k * 5 + j for k in range(d) for j in range(4)]
    nxt = [k * 5 + 4 for k in range(d)]
    gain = np.linalg.solve(cov[np.ix_(seen, seen)], cov[np.ix_(seen, nxt)]).T
    y = prefix.T.reshape(-1).numpy()
    want_mean = mean[nxt] + gain @ (y - mean[seen])
    want_cov = cov[np.ix_(nxt, nxt)] - gain @ cov[np.ix_(seen, nxt)]
    n = 40_000
    draws = model.sample_next(prefix[None], n, torch.Generator().manual_seed(0))[0].numpy()
    sd = np.sqrt(np.diag(want_cov))
    # Monte Carlo: the sample mean errs ~sd / sqrt(n), the sample covariance ~sd^2 sqrt(2 / n)
    np.testing.assert_array_less(np.abs(draws.mean(0) - want_mean), 5 * sd / np.sqrt(n))
    np.testing.assert_array_less(
        np.abs(np.cov(draws.T) - want_cov), 5 * np.outer(sd, sd) * np.sqrt(2 / n)
    )
    with pytest.raises(ValueError, match="at least one frame"):
        model.sample_next(prefix[None, :0], 3)
