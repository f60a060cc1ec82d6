"""Delta-safe backward induction on finite-stage stochastic games (Sec. 5.3).

Every state of the game tree gets its own KL ball; :func:`delta_safe_tree` solves Problem (38)
from the leaves up with the children's delta-safe values as continuation payoffs.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from hgpdm_torch.decision.games import FiniteStageGame, check_counts
from hgpdm_torch.decision.opponent._checks import check_delta
from hgpdm_torch.decision.opponent.cutting_planes import solve_delta_safe
from hgpdm_torch.decision.opponent.kl_ball import KLBall
from hgpdm_torch.decision.opponent.responder import DeltaSafeResponder

__all__ = [
    "TreeResponse",
    "delta_safe_tree",
]


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
    delta = check_delta(delta)
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
