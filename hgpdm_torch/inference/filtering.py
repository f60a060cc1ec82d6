r"""GP-ADF filtering and GP-RTSS smoothing by moment matching (thesis Sec. 3.3.1, Eq. 24-35).

The state-space model is a transition GP ``x_{t+1} = f(x_t, g) + w`` (the GP's targets are the
absolute next states; its noise ``alpha_4`` is the process noise ``w``) and a measurement GP
``z_t = h(x_t) + v``. Every step approximates a joint distribution by the Gaussian with its exact
first two moments (:meth:`~hgpdm_torch.gp.GPPosterior.predict_gaussian`):

- prediction, Eq. 28: ``p(x_{t-1}, x_t | z_{1:t-1})``;
- measurement update, Eq. 25 and 32: ``p(x_t, z_t | z_{1:t-1})`` conditioned on ``z_t``;
- RTS smoothing, Eq. 26-27 (with the corrected left side of Eq. 26,
  docs/design/math.md#rts-smoothing-the-corrected-eq-26)::

      J_{t-1} = Sigma_{t-1,t|t-1} Sigma_{t|t-1}^-1
      mu_{t-1|T} = mu_{t-1|t-1} + J_{t-1} (mu_{t|T} - mu_{t|t-1})
      Sigma_{t-1|T} = Sigma_{t-1|t-1} + J_{t-1} (Sigma_{t|T} - Sigma_{t|t-1}) J_{t-1}^T
      Sigma_{t-1,t|T} = J_{t-1} Sigma_{t|T}

  which give the block-tri-diagonal covariance of Eq. 24.

The intention ``g`` may be

- absent (``g=None``, a GPDM transition over ``x`` alone);
- known (``g`` a tensor of values, or of the integer codes of a discrete intention); a leading
  dim of ``g`` runs all K values at once, e.g. ``g [K, 1, Dg]`` with observations ``[B, T, Dz]``
  gives results ``[K, B, ...]``;
- Gaussian (``g`` the mean and ``g_cov`` the covariance): the state is augmented to
  ``s = [x, g]`` with a static ``g``, and the filter also infers ``g``. Results then have
  ``D = Dx + Dg`` columns, the last ``Dg`` being the belief over ``g``.

Observations are checked before filtering (:class:`ObservationCheck`): a row of NaN is a missing
observation (a prediction-only step); a row with inf, with NaN in some channels only, or with a
value more than ``outlier_sd`` (default 100) training standard deviations from the training mean
of its channel raises a ``ValueError`` naming its batch index, step and channel. Such values would
otherwise overflow the moment matching and fail far from their cause.

Shapes: ``T`` time steps, ``D`` state dim, ``Dz`` observation dim; ``...`` batch dims.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from .. import settings
from ..expectations import check_gaussian
from ..gaussian import conditional, independent_joint, log_density, rts_step
from ..gp import GPPosterior
from ..linalg import positive_definite, psd_cholesky, symmetrize
from ..observations import DEFAULT_OUTLIER_SD, ObservationCheck
from ..progress import tqdm
from ..validation import (
    as_observations,
    as_tensor,
    bad_observation,
)

__all__ = [
    "FilterResult",
    "SmootherResult",
    "filter_sequence",
    "gp_adf_predict",
    "gp_adf_update",
    "smooth",
]


def check_window_model(model: object, kind: type, kinds: str, what: str) -> None:
    """Refuse a model that ``what`` (the inference of windows of observations, in its own words)
    cannot take: one that is not a ``kind`` (``kinds`` names those accepted), or a phase-aware
    IDDM (``phase_width`` set), whose phase a window does not carry.

    Raises:
        TypeError: not a ``kind``.
        ValueError: a phase-aware IDDM, naming the online filter that takes it.
    """
    if not isinstance(model, kind):
        raise TypeError(f"model must be {kinds}, got {type(model).__name__}")
    if getattr(model, "phase_width", None) is not None:
        raise ValueError(
            f"{what}: a phase-aware IDDM (phase_width set) is filtered online "
            "(OnlineIntentionFilter), which counts each stream's frames"
        )


@dataclass
class FilterResult:
    """Output of :func:`filter_sequence`.

    Attributes:
        mean: ``[..., T, D]`` filtered means ``mu_{t|t}``.
        cov: ``[..., T, D, D]`` filtered covariances ``Sigma_{t|t}``.
        pred_mean: ``[..., T, D]`` predicted means ``mu_{t|t-1}`` (``t = 1``: the prior).
        pred_cov: ``[..., T, D, D]`` predicted covariances ``Sigma_{t|t-1}``.
        cross_cov: ``[..., T-1, D, D]`` ``Sigma_{t-1,t|t-1} = Cov[x_{t-1}, x_t | z_{1:t-1}]``
            (Eq. 28), entry ``t-1`` for the pair ``(t-1, t)``.
        log_likelihood: ``[...]`` ``sum_t log N(z_t | mu^z_{t|t-1}, Sigma^z_{t|t-1})``, the
            moment-matching approximation of ``log p(z_{1:T})`` (missing steps contribute 0).
    """

    mean: torch.Tensor
    cov: torch.Tensor
    pred_mean: torch.Tensor
    pred_cov: torch.Tensor
    cross_cov: torch.Tensor
    log_likelihood: torch.Tensor


@dataclass
class SmootherResult:
    """Output of :func:`smooth`: the Gaussian ``q(x_{1:T})`` of Eq. 23-24.

    Attributes:
        mean: ``[..., T, D]`` ``mu_{t|T}``.
        cov: ``[..., T, D, D]`` ``Sigma_{t|T}``.
        cross_cov: ``[..., T-1, D, D]`` ``Sigma_{t-1,t|T} = Cov[x_{t-1}, x_t | z_{1:T}]``.
    """

    mean: torch.Tensor
    cov: torch.Tensor
    cross_cov: torch.Tensor


def _check_posterior(gp: object, name: str) -> GPPosterior:
    if not isinstance(gp, GPPosterior):
        raise TypeError(f"{name} must be a GPPosterior, got {type(gp).__name__}")
    return gp


def gp_adf_predict(
    transition: GPPosterior,
    mu: torch.Tensor,
    Sigma: torch.Tensor,
    *,
    g: torch.Tensor | None = None,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """One GP-ADF time update: the Gaussian of Eq. 28 for ``p(s_{t-1}, s_t | z_{1:t-1})``.

    Args:
        transition: GP from ``[x, g]`` (or ``x``) to the next ``x`` (``Dx`` outputs); its noise is
            the process noise.
        mu: ``[..., D]`` filtered mean of the state; ``D = Dx``, or ``Dx + Dg`` for a state
            augmented with a Gaussian intention (then ``g`` must be ``None``).
        Sigma: ``[..., D, D]`` filtered covariance.
        g: ``[..., Dg]`` known intention values or discrete codes, or ``None``.

    Returns:
        ``mean [..., D]`` and ``cov [..., D, D]`` of the next state, and the cross-covariance
        ``Cov[s_{t-1}, s_t] [..., D, D]``. The static part of an augmented state is copied.
    """
    transition = _check_posterior(transition, "transition")
    mu, Sigma = check_gaussian(mu, Sigma, "state")
    dx, D = transition.output_dim, mu.shape[-1]
    if D < dx:
        raise ValueError(f"state dim {D} is smaller than the transition output dim {dx}")
    if g is not None and D != dx:
        raise ValueError(
            f"with a known g the state must have the transition output dim {dx}, got {D}"
        )
    m, S, C = transition.predict_gaussian(mu, Sigma, g=g, include_noise=True)
    if D == dx:
        return m, S, C
    # augmented [x, g]: g is static, so Cov[s_t, g_{t+1}] = Cov[s_t, g_t]
    batch = m.shape[:-1]
    mg = mu[..., dx:].expand(*batch, D - dx)
    Sfg = C[..., dx:, :]  # Cov[g, f]
    Sgg = Sigma[..., dx:, dx:].expand(*batch, D - dx, D - dx)
    mean = torch.cat([m, mg], dim=-1)
    cov = torch.cat([torch.cat([S, Sfg.transpose(-1, -2)], -1), torch.cat([Sfg, Sgg], -1)], dim=-2)
    cross = torch.cat([C, Sigma[..., :, dx:].expand(*batch, D, D - dx)], dim=-1)
    return mean, symmetrize(cov), cross


def gp_adf_update(
    measurement: GPPosterior,
    mu_pred: torch.Tensor,
    Sigma_pred: torch.Tensor,
    z: torch.Tensor,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """GP-ADF measurement update (Eq. 25 with the joint of Eq. 32-35).

    The measurement GP reads the first ``measurement.input_dim`` state columns; further columns
    (a Gaussian intention) are updated through their correlation with them.

    Args:
        measurement: GP from ``x`` to ``z`` (its noise is the observation noise).
        mu_pred: ``[..., D]`` predicted mean ``mu_{t|t-1}``.
        Sigma_pred: ``[..., D, D]`` predicted covariance.
        z: ``[..., Dz]`` observation; a row of NaN marks a missing observation (the prediction is
            returned unchanged).

    Returns:
        ``mu_{t|t} [..., D]``, ``Sigma_{t|t} [..., D, D]`` and ``log N(z | mu^z, Sigma^z)
        [...]`` (0 where z is missing).
    """
    measurement = _check_posterior(measurement, "measurement")
    mu_pred, Sigma_pred = check_gaussian(mu_pred, Sigma_pred, "predicted state")
    z = as_tensor(z, "z", min_ndim=1, dtype=mu_pred.dtype, device=mu_pred.device, allow_nan=True)
    dz, dm = measurement.output_dim, measurement.input_dim
    if z.shape[-1] != dz:
        raise ValueError(f"z must have {dz} columns (measurement output dim), got {z.shape[-1]}")
    if mu_pred.shape[-1] < dm:
        raise ValueError(f"state dim {mu_pred.shape[-1]} < measurement input dim {dm}")
    nan = torch.isnan(z)
    missing = nan.all(-1)
    if bool((nan.any(-1) & ~missing).any()):
        raise ValueError("z rows must be fully observed or all NaN (missing); got partial NaN")
    mz, Sz, Csz = measurement.predict_gaussian(
        mu_pred[..., :dm],
        Sigma_pred[..., :dm, :dm],
        include_noise=True,
        joint_cov=Sigma_pred[..., :, :dm],
    )
    L = psd_cholesky(Sz, name="predicted observation covariance")
    zr = torch.where(missing[..., None], mz, z)  # zero innovation where z is missing
    gain_t, Sigma = conditional(Sigma_pred, Csz, L)  # (Sz^-1 Czs)  [..., Dz, D]
    mu = mu_pred + ((zr - mz)[..., None, :] @ gain_t)[..., 0, :]
    ll = log_density(zr, mz, L)
    keep = missing[..., None]
    mu = torch.where(keep, mu_pred.expand_as(mu), mu)
    Sigma = torch.where(keep[..., None], Sigma_pred.expand_as(Sigma), Sigma)
    return mu, Sigma, torch.where(missing, torch.zeros_like(ll), ll)


def filter_sequence(
    transition: GPPosterior,
    measurement: GPPosterior,
    z: torch.Tensor,
    mu0: torch.Tensor,
    Sigma0: torch.Tensor,
    *,
    g: torch.Tensor | None = None,
    g_cov: torch.Tensor | None = None,
    outlier_sd: float | None = DEFAULT_OUTLIER_SD,
    progress: bool = False,
) -> FilterResult:
    """GP-ADF over a sequence: alternate :func:`gp_adf_update` and :func:`gp_adf_predict`.

    Args:
        transition: transition GP (``[x, g] -> x_{t+1}``, noise = process noise).
        measurement: measurement GP (``x -> z``).
        z: ``[..., T, Dz]`` observations; NaN rows are missing (prediction-only steps). A row
            that :class:`ObservationCheck` calls bad (inf, partly NaN, or more than
            ``outlier_sd`` training standard deviations from the training mean in a channel)
            raises a ``ValueError`` naming its batch index, step and channel.
        mu0: ``[..., Dx]`` prior mean of ``x_1``.
        Sigma0: ``[..., Dx, Dx]`` prior covariance of ``x_1``.
        g: known intention values/codes ``[..., Dg]``; or, with ``g_cov``, the prior mean of a
            Gaussian intention; or ``None``.
        g_cov: ``[..., Dg, Dg]`` prior covariance of a Gaussian intention (augments the state).
        outlier_sd: plausibility threshold of :class:`ObservationCheck` (limits from the
            measurement GP's training data); ``None`` refuses only non-finite entries.
        progress: show a tqdm bar over time steps.

    Returns:
        :class:`FilterResult` with ``D = Dx`` (or ``Dx + Dg`` with ``g_cov``).
    """
    _check_posterior(transition, "transition")
    _check_posterior(measurement, "measurement")
    mu, Sigma = check_gaussian(mu0, Sigma0, "initial state")
    z = as_observations(z, min_ndim=2)
    if z.shape[-1] != measurement.output_dim:
        raise ValueError(
            f"z must have {measurement.output_dim} columns (measurement output dim), got "
            f"{z.shape[-1]}"
        )
    found = ObservationCheck.from_measurement(measurement, outlier_sd).first_bad(z)
    if found is not None:
        index, why = found
        lead = ", ".join(map(str, index[:-1]))
        lead = f"batch index {lead}, " if lead else ""
        raise bad_observation(f"z{list(index)} ({lead}step {index[-1]})", why)
    z = z.to(dtype=mu.dtype, device=mu.device)
    known = g
    if g_cov is not None:
        if g is None:
            raise ValueError("g_cov needs g, the prior mean of the intention")
        mg, Sg = check_gaussian(g, g_cov, "intention")
        mu, Sigma = independent_joint(mu, Sigma, mg, Sg)
        known = None
    T = z.shape[-2]
    if T < 1:
        raise ValueError("z must hold at least one time step")
    means, covs, pmeans, pcovs, crosses = [], [], [], [], []
    ll = torch.zeros((), dtype=mu.dtype, device=mu.device)
    with settings.internal_step():  # the state is checked once above, per step under debug
        for t in tqdm(range(T), disable=not progress, desc="GP-ADF", leave=False):
            if t > 0:
                mu, Sigma, C = gp_adf_predict(transition, mu, Sigma, g=known)
                crosses.append(C)
            pmeans.append(mu)
            pcovs.append(Sigma)
            mu, Sigma, step_ll = gp_adf_update(measurement, mu, Sigma, z[..., t, :])
            ll = ll + step_ll
            means.append(mu)
            covs.append(Sigma)
    # one batched check of every filtered and predicted covariance (the per-step structure check
    # runs only under settings.debug): a covariance that rounding made indefinite never returns
    bad = [~positive_definite(torch.stack(torch.broadcast_tensors(*c))) for c in (covs, pcovs)]
    for which, mask in zip(("filtered", "predicted"), bad, strict=True):
        if bool(mask.any()):
            step = int(torch.nonzero(mask.reshape(T, -1).any(-1))[0])
            raise ValueError(
                f"the {which} state covariance at step {step} is not positive definite (or not "
                "finite): the GP-ADF moments lost their precision there; use float64, a larger "
                "process noise, or settings.debug(True) to find the first bad step's input"
            )
    batch = torch.broadcast_shapes(*(m.shape[:-1] for m in means + pmeans))
    D = mu.shape[-1]

    def stack(items: list[torch.Tensor], shape: tuple[int, ...]) -> torch.Tensor:
        if not items:
            return torch.zeros(*batch, 0, *shape, dtype=mu.dtype, device=mu.device)
        return torch.stack([x.expand(*batch, *shape) for x in items], dim=len(batch))

    return FilterResult(
        mean=stack(means, (D,)),
        cov=stack(covs, (D, D)),
        pred_mean=stack(pmeans, (D,)),
        pred_cov=stack(pcovs, (D, D)),
        cross_cov=stack(crosses, (D, D)),
        log_likelihood=ll.expand(batch),
    )


def smooth(result: FilterResult) -> SmootherResult:
    """GP-RTSS backward pass (Eq. 26-27): smoothed marginals and consecutive cross-covariances.

    Args:
        result: output of :func:`filter_sequence`.

    Returns:
        :class:`SmootherResult` with the shapes of ``result``.
    """
    if not isinstance(result, FilterResult):
        raise TypeError(f"result must be a FilterResult, got {type(result).__name__}")
    T = result.mean.shape[-2]
    m, P = result.mean[..., -1, :], result.cov[..., -1, :, :]
    means, covs, crosses = [m], [P], []
    for t in range(T - 2, -1, -1):
        m, P, C = rts_step(
            result.mean[..., t, :],
            result.cov[..., t, :, :],
            result.pred_mean[..., t + 1, :],
            result.pred_cov[..., t + 1, :, :],
            result.cross_cov[..., t, :, :],
            m,
            P,
            name=f"predicted covariance at step {t + 2}",
        )
        crosses.append(C)  # Sigma_{t,t+1|T}
        means.append(m)
        covs.append(P)
    D = result.mean.shape[-1]
    cross = (
        torch.stack(crosses[::-1], dim=-3)
        if crosses
        else result.mean.new_zeros(*result.mean.shape[:-2], 0, D, D)
    )
    return SmootherResult(
        mean=torch.stack(means[::-1], dim=-2), cov=torch.stack(covs[::-1], dim=-3), cross_cov=cross
    )
