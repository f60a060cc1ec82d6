"""The delta-safe opponent model: the KL ball around the empirical strategy (Sec. 5.2.1).

``Omega(delta) = {pi_j : KL(pi~_j || pi_j) <= eps(delta)}`` holds the opponent's true stationary
strategy with probability at least ``1 - delta``: :func:`kl_bound` is the radius, :class:`KLBall`
the ball, and its exact worst case (``WorstCase``, not re-exported) the inner step that both solvers
of Problem (38) share.

Inner problem and its dual. For a payoff vector ``c = R^T pi_i`` ``[Aj]``, empirical ``p`` and
radius ``eps``, ``min {c^T q : q in simplex, KL(p || q) <= eps}`` has the Lagrange dual

    max_{mu <= min_k c_k}  mu + exp(-eps) prod_{k: p_k > 0} (c_k - mu)^{p_k},

a concave problem in one variable. At an interior maximiser the worst opponent is
``q_k = p_k r_k / sum_l p_l r_l`` with ``r_k = (c_s - mu) / (c_k - mu)`` (``c_s`` the smallest
payoff on the support of ``p``), and ``KL(p || q) = eps`` exactly; at the boundary
``mu = min_k c_k`` the mass the ball leaves free goes to the cheapest unobserved action.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from hgpdm_torch.decision.games import as_array, check_counts, check_strategy
from hgpdm_torch.decision.opponent._checks import as_integer, as_scalar, check_delta

__all__ = [
    "KLBall",
    "kl_bound",
    "kl_divergence",
]


def kl_divergence(p: object, q: object) -> float:
    """``KL(p || q) = sum_k p_k ln(p_k / q_k)`` with ``0 ln 0 = 0``; ``inf`` if ``q`` misses
    mass that ``p`` has.

    Args:
        p: ``[A]`` probability vector.
        q: ``[A]`` probability vector.
    """
    p_ = check_strategy(p, None, "p")
    q_ = check_strategy(q, p_.shape[0], "q")
    on = p_ > 0
    if (q_[on] <= 0).any():
        return math.inf
    return float(np.sum(p_[on] * np.log(p_[on] / q_[on])))


def kl_bound(delta: float, n_samples: int, n_actions: int, n_states: int = 1) -> float:
    """The KL radius ``eps(delta / |S|, N)`` of Sec. 5.2.1 and 5.3.

    ``eps = ((|Aj| - 1) ln(N + 1) - ln(delta / |S|)) / N``: by the method of types (Cover and
    Thomas, Thm. 12.2.1) the empirical distribution of ``N`` draws is within ``eps`` of the true
    one in KL with probability at least ``1 - delta / |S|``.

    Args:
        delta: confidence parameter in (0, 1).
        n_samples: ``N >= 0`` observations; ``N = 0`` gives ``inf`` (nothing is known).
        n_actions: ``|Aj| >= 1`` opponent actions.
        n_states: ``|S|`` models that must hold together (union bound); 1 for a normal-form game.
    """
    delta = check_delta(delta)
    n_samples = as_integer(n_samples, "n_samples", 0)
    n_actions = as_integer(n_actions, "n_actions", 1)
    n_states = as_integer(n_states, "n_states", 1)
    if n_samples == 0:
        return math.inf
    return ((n_actions - 1) * math.log1p(n_samples) - math.log(delta / n_states)) / n_samples


_U_FLOOR = -700.0  # exp(-u) must not overflow


def _log_expm1(x: float) -> float:
    """``ln(e^x - 1)`` without overflow for large ``x``."""
    return x + math.log1p(-math.exp(-x)) if x > 1.0 else math.log(math.expm1(x))


class WorstCase:
    """The inner minimisation ``min_{q in Omega} c^T q`` for one ball, solved through its dual.

    Works on Python floats: for the handful of actions of these games, NumPy's per-call overhead
    would dominate the sub-gradient loop that calls this hundreds of times per response.
    """

    def __init__(self, center: Sequence[float], radius: float) -> None:
        self.n = len(center)
        self.radius = radius
        self.support = [k for k in range(self.n) if center[k] > 0]
        self.ps = [center[k] for k in self.support]
        self.center = list(center)
        self.w = math.exp(-radius)  # e^-eps, also right for eps = inf
        self.u = None  # last root, the warm start of the next call

    def solve(self, c: Sequence[float]) -> tuple[float, list[float]]:
        """Returns ``(min value, worst-case q)`` for payoffs ``c`` ``[Aj]``.

        The dual variable is parametrised as ``mu = c_s - e^u``; the stationarity condition
        ``sum_k q_k(mu) = 1`` becomes ``y(u) = 0`` with ``y`` decreasing in ``u``, solved by
        Newton's method inside a bracket and warm-started from the previous root.
        """
        n, eps = self.n, self.radius
        k_min = min(range(n), key=c.__getitem__)
        c_all = c[k_min]
        q = [0.0] * n
        if math.isinf(eps):
            q[k_min] = 1.0
            return c_all, q
        cs = [c[k] for k in self.support]
        c_s = min(cs)
        d = [ck - c_s for ck in cs]
        spread = sum(pk * dk for pk, dk in zip(self.ps, d, strict=True))
        if spread <= 1e-15 * max(1.0, abs(c_s)) or eps == 0.0:
            # c is flat on the support (or the ball is a point): the dual optimum is the
            # boundary mu = min c and the ball's free mass 1 - e^-eps sits on the cheapest action.
            w = 1.0 if eps == 0.0 else self.w
            for k in self.support:
                q[k] = w * self.center[k]
            q[k_min] += 1.0 - w
            return sum(ck * qk for ck, qk in zip(c, q, strict=True)), q
        # y(u_hi) <= 0 by AM-GM; below the floor mu is within e^-700 of c_s, as good as there
        u_hi = max(math.log(spread) - _log_expm1(eps), _U_FLOOR)
        u_lo = -math.inf  # y > 0 below u_lo; unknown yet unless the boundary is checked
        if c_all < c_s:
            u_lo = max(math.log(c_s - c_all), _U_FLOOR)
            y, _, r, s = self._y(u_lo, d)
            if y <= 0.0:  # boundary: mu = min c, the leftover mass goes to k_min
                scale = math.exp(y) / s  # = e^{a - eps}
                for k, pk, rk in zip(self.support, self.ps, r, strict=True):
                    q[k] = scale * pk * rk
                q[k_min] += 1.0 - sum(q)
                return sum(ck * qk for ck, qk in zip(c, q, strict=True)), q
        lo_known = u_lo > -math.inf  # whether y(u_lo) > 0 was seen; else u_lo is a floor
        u_lo = max(u_lo, _U_FLOOR)
        u = self.u if self.u is not None and u_lo < self.u < u_hi else u_hi
        for _ in range(100):  # safeguarded Newton on y(u) = 0, y decreasing in u
            y, dy, r, s = self._y(u, d)
            if y > 0.0:
                u_lo, lo_known = u, True
            elif u <= _U_FLOOR:  # mu within e^-700 of c_s: the root is numerically there
                break
            else:
                u_hi = u
            # y = KL(p || q) - eps for the q below, and the value moves by y times the KL
            # multiplier (~ 1 / sqrt(eps), 500 at eps = 1e-6): stop at y's rounding level
            if abs(y) < 1e-15 or u_hi - u_lo < 1e-13 * max(1.0, abs(u)):
                break
            step = u - y / dy if dy < 0.0 else u_lo
            if not u_lo < step < u_hi:
                step = 0.5 * (u_lo + u_hi) if lo_known else max(min(step, u_hi - 1.0), u_lo)
            u = step
        self.u = u
        for k, pk, rk in zip(self.support, self.ps, r, strict=True):
            q[k] = pk * rk / s
        return sum(ck * qk for ck, qk in zip(c, q, strict=True)), q

    def _y(self, u: float, d: list[float]) -> tuple[float, float, list[float], float]:
        """``y(u) = ln sum(q)`` at ``mu = c_s - e^u``, its derivative, ``r`` and ``sum p r``."""
        x = math.exp(-u)
        r = []
        s = s2 = a = 0.0
        for pk, dk in zip(self.ps, d, strict=True):
            rk = 1.0 / (1.0 + dk * x)
            r.append(rk)
            prk = pk * rk
            s += prk
            s2 += prk * rk
            a += pk * math.log1p(dk * x)  # -p ln r
        return a - self.radius + math.log(s), s - s2 / s, r, s


@dataclass(frozen=True)
class KLBall:
    """The delta-safe opponent model ``Omega(delta)`` (Sec. 5.2.1).

    Attributes:
        center: ``[Aj]`` the empirical distribution ``pi~_j`` of the observed actions.
        radius: ``eps``, the KL bound; ``inf`` means the whole simplex (no observations). Any
            real scalar (Python, NumPy, 0-dim array or tensor) is stored as a Python float.

    Raises:
        TypeError: a radius that is not a real scalar.
        ValueError: a negative or NaN radius, or a centre that is not a distribution.
    """

    center: np.ndarray
    radius: float

    def __post_init__(self) -> None:
        object.__setattr__(self, "center", check_strategy(self.center, None, "center"))
        radius = as_scalar(self.radius, "radius")
        if math.isnan(radius) or radius < 0:
            raise ValueError(f"radius must be a non-negative float (inf allowed), got {radius}")
        object.__setattr__(self, "radius", radius)

    @classmethod
    def from_counts(cls, counts: object, delta: float, n_states: int = 1) -> KLBall:
        """The ball ``Omega(delta)`` for observed action counts ``[Aj]`` (uniform centre and
        infinite radius when nothing was observed)."""
        c = check_counts(counts, None)
        n = int(c.sum())
        center = c / n if n > 0 else np.full(c.shape[0], 1.0 / c.shape[0])
        return cls(center, kl_bound(delta, n, c.shape[0], n_states))

    def contains(self, strategy: object, atol: float = 1e-12) -> bool:
        """Whether ``KL(center || strategy) <= radius + atol``."""
        return kl_divergence(self.center, strategy) <= self.radius + atol

    def worst_case(self, payoff: object) -> tuple[float, np.ndarray]:
        """``min_{q in Omega} payoff^T q`` and a minimiser, via the 1-D dual (module docstring).

        Args:
            payoff: ``[Aj]`` Player i's payoff for each opponent action, ``R^T pi_i``.

        Returns:
            ``(value, q)`` with ``q`` ``[Aj]`` in the ball.
        """
        c = as_array(payoff, "payoff", 1)
        if c.shape[0] != self.center.shape[0]:
            raise ValueError(
                f"payoff must have {self.center.shape[0]} entries (one per opponent action), "
                f"got {c.shape[0]}"
            )
        value, q = WorstCase(self.center.tolist(), self.radius).solve(c.tolist())
        return value, np.asarray(q)


def kl_of_lists(p: list[float], q: list[float]) -> float:
    """``KL(p || q)`` on lists, ``inf`` where ``q`` misses mass of ``p``."""
    total = 0.0
    for pk, qk in zip(p, q, strict=True):
        if pk > 0.0:
            if qk <= 0.0:
                return math.inf
            total += pk * math.log(pk / qk)
    return total
