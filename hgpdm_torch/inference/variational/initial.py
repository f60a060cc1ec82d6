r"""Initial latent states of a window for VB and MAP inference (thesis Algorithm 2.2, step 1;
Sec. 2.4.2 for the filter start).

``"nearest"`` reads each observed row's state off the nearest training frame of candidate g,
``"filter"`` / ``"smoother"`` run GP-ADF / GP-RTSS moment matching (Eq. 20-26) through the window,
``"prior"`` starts every step at ``p(x_1) = N(m_1, S_1)``.

Shapes: ``T`` window length, ``K`` candidate values of g, ``M`` training frames, ``Dx`` latent
dim, ``Dg`` dim of a continuous g; ``...`` leading batch dims.
"""

from __future__ import annotations

import math

import torch

from ...validation import check_choice
from ..filtering import filter_sequence, smooth
from .window import WindowModel

__all__ = ["INITIALISATIONS", "initial_guess"]

INITIALISATIONS = ("nearest", "filter", "smoother", "prior")


def initial_guess(
    window: WindowModel, z: torch.Tensor, values: torch.Tensor, init: str = "nearest"
) -> tuple[torch.Tensor | None, ...]:
    """Initial q(x) [and q(g)] of a window (Algorithm 2.2, step 1).

    ``"nearest"``: each observed row takes the latent state of the nearest training frame
    (in the model's scaled observation units) among the frames of candidate g, so every g
    starts on its own part of the latent space; missing rows follow the transition mean of
    g from the previous state (rows before the first observation copy its state).
    Covariances ``S_1 / 100`` (the Laplace step of VB replaces them).
    ``"filter"``: the forward sweep of Sec. 2.4.2, done by GP-ADF moment matching
    (:func:`~hgpdm_torch.inference.filtering.filter_sequence`): ``q(x_t)`` from
    ``z_{1:t}`` only, so a missing row is filled by the learned transition model of each g.
    ``"smoother"``: the GP-RTSS smoothed marginals. ``"prior"``: ``p(x_1)`` at every step.
    A continuous g starts at its prior (``"filter"``/``"smoother"``: at the filter's belief).

    Args:
        window: the model's :class:`WindowModel`.
        z: ``[..., T, Dz]`` window (NaN rows missing); values: ``[..., K]`` candidate codes.
        init: one of ``"nearest"``, ``"filter"``, ``"smoother"``, ``"prior"``.

    Returns:
        ``loc [..., K, T, Dx]``, ``cov [..., K, T, Dx, Dx]``, and ``g_loc [..., Dg]``,
        ``g_cov [..., Dg, Dg]`` (``None`` unless g is continuous).
    """
    check_choice(init, "init", INITIALISATIONS)
    T, dx = z.shape[-2], window.latent_dim
    K = max(int(values.shape[-1]), 1) if window.kind == "discrete" else 1
    batch = (*z.shape[:-2], K)
    g_loc = g_cov = None
    if window.kind == "continuous":
        g_loc = window.g_prior_mean.expand(*z.shape[:-2], window.g_dim).clone()
        g_cov = window.g_prior_cov.expand(*g_loc.shape, window.g_dim).clone()
    if init == "prior":
        loc = window.x1_mean.expand(*batch, T, dx).clone()
        cov = window.x1_cov.expand(*batch, T, dx, dx).clone()
        return loc, cov, g_loc, g_cov
    if init == "nearest":
        loc = nearest_states(window, z, values, g_loc)
        return loc, (0.01 * window.x1_cov).expand(*batch, T, dx, dx).clone(), g_loc, g_cov
    g = g_cov = None
    if window.kind == "discrete":
        g = values.to(z.dtype)[..., None]  # [..., K, 1] codes
    elif window.kind == "continuous":
        g, g_cov = window.g_prior_mean, window.g_prior_cov
    with torch.no_grad():
        res = filter_sequence(
            window.transition,
            window.measurement,
            z[..., None, :, :],
            window.x1_mean,
            window.x1_cov,
            g=g,
            g_cov=g_cov,
        )
        mean, cov = res.mean, res.cov
        if init == "smoother":
            sm = smooth(res)
            mean, cov = sm.mean, sm.cov
    mean = mean.expand(*batch, *mean.shape[-2:])
    cov = cov.expand(*batch, *cov.shape[-3:])
    loc, xcov = mean[..., :dx], cov[..., :dx, :dx]
    if window.kind != "continuous":
        return loc, xcov, None, None
    return loc, xcov, mean[..., 0, -1, dx:], cov[..., 0, -1, dx:, dx:]


def nearest_states(
    window: WindowModel, z: torch.Tensor, values: torch.Tensor, g_loc: torch.Tensor | None
) -> torch.Tensor:
    """States ``[..., K, T, Dx]`` of the ``"nearest"`` initialisation (see
    :func:`initial_guess`)."""
    model = window.model
    w = model.scales.detach()
    train = model.observations * w  # [M, Dz]
    rows = torch.nan_to_num(z) * w
    d2 = (rows.pow(2).sum(-1)[..., None] - 2.0 * rows @ train.T) + train.pow(2).sum(-1)
    d2 = d2[..., None, :, :]  # [..., 1, T, M]
    lat = model.latent.detach()
    if window.kind == "discrete":
        lengths = model.lengths
        seq = torch.repeat_interleave(torch.arange(len(lengths), device=lengths.device), lengths)
        code = model.intention_codes()[seq].to(values.device)  # [M]
        other = code != values[..., :, None, None]  # [..., K, 1, M]
        d2 = d2.masked_fill(other, math.inf)
    x = lat[d2.argmin(-1)]  # [..., K, T, Dx]
    observed = ~torch.isnan(z).all(-1)  # [..., T]
    if bool(observed.all()):
        return x
    f = window.transition_gp(values)
    first = observed.to(torch.long).argmax(-1)  # first observed row
    x0 = x.gather(-2, first[..., None, None, None].expand(*x.shape[:-2], 1, x.shape[-1]))
    states = []
    for t in range(z.shape[-2]):
        obs_t = observed[..., t, None, None]
        if t == 0:
            states.append(torch.where(obs_t, x[..., 0, :], x0[..., 0, :]))
            continue
        m, _ = f.predict_point(window.transition_inputs(states[-1][..., None, :], g_loc))
        before = (first >= t)[..., None, None]  # rows before the first observation
        fill = torch.where(before, x0[..., 0, :], m[..., 0, :])
        states.append(torch.where(obs_t, x[..., t, :], fill))
    return torch.stack(states, -2)
