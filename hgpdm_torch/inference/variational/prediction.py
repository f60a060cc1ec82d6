r"""Prediction from the variational posterior of a window: forecasting and gap recovery (thesis
Sec. 2.3.2, App. 2.B).

Each ``q(x_t)`` gives the moment-matched ``q(z_t) = int p(z_t | x_t) q(x_t) dx_t``; under the
FIC factorisation the rows of the window covary through the GP only, with cross-time covariances
(independent ``x_s, x_t`` under the mean-field q)

    Cov[z_s,d, z_t,e] = delta_de scale_d^2 (E[k(x_s, x_t)] - l_s^T K^-1 l_t),   l_t = E[k(X, x_t)],

which makes the joint Gaussian ``q(z_{1:T})``; conditioning it on the observed rows
(:func:`~hgpdm_torch.gaussian.condition_gaussian`) forecasts and recovers the missing ones.
:func:`forecast` appends a missing row to a window and predicts it, for any engine with
``infer``, ``predict_observations`` and ``reconstruct`` (VB and the MAP baseline).

Shapes: ``T`` window length, ``Dx`` latent dim, ``Dz`` observation dim; ``...`` leading batch
dims.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Protocol

import torch

from ...gaussian import condition_gaussian
from ...linalg import symmetrize
from ...validation import as_tensor, check_choice
from ..residual import ar1_residual_forecast
from .window import WindowModel, window_mask

# numbers in one chunk of joint covariances q(z_{1:T}) in predict_observations: conditioning
# them is bound by memory traffic more than by flops, so chunks that stay near the cache are
# faster than one batch (16 MB in float64; `python -m benchmarks joint_chunks`)
_JOINT_ENTRIES = 2e6

__all__ = [
    "CandidateForecasts",
    "Forecaster",
    "candidate_forecasts",
    "candidate_predictions",
    "forecast",
    "observation_joint",
    "observation_marginals",
    "predict_observations",
]


def observation_marginals(
    window: WindowModel, mean: torch.Tensor, cov: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """Moment-matched ``q(z_t) = int p(z_t | x_t) q(x_t) dx_t`` per time step (FIC).

    Shapes: ``mean [..., T, Dx]``, ``cov [..., T, Dx, Dx]`` -> ``[..., T, Dz]``,
    ``[..., T, Dz, Dz]`` (observation noise included).
    """
    m, S, _ = window.measurement.predict_gaussian(mean, cov, include_noise=True)
    return m, S


def observation_joint(
    window: WindowModel,
    mean: torch.Tensor,
    cov: torch.Tensor,
    marginals: tuple[torch.Tensor, torch.Tensor] | None = None,
) -> tuple[torch.Tensor, torch.Tensor]:
    r"""Gaussian ``q(z_{1:T})`` with cross-time covariances (Sec. 2.3.2, App. 2.B).

    Diagonal blocks are the moment-matched ``Cov[z_t]``; for ``s != t`` (independent
    ``x_s, x_t`` under q, so the means do not covary)::

        Cov[z_s,d, z_t,e] = delta_de scale_d^2 (E[k(x_s, x_t)] - l_s^T K^-1 l_t),

    with ``l_t = E[k(X, x_t)]`` and ``E[k(x_s, x_t)]`` the expectation of ``k(x, mu_t)`` at
    ``x ~ N(mu_s, Sigma_s + Sigma_t)`` (exact for stationary and linear kernels alike).

    Shapes: ``mean [..., T, Dx]``, ``cov [..., T, Dx, Dx]`` -> ``mean [..., T, Dz]`` and
    ``cov [..., T * Dz, T * Dz]`` (time-major). ``marginals``: :func:`observation_marginals` of
    ``(mean, cov)`` if the caller has them already.
    """
    m, S = observation_marginals(window, mean, cov) if marginals is None else marginals
    T, dz = m.shape[-2:]
    gp = window.h
    lt = gp.expected_kernel(mean, cov, gp.X)  # [..., T, N]
    ls_kinv_lt = (lt @ gp.kinv) @ lt.transpose(-1, -2)  # [..., T, T]
    pair = cov[..., :, None, :, :] + cov[..., None, :, :, :]
    c = gp.expected_kernel(mean[..., :, None, :], pair, mean[..., None, :, None, :])[..., 0]
    cross = symmetrize(c - ls_kinv_lt)  # [..., T, T]
    scale2 = window.measurement.scale.pow(2)
    batch = torch.broadcast_shapes(cross.shape[:-2], S.shape[:-3])
    full = S.new_zeros(*batch, T, dz, T, dz)
    # blocks (s, t): scale^2 cross_st on their diagonals, then the moment-matched Cov[z_t] on
    # the time diagonal (written through views: no [.., T, Dz, T, Dz] temporaries)
    full.diagonal(dim1=-3, dim2=-1).copy_(cross[..., None] * scale2)
    full.diagonal(dim1=-4, dim2=-2).copy_(S.movedim(-3, -1))
    return m, full.reshape(*batch, T * dz, T * dz)


def predict_observations(
    window: WindowModel,
    z: torch.Tensor,
    observed: torch.Tensor,
    mean: torch.Tensor,
    cov: torch.Tensor,
    *,
    joint: bool = True,
    marginals: tuple[torch.Tensor, torch.Tensor] | None = None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Predict every row of a window from ``q(x) = N(mean, cov)`` (Sec. 2.3.2).

    With ``joint=True`` from ``q(z_missing | z_observed)`` (:func:`observation_joint`
    conditioned on the observed rows, which are returned unchanged with variance 0); with
    ``joint=False`` from the per-step marginals ``q(z_t)`` (FIC).

    Args:
        window: the model's :class:`~hgpdm_torch.inference.variational.window.WindowModel`.
        z: ``[..., T, Dz]`` window (NaN rows missing), observed: ``[..., T]`` its mask.
        mean: ``[..., T, Dx]``, cov: ``[..., T, Dx, Dx]`` q(x).
        marginals: :func:`observation_marginals` of ``(mean, cov)``, if already computed.

    Returns:
        ``mean [..., T, Dz]`` and ``var [..., T, Dz]``.
    """
    with torch.no_grad():
        m, S = observation_marginals(window, mean, cov) if marginals is None else marginals
        if not joint:
            return m, S.diagonal(dim1=-2, dim2=-1)
        T, dz = z.shape[-2:]
        batch = torch.broadcast_shapes(
            z.shape[:-2], observed.shape[:-1], mean.shape[:-2], m.shape[:-2]
        )
        flat = [
            t.expand(*batch, *t.shape[t.dim() - k :]).reshape(-1, *t.shape[t.dim() - k :])
            for t, k in ((z, 2), (observed, 1), (mean, 2), (cov, 3), (m, 2), (S, 3))
        ]
        size = max(1, int(_JOINT_ENTRIES // (T * dz) ** 2))
        means, variances = [], []
        for i in range(0, flat[0].shape[0], size):
            zc, oc, mc, cc, mm, SS = (t[i : i + size] for t in flat)
            jm, jS = observation_joint(window, mc, cc, (mm, SS))
            cm, cS = condition_gaussian(
                jm.reshape(-1, T * dz),
                jS,
                oc[:, :, None].expand(-1, T, dz).reshape(-1, T * dz),
                torch.nan_to_num(zc).reshape(-1, T * dz),
            )
            means.append(cm)
            variances.append(cS.diagonal(dim1=-2, dim2=-1))
        shape = (*batch, T, dz)
        return torch.cat(means).reshape(shape), torch.cat(variances).reshape(shape)


def _with_missing_row(z: torch.Tensor) -> torch.Tensor:
    """``[..., T, Dz]`` -> ``[..., T + 1, Dz]``: the windows with a missing (NaN) row appended,
    the frame to forecast."""
    nan = torch.full((*z.shape[:-2], 1, z.shape[-1]), float("nan"), dtype=z.dtype, device=z.device)
    return torch.cat([z, nan], -2)


class Forecaster(Protocol):
    """An inference engine :func:`forecast` can drive (VB or the MAP baseline)."""

    def infer(self, z: object, **kwargs: Any) -> Any: ...

    def predict_observations(self, z: object, result: Any) -> tuple[torch.Tensor, torch.Tensor]: ...

    def reconstruct(self, result: Any) -> tuple[torch.Tensor, torch.Tensor]: ...


def forecast(
    engine: Forecaster, z: object, *, residual: str | None = None, **infer_kwargs: Any
) -> tuple[torch.Tensor, torch.Tensor, Any]:
    """Forecast ``z_{T+1}`` from a window ``z_{1:T}`` (Sec. 2.3.2, Tables 2.1-2.4 protocol).

    Runs ``engine.infer`` on ``z_{1:T}`` with a missing row appended and predicts that row with
    ``engine.predict_observations`` (the ML value of g, conditioned on the observed rows).

    Args:
        engine: the inference engine.
        z: ``[..., T, Dz]`` windows (NaN marks missing values).
        residual: ``None`` (the thesis's forecast) or ``"ar1"``: the window's deviation from
            ``engine.reconstruct`` continues as an AR(1) process whose coefficient is estimated
            from the window (:func:`~hgpdm_torch.inference.residual.ar1_residual_forecast`); for
            new recordings that sit off the training manifold.
        **infer_kwargs: passed to ``engine.infer``.

    Returns:
        ``mean [..., Dz]``, ``var [..., Dz]`` of the next observation, and the result of
        ``engine.infer``.
    """
    if residual is not None:
        check_choice(residual, "residual", ("ar1",))
    z = as_tensor(z, "z", min_ndim=2, allow_nan=True)
    window = _with_missing_row(z)
    res = engine.infer(window, **infer_kwargs)
    if residual is None:
        m, v = engine.predict_observations(window, res)
        return m[..., -1, :], v[..., -1, :], res
    rec, var = engine.reconstruct(res)
    mean, var, _ = ar1_residual_forecast(z, rec[..., :-1, :], rec[..., -1, :], var[..., -1, :])
    return mean, var, res


def candidate_predictions(
    engine: Any,
    z: object,
    result: Any,
    marginals: tuple[torch.Tensor, torch.Tensor] | None = None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """:func:`predict_observations` (joint, conditioned on the observed rows) under every
    candidate's ``q(x)`` of a VB ``result`` of the windows ``z [..., T, Dz]``: ``mean`` and
    ``var`` ``[..., K, T, Dz]`` (missing rows forecast or recovered, App. 2.B). ``marginals``:
    :func:`observation_marginals` of the result's ``q(x)``, if already computed."""
    w = engine.window
    padded, observed = window_mask(z, engine.obs_dim, w.x1_mean)
    return predict_observations(
        w,
        padded[..., None, :, :],
        observed[..., None, :],
        result.mean,
        result.cov,
        marginals=marginals,
    )


@dataclass
class CandidateForecasts:
    """Next-frame forecasts of windows under every candidate value of g, from one VB posterior
    (:func:`candidate_forecasts`).

    Attributes:
        mean: ``[..., K, Dz]`` the thesis's forecast (joint ``q(z)`` conditioned on the window)
            under each candidate's ``q(x)``; var: ``[..., K, Dz]`` its variance.
        ar1_mean, ar1_var: ``[..., K, Dz]`` the same with the AR(1) residual
            (:func:`~hgpdm_torch.inference.residual.ar1_residual_forecast`).
        result: the :class:`~hgpdm_torch.inference.variational.VBResult` of the windows.
        reconstruction: ``[..., K, T + 1, Dz]`` the per-step marginal means of ``q(z_t)``
            (:func:`observation_marginals`) of the window's rows and the appended one under each
            candidate's ``q(x)``: how well the model reconstructs what it saw (the AR(1)
            residual's deviations are the observed rows minus these).
        map_mean: ``[..., K, Dz]`` the MAP baseline's forecast under each candidate: the
            measurement GP's mean at the appended row's MAP state (``result.map_states``, the
            Laplace start), as :meth:`~hgpdm_torch.inference.map.MAPInference.forecast` gives
            with ``steps`` = the VB run's ``newton_steps``; ``None`` without a Laplace start.
    """

    mean: torch.Tensor
    var: torch.Tensor
    ar1_mean: torch.Tensor
    ar1_var: torch.Tensor
    result: Any
    reconstruction: torch.Tensor
    map_mean: torch.Tensor | None = None

    def pick(
        self, index: torch.Tensor, *, ar1: bool = False, map_states: bool = False
    ) -> torch.Tensor:
        """The forecast mean ``[..., Dz]`` under candidate ``index [...]`` (e.g. ``g_ml``);
        ``map_states=True``: the MAP baseline's (:attr:`map_mean`)."""
        if map_states and (ar1 or self.map_mean is None):
            raise ValueError(
                "the MAP forecast has no AR(1) variant here and needs a Laplace start "
                "(newton_steps > 0)"
            )
        mean = self.map_mean if map_states else self.ar1_mean if ar1 else self.mean
        i = index.to(mean.device)[..., None, None].expand(*index.shape, 1, mean.shape[-1])
        return mean.gather(-2, i)[..., 0, :]

    def averaged(self, *, ar1: bool = False) -> torch.Tensor:
        """Bayesian model averaging over g: ``sum_k p(g_k | z) mean_k`` ``[..., Dz]``, the mean of
        the mixture of the candidates' forecasts under the posterior over g."""
        mean = self.ar1_mean if ar1 else self.mean
        return (self.result.posterior[..., None] * mean).sum(-2)


def candidate_forecasts(engine: Any, z: object, **infer_kwargs: Any) -> CandidateForecasts:
    """Forecast ``z_{T+1}`` of windows ``z_{1:T}`` under every candidate g from one inference.

    One ``engine.infer`` (a :class:`~hgpdm_torch.inference.variational.VariationalInference`) on
    the windows with a missing row appended gives ``q(x)`` for every candidate; the forecasts of
    :func:`forecast` (ML g), of the oracle (true g) and their Bayesian average all follow from it
    without another inference, and so do the MAP baseline's (its states are the Laplace
    start's). Pass ``prune=None`` so that every candidate's ``q(x)`` is refined (an oracle
    forecast under a pruned candidate is from a looser posterior).

    Args:
        engine: the VB engine.
        z: ``[..., T, Dz]`` windows (NaN marks missing values; the last row must be observed).
        **infer_kwargs: passed to ``engine.infer``.

    Returns:
        :class:`CandidateForecasts`.
    """
    z = as_tensor(z, "z", min_ndim=2, allow_nan=True)
    window = _with_missing_row(z)
    res = engine.infer(window, **infer_kwargs)
    with torch.no_grad():
        rec, rec_cov = observation_marginals(engine.window, res.mean, res.cov)
    mean, var = candidate_predictions(engine, window, res, (rec, rec_cov))
    rec_var = rec_cov.diagonal(dim1=-2, dim2=-1)
    ar1_mean, ar1_var, _ = ar1_residual_forecast(
        z[..., None, :, :].expand(*rec[..., :-1, :].shape),
        rec[..., :-1, :],
        rec[..., -1, :],
        rec_var[..., -1, :],
    )
    map_mean = None
    if res.map_states is not None:
        with torch.no_grad():
            map_mean = engine.window.h.predict_point(res.map_states[..., -1, :])[0]
            map_mean = map_mean + engine.window.measurement.offset
    return CandidateForecasts(
        mean[..., -1, :], var[..., -1, :], ar1_mean, ar1_var, res, rec, map_mean
    )
