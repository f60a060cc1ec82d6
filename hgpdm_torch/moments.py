r"""Moments of a GP's output at Gaussian inputs, from the kernel expectations.

:func:`input_moments` sums, over the kernel's terms and term pairs, what moment matching
(:meth:`GPPosterior.predict_gaussian <hgpdm_torch.gp.GPPosterior.predict_gaussian>`, Sec. 3.3.1)
and the VB free energy (App. 2.A) need of ``psi1``, ``E[d k / dx]`` and ``psi2``: ``psi1 beta``,
``beta^T psi2 beta``, ``tr(K^-1 psi2)`` and ``E[d f / dx]``. Pairs with a linear or constant term
have rank ``<= D`` and never form an ``N x N`` matrix. An RBF x RBF pair needs ``psi2``, ``N x N``
per input Gaussian, which is reduced on one of two paths
(:class:`~hgpdm_torch.settings.moment_path`):

- ``"fused"`` (default, :func:`_fused_pair`): ``psi2 = exp(left @ right)``
  (:func:`~hgpdm_torch.expectations.rbf_psi2_exponent`) is evaluated for one tile of input
  Gaussians at a time (:mod:`hgpdm_torch.tiling`: a few on a CPU, hundreds on a GPU) and reduced
  before the next; under autograd the tiles are kept for the backward pass up to
  :data:`~hgpdm_torch.tiling.KEEP_FOR_BACKWARD_BYTES` in all, and beyond it each is recomputed
  there (``torch.utils.checkpoint``), so neither pass holds more than that;
- ``"materialised"`` (:func:`_materialised_pair`): the earlier path, kept for comparison.

Both reduce each block with the same :func:`_contract`; they differ by rounding only: the
exponential's last bits where the fused path takes NumPy's (:func:`~hgpdm_torch.tiling.exp_`),
and the BLAS kernels that other batch shapes take.

Shapes: ``N`` training points, ``D`` Gaussian input dims, ``Dout`` outputs; ``...`` batch.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import NamedTuple

import torch

from . import settings
from .expectations import (
    Term,
    rbf_psi2_exponent,
    term_psi1,
    term_psi1_grad,
    term_psi2,
    term_psi2_factors,
)
from .linalg import shared_matmul
from .quadrature import num_nodes, shared_evaluations
from .tiling import OpCount, differentiable_tile, exp_, keeps_tiles, tile_budget

__all__ = ["input_moments", "input_operations", "pair_operations"]


@shared_evaluations()  # a quadrature term's values at the nodes serve psi1 and every psi2 pair
def input_moments(
    terms: list[Term],
    mu: torch.Tensor,
    Sigma: torch.Tensor,
    X: torch.Tensor,
    beta: torch.Tensor,
    kinv: torch.Tensor | None,
    *,
    diagonal: bool = False,
    grad: bool = True,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor | None, torch.Tensor | None]:
    """``psi1 beta``, ``beta^T psi2 beta``, ``tr(K^-1 psi2)`` and ``E[d f / dx]``.

    Shapes: ``X [..., N, D]``, ``beta [..., N, Dout]``, ``kinv [..., N, N]`` -> ``[..., Dout]``,
    ``[..., Dout, Dout]``, ``[...]``, ``[..., D, Dout]``. ``psi2`` is summed over term pairs
    without forming it per intention: factors rescale ``beta`` (``shared_matmul``), and pairs
    with a linear or constant term use their rank ``<= D`` factors (no ``N x N`` matrix).

    With ``diagonal=True`` the second moment is only its diagonal ``[..., Dout]`` (the free
    energy's ``E[m_d(x)^2]``); ``kinv=None`` skips the trace (returned as ``None``) and
    ``grad=False`` the expected gradient.
    """
    reduce_pair = _fused_pair if settings.moment_path.get() == "fused" else _materialised_pair
    ones = torch.ones(X.shape[-2], dtype=X.dtype, device=X.device)
    factors = [ones if t.factor is None else t.factor for t in terms]
    fbeta = [f[..., None] * beta for f in factors]  # [..., N, Dout]
    mean, gradient = 0.0, 0.0
    for t, fb in zip(terms, fbeta, strict=True):
        if grad:
            p1, gr = term_psi1_grad(t, mu, Sigma, X)
            gradient = gradient + shared_matmul(gr, fb)
        else:
            p1 = term_psi1(t, mu, Sigma, X)
        mean = mean + shared_matmul(p1[..., None, :], fb)[..., 0, :]

    def pair(left: torch.Tensor, right: torch.Tensor) -> torch.Tensor:
        """``left^T right`` over the points: ``[..., Dout, Dout]`` or its diagonal."""
        return (left * right).sum(-2) if diagonal else left.transpose(-1, -2) @ right

    second, trace = 0.0, 0.0
    for i, (a, fa, fba) in enumerate(zip(terms, factors, fbeta, strict=True)):
        for j in range(i, len(terms)):
            b, fb, fbb = terms[j], factors[j], fbeta[j]
            low_rank = term_psi2_factors(a, b, mu, Sigma, X)
            tr = None
            if low_rank is None:  # RBF x RBF: one N x N matrix per input Gaussian
                m, tr = reduce_pair(_Pair(a, b, mu, Sigma, X, (fa, fba, fb, fbb), kinv, pair))
            else:  # psi2 = U^T V of rank <= D: no N x N matrix per input
                U, V, a_on_u = low_rank
                (fu, fbu), (fv, fbv) = ((fa, fba), (fb, fbb)) if a_on_u else ((fb, fbb), (fa, fba))
                mu_u, mu_v = shared_matmul(U, fbu), shared_matmul(V, fbv)  # [..., r, Dout]
                m = pair(mu_u, mu_v) if a_on_u else pair(mu_v, mu_u)
                if kinv is not None:
                    vk = (V * fv[..., None, :]) @ kinv  # [..., r, N]; constant when fv is
                    tr = (U * fu[..., None, :] * vk).sum((-1, -2))
            if j > i:  # the (j, i) pair is the transpose
                m = m + (m if diagonal else m.transpose(-1, -2))
                tr = None if tr is None else 2.0 * tr
            second = second + m
            trace = None if tr is None else trace + tr
    return mean, second, trace, gradient if grad else None


# psi2 entries per chunk of input Gaussians on the materialised path (16 MB in float64): the
# N x N matrices are built, exponentiated and reduced while they are in cache instead of
# streaming a [..., N, N] batch of hundreds of MB through memory several times (with the
# contiguous factors of rbf_psi2_exponent, 1.8x faster on Weird Walking's VB forecasts, 2 cores)
_PSI2_CHUNK = 2**21


class _Pair(NamedTuple):
    """An RBF x RBF term pair of :func:`input_moments` and what its reduction reads: the input
    Gaussians ``mu``, ``Sigma``, the points ``X``, the weights ``(fa, fa beta, fb, fb beta)``,
    ``K^-1`` (or ``None``: no trace) and ``pair``, the product of two weighted sums."""

    a: Term
    b: Term
    mu: torch.Tensor
    Sigma: torch.Tensor
    X: torch.Tensor
    weights: tuple[torch.Tensor, ...]
    kinv: torch.Tensor | None
    pair: Callable[[torch.Tensor, torch.Tensor], torch.Tensor]


def _materialised_pair(p: _Pair) -> tuple[torch.Tensor, torch.Tensor | None]:
    """The RBF x RBF term pair of :func:`input_moments` on the materialised path
    (:class:`~hgpdm_torch.settings.moment_path`): ``pair(fa beta, psi2 fb beta)`` and
    ``fa^T (psi2 * K^-1) fb`` (``None`` without ``kinv``), with ``psi2`` formed for a chunk of
    input Gaussians when the training side (``X``, ``weights = (fa, fa beta, fb, fb beta)``,
    ``kinv``) has no batch dims, else for all of them at once."""
    a, b, mu, Sigma, X, weights, kinv, pair = p
    fa, fba, fb, fbb = weights

    def reduce(mu_c: torch.Tensor, Sigma_c: torch.Tensor, X_c: torch.Tensor, *w: torch.Tensor):
        fa_c, fba_c, fb_c, fbb_c, *k = w
        q = term_psi2(a, b, mu_c, Sigma_c, X_c)
        return _contract(q, pair, fa_c, fba_c, fb_c, fbb_c, k[0] if k else None)

    n, d = X.shape[-2:]
    rows = [X, fba, fbb] + ([] if kinv is None else [kinv])  # [..., N, .]
    if any(math.prod(t.shape[:-2]) > 1 for t in rows) or fa.dim() > 1 or fb.dim() > 1:
        return reduce(mu, Sigma, X, *weights, *([] if kinv is None else [kinv]))
    batch = torch.broadcast_shapes(mu.shape[:-1], Sigma.shape[:-2], X.shape[:-2])
    flat_mu = mu.expand(*batch, d).reshape(-1, d)
    flat_S = Sigma.expand(*batch, d, d).reshape(-1, d, d)
    flat = [X.reshape(n, d), fa, fba.reshape(n, -1), fb, fbb.reshape(n, -1)]
    flat += [] if kinv is None else [kinv.reshape(n, n)]
    size = max(1, _PSI2_CHUNK // (n * n))
    parts = [
        reduce(flat_mu[i : i + size], flat_S[i : i + size], *flat)
        for i in range(0, flat_mu.shape[0], size)
    ]
    m = torch.cat([p[0] for p in parts]).reshape(*batch, *parts[0][0].shape[1:])
    tr = None if kinv is None else torch.cat([p[1] for p in parts]).reshape(batch)
    return m, tr


def _contract(
    q: torch.Tensor,
    pair: Callable[[torch.Tensor, torch.Tensor], torch.Tensor],
    fa: torch.Tensor,
    fba: torch.Tensor,
    fb: torch.Tensor,
    fbb: torch.Tensor,
    kinv: torch.Tensor | None,
) -> tuple[torch.Tensor, torch.Tensor | None]:
    """``pair(fa beta, psi2 fb beta)`` and ``fa^T (psi2 * K^-1) fb`` (``None`` without ``kinv``)
    of a ``psi2`` block ``q [..., N, N]``, which is overwritten by ``psi2 * K^-1`` unless it
    needs gradients (both paths' reduction of an RBF x RBF pair)."""
    m = pair(fba, shared_matmul(q, fbb))
    if kinv is None:
        return m, None
    qk = q * kinv if q.requires_grad else q.mul_(kinv)
    return m, (fa * shared_matmul(qk, fb[..., None])[..., 0]).sum(-1)


def _fused_pair(p: _Pair) -> tuple[torch.Tensor, torch.Tensor | None]:
    """The RBF x RBF term pair of :func:`input_moments` on the fused path: what
    :func:`_materialised_pair` gives, with ``psi2`` evaluated and reduced one tile of input
    Gaussians at a time.

    The tiles run along the batch dims in which the input Gaussians differ (streams, windows,
    intentions with their own inputs), outermost first: as many along the first as the tile
    budget (:func:`~hgpdm_torch.tiling.tile_budget`) allows with the inner dims whole, and where
    even one slice of it is over the budget, one at a time and tiled along the next dim. Dims
    along which only the weights differ (K intentions sharing an input, whose factors rescale
    the weights) stay whole inside a tile. ``left`` and ``right`` (``O(N D)`` per input) are
    computed once for all.
    """
    a, b, mu, Sigma, X, weights, kinv, pair = p
    fa, fba, fb, fbb = weights
    left, right = rbf_psi2_exponent(a, b, mu, Sigma, X)
    n = X.shape[-2]
    parts = [left, right, fa[..., None], fba, fb[..., None], fbb]
    parts += [] if kinv is None else [kinv]
    nb = max(p.dim() - 2 for p in parts)
    parts = [p.reshape((1,) * (nb + 2 - p.dim()) + p.shape) for p in parts]
    grad = torch.is_grad_enabled() and any(p.requires_grad for p in parts)
    budget = tile_budget(left.device) // left.dtype.itemsize  # psi2 entries per tile
    keep = keeps_tiles(n * n * math.prod(left.shape[:-2]), left.dtype)

    def reduce(left_t, right_t, fa_t, fba_t, fb_t, fbb_t, *k):
        q = left_t @ right_t
        q = q.exp() if grad else exp_(q)
        return _contract(q, pair, fa_t[..., 0], fba_t, fb_t[..., 0], fbb_t, k[0] if k else None)

    def tile(*t: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor | None]:
        return differentiable_tile(reduce, *t, keep=keep) if grad else reduce(*t)

    def tiled(t: list[torch.Tensor], start: int) -> tuple[torch.Tensor, torch.Tensor | None]:
        inputs = t[0].shape[:-2]  # the input Gaussians' batch (left's)
        along = next((i for i in range(start, nb) if inputs[i] > 1), None)
        if along is None or n * n * math.prod(inputs) <= budget:
            return tile(*t)
        inner = n * n * math.prod(inputs[along + 1 :])  # psi2 entries of one slice
        size = max(1, budget // inner)
        out = []
        for i in range(0, inputs[along], size):
            part = [p if p.shape[along] == 1 else p.narrow(along, i, min(size, p.shape[along] - i))
                    for p in t]  # fmt: skip
            out.append(tile(*part) if inner <= budget else tiled(part, along + 1))
        m = torch.cat([o[0] for o in out], along)
        return m, None if kinv is None else torch.cat([o[1] for o in out], along)

    return tiled(parts, 0)


def pair_operations(
    n: int, d: int, dout: int, *, sets: int = 1, diagonal: bool = False, trace: bool = True
) -> OpCount:
    """Work of one RBF x RBF term pair of :func:`input_moments` for one input Gaussian.

    ``N^2`` exponentials; multiply-adds: ``N D^2`` for the exponent's factors, ``N^2 (D + 2)``
    for the exponent, ``N^2 S Dout`` for ``psi2 (f beta)`` with ``S`` weight sets sharing the
    input (K intentions), ``N S Dout^2`` for the pair (``N S Dout`` with ``diagonal``), and with
    ``trace`` ``N^2`` for the product with ``K^-1`` and ``N^2 S`` for its contraction.
    """
    madds = n * d * d + n * n * (d + 2) + n * n * sets * dout
    madds += n * sets * (dout if diagonal else dout * dout)
    if trace:
        madds += n * n * (1 + sets)
    return OpCount(exps=n * n, madds=madds)


def input_operations(
    terms: list[Term],
    n: int,
    dout: int,
    *,
    sets: int = 1,
    diagonal: bool = False,
    trace: bool = True,
    grad: bool = True,
    inputs: int = 1,
) -> OpCount:
    """Work of :func:`input_moments` for one input Gaussian, in the loops it runs.

    Per term: ``psi1`` (for an RBF ``N`` exponentials and ``N D^2`` multiply-adds to whiten the
    inputs, with ``grad`` ``N D^2`` more for ``E[d k / dx]``; ``N D`` for a linear term; for a
    quadrature term ``Q N`` kernel values at its Q nodes, counted as an exponential and ``Din``
    multiply-adds each, three times that with the gradient), contracted with ``S`` weight sets
    (``N S Dout``, times ``D + 1`` with the gradient). Per term pair: an RBF x RBF pair
    :func:`pair_operations`; a low-rank pair of rank ``r`` (``D``, 1 with a constant term, Q
    with a quadrature term) ``2 r N S Dout`` for the two projections, ``r S Dout^2`` for the
    pair and with ``trace`` ``r N S`` against ``K^-1``, plus its ``r N^2 S`` product with
    ``K^-1``, which one call does once for all its ``inputs`` Gaussians (counted here as a
    share). ``D``
    is the terms' Gaussian dim (their ``weight``).
    """
    ops = OpCount()
    for t in terms:
        d = t.weight.shape[-1]
        if t.kind == "rbf":  # whitening solve (and with grad its Cholesky solve), N exps
            ops = ops + OpCount(exps=n, madds=n * d * d * (1 + int(grad)))
        elif t.kind == "quadrature":  # S N kernel values, each about an exp and Din madds
            s, din = num_nodes(d), d + (0 if t.g is None else t.g.shape[-1])
            ops = ops + OpCount(exps=s * n, madds=s * n * din * (1 + 2 * int(grad)))
        elif t.kind == "linear":
            ops = ops + OpCount(madds=n * d)
        ops = ops + OpCount(madds=n * sets * dout * (1 + d * int(grad)))  # against the weights
    for i, a in enumerate(terms):
        for b in terms[i:]:
            d = a.weight.shape[-1]
            if a.kind == "rbf" and b.kind == "rbf":
                ops = ops + pair_operations(n, d, dout, sets=sets, diagonal=diagonal, trace=trace)
                continue
            if "quadrature" in (a.kind, b.kind):
                r = num_nodes(d)
            else:
                r = 1 if "const" in (a.kind, b.kind) else d
            madds = 2 * r * n * sets * dout + r * sets * (dout if diagonal else dout * dout)
            shared = r * n * n * sets / inputs  # V K^-1: once per call, for all its inputs
            ops = ops + OpCount(madds=madds + (shared + r * n * sets if trace else 0))
    return ops
