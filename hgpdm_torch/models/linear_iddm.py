"""Linear-Gaussian intention-driven dynamics with conjugate Bayesian parameters.

The IDDM of Ch. 3 lets the intention ``g`` drive a GP transition over a low-dimensional latent state
with one isotropic process noise shared by all frames of a movement. :class:`LinearIDDM` keeps the
IDDM's idea (``g`` is an input of the dynamics; inference is Bayes' theorem over ``g``) and drops
those three assumptions: the state is the standardised observation itself, and the transition is
linear in ``[z_t, phi(g), 1]`` (optionally with an intention-state interaction) with its own
coefficients and its own noise covariance (per dimension by default) at each frame index of the
movement (``phase=True``), both integrated out under their conjugate prior, so the one-step
predictive is a Student-t (not in the thesis). For movements recorded from a common start (a
stroke's first frame a fixed time before the hit), this is what the target-prediction experiment
needs: there the target information at 80 ms lies in the step-specific, anisotropic residual of the
last transition, which a stationary transition with isotropic noise over a 6-D latent averages away
(docs, target prediction; ``python -m benchmarks target_dynamics``).

Model, for each phase ``s`` (the frame index of ``z_t``, or one shared phase)::

    z_{t+1} = W_s^T u_t + e_t,   u_t = [z_t, phi(g), 1, phi(g) (x) V_s^T z_t],   e_t ~ N(0, Sigma_s)
    W_s | Sigma_s ~ MN(0, I / lambda, Sigma_s),   Sigma_s ~ IW(psi I, Dz + 2)

with ``z`` standardised by the training frames' mean and standard deviation, ``phi(g) = g`` for a
continuous g and the one-hot code for a discrete g. The interaction block is empty by default; with
``interaction_rank = r``, ``V_s [Dz, r]`` are the partial-least-squares directions of the phase's
training states on ``phi(g)`` (fixed before the conjugate update, so the model stays conjugate): the
intention's effect on the next frame may then scale with how far the current frame already shows it.
``V_s`` is a plug-in estimate from the training ``(z_t, g)`` (per phase it never sees the targets
``z_{t+1}``; with ``phase=False`` it does), so the evidence is conditional on it and is no criterion
for the rank: choose ``r`` by cross-validation. On ten fresh draws of the table-tennis experiment
``r = 1`` (calibrated) predicts the target 5-9 cm better 320-160 ms before the hit than ``r = 0``
and 0.7 cm better at 80 ms (docs, target prediction).

``noise="diagonal"`` replaces ``Sigma_s`` by independent per-dimension variances,
``noise="isotropic"`` by ``sigma_s^2 I`` (the GPDM's assumption); the posterior of each phase, its
Student-t predictive and its evidence are those of conjugate Bayesian linear regression
(:mod:`~hgpdm_torch.models.conjugate_regression`, which states them). The noise kind and the scales
``lambda``, ``psi`` are chosen, unless given, by the closed-form evidence ``p(Y | U)``
(``select="evidence"``) or by cross-validation (``select="cv"``,
:mod:`~hgpdm_torch.models.linear_iddm_selection`).

The log belief over a grid of K intention values after frame ``t`` is
``B_t(g) = (1 - eps) B_{t-1}(g) + log p(z_t | z_{t-1}, g, data) / T``, ``B_0 = log p(g)``,
normalised: causal (frame ``t``'s belief reads frames ``<= t`` only) and computed for all frames
of a batch of streams in one pass. ``eps = 0``, ``T = 1`` (the defaults) is exact Bayes for this
model, ``p(g | z_{0:t}) ~ p(g) prod_{s<t} p(z_{s+1} | z_s, g, data)``. Real transitions are not
this model's independent Gaussians (the noise of a movement's frames is correlated and not
Gaussian), so each step's evidence counts too strongly and the credible sets are too small. The
evidence temperature ``T`` and the forgetting ``eps`` of Algorithm 3.2 (which lets the latest
transitions outweigh the earlier ones) correct for it; ``"cv"`` chooses them by the likelihood
of the true intention values of held-out beliefs of the training sequences (k-fold
cross-validation; ``T`` by :func:`~hgpdm_torch.calibration.fit_temperature`), as the
GP IDDM's filters do with a given ``T`` and ``eps``.
"""

from __future__ import annotations

import math
import numbers
import warnings
from collections.abc import Sequence
from typing import Any, NamedTuple

import numpy as np
import torch

from ..calibration import check_temperature
from ..intention_belief import IntentionBelief
from ..observations import ObservationCheck
from ..validation import (
    as_tensor,
    bad_observation,
    check_choice,
    check_outlier_sd,
    check_sequences,
    real_scalar,
)
from .conjugate_regression import (
    default_grid,
    intention_features,
    pls_directions,
    posterior,
    regression_inputs,
    student_t_log_prob,
    student_t_predictive,
    student_t_sample,
    total_log_marginal,
)
from .linear_iddm_persistence import LinearIDDMPersistence
from .linear_iddm_selection import FORGETTING_CANDIDATES, BeliefSelection, forgetful_sum
from .linear_iddm_stream import LinearIDDMStream

__all__ = [
    "AUTO_COEF_PRECISION",
    "AUTO_NOISE_PRIOR",
    "FORGETTING_CANDIDATES",
    "NOISE_KINDS",
    "SELECTION_CRITERIA",
    "SMALL_INTENTION_SD",
    "LinearIDDM",
    "LinearIDDMStream",
]

NOISE_KINDS = ("full", "diagonal", "isotropic")
#: How ``select`` chooses the ``"auto"`` noise kind and prior scales.
SELECTION_CRITERIA = ("evidence", "cv")
#: Candidates of ``coef_precision="auto"`` and ``noise_prior="auto"`` (half-decade log grids).
AUTO_COEF_PRECISION = tuple(10.0 ** (k / 2) for k in range(-3, 5))  # 0.03 .. 100
AUTO_NOISE_PRIOR = tuple(10.0 ** (k / 2) for k in range(-4, 2))  # 0.01 .. 3.2
#: A continuous g whose standard deviation (in a dimension) is below this warns at fit. The
#: coefficient prior ``lambda`` is set for inputs of unit scale (the states are standardised;
#: g enters as given), so on a g of spread ``s`` it acts as ``lambda / s^2`` would on a unit
#: one: below 0.1 that is 100 times stronger, two of the three and a half decades the auto
#: candidates span, and the beliefs over g stay near uniform (on the belief sources' test
#: strokes, g of sd 0.66, the final belief's sd is 2% of g's; with g scaled to sd 0.066, 31%;
#: to sd 0.0066, 99%: uniform).
SMALL_INTENTION_SD = 0.1


class _Design(NamedTuple):
    """What :meth:`LinearIDDM.fit` derives from training data before the prior's update: the
    standardisation ``[Dz]``, the interaction directions ``[S, Dz, r]`` and, per phase, the
    inputs ``U_s [n_s, P]`` and targets ``Y_s [n_s, Dz]``."""

    mean: torch.Tensor
    std: torch.Tensor
    directions: torch.Tensor
    parts: list[tuple[torch.Tensor, torch.Tensor]]


class LinearIDDM(LinearIDDMPersistence, BeliefSelection):
    """Intention-driven linear-Gaussian dynamics with conjugate (matrix-normal inverse-Wishart)
    parameters and exact beliefs over a grid of intention values.

    Args:
        intention: ``"continuous"`` (``g`` real, ``[J]`` or ``[J, Dg]``) or ``"discrete"``
            (integer codes ``0 .. K-1``, one-hot in the transition).
        num_values: K for a discrete g (default ``max(codes) + 1``).
        phase: ``True`` (default): a transition of its own for each frame index of the
            sequences (needs sequences that start at a common point of the movement; a stream
            may not be longer than the longest training sequence). ``False``: one transition
            shared by all frames.
        noise: ``"full"``, ``"diagonal"`` or ``"isotropic"`` noise covariance, or ``"auto"``
            (default): the kind of largest evidence, chosen jointly with the prior scales.
        coef_precision: ``lambda > 0``, prior precision of the coefficients (ridge strength
            on standardised inputs), or ``"auto"`` (default): the value of
            :data:`AUTO_COEF_PRECISION` of largest marginal likelihood of the training
            transitions (empirical Bayes, jointly with ``noise_prior``; by cross-validation
            with ``select="cv"``). A continuous g enters as given, not standardised: in units
            where it varies by about 1 its coefficients are shrunk as much as the states'.
        noise_prior: ``psi > 0``, the prior's guess of the noise variance of a standardised
            observed dimension, or ``"auto"`` (default, from :data:`AUTO_NOISE_PRIOR`).
        interaction_rank: ``r >= 0``: the transition also takes ``phi(g) (x) (V_s^T z_t)``,
            the intention times the ``r`` directions ``V_s`` of each phase's states that
            covary most with it (partial least squares of ``z_t`` on ``phi(g)`` over the
            training transitions), so that how the intention shows in the next frame may
            depend on the current one (module docstring). Default 0: no interaction.
        temperature: ``T > 0``, the evidence temperature of the beliefs (default 1: exact
            Bayes), or ``"cv"``: the ``T`` that maximises the likelihood of the true intention
            values of cross-validated beliefs on the training sequences (module docstring;
            ``cv_folds`` folds, every frame after the first; a continuous g is scored on the
            grid value nearest to it, the default 25-value grid for ``Dg = 1`` and the training
            intentions otherwise). ``T`` is searched in ``[1e-3, 1e3]``
            (:data:`~hgpdm_torch.calibration.TEMPERATURE_BOUNDS`) and warns at a bound.
        forgetting: ``eps`` in ``[0, 1)``, how much of the log belief each new frame forgets
            (default 0: none, exact Bayes), or ``"cv"``: the value of
            :data:`FORGETTING_CANDIDATES` whose cross-validated beliefs (at their own fitted
            ``T`` when ``temperature="cv"``) give the true values the largest likelihood.
        cv_folds: number of folds for ``"cv"`` (sequence ``j`` is held out in fold
            ``j mod cv_folds``; at most the number of sequences).
        outlier_sd: the plausibility threshold of the observations the beliefs take, in
            training standard deviations per observed dimension (default 100, the online
            filter's :data:`~hgpdm_torch.observations.DEFAULT_OUTLIER_SD`), or ``None``
            to refuse only NaN and inf: a frame beyond it (or with an inf, or a NaN in some
            dimensions only) makes :meth:`beliefs`, :meth:`log_evidence` and
            :meth:`log_predictive` raise a ``ValueError`` naming it, and is rejected for its
            stream alone by :meth:`stream`, as
            :class:`~hgpdm_torch.inference.OnlineIntentionFilter` does
            (:class:`~hgpdm_torch.observations.ObservationCheck`, centred on the
            training mean, with the training standard deviation as the spread).
        select: how the ``"auto"`` noise kind and prior scales are chosen: ``"evidence"``
            (default: the marginal likelihood of the training transitions; fast) or ``"cv"``:
            the candidate (of :data:`NOISE_KINDS`, :data:`AUTO_COEF_PRECISION`,
            :data:`AUTO_NOISE_PRIOR`) whose cross-validated beliefs give the true intention
            values the largest likelihood, the criterion of ``temperature="cv"``, searched
            jointly with ``T`` and ``eps`` (module docstring).
        dtype: floating dtype of the fitted statistics.

    After :meth:`fit`, ``noise_kind`` and ``prior`` hold the noise kind and ``(lambda, psi)``
    used, :meth:`log_marginal_likelihood` the evidence of the training transitions under them
    and ``temperature``, ``forgetting`` the ``T``, ``eps`` the beliefs use. A choice on the edge
    of its candidate grid warns (the criterion may improve beyond it).
    """

    def __init__(
        self,
        *,
        intention: str = "continuous",
        num_values: int | None = None,
        phase: bool = True,
        noise: str = "auto",
        coef_precision: float | str = "auto",
        noise_prior: float | str = "auto",
        interaction_rank: int = 0,
        temperature: float | str = 1.0,
        forgetting: float | str = 0.0,
        cv_folds: int = 5,
        outlier_sd: float | None = 100.0,
        select: str = "evidence",
        dtype: torch.dtype = torch.float64,
    ) -> None:
        self.intention = check_choice(intention, "intention", ("continuous", "discrete"))
        self.select = check_choice(select, "select", SELECTION_CRITERIA)
        self.noise = check_choice(noise, "noise", (*NOISE_KINDS, "auto"))
        if not isinstance(phase, bool):
            raise TypeError(f"phase must be a bool, got {phase!r}")
        for name, v in (("coef_precision", coef_precision), ("noise_prior", noise_prior)):
            if v != "auto" and (
                isinstance(v, bool) or not isinstance(v, int | float) or not v > 0
                or math.isinf(v)
            ):  # fmt: skip
                raise ValueError(f"{name} must be a positive finite number or 'auto', got {v!r}")
        if num_values is not None and (
            intention != "discrete" or isinstance(num_values, bool)
            or not isinstance(num_values, int) or num_values < 1
        ):  # fmt: skip
            raise ValueError(
                f"num_values must be a positive int for a discrete intention, got {num_values!r}"
            )
        if dtype not in (torch.float32, torch.float64):
            raise TypeError(f"dtype must be torch.float32 or torch.float64, got {dtype}")
        if temperature != "cv":
            temperature = check_temperature(temperature)
        if forgetting != "cv":
            try:
                forgetting = real_scalar(forgetting, "forgetting")
            except TypeError as err:
                raise ValueError(f"forgetting must be a number in [0, 1) or 'cv': {err}") from None
            if not 0.0 <= forgetting < 1.0:
                raise ValueError(f"forgetting must be in [0, 1) or 'cv', got {forgetting!r}")
        if isinstance(cv_folds, bool) or not isinstance(cv_folds, int) or cv_folds < 2:
            raise ValueError(f"cv_folds must be an int >= 2, got {cv_folds!r}")
        self.outlier_sd = check_outlier_sd(outlier_sd)
        if (
            isinstance(interaction_rank, bool) or not isinstance(interaction_rank, int)
            or interaction_rank < 0
        ):  # fmt: skip
            raise ValueError(f"interaction_rank must be an int >= 0, got {interaction_rank!r}")
        self.interaction_rank = interaction_rank
        self._temperature_arg, self._forgetting_arg = temperature, forgetting
        self.cv_folds = cv_folds
        self.temperature = None if temperature == "cv" else temperature
        self.forgetting = None if forgetting == "cv" else float(forgetting)
        self.phase, self.num_values, self._num_values_arg = phase, num_values, num_values
        self.coef_precision, self.noise_prior = coef_precision, noise_prior
        self.dtype = dtype
        self.fitted = False

    # ------------------------------------------------------------------------------ fitting
    def fit(self, sequences: Sequence[Any] | torch.Tensor, intentions: Any) -> LinearIDDM:
        """Posterior of each phase's coefficients and noise from training sequences.

        Args:
            sequences: J sequences ``[T_j, Dz]`` (a list; lengths may differ, each >= 2) or a
                ``[J, T, Dz]`` tensor, finite.
            intentions: g per sequence, ``[J]`` / ``[J, Dg]`` reals or ``[J]`` integer codes,
                with at least two distinct values (so ``J >= 2``).

        Returns:
            ``self``.

        Raises:
            ValueError: bad shapes or values; intentions that take one value only (or one
                sequence): nothing can be learnt about how g drives the dynamics; data whose
                squares and cross-products overflow the model's dtype (rescale them).

        Warns:
            UserWarning: a continuous g whose standard deviation in some dimension is below
                :data:`SMALL_INTENTION_SD` (0.1) but not 0: the coefficient prior, set for
                inputs of unit scale, then hides g's effect and the beliefs stay near uniform
                (standardise g); a phase with fewer transitions than coefficients; a prior
                scale chosen at the edge of its candidates.
        """
        seqs = check_sequences(sequences, self.dtype)
        g, num_values = self._check_intentions(intentions, len(seqs))
        g = g.to(seqs[0].device)
        if self.intention == "continuous":
            _warn_small_intentions(g)
        design = self._design(seqs, g, num_values)
        fewest, width = min(len(u) for u, _ in design.parts), design.parts[0][0].shape[1]
        if fewest < width:
            warnings.warn(
                f"LinearIDDM: a phase has {fewest} training transitions for {width} "
                "coefficients per feature; its belief rests on the prior and can be far off "
                "(use more recordings, or phase=False)",
                stacklevel=2,
            )
        kinds = NOISE_KINDS if self.noise == "auto" else (self.noise,)
        lams = AUTO_COEF_PRECISION if self.coef_precision == "auto" else (self.coef_precision,)
        psis = AUTO_NOISE_PRIOR if self.noise_prior == "auto" else (self.noise_prior,)
        priors = [(float(lam), float(psi)) for lam in lams for psi in psis]
        temperature, forgetting = self._temperature_arg, self._forgetting_arg
        if self.select == "evidence" or len(kinds) * len(priors) == 1:
            best = None
            for prior in priors:  # empirical Bayes over the candidates (one when all are given)
                stats = [posterior(u, y, *prior) for u, y in design.parts]
                for kind in kinds:
                    evidence = total_log_marginal(stats, kind, prior)
                    if best is None or evidence > best[0]:
                        best = (evidence, kind, prior, stats)
            evidence, kind, prior, stats = best
            if "cv" in (temperature, forgetting):
                kind, prior, temperature, forgetting = self._cross_validate(
                    seqs, g, num_values, [(kind, prior)]
                )
        else:  # the candidate whose held-out beliefs give the true intentions most probability
            kind, prior, temperature, forgetting = self._cross_validate(
                seqs, g, num_values, [(k, p) for p in priors for k in kinds]
            )
            stats = [posterior(u, y, *prior) for u, y in design.parts]
            evidence = total_log_marginal(stats, kind, prior)
        criterion = "evidence" if self.select == "evidence" else "cross-validation"
        for name, value, grid in (("coef_precision", prior[0], lams), ("noise_prior", prior[1],
                                                                         psis)):  # fmt: skip
            if len(grid) > 1 and value in (grid[0], grid[-1]):
                warnings.warn(
                    f"LinearIDDM: the {criterion} chose {name} = {value:g}, the edge of its "
                    f"candidates {grid[0]:g} .. {grid[-1]:g}; pass a value to go beyond them",
                    stacklevel=2,
                )
        # the fitted state, assigned only once everything above succeeded
        self._assign(design, g, num_values, kind, prior, stats, evidence)
        self.temperature, self.forgetting = temperature, float(forgetting)
        self._sequences = [q.clone() for q in seqs]  # the caller's arrays may change later
        return self

    def _design(self, seqs: list[torch.Tensor], g: torch.Tensor, num_values: int | None) -> _Design:
        """Standardisation, interaction directions and each phase's inputs ``U_s`` and targets
        ``Y_s`` of the training transitions of ``seqs`` (everything but the prior's update)."""
        device = seqs[0].device
        frames = torch.cat(seqs)
        mean, std = frames.mean(0), frames.std(0)
        if not bool(torch.isfinite(mean.sum() + std.sum())):
            raise ValueError(
                f"sequences overflow {self.dtype} arithmetic: the mean or standard deviation "
                f"of their frames is not finite (largest |value| "
                f"{float(frames.abs().max()):.3g}); rescale the observations (e.g. standardise "
                "each dimension) before fitting"
            )
        std = torch.where(std > 0, std, torch.ones_like(std))  # constant dims: as they are
        feats = intention_features(g, self.intention, num_values)
        src, phi, dst, step = [], [], [], []
        for j, seq in enumerate(seqs):
            z = (seq - mean) / std
            src.append(z[:-1])
            phi.append(feats[j].expand(len(z) - 1, -1))
            dst.append(z[1:])
            step.append(torch.arange(len(z) - 1, device=device))
        src, phi, y, step = torch.cat(src), torch.cat(phi), torch.cat(dst), torch.cat(step)
        num_phases = int(step.max()) + 1 if self.phase else 1
        masks = [step == s if self.phase else step >= 0 for s in range(num_phases)]
        if self.interaction_rank > src.shape[1]:
            raise ValueError(
                f"interaction_rank {self.interaction_rank} exceeds Dz = {src.shape[1]}, the "
                "number of directions there are"
            )
        # [S, Dz, r] interaction directions of each phase, then its inputs u_t
        directions = torch.stack([pls_directions(src[m], phi[m], self.interaction_rank)
                                  for m in masks])  # fmt: skip
        parts = [(regression_inputs(src[m], phi[m], directions[s]), y[m])
                 for s, m in enumerate(masks)]  # fmt: skip
        for u, y_s in parts:  # the conjugate update's squares and cross-products [U, Y]^T [U, Y]
            uy = torch.cat([u, y_s], 1)
            if not bool(torch.isfinite((uy.T @ uy).sum())):
                raise ValueError(
                    f"intentions overflow {self.dtype} arithmetic: the squares and "
                    "cross-products of the transitions' inputs [z_t, phi(g), 1, ...] are not "
                    f"finite (largest |g| {float(g.abs().max()):.3g}; the states are "
                    "standardised, a continuous g enters as given); rescale g to about unit "
                    "scale before fitting"
                )
        return _Design(mean, std, directions, parts)

    def _assign(
        self, design: _Design, g: torch.Tensor, num_values: int | None, kind: str,
        prior: tuple[float, float], stats: list[tuple[torch.Tensor, ...]], evidence: float,
    ) -> None:  # fmt: skip
        """Make this model the posterior ``stats`` (one tuple per phase) of ``design``."""
        self.obs_mean, self.obs_std, self.obs_dim = design.mean, design.std, len(design.mean)
        self.intentions, self.intention_dim, self.num_values = g.clone(), g.shape[1], num_values
        self.num_phases, self.noise_kind, self.prior, self._evidence = (
            len(stats), kind, prior, evidence
        )  # fmt: skip
        # [S, P, P] Lambda_n, [S, P, Dz] M_n, [S, Dz, Dz] Psi_n, [S] nu_n
        self.precision, self.coef, self.scatter, self.dof = (
            torch.stack([st[i] for st in stats]) for i in range(4)
        )
        self.directions = design.directions
        self.precision_tril = torch.linalg.cholesky(self.precision)
        self.fitted = True

    def _fold_model(self, num_values: int | None) -> LinearIDDM:
        """An unfitted model of this one's structure, without searches or outlier screen: what
        the cross-validation (:class:`~hgpdm_torch.models.linear_iddm_selection.BeliefSelection`)
        fits on each fold's training sequences."""
        return LinearIDDM(intention=self.intention, num_values=num_values, phase=self.phase,
                          interaction_rank=self.interaction_rank, outlier_sd=None,
                          dtype=self.dtype)  # fmt: skip

    def log_marginal_likelihood(self) -> float:
        """``log p(Z_{1:} | Z_{:-1}, g)`` of the (standardised) training transitions under the
        fitted noise kind and prior, summed over the phases: the closed-form evidence of the
        conjugate model, which ``"auto"`` maximises with ``select="evidence"``."""
        self._check_fitted()
        return float(self._evidence)

    # ---------------------------------------------------------------------------- inference
    def log_predictive(
        self, z_prev: Any, z_next: Any, grid: Any = None, step: int = 0
    ) -> torch.Tensor:
        """``log p(z_{t+1} | z_t, g, data)`` of one transition at each grid value.

        Args:
            z_prev: ``[B, Dz]`` (or ``[Dz]``) raw observations at frame ``step``.
            z_next: the same streams' raw observations at the next frame.
            grid: ``[K]`` / ``[K, Dg]`` intention values (default :meth:`grid`).
            step: the frame index ``t`` of ``z_prev`` (its phase; ignored with ``phase=False``).

        Returns:
            ``[B, K]`` (or ``[K]``) log densities of the raw ``z_next`` (the standardisation's
            Jacobian included).

        Raises:
            ValueError: a row that is not finite or is implausible (``outlier_sd``), or whose
                density overflows the model's dtype, naming it.
        """
        self._check_fitted()
        a = self._check_obs(z_prev, "z_prev", min_ndim=1)
        b = self._check_obs(z_next, "z_next", min_ndim=1)
        if a.shape != b.shape:
            raise ValueError(
                f"z_prev and z_next must have the same shape, got {a.shape}, {b.shape}"
            )
        values = self.grid(grid)
        if isinstance(step, bool) or not isinstance(step, numbers.Integral) or step < 0:
            raise ValueError(f"step must be a non-negative int, got {step!r}")
        step = int(step)
        out = self._log_predictive(a.reshape(-1, self.obs_dim), b.reshape(-1, self.obs_dim),
                                   self._features(values), step)  # fmt: skip
        out = out.reshape(*a.shape[:-1], len(values))
        _check_evidence(out, "z_next", "its transition from z_prev")
        return out

    def _log_predictive(
        self, a: torch.Tensor, b: torch.Tensor, feats: torch.Tensor, step: int
    ) -> torch.Tensor:
        """``[B, K]`` log predictive of raw ``b [B, Dz]`` from raw ``a [B, Dz]`` (not finite
        where the rows overflow the arithmetic: the callers check)."""
        bsz, k, d = len(a), len(feats), self.obs_dim
        za, zb = self._standardise(a), self._standardise(b)
        phi = feats[None].expand(bsz, k, -1)
        df, loc, scale = self._predictive(za[:, None].expand(bsz, k, d), phi, step)
        logp = student_t_log_prob(zb[:, None].expand_as(loc), df, loc, scale, self.noise_kind)
        # an overflow gives NaN or inf (the distributions do not validate): the callers check
        return logp - self.obs_std.log().sum()

    def _predictive(
        self, za: torch.Tensor, phi: torch.Tensor, step: int
    ) -> tuple[float | torch.Tensor, torch.Tensor, torch.Tensor]:
        """The Student-t posterior predictive of the next standardised frame from standardised
        ``za [..., Dz]`` under intention features ``phi [..., P]``: ``(df, loc [..., Dz],
        scale)``, ``scale`` a Cholesky factor ``[..., Dz, Dz]`` (full and isotropic noise) or
        per-dimension scales ``[..., Dz]`` (diagonal noise)."""
        s = step if self.phase else 0
        if s >= self.num_phases:
            raise ValueError(
                f"step {step} has no transition: the training sequences had at most "
                f"{self.num_phases + 1} frames (phase=True fits one transition per frame index)"
            )
        u = regression_inputs(za, phi, self.directions[s])
        return student_t_predictive(u, self.precision_tril[s], self.coef[s], self.scatter[s],
                                    self.dof[s], self.noise_kind, self.prior[1])  # fmt: skip

    def sample_next(
        self, z_prev: Any, g: Any, step: int, generator: torch.Generator | None = None
    ) -> torch.Tensor:
        """Draw the next frame of each stream from the posterior predictive
        ``p(z_{t+1} | z_t, g, data)`` (the density :meth:`log_predictive` scores).

        Args:
            z_prev: ``[B, Dz]`` raw frames at frame index ``step``.
            g: ``[B]`` or ``[B, Dg]`` intention value of each stream (codes for a discrete g).
            step: the frame index of ``z_prev`` (its phase).
            generator: random generator (the Student-t's chi-square scale is drawn from a
                NumPy generator seeded by it, so a seeded generator gives the same draws).

        Returns:
            ``[B, Dz]`` raw frames.
        """
        self._check_fitted()
        a = self._check_obs(z_prev, "z_prev", min_ndim=2)
        if a.dim() != 2:
            raise ValueError(f"z_prev must be [B, Dz], got {tuple(a.shape)}")
        values = as_tensor(g, "g", dtype=self.dtype, device=a.device)
        values = values[:, None] if values.dim() == 1 else values
        if values.shape != (len(a), self.intention_dim):
            raise ValueError(
                f"g must be [B = {len(a)}] or [B, Dg = {self.intention_dim}], got "
                f"{tuple(values.shape)}"
            )
        if isinstance(step, bool) or not isinstance(step, numbers.Integral) or step < 0:
            raise ValueError(f"step must be a non-negative int, got {step!r}")
        df, loc, scale = self._predictive(self._standardise(a), self._features(values), int(step))
        z = student_t_sample(df, loc, scale, self.noise_kind, generator)
        return z * self.obs_std + self.obs_mean

    def log_evidence(self, obs: Any, grid: Any = None) -> torch.Tensor:
        """Cumulative ``log p(z_{1:t} | z_0, g, data)`` after every frame.

        Args:
            obs: ``[B, T, Dz]`` streams (or one ``[T, Dz]``), raw and finite, each starting at
                the phase of the training sequences' first frame.
            grid: intention values (default :meth:`grid`).

        Returns:
            ``[B, T, K]`` (or ``[T, K]``); frame 0 holds zeros (no transition yet).

        Raises:
            ValueError: a frame that is not finite or is implausible (more than ``outlier_sd``
                training standard deviations from the training mean in a dimension), or whose
                transition's density overflows the model's dtype, naming its stream and frame
                (as :func:`~hgpdm_torch.inference.infer_intention` does for a bad row).
        """
        return self._transition_evidence(obs, grid).cumsum(-2)

    def _transition_evidence(self, obs: Any, grid: Any = None) -> torch.Tensor:
        """``log p(z_t | z_{t-1}, g, data)`` of each transition: ``[B, T, K]`` (or ``[T, K]``),
        frame 0 zeros; :meth:`log_evidence` sums it, :meth:`beliefs` forgets and tempers it."""
        self._check_fitted()
        z = self._check_obs(obs, "obs", min_ndim=2)
        obs_shape, single = z.shape, z.dim() == 2
        z = z[None] if single else z
        if z.dim() != 3 or z.shape[0] == 0 or z.shape[1] == 0:
            raise ValueError(
                f"obs must be [T, Dz] or [B, T, Dz] with B, T >= 1, got {tuple(obs_shape)}"
            )
        feats = self._features(self.grid(grid))
        steps = [torch.zeros(z.shape[0], len(feats), dtype=z.dtype, device=z.device)]
        for t in range(z.shape[1] - 1):
            steps.append(self._log_predictive(z[:, t], z[:, t + 1], feats, t))
        out = torch.stack(steps, 1)
        out = out[0] if single else out
        _check_evidence(out, "obs", "the transition into it")
        return out

    def beliefs(self, obs: Any, grid: Any = None, log_prior: Any = None) -> IntentionBelief:
        """The belief over the grid after every frame (causal: frame t reads frames <= t).

        Args:
            obs: ``[B, T, Dz]`` or ``[T, Dz]`` streams (see :meth:`log_evidence`).
            grid: intention values (default :meth:`grid`).
            log_prior: ``[K]`` log prior over the grid (default uniform).

        The log belief is the recursion ``B_t = (1 - forgetting) B_{t-1} + E_t / temperature``
        from ``B_0 = log_prior`` over the evidence ``E_t`` of each transition (module docstring),
        normalised; ``log_prior + log_evidence`` at the defaults.

        Returns:
            :class:`~hgpdm_torch.inference.IntentionBelief` with ``[B, T, K]`` probabilities
            and, for a continuous g, the posterior mean and sd ``[B, T, Dg]``.

        Raises:
            ValueError: a bad frame, naming its stream and frame (:meth:`log_evidence`).
        """

        values = self.grid(grid)
        steps = self._transition_evidence(obs, values) / self.temperature
        steps[..., 0, :] = self._log_prior(log_prior, len(values))  # B_0 (no transition yet)
        log_w = forgetful_sum(steps, self.forgetting)
        return IntentionBelief.from_log(log_w, values, self.intention == "continuous")

    def _log_prior(self, log_prior: Any, k: int) -> torch.Tensor:
        """``[K]`` log prior over the grid (zeros: uniform; ``-inf`` excludes a value)."""
        if log_prior is None:
            return torch.zeros(k, dtype=self.dtype, device=self.coef.device)
        prior = log_prior if isinstance(log_prior, torch.Tensor) else np.asarray(log_prior, float)
        prior = torch.as_tensor(prior, dtype=self.dtype, device=self.coef.device)
        if prior.shape != (k,):
            raise ValueError(f"log_prior must be [K = {k}], got {tuple(prior.shape)}")
        # -inf excludes a value; NaN, +inf or no finite value at all is no prior
        if bool(prior.isnan().any()) or bool((prior == math.inf).any()) or not bool(
            prior.isfinite().any()
        ):  # fmt: skip
            raise ValueError("log_prior must be finite or -inf, with at least one finite value")
        return prior

    def stream(
        self, batch_size: int = 1, grid: Any = None, log_prior: Any = None, *,
        strict: bool = False,
    ) -> LinearIDDMStream:  # fmt: skip
        """An online belief for ``batch_size`` streams that advance one frame per
        :meth:`LinearIDDMStream.update` (the same beliefs as :meth:`beliefs`, frame by frame);
        ``strict``: raise for a bad frame instead of rejecting it for its stream."""
        return LinearIDDMStream(self, batch_size, grid, log_prior, strict=strict)

    def grid(self, values: Any = None, num: int = 25) -> torch.Tensor:
        """``[K, Dg]`` intention values: ``values`` checked, or by default all codes of a
        discrete g / ``num`` values over the training range of a continuous ``Dg = 1`` g."""
        self._check_fitted()
        device = self.coef.device
        if isinstance(num, bool) or not isinstance(num, numbers.Integral) or num < 1:
            raise ValueError(f"num must be a positive int, got {num!r}")
        if values is None:
            if self.intention == "continuous" and self.intention_dim != 1:
                raise ValueError("a multi-dimensional continuous g needs an explicit grid")
            return default_grid(self.intentions, self.intention, self.num_values, num)
        v = as_tensor(values, "grid", dtype=self.dtype, device=device)
        v = v[:, None] if v.dim() == 1 else v
        if v.dim() != 2 or len(v) == 0 or v.shape[1] != self.intention_dim:
            raise ValueError(
                f"grid must be a non-empty [K] or [K, Dg = {self.intention_dim}] tensor, "
                f"got {tuple(v.shape)}"
            )
        if self.intention == "discrete" and bool(
            ((v != v.round()) | (v < 0) | (v >= self.num_values)).any()
        ):
            raise ValueError(f"a discrete grid holds integer codes in [0, {self.num_values - 1}]")
        return v

    # ------------------------------------------------------------------------------ helpers
    def _features(self, g: torch.Tensor) -> torch.Tensor:
        return intention_features(g, self.intention, self.num_values)

    def _standardise(self, z: torch.Tensor) -> torch.Tensor:
        return (z - self.obs_mean) / self.obs_std

    def _check_fitted(self) -> None:
        if not self.fitted:
            raise RuntimeError("this LinearIDDM is not fitted yet: call fit(sequences, intentions)")

    def _observation_check(self) -> ObservationCheck:
        """Which rows are bad (:class:`~hgpdm_torch.observations.ObservationCheck`):
        non-finite, or more than ``outlier_sd`` training standard deviations from the training
        mean in a dimension."""

        return ObservationCheck(self.obs_mean.double(), self.obs_std.double(), self.outlier_sd)

    def _check_obs(self, value: Any, name: str, min_ndim: int) -> torch.Tensor:
        """``value [..., Dz]`` as a finite tensor of the model's dtype and device; a bad row
        (:meth:`_observation_check`) raises a ``ValueError`` naming its index."""
        z = as_tensor(value, name, dtype=self.dtype, device=self.coef.device, min_ndim=min_ndim)
        if z.shape[-1] != self.obs_dim:
            raise ValueError(f"{name} must have Dz = {self.obs_dim} columns, got {z.shape[-1]}")
        found = self._observation_check().first_bad(z)
        if found is not None:
            index, why = found
            raise bad_observation(f"{name}{list(index)}", why)
        return z

    def _check_intentions(self, intentions: Any, num: int) -> tuple[torch.Tensor, int | None]:
        g = as_tensor(intentions, "intentions", dtype=self.dtype)
        g = g[:, None] if g.dim() == 1 else g
        if g.dim() != 2 or len(g) != num:
            raise ValueError(f"intentions must be [J] or [J, Dg] with J = {num} sequences, got "
                             f"{tuple(g.shape)}")  # fmt: skip
        k = None
        if self.intention == "discrete":
            if g.shape[1] != 1 or bool((g != g.round()).any()) or bool((g < 0).any()):
                raise ValueError("discrete intentions must be a [J] vector of codes >= 0")
            k = int(g.max()) + 1 if self._num_values_arg is None else self._num_values_arg
            if bool((g >= k).any()):
                raise ValueError(f"discrete intentions must lie in [0, {k - 1}]")
        if len(torch.unique(g, dim=0)) < 2:
            value = ", ".join(f"{v:.6g}" for v in g[0].tolist())
            raise ValueError(
                f"intentions must take at least 2 distinct values, got the single value {value} "
                f"for all {num} sequence(s): the model learns how g drives the dynamics from "
                "sequences of different g, so it needs at least two sequences with different "
                "intentions"
            )
        return g, k


def _warn_small_intentions(g: torch.Tensor) -> None:
    """Warn where a dimension of the continuous intentions ``g [J, Dg]`` varies by less than
    :data:`SMALL_INTENTION_SD` (a constant dimension, spread 0, carries nothing to scale)."""
    sd = g.std(0)
    small = (sd > 0) & (sd < SMALL_INTENTION_SD)
    if bool(small.any()):
        d = int(torch.nonzero(small)[0])
        where = f" in dimension {d}" if g.shape[1] > 1 else ""
        warnings.warn(
            f"LinearIDDM: the intentions have a standard deviation of {float(sd[d]):.3g}"
            f"{where}, below {SMALL_INTENTION_SD:g}, while the coefficient prior "
            "(coef_precision) is set for inputs of unit scale (the states are standardised to "
            "standard deviation 1; a continuous g enters as given): the prior then hides g's "
            "effect on the dynamics and the beliefs over g stay near uniform; standardise g "
            "(subtract its mean, divide by its standard deviation) before fitting, and map "
            "the belief's values back",
            stacklevel=3,
        )


def _check_evidence(evidence: torch.Tensor, name: str, what: str) -> None:
    """Raise where the log densities ``evidence [..., K]`` of the rows of ``name`` are not
    finite: the rows, finite and within the plausibility threshold or not, overflow the
    arithmetic of the model's dtype."""
    bad = ~torch.isfinite(evidence).all(-1)
    if bool(bad.any()):
        index = [int(i) for i in torch.nonzero(bad)[0]]
        raise ValueError(
            f"{name}{index}: the density of {what} is not finite: the rows overflow "
            f"{evidence.dtype} arithmetic; rescale the observations, or keep outlier_sd "
            "finite (default 100) to refuse such rows"
        )
