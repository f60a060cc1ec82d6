r"""Kernel expectations under a Gaussian input (the "psi statistics").

For an input ``x ~ N(mu, Sigma)`` with full covariance and training inputs ``X [N, Din]``::

    psi0 = E[k(x, x)]                       [...]
    psi1 = E[k(x, X)]                       [..., N]
    psi2 = E[k_a(x, X)^T k_b(x, X)]         [..., N, N]   (entry ij: E[k_a(x, X_i) k_b(x, X_j)])
    x_psi1 = E[x k(x, X)^T]                 [..., D, N]

These are the integrals behind the VB free energy (thesis App. 2.A: ``l``, ``Q``, ``R``) and the
moment-matching filter (Eq. 29-31 and the ``Q^x`` matrix of Sec. 3.3.1). Leading dims of ``mu``,
``Sigma``, ``X`` and ``g`` broadcast (streams B, intentions K, particles I).

Known trailing input columns. The Gaussian covers the first ``D`` input columns; the remaining
``Dg = Din - D`` columns may be passed as known values ``g [..., Dg]`` (a known intention, or the
integer code of a discrete intention, which can never be Gaussian). With ``g=None``, ``D = Din``:
a continuous intention that is uncertain and correlated with ``x`` is simply part of the Gaussian.

How it is organised (GPflow-style dispatch, on a normal form):

1. :func:`~hgpdm_torch.leaves.kernel_leaves` dispatches on the gpytorch kernel type
   (:mod:`hgpdm_torch.leaves`: ``RBFKernel`` ARD or not, ``LinearKernel``, ``ScaleKernel``,
   ``AdditiveKernel``, ``ProductKernel``, ``active_dims``, and our intention kernels; more by
   :func:`~hgpdm_torch.leaves.register_leaves`) and rewrites it as a sum of :class:`Leaf` terms
   over all input columns: ``coef * exp(-1/2 sum_c w_c (x_c - x'_c)^2)`` or
   ``coef * sum_c w_c x_c x'_c``, each times Kronecker deltas on code columns and, from a
   product, times linear factors (``Leaf.factors``). Any other kernel is an opaque leaf, and a
   leaf with an opaque part becomes one ``"quadrature"`` term, integrated at Gauss-Hermite nodes
   (:mod:`hgpdm_torch.quadrature`): Matern, periodic or a user's kernel work everywhere the
   closed forms do, to the rule's accuracy.
2. :func:`split_terms` splits every leaf into a part over the Gaussian columns times a per-training-
   point factor from the known columns (:class:`Term`): e.g. the tensor-product kernel
   ``exp(-|x - x_i|^2/2l_x^2) exp(-|g - g_i|^2/2l_g^2)`` becomes an RBF over ``x`` times the factor
   ``exp(-|g - g_i|^2/2l_g^2)``. The ``x`` part is therefore shared by all values of ``g``
   (docs/design/math.md#shared-work-across-intentions); a discrete kernel's delta is a 0/1 factor.
3. One function per quantity (:func:`term_psi1`, :func:`term_psi1_grad`, :func:`term_psi2`)
   dispatches on the term kinds ``"rbf"``, ``"linear"``, ``"const"``, ``"quadrature"`` (and
   pairs of kinds for psi2: a pair with a quadrature term has rank S, the rule's nodes).

Products (``ProductKernel``) distribute over the sums of their factors' leaves. Two RBF leaves
multiply into one RBF leaf with the summed precisions,
``exp(-1/2 sum_c a_c r_c^2) exp(-1/2 sum_c b_c r_c^2) = exp(-1/2 sum_c (a_c + b_c) r_c^2)``, on any
columns and under any input covariance, so e.g. ``RBF(x) * RBF(g)`` is exactly the ARD RBF over
``[x, g]`` with per-block length scales (the IDDM tensor product of Sec. 3.2.2). A product with a
linear leaf keeps the linear part as a factor: it has closed-form expectations when at most one of
its parts reads Gaussian columns, the others reading known columns only (``g``), where
``E[k_x(x, X_i) f(g, X_i)] = f(g, X_i) E[k_x(x, X_i)]`` (likewise psi2 with ``f_i f_j`` and the
gradients); a Gaussian input spanning two such parts raises.

Closed forms (``s = sqrt(w)`` elementwise, ``B = I + diag(s) Sigma diag(s)``, ``d_i = X_i - mu``):

- RBF psi1: ``coef |B|^{-1/2} exp(-1/2 (s d_i)^T B^{-1} (s d_i))`` (Eq. 30-31 with
  ``Omega = Sigma Lambda^{-1} + I``; ``|B| = |Omega|``; B stays well conditioned when a precision
  is zero, so unused columns and singular ``Sigma`` need no special case).
- ``E[d/dx k(x, X_i)] = psi1_i diag(s) B^{-1} (s d_i)``, so by Stein's lemma
  ``E[x k(x, X_i)] = mu psi1_i + Sigma E[d/dx k]`` (App. 2.A ``R_i``; the cross-covariance of Sec.
  3.3.1 is ``Sigma E[grad k] beta``).
- RBF x RBF with precisions ``w_a, w_b`` (``w = w_a + w_b``, ``u_i = w_a d_i / s``,
  ``v_j = w_b d_j / s``, ``C = I - B^{-1}``)::

      log psi2_ij = log(coef_a coef_b) - 1/2 log|B| - 1/2 d_i^T W_a d_i - 1/2 d_j^T W_b d_j
                    + 1/2 (u_i + v_j)^T C (u_i + v_j)

  (``Q_ij`` of Sec. 3.3.1 / App. 2.A, evaluated in log space so no factor underflows alone).
- Two independent Gaussian inputs (App. 2.B ``c12``): ``E[k(x1, x2)]`` is the RBF psi1 of the
  difference ``x1 - x2 ~ N(mu1 - mu2, Sigma1 + Sigma2)`` at 0, and ``mu1^T W mu2`` for a linear
  kernel (:func:`psi0_cross`).
- RBF x Linear: ``E[x k_a(x, X_i)]^T W_b X_j``; Linear x Linear:
  ``X_i^T W_a (Sigma + mu mu^T) W_b X_j``.

Every closed form is tested against Gauss-Hermite quadrature and Monte Carlo of the gpytorch
kernel itself.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, replace

import torch
from gpytorch.kernels import Kernel

from . import quadrature as quad
from .leaves import Leaf, kernel_leaves, register_leaves
from .linalg import cholesky_logdet, psd_cholesky
from .settings import validate_internal
from .validation import as_tensor

__all__ = [
    "Leaf",
    "Term",
    "check_gaussian",
    "kernel_leaves",
    "leaves_psi0",
    "psi0",
    "psi0_cross",
    "psi1",
    "psi2",
    "rbf_psi1_quadratic",
    "rbf_psi2_exponent",
    "rbf_psi2_quadratic",
    "register_leaves",
    "split_terms",
    "term_k",
    "term_psi1_grad",
    "term_psi1",
    "term_psi2",
    "term_psi2_factors",
    "x_psi1",
]


# --------------------------------------------------------------------------------------------
# 2. Leaves -> terms over the Gaussian columns times per-training-point factors
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Term:
    """A kernel term over the Gaussian columns, times a per-training-point factor.

    ``k_term(x, X_i) = factor_i * coef * base(x, X_i[:D])`` with base an RBF with precisions
    ``weight`` (``"rbf"``), ``sum_c weight_c x_c X_ic`` (``"linear"``) or 1 (``"const"``); a
    ``"quadrature"`` term is a whole opaque leaf ``k_leaf([x, g], X_i)``, which need not
    separate into Gaussian and known columns (:mod:`hgpdm_torch.quadrature`).

    Attributes:
        kind: ``"rbf"``, ``"linear"``, ``"const"`` or ``"quadrature"``.
        coef: scalar tensor (1 for quadrature: the leaf holds its own).
        weight: ``[D]`` precisions or variances over the Gaussian columns (unused for const;
            zeros for quadrature).
        factor: ``[..., N]`` factor from the known columns (``g``), or ``None`` for all ones.
        leaf: a quadrature term's leaf.
        g: ``[..., Dg]`` its known input columns, or ``None``.
        Xg: ``[..., N, Dg]`` the training points' known columns, or ``None``.
    """

    kind: str
    coef: torch.Tensor
    weight: torch.Tensor
    factor: torch.Tensor | None
    leaf: Leaf | None = None
    g: torch.Tensor | None = None
    Xg: torch.Tensor | None = None


def split_terms(
    leaves: Sequence[Leaf], train_inputs: torch.Tensor, g: torch.Tensor | None, dim: int
) -> list[Term]:
    """Split leaves into Gaussian-column terms and known-column factors.

    Args:
        leaves: from :func:`kernel_leaves`.
        train_inputs: ``[..., N, Din]`` training inputs.
        g: ``[..., Din - dim]`` known values of the trailing columns, or ``None`` when
            ``dim == Din``.
        dim: ``D``, the number of leading Gaussian columns.

    Returns:
        Terms with factors of shape ``[..., N]`` (batch of ``g`` and ``train_inputs``).

    A kernel with an opaque leaf (a kernel without closed forms) becomes one ``"quadrature"``
    term per leaf, its closed-form leaves included, so that all its moments come from one rule.
    A leaf with product factors (:attr:`Leaf.factors`) becomes the terms of its one part over
    the Gaussian columns (or of its first part when none is), each times the other parts'
    known-column factors: ``E[k_x(x, X_i) f(g, X_i)] = f(g, X_i) E[k_x(x, X_i)]``.

    Raises:
        ValueError: when a discrete code column lies among the Gaussian columns, or when two
            parts of a product (a linear factor and another part) both read Gaussian columns
            (the input covariance couples them; only RBF x RBF products are closed-form there).
    """
    terms: list[Term] = []
    whole = any(leaf.opaque for leaf in leaves)  # one rule for all: quadrature's docstring
    for leaf in leaves:
        if any(c < dim for c in leaf.codes):
            raise ValueError(
                "a discrete intention code column cannot be Gaussian: pass the code as the known "
                f"input g (code column {min(leaf.codes)} < Gaussian dim {dim})"
            )
        if whole:
            # without g the columns past dim are not read (e.g. a discrete block's code column)
            known = None if g is None else train_inputs[..., dim:]
            one = torch.ones_like(leaf.coef)
            terms.append(Term("quadrature", one, leaf.weight[:dim], None, leaf, g, known))
            continue
        parts = leaf.parts()
        if len(parts) == 1:
            terms += _split_leaf(leaf, train_inputs, g, dim)
            continue
        head = _gaussian_part(parts, dim)
        part_terms = _split_leaf(parts[head], train_inputs, g, dim)
        for i, part in enumerate(parts):
            if i != head:  # a part on known columns only: one const term, its factor
                (known,) = _split_leaf(part, train_inputs, g, dim)
                part_terms = [
                    replace(
                        t,
                        coef=t.coef * known.coef,
                        factor=known.factor if t.factor is None else t.factor * known.factor,
                    )
                    for t in part_terms
                ]
        terms += part_terms
    return terms


def _gaussian_part(parts: Sequence[Leaf], dim: int) -> int:
    """Index of the one part of a product leaf that reads Gaussian columns (0 if none).

    Raises:
        ValueError: two parts read Gaussian columns.
    """
    on_x = [i for i, p in enumerate(parts) if any(c < dim for c in p.cols)]
    if len(on_x) > 1:
        cols = sorted(c for i in on_x for c in parts[i].cols if c < dim)
        raise ValueError(
            "no closed-form expectation for a product kernel whose factors (a linear factor and "
            f"another) both read Gaussian input columns {cols}: the input covariance couples "
            "them. Only RBF x RBF products are exact there; pass the other factor's columns as "
            "the known input g"
        )
    return on_x[0] if on_x else 0


def _split_leaf(
    leaf: Leaf, train_inputs: torch.Tensor, g: torch.Tensor | None, dim: int
) -> list[Term]:
    """The terms of one leaf without product factors (see :func:`split_terms`)."""
    Xg = train_inputs[..., dim:]
    factor = None
    for c in leaf.codes:
        same = (g[..., c - dim, None] == Xg[..., c - dim]).to(Xg.dtype)
        factor = same if factor is None else factor * same
    wx, wg = leaf.weight[:dim], leaf.weight[dim:]
    on_x, on_g = any(c < dim for c in leaf.cols), any(c >= dim for c in leaf.cols)
    if leaf.kind == "rbf":
        if on_g:
            # exp(-1/2 sum_c w_c (g_c - X_ic)^2) for the known columns
            f = torch.exp(-0.5 * ((g[..., None, :] - Xg).pow(2) * wg).sum(-1))
            factor = f if factor is None else factor * f
        return [Term("rbf" if on_x else "const", leaf.coef, wx, factor)]
    terms: list[Term] = []
    if on_x:
        terms.append(Term("linear", leaf.coef, wx, factor))
    if on_g:
        f = (Xg * wg) @ g[..., :, None]
        f = f.squeeze(-1)
        terms.append(Term("const", leaf.coef, wx, f if factor is None else factor * f))
    return terms


def leaves_psi0(
    leaves: Sequence[Leaf], mu: torch.Tensor, Sigma: torch.Tensor, g: torch.Tensor | None
) -> torch.Tensor:
    """``E[k(x~, x~)]``, ``x~ = [x, g]``, from leaves; only ``diag(Sigma)`` matters. ``[...]``.

    An RBF part is 1 at ``x~ = x~'`` (``delta(g, g) = 1`` for code columns too), a linear part
    ``sum_c w_c E[x~_c^2]``; the parts of a product multiply (exact as at most one part reads
    Gaussian columns, :func:`split_terms`).
    """
    second = Sigma.diagonal(dim1=-2, dim2=-1) + mu.pow(2)  # E[x_c^2]
    if g is not None:
        batch = torch.broadcast_shapes(second.shape[:-1], g.shape[:-1])
        second = torch.cat(
            [second.expand(*batch, second.shape[-1]), g.pow(2).expand(*batch, g.shape[-1])], -1
        )
    out = torch.zeros(second.shape[:-1], dtype=mu.dtype, device=mu.device)
    whole = any(leaf.opaque for leaf in leaves)  # as split_terms: one rule for all
    for leaf in leaves:
        if whole:
            out = out + quad.leaf_psi0(leaf, mu, Sigma, g)
            continue
        parts = leaf.parts()
        if len(parts) > 1:
            _gaussian_part(parts, mu.shape[-1])
        value = leaf.coef
        for part in parts:
            if part.kind == "linear":  # callers may have cut the weights to the Gaussian columns
                value = value * (second * part.weight[: second.shape[-1]]).sum(-1)
        out = out + value
    return out


# --------------------------------------------------------------------------------------------
# 3. One function per quantity, dispatched on the term kinds
# --------------------------------------------------------------------------------------------


def _sqrt_weight(w: torch.Tensor) -> torch.Tensor:
    # sqrt with a finite gradient at w = 0 (unused columns)
    pos = w > 0
    return torch.where(pos, torch.where(pos, w, torch.ones_like(w)).sqrt(), torch.zeros_like(w))


def _rbf_factor(
    w: torch.Tensor, Sigma: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """``s = sqrt(w)``, Cholesky factor of ``B = I + diag(s) Sigma diag(s)`` and ``log|B|``."""
    s = _sqrt_weight(w)
    eye = torch.eye(w.shape[-1], dtype=Sigma.dtype, device=Sigma.device)
    B = eye + s[:, None] * Sigma * s[None, :]
    L = psd_cholesky(B, name="I + S^1/2 Sigma S^1/2")  # >= I up to roundoff in Sigma
    logdet = cholesky_logdet(L)
    return s, L, logdet


def rbf_psi1_quadratic(t: Term, Sigma: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """The RBF ``psi1`` as a quadratic form in the point's offset ``d = X - mu`` (module
    docstring's closed form): ``psi1_i = coef exp(d_i^T P d_i + c)`` with ``P = -S B^-1 S / 2``
    (``S = diag(s)``) and ``c = -log|B| / 2``; its gradient ``E[d/dx k(x, X_i)] = -2 psi1_i P
    d_i``. Shapes: ``Sigma [..., D, D]`` -> ``P [..., D, D]`` and ``c [...]``.
    """
    s, L, logdet = _rbf_factor(t.weight, Sigma)
    return -0.5 * s[..., :, None] * torch.cholesky_inverse(L) * s[..., None, :], -0.5 * logdet


def _rbf_psi1_parts(
    t: Term, mu: torch.Tensor, Sigma: torch.Tensor, X: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """``psi1 [..., N]`` and ``P d_i`` as ``[..., D, N]`` (:func:`rbf_psi1_quadratic`), the points
    along the last dim: the form's sum over D then runs over contiguous rows of N."""
    P, c = rbf_psi1_quadratic(t, Sigma)
    d = X.transpose(-1, -2) - mu[..., :, None]  # [..., D, N]
    Pd = P @ d
    return t.coef * torch.exp((Pd * d).sum(-2) + c[..., None]), Pd


def term_psi1(t: Term, mu: torch.Tensor, Sigma: torch.Tensor, X: torch.Tensor) -> torch.Tensor:
    """``coef E[base(x, X_i)]`` of one term, without its factor.

    Shapes: ``mu [..., D]``, ``Sigma [..., D, D]``, ``X [..., N, D]`` -> ``[..., N]``.
    """
    if t.kind == "rbf":
        return _rbf_psi1_parts(t, mu, Sigma, X)[0]
    if t.kind == "quadrature":
        return quad.term_psi1_grad(t, mu, Sigma, X, grad=False)[0]
    if t.kind == "linear":
        return t.coef * ((X * t.weight) @ mu[..., :, None]).squeeze(-1)
    return t.coef * torch.ones(X.shape[:-1], dtype=X.dtype, device=X.device)


def term_psi1_grad(
    t: Term, mu: torch.Tensor, Sigma: torch.Tensor, X: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """:func:`term_psi1` and ``coef E[d base(x, X_i) / dx]`` ``[..., D, N]`` of one term.

    By Stein's lemma ``Cov[x, k(x, X_i)] = Sigma E[grad k]``; the expected gradient also gives the
    covariance of any variable jointly Gaussian with ``x``.
    """
    if t.kind == "rbf":
        p1, Pd = _rbf_psi1_parts(t, mu, Sigma, X)
        return p1, -2.0 * p1[..., None, :] * Pd
    if t.kind == "quadrature":
        return quad.term_psi1_grad(t, mu, Sigma, X)
    p1 = term_psi1(t, mu, Sigma, X)
    if t.kind == "linear":
        return p1, t.coef * (X * t.weight).transpose(-1, -2)
    return p1, torch.zeros(X.shape[-1], X.shape[-2], dtype=X.dtype, device=X.device)


def term_k(
    t: Term, x: torch.Tensor, X: torch.Tensor, *, grad: bool = False
) -> tuple[torch.Tensor, torch.Tensor | None]:
    """``coef base(x, X_i)`` ``[..., N]`` at points ``x [..., D]`` (no factor), and with ``grad``
    its gradient in ``x`` ``[..., D, N]``.

    The ``Sigma = 0`` limit of :func:`term_psi1_grad` without its Cholesky factor and solves:
    the fast path for point evaluations (MAP states, Gauss-Newton Jacobians).
    """
    if t.kind == "quadrature":
        k, dk = quad.term_points(t, x[..., None, :], X, grad=grad)
        return k[..., 0, :], None if dk is None else dk[..., 0, :, :]
    if t.kind == "rbf":
        diff = X - x[..., None, :]  # [..., N, D]
        k = t.coef * torch.exp(-0.5 * (diff.pow(2) * t.weight).sum(-1))
        if not grad:
            return k, None
        return k, (diff * t.weight).transpose(-1, -2) * k[..., None, :]
    if t.kind == "linear":
        k = t.coef * ((X * t.weight) @ x[..., :, None]).squeeze(-1)
        return k, (t.coef * (X * t.weight).transpose(-1, -2)) if grad else None
    k = t.coef * torch.ones(X.shape[:-1], dtype=X.dtype, device=X.device)
    if not grad:
        return k, None
    return k, torch.zeros(X.shape[-1], X.shape[-2], dtype=X.dtype, device=X.device)


def _x_psi1(t: Term, mu: torch.Tensor, Sigma: torch.Tensor, X: torch.Tensor) -> torch.Tensor:
    """``coef E[x base(x, X_i)]`` of one term, ``[..., D, N]``."""
    p1, grad = term_psi1_grad(t, mu, Sigma, X)
    return mu[..., :, None] * p1[..., None, :] + Sigma @ grad


def rbf_psi2_quadratic(
    a: Term, b: Term, Sigma: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """The RBF x RBF ``log psi2`` as one quadratic form in the two points' offsets ``d = X - mu``
    (module docstring's closed form)::

        log psi2_ij = d_i^T H d_j + d_i^T M_a d_i + d_j^T M_b d_j + c

    with ``D_a = diag(w_a / s)``, ``D_b = diag(w_b / s)``, ``C = I - B^-1``: ``H = D_a C D_b``,
    ``M_a = (D_a C D_a - W_a) / 2``, ``M_b = (D_b C D_b - W_b) / 2`` and ``c = log(coef_a coef_b)
    - log|B| / 2``. Everything that depends on the input Gaussian but not on the points, so that
    the ``N``-sized work is the forms themselves (:func:`rbf_psi2_exponent` in torch, the compiled
    kernel of :mod:`hgpdm_torch.native` in registers).

    Shapes: ``Sigma [..., D, D]`` -> ``H``, ``M_a``, ``M_b`` ``[..., D, D]`` and ``c [...]``
    (``M_b`` is ``M_a`` where ``b is a``).
    """
    s, L, logdet = _rbf_factor(a.weight + b.weight, Sigma)
    inv_s = torch.where(s > 0, 1.0 / torch.where(s > 0, s, torch.ones_like(s)), torch.zeros_like(s))
    C = -torch.cholesky_inverse(L)  # I - B^{-1}, PSD with eigenvalues in [0, 1)
    C.diagonal(dim1=-2, dim2=-1).add_(1.0)
    da = a.weight * inv_s
    H_a = da[..., :, None] * C * da[..., None, :]
    M_a = 0.5 * (H_a - torch.diag_embed(a.weight))
    const = torch.log(a.coef * b.coef) - 0.5 * logdet
    if b is a:
        return H_a, M_a, M_a, const
    db = b.weight * inv_s
    M_b = 0.5 * (db[..., :, None] * C * db[..., None, :] - torch.diag_embed(b.weight))
    return da[..., :, None] * C * db[..., None, :], M_a, M_b, const


def rbf_psi2_exponent(
    a: Term,
    b: Term,
    mu: torch.Tensor,
    Sigma: torch.Tensor,
    X: torch.Tensor,
) -> tuple[torch.Tensor, torch.Tensor]:
    """The RBF x RBF ``psi2`` block as ``exp(left @ right)`` (:func:`rbf_psi2_quadratic`).

    Shapes: ``mu [..., D]``, ``Sigma [..., D, D]``, ``X [..., N, D]`` -> ``left [..., N, D+2]``
    and ``right [..., D+2, N]``: ``left_i = [d_i^T H, row_i, 1]``, ``right_j = [d_j; 1; col_j]``
    with ``row_i = d_i^T M_a d_i + c`` and ``col_j = d_j^T M_b d_j``, so ``(left @ right)_ij =
    log psi2_ij``: the whole exponent as one product with a small inner dimension, so that the
    ``N x N`` work is one matmul and one exponential, whether the block is stored
    (:func:`term_psi2`) or reduced tile by tile (:mod:`hgpdm_torch.tiling`). ``right`` is built
    contiguous (a transposed view makes the small-inner-dimension matmul 2-3x slower).
    """
    H, M_a, M_b, const = rbf_psi2_quadratic(a, b, Sigma)
    d = X - mu[..., None, :]  # [..., N, D]
    D = d.shape[-1]
    forms = [H, M_a] if M_b is M_a else [H, M_a, M_b]
    dF = d @ torch.cat(forms, -1)  # [..., N, 2D or 3D]: d^T H, d^T M_a (, d^T M_b)
    quad_a = (dF[..., D : 2 * D] * d).sum(-1)
    quad_b = quad_a if M_b is M_a else (dF[..., 2 * D :] * d).sum(-1)
    one = torch.ones_like(quad_a)
    left = torch.cat([dF[..., :D], (quad_a + const[..., None])[..., None], one[..., None]], -1)
    dT = d.transpose(-1, -2).expand(*quad_b.shape[:-1], D, -1)  # Sigma's batch dims too
    right = torch.cat([dT, one[..., None, :], quad_b[..., None, :]], -2)
    return left, right


def _psi2_rbf_rbf(a: Term, b: Term, mu: torch.Tensor, Sigma: torch.Tensor, X: torch.Tensor):
    left, right = rbf_psi2_exponent(a, b, mu, Sigma, X)
    return (left @ right).exp_()


def term_psi2_factors(
    a: Term, b: Term, mu: torch.Tensor, Sigma: torch.Tensor, X: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor, bool] | None:
    """Low-rank form of a psi2 block unless both terms are RBFs (then ``None``).

    Every pair involving a linear or constant term has rank ``r <= D``:
    ``psi2_ab = U^T V`` (``a_on_u=True``: U indexes a's points) or ``V^T U`` (``a_on_u=False``),
    where ``V [..., r, N]`` depends on the training inputs only. Rbf x Linear is
    ``E[x k_a(x, X_i)]^T W_b X_j``, Linear x Linear ``X_i^T W_a (Sigma + mu mu^T) W_b X_j``,
    Const x any ``coef_a psi1_b``. Moment matching uses the factors directly, so a linear
    measurement kernel never forms an ``N x N`` matrix per input (Eq. 33-35).

    Returns:
        ``(U [..., r, N], V [..., r, N], a_on_u)`` or ``None``.
    """
    if a.kind == "rbf" and b.kind == "rbf":
        return None
    if "quadrature" in (a.kind, b.kind):  # both at the rule's nodes: rank S
        U, V = quad.psi2_factors(a, b, mu, Sigma, X, _term_values)
        return U, V, True
    if b.kind == "linear":
        return _x_psi1(a, mu, Sigma, X), b.coef * (X * b.weight).transpose(-1, -2), True
    if a.kind == "linear":
        U, V, _ = term_psi2_factors(b, a, mu, Sigma, X)
        return U, V, False
    ones = torch.ones(1, X.shape[-2], dtype=X.dtype, device=X.device)
    if a.kind == "const":
        return term_psi1(b, mu, Sigma, X)[..., None, :], a.coef * ones, False
    return term_psi1(a, mu, Sigma, X)[..., None, :], b.coef * ones, True


def _term_values(t: Term, x: torch.Tensor, X: torch.Tensor) -> torch.Tensor:
    """A term without its factor at points ``x [..., S, D]`` against ``X [..., N, D]``:
    ``[..., S, N]`` (a constant term broadcasts along S)."""
    if t.kind == "quadrature":
        return quad.term_points(t, x, X)[0]
    return term_k(t, x, X[..., None, :, :])[0]


def term_psi2(
    a: Term, b: Term, mu: torch.Tensor, Sigma: torch.Tensor, X: torch.Tensor
) -> torch.Tensor:
    """``coef_a coef_b E[base_a(x, X_i) base_b(x, X_j)]`` without factors. ``[..., N, N]``."""
    factors = term_psi2_factors(a, b, mu, Sigma, X)
    if factors is None:
        return _psi2_rbf_rbf(a, b, mu, Sigma, X)
    U, V, a_on_u = factors
    return U.transpose(-1, -2) @ V if a_on_u else V.transpose(-1, -2) @ U


# --------------------------------------------------------------------------------------------
# Public quantities
# --------------------------------------------------------------------------------------------


def check_gaussian(
    mu: object, Sigma: object, name: str = "input"
) -> tuple[torch.Tensor, torch.Tensor]:
    """Validate a batch of Gaussians; return ``mu [..., D]`` and ``Sigma [..., D, D]``.

    Raises:
        ValueError: NaN/inf entries, mismatched shapes, an asymmetric or a non-PSD covariance
            (tolerance ``10 sqrt(eps)`` relative to the largest variance). The last two (an
            ``eigvalsh`` and a host synchronisation) are skipped for the state a hot loop
            passes between its steps (:func:`hgpdm_torch.settings.internal_step`) unless
            :class:`hgpdm_torch.settings.debug` is on.
    """
    mu = as_tensor(mu, f"{name} mean mu", min_ndim=1)
    Sigma = as_tensor(
        Sigma, f"{name} covariance Sigma", min_ndim=2, dtype=mu.dtype, device=mu.device
    )
    D = mu.shape[-1]
    if Sigma.shape[-2:] != (D, D):
        raise ValueError(
            f"{name} covariance Sigma must have trailing shape [{D}, {D}] to match mu [..., {D}], "
            f"got {tuple(Sigma.shape)}"
        )
    try:
        torch.broadcast_shapes(mu.shape[:-1], Sigma.shape[:-2])
    except RuntimeError as err:
        raise ValueError(
            f"{name} batch shapes of mu {tuple(mu.shape)} and Sigma {tuple(Sigma.shape)} do not "
            "broadcast"
        ) from err
    if not validate_internal():  # a hot loop's own state: checked under settings.debug only
        return mu, Sigma
    scale = Sigma.diagonal(dim1=-2, dim2=-1).abs().amax(-1).clamp_min(torch.finfo(mu.dtype).tiny)
    tol = 10.0 * torch.finfo(mu.dtype).eps ** 0.5 * scale
    if bool(((Sigma - Sigma.transpose(-1, -2)).abs().amax((-1, -2)) > tol).any()):
        raise ValueError(f"{name} covariance Sigma must be symmetric")
    eig_min = torch.linalg.eigvalsh(Sigma.detach()).amin(-1)
    if bool((eig_min < -tol.detach()).any()):
        raise ValueError(
            f"{name} covariance Sigma must be positive semi-definite; smallest eigenvalue "
            f"{float(eig_min.min()):.3g}"
        )
    return mu, Sigma


def _prepare(
    kernel: Kernel, mu: object, Sigma: object, X: object | None, g: object | None
) -> tuple[list[Leaf], torch.Tensor, torch.Tensor, torch.Tensor | None, torch.Tensor | None]:
    mu, Sigma = check_gaussian(mu, Sigma)
    D = mu.shape[-1]
    if g is not None:
        g = as_tensor(g, "g", min_ndim=1, dtype=mu.dtype, device=mu.device)
    din = D + (0 if g is None else g.shape[-1])
    if X is not None:
        X = as_tensor(X, "X", min_ndim=2, dtype=mu.dtype, device=mu.device)
        if X.shape[-1] != din:
            raise ValueError(
                f"X must have {din} columns (mu's {D} + g's {din - D}), got {tuple(X.shape)}"
            )
    return kernel_leaves(kernel, din), mu, Sigma, X, g


def psi0(kernel: Kernel, mu: object, Sigma: object, *, g: object | None = None) -> torch.Tensor:
    """``E[k(x~, x~)]`` with ``x~ = [x, g]``, ``x ~ N(mu, Sigma)``.

    Shapes: ``mu [..., D]``, ``Sigma [..., D, D]``, ``g [..., Dg]`` -> ``[...]``.
    """
    leaves, mu, Sigma, _, g = _prepare(kernel, mu, Sigma, None, g)
    return leaves_psi0(leaves, mu, Sigma, g)


def psi1(
    kernel: Kernel, mu: object, Sigma: object, X: object, *, g: object | None = None
) -> torch.Tensor:
    """``E[k([x, g], X)]`` (Eq. 29-31; App. 2.A vector ``l``).

    Shapes: ``mu [..., D]``, ``Sigma [..., D, D]``, ``X [..., N, D + Dg]``, ``g [..., Dg]``
    -> ``[..., N]``.
    """
    leaves, mu, Sigma, X, g = _prepare(kernel, mu, Sigma, X, g)
    D = mu.shape[-1]
    out = 0.0
    for t in split_terms(leaves, X, g, D):
        p = term_psi1(t, mu, Sigma, X[..., :D])
        out = out + (p if t.factor is None else t.factor * p)
    return out


def x_psi1(
    kernel: Kernel, mu: object, Sigma: object, X: object, *, g: object | None = None
) -> torch.Tensor:
    """``E[x k([x, g], X)^T]`` over the Gaussian columns (App. 2.A matrix ``R``).

    Shapes: ``mu [..., D]``, ``Sigma [..., D, D]``, ``X [..., N, D + Dg]``, ``g [..., Dg]``
    -> ``[..., D, N]``.
    """
    leaves, mu, Sigma, X, g = _prepare(kernel, mu, Sigma, X, g)
    D = mu.shape[-1]
    out = 0.0
    for t in split_terms(leaves, X, g, D):
        p = _x_psi1(t, mu, Sigma, X[..., :D])
        out = out + (p if t.factor is None else t.factor[..., None, :] * p)
    return out


def psi2(
    kernel: Kernel,
    mu: object,
    Sigma: object,
    X: object,
    *,
    g: object | None = None,
    kernel_b: Kernel | None = None,
) -> torch.Tensor:
    """``E[k_a([x, g], X)^T k_b([x, g], X)]`` (Sec. 3.3.1 ``Q^x``; App. 2.A ``Q`` and cross terms).

    Args:
        kernel: ``k_a``.
        mu: ``[..., D]`` input mean.
        Sigma: ``[..., D, D]`` input covariance.
        X: ``[..., N, D + Dg]`` training inputs.
        g: ``[..., Dg]`` known trailing input columns, or ``None``.
        kernel_b: ``k_b``; default ``k_a``. E.g. the two parts of a sum kernel.

    Returns:
        ``[..., N, N]`` with entry ``ij = E[k_a(x~, X_i) k_b(x~, X_j)]``.
    """
    leaves, mu, Sigma, X, g = _prepare(kernel, mu, Sigma, X, g)
    D = mu.shape[-1]
    leaves_b = leaves if kernel_b is None else kernel_leaves(kernel_b, X.shape[-1])
    terms_a, terms_b = split_terms(leaves, X, g, D), split_terms(leaves_b, X, g, D)
    out = 0.0
    for a in terms_a:
        for b in terms_b:
            q = term_psi2(a, b, mu, Sigma, X[..., :D])
            if a.factor is not None:
                q = a.factor[..., :, None] * q
            if b.factor is not None:
                q = q * b.factor[..., None, :]
            out = out + q
    return out


def psi0_cross(
    kernel: Kernel, mu1: object, Sigma1: object, mu2: object, Sigma2: object
) -> torch.Tensor:
    """``E[k(x1, x2)]`` for independent ``x1 ~ N(mu1, Sigma1)``, ``x2 ~ N(mu2, Sigma2)``.

    The expected prior covariance between GP outputs at two uncertain inputs (App. 2.B ``c12``).
    Discrete-code kernels are not supported (their codes are never Gaussian).

    Shapes: ``mu1, mu2 [..., D]``, ``Sigma1, Sigma2 [..., D, D]`` -> ``[...]``.
    """
    mu1, Sigma1 = check_gaussian(mu1, Sigma1, "first input")
    mu2, Sigma2 = check_gaussian(mu2, Sigma2, "second input")
    if mu1.shape[-1] != mu2.shape[-1]:
        raise ValueError(f"inputs must have the same dim, got {mu1.shape[-1]} and {mu2.shape[-1]}")
    leaves = kernel_leaves(kernel, mu1.shape[-1])
    if any(leaf.opaque for leaf in leaves):
        raise ValueError(
            "psi0_cross has closed forms only (RBF and linear kernels, their scales, sums and "
            "RBF products)"
        )
    if any(leaf.codes for leaf in leaves):
        raise ValueError("psi0_cross does not support discrete intention kernels")
    if any(leaf.factors for leaf in leaves):
        raise ValueError(
            "psi0_cross does not support products with a linear factor (only RBF x RBF products)"
        )
    out = 0.0
    for leaf in leaves:
        t = Term(leaf.kind, leaf.coef, leaf.weight, None)
        if leaf.kind == "rbf":  # the difference x1 - x2 is Gaussian; evaluate at 0
            p = term_psi1(t, mu1 - mu2, Sigma1 + Sigma2, torch.zeros_like(mu1)[..., None, :])
        else:
            p = term_psi1(t, mu1, Sigma1, mu2.to(mu1.dtype)[..., None, :])
        out = out + p[..., 0]
    return out
