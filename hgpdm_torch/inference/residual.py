"""A temporally correlated deviation from the model's reconstruction, for forecasting.

The GPDM's measurement noise is white: ``z_t = h(x_t) + eps_t``. New recordings (another trial,
another person) deviate from the training manifold ``h(x)`` by an amount that persists from
frame to frame (a posture offset, a slightly different gait), so a forecast ``E[h(x_{T+1})]``
forgets what the window showed about that deviation. Here the deviation is an AR(1) process per
channel, ``e_t = z_t - E[h(x_t)] = rho e_{t-1} + w_t``, with ``rho`` estimated from the window
itself by pooled least squares over its channels and consecutive observed frames (no tuning on
held-out data), clipped to ``[0, 1]``. The forecast ``k`` frames ahead adds ``rho^k e_T``.

The deviation is estimated after q(x) has been inferred under the white-noise model. Small
deviations stay in ``e`` and are carried forward (tests: an offset of 0.1 sd brings the forecast
error back near that of unshifted data); large ones (several tenths of an sd on synthetic data)
are partly absorbed by moving q(x), and the correction is then partial. Inferring the deviation
jointly with x would remove that limitation.
"""

from __future__ import annotations

import torch

__all__ = ["ar1_residual_forecast"]


def ar1_residual_forecast(
    z: torch.Tensor,
    reconstruction: torch.Tensor,
    mean: torch.Tensor,
    var: torch.Tensor,
    *,
    steps: int = 1,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Add the AR(1) continuation of the window's deviation to a model forecast.

    Args:
        z: ``[..., T, Dz]`` the window (NaN rows are missing; the last row must be observed).
        reconstruction: ``[..., T, Dz]`` the model's unconditioned predictions of those rows.
        mean: ``[..., Dz]`` the model's forecast mean of row ``T + steps``.
        var: ``[..., Dz]`` its marginal variance.
        steps: how many frames after the window's last row the forecast is.

    Returns:
        ``mean [..., Dz]``: ``mean + rho^steps e_T``; ``var [..., Dz]``: ``var`` plus the
        deviation's innovation variance ``s_d^2 (1 + rho^2 + ... + rho^(2 (steps - 1)))``, with
        ``s_d^2`` the mean squared one-step residual of channel d; and ``rho [...]``.
    """
    if z.shape != reconstruction.shape:
        raise ValueError(
            f"z and reconstruction must have the same shape, got {tuple(z.shape)} and "
            f"{tuple(reconstruction.shape)}"
        )
    if not isinstance(steps, int) or steps < 1:
        raise ValueError(f"steps must be a positive int, got {steps!r}")
    observed = ~torch.isnan(z).any(-1)  # [..., T]
    if not bool(observed[..., -1].all()):
        raise ValueError("an AR(1) residual forecast needs the window's last row observed")
    e = torch.nan_to_num(z - reconstruction)
    pair = (observed[..., 1:] & observed[..., :-1]).to(e.dtype)[..., None]  # [..., T-1, 1]
    cur, prev = e[..., 1:, :] * pair, e[..., :-1, :] * pair
    num = (cur * prev).sum((-1, -2))
    den = prev.pow(2).sum((-1, -2))
    rho = torch.where(den > 0, num / den.clamp_min(1e-300), torch.zeros_like(num)).clamp(0.0, 1.0)
    n_pairs = pair.sum((-1, -2)).clamp_min(1.0)
    s2 = (cur - rho[..., None, None] * prev).pow(2).sum(-2) / n_pairs[..., None]  # [..., Dz]
    power = rho**steps
    growth = sum(rho ** (2 * k) for k in range(steps))
    return mean + power[..., None] * e[..., -1, :], var + growth[..., None] * s2, rho
