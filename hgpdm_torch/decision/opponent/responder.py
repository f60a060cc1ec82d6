"""The online solver of Problem (38): projected sub-gradient ascent, warm-started.

:class:`DeltaSafeResponder` answers a stream of opponent models, each a little different from the
last, as the thesis does in repeated games; every response is certified to a gap, with the
cutting planes of :mod:`~hgpdm_torch.decision.opponent.cutting_planes` as its last resort.
"""

from __future__ import annotations

import math
from operator import mul

import numpy as np

from hgpdm_torch.decision.games import (
    check_counts,
    check_reward_matrix,
    check_strategy,
    minimax_equilibrium,
)
from hgpdm_torch.decision.opponent._checks import as_integer, check_tol
from hgpdm_torch.decision.opponent.cutting_planes import SafeResponse, run_cutting_planes
from hgpdm_torch.decision.opponent.kl_ball import KLBall, WorstCase, kl_bound, kl_of_lists

__all__ = [
    "DeltaSafeResponder",
]


_PATH_BUDGET = 1.0  # sub-gradient path length, in simplex units, before the target is lowered
_POLISH_STEPS = 6  # Newton steps on the support face before the cutting planes take over
_FD_STEP = 1e-7  # forward-difference step for the Jacobian of the gains, in simplex units
_FALLBACK_MAX_ITER = 500  # cutting planes after a stalled sub-gradient run (tens suffice)


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
        self.tol = check_tol(tol)
        self.max_iter = as_integer(max_iter, "max_iter", 0)
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
        worst = WorstCase(center, radius)
        if math.isinf(radius):  # no data: (38) is the minimax problem, solved exactly by the LP
            self._pi = self.minimax.tolist()
            v, q = worst.solve(self._payoff(self._pi))
            return self._result(self._pi, v, v, q, 0)
        pi = self._pi
        v, q = worst.solve(self._payoff(pi))
        upper = max(self._gain(q))
        if (
            kl_of_lists(center, self._opponent_minimax) <= radius
        ):  # certifies minimax at a kink of phi
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
            exact = run_cutting_planes(
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
        self, worst: WorstCase, pi: list[float], v: float, q: list[float], upper: float
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
        self, worst: WorstCase, pi: list[float], v: float, q: list[float], upper: float
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
