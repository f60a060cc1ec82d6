r"""Monte-Carlo planning on IDDM beliefs (thesis Algorithms 4.2 and 4.3, Sec. 4.2.4).

Any model the online filter runs on works (IDDM, H-GPDM, a subclass with a supported kernel, a
plain GPDM as one intention value): the particles replay the filter's own transition moments
(:mod:`~hgpdm_torch.inference.intention.transition`), the IDDM's fast path or the generic one.

The value of waiting one step is estimated by particle projection (Algorithm 4.2)::

    Q(theta_t, wait) ~= 1/I sum_i max_{a != 0} Q^(theta^i_{t+1}, a; w)      (wait_value="stop")
    Q(theta_t, wait) ~= 1/I sum_i max_{a allowed} Q^(theta^i_{t+1}, a; w)    (wait_value="lspi")

where each particle samples the intention ``g ~ p(g | z_{1:t})``, the next observation
``z^i_{t+1}`` given ``g`` from the IDDM, and runs the online belief update
(:class:`~hgpdm_torch.inference.intention.OnlineIntentionFilter`, predictive evidence) on it.
The stopping values ``Q^(theta, a != 0; w)`` are the linear ones learned by LSPI (stopping is
absorbing, so they are the same for every policy). Algorithm 4.2 as printed values a particle by
its best stopping value: after waiting once the robot must start, so the planner never sees that
waiting twice can pay (information that arrives two steps ahead). With ``wait_value="lspi"`` (the
default of :func:`~hgpdm_torch.decision.policies.planning_policy`) a particle whose next step may
still wait is valued by the best of all LSPI values there, waiting included: one step of planning
on top of LSPI's policy (a rollout with LSPI's values at the leaves). Algorithm 4.3 stops
sampling as soon as a Student-t confidence interval of the mean sampled reward lies entirely
above (wait) or below (stop) the best stopping value.

Where the speed comes from (docs/design/speed.md#particles-share-the-beliefs-predictions): the
K predictions ``q(x_{t+1} | g)`` of the belief and their joints with ``z_{t+1}`` are computed
once per decision; a particle's conditioning on its observation is linear,
``mu^i_g = m_g + C_g S_g^-1 (z^i - m^z_g)``, with a shared covariance and the evidence
``log N(z^i | m^z_g, S_g)``. A chunk's particles (up to :data:`BATCH` or ``chunk_size``) are
advanced in one batched update, stored with the particles last. Where the filter's compiled
step runs (a shared transition and a linear measurement, float64 on a CPU with the kernel:
:class:`~hgpdm_torch.inference.intention.compiled.CompiledStep`), the shared part, the
particles' updates (the filter's own form) and, for a fitted RadialBasis and LinearQ, their
values are the kernel's, the particles never leaving it. The intentions and normal deviates
are torch's from the generator either way (by :func:`hgpdm_torch.native.categorical_normal`).

Particles draw ``z^i`` either from the moment-matched ``N(m^z_g, S_g)`` (``sampling="moments"``,
the fast default, consistent with the filter's own approximation) or literally as Algorithm 4.2
prints, ``x_t ~ q``, ``x_{t+1} ~ GP(x_t, g)``, ``z ~ GP(x_{t+1})`` at points
(``sampling="points"``, one ``[I, N]`` kernel per GP).

Observation health is the filter's (its :class:`~hgpdm_torch.observations.ObservationCheck`):
an observation row that is +-inf, partly NaN or implausible (more than the filter's
``outlier_sd`` training standard deviations from the training mean in a channel) is, for that
particle only, treated as missing, exactly as the filter treats it: a prediction-only step in
which the belief only forgets. :meth:`MonteCarloPlanner.step` flags such rows (or, for a filter
with ``strict=True``, raises); sampled particles are checked the same way (never raising). A
particle's update is affine in its (checked) observation, with factors shared by all particles,
so it cannot fail on its own; where the shared factors of a belief fail, the call raises.

Shapes: ``I`` particles, ``K`` intention values, ``Dx`` latent, ``Dz`` observed, ``S`` stops.
"""

from __future__ import annotations

import math
import numbers
from collections.abc import Callable
from dataclasses import dataclass
from typing import NamedTuple

import torch
from scipy import stats

from .. import native, settings
from ..expectations import kernel_leaves, split_terms
from ..gaussian import conditional, log_density_terms, mixture_moments
from ..inference.intention import OnlineIntentionFilter
from ..inference.intention.measurement import linear_measurement
from ..linalg import cholesky_logdet, psd_cholesky, symmetrize
from ..models import GPDM
from ..moments import input_operations
from ..tiling import OpCount
from ..validation import as_observations, as_tensor, bad_observation, check_choice
from .basis import RadialBasis
from .lspi import LinearQ
from .stopping import WAIT, belief_vector, belief_vector_unchecked

__all__ = [
    "WAIT_VALUES",
    "Belief",
    "EarlyStopping",
    "MCPDecision",
    "MonteCarloPlanner",
    "ParticleProjector",
    "ParticleUpdate",
    "particle_value",
]

#: the most particles drawn and advanced at once where no interval is checked between chunks
#: (``early_stop=False``, :meth:`MonteCarloPlanner.project`) on a CPU, unless ``chunk_size`` is
#: larger: its largest temporaries, the drawn components' Cholesky factors ``[BATCH, Dz, Dz]``
#: and the mixture's products ``[K, Dx, Dx, BATCH]``, are 7.4 MB each at Dz = 15, K = 25, Dx = 3
#: in float64
BATCH = 4096

#: how a particle of the next belief is valued (module docstring): ``"lspi"``, the best LSPI
#: value of the actions allowed there (waiting included where the next step may wait), or
#: ``"stop"``, its best stopping value (Algorithm 4.2 as printed)
WAIT_VALUES = ("lspi", "stop")


def particle_value(q_values: torch.Tensor, wait_value: str, can_wait_next: bool) -> torch.Tensor:
    """The value ``[...]`` of particles from their LSPI values ``q_values [..., 1 + S]``
    (waiting first): the best stopping value, or with ``wait_value="lspi"`` and waiting allowed
    at the next step, the best of all actions."""
    return q_values[..., _first_action(wait_value, can_wait_next) :].max(-1).values


def _first_action(wait_value: str, can_wait_next: bool) -> int:
    """The first of the actions whose best value a particle takes (waiting is action 0)."""
    check_choice(wait_value, "wait_value", WAIT_VALUES)
    return 0 if wait_value == "lspi" and can_wait_next else WAIT + 1


def _check_filter(belief_filter: object) -> None:
    if not isinstance(belief_filter, OnlineIntentionFilter):
        name = type(belief_filter).__name__
        raise TypeError(f"belief_filter must be an OnlineIntentionFilter, got {name}")


@dataclass(frozen=True)
class Belief:
    """One stream's online IDDM belief ``theta_t``.

    Attributes:
        mean: ``[Dx]`` mean of ``q(x_t)`` (shared by all intentions).
        cov: ``[Dx, Dx]`` its covariance.
        log_prob: ``[K]`` normalised ``log p(g_k | z_{1:t})`` over the filter's grid.
        phase: the frame index of ``x_t`` from the stream's start (its filter's ``steps - 1``):
            required for, and only for, a phase-aware IDDM (``IDDM(phase_width=...)``), whose
            transition out of ``x_t`` depends on it.
    """

    mean: torch.Tensor
    cov: torch.Tensor
    log_prob: torch.Tensor
    phase: int | None = None

    @classmethod
    def from_filter(cls, belief_filter: OnlineIntentionFilter, stream: int = 0) -> Belief:
        """The current belief of stream ``stream`` of an online filter (copied; with its phase
        for a phase-aware IDDM)."""
        _check_filter(belief_filter)
        f, s = belief_filter, stream
        phase = int(f.steps[s]) - 1 if f.phase else None
        return cls(f.mean[s].clone(), f.cov[s].clone(), f.log_belief[s].clone(), phase)

    def vector(self) -> torch.Tensor:
        """``[F]`` belief vector (:func:`~hgpdm_torch.decision.stopping.belief_vector`)."""
        return belief_vector(self.mean, self.cov, self.log_prob.exp())


class ParticleUpdate(NamedTuple):
    """Output of :meth:`MonteCarloPlanner.step`: the updated beliefs of I particles.

    Attributes:
        mean: ``[I, Dx]`` mean of the mixed ``q(x_{t+1})``.
        cov: ``[I, Dx, Dx]`` its covariance.
        log_prob: ``[I, K]`` normalised log posterior over the filter's grid.
        rejected: ``[I]`` bool, the particle's observation was bad and treated as missing.
    """

    mean: torch.Tensor
    cov: torch.Tensor
    log_prob: torch.Tensor
    rejected: torch.Tensor


@dataclass(frozen=True)
class MCPDecision:
    """Output of :meth:`MonteCarloPlanner.decide`.

    Attributes:
        action: 0 (wait) or the stopping action ``1 .. S``.
        q_stop: ``[S]`` values of the stopping actions at ``theta_t``.
        q_wait: the Monte-Carlo estimate of ``Q(theta_t, wait)`` (NaN when waiting was not
            allowed and nothing was sampled).
        particles: particles used (fewer than the budget after early termination).
    """

    action: int
    q_stop: torch.Tensor
    q_wait: float
    particles: int


@dataclass(frozen=True)
class _Shared:
    """Per-decision quantities shared by all particles (``[K, ...]``)."""

    prob: torch.Tensor  # [K]
    log_prob: torch.Tensor  # [K]
    pred_mean: torch.Tensor  # [K, Dx]  q(x_{t+1} | g)
    pred_cov: torch.Tensor  # [K, Dx, Dx]
    z_mean: torch.Tensor  # [K, Dz]
    z_chol: torch.Tensor  # [K, Dz, Dz]  chol L of S = Cov[z_{t+1} | g]
    z_logdet: torch.Tensor  # [K]  log |S|
    # a batch of z conditioned on all K at once, particles along the last dim (every elementwise
    # step then runs over I contiguous entries), as innovations y = z - centre [Dz, I] from the
    # particles' mean observation (their terms then stay at the scale of the spread):
    #   mu = gain @ y + gain_offset  ([K Dx, I]),
    #   maha = quad @ [y_a y_b (a <= b), y] + quad_offset  ([K, I]): (z - m^z_k)^T S_k^-1 (.)
    centre: torch.Tensor  # [Dz]  sum_k p_k m^z_k
    gain: torch.Tensor  # [K Dx, Dz]  (C S^-1)_k stacked
    gain_offset: torch.Tensor  # [K Dx, 1]  m_k - C_k S_k^-1 d_k  (d_k = m^z_k - centre)
    quad: torch.Tensor  # [K, Dz (Dz + 1) / 2 + Dz]  S_k^-1 over the pairs (off-diagonal twice),
    #                     then -2 S_k^-1 d_k
    quad_offset: torch.Tensor  # [K, 1]  d_k^T S_k^-1 d_k
    post_cov: torch.Tensor  # [K, Dx, Dx]  P - C S^-1 C^T
    x_chol: torch.Tensor  # [Dx, Dx]  chol of Cov[x_t] (for sampling="points")
    mean: torch.Tensor  # [Dx]
    phase: torch.Tensor | None  # [1] frame index of x_t for a phase-aware IDDM


@dataclass(frozen=True)
class _CompiledShared:
    """Per-decision quantities shared by all particles, in the compiled kernel's layout
    (:meth:`~hgpdm_torch.inference.intention.compiled.CompiledStep.particle_shared`)."""

    prob: torch.Tensor  # [K]
    log_prob: torch.Tensor  # [K]
    state: torch.Tensor  # [K, block]


def _randn(
    shape: tuple[int, ...] | torch.Size, generator: torch.Generator | None, like: torch.Tensor
) -> torch.Tensor:
    """Standard normal draws of ``shape`` in ``like``'s dtype and on its device, drawn on the
    generator's device: a seeded CPU generator gives the same particles on every device."""
    draw_on = like.device if generator is None else generator.device
    out = torch.randn(shape, generator=generator, dtype=like.dtype, device=draw_on)
    return out.to(like.device)


def _kernel_takes(*tensors: torch.Tensor) -> bool:
    """Whether the compiled kernel takes these tensors as they are (contiguous, usable)."""
    return all(t.is_contiguous() for t in tensors) and native.usable(*tensors)


class EarlyStopping:
    """Algorithm 4.3 on any particle projection: sample the value of waiting in chunks until a
    Student-t confidence interval of its mean excludes the best stopping value.

    Args:
        num_particles: I, the sampling budget per decision.
        confidence: level of the two-sided interval.
        min_particles: particles drawn before the interval is first checked.
        chunk_size: particles drawn at once; the interval is checked after each chunk.
            :meth:`choose` with ``early_stop=False`` draws all ``num_particles`` in one call.
    """

    def __init__(
        self, num_particles: int = 500, confidence: float = 0.99, min_particles: int = 100,
        chunk_size: int = 100,
    ) -> None:  # fmt: skip
        for name, value, low in (
            ("num_particles", num_particles, 2),
            ("min_particles", min_particles, 2),
            ("chunk_size", chunk_size, 1),
        ):
            if isinstance(value, bool) or not isinstance(value, int) or value < low:
                raise ValueError(f"{name} must be an int >= {low}, got {value!r}")
        if isinstance(confidence, bool) or not (
            isinstance(confidence, numbers.Real) and 0.0 < float(confidence) < 1.0
        ):
            raise ValueError(f"confidence must be a float in (0, 1), got {confidence!r}")
        self.num_particles, self.min_particles = num_particles, min_particles
        self.chunk_size, self.confidence = chunk_size, confidence
        # interval half-width factors c(n) of Algorithm 4.3 for every checkpoint n
        checks = range(chunk_size, num_particles + chunk_size, chunk_size)
        self._c = {
            min(n, num_particles): float(
                stats.t.ppf(0.5 + confidence / 2, min(n, num_particles) - 1)
            )
            for n in checks
        }

    def choose(
        self,
        q_stop: torch.Tensor,
        draw: Callable[[int], torch.Tensor],
        *,
        can_wait: bool = True,
        early_stop: bool = True,
    ) -> MCPDecision:
        """Wait or stop, given the stopping values ``q_stop [S]`` now and ``draw(m)``, ``m``
        sampled values ``max_a Q(theta^i_{t+1}, a)`` of the next belief (Algorithm 4.2)."""
        best_stop, best = q_stop.max(-1)
        stop = MCPDecision(int(best) + 1, q_stop, math.nan, 0)
        if not can_wait:
            return stop
        if not early_stop:  # no interval to check: every particle in one draw
            q_wait = float(draw(self.num_particles).mean())
            action = WAIT if q_wait > float(best_stop) else stop.action
            return MCPDecision(action, q_stop, q_wait, self.num_particles)
        samples, n = [], 0
        while n < self.num_particles:
            size = min(self.chunk_size, self.num_particles - n)
            samples.append(draw(size))
            n += size
            if n >= self.min_particles and n < self.num_particles:
                r = torch.cat(samples)
                mean = float(r.mean())
                half = self._c[n] * float(r.std()) / math.sqrt(n)
                if mean + half < best_stop:  # waiting is very likely worse
                    return MCPDecision(stop.action, q_stop, mean, n)
                if mean - half > best_stop:  # waiting is very likely better
                    return MCPDecision(WAIT, q_stop, mean, n)
        q_wait = float(torch.cat(samples).mean())
        action = WAIT if q_wait > float(best_stop) else stop.action
        return MCPDecision(action, q_stop, q_wait, n)


class ParticleProjector:
    """Algorithm 4.2's particles for an IDDM belief: sampled next observations and the online
    filter's update on them (module docstring).

    Args:
        model: the fitted IDDM, H-GPDM or GPDM (its measurement GP, and its transition GP for
            ``sampling="points"``).
        belief_filter: the online filter of this model whose belief update the particles replay
            (its ``evidence`` must be ``"predictive"``; its grid, forgetting factor and shared
            transition moments are used, not its streams).
        sampling: ``"moments"`` or ``"points"`` (module docstring).
    """

    def __init__(
        self, model: GPDM, belief_filter: OnlineIntentionFilter, *, sampling: str = "moments"
    ) -> None:
        if not isinstance(model, GPDM):
            raise TypeError(f"model must be a GPDM/HGPDM/IDDM, got {type(model).__name__}")
        _check_filter(belief_filter)
        if belief_filter.mu0.shape[0] != model.latent_dim or belief_filter.obs_dim != model.obs_dim:
            raise ValueError(
                "belief_filter must be a filter of this model (latent/obs dims differ)"
            )
        if belief_filter.options.evidence.kind != "predictive":
            raise ValueError(
                "MonteCarloPlanner replays the filter's predictive-evidence update; got a filter "
                f"with evidence={belief_filter.options.evidence.kind!r}"
            )
        check_choice(sampling, "sampling", ("moments", "points"))
        self.filter, self.sampling = belief_filter, sampling
        self.measurement = model.measurement_posterior()
        # the filter's transition GP (sparse where the filter's is)
        self.transition = belief_filter.posterior if sampling == "points" else None
        # the filter's compiled step, whose kernel draws and updates the particles where it runs
        self._compiled = belief_filter.compiled_step if sampling == "moments" else None
        # the observation's index pairs a <= b and the factor of y_a y_b in a quadratic form
        a, b = torch.triu_indices(*(2 * [belief_filter.obs_dim]), device=belief_filter.mu0.device)
        self._pairs, self._upper = (a, b), a * belief_filter.obs_dim + b
        self._twice = 2.0 - (a == b).to(belief_filter.dtype)

    def sample_beliefs(
        self, belief: Belief, num: int, generator: torch.Generator | None = None
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """``num`` particles of the next belief: ``mean [I, Dx]``, ``cov [I, Dx, Dx]`` and
        ``log_prob [I, K]`` after a sampled observation (Algorithm 4.2, lines 3-6)."""
        if isinstance(num, bool) or not isinstance(num, int) or num < 1:
            raise ValueError(f"num must be a positive int, got {num!r}")
        particles = self._particles(self._shared(self._check_belief(belief)), num, generator)
        return tuple(v.contiguous() for v in particles)

    def _draw(
        self, prob: torch.Tensor, num: int, generator: torch.Generator | None
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """The particles' intentions ``g [I] ~ prob`` and, for ``sampling="moments"``, their
        observations' standard normal draws ``[I, Dz, 1]`` (``None`` for ``"points"``)."""
        draw_on = prob.device if generator is None else generator.device
        moments = self.sampling == "moments"
        if moments and draw_on.type == "cpu" and _kernel_takes(prob):  # prob float64 on the CPU
            g, eps = native.categorical_normal(prob, num, self.filter.obs_dim, generator)
            return g, eps[..., None]  # torch's draws of the two below, from one call
        g = torch.multinomial(prob.to(draw_on), num, replacement=True, generator=generator)
        g = g.to(prob.device)  # [I]
        if not moments:
            return g, None
        return g, _randn((num, self.filter.obs_dim, 1), generator, prob)

    def _particles(
        self, shared: _Shared | _CompiledShared, num: int, generator: torch.Generator | None
    ):
        if isinstance(shared, _CompiledShared):  # drawn as below, then the kernel's update
            return self._compiled.particles(self._compiled_args(shared, num, generator))[:3]
        z = self._sample_observations(shared, num, generator)
        usable = self.filter.check.usable(z)
        return self._update(shared, z, None if bool(usable.all()) else ~usable)

    def _compiled_args(
        self, shared: _CompiledShared, num: int, generator: torch.Generator | None
    ) -> native.ParticleArgs:
        """The compiled kernel's particle arguments: the shared state and ``num`` draws."""
        g, eps = self._draw(shared.prob, num, generator)
        args = (shared.state, shared.log_prob, self.filter.check, g, eps.view(num, -1))
        return self._compiled.particle_args(*args)

    # ----- Algorithm 4.2: particle projection -------------------------------------------------

    def _check_belief(self, belief: Belief) -> Belief:
        if not isinstance(belief, Belief):
            raise TypeError(f"belief must be a Belief, got {type(belief).__name__}")
        f = self.filter
        dx, k = f.mu0.shape[0], f.num_values
        if belief.mean.shape != (dx,) or belief.cov.shape != (dx, dx):
            raise ValueError(
                f"belief mean/cov must have shapes [{dx}] and [{dx}, {dx}], got "
                f"{tuple(belief.mean.shape)} and {tuple(belief.cov.shape)}"
            )
        if belief.log_prob.shape != (k,):
            raise ValueError(
                f"belief.log_prob must have K = {k} entries, got {belief.log_prob.shape}"
            )
        for name in ("mean", "cov", "log_prob"):
            as_tensor(getattr(belief, name), f"belief.{name}", allow_nan=False)
        phase = belief.phase
        if f.phase != (phase is not None):
            raise ValueError(
                "a phase-aware IDDM's belief needs its phase (Belief.from_filter sets it: the "
                "frame index of x_t)"
                if f.phase
                else "belief.phase is for a phase-aware IDDM (phase_width set) only; got "
                f"phase={phase!r}"
            )
        if phase is not None and (
            isinstance(phase, bool) or not isinstance(phase, int) or phase < 0
        ):
            raise ValueError(f"belief.phase must be an int >= 0, got {phase!r}")
        # Stop values and projected values must read the same histogram: normalise once here.
        log_prob = torch.log_softmax(belief.log_prob, -1)  # log p - logsumexp(log p), fused
        return Belief(belief.mean, belief.cov, log_prob, phase)

    def _shared(self, belief: Belief) -> _Shared | _CompiledShared:
        """The K predictions and their joints with ``z_{t+1}``, computed once per decision (by
        the compiled kernel where it runs)."""
        f = self.filter
        m, P = belief.mean.to(f.dtype), belief.cov.to(f.dtype)
        phase = None if belief.phase is None else m.new_full((1,), float(belief.phase))
        if self._compiled is not None:  # the belief as _check_belief normalised it
            log_prob = belief.log_prob.to(f.dtype)
            state = self._compiled.particle_shared(m, P, log_prob, phase)
            if state is not None:
                return _CompiledShared(log_prob.exp(), log_prob, state)
        m, P = m[None], P[None]
        mean, cov, _ = f.transition.moments(m, P, phase, cross=False)  # [1, K, Dx(, Dx)]
        mean, cov = mean[0], cov[0]
        linear = linear_measurement(f.measure)
        if linear is not None:  # the filter's own, precomputed: O(Dx Dz^2)
            mz, Sz, Cxz = linear.moments(mean, cov)
        else:
            gp_dtype = self.measurement.train_inputs.dtype
            with settings.internal_step():  # the filter's own predictions
                moments = self.measurement.predict_gaussian(
                    mean.to(gp_dtype), cov.to(gp_dtype), include_noise=True
                )
            mz, Sz, Cxz = (v.to(f.dtype) for v in moments)
        L = psd_cholesky(Sz, name="predicted observation covariance")
        gain_t, post_cov = conditional(cov, Cxz, L)  # S^-1 C^T  [K, Dz, Dx]
        log_prob = belief.log_prob.to(f.dtype)
        log_prob = log_prob - torch.logsumexp(log_prob, -1)
        prob = log_prob.exp()
        K, dz = mz.shape
        prec = torch.cholesky_inverse(L)  # S^-1  [K, Dz, Dz]
        centre = prob @ mz
        d = mz - centre
        pd = (prec @ d[..., None])[..., 0]  # S^-1 d  [K, Dz]
        # y^T S^-1 y over the pairs a <= b: the entries above the diagonal twice
        upper = prec.reshape(K, -1).index_select(1, self._upper) * self._twice
        return _Shared(
            prob=prob,
            log_prob=log_prob,
            pred_mean=mean,
            pred_cov=cov,
            z_mean=mz,
            z_chol=L,
            z_logdet=cholesky_logdet(L),
            centre=centre,
            gain=gain_t.mT.reshape(-1, dz),
            gain_offset=(mean - (d[:, None, :] @ gain_t)[:, 0]).reshape(-1, 1),
            quad=torch.cat([upper, -2.0 * pd], -1),
            quad_offset=(pd * d).sum(-1, keepdim=True),
            post_cov=post_cov,
            x_chol=psd_cholesky(P[0], name="belief covariance"),
            mean=m[0],
            phase=phase,
        )

    def _sample_observations(
        self, shared: _Shared, num: int, generator: torch.Generator | None
    ) -> torch.Tensor:
        """``z^i_{t+1} [I, Dz]`` (Algorithm 4.2, lines 3-5)."""
        f = self.filter
        g, eps = self._draw(shared.prob, num, generator)
        if self.sampling == "moments":
            mean = shared.z_mean.index_select(0, g)[..., None]
            return torch.baddbmm(mean, shared.z_chol.index_select(0, g), eps)[..., 0]
        dx = shared.mean.shape[0]
        x = shared.mean + _randn((num, dx), generator, shared.mean) @ shared.x_chol.T
        known = [x, f.values[g]]
        if shared.phase is not None:  # a phase-aware IDDM's last input column
            known.append(shared.phase.expand(num, 1))
        gx = torch.cat(known, -1).to(self.transition.train_inputs.dtype)
        m, v = self.transition.predict(gx, include_noise=True)
        x1 = m + v.sqrt() * _randn(m.shape, generator, m)
        m, v = self.measurement.predict(x1, include_noise=True)
        z = m + v.sqrt() * _randn(m.shape, generator, m)
        return z.to(shared.z_mean.dtype)

    def step(self, belief: Belief, z: torch.Tensor) -> ParticleUpdate:
        """The online filter's update of one belief on many observations at once.

        Args:
            belief: the current belief.
            z: ``[I, Dz]`` observations; a NaN row is missing, a bad row (module docstring) is
                treated as missing and flagged.

        Returns:
            :class:`ParticleUpdate`: ``mean [I, Dx]``, ``cov [I, Dx, Dx]`` of the mixed
            ``q(x_{t+1})``, ``log_prob [I, K]`` and ``rejected [I]``: what
            ``OnlineIntentionFilter.update`` gives for I streams in this belief.

        Raises:
            ValueError: a wrong shape; a bad row when the filter is ``strict`` (naming the row
                and channel).
        """
        shared = self._shared(self._check_belief(belief))
        z = as_observations(z, min_ndim=2)
        if z.dim() != 2 or z.shape[1] != self.filter.obs_dim:
            raise ValueError(
                f"z must have shape [I, Dz] with Dz = {self.filter.obs_dim} columns, got "
                f"{tuple(z.shape)}"
            )
        missing, rejected = self.filter.check.classify(z)
        if self.filter.options.observations.strict and bool(rejected.any()):
            i = int(torch.nonzero(rejected)[0])
            raise bad_observation(f"z[{i}] (particle {i})", self.filter.check.reason(z[i]))
        if isinstance(shared, _CompiledShared):  # the rows classify found bad set to NaN
            z = z.to(self.filter.dtype).masked_fill((missing | rejected)[:, None], math.nan)
            args = (shared.state, shared.log_prob, None, None, z.contiguous())
            update = self._compiled.particles(self._compiled.particle_args(*args))[:3]
        else:
            update = self._update(shared, z.to(self.filter.dtype), missing | rejected)
        return ParticleUpdate(*(v.contiguous() for v in update), rejected)

    def _update(
        self, shared: _Shared, z: torch.Tensor, missing: torch.Tensor | None = None
    ) -> tuple[torch.Tensor, ...]:
        """Linear-Gaussian conditioning of the shared predictions on ``z [I, Dz]``; the rows
        ``missing [I]`` (missing or rejected observations) are prediction-only steps, as in the
        filter.

        Returns ``mean [I, Dx]``, ``cov [I, Dx, Dx]`` and ``log_prob [I, K]`` as views of
        tensors stored with the particles last (``[Dx, I]``, ``[Dx, Dx, I]``, ``[K, I]``): each
        elementwise step then runs over I contiguous entries, not over rows of Dx or K.
        """
        num, (K, dx), dz = z.shape[0], shared.pred_mean.shape, z.shape[1]
        skip = missing is not None and bool(missing.any())
        if skip:
            z = z.masked_fill(missing[:, None], 0.0)
        y = (z - shared.centre).T.contiguous()  # [Dz, I]
        mu = torch.addmm(shared.gain_offset, shared.gain, y).view(K, dx, num)  # filtered means
        a, b = self._pairs  # the Dz (Dz + 1) / 2 channel pairs a <= b
        quadratic = torch.cat([y.index_select(0, a) * y.index_select(0, b), y])
        maha = torch.addmm(shared.quad_offset, shared.quad, quadratic).clamp_min_(0.0)  # [K, I]
        evidence = log_density_terms(maha, shared.z_logdet[:, None], dz).T
        observed = torch.ones(num, dtype=torch.bool, device=z.device)
        if skip:
            mu = torch.where(missing, shared.pred_mean[..., None], mu)
            observed = ~missing
        # the filter's recursion B_t = (1 - eps) B_{t-1} + E_t / T from the shared B_{t-1}
        prior = shared.log_prob[:, None].expand(K, num).contiguous().T  # stored [K, I] too
        log_prob = self.filter.options.belief.step(prior, evidence, observed)
        p = log_prob.exp()  # [I, K] (stored [K, I])
        # mixture covariance: sum_k p_k P_k + Cov_p[mu_k], with P_k shared by all particles
        mean, spread = mixture_moments(p, mu.permute(2, 0, 1))
        covs = shared.pred_cov if skip else shared.post_cov
        cov = (covs.reshape(K, dx * dx).T @ p.T).view(dx, dx, num).permute(2, 0, 1)
        if skip:
            posterior = (shared.post_cov.reshape(K, dx * dx).T @ p.T).view(dx, dx, num)
            cov = torch.where(missing[:, None, None], cov, posterior.permute(2, 0, 1))
        return mean, symmetrize(cov + spread), log_prob


class MonteCarloPlanner(ParticleProjector):
    """Anticipatory action selection by Monte-Carlo planning (Algorithms 4.2-4.3).

    Args:
        model: as for :class:`ParticleProjector`, whose particles it values.
        belief_filter: as for :class:`ParticleProjector`.
        q: stopping values ``Q^(theta, a) = phi'(theta)^T w_a`` (e.g. ``lspi(...).q``); row 0
            (waiting) is not used.
        features: state feature map ``phi'`` from belief vectors ``[..., F]`` (e.g. a fitted
            :class:`~hgpdm_torch.decision.basis.RadialBasis`).
        num_particles: I, the sampling budget per decision.
        confidence: level of the two-sided Student-t interval of Algorithm 4.3.
        min_particles: particles drawn before the interval is first checked.
        chunk_size: particles drawn at once where the interval is checked, after each chunk;
            without early termination (``early_stop=False``, :meth:`project`) up to
            :data:`BATCH` particles, or ``chunk_size`` if larger, are drawn and advanced at once
            (other draws than a chunked run's from the same generator).
        sampling: as for :class:`ParticleProjector`.
        vectorize: ``(mean, cov, prob) -> [..., F]`` belief vectors that ``features`` takes
            (default :func:`~hgpdm_torch.decision.stopping.belief_vector`, the thesis's).
        wait_value: how a particle is valued where the next step may wait too
            (:data:`WAIT_VALUES`, module docstring): ``"lspi"`` (default) or ``"stop"`` (the
            thesis's). :meth:`decide` learns whether it may from ``can_wait_next``.
    """

    def __init__(
        self,
        model: GPDM,
        belief_filter: OnlineIntentionFilter,
        q: LinearQ,
        features: Callable[[torch.Tensor], torch.Tensor],
        *,
        num_particles: int = 500,
        confidence: float = 0.99,
        min_particles: int = 100,
        chunk_size: int = 100,
        sampling: str = "moments",
        vectorize: Callable[..., torch.Tensor] | None = None,
        wait_value: str = "lspi",
    ) -> None:
        super().__init__(model, belief_filter, sampling=sampling)
        check_choice(wait_value, "wait_value", WAIT_VALUES)
        self.wait_value = wait_value
        if not isinstance(q, LinearQ):
            raise TypeError(f"q must be a LinearQ, got {type(q).__name__}")
        if not callable(features):
            raise TypeError("features must be callable (belief vectors -> state features)")
        if vectorize is not None and not callable(vectorize):
            raise TypeError("vectorize must be callable ((mean, cov, prob) -> vectors) or None")
        self.rule = EarlyStopping(num_particles, confidence, min_particles, chunk_size)
        self.q, self.features = q, features
        self.vectorize = vectorize or belief_vector_unchecked
        self.num_particles, self.min_particles = num_particles, min_particles
        self.chunk_size, self.confidence = chunk_size, confidence

    def _native_basis(self, dx: int, K: int) -> tuple | None:
        """The fitted :class:`~hgpdm_torch.decision.basis.RadialBasis`'s parameters and
        :class:`~hgpdm_torch.decision.lspi.LinearQ`'s weights as the compiled values take them
        (:func:`hgpdm_torch.native.rbf_values`), for beliefs of ``dx`` dims and ``K`` values;
        ``None`` where ``vectorize``, ``features`` and ``q`` run in torch (decided at each call:
        the attributes may have been replaced since construction)."""
        basis, weights = self.features, self.q.weights
        default = self.vectorize is belief_vector_unchecked and type(self.q) is LinearQ
        if not default or type(basis) is not RadialBasis or basis.centres is None:
            return None
        terms = (basis.mean, basis.std, basis.centres, weights)
        if basis.centres.shape[-1] != dx * (dx + 3) // 2 + K or not _kernel_takes(*terms):
            return None
        return (basis.mean, basis.std, basis.centres, basis.eta, basis.bias), weights

    def _values(
        self, mean: torch.Tensor, cov: torch.Tensor, log_prob: torch.Tensor
    ) -> torch.Tensor:
        """LSPI's values ``[I, 1 + S]`` of I beliefs (``mean [I, Dx]``, ``cov [I, Dx, Dx]``,
        ``log_prob [I, K]``): by the compiled kernel where :meth:`_native_basis` allows
        (:func:`hgpdm_torch.native.rbf_values`), else ``vectorize``, ``features`` and ``q`` in
        torch."""
        parameters = self._native_basis(mean.shape[-1], log_prob.shape[-1])
        if parameters is not None and _kernel_takes(mean, cov, log_prob):
            values = native.rbf_values(mean, cov, log_prob, *parameters)
            if math.isfinite(float(values.sum())):  # all finite; else torch's checks raise
                return values
        vectors = self.vectorize(mean, cov, log_prob.exp()).to(self.filter.dtype)
        return self.q.values(self.features(vectors))

    def operations(self, num: int | None = None) -> OpCount:
        """Work of one :meth:`decide` with ``num`` particles (default ``num_particles``; the
        floor's count, without early termination).

        Shared by the particles: the K transition moments of the belief (the filter's
        ``transition.operations(cross=False)``), the measurement's moments at the K predictions
        (``Dx^2 (Dz + 2) + Dz^2 Dx`` each through the filter's
        :class:`~hgpdm_torch.inference.intention.measurement.LinearMeasurement`, else the GP's,
        :func:`~hgpdm_torch.moments.input_operations`), their Cholesky factors, gains and
        precisions (``K (Dz^3 / 2 + Dz^2 Dx + Dz Dx^2)``; where the compiled kernel runs, the
        factor ``K Dz^3 / 6`` and the measurement's factors in its span of rank ``k``, ``K (k
        Dx^2 + 2 k^2 Dx + k^3 / 3)``). Per particle: the drawn observation and its conditioning
        on all K, the belief and mixture (``2 K Dx^2 + K Dx``, ``K`` exponentials), the
        features (``features.operations(1)`` where the feature map has one, e.g.
        :meth:`~hgpdm_torch.decision.basis.RadialBasis.operations`) and the values (``F A``
        for F features and A actions). The draw and the conditioning are counted as the
        path that runs does them: where the compiled kernel runs (a linear measurement, float64
        on the CPU), the factor's lower triangle (``P = Dz (Dz + 1) / 2``) and the filter's own
        update on the measurement's span of rank ``k`` (``2 Dz + 2 Dz k`` to project ``z``,
        then ``k (k + 1) / 2 + k + k Dx`` per value); else a full ``Dz^2`` product and the
        observation space (``P`` pair products ``y_a y_b``, ``K Dx Dz`` for the means, ``K (P
        + Dz)`` for the quadratic forms).
        """
        num = self.num_particles if num is None else num
        f, meas = self.filter, self.measurement
        compiled = self._compiled is not None and self._compiled.runs(f.mu0)
        K, dx, dz = f.num_values, f.mu0.shape[0], meas.output_dim
        k = min(dx, dz)  # the measurement's rank where the compiled kernel runs
        shared = f.transition.operations(1, cross=False)
        if linear_measurement(f.measure) is not None:
            shared = shared + OpCount(madds=K * (2 * dx * dx + dx * dx * dz + dz * dz * dx))
        else:
            leaves = kernel_leaves(meas.kernel, meas.input_dim)
            terms = split_terms(leaves, meas.train_inputs, None, meas.input_dim)
            n = meas.train_inputs.shape[0]
            shared = shared + input_operations(terms, n, dz, inputs=K) * K
        if compiled:  # the observation's factor, and the measurement's factors in the span
            factors = dz**3 / 6 + k * dx * dx + 2 * k * k * dx + k**3 / 3
        else:  # the factor, its inverse and the gains in the observation space
            factors = dz**3 / 2 + dz * dz * dx + dz * dx * dx
        shared = shared + OpCount(madds=K * factors)
        count = getattr(self.features, "operations", None)
        features = count(1) if callable(count) else OpCount()
        a, phi = self.q.weights.shape
        pairs = dz * (dz + 1) // 2
        if compiled:  # the factor's lower triangle, then the rank-k conditioning
            condition = pairs + 2 * dz + 2 * dz * k + K * (k * (k + 1) // 2 + k + k * dx)
        else:  # a full Dz x Dz product, then the observation space
            condition = dz * dz + pairs + K * (dx * dz + pairs + dz)
        madds = condition + 2 * K * dx * dx + K * dx
        one = OpCount(exps=K, madds=madds)
        return shared + (one + features + OpCount(madds=phi * a)) * num

    def _project(
        self, shared: _Shared, num: int, generator: torch.Generator | None, can_wait_next: bool
    ) -> torch.Tensor:
        """Values ``[num]`` of ``num`` particles, drawn and advanced in batches of up to
        :data:`BATCH` (or ``chunk_size``, if larger) particles."""
        batch = max(BATCH, self.chunk_size)  # an accelerator's chunk may be all particles
        if num > batch:
            sizes = [min(batch, num - start) for start in range(0, num, batch)]
            return torch.cat([self._project(shared, n, generator, can_wait_next) for n in sizes])
        if isinstance(shared, _CompiledShared):  # the values in the same call where they can be
            args = self._compiled_args(shared, num, generator)
            parameters = self._native_basis(self.filter.mu0.shape[0], shared.log_prob.shape[0])
            if parameters is not None:  # each particle's best value
                first = _first_action(self.wait_value, can_wait_next)
                best = self._compiled.particle_values(args, *parameters, first)
                if math.isfinite(float(best.sum())):  # all finite; else torch's checks raise
                    return best
            mean, cov, log_prob = self._compiled.particles(args)[:3]
        else:
            mean, cov, log_prob = self._particles(shared, num, generator)
        return particle_value(self._values(mean, cov, log_prob), self.wait_value, can_wait_next)

    def project(
        self, belief: Belief, num: int | None = None, *, generator: torch.Generator | None = None,
        can_wait_next: bool = False,
    ) -> torch.Tensor:  # fmt: skip
        """Algorithm 4.2: the sampled rewards ``r^i = max_{a != 0} Q^(theta^i_{t+1}, a)``
        (with ``wait_value="lspi"`` and ``can_wait_next``, the max over all actions).

        Args:
            belief: the current belief.
            num: particles (default ``num_particles``), drawn and advanced in batches of up to
                :data:`BATCH` (or ``chunk_size``, if larger).
            generator: random generator.
            can_wait_next: whether the next step may wait too.

        Returns:
            ``[I]``; their mean estimates ``Q(theta_t, wait)``.
        """
        shared = self._shared(self._check_belief(belief))
        num = self.num_particles if num is None else num
        if isinstance(num, bool) or not isinstance(num, int) or num < 1:
            raise ValueError(f"num must be a positive int, got {num!r}")
        return self._project(shared, num, generator, can_wait_next)

    # ----- Algorithm 4.3: decision with early termination -------------------------------------

    def decide(
        self,
        belief: Belief,
        *,
        can_wait: bool = True,
        can_wait_next: bool = False,
        early_stop: bool = True,
        generator: torch.Generator | None = None,
    ) -> MCPDecision:
        """Choose wait or a movement for the current belief (Algorithm 4.3).

        Args:
            belief: the current belief.
            can_wait: whether waiting is allowed (not at the last decision step).
            can_wait_next: whether waiting is allowed at the next step too (not at the last two
                decision steps); with ``wait_value="lspi"`` the particles are then valued with
                LSPI's value of waiting there.
            early_stop: stop sampling once the confidence interval of ``Q(theta_t, wait)``
                excludes the best stopping value (else use all ``num_particles``).
            generator: random generator.
        """
        belief = self._check_belief(belief)
        values = self._values(belief.mean[None], belief.cov[None], belief.log_prob[None])
        q_stop = values[0, WAIT + 1 :]
        if not can_wait:
            return self.rule.choose(q_stop, None, can_wait=False)
        shared = self._shared(belief)
        return self.rule.choose(
            q_stop,
            lambda n: self._project(shared, n, generator, can_wait_next),
            early_stop=early_stop,
        )
