"""A GP intention model's online beliefs with the interface of a :class:`BeliefMixture` member.

:class:`~hgpdm_torch.inference.BeliefMixture` mixes models that give ``beliefs(obs, grid,
log_prior)``, ``stream(batch_size, grid, log_prior)`` and ``grid(values)``, as
:class:`~hgpdm_torch.models.LinearIDDM` does. :class:`FilterBeliefs` gives a fitted GP model
(IDDM, H-GPDM) the same three through :class:`OnlineIntentionFilter` (Algorithm 3.2) with fixed
filter options, so the GP IDDM and the linear models can be mixed.

Shapes: ``B`` streams, ``T`` frames, ``K`` intention values, ``Dz`` observed dims.
"""

from __future__ import annotations

from typing import Any

import torch

from ...intention_belief import IntentionBelief
from ...models import HGPDM
from ...validation import as_tensor
from .grid import intention_grid
from .online import OnlineIntentionFilter

__all__ = ["FilterBeliefs"]


class FilterBeliefs:
    """The online-filtered beliefs of a fitted GP intention model, as a mixture member.

    Args:
        model: a fitted :class:`~hgpdm_torch.models.HGPDM` / ``IDDM``.
        **filter_options: keyword arguments of :class:`OnlineIntentionFilter` other than
            ``intentions``, ``batch_size`` and ``prior`` (e.g. ``forgetting``,
            ``temperature``), used for every belief.

    ``stream`` returns the filter itself (``update``, ``reset``); the look-ahead sampling of a
    mixture stream (``repeat``, ``sample_next``) needs members that have it, as
    :class:`~hgpdm_torch.models.LinearIDDM`'s streams do.
    """

    def __init__(self, model: HGPDM, **filter_options: Any) -> None:
        if not isinstance(model, HGPDM):
            raise TypeError(f"model must be a fitted HGPDM/IDDM, got {type(model).__name__}")
        taken = {"intentions", "batch_size", "prior"} & filter_options.keys()
        if taken:
            raise TypeError(
                f"FilterBeliefs sets {sorted(taken)} itself (grid, streams and log_prior of "
                "each call); pass the other filter options only"
            )
        self.model, self.options = model, dict(filter_options)
        if model.intention == "discrete" or model.intention_dim == 1:
            self.stream(1)  # bad filter options fail here, not at the first belief

    def grid(self, values: Any = None) -> torch.Tensor:
        """``[K, Dg]`` intention values (:func:`intention_grid`: all codes, or 25 values over the
        training range of a continuous ``Dg = 1`` g, by default)."""
        return intention_grid(self.model, values)

    def stream(
        self, batch_size: int = 1, grid: Any = None, log_prior: Any = None
    ) -> OnlineIntentionFilter:
        """The online filter for ``batch_size`` streams over ``grid`` with prior
        ``softmax(log_prior)`` (default uniform)."""
        values = self.grid(grid)
        prior = None
        if log_prior is not None:
            lp = as_tensor(log_prior, "log_prior", ndim=1, dtype=values.dtype, allow_nan=False)
            if lp.shape[0] != len(values) or not bool(torch.isfinite(lp).any()):
                raise ValueError(
                    f"log_prior must be [K = {len(values)}] with a finite entry, got "
                    f"{tuple(lp.shape)}"
                )
            prior = lp.softmax(0)
        return OnlineIntentionFilter(
            self.model, values, batch_size=batch_size, prior=prior, **self.options
        )

    def beliefs(self, obs: Any, grid: Any = None, log_prior: Any = None) -> IntentionBelief:
        """The filter's belief after every frame of each stream.

        Args:
            obs: ``[B, T, Dz]`` or ``[T, Dz]`` streams, each from the frame the training
                sequences start at.
            grid: intention values (default :meth:`grid`).
            log_prior: ``[K]`` log prior over the grid (default uniform).

        Returns:
            :class:`IntentionBelief` with ``[B, T, K]`` (``[T, K]``) probabilities and, for a
            continuous g, the posterior mean and sd.
        """
        z = as_tensor(obs, "obs", dtype=self.model.latent.dtype, allow_nan=True)
        if z.dim() not in (2, 3):
            raise ValueError(f"obs must be [B, T, Dz] or [T, Dz], got {tuple(z.shape)}")
        single = z.dim() == 2
        z = z[None] if single else z
        values = self.grid(grid)
        f = self.stream(z.shape[0], values, log_prior)
        log_prob = torch.stack([f.update(z[:, t]).log_prob for t in range(z.shape[1])], 1)
        log_prob = log_prob[0] if single else log_prob
        return IntentionBelief.from_log(log_prob, values, self.model.intention == "continuous")
