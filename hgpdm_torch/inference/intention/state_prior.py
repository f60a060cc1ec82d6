"""Prior of the first latent state of a window or stream, ``p(x_1)`` or ``p(x_1 | g)``.

``"marginal"`` (the default of both algorithms) is the empirical distribution of all training
latents, shared by every g; ``"class"`` (a discrete g) gives each value its own prior from the
training latents of its sequences (:func:`class_state_prior`).

Shapes: ``K`` intention values, ``Dx`` latent dims.
"""

from __future__ import annotations

from typing import Any

import torch

from ...linalg import psd_cholesky, symmetrize
from ...models import GPDM
from ...validation import as_tensor, check_choice

__all__ = ["STATE_PRIORS", "class_state_prior"]


def marginal_state_prior(
    model: GPDM, mu0: Any, Sigma0: Any, dtype: torch.dtype
) -> tuple[torch.Tensor, torch.Tensor]:
    """Prior of the first latent state: default the empirical marginal of the training latents
    (a window may start anywhere in a movement, not only at its first frame)."""
    x = model.latent.detach()
    mu = x.mean(0) if mu0 is None else as_tensor(mu0, "mu0", ndim=1, dtype=x.dtype, device=x.device)
    if Sigma0 is None:
        d = x - x.mean(0)
        Sigma = d.T @ d / max(x.shape[0] - 1, 1)
    else:
        Sigma = as_tensor(Sigma0, "Sigma0", ndim=2, dtype=x.dtype, device=x.device)
    dx = model.latent_dim
    if mu.shape != (dx,) or Sigma.shape != (dx, dx):
        raise ValueError(
            f"mu0 and Sigma0 must have shapes [{dx}] and [{dx}, {dx}], got "
            f"{tuple(mu.shape)} and {tuple(Sigma.shape)}"
        )
    psd_cholesky(Sigma, name="Sigma0")
    return mu.to(dtype), symmetrize(Sigma).to(dtype)


STATE_PRIORS = ("marginal", "class")


def class_state_prior(
    model: GPDM, values: torch.Tensor, dtype: torch.dtype
) -> tuple[torch.Tensor, torch.Tensor]:
    """Class-conditional prior of a window's first state, ``p(x_1 | g_k)`` for each code.

    The empirical mean and covariance of the training latents of the sequences with
    ``g = g_k`` (a window may start anywhere in a movement *of that class*). The covariance is
    shrunk towards the marginal one with the weight of ``Dx`` pseudo-frames,
    ``(n_k C_k + Dx C) / (n_k + Dx)``, so that a value with few frames still has a proper prior.

    Args:
        model: a fitted IDDM with a discrete g; values: ``[K, 1]`` codes (see
            :func:`intention_grid`); dtype: of the result.

    Returns:
        ``mu0 [K, Dx]``, ``Sigma0 [K, Dx, Dx]``.

    Raises:
        ValueError: a continuous g, or a code without training sequences.
    """
    if getattr(model, "intention", None) != "discrete":
        raise ValueError("state_prior='class' needs a discrete intention; use 'marginal'")
    x = model.latent.detach()
    frames = torch.repeat_interleave(model.intention_codes(), model.lengths)
    mu, Sigma = marginal_state_prior(model, None, None, x.dtype)
    dx = model.latent_dim
    means, covs = [], []
    for code in values[:, 0].long().tolist():
        xk = x[frames == code]
        if xk.shape[0] == 0:
            raise ValueError(f"intention {code} has no training sequences: no class prior")
        d = xk - xk.mean(0)
        means.append(xk.mean(0))
        covs.append(symmetrize((d.T @ d + dx * Sigma) / (xk.shape[0] + dx)))
    return torch.stack(means).to(dtype), torch.stack(covs).to(dtype)


def first_state_prior(
    model: GPDM, values: torch.Tensor, mu0: Any, Sigma0: Any, state_prior: str, dtype: torch.dtype
) -> tuple[torch.Tensor, torch.Tensor]:
    """``(mu0 [Dx], Sigma0 [Dx, Dx])`` for ``"marginal"``, ``([K, Dx], [K, Dx, Dx])`` for
    ``"class"``."""
    check_choice(state_prior, "state_prior", STATE_PRIORS)
    if state_prior == "marginal":
        return marginal_state_prior(model, mu0, Sigma0, dtype)
    if mu0 is not None or Sigma0 is not None:
        raise ValueError("give either mu0/Sigma0 or state_prior='class', not both")
    return class_state_prior(model, values, dtype)
