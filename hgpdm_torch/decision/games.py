"""Two-player games of thesis Ch. 5: normal-form games, their baselines and finite-stage trees.

Player i is the learner, Player j the opponent. A normal-form game is Player i's reward matrix
``R`` of shape ``[Ai, Aj]``: Player i gets ``R[a_i, a_j]`` for the joint action, so strategies
``pi_i`` ``[Ai]`` and ``pi_j`` ``[Aj]`` earn ``pi_i^T R pi_j`` in expectation (Sec. 5.2).

The baselines of Sec. 5.1 live here: the best response to one opponent model, fictitious play
(best response to the empirical distribution) and the minimax strategy (a linear program). A
finite-stage stochastic game (Sec. 5.3) is a tree of states, each with its own reward matrix and
transition probabilities to its children given the joint action.

Everything is NumPy: the problems are a few actions wide and the solvers run once per game.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import torch
from scipy.optimize import linprog

__all__ = [
    "RPS_REWARD",
    "SERVE_ACTIONS",
    "SERVE_REGIONS",
    "TABLE_TENNIS_REWARD",
    "FiniteStageGame",
    "as_array",
    "as_rng",
    "best_response",
    "check_counts",
    "check_reward_matrix",
    "check_strategy",
    "expected_reward",
    "fictitious_play",
    "minimax_equilibrium",
    "minimax_strategy",
    "sample_counts",
    "two_stage_rps",
]

#: Table 5.1: rock-paper-scissors, rows and columns ordered rock, paper, scissors.
RPS_REWARD = np.array([[0.0, -1.0, 1.0], [1.0, 0.0, -1.0], [-1.0, 1.0, 0.0]])

#: Table 5.3: success rate of the robot's preparation pose (rows) against the region a serve
#: lands in (columns), estimated by the low-level planner from 600 recorded serves.
TABLE_TENNIS_REWARD = np.array([[0.65, 0.52, 0.06], [0.41, 0.74, 0.56], [0.04, 0.12, 0.39]])
SERVE_ACTIONS = ("forehand", "middle", "backhand")
SERVE_REGIONS = ("forehand side", "middle", "backhand side")


# HiGHS's default feasibility tolerances (1e-7) would limit both strategies, and so the
# cutting planes' certificate, to about 1e-7; these tiny LPs afford its tightest.
_LP_TOLERANCES = {"primal_feasibility_tolerance": 1e-10, "dual_feasibility_tolerance": 1e-10}


def as_rng(generator: np.random.Generator | torch.Generator | int) -> np.random.Generator:
    """A NumPy generator from a NumPy generator, a seeded torch generator or an integer seed."""
    if isinstance(generator, np.random.Generator):
        return generator
    if isinstance(generator, torch.Generator):
        seed = int(torch.randint(0, 2**62, (), generator=generator))
        return np.random.default_rng(seed)
    if isinstance(generator, int | np.integer) and not isinstance(generator, bool):
        return np.random.default_rng(int(generator))
    raise TypeError(
        "generator must be a numpy Generator, a torch Generator or an int seed, "
        f"got {type(generator).__name__}"
    )


def as_array(value: object, name: str, ndim: int) -> np.ndarray:
    """``value`` as a finite float64 NumPy array with ``ndim`` dimensions.

    The checks of :mod:`hgpdm_torch.validation` in NumPy: the online learner validates its
    inputs on every game, and a round trip through torch would cost more than the solve.
    """
    if isinstance(value, torch.Tensor):
        value = value.detach().cpu().numpy()
    if isinstance(value, str | bytes) or value is None:
        raise TypeError(f"{name} must be numeric array-like, got {type(value).__name__}")
    try:
        arr = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError) as err:
        raise TypeError(f"{name} must be numeric array-like, got {type(value).__name__}") from err
    if arr.ndim != ndim:
        raise ValueError(f"{name} must have {ndim} dimensions, got shape {arr.shape}")
    if not np.isfinite(arr).all():
        raise ValueError(f"{name} contains NaN or inf; expected finite values")
    return arr


def check_reward_matrix(reward: object, name: str = "reward") -> np.ndarray:
    """Validate a reward matrix: finite, 2-D, at least one action each. Returns ``[Ai, Aj]``."""
    r = as_array(reward, name, 2)
    if r.shape[0] < 1 or r.shape[1] < 1:
        raise ValueError(f"{name} must have at least one row and column, got shape {r.shape}")
    return r


def _action_vector(value: object, n_actions: int | None, name: str, why: str) -> np.ndarray:
    """``value`` as a non-empty ``[n_actions]`` vector (any length if ``None``): the shape
    check of a strategy and of action counts (``why`` says what the length must match)."""
    v = as_array(value, name, 1)
    if n_actions is not None and v.shape[0] != n_actions:
        raise ValueError(f"{name} must have {n_actions} entries {why}, got {v.shape[0]}")
    if v.shape[0] == 0:
        raise ValueError(f"{name} must not be empty")
    return v


def check_strategy(
    strategy: object, n_actions: int | None, name: str, *, atol: float = 1e-8
) -> np.ndarray:
    """Validate a mixed strategy (non-negative, sums to one) of ``n_actions`` entries (any
    number if ``None``).

    Returns:
        ``[n_actions]`` the strategy clipped at zero and renormalised.
    """
    s = _action_vector(strategy, n_actions, name, "to match the reward matrix")
    if (s < -atol).any() or abs(s.sum() - 1.0) > atol:
        raise ValueError(f"{name} must be a probability vector (non-negative, sums to 1), got {s}")
    s = np.clip(s, 0.0, None)
    return s / s.sum()


def check_counts(counts: object, n_actions: int | None, name: str = "counts") -> np.ndarray:
    """Validate observed action counts: non-negative integers, ``[n_actions]`` (any number if
    ``None``). Returns them as float64."""
    c = _action_vector(counts, n_actions, name, "(one per opponent action)")
    if (c < 0).any() or not np.array_equal(c, np.round(c)):
        raise ValueError(f"{name} must hold non-negative integer counts, got {c}")
    return c


def expected_reward(reward: object, strategy_i: object, strategy_j: object) -> float:
    """Player i's expected reward ``pi_i^T R pi_j`` (Sec. 5.2).

    Args:
        reward: ``[Ai, Aj]`` reward matrix of Player i.
        strategy_i: ``[Ai]`` Player i's mixed strategy.
        strategy_j: ``[Aj]`` Player j's mixed strategy.
    """
    r = check_reward_matrix(reward)
    pi_i = check_strategy(strategy_i, r.shape[0], "strategy_i")
    pi_j = check_strategy(strategy_j, r.shape[1], "strategy_j")
    return float(pi_i @ r @ pi_j)


def best_response(reward: object, strategy_j: object) -> np.ndarray:
    """``BR(pi_j) = argmax_pi_i pi_i^T R pi_j`` (Sec. 5.2): uniform over the maximising actions.

    Returns:
        ``[Ai]`` a best-response strategy; ties share the mass equally so the response does not
        depend on action order.
    """
    r = check_reward_matrix(reward)
    payoff = r @ check_strategy(strategy_j, r.shape[1], "strategy_j")
    best = payoff >= payoff.max() - 1e-12 * max(1.0, abs(payoff.max()))
    return best / best.sum()


def fictitious_play(reward: object, counts: object) -> np.ndarray:
    """Fictitious play (Brown 1951): the best response to the empirical opponent distribution.

    Args:
        reward: ``[Ai, Aj]`` reward matrix.
        counts: ``[Aj]`` how often each opponent action was observed; with no observations the
            opponent is modelled as uniform.

    Returns:
        ``[Ai]`` the best response to ``counts / counts.sum()``.
    """
    r = check_reward_matrix(reward)
    c = check_counts(counts, r.shape[1])
    n = c.sum()
    empirical = c / n if n > 0 else np.full(r.shape[1], 1.0 / r.shape[1])
    return best_response(r, empirical)


def minimax_equilibrium(reward: object) -> tuple[np.ndarray, np.ndarray]:
    """Both players' minimax strategies of the zero-sum game ``R`` from one linear program.

    Solves ``max v  s.t.  R^T pi_i >= v 1,  pi_i in simplex`` with scipy's HiGHS ``linprog``;
    ``pi_i`` is its solution and ``pi_j`` its dual (the multipliers of the ``Aj`` constraints,
    which sum to one). Each bounds the game value independently of the LP's accuracy:
    ``min(R^T pi_i) <= value <= max(R pi_j)``.

    The LP sees ``R / max|R|``: both strategies are invariant to a positive scaling of ``R``,
    and HiGHS works in absolute tolerances, so rewards of any magnitude (1e-300 to 1e300) get
    the accuracy of rewards of order one (unscaled, entries near 1e300 are a "Model error" and
    entries near 1e-300 all look alike).

    Returns:
        ``([Ai] pi_i, [Aj] pi_j)``.

    Raises:
        ValueError: ``reward`` is not a finite 2-D array with at least one row and column.
    """
    r = check_reward_matrix(reward)
    biggest = float(np.abs(r).max())
    if biggest > 0:
        r = r / biggest
    n_i, n_j = r.shape
    cost = np.r_[np.zeros(n_i), -1.0]  # minimise -v
    a_ub = np.c_[-r.T, np.ones(n_j)]  # v - (R^T pi)_k <= 0
    a_eq = np.r_[np.ones(n_i), 0.0][None]
    bounds = [(0.0, None)] * n_i + [(None, None)]
    res = linprog(
        cost,
        A_ub=a_ub,
        b_ub=np.zeros(n_j),
        A_eq=a_eq,
        b_eq=[1.0],
        bounds=bounds,
        options=_LP_TOLERANCES,
    )
    if res.status != 0:
        raise RuntimeError(f"minimax LP failed: {res.message}")
    pi = np.clip(res.x[:n_i], 0.0, None)
    q = np.clip(-res.ineqlin.marginals, 0.0, None)  # d(-v)/d b_ub <= 0
    return pi / pi.sum(), q / q.sum()


def minimax_strategy(reward: object) -> tuple[np.ndarray, float]:
    """The maximin strategy ``argmax_pi_i min_pi_j pi_i^T R pi_j`` and its value, by an LP.

    Player i's half of :func:`minimax_equilibrium`. It is Player i's safe strategy without an
    opponent model and the limit of Problem (38) as the opponent model grows to the whole
    simplex.

    Returns:
        ``([Ai] strategy, value)`` with ``value = min(R^T strategy)``, exact for the strategy.
    """
    r = check_reward_matrix(reward)
    pi, _ = minimax_equilibrium(r)
    return pi, float((r.T @ pi).min())


def sample_counts(
    strategy: object, n_samples: int, generator: np.random.Generator | torch.Generator | int
) -> np.ndarray:
    """Counts of ``n_samples`` actions drawn from ``strategy``: one multinomial draw, so 1e8
    games cost no more than ten.

    Returns:
        ``[A]`` int64 counts summing to ``n_samples``.
    """
    if not isinstance(n_samples, int | np.integer) or n_samples < 0:
        raise ValueError(f"n_samples must be a non-negative integer, got {n_samples!r}")
    p = check_strategy(strategy, None, "strategy")
    return as_rng(generator).multinomial(int(n_samples), p)


@dataclass(frozen=True)
class FiniteStageGame:
    """A stochastic game with a finite number of stages, as a tree of states (Sec. 5.3).

    State 0 is the root. ``children[s]`` lists the states that may follow ``s`` (empty for a
    leaf) and ``transitions[s]`` ``[Ai_s, Aj_s, len(children[s])]`` holds
    ``P_s(s_k | a_i, a_j)``. Player i collects ``rewards[s][a_i, a_j]`` at every state it visits;
    its return is the sum over the stages.

    Attributes:
        rewards: per state, the ``[Ai_s, Aj_s]`` reward matrix.
        children: per state, the indices of its child states.
        transitions: per state, ``[Ai_s, Aj_s, n_children]`` transition probabilities (``None``
            or an array with last dim 0 for leaves).

    Any array-likes (nested lists, tensors) are accepted; the instance stores them validated as
    float64 arrays, a leaf's ``None`` as ``zeros((Ai_s, Aj_s, 0))``.
    """

    rewards: tuple[np.ndarray, ...]
    children: tuple[tuple[int, ...], ...]
    transitions: tuple[np.ndarray, ...]

    def __post_init__(self) -> None:
        n = len(self.rewards)
        if n == 0 or len(self.children) != n or len(self.transitions) != n:
            raise ValueError(
                "rewards, children and transitions must be non-empty and have one entry per state, "
                f"got {len(self.rewards)}, {len(self.children)}, {len(self.transitions)}"
            )
        parents = np.zeros(n, dtype=int)
        rewards, children, transitions = [], [], []
        for s in range(n):
            r = check_reward_matrix(self.rewards[s], f"rewards[{s}]")
            kids = tuple(self.children[s])
            if any(isinstance(k, bool) or not isinstance(k, int | np.integer) for k in kids):
                raise TypeError(f"children[{s}] must hold integer state indices, got {kids}")
            kids = tuple(int(k) for k in kids)
            if any(not 0 < k < n for k in kids):
                raise ValueError(f"children[{s}] must index states 1..{n - 1}, got {kids}")
            parents[list(kids)] += 1
            if self.transitions[s] is None and not kids:
                t = np.zeros((*r.shape, 0))
            else:
                t = as_array(self.transitions[s], f"transitions[{s}]", 3)
            if t.shape != (*r.shape, len(kids)):
                raise ValueError(
                    f"transitions[{s}] must have shape {(*r.shape, len(kids))}, got {t.shape}"
                )
            if kids and ((t < 0).any() or not np.allclose(t.sum(-1), 1.0)):
                raise ValueError(f"transitions[{s}] must sum to 1 over the children of state {s}")
            rewards.append(r)
            children.append(kids)
            transitions.append(t)
        if parents[0] != 0 or (parents[1:] != 1).any():
            raise ValueError("children must form a tree rooted at state 0 (one parent per state)")
        # Keep the validated float arrays, not the caller's lists: the methods rely on them.
        object.__setattr__(self, "rewards", tuple(rewards))
        object.__setattr__(self, "children", tuple(children))
        object.__setattr__(self, "transitions", tuple(transitions))

    @property
    def n_states(self) -> int:
        """Number of states ``|S|``."""
        return len(self.rewards)

    def bottom_up(self) -> list[int]:
        """State indices ordered so that every state comes after all of its children."""
        order, stack = [], [0]
        while stack:
            s = stack.pop()
            order.append(s)
            stack.extend(self.children[s])
        return order[::-1]

    def continuation_matrix(self, state: int, child_values: Sequence[float]) -> np.ndarray:
        """``R^s + sum_k P_s(s_k | a_i, a_j) V(s_k)``: the stage reward plus future values.

        Args:
            state: the state ``s``.
            child_values: one value per child of ``s``, in the order of ``children[s]``.

        Returns:
            ``[Ai_s, Aj_s]`` the reward matrix the backward recursion plays at ``s``.
        """
        v = np.asarray(child_values, dtype=float)
        if v.shape != (len(self.children[state]),):
            raise ValueError(
                f"child_values must have one value per child of state {state} "
                f"({len(self.children[state])}), got shape {v.shape}"
            )
        r = self.rewards[state]
        return r + self.transitions[state] @ v if v.size else r.copy()

    def values(self, strategies_i: Sequence[object], strategies_j: Sequence[object]) -> np.ndarray:
        """Expected return from every state when both players follow the given local strategies.

        Returns:
            ``[|S|]`` expected sum of rewards from each state to a leaf.
        """
        pis = self._check_profile(strategies_i, 0, "strategies_i")
        pjs = self._check_profile(strategies_j, 1, "strategies_j")
        v = np.zeros(self.n_states)
        for s in self.bottom_up():
            m = self.continuation_matrix(s, v[list(self.children[s])])
            v[s] = pis[s] @ m @ pjs[s]
        return v

    def best_response(self, strategies_j: Sequence[object]) -> tuple[list[np.ndarray], np.ndarray]:
        """Backward induction against known opponent strategies: the globally optimal return.

        Returns:
            ``(strategies_i, values)``: a best-response local strategy per state and ``[|S|]``
            the optimal expected returns.
        """
        pjs = self._check_profile(strategies_j, 1, "strategies_j")
        v = np.zeros(self.n_states)
        pis: list[np.ndarray] = [np.zeros(0)] * self.n_states
        for s in self.bottom_up():
            m = self.continuation_matrix(s, v[list(self.children[s])])
            pis[s] = best_response(m, pjs[s])
            v[s] = pis[s] @ m @ pjs[s]
        return pis, v

    def _check_profile(
        self, strategies: Sequence[object], axis: int, name: str
    ) -> list[np.ndarray]:
        """One validated ``[A_s]`` strategy per state for the player on ``axis`` of the rewards."""
        if len(strategies) != self.n_states:
            raise ValueError(f"{name} must hold one strategy per state ({self.n_states})")
        return [
            check_strategy(pi, self.rewards[s].shape[axis], f"{name}[{s}]")
            for s, pi in enumerate(strategies)
        ]


def two_stage_rps(stage2_scale: float = 2.0) -> FiniteStageGame:
    """Two-stage rock-paper-scissors (Sec. 5.4.1): a root game and one child per joint action.

    State 0 is Stage 1; state ``1 + 3 a_i + a_j`` follows the joint action ``(a_i, a_j)``
    (actions ordered rock, paper, scissors, so states 1..9 are s_1..s_9 of Table 5.2). Stage 2
    pays ``stage2_scale`` times the Stage 1 reward (twice in the thesis).
    """
    n = 3
    transitions = np.zeros((n, n, n * n))
    for a_i in range(n):
        for a_j in range(n):
            transitions[a_i, a_j, n * a_i + a_j] = 1.0
    leaf = np.zeros((n, n, 0))
    return FiniteStageGame(
        rewards=(RPS_REWARD.copy(),) + (stage2_scale * RPS_REWARD,) * (n * n),
        children=(tuple(range(1, n * n + 1)),) + ((),) * (n * n),
        transitions=(transitions,) + (leaf,) * (n * n),
    )
