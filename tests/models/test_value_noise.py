"""Per-value process noise of a discrete-g IDDM (``noise_per_value``), each part against an
independent oracle: dense numpy GP formulas, numpy marginal likelihoods optimised on a grid,
the shared-noise model, and GP-ADF through ``GPPosterior.predict_gaussian`` per code."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from scipy.optimize import minimize_scalar

from hgpdm_torch.datasets import styled_movements
from hgpdm_torch.gp import GPPosterior
from hgpdm_torch.inference.filtering import filter_sequence
from hgpdm_torch.inference.intention import OnlineIntentionFilter, SharedTransition
from hgpdm_torch.kernels import transition_kernel
from hgpdm_torch.models import HGPDM, IDDM, load_model
from hgpdm_torch.models.gpdm import NOISE_FLOOR

A1, A2 = 0.9, 0.3  # alpha_1, alpha_2 of the transition RBF below


def np_kernel(xa: np.ndarray, xb: np.ndarray) -> np.ndarray:
    """``delta(g, g') a1 exp(-a2/2 |x - x'|^2)`` on ``[x, code]`` rows, in numpy."""
    d2 = ((xa[:, None, :-1] - xb[None, :, :-1]) ** 2).sum(-1)
    same = xa[:, None, -1] == xb[None, :, -1]
    return same * A1 * np.exp(-0.5 * A2 * d2)


def np_block_nll(k: np.ndarray, y: np.ndarray, noise: float) -> float:
    """``-log N(y; 0, k + noise I)`` summed over the columns of ``y``, in numpy."""
    c = k + noise * np.eye(len(k))
    sign, logdet = np.linalg.slogdet(c)
    assert sign > 0
    n, d = y.shape
    return (
        0.5 * d * logdet
        + 0.5 * float(np.sum(y * np.linalg.solve(c, y)))
        + 0.5 * n * d * (math.log(2 * math.pi))
    )


@pytest.fixture(scope="module")
def styles():
    return styled_movements(3, 4, 14, 6, noise=0.02, seed=2)


def make(styles, **kwargs) -> IDDM:
    torch.manual_seed(0)
    return IDDM(
        styles.sequences, styles.labels, 3, intention="discrete", measurement="linear",
        alpha=(A1, A2, 0.1, 1e-2), **kwargs,
    )  # fmt: skip


@pytest.fixture(scope="module")
def fitted(styles) -> IDDM:
    model = make(styles, noise_per_value=True)
    model.fit(15, warn=False)
    return model


@pytest.fixture(scope="module")
def scaled(styles) -> IDDM:
    """Per-value noises and an output scale per latent dim (``scale_transitions``)."""
    model = make(styles, noise_per_value=True, scale_transitions=True)
    model.fit(15, warn=False)
    with torch.no_grad():
        model.transition_scales = torch.tensor([0.6, 1.0, 2.5])
    model.estimate_value_noise()
    return model


# ----- GPPosterior with a noise per training point and per code ---------------------------------


def test_posterior_with_per_point_noise_equals_dense_formula(generator):
    n, dx, k = 14, 2, 3
    x = torch.randn(n, dx, generator=generator)
    codes = (torch.arange(n) % k).double()
    X = torch.cat([x, codes[:, None]], 1)
    Y = torch.sin(x) + 0.1 * codes[:, None]
    noise = 0.01 + 0.2 * torch.rand(n, generator=generator)
    code_noise = torch.tensor([0.03, 0.5, 0.002])
    kernel = transition_kernel("iddm_discrete", dx, num_values=k, alpha=(A1, A2, 0.1, 1e-2))
    post = GPPosterior(kernel, X, Y, noise, code_noise=code_noise)
    xs = torch.cat([torch.randn(7, dx, generator=generator), (torch.arange(7) % k)[:, None]], 1)
    Xn, Yn, xsn = X.numpy(), Y.numpy(), xs.double().numpy()
    np.testing.assert_allclose(kernel(X).to_dense().detach().numpy(), np_kernel(Xn, Xn), 1e-12)
    C = np_kernel(Xn, Xn) + np.diag(noise.numpy())
    ks = np_kernel(xsn, Xn)
    mean = ks @ np.linalg.solve(C, Yn)
    var = A1 - np.einsum("ij,ji->i", ks, np.linalg.solve(C, ks.T))
    m, v = post.predict(xs)
    np.testing.assert_allclose(m.numpy(), mean, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(v.numpy(), var[:, None].repeat(dx, 1), rtol=1e-9, atol=1e-12)
    _, vn = post.predict(xs, include_noise=True)
    with_noise = var + code_noise.numpy()[xsn[:, -1].astype(int)]
    np.testing.assert_allclose(vn.numpy(), with_noise[:, None].repeat(dx, 1), rtol=1e-9)
    # moment matching at a point input (Sigma = 0), the code given as g: the same numbers
    gm, gc, _ = post.predict_gaussian(
        xs[:, :dx], torch.zeros(7, dx, dx), g=xs[:, dx:], include_noise=True
    )
    np.testing.assert_allclose(gm.numpy(), mean, rtol=1e-8, atol=1e-10)
    np.testing.assert_allclose(
        gc.diagonal(dim1=-2, dim2=-1).numpy(), with_noise[:, None].repeat(dx, 1), rtol=1e-7
    )
    # an [N] noise of equal entries is the scalar noise
    same = GPPosterior(kernel, X, Y, torch.full((n,), 0.07))
    scalar = GPPosterior(kernel, X, Y, 0.07)
    torch.testing.assert_close(same.chol, scalar.chol, rtol=1e-14, atol=1e-14)
    torch.testing.assert_close(same.predict(xs)[1], scalar.predict(xs)[1])


def test_posterior_noise_arguments_are_validated(generator):
    dx, k = 2, 3
    X = torch.cat([torch.randn(6, dx, generator=generator), (torch.arange(6) % k)[:, None]], 1)
    Y = torch.randn(6, dx, generator=generator)
    kernel = transition_kernel("iddm_discrete", dx, num_values=k, alpha=(A1, A2, 0.1, 1e-2))
    with pytest.raises(ValueError, match="noise"):
        GPPosterior(kernel, X, Y, torch.ones(5))
    with pytest.raises(ValueError, match="noise"):
        GPPosterior(kernel, X, Y, torch.tensor([0.1, 0.1, 0.1, 0.1, 0.1, 0.0]))
    with pytest.raises(ValueError, match="code_noise"):
        GPPosterior(kernel, X, Y, 0.1, code_noise=torch.ones(2))
    with pytest.raises(ValueError, match="code_noise"):
        GPPosterior(kernel, X, Y, 0.1, code_noise=torch.tensor([0.1, -1.0, 0.1]))
    rbf = transition_kernel("iddm_continuous", dx, g_dim=1, alpha=(A1, A2, 0.1, 1e-2))
    with pytest.raises(ValueError, match="code_noise"):
        GPPosterior(rbf, X, Y, 0.1, code_noise=torch.ones(3))
    post = GPPosterior(kernel, X, Y, 0.1 + torch.rand(6, generator=generator))
    with pytest.raises(ValueError, match="include_noise"):
        post.predict(X, include_noise=True)
    post = GPPosterior(kernel, X, Y, 0.1, code_noise=torch.ones(3))
    with pytest.raises(ValueError, match="code"):
        post.predict_gaussian(X, torch.zeros(6, dx + 1, dx + 1), include_noise=True)
    with pytest.raises(ValueError, match="codes"):
        post.predict(X + 0.5, include_noise=True)


# ----- the model: equal noises are the shared model; the estimate; the loss -------------------


def test_equal_value_noises_give_the_shared_model(styles):
    shared, per = make(styles), make(styles, noise_per_value=True)
    torch.testing.assert_close(per.value_noise, shared.transition_noise.expand(3))
    assert per.transition_nll().item() == shared.transition_nll().item()
    assert per.loss().item() == shared.loss().item()
    gs = torch.autograd.grad(shared.loss(), shared.latent)[0]
    gp = torch.autograd.grad(per.loss(), per.latent)[0]
    torch.testing.assert_close(gp, gs, rtol=1e-12, atol=1e-12)
    ps, pp = shared.transition_posterior(), per.transition_posterior()
    xs = torch.cat([torch.randn(8, 3), (torch.arange(8) % 3)[:, None].double()], 1)
    for a, b in zip(
        ps.predict(xs, include_noise=True), pp.predict(xs, include_noise=True), strict=True
    ):
        torch.testing.assert_close(a, b, rtol=1e-12, atol=1e-14)
    z = torch.stack(shared.sequences()[:4])[:, :5]
    beliefs = []
    for model in (shared, per):
        f = OnlineIntentionFilter(model, forgetting=0.1, batch_size=4)
        beliefs.append(torch.stack([f.update(z[:, t]).prob for t in range(5)], 1))
    torch.testing.assert_close(beliefs[1], beliefs[0], rtol=1e-10, atol=1e-12)


@pytest.mark.parametrize("name", ["fitted", "scaled"])
def test_estimate_maximises_each_blocks_marginal_likelihood(name, request):
    model = request.getfixturevalue(name)
    assert model.config()["noise_per_value"] is True
    x = model.latent.detach().numpy()
    src = model.src_index.numpy()
    codes = model.intentions[model.seq_of_src, 0].numpy()
    inputs = np.concatenate([x[src], codes[:, None]], 1)
    v = model.transition_scales.detach().numpy()  # ones unless scale_transitions
    targets = x[src + 1] * v  # Eq. 5's columns, scaled by v_d
    expected = []
    centre, sd = math.log(float(model.transition_noise)), model.NOISE_PRIOR_SD

    def neg_log_post(a: float, K: np.ndarray, y: np.ndarray) -> float:
        # block marginal likelihood times the log-normal prior centred on the shared alpha_4
        return np_block_nll(K, y, math.exp(a)) + 0.5 * ((a - centre) / sd) ** 2

    for k in range(3):
        rows = codes == k
        K, y = np_kernel(inputs[rows], inputs[rows]), targets[rows]
        grid = np.linspace(math.log(NOISE_FLOOR), math.log(10.0), 600)
        best = grid[np.argmin([neg_log_post(a, K, y) for a in grid])]
        step = grid[1] - grid[0]
        res = minimize_scalar(
            lambda a, K=K, y=y: neg_log_post(a, K, y),
            bounds=(max(best - step, grid[0]), best + step), method="bounded",
            options={"xatol": 1e-9},
        )  # fmt: skip
        expected.append(res.x)
    np.testing.assert_allclose(model.value_noise.log().numpy(), expected, atol=1e-3)
    assert float(model.value_noise.max() / model.value_noise.min()) > 1.5  # not all equal
    # re-estimating is idempotent (latents and kernel fixed)
    before = model.value_noise.clone()
    torch.testing.assert_close(model.estimate_value_noise(), before, rtol=1e-4, atol=0)
    model.value_noise.copy_(before)
    # the transition term of the loss uses each block's own noise
    first = x[model.first_index.numpy()]
    nll = (
        sum(
            np_block_nll(
                np_kernel(inputs[codes == k], inputs[codes == k]),
                targets[codes == k],
                float(model.value_noise[k]),
            )
            for k in range(3)
        )
        + 0.5 * float((first**2).sum())
        + 0.5 * first.size * math.log(2 * math.pi)
        - len(src) * float(np.log(v).sum())  # the Jacobian of the scaling
    )
    assert float(model.transition_nll().detach()) == pytest.approx(nll, rel=1e-10)
    # the posterior: each pair's own alpha_4 on the diagonal, each code's for new outputs
    post = model.transition_posterior()
    torch.testing.assert_close(post.scale, 1.0 / model.transition_scales.detach())
    torch.testing.assert_close(post.noise, model.value_noise[torch.as_tensor(codes).long()])
    torch.testing.assert_close(post.code_noise, model.value_noise)


def test_fit_starts_from_the_shared_noise_and_few_pairs_keep_it(styles):
    """Repeated fits do not ratchet the noises down; a value with one transition pair (whose
    likelihood alone is flat down to the noise floor) stays near the shared alpha_4."""
    a, b = make(styles, noise_per_value=True), make(styles, noise_per_value=True)
    b.value_noise.fill_(1e-5)  # a stale estimate: fit must not start from it
    a.fit(5, warn=False)
    b.fit(5, warn=False)
    torch.testing.assert_close(a.value_noise, b.value_noise, rtol=0, atol=0)
    # one class with a single 2-frame sequence (one pair)
    seqs = [*styles.sequences[:8], styles.sequences[8][:2]]
    labels = torch.cat([styles.labels[:8], torch.tensor([2])])
    assert set(labels[:8].tolist()) == {0, 1}
    torch.manual_seed(0)
    lone = IDDM(
        seqs, labels, 3, intention="discrete", measurement="linear",
        alpha=(A1, A2, 0.1, 1e-2), noise_per_value=True,
    )  # fmt: skip
    lone.fit(5, warn=False)
    assert 1e-3 < float(lone.value_noise[2]) < 1e-1  # not NOISE_FLOOR (1e-6)
    # relabelling resets the per-value noises to the shared one
    lone.set_intentions(labels.flip(0))
    assert torch.all(lone.value_noise == lone.transition_noise)


def test_value_noise_is_saved_and_loaded(fitted, tmp_path):
    fitted.save(tmp_path / "m.pt")
    loaded = load_model(tmp_path / "m.pt")
    assert loaded.noise_per_value
    torch.testing.assert_close(loaded.value_noise, fitted.value_noise, rtol=0, atol=0)
    assert loaded.loss().item() == fitted.loss().item()


def test_online_first_prediction_per_class_equals_gp_adf(fitted, styles, gp_rounding):
    model = fitted
    trans, meas = model.transition_posterior(), model.measurement_posterior()
    codes = torch.arange(3).double()[:, None]
    f = OnlineIntentionFilter(
        model, forgetting=0.0, batch_size=3, evidence="predictive", state_prior="marginal"
    )
    z = torch.stack([s[:2] for s in styles.sequences[:3]])
    f.update(z[:, 0])
    m1, P1 = f.mean.clone(), f.cov.clone()
    # the per-class prediction from q(x_1 | z_1): SharedTransition vs GP-ADF per code
    mean, cov, cross = f.transition.moments(m1, P1)
    # the same moments by other algebra and shapes: rounding of solves with K + noise I,
    # gp_rounding (N EPS cond) of each quantity's scale (measured: up to 0.06 of it)
    rel = gp_rounding(trans)
    for k in range(3):
        ref = trans.predict_gaussian(m1, P1, g=codes[k], include_noise=True)
        for a, b in zip((mean[:, k], cov[:, k], cross[:, k]), ref, strict=True):
            torch.testing.assert_close(a, b, rtol=rel, atol=rel * float(b.abs().max()))
    assert not torch.allclose(cov[:, 0], cov[:, 1])
    # a grid of some codes, in any order, takes each code's own noise
    sub = SharedTransition(trans, torch.tensor([[2.0], [0.0]]))
    torch.testing.assert_close(sub.noise, model.value_noise[[2, 0]])
    for j, k in enumerate((2, 0)):
        # each code's block is computed on its own; only the batch of K grid values differs
        # (2 against 3), which may take other BLAS kernels for the weighted contractions: 1e-12,
        # of each matrix's scale for its small entries (the fused path subtracts mean mean^T
        # after contracting, so an entry carries the rounding of the second moment; measured:
        # 1.3e-14 of the scale)
        got = sub.moments(m1, P1)[1][:, j]
        scale = float(cov[:, k].abs().max())
        torch.testing.assert_close(got, cov[:, k], rtol=1e-12, atol=1e-12 * scale)
    # the belief after z_2 is the GP-ADF evidence of each code (z_1's is the same for all)
    belief = f.update(z[:, 1])
    ll = filter_sequence(trans, meas, z, f.mu0, f.Sigma0, g=codes[:, None, :]).log_likelihood
    # two filter steps by other code: the log-likelihoods agree to 2 gp_rounding of their
    # scale, and the probabilities move by that much (measured: up to 0.001 of it)
    rel = 2 * gp_rounding(trans, meas) * max(1.0, float(ll.abs().max()))
    torch.testing.assert_close(belief.prob, torch.softmax(ll.T, -1), rtol=rel, atol=rel)


def test_bad_arguments_raise(styles, fitted):
    seqs, labels = styles.sequences, styles.labels
    with pytest.raises(ValueError, match="noise_per_value"):
        IDDM(seqs, labels.double(), 3, intention="continuous", noise_per_value=True)
    with pytest.raises(ValueError, match="noise_per_value"):
        IDDM(seqs, labels, 3, sharing=0.3, noise_per_value=True)
    with pytest.raises(ValueError, match="noise_per_value"):
        HGPDM(seqs, labels, 3, learn_noise=True, noise_per_value=True)
    with pytest.raises(TypeError, match="noise_per_value"):
        IDDM(seqs, labels, 3, noise_per_value="yes")
    with pytest.raises(ValueError, match="noise_per_value"):
        make(styles).estimate_value_noise()
    with pytest.raises(ValueError, match="inducing"):
        OnlineIntentionFilter(fitted, batch_size=1, inducing=10)


def test_window_inference_uses_each_candidates_noise(fitted, styles):
    """VB and MAP window inference given g = k equal those of the shared-noise model whose
    alpha_4 is alpha_4,k (same latents and kernel): with sharing = 0 code k's transition GP
    reads only block k, whose training diagonal and new-step noise are both alpha_4,k. The
    shared model's alpha_4 passes through its constraint and back, which can move it by an ulp;
    the iterative solves (Levenberg-Marquardt, 5 L-BFGS steps) carry that to ~2e-9 nats on
    evidences of tens of nats and ~2e-10 on O(1) states, well inside the tolerances below. A
    wrong noise moves the evidence by nats."""
    from hgpdm_torch.inference import MAPInference, VariationalInference

    noises = fitted.value_noise
    assert float(noises.max() / noises.min()) > 1.5  # the noises differ: the test can fail
    z = torch.stack([s[:6] for s in styles.sequences[:4]])
    z[:, 2] = float("nan")  # a missing row: its state comes from the dynamics alone
    per_vb, per_map = VariationalInference(fitted), MAPInference(fitted)
    for k in range(3):
        shared = make(styles)
        shared.load_state_dict(fitted.state_dict(), strict=False)
        shared.transition_noise = noises[k]
        a = per_vb.infer(z, values=[k], steps=5)
        b = VariationalInference(shared).infer(z, values=[k], steps=5)
        torch.testing.assert_close(a.log_evidence, b.log_evidence, rtol=1e-9, atol=1e-9)
        torch.testing.assert_close(a.mean, b.mean, rtol=1e-7, atol=1e-9)
        torch.testing.assert_close(a.cov, b.cov, rtol=1e-7, atol=1e-11)
        ma = per_map.infer(z, values=[k])
        mb = MAPInference(shared).infer(z, values=[k])
        torch.testing.assert_close(ma.log_joint, mb.log_joint, rtol=1e-9, atol=1e-9)
        torch.testing.assert_close(ma.latent, mb.latent, rtol=1e-7, atol=1e-9)
    # and all candidates at once (no pruning, which depends on the other candidates): each
    # reads its own noise, not the first's or alpha_4. Batched and single solves round
    # differently and 5 L-BFGS steps amplify that to ~1e-8 nats; a wrong noise moves nats.
    every = per_vb.infer(z, steps=5, prune=None)
    one = per_vb.infer(z, values=[2], steps=5, prune=None)
    torch.testing.assert_close(
        every.log_evidence[..., 2], one.log_evidence[..., 0], rtol=1e-7, atol=1e-7
    )
    # candidates that differ per window (codes varying along two axes) gather each code's
    # block and noise in one batch
    per_window = torch.tensor([[0, 2], [1, 0], [2, 1], [0, 1]])
    mixed = per_vb.infer(z, values=per_window, steps=5, prune=None)
    for w in range(4):
        for j in range(2):
            alone = per_vb.infer(z[w : w + 1], values=[int(per_window[w, j])], steps=5, prune=None)
            torch.testing.assert_close(
                mixed.log_evidence[w, j], alone.log_evidence[0, 0], rtol=1e-7, atol=1e-7
            )
