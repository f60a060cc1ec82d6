"""Algorithm 5.1: the adaptive learner, delta-safe play against a locally stationary opponent.

:class:`AdaptiveLearner` re-solves Problem (38) with a
:class:`~hgpdm_torch.decision.opponent.responder.DeltaSafeResponder` as observations come in and
restarts when the two-sample tests of
:mod:`~hgpdm_torch.decision.opponent.change_detection` detect that the opponent changed.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
import torch

from hgpdm_torch.decision.games import as_rng
from hgpdm_torch.decision.opponent._checks import (
    as_integer,
    as_scalar,
    check_delta,
    check_open_probability,
)
from hgpdm_torch.decision.opponent.change_detection import two_sample_z_test
from hgpdm_torch.decision.opponent.responder import DeltaSafeResponder

__all__ = [
    "AdaptiveLearner",
]


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
            self.delta = check_delta(self.delta)
        self.n_min = as_integer(self.n_min, "n_min", 1)
        self.alpha = check_open_probability(self.alpha, "alpha")
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
            index = as_scalar(action, "action", integer=True)
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
        res = self.responder.respond(self._x, check_delta(delta))
        self.strategy, self.bound = res.strategy, res.value
