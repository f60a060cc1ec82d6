"""The Gaussian Process Dynamics Model (GPDM), the base of its extensions.

A GPDM explains J observed sequences ``Z^j [T_j, Dz]`` by latent trajectories ``X^j [T_j, Dx]``
with a GP measurement map ``h: x -> z`` and a GP transition map ``f: x_t -> x_{t+1}``, both
marginalised out (thesis Sec. 2.2). The latent states X, the measurement hyperparameters beta and
the output scales W are learned by minimising the negative log posterior of Eq. 6 with any torch
optimizer; the model defines the GPs and latents, and its objective
(:class:`~hgpdm_torch.models.objective.MAPObjective`, ``model.objective()``) computes Eq. 6
beside it. The transition kernel's hyperparameters alpha_1..3 are fixed to alpha-bar (Sec. 2.4.1)
unless ``learn_alpha=True``; the process noise alpha_4 can be learned under a weak log-normal prior
centred on alpha-bar (``learn_noise=True``). It is fixed by default, as in the thesis: on real
walks the MAP estimate collapses towards the noise floor and forecasts get worse (docs, Walkers);
choose it by cross-validation (:func:`hgpdm_torch.model_selection.cross_validate`) instead.

Subclasses change the transition inputs and kernel (:class:`~hgpdm_torch.models.HGPDM` appends
the exogenous variable g), or override :meth:`GPDM.initial_latents` and
:meth:`GPDM.build_transition_kernel`; the objective reads the hooks :meth:`GPDM.transition_inputs`,
:meth:`GPDM.transition_targets`, :meth:`GPDM.transition_blocks` and
:meth:`GPDM.transition_block_noise`, and a new term goes in a ``MAPObjective`` subclass named by
``objective_class``.
"""

from __future__ import annotations

import copy
import math
import os
from collections.abc import Mapping, Sequence
from typing import Any

import gpytorch
import numpy as np
import torch
from gpytorch.constraints import GreaterThan, Positive
from gpytorch.kernels import Kernel
from gpytorch.priors import NormalPrior, Prior

from ..fitting import FitResult, OptimizerLike
from ..gp import GPPosterior
from ..kernels import ALPHA_BAR, set_requires_grad, transition_kernel
from ..kernels import measurement_kernel as make_measurement_kernel
from ..validation import (
    as_tensor,
    check_choice,
    check_dtype,
    check_magnitude,
    check_sequences,
    positive_reals,
)
from .back_constraints import make_back_constraint
from .objective import MAPObjective
from .objective import fit as fit_model
from .persistence import SavedModel, save_model

__all__ = ["GPDM"]

#: Lower bound of both noise variances. It is the fixed jitter of the objective: it keeps the
#: kernel matrices of Eq. 4-5 positive definite in float64, so the loss is a smooth function of
#: the parameters and never needs jitter escalation (which would make it discontinuous).
NOISE_FLOOR = 1e-6
SequencesLike = Sequence[Any] | torch.Tensor
#: Hyperparameters with a prior in Eq. 6, the keys of the ``priors`` argument of :class:`GPDM`.
PRIOR_NAMES = ("beta1", "measurement_noise", "scales", "transition_noise", "transition_scales")


# Prior closures are module-level functions, not lambdas, so that models pickle (torch.save of the
# whole model, copy.deepcopy, multiprocessing). Each maps the module holding the prior to the log
# of the hyperparameter: the priors of Eq. 6 are log-normal, i.e. normal on these logs.
def _log_beta1(kernel: Kernel) -> torch.Tensor:
    """``log beta_1`` of an RBF measurement kernel (``beta_1 = lengthscale^-2``)."""
    return kernel.lengthscale.pow(-2).log()


def _log_measurement_noise(model: GPDM) -> torch.Tensor:
    return model.measurement_noise.log()


def _log_scales(model: GPDM) -> torch.Tensor:
    """``log w_d`` of the varying observed dims (a constant channel's scale is not modelled)."""
    return model.scales[model.varying].log()


def _log_transition_noise(model: GPDM) -> torch.Tensor:
    return model.transition_noise.log()


def _log_transition_scales(model: GPDM) -> torch.Tensor:
    """``log v_d`` of the transition GP's output scales (``scale_transitions=True``)."""
    return model.transition_scales.log()


def _check_priors(priors: Mapping[str, Prior | None] | None) -> dict[str, Prior | None]:
    """Validate the ``priors`` argument; returns the given entries (a copy)."""
    if priors is None:
        return {}
    if not isinstance(priors, Mapping):
        raise TypeError(
            f"priors must be a dict mapping some of {PRIOR_NAMES} to gpytorch priors (or None), "
            f"got {type(priors).__name__}"
        )
    unknown = [k for k in priors if k not in PRIOR_NAMES]
    if unknown:
        raise ValueError(f"unknown key(s) {unknown} in priors; expected some of {PRIOR_NAMES}")
    for key, prior in priors.items():
        if prior is not None and not isinstance(prior, Prior):
            raise TypeError(
                f"priors[{key!r}] must be a gpytorch Prior or None, got {type(prior).__name__}"
            )
    return dict(priors)


def _constrained_property(name: str, doc: str) -> property:
    """A model property reading and setting the constrained parameter ``name`` (a tensor; set
    from a float or a tensor, checked against its constraint)."""
    return property(
        lambda self: self._constrained(name),
        lambda self, value: self._set_constrained(name, value),
        doc=doc,
    )


class GPDM(gpytorch.Module, SavedModel):
    """Gaussian Process Dynamics Model with MAP learning (Eq. 3-6 without the exogenous g).

    Args:
        sequences: J observed sequences, each ``[T_j, Dz]`` with ``T_j >= 2`` (a list; lengths may
            differ), or a ``[J, T, Dz]`` tensor. No transition crosses a sequence boundary.
        latent_dim: ``Dx``.
        measurement: measurement kernel, ``"rbf"`` (Eq. 1), ``"linear"`` (Eq. 2), or a gpytorch
            ``Kernel`` over ``[..., Dx]`` latent states (used as it is, its own priors included
            in the loss; noise and output scales W are added as for the named kernels, the noise
            starting at 0.01). The moment-matching inference supports the kernels of
            :mod:`hgpdm_torch.expectations`. ``model.measurement`` is the name, or ``"custom"``.
            Any gpytorch kernel works everywhere: those without closed-form Gaussian-input
            expectations are integrated by quadrature (:mod:`hgpdm_torch.quadrature`).
        measurement_kernel: a gpytorch kernel object for the measurement GP, the same as
            passing it as ``measurement`` (give one of the two).
        transition_kernel: a gpytorch kernel object over the transition GP's inputs (``[x]``;
            ``[x, g]`` for an H-GPDM or IDDM, the code last for a discrete g) instead of the
            model's own (:meth:`build_transition_kernel`; ``alpha[:3]`` then do not apply).
            Its hyperparameters are learned with ``learn_alpha=True`` and kept at their values
            otherwise. For a discrete g, wrap it in
            :class:`~hgpdm_torch.kernels.DiscreteIntentionKernel` for dynamics of their own per
            value (block-diagonal ``K_x``); any other kernel reads the code as a number.
        priors: priors of the hyperparameters of Eq. 6, replacing the defaults key by key:
            ``"beta1"`` (width of the ``"rbf"`` measurement kernel), ``"measurement_noise"``,
            ``"scales"`` (each w_d of a varying dim), ``"transition_noise"`` (alpha_4, in the
            loss only while it is learned) and ``"transition_scales"`` (each v_d, with
            ``scale_transitions``). Each is a gpytorch ``Prior`` over the **natural log**
            of the hyperparameter, or ``None`` for none; the defaults
            (:meth:`default_priors`) are ``NormalPrior(0, 1)``, and
            ``NormalPrior(log alpha[3], NOISE_PRIOR_SD)`` for alpha_4.
        alpha: transition hyperparameters ``[alpha_1, alpha_2, alpha_3, alpha_4]``
            (default alpha-bar of Sec. 2.4.1).
        learn_alpha: learn the transition kernel's alpha_1..3 (and alpha_4) with the other
            parameters instead of keeping them at ``alpha``.
        learn_noise: learn the process noise alpha_4 with a weak log-normal prior centred on
            ``alpha[3]`` (log-space standard deviation :attr:`NOISE_PRIOR_SD`); default
            ``False`` keeps it fixed (the thesis's setting, better on real data so far).
        scale_transitions: learn an output scale ``v_d`` per latent dim for the transition GP
            (not in the thesis; default ``False``): Eq. 5 then models ``X_out diag(v)`` like Eq. 4
            models ``Z W``, so latent dim d has its own process noise ``alpha_4 / v_d^2`` (and
            prior variance ``k_x / v_d^2``). Every inference path takes it through the
            transition posterior's ``scale``.
        learn_measurement_width: learn the RBF measurement kernel's width beta_1 (default);
            ``False`` keeps it at its initial value. With free latents the MAP width shrinks as
            the fit proceeds until the measurement GP interpolates single training frames,
            which hurts predictions for new recordings (docs, Walkers).
        back_constraint: ``None`` (free latent states, the default), ``"kernel"`` or ``"mlp"``:
            latent states ``X = f(Z)`` of the standardised observations, with the map's
            parameters learned instead of X (:mod:`~hgpdm_torch.models.back_constraints`); or a
            module of your own with ``forward([..., Dz]) -> [..., Dx]`` and
            ``initialise(inputs, latent)``.
        init: ``"pca"`` (default) or a ``[M, Dx]`` tensor of initial latent states, M the total
            number of frames.
        dtype: ``torch.float64`` (recommended for GP algebra) or ``torch.float32``, the dtype
            of data and parameters.

    Raises:
        TypeError: ``dtype`` is not torch.float32/float64, ``alpha`` is not a sequence of
            numbers, or another argument has the wrong type.
        ValueError: ``alpha`` is not 4 positive finite numbers; ``sequences`` are malformed
            (:func:`~hgpdm_torch.validation.check_sequences`), constant, or of a magnitude the
            dtype cannot carry (:func:`~hgpdm_torch.validation.check_magnitude`: beyond about
            1e150 or below 1e-150 in float64); or another argument is out of range.

    Attributes:
        latent: ``[M, Dx]`` latent states of all frames, sequences concatenated: a parameter, or
            the back-constraint map of the observations (``latent_map``).
        observations: ``[M, Dz]`` buffer; ``obs_mean`` ``[Dz]`` its column means.
        measurement_kernel, transition_kernel: gpytorch kernels (noise terms excluded).
    """

    transition_kind = "gpdm"
    #: constructor arguments that may be objects a saved file cannot hold (see :meth:`save`)
    object_arguments = (
        "measurement",
        "measurement_kernel",
        "transition_kernel",
        "priors",
        "back_constraint",
    )
    #: Standard deviation of the log-normal prior of a learned process noise alpha_4.
    NOISE_PRIOR_SD = 2.0
    #: whether the transition GP has an output scale per latent dim (class default: models
    #: pickled before the option existed have none)
    scale_transitions = False
    #: the class of :meth:`objective`, the negative log posterior of Eq. 6: a subclass of
    #: :class:`~hgpdm_torch.models.objective.MAPObjective` changes the terms of every fit
    objective_class: type[MAPObjective] = MAPObjective

    def __init__(
        self,
        sequences: SequencesLike,
        latent_dim: int = 3,
        *,
        measurement: str | Kernel = "rbf",
        measurement_kernel: Kernel | None = None,
        transition_kernel: Kernel | None = None,
        alpha: Sequence[float] = ALPHA_BAR,
        priors: Mapping[str, Prior | None] | None = None,
        learn_alpha: bool = False,
        learn_noise: bool = False,
        learn_measurement_width: bool = True,
        scale_transitions: bool = False,
        back_constraint: str | torch.nn.Module | None = None,
        init: str | torch.Tensor = "pca",
        dtype: torch.dtype = torch.float64,
    ) -> None:
        super().__init__()
        if not isinstance(latent_dim, int) or latent_dim < 1:
            raise ValueError(f"latent_dim must be a positive int, got {latent_dim!r}")
        for arg, value in (
            ("measurement_kernel", measurement_kernel),
            ("transition_kernel", transition_kernel),
        ):
            if value is not None and not isinstance(value, Kernel):
                raise TypeError(f"{arg} must be a gpytorch Kernel, got {type(value).__name__}")
        if measurement_kernel is not None:
            if not (isinstance(measurement, str) and measurement == "rbf"):
                raise ValueError(
                    "give the measurement kernel as measurement= or measurement_kernel="
                )
            measurement = measurement_kernel
        if isinstance(measurement, Kernel):
            name = "custom"
        elif isinstance(measurement, str):
            name = check_choice(measurement, "measurement", ("rbf", "linear"))
        else:
            raise TypeError(
                "measurement must be 'rbf', 'linear' or a gpytorch Kernel, got "
                f"{type(measurement).__name__}"
            )
        if not isinstance(scale_transitions, bool | np.bool_):
            raise TypeError(f"scale_transitions must be a bool, got {scale_transitions!r}")
        dtype = check_dtype(dtype)
        alpha = positive_reals(alpha, "alpha", 4)
        given_priors = _check_priors(priors)
        if given_priors.get("beta1") is not None and name != "rbf":
            raise ValueError(
                f"priors['beta1'] applies to measurement='rbf' only, got measurement={name!r}; "
                "give a kernel of your own its priors when you build it"
            )
        hyper_priors = {**self.default_priors(alpha[3]), **given_priors}
        seqs = check_sequences(sequences, dtype)
        self.latent_dim = latent_dim
        self.measurement = name
        self.alpha_init = alpha
        #: the constructor arguments :meth:`config` does not hold: a custom kernel, priors or
        #: back-constraint module (saving records plain priors, asks the user for objects)
        self._object_arguments = [
            arg
            for arg, custom in (
                (
                    "measurement" if measurement_kernel is None else "measurement_kernel",
                    name == "custom",
                ),
                ("transition_kernel", transition_kernel is not None),
                ("priors", bool(given_priors)),
                ("back_constraint", isinstance(back_constraint, torch.nn.Module)),
            )
            if custom
        ]
        self._config: dict[str, Any] = {
            "latent_dim": latent_dim,
            "measurement": name,
            "alpha": list(alpha),
            "learn_alpha": bool(learn_alpha),
            "learn_noise": bool(learn_noise),
            "learn_measurement_width": bool(learn_measurement_width),
            "back_constraint": back_constraint,
        }
        for arg in self._object_arguments:  # saved in the state; rebuilt by the user's code
            self._config.pop(arg, None)

        z = torch.cat(seqs, dim=0)
        check_magnitude(z, "sequences")
        device = z.device  # the model is built where its data are (and moves with .to)
        lengths = torch.tensor([s.shape[0] for s in seqs], device=device)
        starts = torch.cumsum(lengths, 0) - lengths
        src = torch.cat(
            [
                torch.arange(s, s + n - 1, device=device)
                for s, n in zip(starts.tolist(), lengths.tolist(), strict=True)
            ]
        )
        self.register_buffer("observations", z)
        self.register_buffer("obs_mean", z.mean(0))
        self.register_buffer("lengths", lengths)
        self.register_buffer("first_index", starts)
        self.register_buffer("src_index", src)
        self.register_buffer(
            "seq_of_src",
            torch.repeat_interleave(torch.arange(len(seqs), device=device), lengths - 1),
        )

        latent = self._initial(init, z - z.mean(0))
        self.latent_map: torch.nn.Module | None = None
        if back_constraint is None:
            self.register_parameter("latent", torch.nn.Parameter(latent))
        else:
            # The map sees standardised frames (training statistics, fixed): channel units and
            # the learned output scales W do not move the latent positions.
            std = z.std(0)
            inputs = (z - z.mean(0)) / torch.where(std > 0, std, torch.ones_like(std))
            self.register_buffer("map_inputs", inputs)
            self.latent_map = make_back_constraint(back_constraint, inputs, latent)

        # Measurement: beta (kernel width for "rbf", and noise) and the output scales W carry
        # log-normal priors, i.e. 1/2 ||log beta||^2 + 1/2 ||log w||^2 in Eq. 6 (by default).
        self.measurement_kernel = make_measurement_kernel(measurement)
        if name == "rbf":
            self.measurement_kernel.raw_lengthscale.requires_grad_(bool(learn_measurement_width))
            self._register_log_prior(self.measurement_kernel, "beta1", hyper_priors, _log_beta1)
        self.register_parameter(
            "raw_measurement_noise", torch.nn.Parameter(z.new_zeros((), dtype=dtype))
        )
        self.register_constraint("raw_measurement_noise", GreaterThan(NOISE_FLOOR))
        self.measurement_noise = 0.1 if name == "linear" else 0.01
        self._register_log_prior(self, "measurement_noise", hyper_priors, _log_measurement_noise)
        # Constant channels (e.g. fixed joints) carry no information about x: the measurement GP
        # models the others and predicts a constant channel's value exactly. "Constant" is
        # relative to the channel's magnitude, so data in small units are not mistaken for it.
        std = z.std(0)
        varying = std > 1e-10 * z.abs().amax(0)
        if not bool(varying.any()):
            raise ValueError("every observed dim of sequences is constant; nothing to model")
        self.register_buffer("varying", varying)
        self.register_parameter("raw_scales", torch.nn.Parameter(torch.zeros_like(std)))
        self.register_constraint("raw_scales", Positive())
        self.scales = torch.where(varying, 1.0 / std.clamp_min(1e-300), torch.ones_like(std))
        self._register_log_prior(self, "scales", hyper_priors, _log_scales)

        self.transition_kernel = (
            self.build_transition_kernel() if transition_kernel is None else transition_kernel
        )
        self.register_parameter(
            "raw_transition_noise", torch.nn.Parameter(z.new_zeros((), dtype=dtype))
        )
        self.register_constraint("raw_transition_noise", GreaterThan(NOISE_FLOOR))
        self.transition_noise = alpha[3]
        self._register_log_prior(self, "transition_noise", hyper_priors, _log_transition_noise)
        self.scale_transitions = bool(scale_transitions)
        if self.scale_transitions:
            self._config["scale_transitions"] = True
            self.register_parameter(
                "raw_transition_scales", torch.nn.Parameter(z.new_zeros(latent_dim, dtype=dtype))
            )
            self.register_constraint("raw_transition_scales", Positive())
            self.transition_scales = 1.0
            self._register_log_prior(
                self, "transition_scales", hyper_priors, _log_transition_scales
            )
        self.learn_alpha = learn_alpha
        self.learn_noise = learn_noise or learn_alpha
        self.to(device=device, dtype=dtype)  # the kernels' parameters too

    # ----------------------------------------------------------------- construction hooks
    @classmethod
    def default_priors(cls, alpha4: float = ALPHA_BAR[3]) -> dict[str, Prior]:
        """The default priors of Eq. 6 over the log of each hyperparameter (new objects).

        Args:
            alpha4: the initial process noise ``alpha[3]``, the centre of its prior.

        Returns:
            ``{"beta1", "measurement_noise", "scales", "transition_scales": NormalPrior(0, 1),
            "transition_noise": NormalPrior(log alpha4, NOISE_PRIOR_SD)}``.
        """
        return {
            "beta1": NormalPrior(0.0, 1.0),
            "measurement_noise": NormalPrior(0.0, 1.0),
            "scales": NormalPrior(0.0, 1.0),
            "transition_noise": NormalPrior(math.log(alpha4), cls.NOISE_PRIOR_SD),
            "transition_scales": NormalPrior(0.0, 1.0),
        }

    @staticmethod
    def _register_log_prior(
        module: gpytorch.Module, key: str, priors: Mapping[str, Prior | None], closure: Any
    ) -> None:
        """Register ``priors[key]`` (if not None) as ``<key>_prior`` of ``module``."""
        if priors[key] is not None:
            module.register_prior(f"{key}_prior", priors[key], closure)

    def build_transition_kernel(self) -> Kernel:
        """The transition kernel ``k_x`` without noise; override to use another kernel."""
        return transition_kernel(self.transition_kind, self.latent_dim, alpha=self.alpha_init)

    def initial_latents(self, centred: torch.Tensor) -> torch.Tensor:
        """PCA initialisation of the latent states.

        Args:
            centred: ``[M, Dz]`` observations minus their column means.

        Returns:
            ``[M, Dx]`` projections on the leading principal directions, scaled to unit variance.
        """
        dz = centred.shape[1]
        if self.latent_dim > dz:
            raise ValueError(
                f"latent_dim ({self.latent_dim}) must not exceed Dz ({dz}) for PCA init"
            )
        # floors relative to the largest spread, so the result does not depend on the units
        tiny = torch.finfo(centred.dtype).tiny
        std = centred.std(0)
        scaled = centred / std.clamp_min(1e-10 * float(std.max()) + tiny)
        _, _, v = torch.linalg.svd(scaled, full_matrices=False)
        proj = scaled @ v[: self.latent_dim].T
        spread = proj.std(0)
        return proj / spread.clamp_min(1e-10 * float(spread.max()) + tiny)

    def _initial(self, init: str | torch.Tensor, centred: torch.Tensor) -> torch.Tensor:
        if isinstance(init, str):
            check_choice(init, "init", ("pca",))
            return self.initial_latents(centred)
        x = as_tensor(init, "init", ndim=2, dtype=centred.dtype, device=centred.device)
        if x.shape != (centred.shape[0], self.latent_dim):
            raise ValueError(
                f"init must have shape [M, Dx] = [{centred.shape[0]}, {self.latent_dim}], "
                f"got {tuple(x.shape)}"
            )
        return x.clone()

    # ----------------------------------------------------------------- parameters
    @property
    def latent(self) -> torch.Tensor:
        """``[M, Dx]`` latent states: the free parameter, or ``latent_map(map_inputs)``."""
        if self.latent_map is not None:
            return self.latent_map(self.map_inputs)
        if "latent" not in self._parameters:
            raise AttributeError("latent")
        return self._parameters["latent"]

    def _constrained(self, name: str) -> torch.Tensor:
        return getattr(self, f"raw_{name}_constraint").transform(getattr(self, f"raw_{name}"))

    def _set_constrained(self, name: str, value: float | torch.Tensor) -> None:
        """Set ``raw_<name>`` so that the constrained value is ``value`` (a float, a 0-dim
        tensor, or a tensor broadcastable to the parameter's shape).

        Raises:
            TypeError: ``value`` is not a real number or tensor.
            ValueError: ``value`` has the wrong shape, is NaN or inf, or lies outside the
                constraint's open range (for the noises: at or below :data:`NOISE_FLOOR`).
        """
        raw = getattr(self, f"raw_{name}")
        constraint = getattr(self, f"raw_{name}_constraint")
        if isinstance(value, bool) or (
            isinstance(value, torch.Tensor) and (value.dtype == torch.bool or value.is_complex())
        ):
            raise TypeError(f"{name} must be a real number or tensor, got {value!r}")
        try:
            target = torch.as_tensor(value, dtype=raw.dtype, device=raw.device).detach()
        except (TypeError, ValueError, RuntimeError) as err:
            raise TypeError(f"{name} must be a real number or tensor, got {value!r}") from err
        try:
            target = target.expand_as(raw)
        except RuntimeError as err:
            raise ValueError(
                f"{name} must be a scalar or broadcast to shape {tuple(raw.shape)}, got shape "
                f"{tuple(target.shape)}"
            ) from err
        lower, upper = float(constraint.lower_bound), float(constraint.upper_bound)
        new_raw = constraint.inverse_transform(target)
        bad = ~(torch.isfinite(target) & (target > lower) & (target < upper))
        bad |= ~torch.isfinite(new_raw)
        if bool(bad.any()):
            shown = target[bad].tolist()
            shown = shown[0] if raw.dim() == 0 else shown
            raise ValueError(
                f"{name} must be finite and in the open range ({lower:g}, {upper:g}), got {shown!r}"
            )
        with torch.no_grad():
            raw.copy_(new_raw)

    measurement_noise = _constrained_property(
        "measurement_noise",
        "White noise of the measurement kernel: beta_2 of Eq. 1, or beta_1 of Eq. 2.",
    )
    scales = _constrained_property(
        "scales", "``[Dz]`` diagonal of W, the per-dimension output scales."
    )

    @property
    def transition_scales(self) -> torch.Tensor:
        """``[Dx]`` output scales ``v_d`` of the transition GP (ones without
        ``scale_transitions``): latent dim d has process noise ``alpha_4 / v_d^2``."""
        if not self.scale_transitions:
            return self.latent.new_ones(self.latent_dim)
        return self._constrained("transition_scales")

    @transition_scales.setter
    def transition_scales(self, value: float | torch.Tensor) -> None:
        if not self.scale_transitions:
            raise ValueError("transition_scales needs a model built with scale_transitions=True")
        self._set_constrained("transition_scales", value)

    def transition_posterior_scale(self) -> torch.Tensor | None:
        """``[Dx]`` predictive scale ``1 / v_d`` of the transition posterior, or ``None``
        without ``scale_transitions`` (the posterior's default of ones)."""
        if not self.scale_transitions:
            return None
        return 1.0 / self.transition_scales.detach()

    transition_noise = _constrained_property(
        "transition_noise", "alpha_4, the white noise of the transition kernel."
    )

    @property
    def learn_alpha(self) -> bool:
        """Whether the transition kernel's alpha_1..3 are learned (default: fixed)."""
        return bool(self._config["learn_alpha"])

    @learn_alpha.setter
    def learn_alpha(self, flag: bool) -> None:
        set_requires_grad(self.transition_kernel, bool(flag))
        self._config["learn_alpha"] = bool(flag)
        if flag:
            self.learn_noise = True

    @property
    def learn_noise(self) -> bool:
        """Whether the process noise alpha_4 is learned (its prior enters the loss only then)."""
        return self.raw_transition_noise.requires_grad

    @learn_noise.setter
    def learn_noise(self, flag: bool) -> None:
        self.raw_transition_noise.requires_grad_(bool(flag))
        self._config["learn_noise"] = bool(flag)

    # ----------------------------------------------------------------- data views
    @property
    def num_sequences(self) -> int:
        """J, the number of training sequences."""
        return int(self.lengths.numel())

    @property
    def obs_dim(self) -> int:
        """Dz, the observation dimension."""
        return int(self.observations.shape[1])

    def sequences(self) -> list[torch.Tensor]:
        """The training sequences, each ``[T_j, Dz]``."""
        return list(torch.split(self.observations, self.lengths.tolist()))

    def latent_sequences(self) -> list[torch.Tensor]:
        """The latent trajectories, each ``[T_j, Dx]`` (detached)."""
        return list(torch.split(self.latent.detach(), self.lengths.tolist()))

    def transition_inputs(self, latent: torch.Tensor) -> torch.Tensor:
        """Inputs of the transition GP: ``[m, Dx]`` states ``X_{1:T-1}`` of every sequence."""
        return latent[self.src_index]

    def transition_targets(self, latent: torch.Tensor) -> torch.Tensor:
        """Targets of the transition GP: ``[m, Dx]`` states ``X_{2:T}`` of every sequence."""
        return latent[self.src_index + 1]

    # ----------------------------------------------------------------- objective
    def objective(self) -> MAPObjective:
        """A new :class:`~hgpdm_torch.models.objective.MAPObjective` (``objective_class``) of
        this model: the negative log posterior of Eq. 6, computed beside the model."""
        return self.objective_class(self)

    def measurement_nll(self, latent: torch.Tensor | None = None) -> torch.Tensor:
        """``-log p(Z | X, beta, W)`` of Eq. 4, by :meth:`objective` (X: ``latent`` or the
        model's, ``[M, Dx]``)."""
        return self.objective().measurement_nll(latent)

    def transition_block_noise(self, rows: torch.Tensor) -> torch.Tensor:
        """Process noise alpha_4 of the block of transition pairs ``rows`` (one of
        :meth:`transition_blocks`): :attr:`transition_noise` here; a subclass may give each
        block its own (:class:`~hgpdm_torch.models.HGPDM` with ``noise_per_value``)."""
        return self.transition_noise

    def transition_nll(self, latent: torch.Tensor | None = None) -> torch.Tensor:
        """``-log p(X | g)`` of Eq. 5, by :meth:`objective`: GP transitions plus the unit
        Gaussian on first states (X: ``latent`` or the model's, ``[M, Dx]``)."""
        return self.objective().transition_nll(latent)

    def transition_blocks(self) -> list[torch.Tensor]:
        """Row sets of independent blocks of ``K_x`` (one block: all transitions).

        Subclasses whose transition kernel is block-diagonal (a discrete g) return one index set
        per block, so Eq. 5 factorises into smaller Cholesky factors.
        """
        return [torch.arange(self.src_index.numel(), device=self.src_index.device)]

    def prior_nll(self) -> torch.Tensor:
        """``-sum log p(theta)`` over every registered gpytorch prior, by :meth:`objective`."""
        return self.objective().prior_nll()

    def loss(self) -> torch.Tensor:
        """The negative log posterior ``L`` of Eq. 6 (with all normalising constants):
        ``self.objective()()``.

        Raises:
            FloatingPointError: ``L`` is not finite.
        """
        return self.objective()()

    def forward(self) -> torch.Tensor:
        """Calling the model returns :meth:`loss` (so ``torch.func.functional_call`` works)."""
        return self.loss()

    def log_posterior(self) -> float:
        """``-loss()`` as a float (no gradient)."""
        with torch.no_grad():
            return float(-self.loss())

    # ----------------------------------------------------------------- fitting
    def fit(
        self,
        steps: int = 100,
        *,
        optimizer: OptimizerLike = "lbfgs",
        lr: float | None = None,
        progress: bool = False,
        **options: Any,
    ) -> FitResult:
        """MAP fit (Eq. 3): minimise :meth:`loss` over X, beta, W (and alpha if learned).

        The convenience for :func:`hgpdm_torch.models.objective.fit` with the default objective
        (:meth:`objective`): :func:`hgpdm_torch.fitting.fit_map`'s L-BFGS with a strong-Wolfe
        line search (or any torch optimizer), explicit convergence criteria, recovery from
        failed steps and rollback to the best state on divergence. A fit that does not converge
        emits a :class:`~hgpdm_torch.fitting.ConvergenceWarning` (``warn=False`` silences it).

        Args:
            steps: maximum optimizer steps (for L-BFGS each has a line search).
            optimizer: ``"lbfgs"`` (default), ``"adam"``, an optimizer over this model's
                parameters, or a callable ``params -> optimizer``.
            lr: learning rate for ``"lbfgs"`` (default 1) or ``"adam"`` (default 0.01).
            progress: show a tqdm progress bar.
            **options: ``ftol``, ``gtol``, ``patience``, ``max_eval``, ``restarts``,
                ``restart_scale``, ``seed``, ``warn`` of :func:`~hgpdm_torch.fitting.fit_map`.

        Returns:
            A :class:`~hgpdm_torch.fitting.FitResult` (loss history, converged flag, reason).
        """
        return fit_model(
            self, self.objective(), optimizer, steps, lr=lr, progress=progress, **options
        )

    # ----------------------------------------------------------------- posteriors
    def measurement_posterior(self, points: int | None = None) -> GPPosterior:
        """The measurement GP ``x -> z`` conditioned on the fitted model (detached).

        Predictions are in the units of the observations: mean ``k^T K_z^-1 (Z - mean) + mean``,
        variance per dim ``sigma^2(x) / w_d^2``.

        Args:
            points: route the GP through at most this many pseudo-inputs, the latents of evenly
                spaced training frames (the DTC sparse GP of :meth:`GPPosterior.sparse`, on all
                the data, with the fitted hyperparameters): prediction at a Gaussian input then
                costs ``points^2`` instead of ``N^2``. ``None`` (default) or ``points >= N``:
                the exact GP.
        """
        n = self.latent.shape[0]
        if points is not None and (
            isinstance(points, bool) or not isinstance(points, int) or points < 2
        ):
            raise ValueError(f"points must be an int >= 2 or None, got {points!r}")
        with torch.no_grad():
            exact = GPPosterior(
                self.measurement_kernel,
                self.latent.detach(),
                self.observations - self.obs_mean,
                self.measurement_noise.detach(),
                scale=1.0 / self.scales.detach(),
                offset=self.obs_mean,
            )
            if points is None or points >= n:
                return exact
            rows = torch.linspace(0, n - 1, points, device=self.latent.device).round().long()
            return exact.sparse(self.latent.detach()[rows])

    def transition_posterior(self) -> GPPosterior:
        """The transition GP ``[x_t, g] -> x_{t+1}`` conditioned on the fitted model (detached)."""
        with torch.no_grad():
            x = self.latent.detach()
            return GPPosterior(
                self.transition_kernel,
                self.transition_inputs(x),
                self.transition_targets(x),
                self.transition_noise.detach(),
                scale=self.transition_posterior_scale(),
            )

    def _rollout_inputs(self, x: torch.Tensor, g: Any, step: int) -> torch.Tensor:
        """The transition GP's input at ``x [..., Dx]``, the ``step``-th of a rollout."""
        if g is not None:
            raise ValueError("a GPDM has no exogenous variable; pass g=None")
        return x

    def rollout(self, x0: torch.Tensor, steps: int, g: Any = None) -> torch.Tensor:
        """Mean rollout of the latent dynamics: ``x_{t+1} = E[f(x_t, g)]``.

        Args:
            x0: ``[..., Dx]`` initial states.
            steps: number of transitions.
            g: the exogenous variable (HGPDM only).

        Returns:
            ``[..., steps + 1, Dx]`` latent trajectory, ``x0`` first.
        """
        if not isinstance(steps, int) or steps < 0:
            raise ValueError(f"steps must be a non-negative int, got {steps!r}")
        x = as_tensor(x0, "x0", min_ndim=1, dtype=self.latent.dtype)
        if x.shape[-1] != self.latent_dim:
            raise ValueError(
                f"x0 must have trailing dim Dx={self.latent_dim}, got {tuple(x.shape)}"
            )
        post = self.transition_posterior()
        out = [x]
        for step in range(steps):
            x, _ = post.predict(self._rollout_inputs(x, g, step))
            out.append(x)
        return torch.stack(out, dim=-2)

    # ----------------------------------------------------------------- persistence
    def config(self) -> dict[str, Any]:
        """Constructor options (other than data) that rebuild this model, all plain values (a
        deep copy); a custom measurement kernel or back-constraint module is left out."""
        return copy.deepcopy(self._config)

    def _data_arguments(self) -> dict[str, Any]:
        """Constructor arguments holding training data: ``sequences``, each ``[T_j, Dz]``.

        :func:`~hgpdm_torch.models.load_model` rebuilds the model from these and
        :meth:`config`, then checks that they equal the same method's result on the loaded
        ``state_dict``: subclasses that add data arguments extend it.
        """
        return {"sequences": [s.clone() for s in self.sequences()]}

    def save(self, path: str | os.PathLike[str]) -> None:
        """Save the model to ``path``: class name, plain configuration, training data and
        ``state_dict`` (:mod:`hgpdm_torch.models.persistence` has the layout).

        Load it with :func:`~hgpdm_torch.models.load_model` or :meth:`load`. A model built with
        a custom measurement kernel, priors or back-constraint module (or a subclass's object
        argument) is saved too, its parameters in the state; the file cannot rebuild those
        objects, so load it into a model your code builds with the same ones:
        ``load_model(path, model=GPDM(sequences, 2, measurement=kernel))``.

        Raises:
            TypeError: the model's class is not registered
                (:func:`~hgpdm_torch.models.register_model`).
            FileNotFoundError: the folder of ``path`` does not exist (``NotADirectoryError``:
                it is a file; ``IsADirectoryError``: ``path`` is a folder).
        """
        save_model(self, path)

    def _saved_dtype(self) -> torch.dtype:
        return self.latent.dtype
