"""Supervised initial latent states: the latent directions a MAP fit starts from, chosen by how
they covary with the intention (an alternative to the default PCA initialisation of
:class:`~hgpdm_torch.models.GPDM`'s ``init``)."""

from __future__ import annotations

import torch
from sklearn.cross_decomposition import PLSRegression

from ..validation import as_tensor

__all__ = ["supervised_init"]


def supervised_init(obs: torch.Tensor, targets: torch.Tensor, latent_dim: int) -> torch.Tensor:
    """Initial latent states from partial least squares of the frames on their play's target.

    The MAP fit of the IDDM (Eq. 6) is local, so the initial latent decides which observation
    directions the latent keeps. PCA keeps the directions of largest variance; here those are
    the ball's flight, which does not depend on the opponent's target, so the target, carried by
    low-variance racket features, is lost and cannot be recovered from test observations. PLS
    (sklearn, on standardised features) picks the ``Dx`` projections of ``z`` of largest
    covariance with ``g``; like the PCA init, they are linear in ``z`` and scaled to unit
    variance, and only the training targets are used.

    Args:
        obs: ``[n, T, Dz]`` training plays.
        targets: ``[n]`` or ``[n, Dg]`` their targets.
        latent_dim: ``Dx`` (at most ``Dz``).

    Returns:
        ``[n T, Dx]`` initial latent states, the plays' frames in order.
    """
    obs = as_tensor(obs, "obs", ndim=3)
    targets = as_tensor(targets, "targets", dtype=obs.dtype)
    n, T, dz = obs.shape
    if targets.dim() not in (1, 2) or targets.shape[0] != n:
        raise ValueError(
            f"targets must be [n] or [n, Dg] with n = {n} plays, got {tuple(targets.shape)}"
        )
    g = targets.reshape(n, -1)
    if not isinstance(latent_dim, int) or not 1 <= latent_dim <= dz:
        raise ValueError(f"latent_dim must be an int in [1, Dz = {dz}], got {latent_dim!r}")
    frames = obs.reshape(n * T, dz).numpy()
    pls = PLSRegression(latent_dim, scale=True).fit(frames, g.repeat_interleave(T, 0).numpy())
    x = torch.as_tensor(pls.transform(frames), dtype=obs.dtype)
    return x / x.std(0).clamp_min(1e-8)
