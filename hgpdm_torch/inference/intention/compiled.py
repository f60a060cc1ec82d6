r"""The online filter's predictive step on the compiled CPU kernel, one call per chunk of streams.

Where :class:`~hgpdm_torch.inference.intention.online.OnlineIntentionFilter` takes the
predictive evidence (its default), a shared transition GP on the compiled kernel
(:meth:`~hgpdm_torch.gp_shared.SharedTransition.compiled`) and a linear measurement
(:class:`~hgpdm_torch.inference.intention.measurement.LinearMeasurement`), its whole step runs
in :func:`hgpdm_torch.native.predictive_step`: per stream, the ``psi2`` contraction, the K
transition moments (Eq. 13-15 with Gaussian inputs), their GP-ADF measurement updates (Eq. 25,
32-35), the belief step (Algorithm 3.2, lines 10-11) and the moment-matched mixture, one stream
after another. In torch the same step holds ``[S, K, Dx, Dx]`` tensors for a chunk of S streams
and makes some 200 calls per chunk; here nothing of a stream but its new state leaves the
kernel, so a chunk needs a few kilobytes per stream and its fixed cost is two calls into the
kernel (the streams' quadratic forms, :func:`hgpdm_torch.native.rbf_forms`, then the step).

Monte-Carlo planning's particles replay this step from one belief
(:class:`~hgpdm_torch.decision.mcp.ParticleProjector`): :meth:`CompiledStep.particle_shared`
computes what they share once per decision; :meth:`CompiledStep.particles` updates a chunk of
them (from :meth:`CompiledStep.particle_args`) with the same C functions, and
:meth:`CompiledStep.particle_values` values them in the same call.

The torch path stays the reference (the tests compare the two) and takes over whole chunks:
where the kernel does not run (float32, a gradient, another device,
:class:`hgpdm_torch.settings.native_kernels` off, the materialised moment path, the checks of
:class:`hgpdm_torch.settings.debug`) and where an innovation covariance of some stream does not
factorise (then the torch path's jitter and the filter's isolation of failing streams apply
exactly as without the kernel).
"""

from __future__ import annotations

import math

import torch

from ... import native, settings
from ...gp_shared import SharedTransition
from ...observations import ObservationCheck
from .measurement import linear_measurement
from .options import FilterOptions

__all__ = ["CompiledStep"]


class CompiledStep:
    """``(mean [S, Dx], cov [S, Dx, Dx], log_belief [S, K], z [S, Dz], phase [S] | None) ->
    (mean, cov, log_belief)`` of the predictive step by the compiled kernel, or ``None`` where
    the torch path must take the chunk (module docstring). Build with :meth:`build`."""

    def __init__(self, transition: SharedTransition, measure, options: FilterOptions) -> None:
        linear = linear_measurement(measure)
        self.transition, self.meas = transition, linear.native_terms
        self.rank, self.dz = linear.R.shape[0], linear.U.shape[0]
        self.keep = 1.0 - options.belief.forgetting
        self.temperature = options.belief.temperature

    @classmethod
    def build(cls, transition: object, measure, options: FilterOptions) -> CompiledStep | None:
        """The compiled step of a filter with this transition, measurement update and options,
        or ``None`` where it cannot run at all (bound evidence, a generic transition, a
        measurement GP whose kernel is not linear, Dx above the kernel's limit); whether the
        kernel runs here is decided at each call (settings, dtype, gradients)."""
        if (
            options.evidence.kind != "predictive"
            or not isinstance(transition, SharedTransition)
            or linear_measurement(measure) is None
            or transition.dx > native.MAX_D
        ):
            return None
        return cls(transition, measure, options)

    def __call__(
        self,
        mean: torch.Tensor,
        cov: torch.Tensor,
        log_belief: torch.Tensor,
        z: torch.Tensor,
        phase: torch.Tensor | None,
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor] | None:
        trans = self.transition
        if not self.runs(mean, cov, log_belief, z):
            return None
        log_phase = None if phase is None else trans.log_phase(phase.to(mean))
        # a state that is no covariance raises here as in the torch step (a stream's failure)
        operands = trans.native_operands(mean, cov, log_phase)
        try:
            new_mean, new_cov, new_belief, status = native.predictive_step(
                operands, trans.native_moment_terms, self.meas, self.rank, self.keep,
                self.temperature, z.contiguous(), log_belief.contiguous(),
            )  # fmt: skip
        except ValueError as err:  # operands that do not fit: a bug, not a stream's failure
            raise RuntimeError(
                f"the compiled predictive step's operands do not fit: {err}"
            ) from err
        if bool(status.any()):
            return None
        return new_mean, new_cov, new_belief

    def runs(self, *tensors: torch.Tensor) -> bool:
        """Whether the kernel takes these operands now (module docstring): the settings, and the
        operands (with the transition's and the measurement's terms) float64 on the CPU without
        a gradient."""
        trans = self.transition
        return (
            settings.moment_path.get() == "fused"
            and not settings.debug.on()  # the torch step checks its internal Gaussians there
            and native.usable(*tensors, self.meas, trans.native_moment_terms)
            and trans.compiled()
        )

    def particle_shared(
        self,
        mean: torch.Tensor,
        cov: torch.Tensor,
        log_belief: torch.Tensor,
        phase: torch.Tensor | None,
    ) -> torch.Tensor | None:
        """What every Monte-Carlo particle of the belief ``mean [Dx]``, ``cov [Dx, Dx]``,
        ``log_belief [K]`` (``phase [1]`` for a phase-aware IDDM) shares
        (:func:`hgpdm_torch.native.particle_shared`), or ``None`` where the torch path must take
        the decision (as for a chunk of :meth:`__call__`)."""
        if not self.runs(mean, cov, log_belief):
            return None
        trans = self.transition
        log_phase = None if phase is None else trans.log_phase(phase.to(mean))
        operands = trans.native_operands(mean[None], cov[None], log_phase)
        shared, defined = native.particle_shared(
            operands, trans.native_moment_terms, self.meas, self.rank, log_belief.shape[0],
            self.dz,
        )  # fmt: skip
        return shared if defined else None

    def particle_args(
        self,
        shared: torch.Tensor,
        log_belief: torch.Tensor,
        check: ObservationCheck | None,
        draws: torch.Tensor | None,
        noise: torch.Tensor,
    ) -> native.ParticleArgs:
        """The predictive step of the belief behind ``shared`` (:meth:`particle_shared`;
        ``log_belief [K]`` normalised) on I observations, ``z = mz_g + Lz_g noise_i`` for the
        grid values ``draws [I]``, or ``z = noise [I, Dz]`` where ``draws`` is ``None``; a ``z``
        that ``check`` would not use (with ``check=None``: that is not finite, for
        observations the caller has checked and whose bad rows it has set to NaN) is a
        prediction-only step: the arguments of :meth:`particles` and :meth:`particle_values`."""
        dims = (self.transition.dx, self.dz, self.rank)
        if check is None or check.outlier_sd is None:  # finiteness alone, as check.usable
            center = noise.new_zeros(self.dz) if check is None else check.center.to(noise)
            limit = noise.new_full((self.dz,), math.inf)  # (inf * a zero spread is NaN)
        else:
            center, limit = check.center, check.limit
            if center.dtype != noise.dtype:
                center, limit = center.to(noise), limit.to(noise)
        return native.ParticleArgs(
            shared, self.meas, dims, center, limit, log_belief, self.keep, self.temperature,
            draws, noise,
        )  # fmt: skip

    def particles(
        self, args: native.ParticleArgs
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
        """``mean [I, Dx]``, ``cov [I, Dx, Dx]``, ``log_belief [I, K]`` and the observations
        ``z [I, Dz]`` of the particles ``args`` (:meth:`particle_args`;
        :func:`hgpdm_torch.native.particles`)."""
        return native.particles(args)

    def particle_values(
        self,
        args: native.ParticleArgs,
        basis: tuple[torch.Tensor, torch.Tensor, torch.Tensor, float, bool],
        weights: torch.Tensor,
        first: int,
    ) -> torch.Tensor:
        """The best value ``[I]`` over the actions ``first ..`` of each belief :meth:`particles`
        would return, by the radial basis ``basis`` and the linear weights ``weights``, in one
        call (:func:`hgpdm_torch.native.particle_values`)."""
        return native.particle_values(args, basis, weights, first)
