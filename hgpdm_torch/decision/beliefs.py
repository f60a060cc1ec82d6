"""Beliefs at decision times: an IDDM fitted on training strokes, filtered over every trial.

Anticipatory action selection (thesis Sec. 4.3) decides at a few times before the opponent's hit.
:func:`fit_beliefs` fits an IDDM (continuous target g, linear measurement kernel) on training
strokes and runs the online filter (Algorithm 3.2) over all trials; :class:`Beliefs` holds every
trial's latent state and target histogram after the observations available at each decision time
(:func:`decision_indices`), the input of the policies in :mod:`~hgpdm_torch.decision.policies`.
"""

from __future__ import annotations

import numbers
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, Protocol

import torch

from ..inference.intention import OnlineIntentionFilter
from ..intention_belief import IntentionBelief
from ..models import IDDM
from ..validation import as_tensor
from .mcp import Belief
from .stopping import belief_vector

__all__ = [
    "PHASE_IDDM",
    "BeliefConfig",
    "Beliefs",
    "check_decision_steps",
    "decision_indices",
    "filter_beliefs",
    "fit_beliefs",
    "fit_iddm",
]


#: The phase-aware IDDM's options for the simulated opponent's strokes (not in the thesis):
#: ``IDDM(phase_width=0.25, scale_transitions=True)``, transitions that change along the stroke
#: with a process noise per latent dim (``alpha_4 / v_d^2``, alpha_4 = 0.3), and twice the
#: thesis's g width. Chosen by 5-fold cross-validation on the target-prediction protocol's
#: training strokes (``python -m benchmarks target_sweep --only=phase`` and ``--only="transition
#: scales"``; docs page "Target prediction").
PHASE_IDDM: dict[str, object] = {
    "phase_width": 0.25, "alpha": (0.9, 0.3, 0.1, 0.3), "alpha_g": (1.0, 0.1),
    "scale_transitions": True,
}  # fmt: skip


def decision_indices(obs_times: torch.Tensor, start_times: tuple[float, ...]) -> list[int]:
    """For each decision (start) time, the index of the last observation available by then."""
    obs_times = as_tensor(obs_times, "obs_times", ndim=1)
    out = []
    for s in start_times:
        seen = torch.nonzero(obs_times <= s + 1e-9).flatten()
        if seen.numel() == 0:
            raise ValueError(f"no observation precedes the decision time {s}")
        out.append(int(seen[-1]))
    return out


def check_decision_steps(
    steps_at: object, num_frames: int | None = None, *, consecutive: bool = False
) -> list[int]:
    """``steps_at`` (the observation index of each decision time) as a list of ints.

    Args:
        steps_at: a non-empty sequence (or 1-D tensor) of observation indices >= 0.
        num_frames: the strokes' observations; the indices must lie below it (``None``: any).
        consecutive: whether the indices must be consecutive (Monte-Carlo planning projects
            one observation ahead).

    Raises:
        TypeError: not a sequence of ints.
        ValueError: empty, an index < 0 or ``>= num_frames``, or (``consecutive``) a gap.
    """
    if isinstance(steps_at, torch.Tensor) and steps_at.dim() == 1:
        steps_at = steps_at.tolist()
    if not isinstance(steps_at, Sequence) or isinstance(steps_at, str) or any(
        isinstance(s, bool) or not isinstance(s, numbers.Integral) for s in steps_at
    ):  # fmt: skip
        raise TypeError(f"steps_at must be a list of observation indices (ints), got {steps_at!r}")
    steps = [int(s) for s in steps_at]
    if not steps:
        raise ValueError(
            "steps_at must hold the observation index of at least one decision time, got []"
        )
    if min(steps) < 0:
        raise ValueError(f"steps_at must be observation indices >= 0, got {steps}")
    if num_frames is not None and max(steps) >= num_frames:
        raise ValueError(
            f"steps_at must be observation indices of the strokes' {num_frames} frames "
            f"(0 .. {num_frames - 1}), got {steps}"
        )
    if consecutive and any(b != a + 1 for a, b in zip(steps, steps[1:], strict=False)):
        raise ValueError(
            f"steps_at must be consecutive observation indices (a particle projects one "
            f"observation ahead), got {steps}"
        )
    return steps


@dataclass
class Beliefs:
    """Beliefs of every trial under one fold's IDDM and the fold's split.

    ``mean [n, T, Dx]``, ``cov [n, T, Dx, Dx]`` and ``log_prob [n, T, K]`` are the online
    filter's latent state and target histogram after the observations available at each of the
    ``T`` decision times; ``train``/``test`` index the trials. ``phases`` (a phase-aware IDDM
    only) is the frame index of the state at each decision time. ``rejected [n, T_seen]`` (bool,
    ``None`` where not recorded) flags the observations ``0 .. max(steps_at)`` the filter
    rejected as implausible and took as missing (its ``belief.rejected``).
    """

    model: IDDM
    belief_filter: OnlineIntentionFilter
    mean: torch.Tensor
    cov: torch.Tensor
    log_prob: torch.Tensor
    train: torch.Tensor
    test: torch.Tensor
    phases: list[int] | None = None
    rejected: torch.Tensor | None = None

    def vectors(self) -> torch.Tensor:
        """``[n, T, F]`` belief vectors (:func:`~hgpdm_torch.decision.stopping.belief_vector`)."""
        return belief_vector(self.mean, self.cov, self.log_prob.exp())

    def intentions(self) -> IntentionBelief:
        """The target histograms ``[n, T, K]`` as an
        :class:`~hgpdm_torch.intention_belief.IntentionBelief` over the filter's grid (its mean
        and sd, entropy, credible sets), the belief every inference path reports."""
        f = self.belief_filter
        return IntentionBelief.from_log(self.log_prob, f.values, f.continuous)

    def belief(self, i: int, t: int) -> Belief:
        """The planner's :class:`~hgpdm_torch.decision.mcp.Belief` of trial ``i`` at step ``t``."""
        phase = None if self.phases is None else self.phases[t]
        return Belief(self.mean[i, t], self.cov[i, t], self.log_prob[i, t], phase)


class BeliefConfig(Protocol):
    """The settings :func:`fit_beliefs` reads, e.g. those of an
    :class:`~hgpdm_torch.experiments.anticipation.AnticipationConfig`.

    Attributes:
        seed: seeds the choice of the IDDM's training strokes.
        iddm_trials: training strokes the IDDM is fitted on (all when larger).
        latent_dim: the IDDM's latent dimension.
        alpha: the IDDM's transition kernel parameters.
        alpha_g: the IDDM's g kernel parameters.
        fit_steps: optimiser steps of the IDDM's fit.
        grid_size: K, targets in the belief histogram, evenly over ``+-grid_max``.
        grid_max: the largest target of the grid.
        forgetting: the online filter's forgetting factor.
    """

    seed: int
    iddm_trials: int
    latent_dim: int
    alpha: tuple[float, float, float, float]
    alpha_g: tuple[float, float]
    fit_steps: int
    grid_size: int
    grid_max: float
    forgetting: float

    def initial_latents(self, obs: torch.Tensor, targets: torch.Tensor) -> torch.Tensor:
        """Initial latent states ``[n T, latent_dim]`` of the training strokes ``obs [n, T, Dz]``
        with targets ``[n]``."""


def fit_beliefs(
    obs: torch.Tensor,
    targets: torch.Tensor,
    steps_at: list[int],
    train: torch.Tensor,
    test: torch.Tensor,
    config: BeliefConfig,
) -> Beliefs:
    """Fit an IDDM on (at most ``config.iddm_trials`` of) the training strokes and filter all.

    Args:
        obs: ``[n, T_obs, Dz]`` observations; targets: ``[n]`` true targets.
        steps_at: observation index of each decision time (:func:`decision_indices`).
        train: training trial indices of the split.
        test: test trial indices of the split.
        config: latent size, optimiser steps, target grid, forgetting factor and the latents'
            initialisation (:class:`BeliefConfig`, e.g. an
            :class:`~hgpdm_torch.experiments.anticipation.AnticipationConfig`).

    The IDDM is fitted for ``config.fit_steps`` steps without a
    :class:`~hgpdm_torch.fitting.ConvergenceWarning`; ``result.model.fit_result`` says whether
    it converged (callers report it).
    """
    gen = torch.Generator().manual_seed(config.seed)
    chosen = train[torch.randperm(len(train), generator=gen)[: config.iddm_trials]]
    model = fit_iddm(obs[chosen], targets[chosen], config)
    return filter_beliefs(model, obs, steps_at, config, train, test)


def fit_iddm(
    obs: torch.Tensor, targets: torch.Tensor, config: BeliefConfig, **options: Any
) -> IDDM:
    """The IDDM of :func:`fit_beliefs` fitted on all the strokes ``obs [J, T_obs, Dz]`` with
    targets ``[J]`` (``config.fit_steps`` steps, no warning: ``model.fit_result`` says whether
    it converged); ``options`` override the config's ``alpha``/``alpha_g`` and add IDDM options
    (e.g. :data:`PHASE_IDDM`)."""
    kernel = {"alpha": config.alpha, "alpha_g": config.alpha_g} | options
    model = IDDM(
        list(obs), targets, config.latent_dim, intention="continuous", measurement="linear",
        init=config.initial_latents(obs, targets), **kernel,
    )  # fmt: skip
    # a step budget, not a convergence promise: the experiments report model.fit_result (whether
    # the criteria were met, and why it stopped) in their results instead of a warning
    model.fit(config.fit_steps, warn=False)
    return model


def filter_beliefs(
    model: IDDM,
    obs: torch.Tensor,
    steps_at: list[int],
    config: BeliefConfig,
    train: torch.Tensor | None = None,
    test: torch.Tensor | None = None,
) -> Beliefs:
    """The online filter (Algorithm 3.2) of ``model`` over all strokes ``obs [n, T_obs, Dz]``,
    its beliefs kept at the decision steps ``steps_at`` (grid and forgetting from ``config``)
    and the observations it rejected (``Beliefs.rejected``); ``train``/``test`` are recorded in
    the result (default: none / all).

    Raises:
        ValueError: ``obs`` not a ``[n, T_obs, Dz]`` tensor with ``n >= 1`` strokes;
            ``steps_at`` empty or outside ``0 .. T_obs - 1`` (:func:`check_decision_steps`).
    """
    # NaN (missing) and implausible rows are the filter's to take or reject: no finiteness check
    if not isinstance(obs, torch.Tensor) or obs.dim() != 3 or obs.shape[0] == 0:
        got = tuple(obs.shape) if isinstance(obs, torch.Tensor) else type(obs).__name__
        raise ValueError(f"obs must be a [n, T_obs, Dz] tensor with n >= 1 strokes, got {got}")
    steps_at = check_decision_steps(steps_at, obs.shape[1])
    grid = torch.linspace(-config.grid_max, config.grid_max, config.grid_size)
    f = OnlineIntentionFilter(model, grid, forgetting=config.forgetting, batch_size=obs.shape[0])
    means, covs, logs, flags = [], [], [], []
    with torch.no_grad():
        for t in range(max(steps_at) + 1):
            flags.append(f.update(obs[:, t]).rejected)
            if t in steps_at:
                means.append(f.mean.clone())
                covs.append(f.cov.clone())
                logs.append(f.log_belief.clone())
    stack = [torch.stack(v, 1) for v in (means, covs, logs)]
    train = torch.zeros(0, dtype=torch.long) if train is None else train
    test = torch.arange(obs.shape[0]) if test is None else test
    phases = list(steps_at) if f.phase else None  # x_t after observation t is frame t
    return Beliefs(model, f, *stack, train, test, phases, torch.stack(flags, 1))
