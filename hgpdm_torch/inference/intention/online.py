r"""Online intention inference (Algorithm 3.2) for B streams: :class:`OnlineIntentionFilter`.

One Gaussian ``q`` over the latent state is shared by all K intention values, and the log
belief follows ``B_t(g) = E_t(g) + (1 - eps) B_{t-1}(g)`` with the forgetting factor ``eps``.
The evidence ``E_t(g)`` is either the thesis's ``Q_{t-1}(g)`` from one-step filtering and
one-step backward smoothing under the current belief (``evidence="bound"``,
:func:`~hgpdm_torch.inference.intention.linearisation.expected_log_conditional`), or (the
default) the GP-ADF predictive likelihood ``log q(z_t | z_{1:t-1}, g)`` from the shared ``q``.
With ``q'`` the filtered ``q(x_t | z_{1:t})`` (the ``"bound"`` default) ``Q`` differs from
the KL form (docs/design/math.md#the-online-filters-q) only by terms shared by all g, and the K
moment matchings of the prediction step are reused.

The pieces: the transition moments of all K values at once
(:mod:`~hgpdm_torch.inference.intention.transition`: the IDDM's fast path or the generic one for
any model), the measurement update (:mod:`~hgpdm_torch.inference.intention.measurement`), and
the isolated streams (:mod:`~hgpdm_torch.inference.intention.streams`), whose ``update`` this
class inherits.

Shapes: ``B`` streams, ``K`` intention values, ``Dx`` latent, ``Dz`` observed, ``Dg`` intention
dims.
"""

from __future__ import annotations

import numbers
from typing import Any

import torch

from ... import settings
from ...calibration import intention_log_prior
from ...gaussian import independent_joint, mixture_moments, rts_step
from ...gp_shared import sparse_posterior
from ...linalg import symmetrize
from ...models import GPDM
from ...observations import DEFAULT_OUTLIER_SD, ObservationCheck
from ...tiling import OpCount, stream_chunk
from .compiled import CompiledStep
from .grid import check_chunk_size, intention_grid
from .linearisation import expected_log_conditional
from .measurement import measurement_operations, measurement_update
from .options import (
    BeliefUpdate,
    Evidence,
    FilterOptions,
    ObservationPolicy,
    StatePrior,
    TransitionPath,
)
from .state_prior import first_state_prior, marginal_state_prior
from .streams import IsolatedStreams
from .transition import check_precision, transition_moments

__all__ = ["OnlineIntentionFilter"]


class OnlineIntentionFilter(IsolatedStreams):
    r"""Online intention inference (Algorithm 3.2) for B independent streams at once.

    One Gaussian ``q`` over the latent state is shared by all intention values. Each
    :meth:`update` with a new observation ``z_t`` per stream predicts ``q(x_{t-1}, x_t)`` for every
    intention value from the filtered ``q(x_{t-1})`` (the transition moments of
    :mod:`~hgpdm_torch.inference.intention.transition`), then updates the log belief
    ``B_t = E_t(g) + (1 - eps) B_{t-1}`` (normalised; lines 10-11) with the evidence ``E_t(g)``
    of this step:

    - ``evidence="bound"`` (Algorithm 3.2 as printed): mix the K predictions under ``B_{t-1}``,
      moment matched (``mixing="grid"``), or moment match the transition at ``[x, g]`` with
      ``g`` Gaussian with the belief's mean and variance (``mixing="gaussian"``, Sec. 3.4.2);
      filter ``q(x_t)`` (GP-ADF, Eq. 25, 32-35); smooth ``q(x_{t-1} | z_{1:t})`` one step back
      (GP-RTSS, Eq. 26-27); ``E_t(g) = Q_{t-1}(g)`` (module docstring).
    - ``evidence="predictive"`` (default): ``E_t(g) = log q(z_t | z_{1:t-1}, g)``, the GP-ADF
      predictive likelihood of ``z_t`` under each intention from the shared ``q(x_{t-1})``; then
      ``q(x_t)`` is the moment-matched mixture of the K filtered Gaussians under ``B_t``.

    Why two: with one ``q`` shared by all g, ``Q_{t-1}(g)`` scores g as if the latent states were
    known exactly, so per step it counts evidence ``~ |f(x, g) - f(x, g')|^2 / alpha_4``; with a
    small process noise ``alpha_4`` the belief collapses after a step or two and is badly
    over-confident (``tests/inference/test_intention.py`` measures it). The predictive
    likelihood weighs the same transition difference against the state and observation
    uncertainty: it is the exact Bayes recursion of a filter that collapses ``q`` to one
    Gaussian per step, and its credible sets are calibrated when the model is right. Both
    reduce to GP-ADF/GP-RTSS for K = 1.

    The first observation of a stream initialises ``q(x_1)`` from the prior ``N(mu0, Sigma0)``
    and leaves the belief at the prior (lines 1-3). A NaN row is a prediction-only step: ``q``
    is predicted under the belief and the belief only forgets (``B_t = (1 - eps) B_{t-1}``),
    since an unobserved step carries no evidence about g; before the first observation it leaves
    the stream unstarted.

    Stream isolation: nothing one stream receives or computes changes another's belief, bit for
    bit: streams are updated in chunks that are fixed ranges of stream indices, each computing
    all its streams (unobserved and discarded where they are not due), so that not even the
    rounding of a stream's update depends on the other streams' observations, failures or
    (re)starts.

    - An observation row that is bad (:class:`~hgpdm_torch.observations.ObservationCheck`:
      +-inf, NaN in some channels only, or more than ``outlier_sd`` training standard
      deviations from the training mean in a channel) is *rejected*: that stream takes a
      prediction-only step, exactly as for a NaN row, and ``belief.rejected`` flags it;
      ``rejected_count`` counts the stream's rejections.
    - A stream whose update fails numerically (a covariance that does not factorise even with
      jitter, e.g. an indefinite state covariance; a LAPACK error; or a result that is not
      finite) or whose stored state is not finite is *restarted*: its state goes back to the
      prior (``mu0``, ``Sigma0``, the prior belief, not started), ``belief.reset_streams``
      flags it and ``reset_count`` counts it. A stream that failed during the update restarts
      with its next observation; one found with a non-finite stored state (e.g. set by hand)
      restarts with the current one. A failing chunk of streams is split in halves until the
      failing streams are found, then recomputed with them at the prior and unobserved (the
      extra work is paid only when a stream fails).
    - With ``strict=True`` both raise a ``ValueError`` naming the stream, its step and (for an
      observation) the channel instead, and the update changes no state.

    The checks are vectorised over streams: an update costs a few elementwise operations on the
    ``[B, Dz]`` observations and the ``[B, ...]`` state more than the filter itself (about 0.1 ms
    for one stream).

    Args:
        model: any fitted model of the toolkit: an :class:`~hgpdm_torch.models.IDDM`, an
            :class:`~hgpdm_torch.models.HGPDM`, a subclass with a transition kernel that
            :mod:`hgpdm_torch.expectations` supports, or a plain
            :class:`~hgpdm_torch.models.GPDM` (no g: one value, K = 1; the belief stays 1 and
            the filter is GP-ADF, :func:`~hgpdm_torch.inference.filtering.filter_sequence`).
        intentions: grid of values (continuous g, ``[K]``/``[K, Dg]``) or codes (discrete g);
            see :func:`intention_grid`.
        forgetting: ``eps`` in ``[0, 1)``, a Python or NumPy real number or a 0-dim tensor; 0
            keeps all evidence (plain Bayes recursion).
        batch_size: B, the number of independent streams.
        prior: ``[K]`` prior probabilities (default uniform).
        evidence: ``"predictive"`` or ``"bound"``.
        mixing: ``"grid"`` or ``"gaussian"`` (continuous g with ``evidence="bound"`` only).
        relinearize: (``"bound"``) score ``Q`` with the transition moment matched at the smoothed
            ``q(x_{t-1} | z_{1:t})`` (exactly the KL form of
            docs/design/math.md#the-online-filters-q, twice the cost) instead of the filtered
            ``q(x_{t-1} | z_{1:t-1})``. ``mixing="gaussian"`` always does.
        mu0: ``[Dx]`` mean of the first state's prior (default: the training latents' mean).
        Sigma0: ``[Dx, Dx]`` its covariance (default: the training latents' covariance).
        state_prior: ``"marginal"`` (``mu0``, ``Sigma0``) or, for a discrete g, ``"class"``:
            the first observation is scored under each value's prior ``p(x_1 | g)``
            (:func:`class_state_prior`), ``B_1(g) = log p(g) + log q(z_1 | g)``, and ``q(x_1)``
            is the moment-matched mixture of the K posteriors; see :func:`infer_intention`.
        temperature: ``T > 0``; every step's evidence counts as ``E_t(g) / T``
            (:mod:`~hgpdm_torch.calibration`): 1 is the thesis's recursion, ``T > 1``
            a less confident belief (choose it with
            :func:`~hgpdm_torch.calibration.fit_temperature` on held-out streams).
        dtype: computation dtype (default the model's; float32 halves memory traffic). Another
            dtype than the model's is refused (``ValueError``, naming the cause) where, at
            training latents and three state spreads, its rounding error in the transition
            moments exceeds :data:`PRECISION_LIMIT` times the predictive standard deviation
            (covariance: variance), or its rounding error in the evidence ``log q(z_t | g)``
            (differences between grid values; measurement update plus transition moments, for
            the next frame's observation and a distant frame's) exceeds
            :data:`EVIDENCE_LIMIT` = 0.1 nats: typically float32 with a small process noise
            alpha_4 or a measurement GP with an RBF kernel, whose weights
            ``(K + noise I)^-1`` are too large for 7 digits. An accepted float32 filter keeps
            its beliefs within about 0.02 of float64's.
        transition: how the transition moments of the K values are computed
            (:func:`~hgpdm_torch.inference.intention.transition.transition_moments`):
            ``"shared"``, the fast path for the IDDM's tensor-product kernel (one RBF over x
            times a factor of g: :class:`SharedTransition`); ``"generic"``, moment matching of
            the transition GP at ``[x, g_k]`` for any supported kernel
            (:class:`~hgpdm_torch.inference.intention.transition.GenericTransition`); or
            ``"auto"`` (default): shared where the kernel allows it, else generic. Both give
            the same moments where both apply.
        inducing: number of pseudo-inputs of a sparse (DTC) transition GP (Sec. 3.3.3:
            :meth:`GPPosterior.sparse <hgpdm_torch.gp.GPPosterior.sparse>` on training latents
            paired with few intention values,
            :func:`~hgpdm_torch.gp_shared.sparse_posterior`), on either transition path (the
            same pseudo-inputs on both), or ``None`` for the exact GP. Needs one process noise
            (not ``noise_per_value``).
        inducing_values: distinct intention values among the pseudo-inputs (continuous g;
            default ``round(sqrt(inducing))``, all training values when ``inducing >= N``).
        chunk_size: positive int, streams processed together (fixed ranges of stream indices,
            see above). The default (:func:`~hgpdm_torch.tiling.stream_chunk`) is 32 on a CPU
            (128 where the compiled kernel runs) and on an accelerator as many streams as one
            ``psi2`` tile holds; the ``N x N``
            expectations are tiled inside the transition whatever the chunk
            (:class:`~hgpdm_torch.settings.moment_path`; on the materialised path
            ``2^19 / N^2``, which keeps its ``[chunk, N, N]`` temporaries in cache).
        outlier_sd: plausibility threshold in training standard deviations per channel (default
            100; see :class:`~hgpdm_torch.observations.ObservationCheck`); ``None``
            rejects only non-finite values and partly NaN rows.
        strict: raise instead of rejecting an observation or restarting a stream.
        belief: the belief update as one object
            (:class:`~hgpdm_torch.inference.intention.options.BeliefUpdate`: ``forgetting``,
            ``temperature``, ``prior``), instead of those keywords.
        observations: the observation policy as one object
            (:class:`~hgpdm_torch.inference.intention.options.ObservationPolicy`:
            ``outlier_sd``, ``strict``), instead of those keywords.

    The keywords come in groups, each one choice of the algorithm
    (:mod:`~hgpdm_torch.inference.intention.options`): ``belief`` (``forgetting``,
    ``temperature``, ``prior``), ``evidence`` (with ``mixing``, ``relinearize``),
    ``state_prior`` (with ``mu0``, ``Sigma0``), ``transition`` (with ``inducing``,
    ``inducing_values``) and ``observations`` (``outlier_sd``, ``strict``). A group may be
    passed as its object (``evidence=Evidence("bound", relinearize=True)``) or as its flat
    keywords, not both (a ``ValueError`` names them); ``options`` holds the groups a filter
    uses, and ``OnlineIntentionFilter(other_model, grid, **vars(f.options))`` makes the same
    choices.

    Attributes:
        options: the :class:`~hgpdm_torch.inference.intention.options.FilterOptions` in use,
            the one place the choices are read from (``f.options.belief.forgetting``,
            ``f.options.evidence.kind``, ``f.options.observations.strict``, ...).
        mean, cov: ``[B, Dx]``, ``[B, Dx, Dx]`` the shared ``q(x_t)`` of every stream.
        log_belief: ``[B, K]`` normalised log posterior over the grid.
        started: ``[B]`` bool, whether the stream has seen its first observation.
        steps: ``[B]`` int64, observations (missing ones included) given to each stream since it
            was (re)started; a stream's current observation has step ``steps[b]`` in messages.
            For a phase-aware IDDM (``IDDM(phase_width=...)``) the transition out of a stream's
            state takes the phase ``steps - 1``: streams start at frame 0 of the model's
            training sequences, one row per frame.
        rejected_count, reset_count: ``[B]`` int64, rejected observations and automatic restarts
            of each stream since :meth:`reset`.
        check: the :class:`~hgpdm_torch.observations.ObservationCheck` in use.
        posterior: the transition :class:`~hgpdm_torch.gp.GPPosterior` in use (its sparse DTC
            approximation with ``inducing``), in the model's dtype.

    Shapes: ``update(z [B, Dz])`` (or ``[Dz]`` when B = 1) -> :class:`IntentionBelief` with
    ``prob [B, K]`` (or ``[K]``), ``rejected [B]`` and ``reset_streams [B]`` (or ``[]``).
    """

    def __init__(
        self,
        model: GPDM,
        intentions: Any = None,
        *,
        forgetting: float = 0.2,
        batch_size: int = 1,
        prior: Any = None,
        evidence: str | Evidence = "predictive",
        mixing: str = "grid",
        relinearize: bool = False,
        mu0: Any = None,
        Sigma0: Any = None,
        state_prior: str | StatePrior = "marginal",
        temperature: float = 1.0,
        dtype: torch.dtype | None = None,
        transition: str | TransitionPath = "auto",
        inducing: int | None = None,
        inducing_values: int | None = None,
        chunk_size: int | None = None,
        outlier_sd: float | None = DEFAULT_OUTLIER_SD,
        strict: bool = False,
        belief: BeliefUpdate | None = None,
        observations: ObservationPolicy | None = None,
    ) -> None:
        values = intention_grid(model, intentions)
        # the option groups (options.py), each from a group object or its flat keywords
        self.options = options = FilterOptions.from_keywords(
            {"belief": belief, "evidence": evidence, "state_prior": state_prior,
             "transition": transition, "observations": observations},
            {"forgetting": forgetting, "temperature": temperature, "prior": prior,
             "mixing": mixing, "relinearize": relinearize, "mu0": mu0, "Sigma0": Sigma0,
             "inducing": inducing, "inducing_values": inducing_values,
             "outlier_sd": outlier_sd, "strict": strict},
        )  # fmt: skip
        path, state = options.transition, options.state_prior
        if (
            isinstance(batch_size, bool)
            or not isinstance(batch_size, numbers.Integral)
            or int(batch_size) < 1
        ):
            raise ValueError(f"batch_size must be a positive int, got {batch_size!r}")
        chunk_size = check_chunk_size(chunk_size)
        kind = getattr(model, "intention", None)  # None: a GPDM without g
        if options.evidence.mixing == "gaussian" and kind != "continuous":
            raise ValueError("mixing='gaussian' needs a continuous g and evidence='bound'")
        self.dtype = dtype or model.latent.dtype
        self.continuous = kind == "continuous"
        # the exact transition GP or its sparse DTC approximation, for every use below
        # a phase-aware IDDM's transition GP takes each stream's phase (frame index) too
        self.phase = getattr(model, "phase_width", None) is not None
        phased = {"phase": True} if self.phase else {}
        if self.phase and path.inducing is not None:
            raise ValueError(
                "inducing (a sparse transition GP) is not available for a phase-aware IDDM "
                "(phase_width set): use the exact GP (inducing=None)"
            )
        trans = sparse_posterior(
            model.transition_posterior(), values.shape[-1], path.inducing, path.inducing_values
        )
        self.posterior = trans
        self.transition = transition_moments(
            trans, values, self.dtype, transition=path.path, **phased
        )
        meas = model.measurement_posterior()
        self.check = ObservationCheck.from_measurement(meas, options.observations.outlier_sd)
        self.measure = measurement_update(meas, self.dtype)
        self.compiled_step = CompiledStep.build(self.transition, self.measure, options)
        own = trans.train_inputs.dtype
        if self.dtype != own:
            reference = transition_moments(trans, values, own, transition=path.path, **phased)
            measure = measurement_update(meas, own)
            check_precision(model, reference, self.transition, measure, self.measure)
        gaussian = options.evidence.mixing == "gaussian"
        self.gaussian_transition = trans.to_dtype(self.dtype) if gaussian else None
        self.values = self.transition.values
        self.log_prior = intention_log_prior(
            options.belief.prior, len(values), self.dtype, values.device
        )
        mu0, Sigma0 = state.mu0, state.Sigma0
        if state.kind == "class":
            self.class_mu0, self.class_Sigma0 = first_state_prior(
                model, values, mu0, Sigma0, state.kind, self.dtype
            )
            mu0 = Sigma0 = None  # an unstarted stream stores the marginal prior
        self.mu0, self.Sigma0 = marginal_state_prior(model, mu0, Sigma0, self.dtype)
        self.batch_size = int(batch_size)
        self.obs_dim = model.obs_dim
        n, workspace = self.transition.inputs.shape[0], self.transition.workspace()
        # on an accelerator a chunk of streams is what one tile of the transition holds
        self.chunk_size = chunk_size or stream_chunk(
            n, workspace, self.dtype, self.mu0.device, self.transition.compiled()
        )
        self.reset()

    def operations(self) -> OpCount:
        """Work of one :meth:`update` per stream after its first observation, in chunks of
        ``chunk_size`` streams (the floor's count; for predictive evidence): the transition moments
        of the K grid values (:meth:`~hgpdm_torch.gp_shared.SharedTransition.operations` or
        :meth:`~hgpdm_torch.inference.intention.transition.GenericTransition.operations`), K
        measurement updates (``measurement_operations`` of
        :mod:`~hgpdm_torch.inference.intention.measurement`), and the belief and mixture (``K``
        exponentials, ``3 K Dx^2`` multiply-adds)."""
        K, dx = self.num_values, self.mu0.shape[0]
        streams = min(self.batch_size, self.chunk_size)  # that share one transition call
        cross = self.options.evidence.kind != "predictive"  # the bound's mixture uses it
        ops = self.transition.operations(streams, cross=cross)
        ops = ops + measurement_operations(self.measure, dx, streams * K) * K
        return ops + OpCount(exps=K, madds=3 * K * dx * dx + 2 * K * dx + 4 * K)

    @settings.internal_step()  # the prior was checked when set
    def _initialise(
        self,
        m: torch.Tensor,
        P: torch.Tensor,
        log_belief: torch.Tensor,
        z: torch.Tensor,
        phase: torch.Tensor,
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Algorithm 3.2, lines 1-3: ``q(x_1)`` from the prior and ``z_1``; the belief stays
        (``state_prior="class"``: the belief takes ``log q(z_1 | g)``, ``q(x_1)`` the mixture)."""
        if self.options.state_prior.kind == "marginal":
            mean, cov, _ = self.measure(m, P, z)
            return mean, cov, log_belief
        B, K = z.shape[0], self.num_values
        mk = self.class_mu0.expand(B, K, -1)
        Pk = self.class_Sigma0.expand(B, K, -1, -1)
        mean, cov, ll = self.measure(mk, Pk, z[:, None, :].expand(-1, K, -1))
        new = log_belief + ll / self.options.belief.temperature
        new = new - torch.logsumexp(new, -1, keepdim=True)
        mean, cov = mixture_moments(new.exp(), mean, cov)
        return mean, cov, new

    @settings.internal_step()  # the state is the filter's own; finiteness is checked in update
    def _step(
        self,
        m: torch.Tensor,
        P: torch.Tensor,
        log_belief: torch.Tensor,
        z: torch.Tensor,
        phase: torch.Tensor,
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        p = phase if self.phase else None
        if self.compiled_step is not None:  # the whole step in one call of the compiled kernel
            out = self.compiled_step(m, P, log_belief, z, p)
            if out is not None:
                return out
        observed = ~torch.isnan(z).all(-1)
        predictive = self.options.evidence.kind == "predictive"
        if predictive:
            mf, Pf, evidence = self._predictive_step(m, P, z, p)
        else:
            mf, Pf, evidence = self._bound_step(m, P, log_belief, z, p)
        new = self.options.belief.step(log_belief, evidence, observed)
        if predictive:
            mf, Pf = mixture_moments(new.exp(), mf, Pf)
        return mf, Pf, new

    def _predictive_step(
        self, m: torch.Tensor, P: torch.Tensor, z: torch.Tensor, phase: torch.Tensor | None
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Per-intention GP-ADF update: filtered ``[B, K, Dx(, Dx)]`` and ``log q(z_t | g)``."""
        mean, cov, _ = self.transition.moments(m, P, phase, cross=False)
        K = mean.shape[1]
        zk = z[:, None, :].expand(-1, K, -1)
        return self.measure(mean, cov, zk)

    def _bound_step(
        self,
        m: torch.Tensor,
        P: torch.Tensor,
        log_belief: torch.Tensor,
        z: torch.Tensor,
        phase: torch.Tensor | None,
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Algorithm 3.2, lines 6-9: shared filtered ``q(x_t)`` and ``Q_{t-1}(g) [B, K]``."""
        prob = log_belief.exp()
        if self.gaussian_transition is None:
            per_k = self.transition.moments(m, P, phase)
            mp, Pp, C = mixture_moments(prob, *per_k)
        else:
            mp, Pp, C = self._gaussian_prediction(prob, m, P, phase)
        mf, Pf, _ = self.measure(mp, Pp, z)
        # one-step GP-RTSS (Eq. 26-27); Cs = Cov[x_{t-1}, x_t | z_{1:t}]
        ms, Ps, Cs = rts_step(m, P, mp, Pp, C, mf, Pf, name="prediction")
        m_lin, P_lin = m, P
        if self.options.evidence.relinearize:
            m_lin, P_lin = ms, Ps
            per_k = self.transition.moments(ms, Ps, phase)
        Q = expected_log_conditional(
            m_lin[:, None], P_lin[:, None], *per_k,
            ms[:, None], Ps[:, None], mf[:, None], Pf[:, None], Cs[:, None],
        )  # fmt: skip
        return mf, Pf, Q

    def _gaussian_prediction(
        self, prob: torch.Tensor, m: torch.Tensor, P: torch.Tensor, phase: torch.Tensor | None
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Transition moment matched at ``[x, g]`` with ``g ~ N(mean, var)`` of the belief (and
        the known phase ``[B]``, if any)."""
        mu, Sigma = independent_joint(m, P, *mixture_moments(prob, self.values))
        dx = m.shape[-1]
        known = None if phase is None else phase.to(mu)[:, None]
        mean, cov, io = self.gaussian_transition.predict_gaussian(
            mu, symmetrize(Sigma), g=known, include_noise=True
        )
        return mean, cov, io[..., :dx, :]
