"""What the window inference engines share: :class:`WindowEngine`, the base of
:class:`~hgpdm_torch.inference.variational.VariationalInference` and
:class:`~hgpdm_torch.inference.map.MAPInference`.

Both see a fitted model through one :class:`~hgpdm_torch.inference.variational.window.WindowModel`
(GPs, priors, objectives) and start from the same initial states; they differ in what they fit
to a window (a mean-field q, or point estimates).
"""

from __future__ import annotations

import torch

from ...models import GPDM
from .initial import initial_guess
from .window import WindowModel

__all__ = ["WindowEngine"]


class WindowEngine:
    """The window model of a fitted GPDM / H-GPDM, built once for every window an engine infers.

    Args:
        model: a fitted :class:`~hgpdm_torch.models.GPDM` (no g), or an
            :class:`~hgpdm_torch.models.HGPDM` / ``IDDM`` with a discrete g or (where the
            engine takes one, :attr:`continuous_g`) a continuous g.
        x1_prior: ``(mean [Dx], cov [Dx, Dx])`` of ``p(x_1)``, the first state of a window. The
            default is the Gaussian fitted to all training latents, since a window may start
            anywhere in a movement (the thesis's ``N(m_1, S_1)``).
        g_prior: for a discrete g, ``[K]`` prior probabilities (default uniform); for a continuous
            g, ``(mean [Dg], cov [Dg, Dg])`` (default: fitted to the training intentions).
        measurement_points: route the measurement GP through at most this many pseudo-inputs,
            the latents of evenly spaced training frames (the DTC sparse GP on all the data:
            each window's kernel expectations cost ``M^2`` instead of ``N^2``;
            :meth:`~hgpdm_torch.models.GPDM.measurement_posterior`). Default: the exact GP,
            the thesis's model.

    Attributes:
        window: the :class:`~hgpdm_torch.inference.variational.window.WindowModel` (GPs, priors,
            objectives) the engines share.
        model, kind, values, measurement, transition, latent_dim, obs_dim: the window model's.
    """

    #: whether the engine infers a continuous g (the MAP baseline does not: the thesis
    #: compares MAP only for known or discrete g)
    continuous_g: bool = True

    def __init__(
        self,
        model: GPDM,
        *,
        x1_prior: tuple[object, object] | None = None,
        g_prior: object = None,
        measurement_points: int | None = None,
    ) -> None:
        self.window = w = WindowModel(
            model, x1_prior=x1_prior, g_prior=g_prior, measurement_points=measurement_points
        )
        if w.kind == "continuous" and not self.continuous_g:
            name = type(self).__name__
            raise ValueError(f"{name} supports a GPDM or a discrete g, not a continuous g")
        self.model, self.kind, self.values = w.model, w.kind, w.values
        self.measurement, self.transition = w.measurement, w.transition
        self.latent_dim, self.obs_dim = w.latent_dim, w.obs_dim

    def initial_guess(
        self, z: torch.Tensor, values: torch.Tensor, init: str = "nearest"
    ) -> tuple[torch.Tensor | None, ...]:
        """Initial q(x) [and q(g)] of a window (Algorithm 2.2, step 1; MAP's initial states are
        its means ``loc [..., K, T, Dx]``): see
        :func:`~hgpdm_torch.inference.variational.initial.initial_guess`."""
        return initial_guess(self.window, z, values, init)
