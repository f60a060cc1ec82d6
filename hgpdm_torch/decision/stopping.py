r"""Anticipatory action selection as optimal stopping on belief states (thesis Sec. 4.2.1, 4.2.3).

At each decision step ``t = 0 .. T-1`` of a trial the robot either waits (action 0) for the next
observation or initiates one of ``S`` hitting movements (actions ``1 .. S``), which ends the
episode with the reward of that movement started at that step (+1 return, -1 miss in Sec. 4.3).
Stopping actions are absorbing: ``Q(theta, a) = R(theta, a)`` for ``a != 0``. At the last step the
robot must stop (waiting longer leaves no time to hit).

A :class:`StoppingProblem` holds, for ``n`` trials, the belief state vectors ``theta_t`` (the
online IDDM belief: latent mean and covariance plus the histogram over the intention grid, or any
feature vector) and the reward of every stopping action at every step (the enumerated reward
table of Sec. 4.3.2). An episode is then fully described by ``(trial, stop step, stop action)``
(:class:`Episodes`); :class:`Transitions` are the samples ``(theta, a, r, theta')`` that LSPI
consumes.

Shapes: ``n`` trials, ``T`` decision steps, ``F`` belief features, ``A = S + 1`` actions,
``E`` episodes, ``L`` transitions.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np
import torch

from ..validation import as_tensor, check_probability

__all__ = [
    "ACTIONS",
    "EXPLORATION",
    "WAIT",
    "Episodes",
    "StoppingProblem",
    "Transitions",
    "belief_vector",
]

ACTIONS = ("wait", "forehand", "middle", "backhand")
"""Action names: the waiting action first, then the stopping actions (hitting movements)."""

WAIT = 0
"""Index of the waiting action."""

EXPLORATION = (0.5, 1.0 / 6.0, 1.0 / 6.0, 1.0 / 6.0)
"""The uniform exploration policy of Sec. 4.3.2: wait 1/2, each movement 1/6."""

Policy = Callable[[torch.Tensor, int, torch.Tensor], torch.Tensor]
"""A deterministic policy ``(beliefs [m, F], step t, trial index [m]) -> actions [m]``; at the
last step it must return a stopping action."""


def belief_vector(mean: torch.Tensor, cov: torch.Tensor, prob: torch.Tensor) -> torch.Tensor:
    """The belief state ``theta`` of Sec. 4.2.5 as one vector.

    Concatenates the latent mean, the upper triangle of the latent covariance (row by row) and
    the histogram over the intention grid: ``F = Dx + Dx (Dx + 1) / 2 + K``.

    Args:
        mean: ``[..., Dx]``; cov: ``[..., Dx, Dx]``; prob: ``[..., K]`` (batch dims broadcast).

    Returns:
        ``[..., F]``.
    """
    mean = as_tensor(mean, "mean", min_ndim=1)
    cov = as_tensor(cov, "cov", min_ndim=2, dtype=mean.dtype)
    prob = as_tensor(prob, "prob", min_ndim=1, dtype=mean.dtype)
    dx = mean.shape[-1]
    if cov.shape[-2:] != (dx, dx):
        raise ValueError(f"cov must have trailing shape [{dx}, {dx}], got {tuple(cov.shape)}")
    batch = torch.broadcast_shapes(mean.shape[:-1], cov.shape[:-2], prob.shape[:-1])
    return belief_vector_unchecked(mean.expand(*batch, dx), cov.expand(*batch, dx, dx), prob)


def belief_vector_unchecked(
    mean: torch.Tensor, cov: torch.Tensor, prob: torch.Tensor
) -> torch.Tensor:
    """:func:`belief_vector` without validation, for hot loops (batch shapes already equal)."""
    rows, cols = torch.triu_indices(mean.shape[-1], mean.shape[-1], device=mean.device)
    prob = prob.expand(*mean.shape[:-1], prob.shape[-1])
    return torch.cat([mean, cov[..., rows, cols], prob], -1)


_INT_DTYPES = (torch.int8, torch.int16, torch.int32, torch.int64, torch.uint8)


def _index_vector(value: object, name: str, low: int, high: int) -> torch.Tensor:
    """``value`` as a 1-D ``long`` tensor with entries in ``low .. high`` (whole numbers only)."""
    if isinstance(value, str | bytes):
        raise TypeError(f"{name} must be a 1-D integer tensor or sequence, got a string")
    if not isinstance(value, torch.Tensor):
        try:
            value = torch.as_tensor(np.asarray(value))
        except (TypeError, ValueError, RuntimeError) as err:
            raise TypeError(
                f"{name} must be a 1-D integer tensor or sequence, got {type(value).__name__}"
            ) from err
    if not (value.is_floating_point() or value.dtype in _INT_DTYPES):
        raise TypeError(f"{name} must hold integers, got dtype {value.dtype}")
    if value.dim() != 1:
        raise ValueError(f"{name} must be 1-D, got shape {tuple(value.shape)}")
    if value.is_floating_point():
        if not bool(torch.isfinite(value).all()):
            raise ValueError(f"{name} must hold finite whole numbers, got NaN or inf")
        if not bool((value == value.round()).all()):
            raise ValueError(f"{name} must hold whole numbers, got fractional entries")
    if value.numel() and bool(((value < low) | (value > high)).any()):
        bad = value[(value < low) | (value > high)][0].item()
        raise ValueError(f"{name} must be in {low} .. {high}, got {bad}")
    return value.to(torch.long)


@dataclass(frozen=True)
class Episodes:
    """``E`` episodes: trial ``i`` waits until ``stop_step`` and then takes ``stop_action``.

    Attributes:
        trial: ``[E]`` trial indices.
        stop_step: ``[E]`` step of the stopping action.
        stop_action: ``[E]`` stopping action in ``1 .. S``.
        reward: ``[E]`` the reward received.
    """

    trial: torch.Tensor
    stop_step: torch.Tensor
    stop_action: torch.Tensor
    reward: torch.Tensor

    def __len__(self) -> int:
        return int(self.trial.shape[0])


@dataclass(frozen=True)
class Transitions:
    """``L`` samples ``(theta, a, r, theta')`` (Sec. 4.2.3).

    Attributes:
        state: ``[L, F]`` belief ``theta``.
        action: ``[L]`` action taken.
        reward: ``[L]`` immediate reward (0 for waiting).
        next_state: ``[L, F]`` next belief ``theta'`` (zeros after a stopping action).
        next_allowed: ``[L, A]`` actions available in ``theta'``; all ``False`` marks the absorbing
            end of the episode (after a stopping action), only stops at the last step.
        trial: ``[L]`` trial each sample came from; ``step``: ``[L]`` its decision step.
    """

    state: torch.Tensor
    action: torch.Tensor
    reward: torch.Tensor
    next_state: torch.Tensor
    next_allowed: torch.Tensor
    trial: torch.Tensor
    step: torch.Tensor

    def __len__(self) -> int:
        return int(self.action.shape[0])


@dataclass(frozen=True)
class StoppingProblem:
    """Belief states and stopping rewards of ``n`` trials.

    Args:
        beliefs: ``[n, T, F]`` belief state vector at each decision step.
        rewards: ``[n, S, T]`` reward of stopping action ``s + 1`` taken at step ``t`` (the
            layout of :func:`hgpdm_torch.robots.table_tennis.trials.reward_table`).
        actions: action names, the waiting action first (``S + 1`` names).
    """

    beliefs: torch.Tensor
    rewards: torch.Tensor
    actions: tuple[str, ...] = ACTIONS

    def __post_init__(self) -> None:
        beliefs = as_tensor(self.beliefs, "beliefs", ndim=3)
        rewards = as_tensor(self.rewards, "rewards", ndim=3, dtype=beliefs.dtype)
        n, T, _ = beliefs.shape
        if n == 0 or T == 0:
            raise ValueError(
                f"beliefs must hold at least one trial and step, got {tuple(beliefs.shape)}"
            )
        if rewards.shape[0] != n or rewards.shape[2] != T:
            raise ValueError(
                f"rewards must have shape [n={n}, S, T={T}] to match beliefs, got "
                f"{tuple(rewards.shape)}"
            )
        actions = tuple(self.actions)
        if len(actions) != rewards.shape[1] + 1 or not all(isinstance(a, str) for a in actions):
            raise ValueError(
                f"actions must name the waiting action and the {rewards.shape[1]} stopping "
                f"actions ({rewards.shape[1] + 1} strings), got {self.actions!r}"
            )
        object.__setattr__(self, "beliefs", beliefs)
        object.__setattr__(self, "rewards", rewards)
        object.__setattr__(self, "actions", actions)

    def __len__(self) -> int:
        return int(self.beliefs.shape[0])

    @property
    def horizon(self) -> int:
        """T, the number of decision steps."""
        return int(self.beliefs.shape[1])

    @property
    def num_actions(self) -> int:
        """A = S + 1."""
        return len(self.actions)

    def subset(self, index: torch.Tensor) -> StoppingProblem:
        """The problem restricted to the trials ``index [m]`` (e.g. one cross-validation fold).

        Raises:
            ValueError: ``index`` not 1-D, not whole numbers, or outside ``0 .. n - 1``.
        """
        index = _index_vector(index, "index", 0, len(self) - 1)
        return StoppingProblem(self.beliefs[index], self.rewards[index], self.actions)

    def allowed(self, step: int) -> torch.Tensor:
        """``[A]`` mask of the actions available at ``step``: waiting is not at the last step."""
        mask = torch.ones(self.num_actions, dtype=torch.bool)
        mask[WAIT] = step < self.horizon - 1
        return mask

    def episodes(
        self,
        trial: torch.Tensor | Sequence[int],
        stop_step: torch.Tensor | Sequence[int],
        stop_action: torch.Tensor | Sequence[int],
    ) -> Episodes:
        """:class:`Episodes` with their rewards looked up in the table.

        Args:
            trial: ``[E]`` trial indices in ``0 .. n-1``.
            stop_step: ``[E]`` steps in ``0 .. T-1``.
            stop_action: ``[E]`` stopping actions in ``1 .. S``.

        All three are 1-D integer tensors, arrays or sequences of the same length (floats are
        accepted only when they hold whole numbers).

        Raises:
            TypeError: for non-numeric or boolean input.
            ValueError: for the wrong shape, unequal lengths, fractional or out-of-range entries.
        """
        trial = _index_vector(trial, "trial", 0, len(self) - 1)
        stop_step = _index_vector(stop_step, "stop_step", 0, self.horizon - 1)
        stop_action = _index_vector(stop_action, "stop_action", 1, self.num_actions - 1)
        if not trial.shape == stop_step.shape == stop_action.shape:
            raise ValueError(
                "trial, stop_step and stop_action must have the same length, got "
                f"{trial.numel()}, {stop_step.numel()} and {stop_action.numel()}"
            )
        reward = self.rewards[trial, stop_action - 1, stop_step]
        return Episodes(trial, stop_step, stop_action, reward)

    def enumerate_episodes(self) -> Episodes:
        """Every (trial, start step, movement) combination of Sec. 4.3.2: ``n T S`` episodes."""
        n, S, T = self.rewards.shape
        grid = torch.cartesian_prod(torch.arange(n), torch.arange(T), torch.arange(1, S + 1))
        return self.episodes(grid[:, 0], grid[:, 1], grid[:, 2])

    def sample_episodes(
        self,
        per_trial: int = 1,
        *,
        probs: torch.Tensor | None = None,
        generator: torch.Generator | None = None,
    ) -> Episodes:
        """Sample episodes by following a stochastic policy on every trial.

        Args:
            per_trial: episodes per trial.
            probs: ``[n, T, A]`` action probabilities in each belief state; the waiting entry of
                the last step is ignored (there the stopping actions are renormalised). Default:
                the uniform exploration policy :data:`EXPLORATION` (wait 1/2, each movement 1/6;
                at the last step each movement 1/3).
            generator: random generator.

        Returns:
            ``n * per_trial`` :class:`Episodes`, trial-major.
        """
        if isinstance(per_trial, bool) or not isinstance(per_trial, int) or per_trial < 1:
            raise ValueError(f"per_trial must be a positive int, got {per_trial!r}")
        n, T, A = len(self), self.horizon, self.num_actions
        if probs is None:
            if A != len(EXPLORATION):
                raise ValueError(
                    f"the default exploration policy has {len(EXPLORATION)} actions; pass probs "
                    f"for a problem with {A}"
                )
            probs = torch.tensor(EXPLORATION, dtype=self.rewards.dtype).expand(n, T, A)
        probs = as_tensor(probs, "probs", ndim=3, dtype=self.rewards.dtype)
        if probs.shape != (n, T, A):
            raise ValueError(f"probs must have shape [{n}, {T}, {A}], got {tuple(probs.shape)}")
        check_probability(probs, "probs")
        p = probs.repeat_interleave(per_trial, dim=0).clone()  # [E, T, A]
        p[:, -1, WAIT] = 0.0
        stops = p[:, :, 1:].sum(-1)  # probability of stopping at each step, given reached
        if bool((stops[:, -1] <= 0).any()):
            raise ValueError("probs must give some stopping action positive probability at the end")
        u = torch.rand(p.shape[0], T, generator=generator, dtype=p.dtype)
        stop_here = u < stops / p.sum(-1)
        stop_here[:, -1] = True
        stop_step = stop_here.to(torch.int8).argmax(-1)  # first step that stops
        rows = torch.arange(p.shape[0])
        choice = torch.multinomial(p[rows, stop_step, 1:], 1, generator=generator)[:, 0] + 1
        trial = torch.arange(n).repeat_interleave(per_trial)
        return self.episodes(trial, stop_step, choice)

    def expected_reward(self, probs: torch.Tensor) -> torch.Tensor:
        """Exact expected reward of a stochastic policy on each trial.

        ``E[r] = sum_t P(still waiting at t) sum_{a != 0} pi(a | theta_t) r(a, t)``, with the
        waiting probability of the last step moved onto its stopping actions (renormalised).
        Differentiable in ``probs``.

        Args:
            probs: ``[n, T, A]`` action probabilities.

        Returns:
            ``[n]`` expected rewards.
        """
        n, T, A = len(self), self.horizon, self.num_actions
        if not isinstance(probs, torch.Tensor) or probs.shape != (n, T, A):
            raise ValueError(f"probs must be a tensor of shape [{n}, {T}, {A}]")
        check_probability(probs, "probs")
        stop = probs[:, :, 1:]
        last = stop[:, -1].sum(-1, keepdim=True)
        if bool((last <= 0).any()):
            raise ValueError("probs must give some stopping action positive probability at the end")
        stop = torch.cat([stop[:, :-1], (stop[:, -1] / last)[:, None]], 1)  # out of place: autograd
        wait = probs[:, :-1, WAIT]
        reach = torch.cat([wait.new_ones(n, 1), torch.cumprod(wait, 1)], 1)  # [n, T]
        return (reach[:, :, None] * stop * self.rewards.transpose(1, 2)).sum((1, 2))

    def transitions(self, episodes: Episodes, *, unique: bool = False) -> Transitions:
        """The samples ``(theta, a, r, theta')`` visited by ``episodes``.

        An episode stopping at step ``tau`` gives ``tau`` waiting samples (reward 0, next belief
        at ``t + 1``) and one absorbing stopping sample. With ``unique`` a waiting sample shared
        by several episodes of the same trial is kept once (for enumerated episodes, which
        otherwise weight early steps by the number of later combinations).
        """
        if not isinstance(episodes, Episodes):
            raise TypeError(f"episodes must be Episodes, got {type(episodes).__name__}")
        T, A = self.horizon, self.num_actions
        steps = torch.arange(T)
        waits = steps[None, :] < episodes.stop_step[:, None]  # [E, T]
        w_trial = episodes.trial[:, None].expand(-1, T)[waits]
        w_step = steps[None, :].expand(len(episodes), -1)[waits]
        if unique and w_trial.numel():
            key = torch.unique(w_trial * T + w_step)
            w_trial, w_step = key // T, key % T
        F = self.beliefs.shape[-1]
        n_w, n_s = w_trial.numel(), len(episodes)
        next_allowed = torch.zeros(n_w + n_s, A, dtype=torch.bool)
        next_allowed[:n_w] = True
        next_allowed[:n_w, WAIT] = w_step + 1 < T - 1  # no waiting at the last step
        zeros = self.beliefs.new_zeros(n_s, F)
        return Transitions(
            state=torch.cat(
                [self.beliefs[w_trial, w_step], self.beliefs[episodes.trial, episodes.stop_step]]
            ),
            action=torch.cat([torch.full((n_w,), WAIT, dtype=torch.long), episodes.stop_action]),
            reward=torch.cat([self.rewards.new_zeros(n_w), episodes.reward]),
            next_state=torch.cat([self.beliefs[w_trial, w_step + 1], zeros]),
            next_allowed=next_allowed,
            trial=torch.cat([w_trial, episodes.trial]),
            step=torch.cat([w_step, episodes.stop_step]),
        )

    def run(self, policy: Policy) -> Episodes:
        """Follow a deterministic policy on every trial (test-time evaluation).

        Args:
            policy: ``(beliefs [m, F], step t, trial index [m]) -> actions [m]`` for the ``m``
                trials still waiting at step ``t``.

        Returns:
            one :class:`Episodes` entry per trial, in trial order.
        """
        n, T = len(self), self.horizon
        stop_step = torch.full((n,), -1, dtype=torch.long)
        stop_action = torch.zeros(n, dtype=torch.long)
        for t in range(T):
            idx = torch.nonzero(stop_step < 0)[:, 0]
            if idx.numel() == 0:
                break
            a = torch.as_tensor(policy(self.beliefs[idx, t], t, idx), dtype=torch.long)
            if a.shape != idx.shape:
                raise ValueError(
                    f"policy must return one action per trial ([{idx.numel()}]), got "
                    f"{tuple(a.shape)}"
                )
            if bool(((a < 0) | (a >= self.num_actions)).any()):
                raise ValueError(f"policy returned actions outside 0 .. {self.num_actions - 1}")
            if t == T - 1 and bool((a == WAIT).any()):
                raise ValueError("policy must stop at the last step; it returned the wait action")
            stopped = a != WAIT
            stop_step[idx[stopped]] = t
            stop_action[idx[stopped]] = a[stopped]
        return self.episodes(torch.arange(n), stop_step, stop_action)
