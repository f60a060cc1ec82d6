"""The ball model's inputs: its constants, its state, and the ranges one call accepts.

:class:`BallParams` holds the constants of the SL ball model (:data:`DEFAULT_PARAMS` the
defaults), :class:`BallState` the position, velocity and spin of a batch of balls, and
:func:`make_state` validates a state against :data:`MAX_SPEED` and :data:`MAX_SPIN`. The private
checks here (state, params, step, duration, finite results) are the ones every public function of
:mod:`hgpdm_torch.robots.table_tennis.ball` runs on its arguments.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import NamedTuple

import torch

from hgpdm_torch.robots.table_tennis import geometry as geo
from hgpdm_torch.validation import as_tensor, check_choice, check_shape

__all__ = [
    "DEFAULT_PARAMS",
    "MAX_DURATION",
    "MAX_SPEED",
    "MAX_SPIN",
    "MAX_STEPS",
    "BallParams",
    "BallState",
    "make_state",
    "table_point",
]

_AIR_DENSITY = 1.2  # kg/m^3 at ~20 C, sea level
_MAX_DT = 0.05  # one event of each kind per step is assumed; 10 ms is the design step

#: Largest ball speed [m/s] a :class:`BallState` may start with. The fastest measured smashes
#: reach about 32 m/s (116 km/h); far beyond, drag and the contact events leave the model's range
#: and the integration overflows (a ball at 1e8 m/s gives NaN).
MAX_SPEED = 50.0
#: Largest ball spin [rad/s] a :class:`BallState` may start with: top players' loops reach about
#: 150 rev/s (940 rad/s); a table bounce adds up to ~21 rad/s per m/s of slip, so balls that the
#: model itself produced from states within :data:`MAX_SPEED` stay below it.
MAX_SPIN = 2000.0
#: Longest time [s] one call may simulate (``duration``, ``max_time``, ``flight_time``): every
#: table-tennis flight ends on the floor within ~2 s, and the model has no floor, so a longer
#: flight only measures a fall (and a typo like ``1e5`` s would run for hours).
MAX_DURATION = 10.0
#: Most integration steps one call may take (``duration / dt``): 10 s at 0.1 ms.
MAX_STEPS = 100_000


def _magnus_coefficient(radius: float, mass: float) -> float:
    # Lift of a spinning sphere F = 0.5 rho A C_L |v|^2 with C_L ~= r|w|/|v| (the lift coefficient
    # roughly equals the spin parameter S = r|w|/|v| for the S ~ 0.1-0.5 of table-tennis strokes)
    # gives F = 0.5 rho A r (w x v), i.e. k_m = rho pi r^3 / (2 m) ~= 5.6e-3 (dimensionless).
    return _AIR_DENSITY * math.pi * radius**3 / (2.0 * mass)


@dataclass(frozen=True)
class BallParams:
    """Constants of the ball model (SL simulator lineage; Mülling et al., 2011; ITTF rules).

    Attributes:
        gravity: ``g`` [m/s^2] (9.802 in SL).
        drag: ``k_d`` [1/m] of the drag acceleration ``-k_d |v| v`` (0.1414 in SL; equals
            ``0.5 C_D rho A / m`` with ``C_D ~= 0.5``).
        magnus: ``k_m`` (dimensionless) of the Magnus acceleration ``k_m (w x v)``; the SL
            simulator ignores spin, we use ``rho pi r^3 / (2 m) ~= 5.6e-3`` from a lift
            coefficient equal to the spin parameter ``r|w|/|v|``.
        table_restitution: factor ``-e`` on the normal velocity at a table bounce (0.88).
        table_friction_x: tangential velocity factor along ``x`` at a table bounce (0.72).
        table_friction_y: tangential velocity factor along ``y`` at a table bounce (0.68).
        racket_restitution: restitution of the racket contact along its normal (0.78).
        racket_spin: spin law of the racket contact: ``"rolling"`` (the ball leaves the
            gripping rubber rolling) or ``"kept"`` (frictionless, spin unchanged).
        net_restitution: restitution along ``y`` when the ball touches the net (our choice: the
            net is soft and absorbs most of the energy).
        net_damping: factor on the other velocity components and the spin at a net contact.
        radius: ball radius [m].
        mass: ball mass [kg].
        inertia_factor: moment of inertia over ``m r^2`` (2/3 for the thin shell of a ball).
    """

    gravity: float = geo.GRAVITY
    drag: float = 0.1414
    magnus: float = _magnus_coefficient(geo.BALL_RADIUS, geo.BALL_MASS)
    table_restitution: float = 0.88
    table_friction_x: float = 0.72
    table_friction_y: float = 0.68
    racket_restitution: float = 0.78
    racket_spin: str = "rolling"
    net_restitution: float = 0.1
    net_damping: float = 0.5
    radius: float = geo.BALL_RADIUS
    mass: float = geo.BALL_MASS
    inertia_factor: float = 2.0 / 3.0

    def __post_init__(self) -> None:
        for name in ("gravity", "drag", "magnus", "net_restitution", "net_damping"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value >= 0):
                raise ValueError(f"BallParams.{name} must be finite and >= 0, got {value}")
        for name in ("radius", "mass", "inertia_factor"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0):
                raise ValueError(f"BallParams.{name} must be finite and > 0, got {value}")
        for name in (
            "table_restitution",
            "table_friction_x",
            "table_friction_y",
            "racket_restitution",
        ):
            value = getattr(self, name)
            if not 0 <= value <= 1:
                raise ValueError(f"BallParams.{name} must lie in [0, 1], got {value}")
        check_choice(self.racket_spin, "racket_spin", ("rolling", "kept"))


DEFAULT_PARAMS = BallParams()


class BallState(NamedTuple):
    """State of a batch of balls; every field has shape ``[..., 3]``.

    Attributes:
        pos: centre position [m] in the world frame of :mod:`.geometry`.
        vel: linear velocity [m/s].
        spin: angular velocity [rad/s].
    """

    pos: torch.Tensor
    vel: torch.Tensor
    spin: torch.Tensor

    @property
    def batch_shape(self) -> torch.Size:
        """The leading batch dims ``...``."""
        return self.pos.shape[:-1]

    def where(self, mask: torch.Tensor, other: BallState) -> BallState:
        """``self`` where ``mask`` [...] is true, ``other`` elsewhere."""
        m = mask.unsqueeze(-1)
        return BallState(*(torch.where(m, a, b) for a, b in zip(self, other, strict=True)))


# --------------------------------------------------------------------------------------------
# construction and validation


def make_state(
    pos: object, vel: object, spin: object | None = None, *, dtype: torch.dtype | None = None
) -> BallState:
    """Validate and broadcast ``pos``, ``vel``, ``spin`` ([..., 3] each) into a :class:`BallState`.

    ``spin`` defaults to zeros. Raises ``ValueError`` for a wrong trailing shape, non-finite
    entries, a speed ``|vel|`` above :data:`MAX_SPEED` or a spin ``|spin|`` above :data:`MAX_SPIN`,
    and ``TypeError`` for non-numeric input.
    """
    p = as_tensor(pos, "pos", dtype=dtype, min_ndim=1)
    v = as_tensor(vel, "vel", dtype=dtype or p.dtype, device=p.device, min_ndim=1)
    w = (
        torch.zeros_like(v)
        if spin is None
        else as_tensor(spin, "spin", dtype=dtype or p.dtype, device=p.device, min_ndim=1)
    )
    for t, name in ((p, "pos"), (v, "vel"), (w, "spin")):
        check_shape(t, name, (3,))
    limits = ((v, "vel", "MAX_SPEED", MAX_SPEED, "m/s"), (w, "spin", "MAX_SPIN", MAX_SPIN, "rad/s"))
    for t, name, constant, bound, unit in limits:
        largest = float(t.norm(dim=-1).max()) if t.numel() else 0.0
        if largest > bound:
            raise ValueError(
                f"{name}: |{name}| must be at most {constant} = {bound:g} {unit}, "
                f"got {largest:.4g} {unit}"
            )
    try:
        p, v, w = torch.broadcast_tensors(p, v, w)
    except RuntimeError as err:
        raise ValueError(
            f"pos {tuple(p.shape)}, vel {tuple(v.shape)} and spin {tuple(w.shape)} must broadcast"
        ) from err
    return BallState(p.contiguous(), v.contiguous(), w.contiguous())


def check_state(state: BallState, name: str = "state") -> BallState:
    if not isinstance(state, BallState):
        raise TypeError(f"{name} must be a BallState, got {type(state).__name__}")
    return make_state(state.pos, state.vel, state.spin)


def check_params(params: BallParams) -> BallParams:
    if not isinstance(params, BallParams):
        raise TypeError(f"params must be a BallParams, got {type(params).__name__}")
    return params


def check_result(what: str, *tensors: torch.Tensor) -> None:
    """Raise if the integration left the floating-point range (states within the documented
    ranges never do; extreme :class:`BallParams` can)."""
    if not all(bool(torch.isfinite(t).all()) for t in tensors):
        raise ValueError(
            f"{what}: the ball integration produced non-finite values; the state or the "
            "BallParams are outside the model's range"
        )


def check_dt(dt: float, name: str = "dt") -> float:
    if not isinstance(dt, int | float) or not math.isfinite(dt) or not 0 < dt <= _MAX_DT:
        raise ValueError(f"{name} must be a number in (0, {_MAX_DT}] s, got {dt!r}")
    return float(dt)


def check_duration(value: object, name: str) -> float:
    """A positive number of seconds up to :data:`MAX_DURATION`."""
    if (
        isinstance(value, bool)
        or not isinstance(value, int | float)
        or not math.isfinite(value)
        or not 0 < value <= MAX_DURATION
    ):
        raise ValueError(
            f"{name} must be a number of seconds in (0, MAX_DURATION = {MAX_DURATION:g}], "
            f"got {value!r}"
        )
    return float(value)


def check_steps(n: int, name: str, dt: float) -> int:
    if n > MAX_STEPS:
        raise ValueError(
            f"{name} / dt = {n} steps exceeds MAX_STEPS = {MAX_STEPS}; take a larger dt "
            f"(at most {_MAX_DT} s; got {dt}) or a shorter {name}"
        )
    return n


def check_flight(
    state: BallState,
    params: BallParams,
    dt: float,
    duration: object,
    name: str,
    steps: Callable[[float], int],
) -> tuple[BallState, BallParams, float, float, int]:
    """The checked arguments of one simulated flight, as every simulating call takes them: the
    state, the ball constants, the step ``dt``, the simulated time ``duration`` (the argument
    ``name``) and its number of steps ``steps(duration / dt)`` (at most :data:`MAX_STEPS`)."""
    state, params, dt = check_state(state), check_params(params), check_dt(dt)
    duration = check_duration(duration, name)
    return state, params, dt, duration, check_steps(steps(duration / dt), name, dt)


def table_point(x: object, y: object) -> torch.Tensor:
    """Centre ``[..., 3]`` of a ball touching the table surface at ``(x, y)`` (each ``[...]``)."""
    xt = as_tensor(x, "x")
    yt = as_tensor(y, "y", dtype=xt.dtype, device=xt.device)
    xt, yt = torch.broadcast_tensors(xt, yt)
    return torch.stack([xt, yt, torch.full_like(xt, geo.TABLE_HEIGHT + geo.BALL_RADIUS)], -1)
