r"""Belief sources: where the anticipatory player's belief over the opponent's target comes from.

The stopping problem of Sec. 4.2 decides on a belief state. The thesis uses the online GP IDDM
(Algorithm 3.2); any model that gives a belief over the target after each observation will do,
and a better belief is the largest lever on the player's return rate. A source fits on training
strokes and filters every stroke (:func:`track_beliefs`); its :class:`BeliefTrack` holds the
belief over a target grid at each decision time and draws particles of the belief at the next
decision time for Monte-Carlo planning (Algorithm 4.2, :meth:`BeliefTrack.draw_next`):

- ``"gp-iddm"``: the thesis's IDDM with a linear measurement kernel and its online filter
  (:func:`~hgpdm_torch.decision.beliefs.fit_beliefs`); particles replay the filter's update
  (:class:`~hgpdm_torch.decision.mcp.ParticleProjector`).
- ``"phase-gp-iddm"``: the same with the phase-aware IDDM (not in the thesis;
  :data:`~hgpdm_torch.decision.beliefs.PHASE_IDDM`: transitions that change along the stroke
  and a process noise per latent dim); particles replay its filter at the belief's phase.
- ``"linear-iddm"``: the equal :class:`~hgpdm_torch.inference.BeliefMixture` of two
  :class:`~hgpdm_torch.models.LinearIDDM` (without and with the rank-1 interaction, noise,
  prior, temperature and forgetting by cross-validation), the best target predictor of the
  target-prediction experiment; particles draw ``g`` from the belief and the next frame from the
  model's Student-t predictive, then update a copy of the stream.
- ``"oracle"``: the true target as a point belief (a reference row: what a perfect belief would
  give the same planner; waiting teaches it nothing).

Decision features (:data:`FEATURES`): ``"moments"`` -- the belief's mean and standard deviation
of the target and the decision step, ``[mean, sd, onehot(t)]``, for a
:class:`~hgpdm_torch.decision.basis.MomentBasis` (a cubic in mean and sd per step: the stopping
value of a movement depends on where the target probably is and how sure the belief is, and
differently at each time); ``"rbf"`` -- the thesis's belief vector for
:class:`~hgpdm_torch.decision.basis.RadialBasis` (Eq. 37; the GP IDDM's latent mean, covariance
and histogram, the histogram alone for the other sources).

Shapes: ``n`` strokes, ``T`` decision times, ``K`` grid values, ``I`` particles, ``F`` features.
"""

from __future__ import annotations

import copy
import warnings
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import torch

from ..validation import as_tensor, check_choice
from .beliefs import PHASE_IDDM, BeliefConfig, Beliefs, filter_beliefs, fit_iddm
from .mcp import ParticleProjector
from .stopping import belief_vector_unchecked

__all__ = [
    "BELIEF_SOURCES",
    "FEATURES",
    "PLAYER_SOURCES",
    "SELECTABLE_SOURCES",
    "BeliefTrack",
    "moment_vector",
    "track_beliefs",
]

BELIEF_SOURCES = ("gp-iddm", "phase-gp-iddm", "linear-iddm", "oracle")
"""Every belief source :func:`track_beliefs` builds."""

SELECTABLE_SOURCES = ("linear-iddm", "gp-iddm")
"""The candidates of a player's cross-validated choice of source (``belief="auto"``); the order
breaks ties."""

PLAYER_SOURCES = (*SELECTABLE_SOURCES, "phase-gp-iddm")
"""Every source a player may be given (the oracle knows the answer: a reference row only)."""

FEATURES = ("moments", "rbf")
"""Decision features of a belief (module docstring)."""


def moment_vector(
    prob: torch.Tensor, grid: torch.Tensor, step: int, num_steps: int
) -> torch.Tensor:
    """``[..., 2 + T]``: the mean and standard deviation of the target under ``prob [..., K]``
    over ``grid [K]`` and the one-hot decision step ``step`` of ``num_steps``."""
    mean = (prob * grid).sum(-1, keepdim=True)
    sd = ((prob * (grid - mean) ** 2).sum(-1, keepdim=True)).clamp_min(0.0).sqrt()
    onehot = torch.zeros(*prob.shape[:-1], num_steps, dtype=prob.dtype, device=prob.device)
    onehot[..., step] = 1.0
    return torch.cat([mean, sd, onehot], -1)


@dataclass
class BeliefTrack:
    """One source's beliefs of ``n`` strokes at the ``T`` decision times.

    Attributes:
        source: the source's name (:data:`BELIEF_SOURCES`).
        prob: ``[n, T, K]`` belief over ``grid [K]`` after the observations available at each
            decision time (observation indices ``steps_at``).
        latent: the GP IDDM's :class:`~hgpdm_torch.decision.beliefs.Beliefs` (latent state,
            model and filter), ``None`` for the other sources.
        fits: summaries of the source's model fits (for the result's record).
    """

    source: str
    prob: torch.Tensor
    grid: torch.Tensor
    steps_at: list[int]
    latent: Beliefs | None = None
    fits: list[dict[str, Any]] = field(default_factory=list)
    _sampler: Callable[[int, int, int, torch.Generator | None], tuple] | None = None

    @property
    def num_steps(self) -> int:
        return self.prob.shape[1]

    def vectors(self, features: str = "moments") -> torch.Tensor:
        """``[n, T, F]`` decision features of every stroke's belief (module docstring)."""
        check_choice(features, "features", FEATURES)
        if features == "rbf":
            if self.latent is not None:
                return belief_vector_unchecked(self.latent.mean, self.latent.cov, self.prob)
            return self.prob
        return torch.stack(
            [moment_vector(self.prob[:, t], self.grid, t, self.num_steps)
             for t in range(self.num_steps)], 1,
        )  # fmt: skip

    def mean(self) -> torch.Tensor:
        """``[n, T]`` mean target of each belief."""
        return (self.prob * self.grid).sum(-1)

    def draw_next(
        self, trial: int, step: int, num: int, generator: torch.Generator | None = None,
        features: str = "moments",
    ) -> torch.Tensor:  # fmt: skip
        """``[num, F]`` particles of stroke ``trial``'s belief at decision ``step + 1``
        (Algorithm 4.2): the next observation drawn from the source's model given the belief at
        ``step``, then the source's own update on it."""
        check_choice(features, "features", FEATURES)
        if not 0 <= step < self.num_steps - 1:
            raise ValueError(f"step must be in [0, {self.num_steps - 2}], got {step}")
        if self._sampler is None:
            raise RuntimeError(f"the {self.source!r} track draws no particles")
        prob, mean, cov = self._sampler(trial, step, num, generator)
        if features == "rbf":
            return belief_vector_unchecked(mean, cov, prob) if mean is not None else prob
        return moment_vector(prob, self.grid, step + 1, self.num_steps)


def track_beliefs(
    source: str,
    train_obs: torch.Tensor,
    train_targets: torch.Tensor,
    obs: torch.Tensor,
    targets: torch.Tensor,
    steps_at: list[int],
    config: BeliefConfig,
) -> BeliefTrack:
    """Fit ``source`` on training strokes and track the belief of every stroke of ``obs``.

    Args:
        source: one of :data:`BELIEF_SOURCES`.
        train_obs: ``[J, T_obs, Dz]`` training strokes; train_targets: ``[J]`` their targets.
        obs: ``[n, T_obs, Dz]`` the strokes to track; targets: ``[n]`` their true targets (the
            oracle's belief; no model reads them).
        steps_at: observation index of each decision time, consecutive observations
            (:func:`~hgpdm_torch.decision.beliefs.decision_indices`): a particle projects one
            observation ahead.
        config: the GP IDDM's settings and the grid (``grid_size`` values over
            ``+-grid_max``), e.g. an :class:`~hgpdm_torch.experiments.anticipation.
            AnticipationConfig`.

    Returns:
        The :class:`BeliefTrack` of the ``n`` strokes.
    """
    check_choice(source, "source", BELIEF_SOURCES)
    obs = as_tensor(obs, "obs", ndim=3)
    targets = as_tensor(targets, "targets", ndim=1, dtype=obs.dtype)
    train_obs = as_tensor(train_obs, "train_obs", ndim=3, dtype=obs.dtype)
    train_targets = as_tensor(train_targets, "train_targets", ndim=1, dtype=obs.dtype)
    for name, x, g in (("obs", obs, targets), ("train_obs", train_obs, train_targets)):
        if len(x) != len(g):
            raise ValueError(f"{name} and its targets must have the same length, got "
                             f"{len(x)} and {len(g)}")  # fmt: skip
    if train_obs.shape[1:] != obs.shape[1:]:
        raise ValueError(
            f"train_obs and obs must have the same frames and width, got "
            f"{tuple(train_obs.shape[1:])} and {tuple(obs.shape[1:])}"
        )
    steps_at = [int(s) for s in steps_at]
    if any(b != a + 1 for a, b in zip(steps_at, steps_at[1:], strict=False)):
        raise ValueError(
            f"steps_at must be consecutive observation indices (a particle projects one "
            f"observation ahead), got {steps_at}"
        )
    grid = torch.linspace(-config.grid_max, config.grid_max, config.grid_size, dtype=obs.dtype)
    if source in ("gp-iddm", "phase-gp-iddm"):
        options = PHASE_IDDM if source == "phase-gp-iddm" else {}
        return _gp_track(source, train_obs, train_targets, obs, steps_at, config, grid, options)
    if source == "linear-iddm":
        return _linear_track(train_obs, train_targets, obs, steps_at, grid)
    nearest = (grid[None] - targets[:, None]).abs().argmin(-1)
    point = torch.nn.functional.one_hot(nearest, len(grid)).to(obs.dtype)
    prob = point[:, None].expand(-1, len(steps_at), -1).contiguous()

    def same(trial: int, step: int, num: int, generator: torch.Generator | None) -> tuple:
        return prob[trial, step + 1].expand(num, -1), None, None

    return BeliefTrack("oracle", prob, grid, steps_at, _sampler=same)


def _gp_track(
    source: str, train_obs: torch.Tensor, train_targets: torch.Tensor, obs: torch.Tensor,
    steps_at: list[int], config: BeliefConfig, grid: torch.Tensor, options: dict[str, Any],
) -> BeliefTrack:  # fmt: skip
    # at most config.iddm_trials of the training strokes (the GP's cost grows as their cube)
    gen = torch.Generator().manual_seed(config.seed)
    chosen = torch.randperm(len(train_obs), generator=gen)[: config.iddm_trials]
    model = fit_iddm(train_obs[chosen], train_targets[chosen], config, **options)
    beliefs = filter_beliefs(model, obs, steps_at, config)
    projector = ParticleProjector(beliefs.model, beliefs.belief_filter)

    def sample(trial: int, step: int, num: int, generator: torch.Generator | None) -> tuple:
        mean, cov, log_prob = projector.sample_beliefs(beliefs.belief(trial, step), num, generator)
        return log_prob.exp(), mean, cov

    fits = [beliefs.model.fit_result.summary()]
    prob = beliefs.log_prob.exp()
    return BeliefTrack(source, prob, grid, steps_at, beliefs, fits, _sampler=sample)


def _linear_track(
    train_obs: torch.Tensor, train_targets: torch.Tensor, obs: torch.Tensor, steps_at: list[int],
    grid: torch.Tensor,
) -> BeliefTrack:  # fmt: skip
    from ..inference import BeliefMixture
    from ..models import LinearIDDM

    models = []
    for rank in (0, 1):
        model = LinearIDDM(interaction_rank=rank, select="cv", temperature="cv", forgetting="cv")
        with warnings.catch_warnings():  # a prior scale at its grid's edge (the held-out
            warnings.simplefilter("ignore")  # likelihood is flat in it) is fine here
            models.append(model.fit(train_obs, train_targets))
    mixture = BeliefMixture(models)
    stream = mixture.stream(len(obs), grid)
    snapshots, probs = [], []
    for t in range(max(steps_at) + 1):
        belief = stream.update(obs[:, t])
        if t in steps_at:
            probs.append(belief.prob)
            snapshots.append(_copy_stream(stream))

    def sample(trial: int, step: int, num: int, generator: torch.Generator | None) -> tuple:
        particles = snapshots[step].repeat(trial, num)
        return particles.update(particles.sample_next(generator)).prob, None, None

    fits = [m.config() for m in models]
    prob = torch.stack(probs, 1).to(obs.dtype)
    return BeliefTrack("linear-iddm", prob, grid, steps_at, None, fits, _sampler=sample)


def _copy_stream(stream: Any) -> Any:
    """A copy of a (mixture of) LinearIDDM stream(s) that later updates leave alone."""
    out = copy.copy(stream)
    if hasattr(stream, "streams"):
        out.streams = [_copy_stream(s) for s in stream.streams]
    for name, value in vars(stream).items():
        if isinstance(value, torch.Tensor):
            setattr(out, name, value.clone())
    return out
