r"""The Laplace start of VB inference and the MAP solver: batched Levenberg-Marquardt on the
window's log joint (thesis Eq. 8-9), with pruning of hopeless candidates of g.

Every window and candidate g is its own problem. Levenberg-Marquardt maximises the FIC log joint
``log p(x_{1:T}, z_obs | g)`` (:class:`~hgpdm_torch.inference.variational.window.WindowModel`)
over the states (the MAP baseline stops there). For VB the mean-field Laplace
approximation follows: for a narrow q, the negative free energy of Eq. 13 is, to second order,

    F ~= log p(mu, z) - 1/2 sum_t tr(Lambda_tt Sigma_t) + 1/2 sum_t log|2 pi e Sigma_t|,

(``Lambda`` the Fisher precision, the expected Hessian, of the log joint:
:meth:`~hgpdm_torch.inference.variational.window.WindowModel.precision_blocks`), which the
mean-field family (Eq. 11) maximises at ``mu`` = MAP and ``Sigma_t = Lambda_tt^-1``, the inverse
*diagonal block*.

Shapes: ``T`` window length, ``K`` candidate values of g, ``Dx`` latent dim; ``...`` leading
batch dims (windows).
"""

from __future__ import annotations

import math

import torch

from ...linalg import psd_cholesky, symmetrize
from .window import WindowModel

__all__ = ["check_prune", "laplace", "map_states"]

_PRUNE_SAFETY = 3.0  # optimism factor of the LM pruning rule (see map_states)
_PRUNE_MAX_DAMPING = 1.0  # LM damping up to which the pruning rule trusts the step's gain


def check_prune(prune: object) -> None:
    """Raise ``ValueError`` unless ``prune`` is a positive number of nats or ``None``."""
    if prune is not None and not (isinstance(prune, int | float) and prune > 0):
        raise ValueError(f"prune must be a positive number of nats or None, got {prune!r}")


def map_states(
    window: WindowModel,
    z: torch.Tensor,
    observed: torch.Tensor,
    x: torch.Tensor,
    values: torch.Tensor,
    g_loc: torch.Tensor | None,
    *,
    max_iter: int,
    tol: float = 1e-3,
    prune: float | None = None,
) -> tuple[torch.Tensor, list[float]]:
    """Maximise the log joint over ``x [..., K, T, Dx]`` by Levenberg-Marquardt.

    Each window and candidate g is its own problem: the step solves ``(F + lambda diag(F)) s =
    -grad`` with ``F`` the Fisher precision (Gauss-Newton's ``J^T J`` plus the curvature of the
    GP variances, :meth:`~hgpdm_torch.inference.variational.window.WindowModel.precision_blocks`),
    the exact gradient (autograd) and its own damping ``lambda``, which shrinks after an
    accepted step and grows after a rejected one. A problem stops when an accepted step gains
    less than ``tol`` nats (far below the differences between candidates of g that matter), or,
    with ``prune`` (a heuristic), when even an optimistic value, its negative log joint minus
    three times the next step's first-order gain ``-grad^T s``, trails the best candidate of
    its window by more than ``prune`` nats while the damping is moderate (``lambda <= 1``:
    the damped step's gain is then within about ``1 + lambda`` of the undamped step's,
    which the factor 3 covers): a candidate far from its optimum has a large predicted gain
    and is kept. Only the problems still running are computed at each iteration.

    Returns:
        The maximisers and the summed negative log joint after each iteration.
    """
    check_prune(prune)
    batch = torch.broadcast_shapes(z.shape[:-2], observed.shape[:-1], x.shape[:-3])
    if g_loc is not None:
        batch = torch.broadcast_shapes(batch, g_loc.shape[:-1])
    K, T, dx = x.shape[-3:]
    lead = (*batch, K)
    n = math.prod(lead)
    # one row per (window, candidate) problem; K = 1 per row so that the log joint's
    # broadcasting over candidates is unchanged
    zf = z.expand(*batch, *z.shape[-2:])[..., None, :, :].expand(*lead, *z.shape[-2:])
    zf = zf.reshape(n, *z.shape[-2:])
    of = observed.expand(*batch, T)[..., None, :].expand(*lead, T).reshape(n, T)
    discrete = window.kind == "discrete"
    vf = values.to(x.device).expand(*lead).reshape(n) if discrete else values
    gf = None
    if g_loc is not None:
        gf = g_loc.expand(*batch, g_loc.shape[-1])[..., None, :].expand(*lead, -1)
        gf = gf.reshape(n, -1)

    def by_code(idx: torch.Tensor, fn) -> tuple[torch.Tensor, ...]:
        """``fn(rows, z, observed, values, g)`` on the rows ``idx`` (one code per row of a
        discrete g: the transition GP computes the rows of a code together on its own block)."""
        gi = None if gf is None else gf[idx]
        return fn(idx, zf[idx], of[idx], vf[idx, None] if discrete else vf, gi)

    def value_grad(xs: torch.Tensor):
        def fn(sel, zi, oi, vi, gi):
            xi = xs[sel].detach().requires_grad_(True)
            with torch.enable_grad():
                v = -window.log_joint(zi, oi, xi, vi, gi)
                (grad,) = torch.autograd.grad(v.sum(), xi)
            return v.detach()[:, 0], grad

        return fn

    def precision(xs: torch.Tensor):
        def fn(sel, zi, oi, vi, gi):
            with torch.no_grad():
                return (window.dense(*window.precision_blocks(oi, xs[sel], vi, gi))[:, 0],)

        return fn

    x = x.expand(*lead, T, dx).reshape(n, 1, T, dx).detach().clone()
    every = torch.arange(n, device=x.device)
    f, g = by_code(every, value_grad(x))
    lam = torch.full_like(f, 1e-3)
    active = torch.isfinite(f)
    history = [float(f.sum())]
    # the precision at each problem's current states; recomputed only where a step moved them
    # (a rejected step leaves the states, and so the matrix, as they were)
    A_all = x.new_zeros(n, T * dx, T * dx)
    stale = active.clone()
    for _ in range(max_iter):
        idx = torch.nonzero(active).flatten()
        if idx.numel() == 0:
            break
        redo = idx[stale[idx]]
        if redo.numel():
            (A_all[redo],) = by_code(redo, precision(x))
            stale[redo] = False
        A = A_all[idx]
        grad = g[idx].reshape(-1, T * dx, 1)
        with torch.no_grad():
            damped = A + lam[idx, None, None] * torch.diag_embed(A.diagonal(dim1=-2, dim2=-1))
            L = psd_cholesky(damped, name="Fisher precision of the log joint")
            step = -torch.cholesky_solve(grad, L)
            if prune is not None:
                # the step's first-order gain, trusted only while the damping is moderate
                reach = f[idx] + _PRUNE_SAFETY * (grad * step).sum((-1, -2))
                finite = torch.where(torch.isfinite(f), f, torch.full_like(f, math.inf))
                best = finite.reshape(-1, K).min(-1).values.repeat_interleave(K)[idx]
                keep = (reach <= best + prune) | (lam[idx] > _PRUNE_MAX_DAMPING)
                active[idx[~keep]] = False
                idx, step = idx[keep], step[keep]
                if idx.numel() == 0:
                    break
            step = step.reshape(-1, 1, T, dx)
        trial = x.clone()
        trial[idx] = x[idx] + step
        f_t, g_t = by_code(idx, value_grad(trial))
        ok = torch.isfinite(f_t) & (f_t < f[idx])
        gain = torch.where(ok, f[idx] - f_t, torch.zeros_like(f_t))
        x[idx] = torch.where(ok[:, None, None, None], trial[idx], x[idx]).detach()
        f[idx] = torch.where(ok, f_t, f[idx])
        g[idx] = torch.where(ok[:, None, None, None], g_t, g[idx])
        lam[idx] = torch.where(ok, 0.2 * lam[idx], 10.0 * lam[idx])
        stale[idx] = ok
        done = (ok & (gain < tol)) | (lam[idx] > 1e10)
        active[idx[done]] = False
        history.append(float(f.sum()))
    return x.reshape(*lead, T, dx), history


def laplace(
    window: WindowModel,
    z: torch.Tensor,
    observed: torch.Tensor,
    x: torch.Tensor,
    values: torch.Tensor,
    g_loc: torch.Tensor | None = None,
    *,
    max_iter: int = 30,
    prune: float | None = None,
) -> tuple[torch.Tensor, torch.Tensor]:
    r"""Mean-field Laplace start of q(x): MAP means and ``Sigma_t = (Lambda_tt)^-1``.

    For a narrow q, ``F`` is ``log p(mu, z) - 1/2 sum_t tr(Lambda_tt Sigma_t) + 1/2 sum_t
    log|2 pi e Sigma_t|`` to second order (``Lambda`` the Fisher precision of the log joint),
    which the mean-field family maximises at ``mu`` = MAP and ``Sigma_t =
    Lambda_tt^-1`` (the inverse *diagonal block*, not the marginal covariance). L-BFGS on the
    exact ``F`` then only polishes this start.

    Args:
        window: the model's :class:`~hgpdm_torch.inference.variational.window.WindowModel`.
        z: ``[..., T, Dz]`` window (NaN rows missing); observed: ``[..., T]`` its mask.
        x: ``[..., K, T, Dx]`` initial states; values: ``[..., K]`` candidate codes.
        g_loc: ``[..., Dg]`` a continuous g, held fixed here.
        max_iter: Levenberg-Marquardt iterations.
        prune: stop refining a candidate once its log joint trails its window's best by
            more than this many nats (``None``: refine all to convergence).

    Returns:
        ``mean [..., K, T, Dx]`` and ``cov [..., K, T, Dx, Dx]``.
    """
    x, _ = map_states(window, z, observed, x, values, g_loc, max_iter=max_iter, prune=prune)
    with torch.no_grad():
        diag, _ = window.precision_blocks(observed, x, values, g_loc)
        cov = torch.cholesky_inverse(psd_cholesky(diag, name="precision block of q(x_t)"))
    return x, symmetrize(cov)
