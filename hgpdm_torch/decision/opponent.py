"""Delta-safe opponent modelling and strategy learning in repeated games (thesis Ch. 5).

The opponent's stationary strategy is modelled by the KL ball around its empirical distribution,
``Omega(delta) = {pi_j : KL(pi~_j || pi_j) <= eps(delta)}``, which holds the true strategy with
probability at least ``1 - delta`` (Sec. 5.2.1). Player i answers with the generalised best
response of Problem (38), ``max_pi_i min_{pi_j in Omega} pi_i^T R pi_j``; its value is a lower
bound on the true expected reward with the same probability.

Two solvers of Problem (38) share one exact inner step, the worst opponent in the ball, found
through its 1-D concave dual (derived below):

- :class:`DeltaSafeResponder`: projected sub-gradient ascent with warm start, as in the thesis,
  for online play;
- :func:`solve_delta_safe`: Kelley's cutting planes with an LP master, which certifies the
  optimal value to a given gap; the reference the tests hold the online solver to.

On top: the two-sample z-tests and the adaptive learner of Algorithm 5.1, and delta-safe
backward induction on finite-stage stochastic games (Sec. 5.3).

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
import numbers
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from operator import mul

import numpy as np
import torch
from scipy.stats import norm

from hgpdm_torch.decision.games import (
    FiniteStageGame,
    as_array,
    as_rng,
    check_counts,
    check_reward_matrix,
    check_strategy,
    minimax_equilibrium,
    minimax_strategy,
)

__all__ = [
    "AdaptiveLearner",
    "DeltaSafeResponder",
    "KLBall",
    "SafeResponse",
    "TreeResponse",
    "delta_safe_tree",
    "kl_bound",
    "kl_divergence",
    "solve_delta_safe",
    "two_sample_z_test",
]


def _scalar(value: object, name: str, *, integer: bool = False) -> float:
    """``value`` as a Python float (int if ``integer``): Python and NumPy scalars and 0-dim NumPy
    arrays or torch tensors are accepted, booleans are not."""
    kind = "an integer" if integer else "a real number"
    if isinstance(value, torch.Tensor | np.ndarray):
        if value.ndim != 0:
            raise TypeError(f"{name} must be {kind}, got an array of shape {tuple(value.shape)}")
        value = value.item()
    wanted = numbers.Integral if integer else numbers.Real
    if isinstance(value, bool | np.bool_) or not isinstance(value, wanted):
        raise TypeError(f"{name} must be {kind}, got {type(value).__name__}")
    return int(value) if integer else float(value)


def _integer(value: object, name: str, low: int) -> int:
    number = _scalar(value, name, integer=True)
    if number < low:
        raise ValueError(f"{name} must be an integer >= {low}, got {value!r}")
    return int(number)


def _check_tol(tol: object) -> float:
    value = _scalar(tol, "tol")
    if not (math.isfinite(value) and value > 0):
        raise ValueError(f"tol must be positive and finite, got {tol}")
    return value


def _check_probability(value: object, name: str) -> float:
    p = _scalar(value, name)
    if not 0.0 < p < 1.0:
        raise ValueError(f"{name} must lie in (0, 1), got {value}")
    return p


def _check_delta(delta: float) -> float:
    return _check_probability(delta, "delta")


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
    delta = _check_delta(delta)
    n_samples = _integer(n_samples, "n_samples", 0)
    n_actions = _integer(n_actions, "n_actions", 1)
    n_states = _integer(n_states, "n_states", 1)
    if n_samples == 0:
        return math.inf
    return ((n_actions - 1) * math.log1p(n_samples) - math.log(delta / n_states)) / n_samples


_U_FLOOR = -700.0  # exp(-u) must not overflow
_PATH_BUDGET = 1.0  # sub-gradient path length, in simplex units, before the target is lowered
_POLISH_STEPS = 6  # Newton steps on the support face before the cutting planes take over
_FD_STEP = 1e-7  # forward-difference step for the Jacobian of the gains, in simplex units
_FALLBACK_MAX_ITER = 500  # cutting planes after a stalled sub-gradient run (tens suffice)


def _log_expm1(x: float) -> float:
    """``ln(e^x - 1)`` without overflow for large ``x``."""
    return x + math.log1p(-math.exp(-x)) if x > 1.0 else math.log(math.expm1(x))


class _WorstCase:
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
        radius = _scalar(self.radius, "radius")
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
        value, q = _WorstCase(self.center.tolist(), self.radius).solve(c.tolist())
        return value, np.asarray(q)


@dataclass(frozen=True)
class SafeResponse:
    """A solution of Problem (38).

    Attributes:
        strategy: ``[Ai]`` Player i's delta-safe strategy.
        value: its worst-case expected reward over the ball, ``min_{pi_j in Omega} pi_i^T R pi_j``:
            a lower bound on the true expected reward with probability ``>= 1 - delta``.
        upper_bound: ``max_k (R q)_k`` for the best ball member ``q`` found; the optimum of (38)
            lies in ``[value, upper_bound]``.
        opponent: ``[Aj]`` the worst-case opponent in the ball against ``strategy``.
        iterations: solver iterations used (:class:`DeltaSafeResponder`: sub-gradient and
            Newton steps; :func:`solve_delta_safe`: cutting planes).
        cutting_planes: cutting planes :class:`DeltaSafeResponder` needed after its own steps
            to certify the gap (0 when they sufficed).
    """

    strategy: np.ndarray
    value: float
    upper_bound: float
    opponent: np.ndarray
    iterations: int
    cutting_planes: int = 0


def _kl(p: list[float], q: list[float]) -> float:
    """``KL(p || q)`` on lists, ``inf`` where ``q`` misses mass of ``p``."""
    total = 0.0
    for pk, qk in zip(p, q, strict=True):
        if pk > 0.0:
            if qk <= 0.0:
                return math.inf
            total += pk * math.log(pk / qk)
    return total


def _project_simplex(v: list[float]) -> list[float]:
    """Euclidean projection onto the probability simplex (sort and threshold)."""
    u = sorted(v, reverse=True)
    total, theta = 0.0, 0.0
    for i, ui in enumerate(u, start=1):
        total += ui
        t = (total - 1.0) / i
        if ui - t > 0.0:
            theta = t
    return [max(vi - theta, 0.0) for vi in v]


def _tangent_direction(pi: list[float], g: list[float]) -> list[float]:
    """Projection of ``g`` onto the simplex's tangent cone at ``pi``: ``max(g - m, 0)`` on the
    zero entries of ``pi``, ``g - m`` on the others, with ``m`` making the entries sum to zero.

    Ascent along ``g - mean(g)`` would waste most of a step on actions already at zero.
    """
    free = [p > 0.0 for p in pi]
    while True:
        total = n_free = 0
        for gk, f in zip(g, free, strict=True):
            if f:
                total += gk
                n_free += 1
        m = total / n_free
        grow = False
        for k, gk in enumerate(g):
            if not free[k] and gk > m:
                free[k] = grow = True
        if not grow:
            return [gk - m if f else 0.0 for gk, f in zip(g, free, strict=True)]


class DeltaSafeResponder:
    """Problem (38) by projected sub-gradient ascent, warm-started from the previous answer.

    ``phi(pi_i) = min_{q in Omega} pi_i^T R q`` is concave with super-gradient ``R q*`` (``q*``
    the worst opponent, exact from the 1-D dual). Each step moves ``pi_i`` along the
    super-gradient projected onto the simplex's tangent cone, then projects onto the simplex.
    The step follows Polyak's rule towards a target level ``best + level``: the level starts at
    the certified gap and halves when the path walked since the last real ascent exceeds a
    budget (the variable-target rule of Goffin and Kiwiel), so no optimal value is needed.

    Every ball member ``q`` certifies ``max_k (R q)_k`` as an upper bound on the optimum; the
    solver tries the worst opponents, their step-weighted average and the opponent's minimax
    strategy, and stops once the certified gap is small. Consecutive games change the ball only
    a little, so starting from the last strategy (as the thesis does) needs few steps.

    Sub-gradient steps reach a near-optimal value long before a certificate, so each response
    runs, until the certified gap is below tol: Newton steps on the current face of the simplex
    (enough when the warm start's support is still right), sub-gradient steps, Newton steps
    again, and last the cutting planes of :func:`solve_delta_safe` seeded with the best
    strategy (for kinks of phi or when ``max_iter`` runs out). So every response has
    ``upper_bound - value <= tol * (max R - min R)``: ``value`` is within that of the optimum
    of (38), and exact for the returned strategy, so the safety guarantee never depends on
    ``tol``.

    Args:
        reward: ``[Ai, Aj]`` Player i's reward matrix.
        tol: the certified gap ``upper_bound - value`` to reach, relative to the reward range.
        max_iter: the most sub-gradient steps per response before the cutting planes take over.
    """

    def __init__(self, reward: object, *, tol: float = 1e-4, max_iter: int = 200) -> None:
        self.reward = check_reward_matrix(reward)
        self.tol = _check_tol(tol)
        self.max_iter = _integer(max_iter, "max_iter", 0)
        self._rows = self.reward.tolist()
        self._cols = self.reward.T.tolist()
        spread = float(self.reward.max() - self.reward.min())
        self._abs_tol = self.tol * (spread if spread > 0 else 1.0)
        # The opponent's own minimax strategy: when the ball holds it, nothing beats minimax.
        self.minimax, opponent_minimax = minimax_equilibrium(self.reward)
        self.minimax_value = float((self.reward.T @ self.minimax).min())
        self._opponent_minimax = opponent_minimax.tolist()
        self._pi = self.minimax.tolist()

    def reset(self, strategy: object | None = None) -> None:
        """Warm-start the next response from ``strategy`` (default: the minimax strategy)."""
        pi = (
            self.minimax
            if strategy is None
            else check_strategy(strategy, self.reward.shape[0], "strategy")
        )
        self._pi = list(pi)

    def respond(self, counts: object, delta: float, n_states: int = 1) -> SafeResponse:
        """The delta-safe response to observed opponent action counts ``[Aj]``."""
        c = check_counts(counts, self.reward.shape[1])
        n = int(c.sum())
        center = (c / n).tolist() if n > 0 else [1.0 / c.shape[0]] * c.shape[0]
        return self._solve(center, kl_bound(delta, n, c.shape[0], n_states))

    def respond_to(self, ball: KLBall) -> SafeResponse:
        """The delta-safe response to an opponent model ``ball`` (warm-started)."""
        if not isinstance(ball, KLBall):
            raise TypeError(f"ball must be a KLBall, got {type(ball).__name__}")
        if ball.center.shape[0] != self.reward.shape[1]:
            raise ValueError(
                f"ball has {ball.center.shape[0]} actions, reward matrix has {self.reward.shape[1]}"
            )
        return self._solve(ball.center.tolist(), ball.radius)

    def _solve(self, center: list[float], radius: float) -> SafeResponse:
        worst = _WorstCase(center, radius)
        if math.isinf(radius):  # no data: (38) is the minimax problem, solved exactly by the LP
            self._pi = self.minimax.tolist()
            v, q = worst.solve(self._payoff(self._pi))
            return self._result(self._pi, v, v, q, 0)
        pi = self._pi
        v, q = worst.solve(self._payoff(pi))
        upper = max(self._gain(q))
        if _kl(center, self._opponent_minimax) <= radius:  # certifies minimax at a kink of phi
            upper = min(upper, max(self._gain(self._opponent_minimax)))
        q_avg, it = q, 0
        # Warm start: when the support is unchanged since the last game, Newton steps alone
        # finish; otherwise sub-gradient steps find the new face first.
        for phase in ("polish", "ascend", "polish"):
            if upper - v <= self._abs_tol:
                break
            if phase == "polish":
                pi, v, q, upper, steps = self._polish(worst, pi, v, q, upper)
            else:
                pi, v, q, upper, q_avg, steps = self._ascend(worst, pi, v, q, upper)
            it += steps
        planes = 0
        if upper - v > self._abs_tol:
            # Still no certificate (a kink of phi, or max_iter): finish with the cutting
            # planes, seeded with the best strategy and the averaged opponent.
            exact = _cutting_planes(
                self.reward,
                worst,
                np.asarray(pi),
                self._abs_tol,
                _FALLBACK_MAX_ITER,
                opponents=(q, q_avg),
            )
            upper, planes = min(upper, exact.upper_bound), exact.iterations
            if exact.value > v:
                pi, v, q = exact.strategy.tolist(), exact.value, exact.opponent
            if upper - v > self._abs_tol:
                raise RuntimeError(
                    f"Problem (38) not certified to tol after {_FALLBACK_MAX_ITER} cutting "
                    f"planes: gap {upper - v:.3g} > {self._abs_tol:.3g}"
                )
        self._pi = pi
        return self._result(pi, v, upper, q, it, planes)

    def _ascend(
        self, worst: _WorstCase, pi: list[float], v: float, q: list[float], upper: float
    ) -> tuple[list[float], float, list[float], float, list[float], int]:
        """Projected sub-gradient ascent with the variable-target Polyak step (class docstring).

        Returns:
            ``(best pi, its value, its worst opponent, upper_bound, averaged opponent, steps)``;
            stops at a certificate, when the target level falls below tol, or at ``max_iter``.
        """
        best_v, best_pi, best_q = v, pi, q
        g = self._gain(q)
        level = upper - best_v
        path, it = 0.0, 0
        q_sum, weight = [0.0] * len(q), 0.0  # step-weighted average of the worst opponents
        while it < self.max_iter and upper - best_v > self._abs_tol and level > self._abs_tol:
            it += 1
            d = _tangent_direction(pi, g)
            norm2 = sum(map(mul, d, d))
            if norm2 == 0.0:  # pi is a best response to a ball member: certified optimal
                upper = min(upper, v)
                break
            step = (best_v + level - v) / norm2
            path += step * math.sqrt(norm2)
            pi = _project_simplex([pk + step * dk for pk, dk in zip(pi, d, strict=True)])
            v, q = worst.solve(self._payoff(pi))
            g = self._gain(q)
            # The ball is convex, so the average opponent is a member too; near a kink of phi
            # the single worst opponents jump around while their average settles, and its best
            # answer gives the tight upper bound.
            weight += step
            q_sum = [a + step * b for a, b in zip(q_sum, q, strict=True)]
            upper = min(upper, max(g), max(self._gain([a / weight for a in q_sum])))
            if v >= best_v + 0.5 * level:  # enough ascent: the target is reachable, keep it
                path = 0.0
            if v > best_v:
                best_v, best_pi, best_q = v, pi, q
            if path > _PATH_BUDGET:  # oscillating: lower the target, restart from the best
                level *= 0.5
                path = 0.0
                pi, v, q = best_pi, best_v, best_q
                g = self._gain(q)
            level = min(level, upper - best_v)
        q_avg = [a / weight for a in q_sum] if weight > 0.0 else best_q
        return best_pi, best_v, best_q, upper, q_avg, it

    def _polish(
        self, worst: _WorstCase, pi: list[float], v: float, q: list[float], upper: float
    ) -> tuple[list[float], float, list[float], float, int]:
        """Newton steps on the face of the simplex that holds ``pi``.

        Sub-gradient steps reach a near-optimal value long before a certificate: where phi is
        smooth its certificate ``max_k (R q)_k - phi(pi)`` shrinks only like the distance to the
        optimum, the value error like its square. At the optimum the gains ``R q*(pi)`` of the
        actions in the support are equal, so each step solves the linearised equations
        ``g_S + J_SS d = m 1, sum(d) = 0`` (``J`` by forward differences) for the move ``d``
        and the common gain ``m``. Stops when a step does not raise the value.

        Returns:
            ``(pi, value, q, upper_bound, steps)``.
        """
        for step in range(1, _POLISH_STEPS + 1):
            support = [k for k, pk in enumerate(pi) if pk > 0.0]
            g = np.asarray(self._gain(q))[support]
            jac = np.empty((len(support), len(support)))
            for col, k in enumerate(support):
                shifted = list(pi)
                shifted[k] += _FD_STEP
                g_k = self._gain(worst.solve(self._payoff(shifted))[1])
                upper = min(upper, max(g_k))  # every worst opponent is a ball member
                jac[:, col] = (np.asarray(g_k)[support] - g) / _FD_STEP
            n_s = len(support)
            system = np.block([[jac, -np.ones((n_s, 1))], [np.ones((1, n_s)), np.zeros((1, 1))]])
            move = np.linalg.lstsq(system, np.r_[-g, 0.0], rcond=None)[0][:n_s]
            trial = list(pi)
            for k, dk in zip(support, move, strict=True):
                trial[k] += float(dk)
            trial = _project_simplex(trial)
            v_new, q_new = worst.solve(self._payoff(trial))
            upper = min(upper, max(self._gain(q_new)))
            if v_new <= v:
                return pi, v, q, upper, step
            pi, v, q = trial, v_new, q_new
            if upper - v <= self._abs_tol:
                break
        return pi, v, q, upper, step

    def _payoff(self, pi: list[float]) -> list[float]:
        """``R^T pi`` ``[Aj]``."""
        return [sum(map(mul, pi, col)) for col in self._cols]

    def _gain(self, q: list[float]) -> list[float]:
        """``R q`` ``[Ai]``: the super-gradient of phi and the payoff of each pure answer to q."""
        return [sum(map(mul, row, q)) for row in self._rows]

    @staticmethod
    def _result(
        pi: list[float], v: float, upper: float, q: object, it: int, planes: int = 0
    ) -> SafeResponse:
        return SafeResponse(np.asarray(pi), v, max(upper, v), np.asarray(q), it, planes)


def solve_delta_safe(
    reward: object,
    counts: object | None = None,
    delta: float | None = None,
    *,
    ball: KLBall | None = None,
    n_states: int = 1,
    tol: float = 1e-7,
    max_iter: int = 500,
) -> SafeResponse:
    """Problem (38) to a certified gap: Kelley's cutting planes with an LP master problem.

    Every worst-case opponent ``q_l`` found so far is a member of the ball, so the LP
    ``max_{pi, v} v  s.t.  v <= pi^T R q_l`` over-estimates the optimum, while the exact inner
    value ``phi(pi)`` of each LP solution under-estimates it. The loop adds the worst opponent
    at the LP solution until the two meet within ``tol`` (the LP's own accuracy is about 1e-8).
    Slower than :class:`DeltaSafeResponder` but with a certificate; the tests use it as the
    reference.

    Args:
        reward: ``[Ai, Aj]`` reward matrix.
        counts: ``[Aj]`` observed opponent action counts (with ``delta``), or
        ball: an explicit opponent model instead.
        delta: confidence parameter in (0, 1).
        n_states: ``|S|`` for the union bound of stochastic games.
        tol: required gap ``upper_bound - value``, absolute.
        max_iter: the most cutting planes.
    """
    r = check_reward_matrix(reward)
    tol = _check_tol(tol)
    max_iter = _integer(max_iter, "max_iter", 1)
    if ball is None:
        if counts is None or delta is None:
            raise ValueError("give either counts and delta, or ball")
        ball = KLBall.from_counts(check_counts(counts, r.shape[1]), delta, n_states)
    elif ball.center.shape[0] != r.shape[1]:
        raise ValueError(f"ball has {ball.center.shape[0]} actions, reward has {r.shape[1]}")
    worst = _WorstCase(ball.center.tolist(), ball.radius)
    return _cutting_planes(r, worst, minimax_strategy(r)[0], tol, max_iter)


def _cutting_planes(
    reward: np.ndarray,
    worst: _WorstCase,
    pi: np.ndarray,
    tol: float,
    max_iter: int,
    opponents: Sequence[Sequence[float]] = (),
) -> SafeResponse:
    """Kelley's cutting planes for Problem (38), from strategy ``pi`` ``[Ai]``.

    ``opponents`` are ball members already known. The master problem
    ``max_{pi, v} v  s.t.  v <= pi^T R q_l`` is the minimax game of the ``[Ai, L]`` cut matrix
    (on the matrix over the reward range: HiGHS's tolerances are absolute). Its dual mixes the
    ``q_l`` into one ball member ``q`` (the ball is convex), and ``max_k (R q)_k`` bounds the
    optimum from above whatever the LP's accuracy.
    """
    spread = float(np.ptp(reward))
    scale = spread if spread > 0 else 1.0
    members = [np.asarray(q, dtype=float) for q in opponents]
    best_v, best_pi, best_q = -math.inf, pi, pi
    upper = math.inf
    it = 0
    while it < max_iter:
        it += 1
        v, q = worst.solve((reward.T @ pi).tolist())
        if v > best_v:
            best_v, best_pi, best_q = v, pi, np.asarray(q)
        members.append(np.asarray(q))
        q_members = np.stack(members, axis=1)  # [Aj, L]
        pi, weights = minimax_equilibrium(reward @ q_members / scale)
        upper = min(upper, float((reward @ (q_members @ weights)).max()))
        if upper - best_v <= tol:
            break
    return SafeResponse(best_pi, best_v, max(upper, best_v), best_q, it)


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
    alpha = _check_probability(alpha, "alpha")
    nx, ny = x.sum(), y.sum()
    if nx == 0 or ny == 0:
        raise ValueError("counts_x and counts_y must each hold at least one observation")
    mu = (x + y) / (nx + ny)
    sigma = np.sqrt(mu * (1.0 - mu) * (1.0 / nx + 1.0 / ny))
    diff = x / nx - y / ny
    z = np.divide(diff, sigma, out=np.zeros_like(diff), where=sigma > 0)
    return z, bool(np.all(np.abs(z) <= norm.ppf(1.0 - alpha / 2.0)))


@dataclass
class AdaptiveLearner:
    """Algorithm 5.1: delta-safe play against a locally stationary opponent.

    The learner fills a set ``X`` of observed opponent actions, re-solving Problem (38) after
    each one, until it holds ``n_min``. Then it plays in blocks: it collects ``n_min`` new actions
    ``Y`` with its strategy fixed, tests every action's frequency in ``X`` against ``Y``; if all
    tests pass it merges ``Y`` into ``X`` and re-solves, otherwise it empties ``X`` and restarts
    from the minimax strategy. With ``change_detection=False`` it always merges (the thesis's
    simplified version).

    Attributes:
        reward: ``[Ai, Aj]`` Player i's reward matrix.
        delta: confidence parameter in (0, 1), or a function of ``|X|`` giving it (the thesis's
            ``C / (N + 1)``).
        n_min: block size ``N_min``.
        alpha: significance level of each two-sample test.
        change_detection: whether to run the tests.
        tol: solver tolerance of the :class:`DeltaSafeResponder`.
        max_iter: solver iteration limit of the :class:`DeltaSafeResponder`.
        generator: randomness of :meth:`act`, taken once so that successive calls draw fresh
            actions: a NumPy or seeded torch generator, or an int seed. ``None`` (default) for
            a learner that only computes strategies; :meth:`act` then raises.
        resets: the game indices (0-based, counted over observations) at which a change was
            detected.
    """

    reward: object
    delta: float | Callable[[int], float] = 0.1
    n_min: int = 256
    alpha: float = 0.01
    change_detection: bool = True
    tol: float = 1e-4
    max_iter: int = 200
    generator: np.random.Generator | torch.Generator | int | None = None
    resets: list[int] = field(default_factory=list, init=False)

    def __post_init__(self) -> None:
        self.responder = DeltaSafeResponder(self.reward, tol=self.tol, max_iter=self.max_iter)
        self.reward = self.responder.reward
        if not callable(self.delta):
            self.delta = _check_delta(self.delta)
        self.n_min = _integer(self.n_min, "n_min", 1)
        self.alpha = _check_probability(self.alpha, "alpha")
        n_j = self.reward.shape[1]
        self._x = np.zeros(n_j, dtype=np.int64)
        self._y = np.zeros(n_j, dtype=np.int64)
        self._games = 0
        self.strategy = self.responder.minimax.copy()
        self.bound = self.responder.minimax_value
        self._rng = None if self.generator is None else as_rng(self.generator)

    def act(self) -> int:
        """Draw Player i's action from the current strategy (Alg. 5.1 line 5)."""
        if self._rng is None:
            raise ValueError("act needs randomness: construct the learner with generator=...")
        return int(self._rng.choice(self.strategy.shape[0], p=self.strategy))

    def observe(self, action: int) -> None:
        """Record the opponent's action ``a_j`` and update the strategy (Alg. 5.1 lines 6-17)."""
        n_j = self.reward.shape[1]
        try:
            index = _scalar(action, "action", integer=True)
        except TypeError:
            index = -1
        if not 0 <= index < n_j:
            raise ValueError(f"action must be an integer in [0, {n_j}), got {action!r}")
        action = int(index)
        self._games += 1
        if self._x.sum() < self.n_min:  # lines 4-8: grow X, re-solve after every sample
            self._x[action] += 1
            self._solve()
            return
        self._y[action] += 1
        if self._y.sum() < self.n_min:  # line 10: Y is gathered with the strategy fixed
            return
        passed = not self.change_detection or two_sample_z_test(self._x, self._y, self.alpha)[1]
        if passed:  # lines 12-14
            self._x += self._y
            self._solve()
        else:  # lines 16-17
            self.resets.append(self._games - 1)
            self._x[:] = 0
            self.responder.reset()
            self.strategy = self.responder.minimax.copy()
            self.bound = self.responder.minimax_value
        self._y[:] = 0

    @property
    def counts(self) -> np.ndarray:
        """``[Aj]`` the action counts in ``X``, the model's data."""
        return self._x.copy()

    def _solve(self) -> None:
        n = int(self._x.sum())
        delta = self.delta(n) if callable(self.delta) else self.delta
        res = self.responder.respond(self._x, _check_delta(delta))
        self.strategy, self.bound = res.strategy, res.value


@dataclass(frozen=True)
class TreeResponse:
    """Delta-safe strategies on a finite-stage game.

    Attributes:
        strategies: per state, Player i's ``[Ai_s]`` local strategy.
        values: ``[|S|]`` delta-safe lower bounds on the expected return from each state.
        opponents: per state, the ``[Aj_s]`` worst-case opponent in that state's ball.
    """

    strategies: list[np.ndarray]
    values: np.ndarray
    opponents: list[np.ndarray]


def delta_safe_tree(
    game: FiniteStageGame,
    counts: Sequence[object],
    delta: float,
    *,
    method: str = "subgradient",
    tol: float = 1e-6,
    max_iter: int = 500,
) -> TreeResponse:
    """Delta-safe backward induction on a finite-stage stochastic game (Sec. 5.3).

    Each state ``s`` has its own ball with radius ``eps(delta / |S|, N_s)``, so all of them hold
    the true local strategies together with probability ``>= 1 - delta``. From the leaves up,
    state ``s`` plays Problem (38) on ``R^s + sum_k P_s(s_k | a_i, a_j) V(s_k)``, where ``V`` are
    the children's delta-safe values; the root value then lower-bounds the true expected
    return of the learned strategies with the same probability.

    Args:
        game: the tree of states.
        counts: per state, ``[Aj_s]`` observed opponent action counts at that state.
        delta: confidence parameter in (0, 1).
        method: ``"subgradient"`` (:class:`DeltaSafeResponder`) or ``"exact"``
            (:func:`solve_delta_safe`).
        tol: solver tolerance.
        max_iter: solver iteration limit.
    """
    if not isinstance(game, FiniteStageGame):
        raise TypeError(f"game must be a FiniteStageGame, got {type(game).__name__}")
    if method not in ("subgradient", "exact"):
        raise ValueError(f"unknown method {method!r}; expected 'subgradient' or 'exact'")
    if len(counts) != game.n_states:
        raise ValueError(
            f"counts must hold one vector per state ({game.n_states}), got {len(counts)}"
        )
    delta = _check_delta(delta)
    values = np.zeros(game.n_states)
    strategies: list[np.ndarray] = [np.zeros(0)] * game.n_states
    opponents: list[np.ndarray] = [np.zeros(0)] * game.n_states
    for s in game.bottom_up():
        m = game.continuation_matrix(s, values[list(game.children[s])])
        c = check_counts(counts[s], m.shape[1], f"counts[{s}]")
        ball = KLBall.from_counts(c, delta, game.n_states)
        if method == "exact":
            res = solve_delta_safe(m, ball=ball, tol=tol, max_iter=max_iter)
        else:
            res = DeltaSafeResponder(m, tol=tol, max_iter=max_iter).respond_to(ball)
        strategies[s], values[s], opponents[s] = res.strategy, res.value, res.opponent
    return TreeResponse(strategies, values, opponents)
