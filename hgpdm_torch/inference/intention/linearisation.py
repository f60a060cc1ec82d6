r"""Statistical linearisation: ``E_q[log q~(y | x)]`` for a Gaussian ``q``.

The transition term ``Q_t(g) = E_q[log p(x_{t+1} | x_t, g)]`` of the bound (Sec. 3.3.2,
docs/design/math.md#the-transition-term-in-kl-form) and its measurement term replace the GP by
the conditional of its moment-matched joint Gaussian ``q~`` (:func:`expected_log_conditional`);
the expectation under ``q`` is then exact. Used by batch inference (Algorithm 3.1) and by the
online filter's ``evidence="bound"`` (Algorithm 3.2).
"""

from __future__ import annotations

import torch

from ...gaussian import conditional, entropy, log_density_terms
from ...linalg import cholesky_logdet, psd_cholesky, symmetrize

__all__ = ["expected_log_conditional"]


def expected_log_conditional(
    lin_mean_in: torch.Tensor,
    lin_cov_in: torch.Tensor,
    lin_mean_out: torch.Tensor,
    lin_cov_out: torch.Tensor,
    lin_cross: torch.Tensor,
    q_mean_in: torch.Tensor,
    q_cov_in: torch.Tensor,
    q_mean_out: torch.Tensor,
    q_cov_out: torch.Tensor | None,
    q_cross: torch.Tensor | None,
) -> torch.Tensor:
    r"""``E_q[log q~(y | x)]`` for a jointly Gaussian linearisation ``q~`` and a Gaussian ``q``.

    ``q~(x, y) = N([a, m], [[P, C], [C^T, S]])`` gives ``q~(y | x) = N(m + A (x - a), V)`` with
    ``A = C^T P^-1`` and ``V = S - C^T P^-1 C``; under ``q(x, y)`` with means ``(mu_x, mu_y)``,
    covariances ``Sx, Sy`` and ``Sxy = Cov[x, y]``, with ``r = mu_y - m - A (mu_x - a)``::

        E = -1/2 [log|2 pi V| + tr(V^-1 (r r^T + Sy - A Sxy - Sxy^T A^T + A Sx A^T))]

    This is ``Q_t(g)`` of Sec. 3.3.2 (``x = x_t``, ``y = x_{t+1}``) and, with ``y = z_t`` observed
    (``Sy = Sxy = 0``), the measurement term ``E_q[log p(z_t | x_t)]`` of Eq. 22.

    Shapes: ``lin_*`` over ``[..., Dx]``/``[..., Dy]``; ``q_*`` broadcast against them;
    ``q_cov_out``/``q_cross`` ``None`` for an observed ``y``. Returns ``[...]``.
    """
    L = psd_cholesky(lin_cov_in, name="linearisation input covariance")
    At, V = conditional(lin_cov_out, lin_cross.transpose(-1, -2), L)
    A = At.transpose(-1, -2)  # C^T P^-1  [..., Dy, Dx]
    LV = psd_cholesky(V, name="linearised conditional covariance")
    r = q_mean_out - lin_mean_out - (A @ (q_mean_in - lin_mean_in)[..., None])[..., 0]
    E = r[..., :, None] * r[..., None, :] + A @ q_cov_in @ A.transpose(-1, -2)
    if q_cov_out is not None:
        AC = A @ q_cross
        E = E + q_cov_out - AC - AC.transpose(-1, -2)
    W = torch.linalg.solve_triangular(LV, symmetrize(E), upper=False)
    W = torch.linalg.solve_triangular(LV, W.transpose(-1, -2), upper=False)
    trace = W.diagonal(dim1=-2, dim2=-1).sum(-1)
    return log_density_terms(trace, cholesky_logdet(LV), V.shape[-1])


def gaussian_entropy(cov: torch.Tensor) -> torch.Tensor:
    """Entropy ``[...]`` of ``N(., cov [..., D, D])``."""
    return entropy(psd_cholesky(cov, name="smoothed covariance"))
