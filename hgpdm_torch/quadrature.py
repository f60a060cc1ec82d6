r"""Kernel expectations under a Gaussian input by Gauss-Hermite quadrature, for any kernel.

:mod:`hgpdm_torch.expectations` has closed forms for the kernels it registers (RBF, linear,
their scales, sums and products). Any other gpytorch kernel (Matern, periodic, rational
quadratic, spectral mixture, polynomial, a user's own) becomes an opaque part of a leaf, and a
leaf with such a part is integrated here, at the nodes of a tensor-product Gauss-Hermite rule
for ``N(0, I_D)`` mapped onto the input Gaussian: ``x_s = mu + L xi_s`` with ``L L^T = Sigma``,
``x~_s = [x_s, g]`` with the known columns ``g`` appended, weights ``w_s`` summing to one::

    psi0     ~= sum_s w_s k(x~_s, x~_s)
    psi1_i   ~= sum_s w_s k(x~_s, X_i)
    E[dk/dx] ~= Sigma^-1 sum_s w_s (x_s - mu) k(x~_s, X_i)      (Stein's lemma)
    psi2_ij  ~= sum_s w_s k_a(x~_s, X_i) k_b(x~_s, X_j) = (U^T V)_ij,  U = w k_a, V = k_b  [S, N]

so ``psi2`` has rank at most S and moment matching contracts its factors without an ``N x N``
matrix per input (:func:`hgpdm_torch.moments.input_moments`), as it does a linear kernel's.
Every moment is that of one distribution, the weighted nodes: a kernel with an opaque part is
integrated as a whole by the rule (its RBF and linear leaves too,
:func:`~hgpdm_torch.expectations.split_terms`), and the expected gradient is Stein's form over
the same nodes, so the joint covariance of input and GP output is positive semi-definite
whatever the rule's error, which the filters' conditioning needs. The kernel is evaluated as a
matrix between the nodes and the training points (``kernel.forward(nodes, X)``: gpytorch forms
the distances by products; on pairs of rows an online filter's step took 4.6x as long);
``k(x, x)`` on pairs (``diag=True``), and at points (:func:`term_points` with ``grad``,
Gauss-Newton Jacobians) the gradient by autograd on pairs, each value with its own copy of the
point. Cost: docs/api/expectations.md#cost-of-the-quadrature.

Accuracy. With ``n`` points per dimension the rule integrates exactly every polynomial of degree
``<= 2n - 1`` in each coordinate. A kernel of length scale ``l`` at an input of standard deviation
``sigma`` is smooth on the scale of the nodes when ``sigma / l`` is small, and the error falls
fast with n there; where the input is wide against the length scale, ``psi2``'s products of two
kernels are the hardest part. The tests measure the error against Monte Carlo of the gpytorch
kernel itself (``tests/test_quadrature.py``); the docs' expectations page tabulates it. The rule's
size is ``n^D`` nodes; :func:`default_points` keeps it at most :data:`MAX_NODES`, and
:class:`hgpdm_torch.settings.quadrature_points` sets ``n`` for a block.

Shapes: ``S`` nodes, ``N`` training points, ``D`` Gaussian columns, ``Din`` all input columns.
"""

from __future__ import annotations

import contextlib
import threading
from collections.abc import Callable, Iterator
from functools import lru_cache
from typing import TYPE_CHECKING, Any

import numpy as np
import torch

from . import settings
from .linalg import psd_cholesky

if TYPE_CHECKING:  # the leaf and term types live with the closed forms
    from .expectations import Leaf, Term

__all__ = [
    "MAX_NODES",
    "default_points",
    "gauss_hermite",
    "leaf_diag",
    "leaf_matrix",
    "leaf_pairs",
    "leaf_psi0",
    "nodes",
    "num_nodes",
    "psi2_factors",
    "shared_evaluations",
    "term_points",
    "term_psi1_grad",
]

#: the most nodes :func:`default_points` gives a rule (``n^D``): 6 per dim at D = 3, 4 at D = 4
MAX_NODES = 256


def default_points(dim: int) -> int:
    """Points per dimension of the rule for ``dim`` Gaussian columns: the setting
    (:class:`~hgpdm_torch.settings.quadrature_points`) where one is in effect, else the most,
    up to 8, whose ``n^dim`` stays within :data:`MAX_NODES` (at least 2)."""
    chosen = settings.quadrature_points.get()
    if chosen is not None:
        return chosen
    n = 2
    while n < 8 and (n + 1) ** dim <= MAX_NODES:
        n += 1
    return n


@lru_cache(maxsize=32)
def _rule(dim: int, points: int) -> tuple[np.ndarray, np.ndarray]:
    x, w = np.polynomial.hermite_e.hermegauss(points)  # weight exp(-x^2 / 2)
    w = w / w.sum()
    grids = np.meshgrid(*([x] * dim), indexing="ij")
    weights = np.prod(np.meshgrid(*([w] * dim), indexing="ij"), axis=0)
    return np.stack([g.reshape(-1) for g in grids], -1), weights.reshape(-1)


def gauss_hermite(
    dim: int, points: int, *, dtype: torch.dtype = torch.float64, device: torch.device | None = None
) -> tuple[torch.Tensor, torch.Tensor]:
    """The tensor-product Gauss-Hermite rule for ``N(0, I_dim)``.

    Returns:
        ``nodes [points^dim, dim]`` and ``weights [points^dim]`` (summing to one).
    """
    for name, value, low in (("dim", dim, 1), ("points", points, 1)):
        if isinstance(value, bool) or not isinstance(value, int) or value < low:
            raise ValueError(f"{name} must be an int >= {low}, got {value!r}")
    x, w = _rule(dim, points)
    return (
        torch.as_tensor(x, dtype=dtype, device=device),
        torch.as_tensor(w, dtype=dtype, device=device),
    )


_memo = threading.local()


@contextlib.contextmanager
def shared_evaluations() -> Iterator[None]:
    """Within the block (this thread's), the rule's nodes on an input Gaussian and each term's
    values at them are computed once: :func:`hgpdm_torch.moments.input_moments` asks for psi1,
    its gradient and every psi2 pair of the same terms at the same inputs. Entries are matched by
    the identity of the objects they were computed from and dropped when the block ends."""
    if getattr(_memo, "table", None) is not None:  # an enclosing block shares its table
        yield
        return
    _memo.table = {}
    try:
        yield
    finally:
        _memo.table = None


def _once(sources: tuple[Any, ...], compute: Callable[[], Any]) -> Any:
    """``compute()``, or inside :func:`shared_evaluations` its earlier result for the same
    ``sources`` (the same objects: the table holds them, so their ids stay theirs)."""
    table = getattr(_memo, "table", None)
    if table is None:
        return compute()
    key = tuple(map(id, sources))
    hit = table.get(key)
    if hit is None or any(a is not b for a, b in zip(hit[0], sources, strict=True)):
        hit = table[key] = (sources, compute())
    return hit[1]


def _rule_on(
    mu: torch.Tensor, Sigma: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Nodes ``x [..., S, D]``, weights ``[S]``, standard nodes ``xi [S, D]`` and the factor
    ``L [..., D, D]`` of ``Sigma`` (:func:`~hgpdm_torch.linalg.psd_cholesky`: a singular one with
    a little jitter, which moves the nodes by far less than the kernel's scale)."""

    def compute() -> tuple[torch.Tensor, ...]:
        dim = mu.shape[-1]
        xi, w = gauss_hermite(dim, default_points(dim), dtype=mu.dtype, device=mu.device)
        L = psd_cholesky(Sigma, name="input covariance Sigma")
        return mu[..., None, :] + xi @ L.transpose(-1, -2), w, xi, L

    return _once((mu, Sigma), compute)


def nodes(mu: torch.Tensor, Sigma: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """The rule's nodes on ``N(mu, Sigma)``: ``x [..., S, D]`` and weights ``[S]``."""
    x, w, _, _ = _rule_on(mu, Sigma)
    return x, w


# --------------------------------------------------------------------------------------------
# Evaluating a leaf at pairs of points
# --------------------------------------------------------------------------------------------


def _part_pairs(part: Leaf, a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """One part of a leaf (no factors, no codes, unit coefficient) at pairs ``a, b [..., Din]``."""
    if part.kind == "rbf":
        return torch.exp(-0.5 * ((a - b).pow(2) * part.weight).sum(-1))
    if part.kind == "linear":
        return (a * b * part.weight).sum(-1)
    cols = list(part.columns)
    out = part.kernel.forward(a[..., cols], b[..., cols], diag=True)
    return out if isinstance(out, torch.Tensor) else out.to_dense()


def leaf_pairs(leaf: Leaf, a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """``k_leaf(a, b)`` for pairs of full input rows ``a, b [..., Din]`` (broadcast) -> ``[...]``:
    its coefficient, the product of its parts and the Kronecker deltas of its code columns."""
    shape = torch.broadcast_shapes(a.shape, b.shape)
    a, b = a.expand(shape), b.expand(shape)
    out = leaf.coef * _part_pairs(leaf, a, b)
    for part in leaf.factors:
        out = out * _part_pairs(part, a, b)
    for c in leaf.codes:
        out = out * (a[..., c] == b[..., c]).to(out.dtype)
    return out


def _part_matrix(part: Leaf, a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """One part of a leaf (no factors, no codes, unit coefficient) at every pair of rows of
    ``a [..., S, Din]`` and ``b [..., N, Din]`` (equal batch dims) -> ``[..., S, N]``."""
    if part.kind == "rbf":  # |a - b|^2 by one product, from a common centre (as gpytorch does)
        s = part.weight.clamp_min(0.0).sqrt()
        centre = b.mean(-2, keepdim=True)
        sa, sb = (a - centre) * s, (b - centre) * s
        d2 = sa.pow(2).sum(-1)[..., :, None] + sb.pow(2).sum(-1)[..., None, :] - 2 * sa @ sb.mT
        return torch.exp(-0.5 * d2.clamp_min(0.0))
    if part.kind == "linear":
        return (a * part.weight) @ b.mT
    cols = list(part.columns)
    out = part.kernel.forward(a[..., cols], b[..., cols])
    return out if isinstance(out, torch.Tensor) else out.to_dense()


def leaf_matrix(leaf: Leaf, a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """``k_leaf(a_s, b_i)`` for all rows ``a [..., S, Din]`` and ``b [..., N, Din]`` (batch dims
    broadcast) -> ``[..., S, N]``: the kernel's matrix evaluation (gpytorch forms its distances
    by products), without the ``[..., S, N, Din]`` differences of :func:`leaf_pairs`."""
    batch = torch.broadcast_shapes(a.shape[:-2], b.shape[:-2])
    a, b = a.expand(*batch, *a.shape[-2:]), b.expand(*batch, *b.shape[-2:])
    out = leaf.coef * _part_matrix(leaf, a, b)
    for part in leaf.factors:
        out = out * _part_matrix(part, a, b)
    for c in leaf.codes:
        out = out * (a[..., :, None, c] == b[..., None, :, c]).to(out.dtype)
    return out


def leaf_diag(leaf: Leaf, a: torch.Tensor) -> torch.Tensor:
    """``k_leaf(a, a)`` for rows ``a [..., Din]`` -> ``[...]``."""
    return leaf_pairs(leaf, a, a)


def _full(x: torch.Tensor, g: torch.Tensor | None) -> torch.Tensor:
    """Rows ``[x, g]`` of the Gaussian columns ``x [..., S, D]`` and known columns ``g``."""
    if g is None:
        return x
    g = g[..., None, :]
    batch = torch.broadcast_shapes(x.shape[:-1], g.shape[:-1])
    return torch.cat([x.expand(*batch, x.shape[-1]), g.expand(*batch, g.shape[-1])], -1)


def term_points(
    t: Term, x: torch.Tensor, X: torch.Tensor, *, grad: bool = False
) -> tuple[torch.Tensor, torch.Tensor | None]:
    """A quadrature term at points: ``k(x~_s, X~_i)`` ``[..., S, N]`` for ``x [..., S, D]`` and
    the training points' Gaussian columns ``X [..., N, D]`` (the term holds their known ones),
    and with ``grad`` its gradient in ``x`` ``[..., S, D, N]``."""
    if t.Xg is None:
        Xfull = X
    else:
        batch = torch.broadcast_shapes(X.shape[:-2], t.Xg.shape[:-2])
        n = X.shape[-2]
        Xfull = torch.cat([X.expand(*batch, n, -1), t.Xg.expand(*batch, n, -1)], -1)
    if not grad:
        return leaf_matrix(t.leaf, _full(x, t.g), Xfull), None
    a = _full(x, t.g)[..., :, None, :]  # [..., S, 1, Din]
    b = Xfull[..., None, :, :]  # [..., 1, N, Din]
    outer = torch.is_grad_enabled() and (x.requires_grad or any(
        p.requires_grad for p in (t.leaf.coef, Xfull)
    ))  # fmt: skip
    d = x.shape[-1]
    shape = torch.broadcast_shapes(a.shape, b.shape)
    with torch.enable_grad():
        head = a[..., :d].expand(*shape[:-1], d)
        head = head if head.requires_grad else head.detach().requires_grad_(True)
        rows = torch.cat([head, a[..., d:].expand(*shape[:-1], shape[-1] - d)], -1)
        k = leaf_pairs(t.leaf, rows, b)
        (dk,) = torch.autograd.grad(k.sum(), head, create_graph=outer)
    if not outer:
        k = k.detach()
    return k, dk.transpose(-1, -2)  # [..., S, N], [..., S, D, N]


def term_psi1_grad(
    t: Term, mu: torch.Tensor, Sigma: torch.Tensor, X: torch.Tensor, *, grad: bool = True
) -> tuple[torch.Tensor, torch.Tensor | None]:
    """``E[k(x~, X~_i)]`` ``[..., N]`` and with ``grad`` ``E[d k / dx]`` ``[..., D, N]``.

    The expected gradient is Stein's ``Sigma^-1 Cov[x, k] = L^-T sum_s w_s xi_s (k_s - psi1)``
    over the same nodes, not the rule applied to the kernel's gradient: the cross-covariance
    ``Sigma E[d k / dx]`` is then that of the nodes' distribution, like every other moment, and
    the joint covariance of input and output stays positive semi-definite whatever the rule's
    error (the filter conditions on it). Centring on ``psi1`` cancels the rounding of
    ``sum_s w_s xi_s = 0``; the kernel values' own rounding grows as ``eps |k| / sigma`` for an
    input standard deviation ``sigma`` (relative to the kernel's scale), so a nearly
    deterministic input (``sigma`` ~ 1e-8 or less) loses that many digits of the gradient.
    """
    x, w, xi, L = _rule_on(mu, Sigma)
    k = _values(t, x, X, lambda: term_points(t, x, X)[0])
    p1 = (w[:, None] * k).sum(-2)
    if not grad:
        return p1, None
    spread = xi.T @ (w[:, None] * (k - p1[..., None, :]))  # [..., D, N]
    return p1, torch.linalg.solve_triangular(L.transpose(-1, -2), spread, upper=True)


def psi2_factors(
    a: Term, b: Term, mu: torch.Tensor, Sigma: torch.Tensor, X: torch.Tensor, values
) -> tuple[torch.Tensor, torch.Tensor]:
    """``U = w k_a``, ``V = k_b`` ``[..., S, N]`` at the rule's nodes, ``psi2_ab ~= U^T V``;
    ``values(term, x, X)`` evaluates a term at points ``x [..., S, D]`` without its factor."""
    x, w = nodes(mu, Sigma)
    ka = _values(a, x, X, lambda: values(a, x, X))
    kb = ka if b is a else _values(b, x, X, lambda: values(b, x, X))
    return w[:, None] * ka, kb


def _values(t: Term, x: torch.Tensor, X: torch.Tensor, compute: Callable[[], Any]) -> Any:
    """A term's values ``[..., S, N]`` at the nodes ``x``, once per :func:`shared_evaluations`
    block."""
    return _once((t, x, X), compute)


def leaf_psi0(
    leaf: Leaf, mu: torch.Tensor, Sigma: torch.Tensor, g: torch.Tensor | None
) -> torch.Tensor:
    """``E[k(x~, x~)]`` of one leaf at ``x~ = [x, g]``, ``x ~ N(mu, Sigma)`` -> ``[...]``."""
    x, w = nodes(mu, Sigma)
    return (w * leaf_diag(leaf, _full(x, g))).sum(-1)


def num_nodes(dim: int) -> int:
    """S, the nodes of the rule for ``dim`` Gaussian columns in the current setting."""
    return default_points(dim) ** dim
