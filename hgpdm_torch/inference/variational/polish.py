r"""L-BFGS on the exact free energy in whitened coordinates: the last step of VB inference
(thesis Algorithm 2.2, F of Eq. 13 with Eq. 15-17).

The transition term of Eq. 17 is stiff (``sigma_x^2 ~ alpha_4 = 1e-4``), so the optimiser sees
the means as a transition rollout plus whitened innovations,

    mu_{t+1} = m_x(mu_t, g) + sigma_x(mu_t, g) eps_{t+1},

which turns the transition term into ``~ ||eps||^2 / 2`` (the same F, well scaled), and the
Cholesky factors of ``Sigma_t`` as ``diag(e^d) (I + strictly lower M)`` (unconstrained, with
scale-free off-diagonals). :func:`~hgpdm_torch.inference.variational.lbfgs.batched_lbfgs` then
maximises F for every window and candidate g at once.

Shapes: ``T`` window length, ``K`` candidate values of g, ``Dx`` latent dim, ``Dg`` dim of a
continuous g; ``...`` leading batch dims.
"""

from __future__ import annotations

import torch

from ...linalg import psd_cholesky, symmetrize
from .gaussian_input import GaussianInputGP
from .lbfgs import batched_lbfgs
from .window import WindowModel

__all__ = ["polish", "unwhiten", "whiten"]


def _tril_free(cov: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """``(d, M)`` with ``chol(cov) = diag(e^d) (I + strictly lower M)``."""
    L = psd_cholesky(symmetrize(cov), name="covariance of q")
    diag = L.diagonal(dim1=-2, dim2=-1)
    return diag.log(), torch.tril(L / diag[..., :, None], -1)


def _tril_from_free(d: torch.Tensor, M: torch.Tensor) -> torch.Tensor:
    """Lower Cholesky factor ``diag(e^d) (I + strictly lower M)``: scale-free off-diagonals."""
    eye = torch.eye(d.shape[-1], dtype=d.dtype, device=d.device)
    return d.exp()[..., :, None] * (eye + torch.tril(M, -1))


def _step(
    f: GaussianInputGP, x: torch.Tensor, g_loc: torch.Tensor | None
) -> tuple[torch.Tensor, torch.Tensor]:
    """Transition mean ``[..., K, Dx]`` and plug-in variance ``[..., K, 1]`` at ``x``."""
    m, v = f.predict_point(WindowModel.transition_inputs(x[..., None, :], g_loc))
    return m[..., 0, :], v


def whiten(
    f: GaussianInputGP,
    loc: torch.Tensor,
    cov: torch.Tensor,
    g_loc: torch.Tensor | None,
    g_cov: torch.Tensor | None,
) -> list[torch.Tensor]:
    """Free variables of the optimiser for q (inverse of :func:`unwhiten`).

    Args:
        f: the transition GP of the candidates (``WindowModel.transition_gp``).
        loc: ``[..., K, T, Dx]``, cov: ``[..., K, T, Dx, Dx]`` q(x).
        g_loc: ``[..., Dg]``, g_cov: ``[..., Dg, Dg]`` q(g) of a continuous g, else ``None``.

    Returns:
        ``[mu_1 [..., K, Dx], eps [..., K, T-1, Dx], d, M]`` (+ ``[g_loc, d_g, M_g]``).
    """
    eps = []
    for t in range(loc.shape[-2] - 1):
        m, v = _step(f, loc[..., t, :], g_loc)
        eps.append((loc[..., t + 1, :] - m) / v.sqrt())
    free = [loc[..., 0, :], torch.stack(eps, -2), *_tril_free(cov)]
    return free if g_loc is None else [*free, g_loc, *_tril_free(g_cov)]


def unwhiten(
    f: GaussianInputGP, free: list[torch.Tensor]
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor | None, torch.Tensor | None]:
    """``loc``, ``scale_tril`` (and q(g)'s ``g_loc``, ``g_scale_tril``) from the free variables
    of :func:`whiten`."""
    a1, eps, d, M = free[:4]
    g_loc = g_tril = None
    if len(free) > 4:
        g_loc, g_tril = free[4], _tril_from_free(free[5], free[6])
    mus = [a1]
    for t in range(eps.shape[-2]):
        m, v = _step(f, mus[-1], g_loc)
        mus.append(m + v.sqrt() * eps[..., t, :])
    return torch.stack(mus, -2), _tril_from_free(d, M), g_loc, g_tril


def polish(
    window: WindowModel,
    z: torch.Tensor,
    observed: torch.Tensor,
    values: torch.Tensor,
    q: tuple[torch.Tensor | None, ...],
    steps: int,
    progress: bool = False,
) -> tuple[tuple[torch.Tensor | None, ...], list[float]]:
    """L-BFGS on the exact F from ``q = (loc, cov, g_loc, g_cov)``.

    Args:
        window: the model's :class:`~hgpdm_torch.inference.variational.window.WindowModel`.
        z: ``[..., T, Dz]`` window, observed: ``[..., T]`` its mask, values: ``[..., K]``.
        q: ``loc [..., K, T, Dx]``, ``cov [..., K, T, Dx, Dx]``, ``g_loc``, ``g_cov`` (``None``
            without a continuous g).
        steps: maximum L-BFGS iterations.
        progress: show a progress bar.

    Returns:
        The new ``q`` (same layout) and ``-sum F`` after each iteration.
    """
    loc = q[0]
    f = window.transition_gp(values)
    with torch.no_grad():
        free = whiten(f, *q)
    shapes = [p.shape for p in free]
    nb = loc.shape[:-2].numel()  # independent blocks: windows x candidates

    def unflatten(flat: torch.Tensor) -> list[torch.Tensor]:
        parts = torch.split(flat, [sh.numel() // nb for sh in shapes], dim=-1)
        return [p.reshape(sh) for p, sh in zip(parts, shapes, strict=True)]

    def objective(flat: torch.Tensor) -> torch.Tensor:
        loc, tril, g_l, g_t = unwhiten(f, unflatten(flat))
        return -window.free_energy(z, observed, loc, tril, values, g_l, g_t).reshape(nb)

    x0 = torch.cat([p.reshape(nb, -1) for p in free], -1)
    x, history = batched_lbfgs(objective, x0, max_iter=steps, progress=progress)
    with torch.no_grad():
        loc, tril, g_l, g_t = unwhiten(f, unflatten(x.detach()))
        g_c = None if g_l is None else g_t @ g_t.transpose(-1, -2)
        return (loc, tril @ tril.transpose(-1, -2), g_l, g_c), history
