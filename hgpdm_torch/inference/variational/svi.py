r"""VB inference through Pyro: the window's generative model as a Pyro model and
``pyro.infer.SVI`` on the :class:`~hgpdm_torch.inference.variational.guide.MeanFieldGuide`
(thesis Sec. 2.3, Eq. 10-17).

The Pyro model has the latent site ``"x"`` ``[..., K, T, Dx]`` with density

    log N(x_1 | m_1, S_1) + sum_t log N(x_{t+1} | m_x(x_t, g), sigma_x^2(mu_t, g) I)

(an improper flat base with this density added by ``pyro.factor``), a continuous g's prior
``N(g | m_g, S_g)``, and the observed site ``"z"`` with ``N(z_t | m_z(x_t), sigma_z^2(mu_t)
diag(scale^2))``. The variances are the plug-ins of Eq. 15-17 at the guide's means, the GP means
are evaluated at the sampled states (no kernel expectations), so its ELBO against the guide is the
negative free energy ``F(q, g)`` of Eq. 13 exactly, and ``Trace_ELBO`` gives an independent
Monte-Carlo estimate of the closed form.

Two losses for SVI (:func:`fit_svi`):

- ``"closed_form"`` (default): ``-sum F`` from
  :meth:`~hgpdm_torch.inference.variational.window.WindowModel.free_energy`, exact and
  deterministic;
- ``"trace_elbo"``: ``pyro.infer.Trace_ELBO``, the reparameterised Monte-Carlo estimate of the
  same objective (noisy gradients, a check on the closed form).

Shapes: ``T`` window length, ``K`` candidate values of g, ``Dx`` latent dim, ``Dz`` observation
dim, ``Dg`` dim of a continuous g; ``...`` leading batch dims (windows).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import pyro
import pyro.distributions as dist
import torch
from pyro.distributions import constraints
from pyro.nn import pyro_method

from ...progress import trange
from ...validation import check_choice
from .guide import MeanFieldGuide, batch_plates
from .window import WindowModel

__all__ = ["SVIOptions", "closed_form_loss", "fit_svi", "pyro_model"]

SVI_LOSSES = ("closed_form", "trace_elbo")

# q's parameters as sites of Pyro's parameter store (what SVI's optimiser steps)
_q_as_pyro_params = pyro_method(MeanFieldGuide.q)


@dataclass(frozen=True)
class SVIOptions:
    """Settings of ``method="svi"`` in :meth:`VariationalInference.infer
    <hgpdm_torch.inference.variational.VariationalInference.infer>`.

    Attributes:
        loss: ``"closed_form"`` (``-F`` of Eq. 13 in closed form) or ``"trace_elbo"`` (Pyro's
            Monte-Carlo ELBO of :func:`pyro_model`).
        lr: initial Adam learning rate (``pyro.optim.ClippedAdam``); the default suits a start
            near the optimum (the Laplace start of ``infer`` for a discrete g): from far off
            (``newton_steps=0``, or a continuous g, whose q(g) the Laplace start leaves at its
            prior) use a larger one, e.g. 0.05, or more steps.
        final_lr: learning rate after the last step (geometric decay from ``lr``): Adam's steps do
            not shrink with the gradient, so a decaying rate is what lets it settle in the stiff
            directions of F.
        num_particles: particles per step of ``"trace_elbo"`` (vectorised).
    """

    loss: str = "closed_form"
    lr: float = 5e-3
    final_lr: float = 1e-5
    num_particles: int = 16

    def __post_init__(self) -> None:
        check_choice(self.loss, "loss", SVI_LOSSES)
        if not (self.lr > 0 and self.final_lr > 0):
            raise ValueError(f"lr and final_lr must be positive, got {self.lr}, {self.final_lr}")
        if not (isinstance(self.num_particles, int) and self.num_particles > 0):
            raise ValueError(f"num_particles must be a positive int, got {self.num_particles!r}")


def pyro_model(
    window: WindowModel,
    z: torch.Tensor,
    observed: torch.Tensor,
    values: torch.Tensor,
    guide: MeanFieldGuide,
) -> None:
    r"""Pyro model of a window whose ELBO against ``guide`` is ``F(q, g)`` (Eq. 13, 15-17).

    Args:
        window: the model's :class:`~hgpdm_torch.inference.variational.window.WindowModel`.
        z: ``[..., T, Dz]`` window and observed: ``[..., T]`` its mask (validated).
        values: ``[..., K]`` candidate codes.
        guide: the :class:`MeanFieldGuide` (``loc [..., K, T, Dx]``), whose means set the
            plug-in variances.
    """
    T, dx = z.shape[-2], window.latent_dim
    lead = guide.loc.shape[:-2]
    with batch_plates(lead, z.device):
        x = pyro.sample("x", dist.ImproperUniform(constraints.real, lead, (T, dx)))
        mu = guide.loc
        h, f = window.h, window.transition_gp(values)
        scale2 = window.measurement.scale.pow(2)
        var_z = h.var_at_mean(mu)[..., None] * scale2  # plug-ins at the means [..., K, T, Dz]
        m_z = h.predict_point(x)[0] + window.measurement.offset
        inputs, plug = x[..., :-1, :], mu[..., :-1, :]
        if window.kind == "continuous":
            prior_g = dist.MultivariateNormal(window.g_prior_mean, scale_tril=window.g_chol)
            g = pyro.sample("g", prior_g.expand(lead))  # [..., 1, Dg], like the guide's
            gx = g[..., None, :].expand(*inputs.shape[:-1], window.g_dim)
            inputs = torch.cat([inputs, gx], -1)
            gm = guide.g_loc[..., None, None, :].expand(*plug.shape[:-1], window.g_dim)
            plug = torch.cat([plug, gm], -1)
        m_x = f.predict_point(inputs)[0]
        var_x = f.var_at_mean(plug)[..., None] * window.transition.scale.pow(2)
        log_p = dist.Normal(m_x, var_x.sqrt()).log_prob(x[..., 1:, :]).sum((-1, -2))
        x1 = dist.MultivariateNormal(window.x1_mean, scale_tril=window.x1_chol)
        pyro.factor("latent_dynamics", log_p + x1.log_prob(x[..., 0, :]))
        zc = torch.nan_to_num(z)[..., None, :, :].expand(m_z.shape)
        mask = observed[..., None, :, None].expand(m_z.shape)
        lik = dist.Normal(m_z, var_z.sqrt()).mask(mask).to_event(2)
        pyro.sample("z", lik, obs=zc)


def closed_form_loss(
    window: WindowModel, z: torch.Tensor, observed: torch.Tensor, values: torch.Tensor
) -> Callable[..., torch.Tensor]:
    """A ``pyro.infer.SVI`` loss ``(model, guide, *args) -> -sum F`` in closed form.

    ``F [..., K]`` is :meth:`~hgpdm_torch.inference.variational.window.WindowModel.free_energy`
    of the guide's parameters, read as Pyro parameters (:meth:`MeanFieldGuide.q` in the guide's
    Pyro context, so that SVI finds and updates them); the model is not run.
    """

    def loss(model: object, guide: MeanFieldGuide, *args: object, **kwargs: object) -> torch.Tensor:
        loc, tril, g_loc, g_tril = _q_as_pyro_params(guide)
        return -window.free_energy(z, observed, loc, tril, values, g_loc, g_tril).sum()

    return loss


def fit_svi(
    window: WindowModel,
    z: torch.Tensor,
    observed: torch.Tensor,
    values: torch.Tensor,
    guide: MeanFieldGuide,
    steps: int,
    options: SVIOptions | None = None,
    progress: bool = False,
) -> list[float]:
    """Maximise F over ``guide`` with ``pyro.infer.SVI`` (Adam with a decaying rate).

    Runs in a scope of Pyro's parameter store of its own (the global store is left as it was);
    the guide's parameters are updated in place.

    Args:
        window: the model's :class:`~hgpdm_torch.inference.variational.window.WindowModel`.
        z: ``[..., T, Dz]`` window, observed: ``[..., T]`` its mask, values: ``[..., K]``.
        guide: the :class:`MeanFieldGuide` to fit (``loc [..., K, T, Dx]``).
        steps: SVI iterations.
        options: :class:`SVIOptions` (default: closed-form loss).
        progress: show a progress bar.

    Returns:
        The SVI loss (``-sum F``, or its estimate) after each step.
    """
    options = options or SVIOptions()
    if options.loss == "closed_form":
        loss = closed_form_loss(window, z, observed, values)
    else:
        loss = pyro.infer.Trace_ELBO(num_particles=options.num_particles, vectorize_particles=True)
    lrd = (options.final_lr / options.lr) ** (1.0 / max(steps, 1))
    optim = pyro.optim.ClippedAdam({"lr": options.lr, "lrd": lrd, "clip_norm": 1e6})

    def model(*args: object) -> None:
        pyro_model(window, z, observed, values, guide)

    history = []
    with pyro.get_param_store().scope():
        svi = pyro.infer.SVI(model, guide, optim, loss)
        for _ in trange(steps, disable=not progress, desc="VB (SVI)", leave=False):
            history.append(svi.step())
    return history
