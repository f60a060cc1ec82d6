"""Linear-Gaussian intention-driven dynamics with conjugate Bayesian parameters.

The IDDM of Ch. 3 lets the intention ``g`` drive a GP transition over a low-dimensional latent
state with one isotropic process noise shared by all frames of a movement. :class:`LinearIDDM`
keeps the IDDM's idea (``g`` is an input of the dynamics; inference is Bayes' theorem over
``g``) and drops those three assumptions: the state is the standardised observation itself, and the
transition is linear in ``[z_t, phi(g), 1]`` (optionally with an intention-state interaction) with
its own coefficients and its own noise covariance (per dimension by default) at each frame index of
the movement (``phase=True``), both
integrated out under their conjugate prior, so the one-step predictive is a Student-t (not in the
thesis). For movements recorded from a common start (a stroke's first frame a fixed time before
the hit), this is what the target-prediction experiment needs: there the target information at
80 ms lies in the step-specific, anisotropic residual of the last transition, which a stationary
transition with isotropic noise over a 6-D latent averages away (docs, target prediction;
``python -m benchmarks target_dynamics``).

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

``noise="diagonal"`` replaces ``Sigma_s`` by independent per-dimension variances (inverse-gamma,
the ``Dz = 1`` case of the prior per dimension), ``noise="isotropic"`` by ``sigma_s^2 I`` with
``sigma_s^2 ~ IG(2, psi)`` (the GPDM's assumption). Posterior after ``n`` transitions
``U [n, P]``, ``Y [n, Dz]``:
``Lambda_n = U^T U + lambda I``, ``M_n = Lambda_n^-1 U^T Y``,
``Psi_n = psi I + Y^T Y - M_n^T Lambda_n M_n`` (computed as ``psi I + R^T R + lambda M_n^T M_n``
with the residuals ``R = Y - U M_n``, which does not cancel in float32), ``nu_n = Dz + 2 + n``;
the predictive of
``z_{t+1}`` given ``u`` is Student-t with ``nu_n - Dz + 1`` degrees of freedom, location
``M_n^T u`` and scale matrix ``(1 + u^T Lambda_n^-1 u) Psi_n / (nu_n - Dz + 1)``. The noise
kind and the scales ``lambda``, ``psi`` are chosen, unless given, by the closed-form evidence
``p(Y | U)`` (``select="evidence"``) or by cross-validation (``select="cv"``, below).

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
cross-validation; ``T`` by :func:`~hgpdm_torch.inference.calibration.fit_temperature`), as the
GP IDDM's filters do with a given ``T`` and ``eps``.

The evidence scores how well the model predicts the next frame, all ``Dz`` dimensions of it; the
beliefs need only the part of the dynamics that depends on ``g``, a few of the ``P Dz``
coefficients. ``select="cv"`` therefore chooses the noise kind and the prior scales by the
criterion of ``T`` and ``eps``: the likelihood of the true intentions under cross-validated beliefs
(jointly with ``T`` and ``eps`` where they are ``"cv"``). On the table-tennis strokes it picks a
3-30 times stronger ridge ``lambda`` than the evidence does and predicts the target better
(docs, target prediction). It costs a posterior per fold and candidate and the held-out
evidence of each (144 candidates with everything ``"auto"``: about 8 s for a hundred sequences
of 5 frames; each fold's held-out sequences are scored in one batch, padded to the longest).
"""

from __future__ import annotations

import math
import numbers
import warnings
from collections.abc import Sequence
from typing import TYPE_CHECKING, Any, NamedTuple

import numpy as np
import torch
from pyro.distributions import MultivariateStudentT
from torch.distributions import StudentT

from ..validation import (
    as_tensor,
    bad_observation,
    check_choice,
    check_outlier_sd,
    real_scalar,
)
from .persistence import SavedModel, save_model

if TYPE_CHECKING:  # the inference package imports the models: no import at run time
    from ..inference.filtering import ObservationCheck
    from ..inference.intention.grid import IntentionBelief

__all__ = [
    "AUTO_COEF_PRECISION",
    "AUTO_NOISE_PRIOR",
    "FORGETTING_CANDIDATES",
    "NOISE_KINDS",
    "SELECTION_CRITERIA",
    "LinearIDDM",
    "LinearIDDMStream",
]

NOISE_KINDS = ("full", "diagonal", "isotropic")
#: How ``select`` chooses the ``"auto"`` noise kind and prior scales.
SELECTION_CRITERIA = ("evidence", "cv")
#: Candidates of ``forgetting="cv"``.
FORGETTING_CANDIDATES = (0.0, 0.1, 0.2, 0.3, 0.5, 0.7)
#: Candidates of ``coef_precision="auto"`` and ``noise_prior="auto"`` (half-decade log grids).
AUTO_COEF_PRECISION = tuple(10.0 ** (k / 2) for k in range(-3, 5))  # 0.03 .. 100
AUTO_NOISE_PRIOR = tuple(10.0 ** (k / 2) for k in range(-4, 2))  # 0.01 .. 3.2


class _Design(NamedTuple):
    """What :meth:`LinearIDDM.fit` derives from training data before the prior's update: the
    standardisation ``[Dz]``, the interaction directions ``[S, Dz, r]`` and, per phase, the
    inputs ``U_s [n_s, P]`` and targets ``Y_s [n_s, Dz]``."""

    mean: torch.Tensor
    std: torch.Tensor
    directions: torch.Tensor
    parts: list[tuple[torch.Tensor, torch.Tensor]]


class LinearIDDM(SavedModel):
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
            (:data:`~hgpdm_torch.inference.calibration.TEMPERATURE_BOUNDS`) and warns at a bound.
        forgetting: ``eps`` in ``[0, 1)``, how much of the log belief each new frame forgets
            (default 0: none, exact Bayes), or ``"cv"``: the value of
            :data:`FORGETTING_CANDIDATES` whose cross-validated beliefs (at their own fitted
            ``T`` when ``temperature="cv"``) give the true values the largest likelihood.
        cv_folds: number of folds for ``"cv"`` (sequence ``j`` is held out in fold
            ``j mod cv_folds``; at most the number of sequences).
        outlier_sd: the plausibility threshold of the observations the beliefs take, in
            training standard deviations per observed dimension (default 100, the online
            filter's :data:`~hgpdm_torch.inference.filtering.DEFAULT_OUTLIER_SD`), or ``None``
            to refuse only NaN and inf: a frame beyond it (or with an inf, or a NaN in some
            dimensions only) makes :meth:`beliefs`, :meth:`log_evidence` and
            :meth:`log_predictive` raise a ``ValueError`` naming it, and is rejected for its
            stream alone by :meth:`stream`, as
            :class:`~hgpdm_torch.inference.OnlineIntentionFilter` does
            (:class:`~hgpdm_torch.inference.filtering.ObservationCheck`, centred on the
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
            from ..inference.calibration import check_temperature  # no import cycle at run time

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
        """
        seqs = self._check_sequences(sequences)
        g, num_values = self._check_intentions(intentions, len(seqs))
        g = g.to(seqs[0].device)
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
                stats = [_posterior(u, y, *prior) for u, y in design.parts]
                for kind in kinds:
                    evidence = _total_log_marginal(stats, kind, prior)
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
            stats = [_posterior(u, y, *prior) for u, y in design.parts]
            evidence = _total_log_marginal(stats, kind, prior)
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
        feats = _features(g, self.intention, num_values)
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
        directions = torch.stack([_directions(src[m], phi[m], self.interaction_rank)
                                  for m in masks])  # fmt: skip
        parts = [(_inputs(src[m], phi[m], directions[s]), y[m]) for s, m in enumerate(masks)]
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

    def _cross_validate(
        self, seqs: list[torch.Tensor], g: torch.Tensor, num_values: int | None,
        candidates: list[tuple[str, tuple[float, float]]],
    ) -> tuple[str, tuple[float, float], float, float]:  # fmt: skip
        """The candidate ``(noise kind, (lambda, psi))`` and ``(T, eps)`` whose beliefs of each
        held-out sequence, by the candidate fitted on the other folds (every frame after the
        first; the truth is the nearest grid value), give the truths the smallest mean negative
        log probability: for each candidate and each candidate ``eps``, ``T`` by
        :func:`~hgpdm_torch.inference.calibration.fit_temperature` (or the given ``T``; the
        given ``eps``). Ties go to the earlier candidate."""
        from ..inference.calibration import TEMPERATURE_BOUNDS, fit_temperature

        folds = min(self.cv_folds, len(seqs))  # >= 2: fit refuses a single intention value
        # the fitted model's default grid; the distinct training intentions for a 2-D+ g
        if g.shape[1] > 1:
            values = torch.unique(g, dim=0)
        else:
            values = _default_grid(g, self.intention, num_values, 25)
        truth = torch.cdist(g, values).argmin(-1)
        # per fold: its design, its held-out sequences [n, T, Dz] and the mask of their
        # transitions, and the true value index of each transition
        # held-out training frames are scored whatever their distance from the other folds'
        sub = LinearIDDM(intention=self.intention, num_values=num_values, phase=self.phase,
                         interaction_rank=self.interaction_rank, outlier_sd=None,
                         dtype=self.dtype)  # fmt: skip
        splits, hits = [], []
        for fold in range(folds):
            held = [j for j in range(len(seqs)) if j % folds == fold]
            rest = [j for j in range(len(seqs)) if j % folds != fold]
            with warnings.catch_warnings():  # few transitions per phase: the full fit warned
                warnings.simplefilter("ignore")
                design = sub._design([seqs[j] for j in rest], g[rest], num_values)
            cut = len(design.parts) + 1 if self.phase else None
            held_seqs = [seqs[j][:cut] for j in held]
            # one batch: each sequence padded with its last frame to the longest, and a mask
            # [n, T - 1] of its own transitions (the padding's evidence is never scored)
            longest = max(len(q) for q in held_seqs)
            batch = torch.stack([torch.cat([q, q[-1:].expand(longest - len(q), -1)])
                                 for q in held_seqs])  # fmt: skip
            steps_idx = torch.arange(longest - 1, device=batch.device)
            lengths = torch.tensor([len(q) for q in held_seqs], device=batch.device)
            mask = steps_idx < (lengths[:, None] - 1)
            hits.append(truth[held][:, None].expand_as(mask)[mask])
            splits.append((design, rest, batch, mask))
        hits_all = torch.cat(hits)
        epsilons = (FORGETTING_CANDIDATES if self._forgetting_arg == "cv"
                    else (self._forgetting_arg,))  # fmt: skip
        posteriors: dict[tuple[int, tuple[float, float]], list] = {}  # per (fold, prior)
        best = None
        for kind, prior in candidates:  # one candidate's held-out evidence in memory at a time
            steps = []  # per fold: [n, T - 1, K] evidence of each held-out transition, mask
            for fold, (design, rest, batch, mask) in enumerate(splits):
                if (fold, prior) not in posteriors:
                    posteriors[fold, prior] = [_posterior(u, y, *prior) for u, y in design.parts]
                sub._assign(design, g[rest], num_values, kind, prior, posteriors[fold, prior],
                            math.nan)  # fmt: skip
                steps.append((sub._transition_evidence(batch, values)[:, 1:], mask))
            for eps in epsilons:
                # from a uniform prior B_0 = 0, B_t is the forgetful sum of the first t steps
                # (a padded step comes after all of a sequence's own: it changes none of them)
                logs = torch.cat([_forget(e, float(eps))[m] for e, m in steps])
                if self._temperature_arg == "cv":
                    temperature = fit_temperature(logs, hits_all)
                else:
                    temperature = self._temperature_arg
                log_p = torch.log_softmax(logs / temperature, -1)
                nll = -float(log_p.gather(-1, hits_all[:, None]).mean())
                if best is None or nll < best[0]:
                    best = (nll, kind, prior, temperature, float(eps))
        _, kind, prior, temperature, eps = best
        if self._temperature_arg == "cv" and not (
            1.01 * TEMPERATURE_BOUNDS[0] < temperature < TEMPERATURE_BOUNDS[1] / 1.01
        ):
            warnings.warn(
                f"LinearIDDM: the cross-validated temperature is at its bound ({temperature:.3g}"
                "): the held-out beliefs are " + ("never wrong (separable data: the beliefs "
                "become one-hot)" if temperature < 1 else "uninformative about g") + "; pass a "
                "temperature to choose it yourself",
                stacklevel=3,
            )  # fmt: skip
        if len(epsilons) > 1 and eps == epsilons[-1]:
            warnings.warn(
                f"LinearIDDM: the cross-validation chose forgetting = {eps:g}, the edge of its "
                f"candidates; pass a value to go beyond it",
                stacklevel=3,
            )
        return kind, prior, temperature, eps

    # --------------------------------------------------------------------------- persistence
    #: the fitted statistics :meth:`state_dict` holds
    _STATE = (
        "obs_mean", "obs_std", "intentions", "directions", "precision", "coef", "scatter", "dof",
    )  # fmt: skip

    def config(self) -> dict[str, Any]:
        """Constructor arguments that refit this model without any search: the noise kind,
        prior, temperature and forgetting as chosen (not ``"auto"``/``"cv"``)."""
        self._check_fitted()
        return {"intention": self.intention, "num_values": self._num_values_arg,
                "phase": self.phase, "noise": self.noise_kind,
                "coef_precision": self.prior[0], "noise_prior": self.prior[1],
                "interaction_rank": self.interaction_rank, "temperature": self.temperature,
                "forgetting": self.forgetting, "cv_folds": self.cv_folds,
                "outlier_sd": self.outlier_sd}  # fmt: skip

    def _data_arguments(self) -> dict[str, Any]:
        """:meth:`fit`'s arguments: the training ``sequences`` and their ``intentions``."""
        self._check_fitted()
        g = self.intentions[:, 0] if self.intention_dim == 1 else self.intentions
        if self.intention == "discrete":
            g = g.long()
        return {"sequences": [s.clone() for s in self._sequences], "intentions": g.clone()}

    def state_dict(self) -> dict[str, torch.Tensor]:
        """The fitted statistics (standardisation, training intentions and each phase's
        interaction directions ``V_s``, ``Lambda_n``, ``M_n``, ``Psi_n``, ``nu_n``) and the
        evidence, as tensors."""
        self._check_fitted()
        state = {k: getattr(self, k).clone() for k in self._STATE}
        state["log_evidence"] = torch.tensor(self._evidence, dtype=self.dtype)
        return state

    def load_state_dict(self, state: dict[str, torch.Tensor]) -> None:
        """Take saved statistics into this fitted model; each must agree with what its own
        training data give, to ``1e-6`` (float64) or ``1e-3`` (float32) of the tensor's largest
        entry (at least 1): another machine's summation order moves them by far less (measured
        up to ``1e-9`` / ``3e-6``), statistics of other data by far more.

        Raises:
            RuntimeError: other keys, shapes or dtypes, or statistics of other data.
        """
        own = self.state_dict()
        if "directions" not in state and own["directions"].shape[-1] == 0:
            state = {**state, "directions": own["directions"]}  # files from before the option
        if set(state) != set(own):
            raise RuntimeError(f"state keys {sorted(state)} differ from {sorted(own)}")
        for key, mine in own.items():
            theirs = state[key]
            if not isinstance(theirs, torch.Tensor) or (theirs.shape, theirs.dtype) != (
                mine.shape, mine.dtype
            ):  # fmt: skip
                raise RuntimeError(f"state[{key!r}] must be a {mine.dtype} tensor {mine.shape}")
            tol = 1e-6 if self.dtype == torch.float64 else 1e-3
            scale = float(mine.abs().max().clamp_min(1.0)) if mine.numel() else 1.0
            if mine.numel() and float((theirs.to(mine.device) - mine).abs().max()) > tol * scale:
                raise RuntimeError(
                    f"state[{key!r}] differs from what the training data give: the statistics "
                    "belong to other data"
                )
        for key in self._STATE:
            setattr(self, key, state[key].to(own[key].device).clone())
        self._evidence = float(state["log_evidence"])
        self.precision_tril = torch.linalg.cholesky(self.precision)

    @classmethod
    def _from_saved(
        cls, data: dict[str, Any], config: dict[str, Any], dtype: torch.dtype,
        state: dict[str, Any],
    ) -> LinearIDDM:  # fmt: skip
        """The model :func:`~hgpdm_torch.models.load_model` rebuilds from a file: constructed
        from ``config`` and fitted on ``data``. ``config`` must hold the choices (no
        ``"auto"``/``"cv"`` search), and the saved coefficients' shape must be the one the
        data and ``config`` imply before anything is fitted, so a file cannot ask for more work
        than its own size.

        Raises:
            ValueError: a search in ``config``, or statistics of another shape.
        """
        searched = [k for k in ("noise", "coef_precision", "noise_prior", "temperature",
                                "forgetting") if config.get(k) in ("auto", "cv")]  # fmt: skip
        if searched:
            raise ValueError(f"the configuration asks for a search ({', '.join(searched)})")
        seqs, g = data.get("sequences"), data.get("intentions")
        coef = state.get("coef")
        if not (isinstance(seqs, list) and seqs and isinstance(g, torch.Tensor)
                and isinstance(coef, torch.Tensor) and coef.dim() == 3):  # fmt: skip
            raise ValueError("the data need sequences, intentions and [S, P, Dz] coefficients")
        if config.get("intention") == "discrete":
            width = config.get("num_values") or int(g.max()) + 1
        else:
            width = 1 if g.dim() == 1 else g.shape[-1]
        dz = seqs[0].shape[-1] if isinstance(seqs[0], torch.Tensor) else -1
        phases = max(len(q) for q in seqs) - 1 if config.get("phase", True) else 1
        rank = config.get("interaction_rank", 0)
        size = dz + width + 1 + width * rank if isinstance(rank, int) else -1
        if tuple(coef.shape) != (phases, size, dz):
            raise ValueError(
                f"the saved coefficients {tuple(coef.shape)} do not fit the data "
                f"({phases}, {size}, {dz})"
            )
        with warnings.catch_warnings():  # the original fit warned already
            warnings.simplefilter("ignore")
            return cls(**config, dtype=dtype).fit(**data)

    def save(self, path: Any) -> None:
        """Save the fitted model to ``path`` in the checksummed, versioned format of
        :mod:`~hgpdm_torch.models.persistence` (configuration, training data, statistics);
        load it with :func:`~hgpdm_torch.models.load_model` or :meth:`load`. A registered
        subclass with constructor arguments of its own adds them in an override of
        :meth:`config`.

        Raises:
            RuntimeError: the model is not fitted.
            TypeError: its class is not registered (:func:`~hgpdm_torch.models.register_model`).
        """
        self._check_fitted()
        save_model(self, path)

    def _saved_dtype(self) -> torch.dtype:
        return self.dtype

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
        if self.noise_kind == "diagonal":  # independent dimensions, each a Student-t
            logp = StudentT(df, loc, scale, validate_args=False).log_prob(zb[:, None]).sum(-1)
        else:
            logp = MultivariateStudentT(df, loc, scale, validate_args=False).log_prob(
                zb[:, None].expand_as(loc)
            )
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
        d = self.obs_dim
        u = _inputs(za, phi, self.directions[s])
        loc = u @ self.coef[s]  # [..., Dz]
        # 1 + u^T Lambda_n^-1 u, with the Cholesky factor of Lambda_n
        flat = u.reshape(-1, u.shape[-1])
        v = torch.linalg.solve_triangular(self.precision_tril[s], flat.T, upper=False)
        inflate = (1.0 + v.pow(2).sum(0)).reshape(u.shape[:-1])
        nu, scatter = self.dof[s], self.scatter[s]
        if self.noise_kind == "full":
            tril = torch.linalg.cholesky(scatter / (nu - d + 1))
            return nu - d + 1, loc, tril * inflate[..., None, None].sqrt()
        if self.noise_kind == "diagonal":
            # per dimension the Dz = 1 prior, with the same nu_n - Dz + 1 = 3 + n
            df = nu - d + 1
            return df, loc, (scatter.diagonal() / df).sqrt() * inflate[..., None].sqrt()
        # isotropic: sigma^2 ~ IG(2, psi): a_n = 2 + n Dz / 2, b_n = psi + tr(Psi_n - psi I) / 2
        n = nu - d - 2
        a_n = 2.0 + n * d / 2
        psi = self.prior[1]
        b_n = psi + 0.5 * (scatter.trace() - d * psi)
        eye = torch.eye(d, dtype=za.dtype, device=za.device)
        return 2 * a_n, loc, eye * (b_n / a_n * inflate)[..., None, None].sqrt()

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
        draw_on = a.device if generator is None else generator.device
        eps = torch.randn(loc.shape, generator=generator, dtype=loc.dtype, device=draw_on)
        eps = eps.to(a.device)
        seed = int(torch.randint(2**62, (1,), generator=generator, device=draw_on))
        shape = loc.shape if self.noise_kind == "diagonal" else loc.shape[:-1]
        chi2 = np.random.default_rng(seed).chisquare(float(df), size=tuple(shape))
        t_scale = (float(df) / torch.as_tensor(chi2, dtype=loc.dtype, device=a.device)).sqrt()
        if self.noise_kind == "diagonal":
            z = loc + scale * eps * t_scale
        else:
            z = loc + (scale @ eps[..., None])[..., 0] * t_scale[..., None]
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
        from ..inference.intention.grid import IntentionBelief

        values = self.grid(grid)
        steps = self._transition_evidence(obs, values) / self.temperature
        steps[..., 0, :] = self._log_prior(log_prior, len(values))  # B_0 (no transition yet)
        log_w = _forget(steps, self.forgetting)
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
            return _default_grid(self.intentions, self.intention, self.num_values, num)
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
        return _features(g, self.intention, self.num_values)

    def _standardise(self, z: torch.Tensor) -> torch.Tensor:
        return (z - self.obs_mean) / self.obs_std

    def _check_fitted(self) -> None:
        if not self.fitted:
            raise RuntimeError("this LinearIDDM is not fitted yet: call fit(sequences, intentions)")

    def _observation_check(self) -> ObservationCheck:
        """Which rows are bad (:class:`~hgpdm_torch.inference.filtering.ObservationCheck`):
        non-finite, or more than ``outlier_sd`` training standard deviations from the training
        mean in a dimension."""
        from ..inference.filtering import ObservationCheck

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

    def _check_sequences(self, sequences: Any) -> list[torch.Tensor]:
        if isinstance(sequences, np.ndarray) and sequences.dtype != object:
            sequences = torch.as_tensor(sequences)
        if isinstance(sequences, torch.Tensor):
            if sequences.dim() != 3:
                raise ValueError(f"sequences as a tensor must be [J, T, Dz], got "
                                 f"{tuple(sequences.shape)}")  # fmt: skip
            sequences = list(sequences)
        if not isinstance(sequences, Sequence) or isinstance(sequences, str) or not sequences:
            raise TypeError("sequences must be a non-empty list of [T, Dz] arrays or a tensor")
        out = []
        for j, s in enumerate(sequences):
            t = as_tensor(s, f"sequences[{j}]", ndim=2, dtype=self.dtype)
            if len(t) < 2:
                raise ValueError(f"sequences[{j}] needs at least 2 frames, got {len(t)}")
            if out and t.shape[1] != out[0].shape[1]:
                raise ValueError(f"sequences[{j}] has {t.shape[1]} columns, expected "
                                 f"{out[0].shape[1]}")  # fmt: skip
            out.append(t.to(out[0].device) if out else t)
        return out

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


def _check_index(index: int, size: int) -> None:
    if isinstance(index, bool) or not isinstance(index, numbers.Integral) or not (
        0 <= index < size
    ):  # fmt: skip
        raise ValueError(f"index must be an int in [0, {size}), got {index!r}")


def _forget(steps: torch.Tensor, eps: float) -> torch.Tensor:
    """``B_t = (1 - eps) B_{t-1} + steps_t`` along dim -2 from ``B_0 = steps_0``:
    ``[..., T, K] -> [..., T, K]`` (a cumulative sum for ``eps = 0``)."""
    if eps == 0.0:
        return steps.cumsum(-2)
    out = [steps[..., 0, :]]
    for t in range(1, steps.shape[-2]):
        out.append((1.0 - eps) * out[-1] + steps[..., t, :])
    return torch.stack(out, -2)


def _directions(z: torch.Tensor, phi: torch.Tensor, rank: int) -> torch.Tensor:
    """``[Dz, rank]``: the partial-least-squares directions of the states ``z [n, Dz]`` on the
    intention features ``phi [n, P]`` (sklearn, unscaled: ``z`` is standardised already).
    Zeros, with a warning, where they cannot be estimated: fewer than ``rank + 1`` transitions,
    or an intention that does not vary over them (no interaction in that phase)."""
    zeros = z.new_zeros(z.shape[1], rank)
    if rank == 0:
        return zeros
    if len(z) < rank + 1 or bool((phi.std(0) == 0).all()):
        warnings.warn(
            f"LinearIDDM: a phase has {len(z)} training transitions"
            + (" whose intentions are all equal" if len(z) >= rank + 1 else "")
            + f"; its interaction directions (rank {rank}) cannot be estimated and are left "
            "out (zeros)",
            stacklevel=4,
        )
        return zeros
    from sklearn.cross_decomposition import PLSRegression

    pls = PLSRegression(rank, scale=False).fit(z.cpu().numpy(), phi.cpu().numpy())
    return torch.as_tensor(pls.x_rotations_, dtype=z.dtype, device=z.device)


def _inputs(z: torch.Tensor, phi: torch.Tensor, directions: torch.Tensor) -> torch.Tensor:
    """``u = [z, phi(g), 1, phi(g) (x) (V^T z)]``: ``z [..., Dz]``, ``phi [..., P]``,
    ``V [Dz, r]`` -> ``[..., Dz + P + 1 + P r]`` (the last block empty for ``r = 0``)."""
    inter = phi[..., :, None] * (z @ directions)[..., None, :]
    one = torch.ones(*z.shape[:-1], 1, dtype=z.dtype, device=z.device)
    return torch.cat([z, phi, one, inter.flatten(-2)], -1)


def _default_grid(
    g: torch.Tensor, intention: str, num_values: int | None, num: int
) -> torch.Tensor:
    """``[K, 1]``: every code of a discrete g, or ``num`` values over the range of a continuous
    ``g [J, 1]``."""
    if intention == "discrete":
        return torch.arange(num_values, dtype=g.dtype, device=g.device)[:, None]
    return torch.linspace(float(g.min()), float(g.max()), num, dtype=g.dtype,
                          device=g.device)[:, None]  # fmt: skip


def _features(g: torch.Tensor, intention: str, num_values: int | None) -> torch.Tensor:
    """``phi(g)``: g itself, or the one-hot code of a discrete g."""
    if intention == "continuous":
        return g
    return torch.nn.functional.one_hot(g[:, 0].long(), num_values).to(g.dtype)


def _posterior(u: torch.Tensor, y: torch.Tensor, lam: float, psi: float):
    """Conjugate update of one phase from ``u [n, P]``, ``y [n, Dz]``: ``Lambda_n [P, P]``,
    ``M_n [P, Dz]``, ``Psi_n [Dz, Dz]`` (prior ``psi I`` included) and ``nu_n``."""
    p, d = u.shape[1], y.shape[1]
    precision = u.T @ u + lam * torch.eye(p, dtype=u.dtype, device=u.device)
    coef = torch.cholesky_solve(u.T @ y, torch.linalg.cholesky(precision))
    # Y^T Y - M^T Lambda_n M as a sum of squares: the subtraction cancels in float32
    resid = y - u @ coef
    scatter = resid.T @ resid + lam * coef.T @ coef
    scatter = 0.5 * (scatter + scatter.T) + psi * torch.eye(d, dtype=u.dtype, device=u.device)
    return precision, coef, scatter, torch.tensor(d + 2.0 + len(u), dtype=u.dtype, device=u.device)


def _total_log_marginal(
    stats: list[tuple[torch.Tensor, ...]], kind: str, prior: tuple[float, float]
) -> float:
    """The evidence of all phases: the sum of :func:`_log_marginal` over ``stats``."""
    return float(sum(_log_marginal(*st, kind, *prior) for st in stats))


def _log_marginal(
    precision: torch.Tensor, coef: torch.Tensor, scatter: torch.Tensor, dof: torch.Tensor,
    noise: str, lam: float, psi: float,
) -> torch.Tensor:  # fmt: skip
    """``log p(Y | U)`` of one phase: the matrix-normal inverse-Wishart evidence
    ``pi^(-n D/2) (|Lambda_0| / |Lambda_n|)^(D/2) |Psi_0|^(nu_0/2) / |Psi_n|^(nu_n/2)
    Gamma_D(nu_n/2) / Gamma_D(nu_0/2)``; per dimension with ``D = 1`` for diagonal noise; with
    the inverse-gamma ``IG(2, psi)`` and ``(2 pi)^(-n D/2)`` for isotropic noise."""
    p, d = coef.shape
    n = float(dof) - d - 2
    coef_term = 0.5 * (p * math.log(lam) - torch.linalg.cholesky(precision).diagonal().log().sum()
                       * 2)  # fmt: skip
    if noise == "isotropic":
        a_n = 2.0 + n * d / 2
        b_n = psi + 0.5 * (scatter.trace() - d * psi)
        return (-0.5 * n * d * math.log(2 * math.pi) + d * coef_term + 2.0 * math.log(psi)
                - a_n * b_n.log() + math.lgamma(a_n) - math.lgamma(2.0))  # fmt: skip
    if noise == "diagonal":  # each dimension its own D = 1 model: nu_0 = 3, nu_n = 3 + n
        nu0, nun = 3.0, 3.0 + n
        per_dim = (-0.5 * n * math.log(math.pi) + coef_term + 0.5 * nu0 * math.log(psi)
                   - 0.5 * nun * scatter.diagonal().log() + math.lgamma(nun / 2)
                   - math.lgamma(nu0 / 2))  # fmt: skip
        return per_dim.sum()
    nu0, nun = d + 2.0, float(dof)
    logdet = 2 * torch.linalg.cholesky(scatter).diagonal().log().sum()
    return (-0.5 * n * d * math.log(math.pi) + d * coef_term + 0.5 * nu0 * d * math.log(psi)
            - 0.5 * nun * logdet + torch.special.multigammaln(scatter.new_tensor(nun / 2), d)
            - torch.special.multigammaln(scatter.new_tensor(nu0 / 2), d))  # fmt: skip


class LinearIDDMStream:
    """Online beliefs of a fitted :class:`LinearIDDM` for B streams (:meth:`LinearIDDM.stream`).

    Every :meth:`update` brings the next frame of all B streams, which therefore share their
    frame index (the phase). The frames are taken as by
    :class:`~hgpdm_torch.inference.OnlineIntentionFilter`, through the same code
    (:func:`~hgpdm_torch.inference.intention.streams.screen_observations`): a row of NaN is a
    missing frame; a bad row (an inf, a NaN in some dimensions only, or more than the model's
    ``outlier_sd`` training standard deviations from the training mean in a dimension) is
    *rejected*: it counts as missing, ``belief.rejected`` flags it and ``rejected_count``
    counts it (``strict``: a ``ValueError`` naming the stream, frame and dimension, with no
    state changed). A missing or rejected frame is missing for its stream alone: the
    transitions into and out of it carry no evidence. A frame whose transition's density
    overflows the arithmetic (possible only with ``outlier_sd=None``) is rejected too. The
    belief follows Algorithm 3.2 (:func:`~hgpdm_torch.inference.intention.streams.belief_step`):
    with ``forgetting > 0`` every stream's log belief decays at every frame after the first,
    its row missing or not.

    Stream isolation: every stream's transition is computed at every frame (an unusable one at
    the training mean, and discarded), so nothing one stream receives changes another's belief,
    not even its rounding.

    Attributes:
        log_weights: ``[B, K]`` log belief (normalised after the first frame).
        previous: ``[B, Dz]`` each stream's last usable frame; ``has_previous [B]``: whether
            it was the frame just before.
        frames: frames given so far (the next frame's index).
        rejected_count: ``[B]`` int64, rejected frames of each stream since :meth:`reset`.
        check: the :class:`~hgpdm_torch.inference.filtering.ObservationCheck` in use.
    """

    def __init__(
        self, model: LinearIDDM, batch_size: int, grid: Any, log_prior: Any, *,
        strict: bool = False,
    ) -> None:  # fmt: skip
        model._check_fitted()
        if isinstance(batch_size, bool) or not isinstance(batch_size, numbers.Integral) or (
            batch_size < 1
        ):  # fmt: skip
            raise ValueError(f"batch_size must be a positive int, got {batch_size!r}")
        if not isinstance(strict, bool):
            raise TypeError(f"strict must be a bool, got {strict!r}")
        self.model, self.batch_size, self.strict = model, int(batch_size), strict
        self.values = model.grid(grid)
        self._feats = model._features(self.values)
        self._prior = model._log_prior(log_prior, len(self.values))
        self.check = model._observation_check()
        self.reset()

    def reset(self) -> None:
        """Start every stream again at frame 0 with the prior belief."""
        b, d = self.batch_size, self.model.obs_dim
        device = self.model.coef.device
        self.frames = 0
        self.previous = torch.zeros(b, d, dtype=self.model.dtype, device=device)
        self.has_previous = torch.zeros(b, dtype=torch.bool, device=device)
        self.log_weights = self._prior.expand(b, -1).clone()
        self.rejected_count = torch.zeros(b, dtype=torch.long, device=device)

    def _where(self, b: int) -> str:
        return f"z[{b}] (stream {b}, frame {self.frames})"

    def repeat(self, index: int, num: int) -> LinearIDDMStream:
        """A new stream object holding ``num`` copies of stream ``index`` (its belief, last frame
        and frame count): the particles of a look-ahead (Monte-Carlo planning) start there."""
        _check_index(index, self.batch_size)
        if isinstance(num, bool) or not isinstance(num, numbers.Integral) or num < 1:
            raise ValueError(f"num must be a positive int, got {num!r}")
        out = object.__new__(LinearIDDMStream)
        out.__dict__.update(self.__dict__)
        out.batch_size = int(num)
        for name in ("previous", "has_previous", "log_weights", "rejected_count"):
            value = getattr(self, name)[index]
            setattr(out, name, value.expand(num, *value.shape).clone())
        return out

    def sample_next(self, generator: torch.Generator | None = None) -> torch.Tensor:
        """``[B, Dz]``: each stream's next frame drawn from the model given its belief, with
        ``g ~ p(g | z_{0:t})`` over the grid and ``z_{t+1} ~ p(z_{t+1} | z_t, g, data)``
        (:meth:`LinearIDDM.sample_next`). Every stream needs its last frame (``has_previous``)
        and a transition after it."""
        if self.frames == 0 or not bool(self.has_previous.all()):
            raise ValueError(
                "sample_next needs every stream's frame just before (update them with a usable "
                "frame first)"
            )
        prob = self.log_weights.softmax(-1)
        draw_on = prob.device if generator is None else generator.device
        k = torch.multinomial(prob.to(draw_on), 1, generator=generator)[:, 0].to(prob.device)
        return self.model.sample_next(self.previous, self.values[k], self.frames - 1, generator)

    def update(self, z: Any) -> IntentionBelief:
        """Add the next frame ``z [B, Dz]`` (``[Dz]`` for one stream) of every stream.

        Returns:
            The belief ``[B, K]`` after it (``[K]``, with a scalar ``rejected``, for a ``[Dz]``
            row, as :meth:`~hgpdm_torch.inference.OnlineIntentionFilter.update`), with
            ``rejected [B]``: the streams whose frame was bad and taken as missing.

        Raises:
            ValueError: a row of the wrong size, (``phase=True``) a frame past the longest
                training sequence, or (``strict``) a bad frame; the streams are then left as
                they were.
        """
        from ..inference.intention.streams import belief_step, flagged_belief, screen_observations

        model = self.model
        if model.phase and self.frames > model.num_phases:
            raise ValueError(
                f"frame {self.frames} has no transition: the training sequences had at most "
                f"{model.num_phases + 1} frames (phase=True); reset() the streams"
            )
        z, rejected, single = screen_observations(
            z, self.check, self.batch_size, model.obs_dim, device=model.coef.device,
            strict=self.strict, where=self._where,
        )  # fmt: skip
        z = z.to(model.dtype)
        good = torch.isfinite(z).all(-1)  # neither missing nor rejected
        log_weights = self.log_weights
        if self.frames > 0:  # the transition from the previous frame, for every stream
            use = good & self.has_previous
            fill = model.obs_mean.expand_as(z)
            a = torch.where(use[:, None], self.previous, fill)
            b = torch.where(use[:, None], z, fill)
            evidence = model._log_predictive(a, b, self._feats, self.frames - 1)
            overflow = use & ~torch.isfinite(evidence).all(-1)
            if bool(overflow.any()):  # outlier_sd=None let a frame through that overflows
                bad = int(torch.nonzero(overflow)[0])
                if self.strict:
                    raise ValueError(
                        f"{self._where(bad)} cannot be used: the density of its transition is "
                        f"not finite (the frame overflows {model.dtype} arithmetic); rescale "
                        "the observations or keep outlier_sd finite"
                    )
                rejected, good, use = rejected | overflow, good & ~overflow, use & ~overflow
            # every stream forgets at every frame, its row missing or not
            log_weights = belief_step(
                log_weights, evidence, use, model.forgetting, model.temperature
            )
        self.log_weights = log_weights
        self.previous = torch.where(good[:, None], z, self.previous)
        self.has_previous = good
        self.rejected_count += rejected
        self.frames += 1
        return flagged_belief(
            self.log_weights, self.values, model.intention == "continuous", single, rejected
        )
