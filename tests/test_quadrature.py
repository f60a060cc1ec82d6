"""Gaussian-input expectations of kernels without closed forms (hgpdm_torch.quadrature).

Oracles: the exact Gaussian moments of the rule's polynomials; the closed forms of
hgpdm_torch.expectations for an RBF kernel that hides its type (a subclass with its own
``forward``, so it takes the quadrature path); Monte Carlo of the gpytorch kernel itself for
Matern and periodic kernels; finite differences and gradcheck for gradients.
"""

from __future__ import annotations

import math

import pytest
import torch
from gpytorch.kernels import (
    LinearKernel,
    MaternKernel,
    PeriodicKernel,
    RBFKernel,
    ScaleKernel,
)

from hgpdm_torch import expectations as ex
from hgpdm_torch import quadrature, settings
from hgpdm_torch.leaves import Leaf, kernel_leaves, register_leaves

torch.set_default_dtype(torch.float64)


class OpaqueRBF(RBFKernel):
    """An RBF kernel whose own ``forward`` hides it from the closed forms."""

    def forward(self, x1, x2, diag=False, **params):
        return super().forward(x1, x2, diag=diag, **params)


def _gaussian(d: int, sd: float, seed: int = 0, batch: tuple[int, ...] = (3,)):
    gen = torch.Generator().manual_seed(seed)
    mu = 0.5 * torch.randn(*batch, d, generator=gen)
    a = torch.randn(*batch, d, d, generator=gen)
    Sigma = sd**2 * (a @ a.mT / d + 0.2 * torch.eye(d)) / 1.2
    return mu, Sigma


def _double_factorial_moment(k: int) -> float:
    return 0.0 if k % 2 else float(math.prod(range(k - 1, 0, -2)))


def test_rule_integrates_gaussian_moments_exactly():
    """n points per dim: every monomial of degree <= 2n - 1 per coordinate has its N(0, I)
    moment (products of (k-1)!!); the weights sum to one. Tolerance: a few ulp of the largest
    term, 15 * 3^... ~ 1e2, summed over 16 nodes."""
    xi, w = quadrature.gauss_hermite(2, 4)
    assert xi.shape == (16, 2) and w.shape == (16,)
    for a in range(8):
        for b in range(8):
            got = float((w * xi[:, 0] ** a * xi[:, 1] ** b).sum())
            want = _double_factorial_moment(a) * _double_factorial_moment(b)
            assert abs(got - want) <= 1e-12 * max(1.0, abs(want)), (a, b)
    # degree 2n = 8 is beyond it: the rule must miss E[x^8] = 105
    assert abs(float((w * xi[:, 0] ** 8).sum()) - 105.0) > 1.0
    with pytest.raises(ValueError, match="points"):
        quadrature.gauss_hermite(2, 0)


def test_dispatch_closed_forms_and_opaque_kernels():
    """Registered types (and subclasses keeping their forward) take the closed forms; a
    subclass with its own forward, or an unregistered kernel, is one opaque leaf; a closed form
    registered for a new type is used."""
    assert [lf.kind for lf in kernel_leaves(ScaleKernel(RBFKernel()), 2)] == ["rbf"]
    assert [lf.kind for lf in kernel_leaves(OpaqueRBF(), 2)] == ["kernel"]
    leaves = kernel_leaves(ScaleKernel(MaternKernel()) + LinearKernel(), 2)
    assert [lf.kind for lf in leaves] == ["kernel", "linear"]
    product = kernel_leaves(MaternKernel(active_dims=[0]) * RBFKernel(active_dims=[1]), 2)
    assert len(product) == 1 and product[0].opaque and product[0].factors[0].kind == "rbf"

    class Doubled(RBFKernel):
        def forward(self, x1, x2, diag=False, **params):
            return 2.0 * super().forward(x1, x2, diag=diag, **params)

    @register_leaves(Doubled)
    def _(kernel, cols, din):
        weight = torch.zeros(din)
        weight[cols] = kernel.lengthscale.reshape(-1).pow(-2)
        return [Leaf("rbf", torch.tensor(2.0), weight, frozenset(cols))]

    assert [lf.kind for lf in kernel_leaves(Doubled(), 2)] == ["rbf"]
    mu, Sigma = _gaussian(2, 0.4)
    X = torch.randn(5, 2, generator=torch.Generator().manual_seed(1))
    with torch.no_grad():
        closed = ex.psi1(Doubled(), mu, Sigma, X)
        torch.testing.assert_close(closed, 2.0 * ex.psi1(RBFKernel(), mu, Sigma, X))
    with pytest.raises(TypeError, match="Kernel subclass"):
        register_leaves(int)


@pytest.mark.parametrize("sd", [0.1, 0.3])
def test_opaque_rbf_equals_the_closed_forms(sd):
    """The whole quadrature path (nodes, pairwise evaluation, known columns, Stein gradient,
    rank-S psi2, psi0) on an RBF kernel against its closed forms, with a known column g and a
    sum with a linear kernel. Tolerance: the rule's error for a Gaussian integrand of width
    sd / l = 0.3 with 6 points per dim is below 1e-7 of the kernel's scale (measured 1e-9)."""
    d, n = 2, 7
    gen = torch.Generator().manual_seed(2)
    X = torch.randn(n, d + 1, generator=gen)
    g = torch.tensor([[0.3], [-0.2], [0.5]])
    mu, Sigma = _gaussian(d, sd)
    lengthscale = torch.tensor([[1.0, 1.4, 0.8]])

    def build(cls):
        k = cls(ard_num_dims=3)
        k.lengthscale = lengthscale
        s = ScaleKernel(k)
        s.outputscale = 0.7
        lin = LinearKernel(active_dims=[0, 1])
        lin.variance = 0.3
        return s + lin

    closed, opaque = build(RBFKernel), build(OpaqueRBF)
    assert any(lf.opaque for lf in kernel_leaves(opaque, 3))
    with torch.no_grad():
        for fn in (ex.psi0, ex.psi1, ex.x_psi1, ex.psi2):
            args = (mu, Sigma) if fn is ex.psi0 else (mu, Sigma, X)
            want, got = fn(closed, *args, g=g), fn(opaque, *args, g=g)
            torch.testing.assert_close(got, want, rtol=0, atol=1e-7, msg=fn.__name__)


def _mc(kernel, mu, Sigma, X, m=200_000, seed=0):
    gen = torch.Generator().manual_seed(seed)
    L = torch.linalg.cholesky(Sigma)
    xs = mu[..., None, :] + torch.randn(*mu.shape[:-1], m, mu.shape[-1], generator=gen) @ L.mT
    with torch.no_grad():
        kv = kernel(xs, X.expand(*mu.shape[:-1], *X.shape)).to_dense()  # [..., m, N]
    pairs = kv[..., :, None] * kv[..., None, :]
    centred = xs - mu[..., None, :]
    moments = {
        "psi1": kv,
        "psi2": pairs,
        "x_psi1": centred[..., :, None] * kv[..., None, :]
        + mu[..., None, :, None] * kv[..., None, :],
    }
    return {k: (v.mean(-3 if k != "psi1" else -2), v.std(-3 if k != "psi1" else -2) / math.sqrt(m))
            for k, v in moments.items()}  # fmt: skip


@pytest.mark.parametrize("name", ["matern52", "periodic"])
def test_matern_and_periodic_agree_with_monte_carlo(name):
    """psi1, x_psi1 and psi2 of a Matern-5/2 and a periodic kernel at input sd 0.3 l (D = 2)
    against 2e5 Monte-Carlo draws of the gpytorch kernel: within the rule's documented error at
    that width (docs/api/expectations.md: 1e-3 for psi1, 1e-2 for psi2 of a unit-scale kernel)
    plus 5 Monte-Carlo standard errors."""
    if name == "matern52":
        kernel = MaternKernel(nu=2.5)
        kernel.lengthscale = 1.0
    else:
        kernel = PeriodicKernel()
        kernel.lengthscale, kernel.period_length = 1.0, 2.0
    mu, Sigma = _gaussian(2, 0.3, seed=4, batch=(2,))
    X = torch.randn(6, 2, generator=torch.Generator().manual_seed(5))
    mc = _mc(kernel, mu, Sigma, X)
    bound = {"psi1": 1e-3, "x_psi1": 1e-3, "psi2": 1e-2}
    with torch.no_grad():
        for key, fn in (("psi1", ex.psi1), ("x_psi1", ex.x_psi1), ("psi2", ex.psi2)):
            mean, se = mc[key]
            err = (fn(kernel, mu, Sigma, X) - mean).abs()
            assert bool((err <= bound[key] + 5 * se).all()), (key, float(err.max()))


def test_joint_of_input_and_output_stays_positive_semidefinite():
    """A periodic measurement GP at inputs wide against its period, where the rule is off by
    ~10%: the joint covariance of (x, f(x)) from predict_gaussian is still that of the nodes'
    distribution, so positive semi-definite (smallest eigenvalue above -1e-9 of the largest)."""
    from hgpdm_torch.gp import GPPosterior

    gen = torch.Generator().manual_seed(6)
    X = torch.randn(25, 2, generator=gen)
    kernel = ScaleKernel(PeriodicKernel()) + ScaleKernel(RBFKernel())
    Y = torch.sin(3 * X[:, :1]) + 0.05 * torch.randn(25, 3, generator=gen)
    post = GPPosterior(kernel, X, Y, 1e-4)
    mu, Sigma = _gaussian(2, 1.2, seed=7, batch=(4,))
    with torch.no_grad():
        mean, cov, cross = post.predict_gaussian(mu, Sigma, include_noise=False)
    joint = torch.cat([torch.cat([Sigma, cross], -1), torch.cat([cross.mT, cov], -1)], -2)
    eig = torch.linalg.eigvalsh(joint)
    assert bool((eig[..., 0] >= -1e-9 * eig[..., -1]).all()), eig[..., 0]


def test_gradients_of_the_quadrature():
    """gradcheck of psi1 and psi2 (through nodes, kernel and Stein) in mu and Sigma's factor,
    and the point gradient of term_k (autograd on pairs) against the RBF closed form."""
    kernel = MaternKernel(nu=2.5)
    X = torch.randn(4, 2, generator=torch.Generator().manual_seed(8))
    mu, Sigma = _gaussian(2, 0.4, batch=(2,))
    A = torch.linalg.cholesky(Sigma).requires_grad_(True)
    mu = mu.clone().requires_grad_(True)
    with settings.quadrature_points(3):
        assert torch.autograd.gradcheck(
            lambda m, a: ex.psi1(kernel, m, a @ a.mT, X), (mu, A), atol=1e-6
        )
        assert torch.autograd.gradcheck(
            lambda m, a: ex.psi2(kernel, m, a @ a.mT, X), (mu, A), atol=1e-6
        )
    (opaque,) = ex.split_terms(kernel_leaves(OpaqueRBF(), 2), X, None, 2)
    (closed,) = ex.split_terms(kernel_leaves(RBFKernel(), 2), X, None, 2)
    x = torch.randn(3, 2, generator=torch.Generator().manual_seed(9))
    k1, d1 = ex.term_k(opaque, x, X, grad=True)
    k2, d2 = ex.term_k(closed, x, X, grad=True)
    torch.testing.assert_close(k1, k2)
    torch.testing.assert_close(d1, d2)


def test_settings_choose_the_rule():
    assert quadrature.default_points(3) == 6 and quadrature.num_nodes(3) == 216
    assert quadrature.default_points(1) == 8 and quadrature.num_nodes(5) <= quadrature.MAX_NODES
    with settings.quadrature_points(2):
        assert quadrature.num_nodes(3) == 8
        snap = settings.snapshot()
    assert snap.quadrature == 2 and settings.quadrature_points.get() is None
    with snap.applied():
        assert settings.quadrature_points.get() == 2
    with pytest.raises(ValueError, match="positive int"):
        settings.quadrature_points(0)


def test_matrix_and_pairwise_evaluations_agree():
    """The node-by-point matrix (values) and the pairwise rows (k(x, x), gradients) of one leaf
    with an opaque part, RBF and linear factors and a code column: equal to rounding of O(1)
    values (the RBF part's distances are formed by products in one, by differences in the
    other)."""
    from hgpdm_torch.kernels import DiscreteIntentionKernel

    kernel = DiscreteIntentionKernel(
        MaternKernel(nu=1.5, active_dims=[0, 1]) * RBFKernel(active_dims=[1])
        * LinearKernel(active_dims=[0]),
        num_values=3,
    )  # fmt: skip
    (leaf,) = kernel_leaves(kernel, 3)
    assert leaf.opaque and leaf.codes == (2,)
    gen = torch.Generator().manual_seed(10)
    a = torch.cat(
        [torch.randn(2, 5, 2, generator=gen), torch.randint(3, (2, 5, 1), generator=gen)], -1
    )
    b = torch.cat([torch.randn(7, 2, generator=gen), torch.randint(3, (7, 1), generator=gen)], -1)
    with torch.no_grad():
        matrix = quadrature.leaf_matrix(leaf, a, b)
        pairs = quadrature.leaf_pairs(leaf, a[..., :, None, :], b[None, None])
    assert matrix.shape == (2, 5, 7)
    torch.testing.assert_close(matrix, pairs, rtol=1e-12, atol=1e-12)
    assert bool((matrix[a[..., 2:3].expand(-1, -1, 7) != b[:, 2]] == 0).all())


def test_one_moment_call_evaluates_each_term_once():
    """input_moments asks for psi1, its gradient and psi2 of the same opaque term: its kernel
    runs once at the nodes (shared_evaluations), and again in a new call."""
    from hgpdm_torch.moments import input_moments

    calls = []

    class Counted(MaternKernel):
        def forward(self, x1, x2, diag=False, **params):
            calls.append(diag)
            return super().forward(x1, x2, diag=diag, **params)

    X = torch.randn(6, 2, generator=torch.Generator().manual_seed(11))
    terms = ex.split_terms(kernel_leaves(Counted(nu=2.5), 2), X, None, 2)
    mu, Sigma = _gaussian(2, 0.3)
    beta = torch.randn(6, 3, generator=torch.Generator().manual_seed(12))
    with torch.no_grad():
        first = input_moments(terms, mu, Sigma, X, beta, torch.eye(6))
        assert calls == [False]
        with settings.quadrature_points(quadrature.default_points(2)):  # the same rule, anew
            again = input_moments(terms, mu, Sigma, X, beta, torch.eye(6))
    assert calls == [False, False]
    for a, b in zip(first, again, strict=True):
        torch.testing.assert_close(a, b, rtol=0, atol=0)
