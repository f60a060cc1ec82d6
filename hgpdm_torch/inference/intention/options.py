"""The choices of an :class:`~hgpdm_torch.inference.OnlineIntentionFilter`, in groups.

Each group is one decision of the filter's algorithm, a small frozen object that checks its
values when it is made and can be passed around, compared and reused by several filters:

- :class:`BeliefUpdate`: how the belief over g takes each step's evidence (forgetting,
  temperature, prior; Algorithm 3.2, lines 10-11), with the update itself (:meth:`step`);
- :class:`Evidence`: what evidence a step gives about g (the GP-ADF predictive likelihood or the
  thesis's bound, and how the bound mixes the K predictions);
- :class:`StatePrior`: the first latent state's prior (marginal, or one per discrete value);
- :class:`TransitionPath`: how the transition moments of the K values are computed (shared or
  generic path, exact or sparse GP);
- :class:`ObservationPolicy`: which observation rows are refused, and whether a refused row or a
  failed stream raises instead of being rejected or restarted.

:class:`FilterOptions` holds one of each (a filter's ``options``).

The filter takes either a group or its flat keywords (``OnlineIntentionFilter(model,
forgetting=0.1)`` and ``OnlineIntentionFilter(model, belief=BeliefUpdate(forgetting=0.1))`` are
the same filter), never both for one group; :meth:`FilterOptions.from_keywords` does that,
reading which flat keyword belongs to which group from the groups' own fields.
"""

from __future__ import annotations

from dataclasses import dataclass, field, fields
from typing import Any

import numpy as np
import torch

from ...calibration import check_temperature
from ...intention_belief import belief_step
from ...observations import DEFAULT_OUTLIER_SD
from ...validation import check_choice, check_outlier_sd, real_scalar
from .state_prior import STATE_PRIORS
from .transition import TRANSITIONS

__all__ = [
    "BeliefUpdate",
    "Evidence",
    "FilterOptions",
    "ObservationPolicy",
    "StatePrior",
    "TransitionPath",
]


def _same(a: Any, b: Any) -> bool:
    """Whether two field values are equal: array-likes (a prior, ``mu0``, ``Sigma0``) entry for
    entry in float64, anything else by ``==``."""
    if a is b:
        return True
    arrays = (torch.Tensor, np.ndarray, list, tuple)
    if isinstance(a, arrays) or isinstance(b, arrays):
        try:
            x, y = (torch.as_tensor(v).detach().cpu().to(torch.float64) for v in (a, b))
        except (TypeError, ValueError, RuntimeError):
            return False
        return x.shape == y.shape and torch.equal(x, y)
    return bool(a == b)


class _Group:
    """Equality of an option group field by field (:func:`_same`); groups are not hashable."""

    def __eq__(self, other: object) -> bool:
        if type(other) is not type(self):
            return NotImplemented
        return all(_same(getattr(self, f.name), getattr(other, f.name)) for f in fields(self))

    __hash__ = None  # type: ignore[assignment]


@dataclass(frozen=True, eq=False)
class BeliefUpdate(_Group):
    """How the log belief takes each step's evidence: ``B_t = (1 - eps) B_{t-1} + E_t(g) / T``,
    normalised (Algorithm 3.2, lines 10-11, with the evidence temperature of
    :mod:`~hgpdm_torch.calibration`).

    Attributes:
        forgetting: ``eps`` in ``[0, 1)``; 0 keeps all evidence (plain Bayes recursion).
        temperature: ``T > 0``; 1 is the thesis's recursion, ``T > 1`` a less confident belief.
        prior: ``[K]`` prior probabilities of the intention values (``None``: uniform).
    """

    forgetting: float = 0.2
    temperature: float = 1.0
    prior: Any = None

    def __post_init__(self) -> None:
        eps = real_scalar(self.forgetting, "forgetting (epsilon)")
        if not 0.0 <= eps < 1.0:
            raise ValueError(f"forgetting (epsilon) must be in [0, 1), got {self.forgetting!r}")
        object.__setattr__(self, "forgetting", eps)
        object.__setattr__(self, "temperature", check_temperature(self.temperature))

    def step(
        self, log_belief: torch.Tensor, evidence: torch.Tensor, observed: torch.Tensor
    ) -> torch.Tensor:
        """``[S, K]`` normalised ``B_t`` from ``log_belief [S, K]``, the step's ``evidence [S,
        K]`` and ``observed [S]`` (an unobserved step only forgets):
        :func:`~hgpdm_torch.intention_belief.belief_step`."""
        return belief_step(log_belief, evidence, observed, self.forgetting, self.temperature)


@dataclass(frozen=True, eq=False)
class Evidence(_Group):
    """What evidence ``E_t(g)`` a step gives about g.

    Attributes:
        kind: ``"predictive"`` (the GP-ADF predictive likelihood ``log q(z_t | z_{1:t-1}, g)``)
            or ``"bound"`` (the thesis's ``Q_{t-1}(g)``, Algorithm 3.2 as printed).
        mixing: (``"bound"``) how the K predictions are combined under the belief: ``"grid"``
            (moment-matched mixture) or ``"gaussian"`` (the transition moment matched at
            ``[x, g]`` with a Gaussian g; continuous g only, Sec. 3.4.2).
        relinearize: (``"bound"``) score ``Q`` at the smoothed ``q(x_{t-1} | z_{1:t})`` instead
            of the filtered one; ``mixing="gaussian"`` always does.
    """

    kind: str = "predictive"
    mixing: str = "grid"
    relinearize: bool = False

    def __post_init__(self) -> None:
        check_choice(self.kind, "evidence", ("predictive", "bound"))
        check_choice(self.mixing, "mixing", ("grid", "gaussian"))
        if self.mixing == "gaussian" and self.kind != "bound":
            raise ValueError("mixing='gaussian' needs a continuous g and evidence='bound'")
        object.__setattr__(self, "relinearize", bool(self.relinearize) or self.mixing == "gaussian")


@dataclass(frozen=True, eq=False)
class StatePrior(_Group):
    """The first latent state's prior.

    Attributes:
        kind: ``"marginal"`` (``N(mu0, Sigma0)`` for every value) or, for a discrete g,
            ``"class"`` (each value's own prior ``p(x_1 | g)``,
            :func:`~hgpdm_torch.inference.intention.class_state_prior`; the first observation
            then scores the values).
        mu0: ``[Dx]`` mean of the marginal prior (``None``: the training latents' mean).
        Sigma0: ``[Dx, Dx]`` its covariance (``None``: the training latents' covariance).
    """

    kind: str = "marginal"
    mu0: Any = None
    Sigma0: Any = None

    def __post_init__(self) -> None:
        check_choice(self.kind, "state_prior", STATE_PRIORS)


@dataclass(frozen=True, eq=False)
class TransitionPath(_Group):
    """How the transition moments of the K intention values are computed
    (:func:`~hgpdm_torch.inference.intention.transition.transition_moments`).

    Attributes:
        path: ``"shared"`` (the IDDM's fast path), ``"generic"`` (moment matching at ``[x,
            g_k]`` for any supported kernel) or ``"auto"`` (shared where the kernel allows it).
        inducing: pseudo-inputs of a sparse (DTC) transition GP (Sec. 3.3.3), or ``None`` for
            the exact GP.
        inducing_values: distinct intention values among the pseudo-inputs (continuous g;
            ``None``: ``round(sqrt(inducing))``).
    """

    path: str = "auto"
    inducing: int | None = None
    inducing_values: int | None = None

    def __post_init__(self) -> None:
        check_choice(self.path, "transition", TRANSITIONS)
        # inducing and inducing_values are checked where the sparse GP is built
        # (hgpdm_torch.gp_shared.sparse_posterior), against the model's training data


@dataclass(frozen=True, eq=False)
class ObservationPolicy(_Group):
    """Which observation rows are refused, and what a refusal or a numerical failure does.

    Attributes:
        outlier_sd: plausibility threshold in training standard deviations per channel
            (:class:`~hgpdm_torch.observations.ObservationCheck`); ``None`` refuses only
            non-finite values and partly NaN rows.
        strict: raise a ``ValueError`` instead of rejecting a bad row (for its stream only) or
            restarting a stream whose update fails numerically.
    """

    outlier_sd: float | None = DEFAULT_OUTLIER_SD
    strict: bool = False

    def __post_init__(self) -> None:
        object.__setattr__(self, "outlier_sd", check_outlier_sd(self.outlier_sd))
        if not isinstance(self.strict, bool):
            raise TypeError(f"strict must be a bool, got {self.strict!r}")


@dataclass(frozen=True)
class FilterOptions:
    """All choices of one filter, a group each (the filter's ``options``); pass its groups to
    another filter to make the same choices: ``OnlineIntentionFilter(model, grid,
    **vars(options))``."""

    belief: BeliefUpdate = field(default_factory=BeliefUpdate)
    evidence: Evidence = field(default_factory=Evidence)
    state_prior: StatePrior = field(default_factory=StatePrior)
    transition: TransitionPath = field(default_factory=TransitionPath)
    observations: ObservationPolicy = field(default_factory=ObservationPolicy)

    @classmethod
    def from_keywords(cls, groups: dict[str, Any], flat: dict[str, Any]) -> FilterOptions:
        """A filter's options from its keywords.

        Args:
            groups: each group's keyword (``"belief"``, ``"evidence"``, ...) -> its value: a
                group object, ``None``, or (``evidence``, ``state_prior``, ``transition``) the
                value of the group's first field, e.g. ``"bound"``.
            flat: the flat keywords -> their values; a group's flat keywords are its fields,
                and one at its field's default counts as not given.

        Raises:
            ValueError: a group object and flat keywords of that group that differ from their
                defaults, naming them; or a bad value (from the group's own checks).
            TypeError: a group keyword that is neither its group, ``None`` nor (where the group
                has one) its first field's value.
        """
        out = {}
        for f in fields(cls):
            group = f.default_factory
            own = {g.name: flat[g.name] for g in fields(group) if g.name in flat}
            out[f.name] = _resolve(group, f.name, groups[f.name], own)
        return cls(**out)


#: The flat keyword of a group that takes the group's first field (e.g. ``evidence="bound"``).
_LEADING = {"evidence": "kind", "state_prior": "kind", "transition": "path"}


def _given(value: Any, default: Any) -> bool:
    """Whether a flat keyword's ``value`` differs from its field's ``default`` (then it was
    given: a keyword left at its default says nothing)."""
    if default is None or value is None:
        return value is not default
    if isinstance(value, torch.Tensor):
        return True
    try:
        return bool(value != default)
    except (TypeError, ValueError):  # an array: compared elementwise
        return True


def _resolve(group: type, name: str, given: Any, flat: dict[str, Any]) -> Any:
    """The ``group`` object of a filter from its keyword ``name`` (value ``given``) and the flat
    keywords ``flat`` of the group's fields (:meth:`FilterOptions.from_keywords`)."""
    defaults = {f.name: f.default for f in fields(group)}
    passed = {k: v for k, v in flat.items() if _given(v, defaults[k])}
    if isinstance(given, group):
        if passed:
            raise ValueError(
                f"pass {name}={group.__name__}(...) or the keywords {sorted(passed)}, not both"
            )
        return given
    if name in _LEADING:
        passed[_LEADING[name]] = defaults[_LEADING[name]] if given is None else given
    elif given is not None:
        raise TypeError(f"{name} must be a {group.__name__} or None, got {given!r}")
    return group(**{**flat, **passed})
