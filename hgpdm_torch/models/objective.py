"""The MAP objective of the GP models, apart from the model, and the fit that minimises it.

As gpytorch keeps a model, its likelihood and its ``ExactMarginalLogLikelihood`` apart, a
:class:`~hgpdm_torch.models.GPDM` (and :class:`~hgpdm_torch.models.HGPDM`,
:class:`~hgpdm_torch.models.IDDM`) defines its GPs and latent states, and a
:class:`MAPObjective` beside it computes the negative log posterior ``L`` of Eq. 6 (thesis):

- the **measurement term** ``-log p(Z | X, beta, W)`` of Eq. 4,
- the **transition term** ``-log p(X | g)`` of Eq. 5 (GP transitions plus the unit Gaussian on
  each sequence's first state),
- the **prior term** ``-sum log p(theta)`` over the model's registered gpytorch priors.

This module is the only place that algebra lives; ``model.loss()``, ``model.measurement_nll``,
``model.transition_nll`` and ``model.prior_nll`` delegate to ``model.objective()``.

The objective reads the model's structural hooks, which subclasses override to change Eq. 5:
``transition_inputs`` / ``transition_targets`` (the GP's input and output rows; the H-GPDM
appends g), ``transition_blocks`` (independent blocks of ``K_x``, one per value of a discrete
g) and ``transition_block_noise`` (a block's alpha_4, e.g. ``noise_per_value``). To change a
*term* itself, subclass :class:`MAPObjective` and set the model class's ``objective_class`` to
it: ``model.loss()``, ``model.fit()`` and the delegating methods then use it.

Training is user code if you want it: ``objective = model.objective()`` is a ``torch.nn.Module``
over the model's parameters, ``objective()`` the scalar to minimise with any torch optimizer.
:func:`fit` runs the toolkit's guarded loop (:func:`hgpdm_torch.fitting.fit_map`: L-BFGS with
line-search recovery, convergence criteria, rollback) for a model, an objective and an optimizer;
``model.fit()`` is the convenience that calls it with the default objective and optimizer.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING, Any

import torch

from ..fitting import FitResult, OptimizerLike, fit_map
from ..gaussian import LOG_2PI
from ..linalg import gaussian_nll

if TYPE_CHECKING:
    from .gpdm import GPDM

__all__ = ["FIT_OPTIONS", "MAPObjective", "fit"]

#: options of :func:`fit` (and ``model.fit``) passed on to :func:`~hgpdm_torch.fitting.fit_map`
FIT_OPTIONS = frozenset(
    {"ftol", "gtol", "patience", "max_eval", "restarts", "restart_scale", "seed", "warn"}
)


class MAPObjective(torch.nn.Module):
    """The negative log posterior ``L`` of Eq. 6 of a GP model, a module beside it.

    Like gpytorch's ``ExactMarginalLogLikelihood`` it holds the model (its ``parameters()`` are
    the model's) and calling it evaluates the objective at the model's current parameters.

    Args:
        model: a :class:`~hgpdm_torch.models.GPDM` or subclass.

    Example:
        >>> objective = MAPObjective(model)  # or model.objective()
        >>> opt = torch.optim.Adam(model.parameters(), lr=0.01)
        >>> for _ in range(100):
        ...     opt.zero_grad()
        ...     loss = objective()
        ...     loss.backward()
        ...     opt.step()
    """

    def __init__(self, model: GPDM) -> None:
        super().__init__()
        self.model = model

    # ----------------------------------------------------------------- terms of Eq. 6
    def measurement_nll(self, latent: torch.Tensor | None = None) -> torch.Tensor:
        """``-log p(Z | X, beta, W)`` of Eq. 4, constants included (X: ``latent`` or the
        model's, ``[M, Dx]``)."""
        model = self.model
        x = model.latent if latent is None else latent
        m, dz = model.observations.shape
        k = model.measurement_kernel(x).to_dense()
        k = k + model.measurement_noise * torch.eye(m, dtype=x.dtype, device=x.device)
        y = ((model.observations - model.obs_mean) * model.scales)[:, model.varying]
        nll = gaussian_nll(k, y, name="measurement kernel matrix K_z")
        return nll - m * model.scales[model.varying].log().sum()

    def gaussian_sequence_nll(
        self, inputs: torch.Tensor, targets: torch.Tensor, noise: torch.Tensor | None = None
    ) -> torch.Tensor:
        """``-log N(targets; 0, K_x(inputs) + alpha_4 I)`` per output column, summed (Eq. 5);
        ``noise`` replaces alpha_4 (default the model's ``transition_noise``). With
        ``scale_transitions`` column d is ``N(v_d targets_d; 0, K_x + alpha_4 I)``, whose
        density in ``targets_d`` carries the Jacobian ``v_d^m`` (m rows), as Eq. 4's W."""
        model = self.model
        noise = model.transition_noise if noise is None else noise
        k = model.transition_kernel(inputs).to_dense()
        k = k + noise * torch.eye(k.shape[0], dtype=k.dtype, device=k.device)
        if not model.scale_transitions:
            return gaussian_nll(k, targets, name="transition kernel matrix K_x")
        v = model.transition_scales
        nll = gaussian_nll(k, targets * v, name="transition kernel matrix K_x")
        return nll - targets.shape[0] * v.log().sum()

    def transition_nll(self, latent: torch.Tensor | None = None) -> torch.Tensor:
        """``-log p(X | g)`` of Eq. 5: GP transitions, block by block of the model's
        ``transition_blocks()``, plus the unit Gaussian on first states (X: ``latent`` or the
        model's, ``[M, Dx]``)."""
        model = self.model
        x = model.latent if latent is None else latent
        first = x[model.first_index]
        inputs, targets = model.transition_inputs(x), model.transition_targets(x)
        nll = sum(
            self.gaussian_sequence_nll(
                inputs[rows], targets[rows], model.transition_block_noise(rows)
            )
            for rows in model.transition_blocks()
        )
        return nll + 0.5 * first.pow(2).sum() + 0.5 * first.numel() * LOG_2PI

    def prior_nll(self) -> torch.Tensor:
        """``-sum log p(theta)`` over every registered gpytorch prior of the model (log-normal
        on beta, W by default); a fixed alpha_4's prior is left out."""
        model = self.model
        total = torch.zeros((), dtype=model.latent.dtype, device=model.latent.device)
        for name, module, prior, closure, _ in model.named_priors():
            if name == "transition_noise_prior" and not model.learn_noise:
                continue  # a fixed alpha_4 is not a parameter of the posterior
            total = total - prior.log_prob(closure(module)).sum()
        return total

    # ----------------------------------------------------------------- the objective
    def terms(self) -> dict[str, torch.Tensor]:
        """The named terms of ``L``: ``{"measurement", "transition", "prior"}``, each a scalar
        with gradients (a back-constraint map is evaluated once for both latent terms)."""
        x = self.model.latent
        return {
            "measurement": self.measurement_nll(x),
            "transition": self.transition_nll(x),
            "prior": self.prior_nll(),
        }

    def forward(self) -> torch.Tensor:
        """The negative log posterior ``L`` of Eq. 6 (with all normalising constants): the sum
        of :meth:`terms`, in their order.

        Raises:
            FloatingPointError: ``L`` is not finite.
        """
        values = iter(self.terms().values())
        value = next(values)
        for term in values:
            value = value + term
        if not bool(torch.isfinite(value)):
            raise FloatingPointError(
                "the negative log posterior is not finite; lower the learning rate or check "
                "the data for outliers"
            )
        return value


def fit(
    model: GPDM,
    objective: Callable[[], torch.Tensor] | None = None,
    optimizer: OptimizerLike | None = "lbfgs",
    steps: int = 100,
    *,
    lr: float | None = None,
    progress: bool = False,
    **options: Any,
) -> FitResult:
    """MAP fit of ``model``: minimise ``objective()`` over its trainable parameters.

    Runs :func:`hgpdm_torch.fitting.fit_map` (L-BFGS with a strong-Wolfe line search, or any
    torch optimizer; explicit convergence criteria; recovery from failed steps; rollback to the
    best state on divergence), then records ``model.fit_seconds`` and ``model.fit_result`` and
    puts the model in eval mode. ``model.fit(steps, ...)`` calls this with the default
    objective; subclasses may add steps around it there (the H-GPDM's ``noise_per_value``
    estimates its per-value noises after the fit), which this function does not run.

    Args:
        model: a :class:`~hgpdm_torch.models.GPDM` or subclass.
        objective: the scalar to minimise, a :class:`MAPObjective` of ``model`` or any callable
            returning a scalar tensor of its parameters (default ``model.objective()``).
        optimizer: ``"lbfgs"`` (default; also ``None``), ``"adam"``, an optimizer over the
            model's parameters, or a callable ``params -> optimizer``.
        steps: maximum optimizer steps (for L-BFGS each has a line search).
        lr: learning rate for ``"lbfgs"`` (default 1) or ``"adam"`` (default 0.01).
        progress: show a tqdm progress bar.
        **options: ``ftol``, ``gtol``, ``patience``, ``max_eval``, ``restarts``,
            ``restart_scale``, ``seed``, ``warn`` (default ``True``) of
            :func:`~hgpdm_torch.fitting.fit_map`.

    Returns:
        A :class:`~hgpdm_torch.fitting.FitResult` (loss history, converged flag, reason).

    Raises:
        ValueError: an unknown option, or a :class:`MAPObjective` of another model.
    """
    unknown = set(options) - FIT_OPTIONS
    if unknown:
        raise ValueError(
            f"unknown fit option(s) {sorted(unknown)}; expected some of {sorted(FIT_OPTIONS)}"
        )
    if objective is None:
        objective = model.objective()
    elif isinstance(objective, MAPObjective) and objective.model is not model:
        raise ValueError("objective is a MAPObjective of another model; build it over this one")
    elif not callable(objective):
        raise TypeError(f"objective must be callable, got {type(objective).__name__}")
    options.setdefault("warn", True)
    result = fit_map(
        model,
        steps,
        optimizer="lbfgs" if optimizer is None else optimizer,
        lr=lr,
        progress=progress,
        loss=objective,
        **options,
    )
    model.fit_seconds = result.seconds
    model.fit_result = result
    model.eval()
    return result
