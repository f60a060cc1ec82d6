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
- ``"promp"``: a probabilistic movement primitive over the observations jointly with the
  target, conditioned on the stroke so far with its phase estimated
  (:class:`~hgpdm_torch.baselines.ProMPRegressor`, options by cross-validation; the
  interaction-primitive baseline, not in the thesis); the belief is its Gaussian over the target
  on the grid; particles draw the next observation from its predictive and condition again.
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
import math
import numbers
import warnings
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import torch

from ..validation import as_tensor, check_choice, check_finite
from .beliefs import (
    PHASE_IDDM,
    BeliefConfig,
    Beliefs,
    check_decision_steps,
    filter_beliefs,
    fit_iddm,
)
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

BELIEF_SOURCES = ("gp-iddm", "phase-gp-iddm", "linear-iddm", "promp", "oracle")
"""Every belief source :func:`track_beliefs` builds."""

SELECTABLE_SOURCES = ("linear-iddm", "gp-iddm", "promp")
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
    over ``grid [K]`` and the one-hot decision step ``step`` of ``num_steps``.

    Raises:
        TypeError: ``prob`` or ``grid`` not numeric, ``step`` or ``num_steps`` not an int.
        ValueError: ``grid`` not a finite ``[K]`` vector, ``prob`` not ``[..., K]`` beliefs
            (finite, non-negative, each summing to 1, :func:`_check_belief`), ``num_steps < 1``
            or ``step`` outside ``[0, num_steps - 1]``.
    """
    grid = _check_grid(grid, "grid")
    prob = as_tensor(prob, "prob", min_ndim=1)
    if prob.shape[-1] != len(grid):
        raise ValueError(
            f"prob must hold a belief over the grid's {len(grid)} values in its last dim, got "
            f"shape {tuple(prob.shape)}"
        )
    _check_belief(prob, "prob")
    num_steps = _count(num_steps, "num_steps")
    if isinstance(step, bool) or not isinstance(step, numbers.Integral):
        raise TypeError(f"step must be an int, got {step!r}")
    if not 0 <= step < num_steps:
        raise ValueError(f"step must be a decision step in [0, {num_steps - 1}], got {step}")
    return _moments(prob, grid, int(step), num_steps)


def _moments(prob: torch.Tensor, grid: torch.Tensor, step: int, num_steps: int) -> torch.Tensor:
    """:func:`moment_vector` of arguments already checked."""
    mean = (prob * grid).sum(-1, keepdim=True)
    sd = ((prob * (grid - mean) ** 2).sum(-1, keepdim=True)).clamp_min(0.0).sqrt()
    onehot = torch.zeros(*prob.shape[:-1], num_steps, dtype=prob.dtype, device=prob.device)
    onehot[..., step] = 1.0
    return torch.cat([mean, sd, onehot], -1)


def _belief_tolerance(prob: torch.Tensor) -> float:
    """How far from 1 the sum of a belief ``prob [..., K]`` may be: ``max(1e-6, 16 K eps)``.

    A source normalises its beliefs itself (a softmax, or the exp of a log belief normalised by
    its logsumexp), which leaves a sum off 1 by the rounding of its K terms, at most about
    ``K eps`` (3e-15 for 13 float64 values, 1.5e-6 for 13 float32 ones: hence the ``16 K eps``
    for float32). ``1e-6`` also admits a belief converted between dtypes or written with six
    significant digits, and is far below what a wrong belief is off by (a lost or doubled grid
    value moves the sum by about ``1 / K``).
    """
    return max(1e-6, 16 * prob.shape[-1] * torch.finfo(prob.dtype).eps)


def _check_belief(prob: torch.Tensor, name: str) -> None:
    """Raise unless the last dim of ``prob [..., K]`` holds beliefs: finite, non-negative
    probabilities that sum to 1 within :func:`_belief_tolerance`.

    Raises:
        ValueError: naming ``name``, the first bad belief's index and what is wrong with it.
    """
    check_finite(prob, name)
    if prob.numel() == 0:
        raise ValueError(f"{name} must not be empty, got shape {tuple(prob.shape)}")
    negative = prob < 0
    if bool(negative.any()):
        where = tuple(int(i) for i in torch.nonzero(negative)[0])
        raise ValueError(
            f"{name}{list(where)} = {float(prob[where]):.3g} is negative; a belief holds "
            "probabilities >= 0"
        )
    sums, tol = prob.sum(-1), _belief_tolerance(prob)
    off = (sums - 1).abs() > tol
    if bool(off.any()):
        where = tuple(int(i) for i in torch.nonzero(off)[0]) if off.dim() else ()
        at = f"{name}{list(where)}" if where else name
        raise ValueError(
            f"{at} sums to {float(sums[where]):.6g} over the grid; a belief must sum to 1 "
            f"(within {tol:.0e}): normalise it"
        )


def _check_grid(grid: object, name: str) -> torch.Tensor:
    """``grid`` as a finite, non-empty ``[K]`` tensor."""
    grid = as_tensor(grid, name)
    if grid.dim() != 1 or len(grid) == 0:
        raise ValueError(f"{name} must be a non-empty [K] vector of targets, got shape "
                         f"{tuple(grid.shape)}")  # fmt: skip
    return grid


def _count(value: object, name: str) -> int:
    """``value`` as a positive int."""
    if isinstance(value, bool) or not isinstance(value, numbers.Integral):
        raise TypeError(f"{name} must be an int, got {value!r}")
    if value < 1:
        raise ValueError(f"{name} must be at least 1, got {value}")
    return int(value)


@dataclass
class BeliefTrack:
    """One source's beliefs of ``n`` strokes at the ``T`` decision times.

    Attributes:
        source: the source's name (:data:`BELIEF_SOURCES`).
        prob: ``[n, T, K]`` belief over ``grid [K]`` after the observations available at each
            decision time (observation indices ``steps_at``).
        grid: ``[K]`` the targets the beliefs are over.
        steps_at: ``T`` consecutive observation indices >= 0, one per decision time.
        latent: the GP IDDM's :class:`~hgpdm_torch.decision.beliefs.Beliefs` (latent state,
            model and filter), ``None`` for the other sources.
        fits: summaries of the source's model fits (for the result's record).
        rejected: ``[n, T]`` bool: an observation of the stroke was rejected (an inf, or beyond
            the model's ``outlier_sd`` plausibility threshold) and taken as missing among those
            the belief at this decision time took in after the previous one's (for the first
            decision time, observations ``0 .. steps_at[0]``), as
            :class:`~hgpdm_torch.inference.OnlineIntentionFilter`'s ``belief.rejected`` flags a
            rejected observation; ``rejected.any(1)`` the strokes with one. Default: none.

    Raises:
        TypeError: ``steps_at`` not a list of ints.
        ValueError: at construction, an unknown ``source``; ``prob`` not ``[n, T, K]`` with
            ``n, T >= 1`` and ``K`` the grid's size, or holding a belief that is not finite,
            negative or does not sum to 1 (within ``max(1e-6, 16 K eps)``: the rounding of a
            normalised belief's K terms, with room for a dtype conversion); a ``grid`` that is
            not a finite ``[K]`` vector; ``steps_at`` not ``T`` consecutive indices >= 0;
            ``rejected`` not ``[n, T]``; a ``latent`` of other strokes or decision times.
    """

    source: str
    prob: torch.Tensor
    grid: torch.Tensor
    steps_at: list[int]
    latent: Beliefs | None = None
    fits: list[dict[str, Any]] = field(default_factory=list)
    rejected: torch.Tensor | None = None
    _sampler: Callable[[int, int, int, torch.Generator | None], tuple] | None = None

    def __post_init__(self) -> None:
        check_choice(self.source, "source", BELIEF_SOURCES)
        self.grid = _check_grid(self.grid, "grid")
        self.prob = as_tensor(self.prob, "prob", ndim=3)
        n, t, k = self.prob.shape
        if n == 0 or t == 0 or k != len(self.grid):
            raise ValueError(
                f"prob must be [n, T, K = {len(self.grid)}] beliefs over the grid's values with "
                f"n >= 1 strokes and T >= 1 decision times, got shape {tuple(self.prob.shape)}"
            )
        _check_belief(self.prob, "prob")
        self.steps_at = check_decision_steps(self.steps_at, consecutive=True)
        if len(self.steps_at) != t:
            raise ValueError(
                f"steps_at must hold one observation index per decision time (T = {t} in prob), "
                f"got {len(self.steps_at)}: {self.steps_at}"
            )
        if self.rejected is None:
            self.rejected = torch.zeros(n, t, dtype=torch.bool, device=self.prob.device)
        elif not isinstance(self.rejected, torch.Tensor) or self.rejected.dtype != torch.bool or (
            self.rejected.shape != (n, t)
        ):  # fmt: skip
            got = (f"shape {tuple(self.rejected.shape)} and dtype {self.rejected.dtype}"
                   if isinstance(self.rejected, torch.Tensor)
                   else type(self.rejected).__name__)  # fmt: skip
            raise ValueError(f"rejected must be a [n = {n}, T = {t}] bool tensor, got {got}")
        if self.latent is not None and tuple(self.latent.log_prob.shape) != (n, t, k):
            raise ValueError(
                f"latent must hold the same {n} strokes, {t} decision times and {k} grid values "
                f"as prob, got log_prob of shape {tuple(self.latent.log_prob.shape)}"
            )

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
        # prob and grid were checked at construction
        return torch.stack(
            [_moments(self.prob[:, t], self.grid, t, self.num_steps)
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
        ``step``, then the source's own update on it.

        Raises:
            TypeError: ``trial``, ``step`` or ``num`` not an int.
            ValueError: ``trial`` not a stroke index in ``[0, n - 1]``, ``step`` not in
                ``[0, T - 2]`` (no decision after the last), ``num < 1``, or particles whose
                beliefs are not finite and normalised (the source's model failed on them).
            RuntimeError: a track that draws no particles (built without a sampler).
        """
        check_choice(features, "features", FEATURES)
        n = self.prob.shape[0]
        for name, value in (("trial", trial), ("step", step)):
            if isinstance(value, bool) or not isinstance(value, numbers.Integral):
                raise TypeError(f"{name} must be an int, got {value!r}")
        if not 0 <= trial < n:
            raise ValueError(f"trial must be a stroke index in [0, {n - 1}], got {trial}")
        if not 0 <= step < self.num_steps - 1:
            raise ValueError(
                f"step must be in [0, {self.num_steps - 2}] (a decision time with one after "
                f"it), got {step}"
            )
        num = _count(num, "num")
        if self._sampler is None:
            raise RuntimeError(f"the {self.source!r} track draws no particles")
        prob, mean, cov = self._sampler(int(trial), int(step), num, generator)
        _check_belief(prob, f"the {self.source} particles' beliefs")
        if features == "rbf":
            return belief_vector_unchecked(mean, cov, prob) if mean is not None else prob
        return _moments(prob, self.grid, int(step) + 1, self.num_steps)


def track_beliefs(
    source: str,
    train_obs: torch.Tensor,
    train_targets: torch.Tensor,
    obs: torch.Tensor,
    targets: torch.Tensor,
    steps_at: list[int],
    config: BeliefConfig,
    *,
    clip: bool = False,
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
        clip: (the oracle) put a target beyond the grid on the grid's nearest value instead
            of refusing it.

    Returns:
        The :class:`BeliefTrack` of the ``n`` strokes. An observation the source's model
        rejects (an inf, or beyond its ``outlier_sd`` training standard deviations: taken as
        missing) is flagged in ``track.rejected`` and warned about once per track.

    Warns:
        UserWarning: observations were rejected (naming how many strokes, and the first);
            the spread of the targets the source reads (``train_targets``; the oracle's
            ``targets``) is below the grid's step (the beliefs cannot tell them apart: rescale
            the targets or narrow ``grid_max``).

    Raises:
        TypeError: ``steps_at`` not a list of ints, ``config.grid_size`` not an int.
        ValueError: an unknown source; arrays of the wrong shape or not finite; no stroke in
            ``obs`` or ``train_obs``; ``steps_at`` empty, negative, not consecutive or past the
            strokes' last observation; a grid of fewer than 2 values or a ``grid_max`` that is
            not positive and finite; (the oracle, unless ``clip``) a target farther beyond the
            grid than half its step, naming the target and the grid's range.
    """
    check_choice(source, "source", BELIEF_SOURCES)
    if not isinstance(clip, bool):
        raise TypeError(f"clip must be a bool, got {clip!r}")
    obs = as_tensor(obs, "obs", ndim=3)
    targets = as_tensor(targets, "targets", ndim=1, dtype=obs.dtype)
    train_obs = as_tensor(train_obs, "train_obs", ndim=3, dtype=obs.dtype)
    train_targets = as_tensor(train_targets, "train_targets", ndim=1, dtype=obs.dtype)
    for name, x, what in (("obs", obs, "stroke to track"), ("train_obs", train_obs,
                                                              "training stroke")):  # fmt: skip
        if min(x.shape) == 0:
            raise ValueError(
                f"{name} must be [strokes, frames, Dz] with at least one {what}, one frame and "
                f"one observed dim, got shape {tuple(x.shape)}"
            )
    for name, x, g in (("obs", obs, targets), ("train_obs", train_obs, train_targets)):
        if len(x) != len(g):
            raise ValueError(f"{name} and its targets must have the same length, got "
                             f"{len(x)} and {len(g)}")  # fmt: skip
    if train_obs.shape[1:] != obs.shape[1:]:
        raise ValueError(
            f"train_obs and obs must have the same frames and width, got "
            f"{tuple(train_obs.shape[1:])} and {tuple(obs.shape[1:])}"
        )
    steps_at = check_decision_steps(steps_at, obs.shape[1], consecutive=True)
    grid = _config_grid(config, obs.dtype)
    if source == "oracle":  # the targets the source reads
        _check_target_spread(targets, "targets", grid)
    else:
        _check_target_spread(train_targets, "train_targets", grid)
    if source in ("gp-iddm", "phase-gp-iddm"):
        options = PHASE_IDDM if source == "phase-gp-iddm" else {}
        track = _gp_track(source, train_obs, train_targets, obs, steps_at, config, grid, options)
    elif source == "linear-iddm":
        track = _linear_track(train_obs, train_targets, obs, steps_at, grid)
    elif source == "promp":
        track = _promp_track(train_obs, train_targets, obs, steps_at, grid)
    else:
        track = _oracle_track(targets, steps_at, grid, clip)
    if bool(track.rejected.any()):
        # one warning per track: the flags say which strokes and decision times it touched
        strokes = torch.nonzero(track.rejected.any(1)).flatten().tolist()
        warnings.warn(
            f"{source} beliefs: observations of {len(strokes)} stroke(s) (first: stroke "
            f"{strokes[0]}) were rejected as implausible (an inf, or beyond the model's "
            "outlier_sd training standard deviations) and taken as missing; track.rejected "
            "flags the decision times they affect",
            stacklevel=2,
        )
    return track


def _config_grid(config: BeliefConfig, dtype: torch.dtype) -> torch.Tensor:
    """The belief grid of ``config``: ``grid_size`` values evenly over ``+-grid_max``."""
    size, top = config.grid_size, config.grid_max
    if isinstance(size, bool) or not isinstance(size, numbers.Integral):
        raise TypeError(f"config.grid_size must be an int, got {size!r}")
    if size < 2:
        raise ValueError(f"config.grid_size must be at least 2 grid values, got {size}")
    if isinstance(top, bool) or not isinstance(top, numbers.Real) or not (
        0 < top < math.inf
    ):  # fmt: skip
        raise ValueError(f"config.grid_max must be a positive finite number, got {top!r}")
    return torch.linspace(-float(top), float(top), int(size), dtype=dtype)


def _check_target_spread(targets: torch.Tensor, name: str, grid: torch.Tensor) -> None:
    """Warn where the standard deviation of the targets a source reads is below the grid's
    step: their beliefs then fall on one or two grid values whatever the observations say
    (e.g. targets of +-1 scaled by 0.01 on a grid of +-1.2)."""
    step = float(grid[1] - grid[0])
    spread = float(targets.std()) if len(targets) > 1 else 0.0
    if spread < step:
        warnings.warn(
            f"{name} have a spread (standard deviation) of {spread:.3g}, below the "
            f"belief grid's step {step:.3g} ({len(grid)} values over +-{float(grid[-1]):g}): "
            "the beliefs cannot tell the targets apart; express the targets in units where "
            "they spread over the grid (e.g. standardise them) or narrow config.grid_max",
            stacklevel=3,
        )


def _oracle_track(
    targets: torch.Tensor, steps_at: list[int], grid: torch.Tensor, clip: bool
) -> BeliefTrack:
    """The true targets as point beliefs on their nearest grid values."""
    # a target within half a step beyond an edge rounds to the edge, as any target rounds to
    # its nearest value; farther out the point belief would claim a target the grid cannot hold
    reach = 0.5 * float(grid[1] - grid[0])
    outside = (targets < grid[0] - reach) | (targets > grid[-1] + reach)
    if not clip and bool(outside.any()):
        i = int(torch.nonzero(outside)[0])
        raise ValueError(
            f"targets[{i}] = {float(targets[i]):g} lies outside the belief grid "
            f"[{float(grid[0]):g}, {float(grid[-1]):g}] (config.grid_max; {int(outside.sum())} "
            "target(s) outside): the oracle's point belief would sit at the grid's edge; widen "
            "config.grid_max, or pass clip=True to put such targets on the nearest grid value"
        )
    nearest = (grid[None] - targets[:, None]).abs().argmin(-1)
    point = torch.nn.functional.one_hot(nearest, len(grid)).to(grid.dtype)
    prob = point[:, None].expand(-1, len(steps_at), -1).contiguous()

    def same(trial: int, step: int, num: int, generator: torch.Generator | None) -> tuple:
        return prob[trial, step + 1].expand(num, -1), None, None

    return BeliefTrack("oracle", prob, grid, steps_at, _sampler=same)


def _per_decision(flags: torch.Tensor, steps_at: list[int]) -> torch.Tensor:
    """``[n, T]``: whether any of the observation flags ``[n, T_obs]`` lies among the frames
    decision ``t`` took in after decision ``t - 1`` (frames ``0 .. steps_at[0]`` for the first)."""
    starts = [0, *(s + 1 for s in steps_at[:-1])]
    return torch.stack(
        [flags[:, lo : s + 1].any(1) for lo, s in zip(starts, steps_at, strict=True)], 1
    )


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
    rejected = _per_decision(beliefs.rejected, steps_at)
    return BeliefTrack(source, prob, grid, steps_at, beliefs, fits, rejected, _sampler=sample)


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
            warnings.simplefilter("ignore")  # likelihood is flat in it) is fine here; targets
            warnings.filterwarnings(  # in units too small for the model's prior are not
                "default", message="LinearIDDM: the intentions have a standard deviation"
            )
            models.append(model.fit(train_obs, train_targets))
    mixture = BeliefMixture(models)
    stream = mixture.stream(len(obs), grid)
    snapshots, probs, flags = [], [], []
    for t in range(steps_at[-1] + 1):
        belief = stream.update(obs[:, t])
        flags.append(belief.rejected)
        if t in steps_at:
            probs.append(belief.prob)
            snapshots.append(_copy_stream(stream))

    def sample(trial: int, step: int, num: int, generator: torch.Generator | None) -> tuple:
        particles = snapshots[step].repeat(trial, num)
        return particles.update(particles.sample_next(generator)).prob, None, None

    fits = [m.config() for m in models]
    prob = torch.stack(probs, 1).to(obs.dtype)
    rejected = _per_decision(torch.stack(flags, 1), steps_at)
    return BeliefTrack("linear-iddm", prob, grid, steps_at, None, fits, rejected, _sampler=sample)


def _promp_track(
    train_obs: torch.Tensor, train_targets: torch.Tensor, obs: torch.Tensor, steps_at: list[int],
    grid: torch.Tensor,
) -> BeliefTrack:  # fmt: skip
    from ..baselines import ProMPRegressor

    regressor = ProMPRegressor().fit(list(train_obs.double()), train_targets.double())
    model = regressor.model

    def on_grid(prefix: torch.Tensor) -> torch.Tensor:
        """The ProMP's Gaussian over the target, normalised over the grid values ``[B, K]``."""
        post = model.condition(prefix)
        mean, var = post.mean[:, 0], post.cov[:, 0, 0]
        log_p = -0.5 * (grid.double() - mean[:, None]).pow(2) / var[:, None]
        return log_p.softmax(-1)  # in logs: a sure belief puts all mass on one value, no 0 / 0

    prob = torch.stack([on_grid(obs[:, : s + 1].double()) for s in steps_at], 1)

    def sample(trial: int, step: int, num: int, generator: torch.Generator | None) -> tuple:
        prefix = obs[trial, : steps_at[step] + 1].double()
        nxt = model.sample_next(prefix[None], num, generator)[0]  # [num, Dz]
        grown = torch.cat([prefix.expand(num, -1, -1), nxt[:, None]], 1)
        return on_grid(grown).to(obs.dtype), None, None

    fits = [{"options": {k: str(v) for k, v in regressor.options.items()}}]
    rejected = torch.zeros(prob.shape[:2], dtype=torch.bool)  # the ProMP reads every frame
    return BeliefTrack("promp", prob.to(obs.dtype), grid, steps_at, None, fits, rejected,
                       _sampler=sample)  # fmt: skip


def _copy_stream(stream: Any) -> Any:
    """A copy of a (mixture of) LinearIDDM stream(s) that later updates leave alone."""
    out = copy.copy(stream)
    if hasattr(stream, "streams"):
        out.streams = [_copy_stream(s) for s in stream.streams]
    for name, value in vars(stream).items():
        if isinstance(value, torch.Tensor):
            setattr(out, name, value.clone())
    return out
