"""Two-sample z-tests of the opponent's action frequencies: change detection (Sec. 5.2.3)."""

from __future__ import annotations

import numpy as np
from scipy.stats import norm

from hgpdm_torch.decision.games import check_counts
from hgpdm_torch.decision.opponent._checks import check_open_probability

__all__ = [
    "two_sample_z_test",
]


def two_sample_z_test(
    counts_x: object, counts_y: object, alpha: float = 0.05
) -> tuple[np.ndarray, bool]:
    """Per-action two-sample z-tests of ``H0: p_X(a_j) = p_Y(a_j)`` (Sec. 5.2.3, Alg. 5.1 l. 11).

    ``z_0 = (p~_X - p~_Y) / (sigma sqrt(1/|X| + 1/|Y|))`` with the pooled proportion
    ``mu = (n_X(a_j) + n_Y(a_j)) / (|X| + |Y|)`` and ``sigma^2 = mu (1 - mu)`` (the printed
    ``mu`` divides the sum of the two proportions; the pooled count is meant). An action seen
    always or never in both sets has ``sigma = 0`` and no evidence of change: ``z = 0``.

    Args:
        counts_x: ``[Aj]`` action counts of the first set, non-empty.
        counts_y: ``[Aj]`` action counts of the second set, non-empty.
        alpha: significance level of each test, in (0, 1).

    Returns:
        ``([Aj] z statistics, passed)`` where ``passed`` is True when every ``|z| <= z_{alpha/2}``.
    """
    x = check_counts(counts_x, None, "counts_x")
    y = check_counts(counts_y, x.shape[0], "counts_y")
    alpha = check_open_probability(alpha, "alpha")
    nx, ny = x.sum(), y.sum()
    if nx == 0 or ny == 0:
        raise ValueError("counts_x and counts_y must each hold at least one observation")
    mu = (x + y) / (nx + ny)
    sigma = np.sqrt(mu * (1.0 - mu) * (1.0 / nx + 1.0 / ny))
    diff = x / nx - y / ny
    z = np.divide(diff, sigma, out=np.zeros_like(diff), where=sigma > 0)
    return z, bool(np.all(np.abs(z) <= norm.ppf(1.0 - alpha / 2.0)))
