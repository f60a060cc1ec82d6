"""Confidence intervals for proportions: a return rate and the paired difference of two players
over the same rallies (used by ``hgpdm demo``), and the mean with its standard error.

- :func:`return_rate_interval`: exact Clopper-Pearson interval of a binomial proportion.
- :func:`wilson_interval`: Wilson score interval.
- :func:`paired_difference_interval`: Newcombe's square-and-add interval (method 10 of
  Newcombe 1998) for the difference of two paired proportions.
- :func:`mean_sem`: the mean of per-trial scores and its standard error.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import torch

__all__ = ["mean_sem", "paired_difference_interval", "return_rate_interval", "wilson_interval"]


def mean_sem(values: Sequence[float]) -> tuple[float, float | None]:
    """Mean of ``values`` and its standard error ``sd / sqrt(n)`` (sample sd, ``ddof = 1``;
    ``None`` for one value).

    Raises:
        ValueError: no values, or a value that is not finite (a failed score must be fixed or
            reported, not averaged away).
    """
    v = [float(x) for x in values]
    if not v or not all(math.isfinite(x) for x in v):
        raise ValueError(f"values must be a non-empty list of finite numbers, got {v!r}")
    mean = sum(v) / len(v)
    if len(v) == 1:
        return mean, None
    var = sum((x - mean) ** 2 for x in v) / (len(v) - 1)
    return mean, math.sqrt(var / len(v))


def _check_counts(successes: int, n: int) -> None:
    for name, value in (("successes", successes), ("n", n)):
        if isinstance(value, bool) or not isinstance(value, int):
            raise TypeError(f"{name} must be an int, got {type(value).__name__}")
    if n < 1 or not 0 <= successes <= n:
        raise ValueError(f"need n >= 1 and 0 <= successes <= n, got successes={successes}, n={n}")


def _check_confidence(confidence: float) -> float:
    if isinstance(confidence, bool) or not isinstance(confidence, int | float):
        raise TypeError(f"confidence must be a number, got {type(confidence).__name__}")
    if not 0.0 < confidence < 1.0:
        raise ValueError(f"confidence must be in (0, 1), got {confidence!r}")
    return float(confidence)


def return_rate_interval(successes: int, n: int, confidence: float = 0.95) -> tuple[float, float]:
    """Exact (Clopper-Pearson) interval for a return rate of ``successes`` out of ``n`` rallies.

    It holds the true rate with probability at least ``confidence`` for every rate
    (conservative), from the beta quantiles that
    :meth:`scipy.stats.binomtest(...).proportion_ci <scipy.stats._result_classes.BinomTestResult>`
    computes.

    Returns:
        ``(low, high)`` within ``[0, 1]``.
    """
    from scipy.stats import binomtest

    _check_counts(successes, n)
    ci = binomtest(successes, n).proportion_ci(
        confidence_level=_check_confidence(confidence), method="exact"
    )
    return float(ci.low), float(ci.high)


def wilson_interval(successes: int, n: int, confidence: float = 0.95) -> tuple[float, float]:
    """Wilson score interval for a proportion ``successes / n`` (no continuity correction).

    The roots ``p`` of ``(successes / n - p)^2 = z^2 p (1 - p) / n`` with ``z`` the normal
    quantile of ``(1 + confidence) / 2``; the building block of
    :func:`paired_difference_interval`.

    Returns:
        ``(low, high)`` within ``[0, 1]``.
    """
    from scipy.stats import norm

    _check_counts(successes, n)
    z = float(norm.ppf(0.5 + _check_confidence(confidence) / 2))
    p = successes / n
    centre = (p + z * z / (2 * n)) / (1 + z * z / n)
    half = z / (1 + z * z / n) * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n))
    # exact ends where the proportion is 0 or 1 (rounding would leave 1e-17 off)
    low = 0.0 if successes == 0 else max(0.0, centre - half)
    high = 1.0 if successes == n else min(1.0, centre + half)
    return low, high


def paired_difference_interval(
    first: Sequence[bool] | torch.Tensor,
    second: Sequence[bool] | torch.Tensor,
    confidence: float = 0.95,
) -> tuple[float, float, float]:
    """Difference of two success rates measured on the same rallies, with its interval.

    Rally ``j`` gives the pair ``(first[j], second[j])``; with ``a`` rallies won by both, ``b``
    by ``first`` only, ``c`` by ``second`` only and ``d`` by neither (``n`` in all), the
    difference is ``(b - c) / n``. The interval is Newcombe's square-and-add score interval for
    paired proportions (Newcombe 1998, Stat. Med. 17:2635, method 10): the Wilson intervals
    ``(l1, u1)``, ``(l2, u2)`` of the two rates ``p1 = (a + b) / n``, ``p2 = (a + c) / n``,
    combined with the continuity-corrected correlation ``phi`` of the pairs::

        low  = D - sqrt((p1 - l1)^2 + (u2 - p2)^2 - 2 phi (p1 - l1)(u2 - p2))
        high = D + sqrt((p2 - l2)^2 + (u1 - p1)^2 - 2 phi (p2 - l2)(u1 - p1))

    where ``phi = (ad - bc - n/2) / sqrt((a+b)(c+d)(a+c)(b+d))`` if ``ad - bc > n/2``, ``0`` if
    ``0 <= ad - bc <= n/2``, ``(ad - bc) / sqrt(...)`` if ``ad < bc``, and ``0`` when a margin is
    empty. It is deterministic (no resampling) and keeps close to its nominal coverage for a
    few dozen pairs.

    Args:
        first: ``[n]`` successes (bool or 0/1) of the first player on ``n >= 1`` rallies.
        second: ``[n]`` successes of the second player on the same rallies.
        confidence: the interval's level.

    Returns:
        ``(difference, low, high)``, ``-1 <= low <= difference <= high <= 1``.
    """
    x = torch.as_tensor(first)
    y = torch.as_tensor(second)
    if x.ndim != 1 or x.shape != y.shape or x.numel() < 1:
        raise ValueError(
            f"first and second must be 1-D of the same length >= 1, got {tuple(x.shape)} and "
            f"{tuple(y.shape)}"
        )
    for name, v in (("first", x), ("second", y)):
        if not bool(((v == 0) | (v == 1)).all()):
            raise ValueError(f"{name} must hold successes (bool or 0/1)")
    x, y = x.bool(), y.bool()
    n = int(x.numel())
    a, b = int((x & y).sum()), int((x & ~y).sum())
    c, d = int((~x & y).sum()), int((~x & ~y).sum())
    p1, p2 = (a + b) / n, (a + c) / n
    l1, u1 = wilson_interval(a + b, n, confidence)
    l2, u2 = wilson_interval(a + c, n, confidence)
    margins = (a + b) * (c + d) * (a + c) * (b + d)
    ad_bc = a * d - b * c
    if margins == 0 or 0 <= ad_bc <= n / 2:
        phi = 0.0
    elif ad_bc > n / 2:
        phi = (ad_bc - n / 2) / math.sqrt(margins)
    else:
        phi = ad_bc / math.sqrt(margins)
    diff = (b - c) / n
    low = diff - math.sqrt(
        max(0.0, (p1 - l1) ** 2 + (u2 - p2) ** 2 - 2 * phi * (p1 - l1) * (u2 - p2))
    )
    high = diff + math.sqrt(
        max(0.0, (p2 - l2) ** 2 + (u1 - p1) ** 2 - 2 * phi * (p2 - l2) * (u1 - p1))
    )
    return diff, max(-1.0, low), min(1.0, high)
