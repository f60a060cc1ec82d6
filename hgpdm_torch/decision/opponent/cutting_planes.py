"""Problem (38) solved to a certified gap by Kelley's cutting planes: the reference solver.

``max_pi_i min_{pi_j in Omega} pi_i^T R pi_j`` over the KL ball ``Omega``: :func:`solve_delta_safe`
alternates the exact worst opponent in the ball with an LP master problem until the two bounds
meet, and returns a :class:`SafeResponse` (the solution type of both solvers). The online
:class:`~hgpdm_torch.decision.opponent.responder.DeltaSafeResponder` finishes with these cutting
planes where its own steps leave a gap, and the tests hold it to this reference.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from hgpdm_torch.decision.games import (
    check_counts,
    check_reward_matrix,
    minimax_equilibrium,
    minimax_strategy,
)
from hgpdm_torch.decision.opponent._checks import as_integer, check_tol
from hgpdm_torch.decision.opponent.kl_ball import KLBall, WorstCase

__all__ = [
    "SafeResponse",
    "solve_delta_safe",
]


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
    tol = check_tol(tol)
    max_iter = as_integer(max_iter, "max_iter", 1)
    if ball is None:
        if counts is None or delta is None:
            raise ValueError("give either counts and delta, or ball")
        ball = KLBall.from_counts(check_counts(counts, r.shape[1]), delta, n_states)
    elif ball.center.shape[0] != r.shape[1]:
        raise ValueError(f"ball has {ball.center.shape[0]} actions, reward has {r.shape[1]}")
    worst = WorstCase(ball.center.tolist(), ball.radius)
    return run_cutting_planes(r, worst, minimax_strategy(r)[0], tol, max_iter)


def run_cutting_planes(
    reward: np.ndarray,
    worst: WorstCase,
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
