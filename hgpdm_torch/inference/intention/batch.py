r"""Batch intention inference (Algorithm 3.1): :func:`infer_intention`.

For each value ``g`` of the grid the GP-RTSS smoother gives ``q_g(x_{1:T})`` and the bound of
Eq. 22 is evaluated in full,
``B(g) = log p(g) + E_q[log p(x_1)] + sum_t E_q[log p(z_t | x_t)] + sum_t Q_t(g) + H(q_g)``
(:func:`batch_bound_terms`). Algorithm 3.1 (line 3) prints only the transition part; the other
terms also depend on ``g`` through ``q_g``, so they are kept (with a shared ``q`` they are
constants, which is why the online algorithm can drop them).

Shapes: ``W`` windows, ``K`` intention values, ``T`` steps, ``Dx`` latent, ``Dz`` observed,
``Dg`` intention dims, ``N`` transition training points.
"""

from __future__ import annotations

from typing import Any

import torch

from ... import settings
from ...calibration import check_temperature, intention_log_prior
from ...gaussian import entropy, expected_log_density
from ...gp import GPPosterior
from ...intention_belief import IntentionBelief
from ...linalg import psd_cholesky, symmetrize
from ...models import HGPDM
from ...observations import DEFAULT_OUTLIER_SD, ObservationCheck, check_observations
from ...progress import tqdm
from ...validation import bad_observation
from ..filtering import check_window_model, filter_sequence, smooth
from .grid import check_chunk_size, intention_grid
from .linearisation import expected_log_conditional, gaussian_entropy
from .state_prior import first_state_prior

__all__ = ["batch_bound", "batch_bound_terms", "infer_intention"]


def batch_bound_terms(
    trans: GPPosterior,
    meas: GPPosterior,
    z: torch.Tensor,
    g: torch.Tensor,
    mu0: torch.Tensor,
    Sigma0: torch.Tensor,
    *,
    outlier_sd: float | None = DEFAULT_OUTLIER_SD,
) -> dict[str, torch.Tensor]:
    """The four terms of the bound of Eq. 22 (without ``log p(g)``), each ``[K, W]``.

    ``"state"``: ``E_q[log p(x_1)]``; ``"measurement"``: ``sum_t E_q[log p(z_t | x_t)]``;
    ``"transition"``: ``sum_t Q_t(g)``; ``"entropy"``: ``H(q)``, with ``q = q_g(x_{1:T})`` the
    GP-RTSS smoother under ``g``. Their sum is :func:`batch_bound`. Comparing a term across the
    K values shows where the evidence for (or against) each value comes from: on real gestures
    only ``"transition"`` and ``"state"`` favour the true class (docs, action recognition).

    Args:
        trans: transition GP ``[x, g] -> x_{t+1}``; meas: measurement GP ``x -> z``.
        z: ``[W, T, Dz]`` windows (NaN rows missing; other bad rows raise, see
            :func:`~hgpdm_torch.inference.filtering.filter_sequence`).
        g: ``[K, Dg]`` intention values (codes).
        mu0: ``[Dx]`` mean of the first state's prior (or ``[K, 1, Dx]``: one per intention
            value).
        Sigma0: ``[Dx, Dx]`` its covariance (or ``[K, 1, Dx, Dx]``).
        outlier_sd: plausibility threshold of the observation check (``None``: finiteness only).

    Returns:
        ``{"state", "measurement", "transition", "entropy"}``, each ``[K, W]``.
    """
    gk = g[:, None, :]  # [K, 1, Dg] broadcasts against the W windows
    fr = filter_sequence(trans, meas, z, mu0, Sigma0, g=gk, outlier_sd=outlier_sd)
    sm = smooth(fr)  # [K, W, T, ...]
    shape = (len(g), z.shape[0])
    q1_chol = psd_cholesky(sm.cov[..., 0, :, :], name="smoothed covariance")
    h = entropy(q1_chol).expand(shape)
    L0 = psd_cholesky(Sigma0, name="prior covariance")
    state = expected_log_density(sm.mean[..., 0, :], q1_chol, mu0, L0)
    # E_q[log p(z_t | x_t)] over observed steps
    with settings.internal_step():  # the smoother's own marginals
        zm, zc, zx = meas.predict_gaussian(sm.mean, sm.cov, include_noise=True)
    observed = ~torch.isnan(z).all(-1)
    zz = torch.where(observed[..., None], z, zm)
    lz = expected_log_conditional(sm.mean, sm.cov, zm, zc, zx, sm.mean, sm.cov, zz, None, None)
    measurement = torch.where(observed, lz, torch.zeros_like(lz)).sum(-1)
    transition = torch.zeros_like(measurement)
    if z.shape[-2] > 1:
        m_in, P_in = sm.mean[..., :-1, :], sm.cov[..., :-1, :, :]
        with settings.internal_step():
            pm, pc, px = trans.predict_gaussian(
                m_in, P_in, g=g[:, None, None, :], include_noise=True
            )
        Q = expected_log_conditional(
            m_in, P_in, pm, pc, px, m_in, P_in,
            sm.mean[..., 1:, :], sm.cov[..., 1:, :, :], sm.cross_cov,
        )  # fmt: skip
        # Markov entropy: H = H(x_1) + sum_t [H(x_t, x_{t+1}) - H(x_t)]
        pair = torch.cat(
            [
                torch.cat([P_in, sm.cross_cov], -1),
                torch.cat([sm.cross_cov.transpose(-1, -2), sm.cov[..., 1:, :, :]], -1),
            ],
            -2,
        )
        H = gaussian_entropy(symmetrize(pair)) - gaussian_entropy(P_in)
        transition = Q.sum(-1)
        h = h + H.sum(-1)
    return {
        "state": state.expand(shape),
        "measurement": measurement.expand(shape),
        "transition": transition.expand(shape),
        "entropy": h,
    }


def batch_bound(*args: Any, **kwargs: Any) -> torch.Tensor:
    """The bound of Eq. 22 without ``log p(g)``, ``[K, W]`` for every intention value and window.

    ``B(g) - log p(g) = E_q[log p(x_1)] + sum_t E_q[log p(z_t | x_t)] + sum_t Q_t(g) + H(q)``
    with ``q = q_g(x_{1:T})`` the GP-RTSS smoother under ``g``: the sum of
    :func:`batch_bound_terms`, which takes the same arguments. For a linear-Gaussian model the
    smoother is exact and the bound equals ``log p(z_{1:T} | g)``.
    """
    return sum(batch_bound_terms(*args, **kwargs).values())


def infer_intention(
    model: HGPDM,
    z: Any,
    intentions: Any = None,
    *,
    window: int | None = None,
    prior: Any = None,
    mu0: Any = None,
    Sigma0: Any = None,
    state_prior: str = "marginal",
    temperature: float = 1.0,
    chunk_size: int | None = None,
    outlier_sd: float | None = DEFAULT_OUTLIER_SD,
    progress: bool = False,
) -> IntentionBelief:
    r"""Batch intention inference (Algorithm 3.1), batched over the K intention values.

    For every value ``g_k`` the GP-ADF/RTSS smoother (:mod:`hgpdm_torch.inference.filtering`)
    gives ``q_k(x_{1:T}) ~= p(x_{1:T} | z_{1:T}, g_k)`` (Eq. 23-28); the bound of Eq. 22,
    ``B(g) = log p(g) + E_q[log p(x_1)] + sum_t E_q[log p(z_t | x_t)] + sum_t Q_t(g) + H(q)``
    (``Q_t`` and the measurement term by statistical linearisation, see
    :func:`expected_log_conditional`; ``H`` the entropy of the Markov Gaussian ``q``), is
    normalised over the grid (line 4).

    Args:
        model: a fitted :class:`~hgpdm_torch.models.HGPDM` / ``IDDM``.
        z: ``[T, Dz]`` or ``[W, T, Dz]`` observations; NaN rows are missing. A bad row (inf,
            partly NaN, or more than ``outlier_sd`` training standard deviations from the
            training mean in a channel; see
            :class:`~hgpdm_torch.observations.ObservationCheck`) raises a ``ValueError``
            naming its window, step and channel.
        intentions: grid or codes, see :func:`intention_grid`.
        window: if given, a sliding window: the belief at every step ``t`` from
            ``z_{max(1, t-window+1):t}`` (output ``[..., T, K]``).
        prior: ``[K]`` prior probabilities (default uniform).
        mu0: ``[Dx]`` mean of the prior of each window's first state (default: the training
            latents' empirical mean, as a window may start anywhere in a movement).
        Sigma0: ``[Dx, Dx]`` its covariance (default: the training latents' empirical one).
        state_prior: ``"marginal"`` (the prior above, shared by all g) or, for a discrete g,
            ``"class"``: ``p(x_1 | g)`` from the training latents of each value
            (:func:`class_state_prior`), so that where a window's movement is, not only how it
            moves, is evidence about g. On real gestures (MSRC-12) ``"class"`` recognises far
            better (docs, action recognition).
        temperature: ``T > 0``: the posterior is ``p(g) exp(B'(g) / T)`` normalised, with
            ``B'`` the bound without ``log p(g)`` (:mod:`~hgpdm_torch.calibration`);
            1 is Algorithm 3.1. A uniform prior keeps the ranking (and the decisions); ``T``
            chosen by :func:`~hgpdm_torch.calibration.fit_temperature` on held-out
            windows calibrates the credible sets.
        chunk_size: positive int, windows processed together; default ``2^24 / (K N^2)``
            bounds the ``[K, chunk, N, N]`` moment-matching temporaries to about 128 MB each
            (float64).
        outlier_sd: plausibility threshold (limits from the model's training observations);
            ``None`` refuses only non-finite values and partly NaN rows.
        progress: show a tqdm bar over chunks.

    Returns:
        :class:`IntentionBelief` with ``prob [..., K]`` (``[..., T, K]`` with ``window``).
    """
    check_window_model(model, HGPDM, "an HGPDM/IDDM", "infer_intention's windows carry no phase")
    values = intention_grid(model, intentions)
    dtype = values.dtype
    z = check_observations(z, model.obs_dim, min_ndim=2)
    if z.shape[-2] == 0:
        raise ValueError("z must hold at least one time step")
    if window is not None and (not isinstance(window, int) or window < 1):
        raise ValueError(f"window must be a positive int or None, got {window!r}")
    chunk_size = check_chunk_size(chunk_size)
    temperature = check_temperature(temperature)
    trans, meas = model.transition_posterior(), model.measurement_posterior()
    found = ObservationCheck.from_measurement(meas, outlier_sd).first_bad(z)
    if found is not None:
        index, why = found
        windows = ", ".join(map(str, index[:-1]))
        where = f"window {windows}, step {index[-1]}" if windows else f"step {index[-1]}"
        raise bad_observation(f"z{list(index)} ({where})", why)
    z = z.to(dtype)
    log_prior = intention_log_prior(prior, len(values), dtype, values.device)
    m0, S0 = first_state_prior(model, values, mu0, Sigma0, state_prior, dtype)
    if state_prior == "class":  # [K, 1, ...] broadcasts against the windows in batch_bound
        m0, S0 = m0[:, None], S0[:, None]
    n = trans.train_inputs.shape[0]
    chunk_size = chunk_size or max(1, 2**24 // (len(values) * n * n))
    lead, T = z.shape[:-2], z.shape[-2]
    flat = z.reshape(-1, T, z.shape[-1])
    # one batch of equal-length windows per length: w for t >= w, then the shorter first ones
    if window is None:
        jobs = [(flat, None)]
    else:
        w = min(window, T)
        full = flat.unfold(1, w, 1).transpose(-1, -2)  # [F, T - w + 1, w, Dz]
        jobs = [(full.reshape(-1, w, z.shape[-1]), ("full", w))]
        jobs += [(flat[:, :t], ("start", t)) for t in range(1, w)]
    out = values.new_empty(flat.shape[0], T if window else 1, len(values))
    for batch, tag in tqdm(jobs, disable=not progress, desc="batch intention", leave=False):
        parts = [
            batch_bound(
                trans, meas, batch[i : i + chunk_size], values, m0, S0, outlier_sd=outlier_sd
            ).mT
            for i in range(0, batch.shape[0], chunk_size)
        ]
        score = torch.cat(parts, 0) / temperature + log_prior  # [windows, K]
        if tag is None:
            out[:, 0] = score
        elif tag[0] == "full":
            out[:, tag[1] - 1 :] = score.view(flat.shape[0], -1, len(values))
        else:
            out[:, tag[1] - 1] = score
    shape = (*lead, T, len(values)) if window else (*lead, len(values))
    return IntentionBelief.from_log(out.reshape(shape), values, model.intention == "continuous")
