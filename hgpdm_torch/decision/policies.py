"""Policies of the anticipation stopping problem (thesis Sec. 4.3), as the protocol compares them.

Each is a :data:`~hgpdm_torch.decision.stopping.Policy` for
:meth:`~hgpdm_torch.decision.stopping.StoppingProblem.run`: greedy on learned stopping values
(:func:`greedy_policy`), waiting until a fixed time (:func:`fixed_time_policy`, with values from
:func:`stop_only_q`), or Monte-Carlo planning on the beliefs (:func:`mcp_policy`).
"""

from __future__ import annotations

import torch

from .basis import RadialBasis
from .beliefs import Beliefs
from .lspi import LinearQ, lspi
from .mcp import MonteCarloPlanner
from .stopping import WAIT, Policy, StoppingProblem

__all__ = ["fixed_time_policy", "greedy_policy", "mcp_policy", "stop_only_q"]


def stop_only_q(problem: StoppingProblem, step: int, basis: RadialBasis, ridge: float) -> LinearQ:
    """Stopping values learned from the rewards at one step only (oracle timing: no waiting)."""
    n, S = len(problem), problem.num_actions - 1
    trial = torch.arange(n).repeat_interleave(S)
    action = torch.arange(1, S + 1).repeat(n)
    episodes = problem.episodes(trial, torch.full_like(trial, step), action)
    return lspi(problem.transitions(episodes), features=basis, ridge=ridge).q


def greedy_policy(q: LinearQ, basis: RadialBasis, problem: StoppingProblem) -> Policy:
    """The greedy policy of ``q`` on the basis features (waiting only where allowed)."""
    return lambda beliefs, t, idx: q.greedy(basis(beliefs), problem.allowed(t))


def fixed_time_policy(q: LinearQ, basis: RadialBasis, step: int) -> Policy:
    """Wait until ``step``, then start the movement with the largest stopping value."""

    def policy(beliefs: torch.Tensor, t: int, idx: torch.Tensor) -> torch.Tensor:
        if t < step:
            return torch.full_like(idx, WAIT)
        return q.values(basis(beliefs))[:, 1:].argmax(-1) + 1

    return policy


def mcp_policy(
    planner: MonteCarloPlanner,
    fold: Beliefs,
    test: torch.Tensor,
    horizon: int,
    gen: torch.Generator | None = None,
) -> Policy:
    """Monte-Carlo planning (Algorithm 4.3) on the beliefs of the trials ``test``."""

    def policy(beliefs: torch.Tensor, t: int, idx: torch.Tensor) -> torch.Tensor:
        actions = [
            planner.decide(fold.belief(int(test[i]), t), can_wait=t < horizon - 1, generator=gen)
            for i in idx.tolist()
        ]
        return torch.tensor([d.action for d in actions], dtype=torch.long)

    return policy
