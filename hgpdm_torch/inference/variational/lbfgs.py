"""Batched L-BFGS: many independent smooth minimisations in the same tensor calls.

Used by VB inference to polish q on the exact free energy (Algorithm 2.2): every window and
candidate g is its own problem with its own curvature pairs (the two-loop recursion of
Nocedal & Wright, Alg. 7.4), step length (Armijo backtracking) and stopping test.

Shapes: ``B`` problems, ``P`` variables per problem.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import torch

from ...linalg import CholeskyError
from ...progress import trange

__all__ = ["batched_lbfgs"]


def batched_lbfgs(
    fun: Callable[[torch.Tensor], torch.Tensor],
    x0: torch.Tensor,
    *,
    max_iter: int = 50,
    history_size: int = 10,
    tol_grad: float = 1e-6,
    tol_change: float = 1e-9,
    max_step: float = 3.0,
    progress: bool = False,
) -> tuple[torch.Tensor, list[float]]:
    """Minimise ``B`` independent problems at once by L-BFGS with per-problem state.

    One call of ``fun`` evaluates all problems (one batched free energy), but each problem keeps
    its own curvature pairs, step length (Armijo backtracking) and stopping test, so an
    ill-conditioned window does not slow the others, as it would in one L-BFGS over the sum.

    Args:
        fun: ``x [B, P] -> [B]`` objective values (differentiable).
        x0: ``[B, P]`` starting points.
        max_iter: maximum iterations.
        history_size: curvature pairs kept per problem.
        tol_grad: a problem stops when its largest gradient entry is below this.
        tol_change: ... or when its objective changes by less than this (relative) in a step.
        max_step: largest change of any variable in one step.
        progress: show a tqdm bar over iterations.

    Returns:
        The minimisers ``[B, P]`` and ``sum fun`` after each iteration.
    """
    if x0.dim() != 2:
        raise ValueError(f"x0 must have shape [B, P], got {tuple(x0.shape)}")
    B, P, m = x0.shape[0], x0.shape[1], history_size

    def value_grad(x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        x = x.detach().requires_grad_(True)
        try:
            with torch.enable_grad():
                v = fun(x)
                (grad,) = torch.autograd.grad(v.sum(), x)
        except (torch.linalg.LinAlgError, CholeskyError, ValueError):
            # a trial point outside the domain (e.g. a covariance overflow): reject the step
            return torch.full_like(x[:, 0], math.inf), torch.zeros_like(x)
        return v.detach(), grad

    x = x0.detach().clone()
    f, g = value_grad(x)
    S = x.new_zeros(B, m, P)
    Y = x.new_zeros(B, m, P)
    rho = x.new_zeros(B, m)  # 0 marks an empty slot
    active = g.abs().amax(-1) > tol_grad
    history = [float(f.sum())]
    for _ in trange(max_iter, disable=not progress, desc="VB (Alg. 2.2)", leave=False):
        if not bool(active.any()):
            break
        # two-loop recursion, newest pair last; empty slots have rho = 0 and drop out
        q = -g
        alphas = []
        for j in range(m - 1, -1, -1):
            a = rho[:, j] * (S[:, j] * q).sum(-1)
            q = q - a[:, None] * Y[:, j]
            alphas.append(a)
        sy, yy = (S[:, -1] * Y[:, -1]).sum(-1), Y[:, -1].pow(2).sum(-1)
        first = 1.0 / g.abs().sum(-1).clamp_min(1.0)  # no pairs yet: a short gradient step
        gamma = torch.where(rho[:, -1] > 0, sy / yy.clamp_min(1e-300), first)
        r = gamma[:, None] * q
        for j, a in zip(range(m), reversed(alphas), strict=True):
            b = rho[:, j] * (Y[:, j] * r).sum(-1)
            r = r + (a - b)[:, None] * S[:, j]
        slope = (g * r).sum(-1)
        bad = slope >= 0  # not a descent direction: fall back to the gradient
        r = torch.where(bad[:, None], -first[:, None] * g, r)
        slope = (g * r).sum(-1)
        # per-problem Armijo backtracking; finished problems take a zero step
        # steps move no free variable by more than max_step (keeps trial covariances finite)
        step = active.to(x.dtype) * (max_step / r.abs().amax(-1).clamp_min(1e-300)).clamp_max(1.0)
        accepted = ~active
        f_new, g_new = f, g
        for _ in range(30):
            trial = x + step[:, None] * r
            f_t, g_t = value_grad(trial)
            ok = (f_t <= f + 1e-4 * step * slope) & torch.isfinite(f_t)
            take = ok & ~accepted
            f_new = torch.where(take, f_t, f_new)
            g_new = torch.where(take[:, None], g_t, g_new)
            accepted = accepted | ok
            if bool(accepted.all()):
                break
            step = torch.where(accepted, step, 0.5 * step)
        step = torch.where(accepted, step, torch.zeros_like(step))
        s_k = step[:, None] * r
        y_k = g_new - g
        sy_k = (s_k * y_k).sum(-1)
        good = active & accepted & (sy_k > 1e-10 * y_k.pow(2).sum(-1).sqrt() * s_k.norm(dim=-1))
        S = torch.where(good[:, None, None], torch.cat([S[:, 1:], s_k[:, None]], 1), S)
        Y = torch.where(good[:, None, None], torch.cat([Y[:, 1:], y_k[:, None]], 1), Y)
        new_rho = torch.cat([rho[:, 1:], (1.0 / sy_k.clamp_min(1e-300))[:, None]], 1)
        rho = torch.where(good[:, None], new_rho, rho)
        x = x + s_k
        change = (f - f_new).abs() <= tol_change * f.abs().clamp_min(1.0)
        f, g = f_new, g_new
        active = active & accepted & ~change & (g.abs().amax(-1) > tol_grad)
        history.append(float(f.sum()))
    return x, history
