"""Policies of the anticipation stopping problem (thesis Sec. 4.3), as the protocol compares them.

Each is a :data:`~hgpdm_torch.decision.stopping.Policy` for
:meth:`~hgpdm_torch.decision.stopping.StoppingProblem.run`: greedy on learned stopping values
(:func:`greedy_policy`), waiting until a fixed time (:func:`fixed_time_policy`, with values from
:func:`stop_only_q`), or Monte-Carlo planning on the beliefs (:func:`mcp_policy`).
"""

from __future__ import annotations

from collections.abc import Callable

import torch

from ..validation import as_tensor, check_choice
from .basis import MomentBasis, RadialBasis
from .beliefs import Beliefs
from .lspi import LinearQ, lspi
from .mcp import WAIT_VALUES, EarlyStopping, MonteCarloPlanner, particle_value
from .sources import FEATURES, BeliefTrack
from .stopping import WAIT, Policy, StoppingProblem

__all__ = [
    "blind_choice",
    "choose_source",
    "cv_return_rate",
    "decision_basis",
    "fixed_time_choice",
    "fixed_time_policy",
    "greedy_policy",
    "learn_stopping",
    "mcp_policy",
    "planning_policy",
    "stop_only_q",
]


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
    """Monte-Carlo planning (Algorithm 4.3) on the beliefs of the trials ``test`` (particles
    valued by the planner's ``wait_value``)."""

    def policy(beliefs: torch.Tensor, t: int, idx: torch.Tensor) -> torch.Tensor:
        actions = [
            planner.decide(
                fold.belief(int(test[i]), t),
                can_wait=t < horizon - 1,
                can_wait_next=t + 1 < horizon - 1,
                generator=gen,
            )  # fmt: skip
            for i in idx.tolist()
        ]
        return torch.tensor([d.action for d in actions], dtype=torch.long)

    return policy


def planning_policy(
    track: BeliefTrack,
    test: torch.Tensor,
    q: LinearQ,
    basis: Callable[[torch.Tensor], torch.Tensor],
    rule: EarlyStopping,
    horizon: int,
    features: str = "moments",
    generator: torch.Generator | None = None,
    wait_value: str = "lspi",
) -> Policy:
    """Monte-Carlo planning (Algorithms 4.2-4.3) on any belief source: at each step, the
    stopping values of the belief of stroke ``test[i]`` against the sampled values of waiting
    one step (particles from :meth:`BeliefTrack.draw_next`), each particle valued by
    :func:`~hgpdm_torch.decision.mcp.particle_value`: with ``wait_value="lspi"`` (default) by
    the best of LSPI's values there, waiting included where the next step may wait; with
    ``"stop"`` by its best stopping value (Algorithm 4.2 as printed)."""
    check_choice(wait_value, "wait_value", WAIT_VALUES)
    vectors = track.vectors(features)

    def stop_values(v: torch.Tensor) -> torch.Tensor:
        return q.values(basis(v))[..., WAIT + 1 :]

    def policy(beliefs: torch.Tensor, t: int, idx: torch.Tensor) -> torch.Tensor:
        actions = []
        for i in idx.tolist():
            trial = int(test[i])

            def draw(m: int, trial: int = trial) -> torch.Tensor:
                nxt = track.draw_next(trial, t, m, generator, features)
                return particle_value(q.values(basis(nxt)), wait_value, t + 1 < horizon - 1)

            decision = rule.choose(stop_values(vectors[trial, t]), draw, can_wait=t < horizon - 1)
            actions.append(decision.action)
        return torch.tensor(actions, dtype=torch.long)

    return policy


def decision_basis(
    features: str, states: torch.Tensor, num_steps: int, *, centres: int = 20, seed: int = 0
) -> MomentBasis | RadialBasis:
    """The state features of a belief source's vectors: a :class:`MomentBasis` for
    ``features="moments"``, else RBFs on K-means centres of the training ``states [M, F]``
    (Eq. 37, with a constant feature)."""
    check_choice(features, "features", FEATURES)
    if features == "moments":
        return MomentBasis(num_steps).fit(states)
    return RadialBasis(centres, seed=seed, bias=True).fit(states)


def blind_choice(rewards: torch.Tensor) -> tuple[int, int]:
    """The best *blind* strategy on training strokes ``rewards [n, S, T]``: the (movement index,
    step) returning most of them (the first on ties), one movement at one start time for every
    stroke, no belief."""
    rewards = as_tensor(rewards, "rewards", ndim=3)
    wins = (rewards > 0).sum(0)
    a, t = divmod(int(wins.flatten().argmax()), wins.shape[1])
    return a, t


def fixed_time_choice(
    problem: StoppingProblem, basis: Callable[[torch.Tensor], torch.Tensor], ridge: float
) -> tuple[int, LinearQ]:
    """The best *fixed-time* strategy on the training ``problem``: for every step, stopping
    values learned from that step's rewards (:func:`stop_only_q`); the step whose greedy
    movement returns most training strokes (the first on ties), with its values."""
    best = None
    for step in range(problem.horizon):
        q = stop_only_q(problem, step, basis, ridge)
        wins = int((problem.run(fixed_time_policy(q, basis, step)).reward > 0).sum())
        if best is None or wins > best[0]:
            best = (wins, step, q)
    return best[1], best[2]


def cv_return_rate(
    vectors: torch.Tensor, rewards: torch.Tensor, features: str, *, folds: int = 3,
    centres: int = 20, ridge: float = 1e-3, seed: int = 0,
) -> float:  # fmt: skip
    """The return rate of LSPI's greedy player by ``folds``-fold cross-validation over the given
    strokes (``vectors [n, T, F]`` of one belief source, ``rewards [n, S, T]``): how the
    players choose their belief source on training strokes only."""
    vectors = as_tensor(vectors, "vectors", ndim=3)
    rewards = as_tensor(rewards, "rewards", ndim=3, dtype=vectors.dtype)
    n = len(vectors)
    if n < 2 * folds:
        raise ValueError(f"cv_return_rate needs at least {2 * folds} strokes, got {n}")
    gen = torch.Generator().manual_seed(seed)
    fold_of = torch.empty(n, dtype=torch.long)
    fold_of[torch.randperm(n, generator=gen)] = torch.arange(n) % folds
    problem = StoppingProblem(vectors, rewards)
    won = 0
    for k in range(folds):
        train = problem.subset(torch.nonzero(fold_of != k).flatten())
        test = problem.subset(torch.nonzero(fold_of == k).flatten())
        basis, q = learn_stopping(train, features, centres=centres, ridge=ridge, seed=seed)
        won += int((test.run(greedy_policy(q, basis, test)).reward > 0).sum())
    return won / n


def learn_stopping(
    problem: StoppingProblem, features: str, *, centres: int = 20, ridge: float = 1e-3,
    seed: int = 0,
) -> tuple[MomentBasis | RadialBasis, LinearQ]:  # fmt: skip
    """The state features (:func:`decision_basis`) of a training ``problem``'s beliefs and LSPI's
    values learned from its enumerated episodes."""
    basis = decision_basis(features, problem.beliefs.flatten(0, 1), problem.horizon,
                           centres=centres, seed=seed)  # fmt: skip
    transitions = problem.transitions(problem.enumerate_episodes(), unique=True)
    return basis, lspi(transitions, features=basis, ridge=ridge).q


def choose_source(
    vectors: dict[str, torch.Tensor], rewards: torch.Tensor, candidates: tuple[str, ...],
    features: str, *, centres: int = 20, ridge: float = 1e-3, seed: int = 0,
) -> tuple[str, dict[str, float]]:  # fmt: skip
    """The belief source the players decide on: of ``candidates``, the one whose
    :func:`cv_return_rate` on the training strokes (``vectors[source] [n, T, F]``,
    ``rewards [n, S, T]``) is largest, the first on ties; with one candidate, it (no CV).
    Returns the source and the rates."""
    if len(candidates) == 1:
        return candidates[0], {}
    rates = {
        src: cv_return_rate(
            vectors[src], rewards, features, centres=centres, ridge=ridge, seed=seed
        )  # fmt: skip
        for src in candidates
    }
    return max(candidates, key=rates.__getitem__), rates
