"""The intervals ``hgpdm demo`` reports, against independent oracles: published values, the beta
quantiles of the exact interval, scipy's Wilson interval, exact coverage by enumerating every
outcome, and the normal approximation on a large sample."""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest
from scipy.stats import beta, binom, binomtest, multinomial, norm

from hgpdm_torch.experiments.intervals import (
    mean_sem,
    paired_difference_interval,
    return_rate_interval,
    wilson_interval,
)


def pairs(a: int, b: int, c: int, d: int) -> tuple[list[int], list[int]]:
    """Rallies won by both (a), the first only (b), the second only (c), neither (d)."""
    first = [1] * a + [1] * b + [0] * c + [0] * d
    second = [1] * a + [0] * b + [1] * c + [0] * d
    return first, second


def test_return_rate_interval_is_the_exact_clopper_pearson_interval() -> None:
    # published: 13 of 16 (Ligarden et al. 2010), Fagerland, Lydersen & Laake, "Statistical
    # Analysis of Contingency Tables" (R package contingencytables): 0.5435 to 0.9595
    low, high = return_rate_interval(13, 16)
    assert (round(low, 4), round(high, 4)) == (0.5435, 0.9595)
    assert return_rate_interval(0, 10) == pytest.approx((0.0, 0.3085), abs=1e-4)
    assert return_rate_interval(10, 10) == pytest.approx((0.6915, 1.0), abs=1e-4)
    # the beta-quantile definition, for every count of 60 rallies and two levels
    for level in (0.95, 0.8):
        alpha = 1 - level
        for k in range(61):
            lo = 0.0 if k == 0 else beta.ppf(alpha / 2, k, 61 - k)
            hi = 1.0 if k == 60 else beta.ppf(1 - alpha / 2, k + 1, 60 - k)
            assert return_rate_interval(k, 60, level) == pytest.approx((lo, hi), abs=1e-9)


def test_return_rate_interval_covers_at_least_95_percent_for_every_rate() -> None:
    # exact coverage (no sampling): sum of P(k) over the counts k whose interval holds p
    n = 60
    intervals = [return_rate_interval(k, n) for k in range(n + 1)]
    pmf_k = np.arange(n + 1)
    for p in np.linspace(0.01, 0.99, 99):
        inside = np.array([lo <= p <= hi for lo, hi in intervals])
        assert binom.pmf(pmf_k, n, p)[inside].sum() >= 0.95 - 1e-12, p


def test_wilson_interval_matches_scipy() -> None:
    for n in (1, 7, 60):
        for k in range(n + 1):
            for level in (0.95, 0.9):
                ci = binomtest(k, n).proportion_ci(confidence_level=level, method="wilson")
                assert wilson_interval(k, n, level) == pytest.approx((ci.low, ci.high), abs=1e-12)


def test_paired_difference_interval_matches_published_values() -> None:
    # Cavo et al. (2012) paired table [[59, 6], [16, 80]]: Newcombe square-and-add interval
    # -0.0621 (-0.1186 to -0.0046) in Fagerland, Lydersen & Laake (contingencytables, ch. 8)
    diff, low, high = paired_difference_interval(*pairs(59, 6, 16, 80))
    assert (round(diff, 4), round(low, 4), round(high, 4)) == (-0.0621, -0.1186, -0.0046)
    # swapping the players mirrors the interval
    assert paired_difference_interval(*pairs(59, 16, 6, 80)) == pytest.approx(
        (-diff, -high, -low), abs=1e-12
    )


def test_paired_difference_interval_agrees_with_the_normal_approximation_on_many_rallies() -> None:
    a, b, c, d = 1200, 900, 700, 1200
    n = a + b + c + d
    diff, low, high = paired_difference_interval(*pairs(a, b, c, d))
    half = norm.ppf(0.975) * math.sqrt((b + c) - (b - c) ** 2 / n) / n  # paired Wald interval
    assert diff == pytest.approx((b - c) / n)
    assert (low, high) == pytest.approx((diff - half, diff + half), abs=2e-3)
    assert high - low == pytest.approx(2 * half, rel=0.02)


@pytest.mark.parametrize(
    "probs",
    [(0.35, 0.15, 0.10, 0.40), (0.25, 0.25, 0.25, 0.25), (0.55, 0.20, 0.05, 0.20)],
    ids=["correlated", "independent", "first-better"],
)
def test_paired_difference_interval_has_near_nominal_exact_coverage(probs) -> None:
    # every table (a, b, c, d) of 30 rallies weighed by its multinomial probability
    n = 30
    truth = probs[1] - probs[2]
    covered = total = 0.0
    for a, b, c in itertools.product(range(n + 1), repeat=3):
        d = n - a - b - c
        if d < 0:
            continue
        p = multinomial.pmf([a, b, c, d], n, probs)
        _, low, high = paired_difference_interval(*pairs(a, b, c, d))
        covered += p * (low <= truth <= high)
        total += p
    assert total == pytest.approx(1.0)
    # Newcombe (1998) reports coverage close to nominal for this method; allow a little
    # discreteness either way
    assert 0.93 <= covered <= 0.99, covered


def test_paired_difference_interval_edge_cases_and_bad_inputs() -> None:
    same = [True, False, True, True]
    diff, low, high = paired_difference_interval(same, same)
    assert diff == 0 and low < 0 < high
    diff, low, high = paired_difference_interval([1] * 5, [0] * 5)
    assert diff == 1 and high == 1 and 0 < low < 1
    assert -1 <= paired_difference_interval([0] * 5, [1] * 5)[1]
    with pytest.raises(ValueError, match="same length"):
        paired_difference_interval([1, 0], [1])
    with pytest.raises(ValueError, match="same length"):
        paired_difference_interval([], [])
    with pytest.raises(ValueError, match="successes"):
        paired_difference_interval([1, 2], [0, 1])
    with pytest.raises(ValueError, match="confidence"):
        paired_difference_interval([1, 0], [0, 1], confidence=1.5)
    with pytest.raises(ValueError, match="successes <= n"):
        return_rate_interval(5, 4)
    with pytest.raises(ValueError, match="n >= 1"):
        wilson_interval(0, 0)
    with pytest.raises(TypeError, match="successes must be an int"):
        return_rate_interval(2.0, 4)  # type: ignore[arg-type]


def test_mean_sem_against_numpy_and_refuses_failed_scores():
    values = [0.31, 0.27, 0.45, 0.29]
    mean, sem = mean_sem(values)
    assert mean == pytest.approx(np.mean(values), rel=1e-15)
    assert sem == pytest.approx(np.std(values, ddof=1) / np.sqrt(4), rel=1e-14)
    assert mean_sem([0.5]) == (0.5, None)
    for bad in ([], [0.1, float("nan")], [float("inf")]):
        with pytest.raises(ValueError, match="finite"):
            mean_sem(bad)
