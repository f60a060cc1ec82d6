"""GPPosterior.sparse (the DTC approximation on pseudo-inputs, thesis Sec. 3.3.3) and
GPPosterior.shared_moments, against the DTC formulas written out densely here (LU solves with
``A = noise K_MM + K_MN K_NM`` and ``K_MM``, no Cholesky factor), the exact GP where ``Z = X``,
and Monte Carlo of the dense formulas at sampled inputs for the Gaussian-input moments."""

from __future__ import annotations

import copy

import pytest
import torch

import hgpdm_torch.inference as inference
import hgpdm_torch.inference.intention as intention
from hgpdm_torch.gp import GPPosterior
from hgpdm_torch.gp_shared import SharedTransition, sparse_posterior
from hgpdm_torch.kernels import transition_kernel

DX, NOISE = 2, 0.05
ALPHA = (0.9, 0.5, 0.1, NOISE)
#: transition kernels over [x, g]: the IDDM's tensor-product and block kernels (the block one
#: takes the per-code path of predict_gaussian) and the H-GPDM's RBF + linear ones
KINDS = ("iddm_continuous", "iddm_discrete", "continuous", "discrete")


def _problem(kind: str, gen: torch.Generator, n: int = 48, m: int = 12):
    """A GP over ``[x, g]`` (Dx = 2, Dg = 1, Dout = 2, with scale and offset), pseudo-inputs
    ``Z [m, 3]`` and a grid ``values [3, 1]`` of g (codes for the discrete kinds)."""
    discrete = kind in ("iddm_discrete", "discrete")
    if discrete:
        sharing = 0.3 if kind == "discrete" else 0.0
        kernel = transition_kernel(kind, DX, num_values=3, alpha=ALPHA, sharing=sharing)
        g = (torch.arange(n) % 3).double()[:, None]
        gz = (torch.arange(m) % 3).double()[:, None]
        values = torch.arange(3.0, dtype=torch.float64)[:, None]
    else:
        kernel = transition_kernel(kind, DX, alpha=ALPHA)
        g = (2 * torch.rand(8, generator=gen) - 1).repeat_interleave(n // 8)[:, None]
        gz = (2 * torch.rand(3, generator=gen) - 1).repeat_interleave(m // 3)[:, None]
        values = torch.tensor([[-0.7], [0.1], [0.8]], dtype=torch.float64)
    x = 1.5 * torch.randn(n, DX, generator=gen)
    X = torch.cat([x, g], 1)
    Y = torch.cat([torch.sin(x[:, :1]) + 0.3 * g, torch.cos(x[:, 1:])], 1)
    Z = torch.cat([1.5 * torch.randn(m, DX, generator=gen), gz], 1)
    scale, offset = torch.tensor([1.0, 0.5]), torch.tensor([0.2, -1.0])
    post = GPPosterior(kernel, X, Y, NOISE, scale=scale, offset=offset)
    return post, Z, values


class _DenseDTC:
    """The DTC predictive at points by dense LU solves (the oracle):
    ``mean = k_*M A^-1 K_MN Y + offset``,
    ``var = scale^2 (k_** - k_*M K_MM^-1 k_M* + noise k_*M A^-1 k_M* [+ noise])``."""

    def __init__(self, post: GPPosterior, Z: torch.Tensor) -> None:
        self.kernel, self.Z, self.scale, self.offset = post.kernel, Z, post.scale, post.offset
        with torch.no_grad():
            self.Kmm = post.kernel(Z).to_dense()
            Kmn = post.kernel(Z, post.train_inputs).to_dense()
        self.A = NOISE * self.Kmm + Kmn @ Kmn.T
        self.weights = torch.linalg.solve(self.A, Kmn @ post.train_targets)
        eye = torch.eye(len(Z), dtype=Z.dtype)
        self.kinv = torch.linalg.solve(self.Kmm, eye) - NOISE * torch.linalg.solve(self.A, eye)

    def __call__(
        self, x: torch.Tensor, include_noise: bool = False
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """``mean [P, Dout]`` and ``var [P, Dout]`` at ``x [P, Din]``."""
        with torch.no_grad():
            kxz = self.kernel(x, self.Z).to_dense()  # [P, M]
            kxx = self.kernel(x, diag=True)
        q_mm = (kxz * torch.linalg.solve(self.Kmm, kxz.T).T).sum(-1)
        q_a = (kxz * torch.linalg.solve(self.A, kxz.T).T).sum(-1)
        var = kxx - q_mm + NOISE * q_a + (NOISE if include_noise else 0.0)
        return kxz @ self.weights + self.offset, var[:, None] * self.scale.pow(2)


@pytest.mark.parametrize("kind", KINDS)
def test_sparse_matches_the_dense_dtc_formulas(kind, generator):
    post, Z, _ = _problem(kind, generator)
    sparse = post.sparse(Z)
    oracle = _DenseDTC(post, Z)
    assert isinstance(sparse, GPPosterior) and torch.equal(sparse.train_inputs, Z)
    assert (sparse.input_dim, sparse.output_dim) == (3, 2)
    torch.testing.assert_close(sparse.weights, oracle.weights, rtol=1e-9, atol=1e-10)
    torch.testing.assert_close(sparse.kinv, oracle.kinv, rtol=1e-9, atol=1e-9)
    xs = torch.cat([1.5 * torch.randn(9, DX, generator=generator), Z[:9, DX:]], 1)
    for noisy in (False, True):
        mean, var = sparse.predict(xs.reshape(3, 3, 3), include_noise=noisy)
        ref_mean, ref_var = oracle(xs, noisy)
        torch.testing.assert_close(mean.reshape(9, 2), ref_mean, rtol=1e-10, atol=1e-11)
        torch.testing.assert_close(var.reshape(9, 2), ref_var, rtol=1e-9, atol=1e-11)
    # with Sigma = 0 the Gaussian-input moments are the point prediction (every kernel path)
    mean, cov, cross = sparse.predict_gaussian(
        xs[:, :DX], torch.zeros(9, DX, DX), g=xs[:, DX:], include_noise=True
    )
    ref_mean, ref_var = oracle(xs, True)
    torch.testing.assert_close(mean, ref_mean, rtol=1e-9, atol=1e-10)
    torch.testing.assert_close(cov, torch.diag_embed(ref_var), rtol=1e-8, atol=1e-10)
    assert float(cross.abs().max()) == 0.0


@pytest.mark.parametrize("kind", KINDS)
def test_sparse_on_all_training_inputs_is_the_exact_gp(kind, generator):
    """DTC with ``Z = X``: ``A^-1 K Y = (K + noise I)^-1 Y`` and
    ``K^-1 - noise A^-1 = (K + noise I)^-1``."""
    post, _, values = _problem(kind, generator, n=24)
    sparse = post.sparse(post.train_inputs)
    xs = torch.cat([torch.randn(6, DX, generator=generator), post.train_inputs[:6, DX:]], 1)
    exact = post.predict(xs, include_noise=True)
    for a, b in zip(sparse.predict(xs, include_noise=True), exact, strict=True):
        torch.testing.assert_close(a, b, rtol=1e-8, atol=1e-9)
    mu = torch.randn(4, 1, DX, generator=generator)
    A = torch.randn(4, 1, DX, DX, generator=generator)
    Sigma = 0.1 * A @ A.mT + 1e-3 * torch.eye(DX)
    opts = {"g": values[None], "include_noise": True}
    exact = post.predict_gaussian(mu, Sigma, **opts)
    for a, b in zip(sparse.predict_gaussian(mu, Sigma, **opts), exact, strict=True):
        torch.testing.assert_close(a, b, rtol=1e-8, atol=1e-9)


@pytest.mark.parametrize("kind", KINDS)
def test_sparse_gaussian_input_moments_match_monte_carlo(kind, generator):
    """predict_gaussian on the sparse posterior for two input Gaussians and the three grid values
    at once (``mu [2, 1, Dx]``, ``g [1, 3, 1]``), with the noise and a joint variable ``s``
    (``joint_cov``), against 20,000 draws of ``(x, s)`` pushed through the dense DTC
    formulas: mean, covariance (law of total covariance), ``Cov[x, f]`` and ``Cov[s, f]``
    within 5 Monte-Carlo standard errors."""
    post, Z, values = _problem(kind, generator)
    sparse = post.sparse(Z)
    oracle = _DenseDTC(post, Z)
    B, S = 2, 20_000
    mu = torch.tensor([[0.3, -0.5], [-1.0, 0.8]])
    J = torch.randn(B, DX + 1, DX + 1, generator=generator)
    joint = 0.2 * J @ J.mT + 1e-2 * torch.eye(DX + 1)  # [x, s] jointly Gaussian
    Sigma, C = joint[:, :DX, :DX], joint[:, DX:, :DX]  # C = Cov[s, x]: [B, 1, Dx]
    mean, cov, io = sparse.predict_gaussian(
        mu[:, None], Sigma[:, None], g=values[None], include_noise=True
    )
    _, _, js = sparse.predict_gaussian(
        mu[:, None], Sigma[:, None], g=values[None], include_noise=True, joint_cov=C[:, None]
    )
    assert mean.shape == (B, 3, 2) and cov.shape == (B, 3, 2, 2)
    assert io.shape == (B, 3, DX, 2) and js.shape == (B, 3, 1, 2)
    for b in range(B):
        full_mu = torch.cat([mu[b], torch.zeros(1)])
        xs = torch.distributions.MultivariateNormal(full_mu, joint[b]).sample((S,))
        x, s = xs[:, :DX], xs[:, DX:]
        for k in range(3):
            m, v = oracle(torch.cat([x, values[k].expand(S, 1)], 1), include_noise=True)
            dm = m - m.mean(0)
            second = dm[:, :, None] * dm[:, None, :] + torch.diag_embed(v)
            cx = (x - x.mean(0))[:, :, None] * dm[:, None, :]
            cs = (s - s.mean(0))[:, :, None] * dm[:, None, :]
            for est, samples in (
                (mean[b, k], m), (cov[b, k], second), (io[b, k], cx), (js[b, k], cs)
            ):  # fmt: skip
                se = samples.std(0) / S**0.5
                err = (samples.mean(0) - est).abs()
                assert bool((err <= 5 * se + 1e-9).all()), (kind, b, k, err.max(), se.max())


@pytest.mark.parametrize("kind", ["iddm_continuous", "iddm_discrete"])
def test_repeated_pseudo_inputs_are_regularised(kind, generator):
    """Each pseudo-input twice makes ``K_MM`` singular: its ridge (condition 1e8) keeps the DTC
    what it is on the distinct ones (a repeated pseudo-input adds nothing), and the moments
    reproducible: the grouped fast path equals predict_gaussian to 1e-8 (unregularised, the
    cancellation in ``K_MM^-1 - noise A^-1`` left them to rounding)."""
    post, Z, values = _problem(kind, generator)
    twice = post.sparse(torch.cat([Z, Z]))
    once = post.sparse(Z)
    xs = torch.cat([torch.randn(6, DX, generator=generator), Z[:6, DX:]], 1)
    for a, b in zip(twice.predict(xs), once.predict(xs), strict=True):
        torch.testing.assert_close(a, b, rtol=1e-5, atol=1e-6)
    mu = torch.randn(3, DX, generator=generator)
    A = torch.randn(3, DX, DX, generator=generator)
    Sigma = 0.1 * A @ A.mT + 1e-3 * torch.eye(DX)
    fast = twice.shared_moments(values).moments(mu, Sigma)
    ref = twice.predict_gaussian(mu[:, None], Sigma[:, None], g=values[None], include_noise=True)
    for a, b, c in zip(fast, ref, once.shared_moments(values).moments(mu, Sigma), strict=True):
        torch.testing.assert_close(a, b, rtol=1e-8, atol=1e-10)
        torch.testing.assert_close(a, c, rtol=1e-5, atol=1e-6)


def test_sparse_refuses_bad_inducing_inputs_and_noises(generator):
    post, Z, _ = _problem("iddm_continuous", generator)
    with pytest.raises(ValueError, match=r"inducing_inputs must be \[M, Din\] = \[M > 0, 3\]"):
        post.sparse(Z[:, :2])
    with pytest.raises(ValueError, match="inducing_inputs must be"):
        post.sparse(Z[:0])
    with pytest.raises(ValueError, match="inducing_inputs must have 2 dimensions"):
        post.sparse(Z[0])
    for bad in (float("nan"), float("inf")):
        Zb = Z.clone()
        Zb[3, 1] = bad
        with pytest.raises(ValueError, match="inducing_inputs contains NaN or inf"):
            post.sparse(Zb)
    with pytest.raises(TypeError, match="inducing_inputs"):
        post.sparse("Z")
    X, Y = post.train_inputs, post.train_targets
    per_point = GPPosterior(post.kernel, X, Y, torch.full((len(X),), NOISE))
    with pytest.raises(ValueError, match="one noise.*per training point.*inducing=None"):
        per_point.sparse(Z)
    kernel = transition_kernel("iddm_discrete", DX, num_values=3, alpha=ALPHA)
    codes = torch.cat([X[:, :DX], (torch.arange(len(X)) % 3).double()[:, None]], 1)
    per_code = GPPosterior(kernel, codes, Y, NOISE, code_noise=torch.tensor([0.1, 0.2, 0.3]))
    with pytest.raises(ValueError, match=r"per code \(code_noise\).*noise_per_value"):
        per_code.sparse(codes[:6])
    sparse = post.sparse(Z)
    assert not hasattr(sparse, "chol")  # no Cholesky factor of K + noise I: weights and kinv
    with pytest.raises(AttributeError, match="no Cholesky factor"):
        _ = sparse.chol


def test_sparse_dtype_gradients_and_resparsifying(generator):
    post, Z, _ = _problem("continuous", generator)
    sparse = post.sparse(Z)
    xs = torch.cat([torch.randn(5, DX, generator=generator), Z[:5, DX:]], 1)
    ref_mean, ref_var = sparse.predict(xs)
    # another dtype: the factors and kinv of this one's, cast (K_MM^-1 - noise A^-1 cancels
    # two large matrices, which float32 arithmetic would leave to rounding)
    low = sparse.to_dtype(torch.float32)
    assert low.train_inputs.dtype == low.weights.dtype == low.kinv.dtype == torch.float32
    assert torch.equal(low.kinv, sparse.kinv.float())
    assert torch.equal(low.weights, sparse.weights.float())
    assert sparse.train_inputs.dtype == sparse.kinv.dtype == torch.float64  # unchanged
    assert sparse.to_dtype(torch.float64) is sparse
    mean, var = low.predict(xs.float())
    torch.testing.assert_close(mean.double(), ref_mean, rtol=1e-3, atol=1e-4)
    torch.testing.assert_close(var.double(), ref_var, rtol=1e-3, atol=1e-4)
    # sparse of a sparse posterior starts again from the data
    again = sparse.sparse(Z[:6])
    for a, b in zip(again.predict(xs), post.sparse(Z[:6]).predict(xs), strict=True):
        torch.testing.assert_close(a, b, rtol=0, atol=0)
    # not detached: the factors follow the hyperparameters, and gradients reach them
    kernel = copy.deepcopy(post.kernel).requires_grad_(True)
    live = GPPosterior(kernel, post.train_inputs, post.train_targets, NOISE, detach=False)
    live_sparse = live.sparse(Z)
    assert not live_sparse.detach
    mean, var = live_sparse.predict(xs)
    torch.testing.assert_close(mean, ref_mean - post.offset, rtol=1e-12, atol=1e-12)
    grads = torch.autograd.grad(mean.sum() + var.sum(), list(kernel.parameters()))
    assert all(g is not None and bool(torch.isfinite(g).all()) for g in grads)
    assert any(float(g.abs().max()) > 0 for g in grads)


def test_shared_moments_is_the_shared_transition_on_either_posterior(generator):
    """``posterior.shared_moments(values)`` is :class:`SharedTransition`; on a sparse posterior
    it equals ``predict_gaussian`` at ``[x, g_k]`` with the noise, and ``SharedTransition(...,
    inducing=M)`` is ``sparse_posterior(...).shared_moments(...)`` bit for bit."""
    post, Z, values = _problem("iddm_continuous", generator)
    mu = torch.randn(3, DX, generator=generator)
    A = torch.randn(3, DX, DX, generator=generator)
    Sigma = 0.1 * A @ A.mT + 1e-3 * torch.eye(DX)
    for p in (post, post.sparse(Z)):
        fast = p.shared_moments(values)
        assert isinstance(fast, SharedTransition)
        ref = p.predict_gaussian(mu[:, None], Sigma[:, None], g=values[None], include_noise=True)
        for a, b in zip(fast.moments(mu, Sigma), ref, strict=True):
            torch.testing.assert_close(a, b, rtol=1e-8, atol=1e-10)
    direct = SharedTransition(post, values, inducing=20, inducing_values=2)
    via = sparse_posterior(post, 1, 20, 2).shared_moments(values)
    assert direct.groups == via.groups == 2
    for a, b in zip(direct.moments(mu, Sigma), via.moments(mu, Sigma), strict=True):
        assert torch.equal(a, b)
    # the old import paths name the same class
    assert intention.SharedTransition is inference.SharedTransition is SharedTransition
    # the grid must name the trailing columns, and the kernel must be the IDDM's
    with pytest.raises(ValueError, match=r"values must be \[K, Dg\] with 1 <= Dg < Din = 3"):
        post.shared_moments(values[:, 0])
    with pytest.raises(ValueError, match="values must be"):
        post.shared_moments(torch.zeros(3, 3))
    hgpdm = transition_kernel("continuous", DX, alpha=ALPHA)  # RBF + linear terms
    other = GPPosterior(hgpdm, post.train_inputs, post.train_targets, NOISE)
    with pytest.raises(TypeError, match="SharedTransition needs the IDDM transition kernel"):
        other.shared_moments(values)


def test_sparse_posterior_pseudo_inputs(generator):
    """The pseudo-inputs of :func:`sparse_posterior`: training latents on few g values; without
    g (a GPDM) evenly spread training points; ``inducing >= N`` keeps all training points."""
    post, _, _ = _problem("iddm_continuous", generator)
    n = len(post.train_inputs)
    assert sparse_posterior(post, 1, None) is post
    sp = sparse_posterior(post, 1, 16, 4)
    Z = sp.train_inputs
    assert Z.shape == (16, 3) and len(torch.unique(Z[:, DX])) == 4
    assert bool(torch.isin(Z[:, :DX], post.train_inputs[:, :DX]).all())
    full = sparse_posterior(post, 1, n)
    assert torch.equal(full.train_inputs, post.train_inputs)
    # groups of unequal size (5, 10 and 30 points): M >= N still keeps every training point
    uneven = torch.cat([post.train_inputs[:45, :DX], torch.repeat_interleave(
        torch.tensor([-1.0, 0.0, 1.0], dtype=post.train_inputs.dtype), torch.tensor([5, 10, 30])
    )[:, None]], 1)  # fmt: skip
    post_u = GPPosterior(post.kernel, uneven, post.train_targets[:45], NOISE)
    for m in (45, 60):
        assert torch.equal(sparse_posterior(post_u, 1, m).train_inputs, uneven)
    gpdm = GPPosterior(
        transition_kernel("gpdm", 3, alpha=ALPHA), post.train_inputs, post.train_targets, NOISE
    )
    rows = sparse_posterior(gpdm, 0, 8).train_inputs
    assert torch.equal(rows, post.train_inputs[torch.linspace(0, n - 1, 8).round().long()])
    with pytest.raises(ValueError, match="inducing must be a positive int"):
        sparse_posterior(post, 1, 0)
    with pytest.raises(ValueError, match="inducing_values must be a positive int"):
        sparse_posterior(post, 1, 10, True)
    with pytest.raises(ValueError, match="cannot exceed inducing"):
        sparse_posterior(post, 1, 4, 5)
    with pytest.raises(ValueError, match="needs inducing"):
        sparse_posterior(post, 1, None, 3)
    with pytest.raises(ValueError, match=r"dg must be in \[0, 2\]"):
        sparse_posterior(post, 3, 10)
