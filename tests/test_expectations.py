"""Gaussian-input kernel expectations against quadrature, Monte Carlo and finite differences.

The oracles evaluate the gpytorch kernel objects themselves at the quadrature nodes / samples, so
they are independent of the leaf/term decomposition in ``hgpdm_torch.expectations``.
"""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest
import torch
from gpytorch.kernels import AdditiveKernel, LinearKernel, RBFKernel, ScaleKernel
from scipy import integrate

from hgpdm_torch import expectations as ex
from hgpdm_torch.kernels import IntentionRBFKernel, intention_rbf, transition_kernel


def gauss_hermite(mu: torch.Tensor, Sigma: torch.Tensor, n: int):
    """Tensor-product Gauss-Hermite nodes ``[n^D, D]`` and weights for ``N(mu, Sigma)``."""
    D = mu.shape[-1]
    u, w = np.polynomial.hermite.hermgauss(n)
    nodes = torch.tensor(np.array(list(itertools.product(u, repeat=D))))
    weights = torch.tensor(np.prod(np.array(list(itertools.product(w, repeat=D))), axis=1))
    L = torch.linalg.cholesky(Sigma)
    return mu + math.sqrt(2.0) * nodes @ L.T, weights / math.pi ** (D / 2)


def random_cov(D: int, gen: torch.Generator, scale: float = 0.3) -> torch.Tensor:
    A = torch.randn(D, D, generator=gen) * scale
    return A @ A.T + 0.05 * torch.eye(D)


def dense(kernel, x1, x2=None, diag=False):
    with torch.no_grad():
        out = kernel(x1, x1 if x2 is None else x2, diag=diag)
        return out if diag else out.to_dense()


# nodes per dim: converged to ~1e-10 for the covariances drawn by random_cov
NODES = {1: 60, 2: 48, 3: 40}


def close(actual, expected, rtol=1e-6):
    actual = actual.detach()
    atol = 1e-9 * float(expected.abs().max()) + 1e-300
    torch.testing.assert_close(actual, expected, rtol=rtol, atol=atol)


def check_quadrature(kernel, mu, Sigma, X, g=None, nodes=None):
    """psi0, psi1, psi2 and x_psi1 against Gauss-Hermite quadrature of the gpytorch kernel, with
    the known trailing columns ``g`` (or none)."""
    x, w = gauss_hermite(mu, Sigma, nodes or NODES[mu.shape[-1]])
    xg = x if g is None else torch.cat([x, g.expand(len(x), g.shape[-1])], -1)
    K = dense(kernel, xg, X)
    close(ex.psi0(kernel, mu, Sigma, g=g), w @ dense(kernel, xg, diag=True))
    close(ex.psi1(kernel, mu, Sigma, X, g=g), w @ K)
    close(ex.psi2(kernel, mu, Sigma, X, g=g), torch.einsum("n,ni,nj->ij", w, K, K))
    close(ex.x_psi1(kernel, mu, Sigma, X, g=g), torch.einsum("n,nd,ni->di", w, x, K))


# ----- kernels under test: (name, builder(D) -> kernel, g_dim known) ----------------------------


def rbf_iso(D):
    k = RBFKernel()
    k.lengthscale = 0.9
    return k


def rbf_ard(D):
    k = ScaleKernel(RBFKernel(ard_num_dims=D))
    k.base_kernel.lengthscale = torch.linspace(0.7, 1.6, D)
    k.outputscale = 1.3
    return k


def linear(D):
    k = LinearKernel()
    k.variance = 0.4
    return k


def gpdm(D):
    k = transition_kernel("gpdm", D, alpha=(0.9, 1.2, 0.3, 1e-3))
    return k


def active_dims(D):
    idx = torch.tensor([0, D - 1])
    rbf = ScaleKernel(RBFKernel(ard_num_dims=2, active_dims=idx))
    rbf.base_kernel.lengthscale = torch.tensor([0.8, 1.3])
    lin = LinearKernel(active_dims=torch.tensor([D - 1]))
    lin.variance = 0.7
    return AdditiveKernel(rbf, lin)


def intention_uncertain(D):
    # IDDM tensor product over [x, g] with g uncertain (part of the Gaussian)
    k = transition_kernel(
        "continuous", D - 1, g_dim=1, alpha=(0.8, 1.0, 0.2, 1e-3), alpha_g=(2.0, 0.5)
    )
    return k


KERNELS = {
    "rbf_iso": rbf_iso,
    "rbf_ard": rbf_ard,
    "linear": linear,
    "gpdm": gpdm,
    "active_dims": active_dims,
    "intention_uncertain": intention_uncertain,
}


def setup(D, seed, N=6):
    gen = torch.Generator().manual_seed(seed)
    mu = 0.5 * torch.randn(D, generator=gen)
    Sigma = random_cov(D, gen)
    X = torch.randn(N, D, generator=gen)
    return mu, Sigma, X


@pytest.mark.parametrize("D", [1, 2, 3])
@pytest.mark.parametrize("name", list(KERNELS))
def test_against_gauss_hermite(name, D):
    if name in ("active_dims", "intention_uncertain") and D == 1:
        pytest.skip("needs at least two columns")
    kernel = KERNELS[name](D)
    check_quadrature(kernel, *setup(D, seed=10 * D))


def _pair(kind: str, D: int):
    rbf_a = RBFKernel(ard_num_dims=D)
    rbf_a.lengthscale = torch.linspace(0.8, 1.4, D)
    rbf_b = ScaleKernel(RBFKernel())
    rbf_b.base_kernel.lengthscale = 0.6
    rbf_b.outputscale = 0.5
    lin_a, lin_b = LinearKernel(), LinearKernel(active_dims=torch.tensor([D - 1]))
    lin_a.variance, lin_b.variance = 0.3, 1.7
    return {
        "rbf_rbf": (rbf_a, rbf_b),
        "rbf_linear": (rbf_a, lin_a),
        "linear_rbf": (lin_a, rbf_b),
        "linear_linear": (lin_a, lin_b),
    }[kind]


@pytest.mark.parametrize("D", [1, 2, 3])
@pytest.mark.parametrize("kind", ["rbf_rbf", "rbf_linear", "linear_rbf", "linear_linear"])
def test_cross_psi2_against_gauss_hermite(kind, D):
    ka, kb = _pair(kind, D)
    mu, Sigma, X = setup(D, seed=7 + D)
    x, w = gauss_hermite(mu, Sigma, NODES[D])
    expected = torch.einsum("n,ni,nj->ij", w, dense(ka, x, X), dense(kb, x, X))
    close(ex.psi2(ka, mu, Sigma, X, kernel_b=kb), expected)


@pytest.mark.parametrize("kind", ["continuous", "iddm_continuous", "discrete", "iddm_discrete"])
def test_known_intention_columns(kind):
    """Known trailing columns g (continuous values or discrete codes) against quadrature."""
    Dx, N = 2, 7
    gen = torch.Generator().manual_seed(3)
    kernel = transition_kernel(kind, Dx, g_dim=1, num_values=3, alpha=(0.9, 0.8, 0.3, 1e-3))
    mu, Sigma = 0.3 * torch.randn(Dx, generator=gen), random_cov(Dx, gen)
    X = torch.randn(N, Dx, generator=gen)
    if "discrete" in kind:
        col = torch.tensor([0.0, 1, 2, 1, 0, 2, 1])[:, None]
        g = torch.tensor([1.0])
    else:
        col = torch.randn(N, 1, generator=gen)
        g = torch.tensor([0.4])
    X = torch.cat([X, col], -1)
    check_quadrature(kernel, mu, Sigma, X, g, nodes=40)
    if "discrete" in kind:  # points of other codes are masked out exactly
        assert torch.all(ex.psi1(kernel, mu, Sigma, X, g=g)[col[:, 0] != 1] == 0)


@pytest.mark.parametrize("name", ["rbf_ard", "gpdm", "active_dims", "intention_uncertain"])
def test_cross_expectation_of_two_independent_inputs(name):
    """E[k(x1, x2)] (App. 2.B c12) against quadrature over the joint [x1, x2] (4 dims)."""
    kernel = KERNELS[name](2)
    gen = torch.Generator().manual_seed(9)
    mu1, mu2 = 0.4 * torch.randn(2, generator=gen), 0.4 * torch.randn(2, generator=gen)
    S1, S2 = random_cov(2, gen, 0.2), random_cov(2, gen, 0.2)
    joint = torch.block_diag(S1, S2)
    x, w = gauss_hermite(torch.cat([mu1, mu2]), joint, 20)
    expected = w @ dense(kernel, x[:, :2], x[:, 2:], diag=True)
    close(ex.psi0_cross(kernel, mu1, S1, mu2, S2), expected)


def test_log_space_where_factors_underflow():
    """Far-away training points: k(mu, X_i)^2 underflows, the expectation does not (scipy quad)."""
    k = RBFKernel()
    k.lengthscale = 1.0
    X = torch.tensor([[40.0], [41.0]])
    mu, Sigma = torch.tensor([0.0]), torch.tensor([[900.0]])
    assert float(dense(k, mu[None], X).max()) == 0.0  # exp(-800) underflows in float64

    def gauss(x):
        return math.exp(-0.5 * x**2 / 900.0) / math.sqrt(2 * math.pi * 900.0)

    def kern(x, c):
        return math.exp(-0.5 * (x - c) ** 2)

    p2 = ex.psi2(k, mu, Sigma, X).detach()
    for i, j in [(0, 0), (0, 1), (1, 1)]:
        ci, cj = float(X[i, 0]), float(X[j, 0])
        ref = integrate.quad(
            lambda x, ci=ci, cj=cj: gauss(x) * kern(x, ci) * kern(x, cj), 30, 50, epsabs=0
        )[0]
        assert ref > 1e-6
        assert float(p2[i, j]) == pytest.approx(ref, rel=1e-8)


def monte_carlo(fn, mu, Sigma, n, gen, chunk=100_000):
    """Mean and standard error of ``fn(x)`` for ``x ~ N(mu, Sigma)``, accumulated in chunks."""
    L = torch.linalg.cholesky(Sigma)
    s1 = s2 = 0.0
    for _ in range(n // chunk):
        x = mu + torch.randn(chunk, mu.shape[-1], generator=gen) @ L.T
        v = fn(x)
        s1, s2 = s1 + v.sum(0), s2 + v.pow(2).sum(0)
    mean = s1 / n
    return mean, ((s2 / n - mean.pow(2)).clamp_min(0) / n).sqrt()


@pytest.mark.parametrize(
    "name,D",
    [("intention_uncertain", 4), ("gpdm", 5), ("active_dims", 5), ("intention6", 6)],
)
def test_against_monte_carlo_high_dim(name, D):
    if name == "intention6":
        kernel = transition_kernel("continuous", 4, g_dim=2, alpha=(0.9, 0.6, 0.2, 1e-3))
    else:
        kernel = KERNELS[name](D)
    mu, Sigma, X = setup(D, seed=D, N=4)
    gen = torch.Generator().manual_seed(100 + D)
    N = X.shape[0]

    def stats(x):
        K = dense(kernel, x, X)
        outer = (K[:, :, None] * K[:, None, :]).reshape(len(x), -1)
        xk = (x[:, :, None] * K[:, None, :]).reshape(len(x), -1)
        return torch.cat([K, outer, xk], -1)

    mean, se = monte_carlo(stats, mu, Sigma, 1_000_000, gen)
    ours = torch.cat(
        [
            ex.psi1(kernel, mu, Sigma, X),
            ex.psi2(kernel, mu, Sigma, X).reshape(-1),
            ex.x_psi1(kernel, mu, Sigma, X).reshape(-1),
        ]
    ).detach()
    assert ours.shape == (N + N * N + D * N,)
    z = (ours - mean).abs() / (se + 1e-12)
    assert float(z.max()) < 5.0, f"max |error| / standard error = {float(z.max()):.2f}"


def test_batched_broadcasting_matches_loop():
    kernel = transition_kernel("continuous", 2, g_dim=1, alpha=(0.9, 0.8, 0.3, 1e-3))
    gen = torch.Generator().manual_seed(5)
    B, K, N = 3, 4, 6
    mu = torch.randn(B, 1, 2, generator=gen)
    Sigma = torch.stack([random_cov(2, gen) for _ in range(B)])[:, None]
    g = torch.randn(1, K, 1, generator=gen)
    X = torch.randn(N, 3, generator=gen)
    out1, out2 = ex.psi1(kernel, mu, Sigma, X, g=g), ex.psi2(kernel, mu, Sigma, X, g=g)
    out0, outx = ex.psi0(kernel, mu, Sigma, g=g), ex.x_psi1(kernel, mu, Sigma, X, g=g)
    assert out1.shape == (B, K, N) and out2.shape == (B, K, N, N)
    assert out0.shape == (B, K) and outx.shape == (B, K, 2, N)
    for b, k in itertools.product(range(B), range(K)):
        args = (kernel, mu[b, 0], Sigma[b, 0])
        torch.testing.assert_close(out1[b, k], ex.psi1(*args, X, g=g[0, k]))
        torch.testing.assert_close(out2[b, k], ex.psi2(*args, X, g=g[0, k]))
        torch.testing.assert_close(out0[b, k], ex.psi0(*args, g=g[0, k]))
        torch.testing.assert_close(outx[b, k], ex.x_psi1(*args, X, g=g[0, k]))


@pytest.mark.parametrize("mean_shape", [(2,), (1, 2)])
def test_covariances_with_batch_dims_the_mean_lacks(mean_shape):
    """One mean, several covariances (``mu [D]`` or ``[1, D]``, ``Sigma [B, D, D]``) broadcast
    like any batch: each member as if alone (the same formulas per member, so only the rounding
    of the batched products differs, far below the default tolerance)."""
    kernel = ScaleKernel(RBFKernel(ard_num_dims=2))
    kernel.base_kernel.lengthscale = torch.tensor([[0.7, 1.3]])
    gen = torch.Generator().manual_seed(6)
    B, N = 4, 5
    mu = torch.randn(mean_shape, generator=gen)
    Sigma = torch.stack([random_cov(2, gen) for _ in range(B)])
    X = torch.randn(N, 2, generator=gen)
    out1, out2 = ex.psi1(kernel, mu, Sigma, X), ex.psi2(kernel, mu, Sigma, X)
    outx = ex.x_psi1(kernel, mu, Sigma, X)
    assert out1.shape == (B, N) and out2.shape == (B, N, N) and outx.shape == (B, 2, N)
    for b in range(B):
        args = (kernel, mu.reshape(2), Sigma[b], X)
        torch.testing.assert_close(out1[b], ex.psi1(*args))
        torch.testing.assert_close(out2[b], ex.psi2(*args))
        torch.testing.assert_close(outx[b], ex.x_psi1(*args))


def test_zero_covariance_is_point_evaluation():
    kernel = intention_uncertain(3)
    mu, _, X = setup(3, seed=2)
    zero = torch.zeros(3, 3)
    K = dense(kernel, mu[None], X)[0]
    torch.testing.assert_close(ex.psi1(kernel, mu, zero, X).detach(), K)
    torch.testing.assert_close(ex.psi2(kernel, mu, zero, X).detach(), K[:, None] * K[None, :])
    torch.testing.assert_close(ex.x_psi1(kernel, mu, zero, X).detach(), mu[:, None] * K[None, :])


@pytest.mark.parametrize("name", ["rbf_ard", "linear", "transition"])
def test_point_kernel_matches_gpytorch_and_autograd(name):
    """term_k (the Sigma = 0 fast path) sums to the gpytorch kernel; its gradient to autograd's."""
    builders = {
        "rbf_ard": lambda: ScaleKernel(RBFKernel(ard_num_dims=3)),
        "linear": lambda: LinearKernel(),
        "transition": lambda: transition_kernel("gpdm", 3, alpha=(0.9, 0.8, 0.3, 1e-3)),
    }
    kernel = builders[name]()
    gen = torch.Generator().manual_seed(7)
    x, X = torch.randn(5, 3, generator=gen), torch.randn(9, 3, generator=gen)
    terms = ex.split_terms(ex.kernel_leaves(kernel, 3), X, None, 3)
    x_req = x.clone().requires_grad_(True)
    k = sum(ex.term_k(t, x_req, X)[0] for t in terms)
    close(k, dense(kernel, x, X), rtol=1e-10)
    grad = sum(ex.term_k(t, x, X, grad=True)[1] for t in terms).expand(5, 3, 9)
    for i in range(X.shape[0]):
        (auto,) = torch.autograd.grad(k[:, i].sum(), x_req, retain_graph=True)
        close(grad[..., i], auto, rtol=1e-10)


@pytest.mark.parametrize("fn", ["psi1", "psi2", "x_psi1", "psi0"])
def test_gradcheck_inputs(fn):
    kernel = transition_kernel("continuous", 2, g_dim=1, alpha=(0.9, 0.8, 0.3, 1e-3))
    mu, Sigma, X = setup(3, seed=4, N=4)
    A = torch.linalg.cholesky(Sigma)

    def f(mu, A, X):
        S = A @ A.T
        if fn == "psi0":
            return ex.psi0(kernel, mu, S) + 0.0 * X.sum()
        return getattr(ex, fn)(kernel, mu, S, X)

    inputs = tuple(t.clone().requires_grad_(True) for t in (mu, A, X))
    assert torch.autograd.gradcheck(f, inputs)


def test_hyperparameter_gradients_match_finite_differences():
    """Gradients reach every raw hyperparameter (needed by VB) and match central differences."""
    kernel = transition_kernel("continuous", 2, g_dim=1, alpha=(0.9, 0.8, 0.3, 1e-3))
    mu, Sigma, X = setup(3, seed=6, N=5)

    def value():
        return (
            ex.psi2(kernel, mu, Sigma, X).sum()
            + ex.psi1(kernel, mu, Sigma, X).sum()
            + ex.x_psi1(kernel, mu, Sigma, X).sum()
            + ex.psi0(kernel, mu, Sigma)
        )

    params = dict(kernel.named_parameters())
    kernel.zero_grad()
    value().backward()
    assert len(params) == 5
    for name, p in params.items():
        assert p.grad is not None, name
        for idx in np.ndindex(*p.shape):
            with torch.no_grad():
                old = p[idx].item()
                p[idx] = old + 1e-6
                up = value().item()
                p[idx] = old - 1e-6
                down = value().item()
                p[idx] = old
            assert p.grad[idx].item() == pytest.approx((up - down) / 2e-6, rel=1e-5, abs=1e-8)


def test_bad_inputs_raise():
    kernel = gpdm(2)
    mu, Sigma, X = setup(2, seed=1)
    with pytest.raises(ValueError, match="positive semi-definite"):
        ex.psi1(kernel, mu, torch.tensor([[1.0, 2.0], [2.0, 1.0]]), X)
    with pytest.raises(ValueError, match="symmetric"):
        ex.psi1(kernel, mu, torch.tensor([[1.0, 0.5], [0.0, 1.0]]), X)
    with pytest.raises(ValueError, match="trailing shape"):
        ex.psi1(kernel, mu, torch.eye(3), X)
    with pytest.raises(ValueError, match="NaN"):
        ex.psi1(kernel, torch.tensor([float("nan"), 0.0]), Sigma, X)
    with pytest.raises(ValueError, match="columns"):
        ex.psi1(kernel, mu, Sigma, torch.zeros(4, 3))
    with pytest.raises(TypeError, match="gpytorch Kernel"):
        ex.psi1(lambda a, b: a @ b.T, mu, Sigma, X)
    with pytest.raises(ValueError, match="batch_shape"):
        ex.psi1(RBFKernel(batch_shape=torch.Size([2])), mu, Sigma, X)
    discrete = transition_kernel("discrete", 1, num_values=2)
    with pytest.raises(ValueError, match="code"):
        ex.psi1(discrete, mu, Sigma, X)  # the code column may not be Gaussian
    with pytest.raises(ValueError, match="IntentionRBFKernel"):
        ex.psi1(IntentionRBFKernel(2, 1), mu, Sigma, X)


# ----- products (gpytorch ProductKernel) --------------------------------------------------------


def _dims(*cols):
    return torch.tensor(cols)


def _rbf(cols, ls):
    k = RBFKernel(active_dims=_dims(*cols), ard_num_dims=len(cols))
    k.lengthscale = torch.as_tensor(ls, dtype=torch.float64).expand(len(cols))
    return k


def _linear(cols, variance):
    k = LinearKernel(active_dims=_dims(*cols))
    k.variance = variance
    return k


def _products():
    """Products over 4 columns ``[x0, x1, g0, g1]``; ``g`` known unless ``all_gaussian``."""
    scaled = ScaleKernel(_rbf([0, 1], [0.8, 1.3]) * _linear([2, 3], 0.6))
    scaled.outputscale = 1.4
    return {
        # RBF x RBF, overlapping columns: one RBF with the summed precisions (any covariance)
        "rbf_rbf_overlap": (_rbf([0, 1, 2], [0.9, 1.1, 1.4]) * _rbf([1, 2, 3], [1.2, 0.7, 2.0])),
        "rbf_x_linear_g": scaled,
        "linear_x_rbf_g": _linear([0, 1], 0.5) * _rbf([2, 3], [0.9, 1.6]),
        "linear_x_linear_g": _linear([0, 1], 0.5) * _linear([2, 3], 0.8),
        "linear_g_first": _linear([2, 3], 0.8) * _linear([0, 1], 0.5),
        # a sum times a factor distributes; a linear kernel over [x, g] splits into two terms
        "sum_times_rbf_g": (
            AdditiveKernel(_rbf([0, 1], [1.0, 0.8]), _linear([0, 1, 2], 0.3))
            * _rbf([3], [1.2])
            * _linear([2], 0.7)
        ),
        "product_plus_linear": AdditiveKernel(
            _rbf([0, 1], [1.0, 0.8]) * _rbf([2, 3], [1.5, 0.6]), _linear([0, 3], 0.4)
        ),
    }


PRODUCTS = _products()


@pytest.mark.parametrize("name", list(PRODUCTS))
def test_products_with_known_columns_against_gauss_hermite(name):
    """``E[k_x(x, X_i) f(g, X_i)] = f(g, X_i) E[k_x(x, X_i)]`` (and psi2, x_psi1, psi0)."""
    kernel = PRODUCTS[name]
    gen = torch.Generator().manual_seed(21)
    mu, Sigma = 0.4 * torch.randn(2, generator=gen), random_cov(2, gen)
    X, g = torch.randn(6, 4, generator=gen), torch.tensor([0.3, -0.7])
    check_quadrature(kernel, mu, Sigma, X, g)


def test_rbf_products_with_all_columns_gaussian_against_gauss_hermite():
    """RBF x RBF is exact under any covariance, here coupling both factors' columns."""
    overlap = _rbf([0, 1], [0.9, 1.1]) * _rbf([1, 2], [1.2, 0.7])
    for kernel in (overlap, _rbf([0], [0.9]) * _rbf([1, 2], [1.3, 0.7])):
        mu, Sigma, X = setup(3, seed=4)
        check_quadrature(kernel, mu, Sigma, X)
    ard = RBFKernel(ard_num_dims=3)  # the last kernel is this ARD RBF
    ard.lengthscale = torch.tensor([0.9, 1.3, 0.7])
    args = (mu, Sigma, mu.flip(0), 0.5 * Sigma)
    close(ex.psi0_cross(kernel, *args), ex.psi0_cross(ard, *args).detach())


def test_products_whose_factors_share_gaussian_columns_raise():
    """A linear factor and another factor both on Gaussian columns: no closed form, clear error."""
    mu, Sigma, X = setup(3, seed=5)
    coupled = _rbf([0, 1], [1.0, 1.0]) * _linear([2], 0.5)  # all three columns Gaussian
    for fn in (ex.psi1, ex.psi2, ex.x_psi1):
        with pytest.raises(ValueError, match="couples them"):
            fn(coupled, mu, Sigma, X)
    with pytest.raises(ValueError, match="couples them"):
        ex.psi0(_linear([0], 0.5) * _linear([1], 0.5), mu, Sigma)
    with pytest.raises(ValueError, match="linear factor"):
        ex.psi0_cross(coupled, mu, Sigma, mu, Sigma)
    # the same kernel with its linear factor's column known is fine
    ex.psi2(coupled, mu[:2], Sigma[:2, :2], X, g=torch.tensor([0.2]))


def test_product_form_of_the_intention_rbf_gives_identical_expectations():
    """``intention_rbf`` (RBF(x) * RBF(g)) against IntentionRBFKernel: the same leaves, so the
    same expectations bit for bit, with g known or part of the Gaussian."""
    old = ScaleKernel(IntentionRBFKernel(2, 1))
    old.base_kernel.lengthscale_x, old.base_kernel.lengthscale_g, old.outputscale = 0.8, 1.6, 0.7
    new = ScaleKernel(intention_rbf(2, 1, 0.8, 1.6))
    new.outputscale = 0.7
    (a,), (b,) = ex.kernel_leaves(old, 3), ex.kernel_leaves(new, 3)
    assert (a.kind, a.cols, a.codes, a.factors) == (b.kind, b.cols, b.codes, b.factors)
    assert torch.equal(a.weight, b.weight) and torch.equal(a.coef, b.coef)
    mu, Sigma, X = setup(3, seed=6)
    g = torch.tensor([0.4])
    for fn in (ex.psi1, ex.psi2, ex.x_psi1):
        assert torch.equal(fn(old, mu, Sigma, X), fn(new, mu, Sigma, X))
        assert torch.equal(
            fn(old, mu[:2], Sigma[:2, :2], X, g=g), fn(new, mu[:2], Sigma[:2, :2], X, g=g)
        )
    assert torch.equal(ex.psi0(old, mu, Sigma), ex.psi0(new, mu, Sigma))


def test_product_intention_kernel_takes_the_shared_transition_path():
    """SharedTransition accepts ``alpha_1 RBF(x) * RBF(g)`` and matches predict_gaussian."""
    from hgpdm_torch.gp import GPPosterior
    from hgpdm_torch.inference.intention import SharedTransition

    gen = torch.Generator().manual_seed(8)
    kernel = ScaleKernel(intention_rbf(2, 1, 0.9, 0.7))
    kernel.outputscale = 0.8
    g = torch.randn(3, 1, generator=gen).repeat(4, 1)
    X = torch.cat([torch.randn(12, 2, generator=gen), g], 1)
    post = GPPosterior(kernel, X, torch.randn(12, 2, generator=gen), 0.05)
    values = torch.linspace(-1.0, 1.0, 4)[:, None]
    assert SharedTransition.supports(post, values)
    mu, Sigma = 0.3 * torch.randn(2, 2, generator=gen), random_cov(2, gen)[None].expand(2, 2, 2)
    mean, cov, cross = SharedTransition(post, values).moments(mu, Sigma)
    for k, v in enumerate(values):
        m, c, io = post.predict_gaussian(mu, Sigma, g=v.expand(2, 1), include_noise=True)
        torch.testing.assert_close(mean[:, k], m)
        torch.testing.assert_close(cov[:, k], c)
        torch.testing.assert_close(cross[:, k], io)
