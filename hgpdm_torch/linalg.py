"""Numerically careful linear algebra shared by every GP routine.

All GP code in the toolkit factorises covariance matrices through :func:`psd_cholesky`, which adds
jitter in escalating steps and raises a clear error when the matrix still is not positive
definite. Log-determinants come from the Cholesky diagonal (:func:`cholesky_logdet`) and solves
use ``torch.cholesky_solve``; no explicit inverse is formed.
"""

from __future__ import annotations

import contextlib
import math
from collections.abc import Iterator

import torch
from torch.autograd.function import once_differentiable

__all__ = [
    "LOG_2PI",
    "CholeskyError",
    "cholesky_logdet",
    "gaussian_nll",
    "jitter",
    "positive_definite",
    "psd_cholesky",
    "shared_matmul",
    "symmetrize",
]

#: ``log(2 pi)``, the constant of every Gaussian log density (re-exported by
#: :mod:`hgpdm_torch.gaussian`).
LOG_2PI: float = math.log(2.0 * math.pi)

# Jitter defaults depend on dtype, as in gpytorch's settings: the first try is free (no jitter),
# then jitter grows by a factor of 10 from this value.
_JITTER = {torch.float64: 1e-10, torch.float32: 1e-6, torch.float16: 1e-3, torch.bfloat16: 1e-2}
_MAX_TRIES = 6
_override: list[float] = []


class CholeskyError(RuntimeError):
    """A matrix was not positive definite even after jitter was added to its diagonal."""


@contextlib.contextmanager
def jitter(value: float) -> Iterator[None]:
    """Context manager fixing the first jitter tried by :func:`psd_cholesky`.

    Args:
        value: Positive diagonal jitter, relative to the mean diagonal of the matrix.
    """
    if not value > 0:
        raise ValueError(f"jitter value must be positive, got {value}")
    _override.append(float(value))
    try:
        yield
    finally:
        _override.pop()


def symmetrize(a: torch.Tensor) -> torch.Tensor:
    """Return ``(a + a^T) / 2`` over the last two dimensions. Shapes: ``[..., n, n]``."""
    return (a + a.transpose(-1, -2)).mul_(0.5)  # in place on the sum: one temporary, not two


def positive_definite(a: torch.Tensor) -> torch.Tensor:
    """``[...]`` bool mask of the covariances ``a [..., D, D]`` that are finite and positive
    definite up to rounding: the Cholesky factor of their symmetric part plus the dtype's first
    jitter times the mean variance exists (one batched ``cholesky_ex``, no host synchronisation).
    A covariance that rounding has pushed slightly below zero in one direction passes; one with
    a clearly negative eigenvalue, or NaN/inf entries, does not."""
    finite = torch.isfinite(a).all(-1).all(-1)
    shifted = symmetrize(torch.where(finite[..., None, None], a, 0.0))
    diag = shifted.diagonal(dim1=-2, dim2=-1)
    scale = diag.abs().mean(-1).clamp_min(torch.finfo(a.dtype).tiny)
    diag.add_((_JITTER.get(a.dtype, 1e-6) * scale)[..., None])  # in place: a check's memory
    return finite & (torch.linalg.cholesky_ex(shifted).info == 0)


def psd_cholesky(a: torch.Tensor, *, name: str = "matrix", escalate: bool = True) -> torch.Tensor:
    """Lower Cholesky factor of a batch of symmetric positive-definite matrices.

    Tries the plain factorisation first; where it fails, adds ``eps * mean(diag)`` to the
    diagonal with eps growing tenfold per try (dtype-dependent start, see :func:`jitter`).

    Args:
        a: ``[..., n, n]`` symmetric matrices.
        name: what the matrix is, for the error message.
        escalate: add jitter where the plain factorisation fails; ``False`` raises at once
            (training objectives: jitter that depends on success would make them discontinuous).

    Returns:
        ``[..., n, n]`` lower-triangular factors L with ``L L^T ~= a``.

    Raises:
        CholeskyError: when the matrix is still not positive definite after the last jitter.
        ValueError: when ``a`` contains NaN or inf.
    """
    if a.shape[-1] != a.shape[-2]:
        raise ValueError(f"{name} must be square in its last two dims, got shape {tuple(a.shape)}")
    if not bool(torch.isfinite(a).all()):
        raise ValueError(f"{name} contains NaN or inf; cannot take its Cholesky factor")
    chol, info = torch.linalg.cholesky_ex(a)
    failed = info > 0
    if not bool(failed.any()):
        return chol
    if not escalate:
        raise CholeskyError(
            f"{name} of shape {tuple(a.shape)} is not positive definite (no jitter is added to "
            "training objectives). Raise the noise lower bound, standardise the data, remove "
            "duplicated frames, or compute in float64."
        )
    # Only the batch members that failed get jitter; the others keep their exact factor.
    eps = _override[-1] if _override else _JITTER.get(a.dtype, 1e-6)
    scale = a.diagonal(dim1=-2, dim2=-1).abs().mean(-1).clamp_min(1e-300)
    eye = torch.eye(a.shape[-1], dtype=a.dtype, device=a.device)
    for _ in range(_MAX_TRIES):
        shifted = a[failed] + (eps * scale[failed])[..., None, None] * eye
        fixed, info = torch.linalg.cholesky_ex(shifted)
        if not bool((info > 0).any()):
            chol = chol.clone()
            chol[failed] = fixed
            return chol
        eps *= 10.0
    raise CholeskyError(
        f"{name} of shape {tuple(a.shape)} is not positive definite even with relative jitter "
        f"{eps / 10:.1e} on its diagonal. Check for duplicated inputs, increase the noise "
        "hyperparameter, or compute in float64."
    )


def cholesky_logdet(chol: torch.Tensor) -> torch.Tensor:
    """``log|A| = 2 sum_i log|L_ii|`` from a lower-triangular factor ``L`` of ``A = L L^T`` (a
    Cholesky factor; the signs of its diagonal do not matter). Shapes: ``[..., n, n] -> [...]``."""
    return 2.0 * chol.diagonal(dim1=-2, dim2=-1).abs().log().sum(-1)


class _GaussianNLL(torch.autograd.Function):
    """Forward via Cholesky; backward with the closed form ``dL/dK = (d K^-1 - a a^T) / 2``."""

    @staticmethod
    def forward(ctx, cov: torch.Tensor, y: torch.Tensor, name: str) -> torch.Tensor:  # type: ignore[override]
        chol = psd_cholesky(cov, name=name, escalate=False)
        alpha = torch.cholesky_solve(y, chol)
        n, d = y.shape
        ctx.save_for_backward(chol, alpha)
        return 0.5 * d * cholesky_logdet(chol) + 0.5 * (y * alpha).sum() + 0.5 * n * d * LOG_2PI

    @staticmethod
    @once_differentiable
    def backward(ctx, grad: torch.Tensor):  # type: ignore[override]
        chol, alpha = ctx.saved_tensors
        d = alpha.shape[1]
        grad_cov = grad_y = None
        if ctx.needs_input_grad[0]:
            grad_cov = 0.5 * grad * (d * torch.cholesky_inverse(chol) - alpha @ alpha.T)
        if ctx.needs_input_grad[1]:
            grad_y = grad * alpha
        return grad_cov, grad_y, None


def gaussian_nll(cov: torch.Tensor, y: torch.Tensor, *, name: str = "covariance") -> torch.Tensor:
    """Negative log density of the columns of ``y`` under ``N(0, cov)``, summed over columns.

    ``L = d/2 log|K| + 1/2 tr(K^-1 Y Y^T) + n d/2 log(2 pi)`` (the form of Eq. 4 and 5). The
    gradient uses the closed form ``dL/dK = (d K^-1 - K^-1 Y Y^T K^-1) / 2`` from one Cholesky
    inverse, several times cheaper than differentiating through the factorisation.

    Args:
        cov: ``[n, n]`` symmetric positive-definite covariance. No jitter is added (the
            objective must stay smooth): a matrix that is not positive definite raises
            :class:`CholeskyError`.
        y: ``[n, d]`` observations, one independent Gaussian vector per column.
        name: what ``cov`` is, for error messages.

    Returns:
        A scalar tensor. First derivatives only (no double backward).
    """
    if not bool(torch.isfinite(y).all()):
        raise ValueError("gaussian_nll: y contains NaN or inf")
    if cov.dim() != 2 or y.dim() != 2 or cov.shape[0] != cov.shape[1] or y.shape[0] != cov.shape[0]:
        raise ValueError(
            f"gaussian_nll expects cov [n, n] and y [n, d], got "
            f"{tuple(cov.shape)} and {tuple(y.shape)}"
        )
    return _GaussianNLL.apply(cov, y, name)


def shared_matmul(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """``a @ b`` with batch broadcasting, without expanding ``a`` over dims where it has size 1.

    ``a [*A, n, m]``, ``b [*Bb, m, k]`` -> ``[*broadcast(A, Bb), n, k]``. Batch dims along which
    only ``b`` varies are folded into its columns, so an ``N x N`` matrix shared by K intentions
    is multiplied once with an ``N x (K k)`` matrix instead of being copied K times.
    """
    nb = max(a.dim(), b.dim()) - 2
    a = a.reshape((1,) * (nb + 2 - a.dim()) + a.shape)
    b = b.reshape((1,) * (nb + 2 - b.dim()) + b.shape)
    share = [i for i in range(nb) if a.shape[i] == 1 and b.shape[i] > 1]
    if not share:
        return a @ b
    keep = [i for i in range(nb) if i not in share]
    m, k = b.shape[-2], b.shape[-1]
    bp = b.permute(*keep, nb, *share, nb + 1).reshape(*(b.shape[i] for i in keep), m, -1)
    ap = a.reshape(*(a.shape[i] for i in keep), a.shape[-2], m)
    out = ap @ bp  # [*keep, n, prod(share) k]
    out = out.reshape(*out.shape[:-1], *(b.shape[i] for i in share), k)
    # current order: keep..., n, share..., k -> back to batch order, n, k
    order = keep + share
    nk = len(keep)
    perm = [order.index(i) if order.index(i) < nk else order.index(i) + 1 for i in range(nb)]
    return out.permute(*perm, nk, nb + 1)
