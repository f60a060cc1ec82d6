r"""MAP inference of the latent states of a new window: the conditional GPDM baseline.

The comparator of Tables 2.1-2.5 (Wang et al. 2008, "conditional GPDM"): the test latents
``x_{1:T}`` are point estimates maximising the FIC log joint (Eq. 8-9) given the fitted model,

    log p(x_{1:T}, z_{1:T} | g) = log N(x_1 | m_1, S_1)
        + sum_t log N(x_{t+1} | m_x(x_t, g), sigma_x^2(x_t, g) I)
        + sum_{t observed} log N(z_t | m_z(x_t), sigma_z^2(x_t) diag(scale^2)),

for every candidate g in one batched optimisation. Its value at the optimum stands in for the
evidence of g; it ignores the uncertainty of the states (the point of the VB method).
Forecasts and recovered rows are the GP means ``m_z(x_t)`` at the MAP states.

:class:`MAPInference` has the interface of
:class:`~hgpdm_torch.inference.variational.VariationalInference` and shares, by composition, its
window model (GPs, priors, log joint:
:class:`~hgpdm_torch.inference.variational.window.WindowModel`), initialisation and
Levenberg-Marquardt solver; it works for a GPDM (no g) and an H-GPDM alike.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import torch

from .variational.engine import WindowEngine
from .variational.laplace import map_states
from .variational.prediction import forecast
from .variational.window import window_mask

__all__ = ["MAP_STEPS", "MAPInference", "MAPResult"]

MAP_STEPS = 50  # default Levenberg-Marquardt iterations of the MAP baseline


@dataclass
class MAPResult:
    """Output of :meth:`MAPInference.infer`.

    Attributes:
        values: ``[K]`` candidate codes of a discrete g (empty without one).
        log_joint: ``[..., K]`` maximised log joint per candidate.
        posterior: ``[..., K]`` softmax of ``log_joint`` plus the log prior of g.
        g_ml: ``[...]`` index of the largest ``log_joint``.
        latent: ``[..., K, T, Dx]`` MAP states per candidate.
        history: summed negative log joint after each iteration.
    """

    values: torch.Tensor
    log_joint: torch.Tensor
    posterior: torch.Tensor
    g_ml: torch.Tensor
    latent: torch.Tensor
    history: list[float]

    def ml_state(self) -> torch.Tensor:
        """MAP states of the ML candidate, ``[..., T, Dx]``."""
        T, D = self.latent.shape[-2:]
        i = self.g_ml[..., None, None, None].expand(*self.g_ml.shape, 1, T, D)
        return self.latent.gather(-3, i)[..., 0, :, :]


class MAPInference(WindowEngine):
    """MAP estimate of the test latents (conditional GPDM), for a GPDM or an H-GPDM.

    Built on the same :class:`~hgpdm_torch.inference.variational.window.WindowModel` (GPs,
    priors, log joint) as :class:`~hgpdm_torch.inference.variational.VariationalInference`, with
    its initial states and its Levenberg-Marquardt solver.

    Args:
        model: a fitted :class:`~hgpdm_torch.models.GPDM` or an
            :class:`~hgpdm_torch.models.HGPDM` with a discrete g (a continuous g is not
            supported: the thesis compares MAP only for known or discrete g).

    The keywords ``x1_prior``, ``g_prior`` and ``measurement_points`` are VB's
    (:class:`~hgpdm_torch.inference.variational.engine.WindowEngine`).

    Attributes:
        window: the shared window model.
        model, kind, values, measurement, transition, latent_dim, obs_dim: the window model's.
    """

    continuous_g = False

    def log_joint(self, z: object, x: torch.Tensor, *, values: object = None) -> torch.Tensor:
        """FIC log joint ``[..., K]`` of states ``x [..., K, T, Dx]`` and window ``z``."""
        z, observed = window_mask(z, self.obs_dim, self.window.x1_mean)
        return self.window.log_joint(z.to(x.dtype), observed, x, self.window.candidates(values))

    def infer(
        self,
        z: object,
        *,
        values: object = None,
        steps: int = MAP_STEPS,
        init: str = "nearest",
        progress: bool = False,
    ) -> MAPResult:
        """Maximise the log joint over ``x_{1:T}`` for every candidate g (batched).

        The optimiser is the Levenberg-Marquardt of VB's Laplace start
        (:func:`~hgpdm_torch.inference.variational.laplace.map_states`; each window and
        candidate its own problem), from the same initial states.

        Args:
            z: as :meth:`VariationalInference.infer
                <hgpdm_torch.inference.variational.VariationalInference.infer>`.
            values: as for VB.
            steps: maximum Levenberg-Marquardt iterations.
            init: as for VB.
            progress: unused (kept for the interface of VB's ``infer``).
        """
        w = self.window
        z, observed = window_mask(z, self.obs_dim, self.window.x1_mean)
        if not isinstance(steps, int) or steps < 0:
            raise ValueError(f"steps must be a non-negative int, got {steps!r}")
        values = w.candidates(values)
        loc = self.initial_guess(z, values, init)[0]
        x, history = map_states(w, z, observed, loc, values, None, max_iter=steps)
        with torch.no_grad():
            lj = w.log_joint(z, observed, x, values)
            if not bool(torch.isfinite(lj).all()):
                raise FloatingPointError("the MAP log joint is not finite after optimisation")
            return MAPResult(
                values=values,
                log_joint=lj,
                posterior=torch.softmax(lj + w.log_prior(values), -1),
                g_ml=lj.argmax(-1),
                latent=x,
                history=history,
            )

    def reconstruct(self, result: MAPResult) -> tuple[torch.Tensor, torch.Tensor]:
        """GP predictive mean ``[..., T, Dz]`` and variance of every row at the MAP states."""
        with torch.no_grad():
            m, v = self.window.h.predict_point(result.ml_state())
            return m + self.measurement.offset, v[..., None] * self.measurement.scale.pow(2)

    def predict_observations(
        self, z: object, result: MAPResult
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """GP predictive mean and variance of every row at the MAP states of the ML g.

        Returns:
            ``mean [..., T, Dz]`` (observed rows unchanged) and ``var [..., T, Dz]`` (zero on
            observed rows).
        """
        z, observed = window_mask(z, self.obs_dim, self.window.x1_mean)
        m, var = self.reconstruct(result)
        keep = observed[..., None]
        return torch.where(keep, z, m), torch.where(keep, torch.zeros_like(var), var)

    def forecast(
        self, z: object, *, residual: str | None = None, **infer_kwargs: Any
    ) -> tuple[torch.Tensor, torch.Tensor, MAPResult]:
        """Forecast ``z_{T+1}``: the GP mean at the MAP states of a window with a missing row
        appended (:func:`~hgpdm_torch.inference.variational.prediction.forecast`; ``residual``
        and ``infer_kwargs`` as there).

        Returns:
            ``mean [..., Dz]``, ``var [..., Dz]`` of the next observation, and the result.
        """
        return forecast(self, z, residual=residual, **infer_kwargs)
