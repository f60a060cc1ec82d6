"""Table-tennis ball physics: flight, table bounce, net, racket contact, aiming (thesis Sec. 4.3).

The thesis evaluates its robot player in the SL simulator of the Barrett WAM table-tennis setup
(Mülling et al., 2011; Kober/Mülling lineage), whose ball model this module reproduces in batched
torch (float64, any leading batch dims ``...``):

* flight: ``dv/dt = -g e_z - k_d |v| v + k_m (w x v)`` (gravity, quadratic drag, Magnus force), the
  spin ``w`` constant in flight; integrated with RK4;
* table bounce: normal velocity times ``-0.88``, tangential velocity factors 0.72 (x) and 0.68 (y)
  (SL constants), extended to spin by applying the factors to the contact point's slip velocity
  and giving the spin the matching angular impulse (for a spin-free ball this is exactly the SL
  law);
* net: a vertical plane at ``y = 0`` that the ball must clear by its radius; a ball that touches
  it loses most of its speed;
* racket: reflection of the ball's velocity about the racket normal in the racket's frame with
  restitution 0.78 (the SL racket law); the rubber's grip sets the spin so that the ball leaves
  the face rolling (SL has no spin; a frictionless, spin-keeping contact is an option).

Table and net contacts are events located inside a step to machine precision (a safeguarded
Newton search on the RK4 flow), so results do not depend on the step size for ``dt <= 10 ms``.

A single float64 ball on the CPU (an unbatched state) is integrated by :class:`ScalarBall`, the same
arithmetic on Python floats (tensor operations on three numbers cost more than the numbers); batches
are tensors. One call simulates at most :data:`MAX_DURATION` seconds in at most :data:`MAX_STEPS`
steps.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from functools import lru_cache
from typing import NamedTuple

import numpy as np
import torch
from tqdm.auto import tqdm

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
    "BallTrajectory",
    "BounceAim",
    "Landing",
    "ScalarBall",
    "StepEvents",
    "aim",
    "aim_through_bounce",
    "flight",
    "is_legal_return",
    "landing",
    "make_state",
    "predict_plane_crossing",
    "propagate",
    "racket_contact",
    "racket_velocity_for_return",
    "simulate",
    "step",
    "step_events",
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


class StepEvents(NamedTuple):
    """Contacts that happened during one call of :func:`step_events`; shapes ``[...]``/``[..., 3]``.

    Attributes:
        bounce: whether the ball bounced on the table.
        bounce_pos: contact point on the table surface (``z = TABLE_HEIGHT``) of the first
            bounce; zeros where ``bounce`` is false.
        bounce_time: time of that bounce after the start of the step [s]; zero where none.
        net: whether the ball touched the net.
    """

    bounce: torch.Tensor
    bounce_pos: torch.Tensor
    bounce_time: torch.Tensor
    net: torch.Tensor


class BallTrajectory(NamedTuple):
    """A simulated flight sampled every ``dt``; ``S`` samples including the start.

    Attributes:
        times: ``[S]`` sample times [s], ``times[0] = 0``.
        pos: ``[..., S, 3]`` centre positions.
        vel: ``[..., S, 3]`` velocities.
        spin: ``[..., S, 3]`` angular velocities.
        bounce: ``[..., S]`` whether a table bounce happened in the step ending at sample s
            (``bounce[..., 0]`` is false).
        bounce_pos: ``[..., S, 3]`` contact point of that bounce on the table surface (zeros
            where none).
        bounce_time: ``[..., S]`` absolute time of that bounce [s] (zero where none).
        net: ``[..., S]`` whether the ball touched the net in the step ending at sample s.
    """

    times: torch.Tensor
    pos: torch.Tensor
    vel: torch.Tensor
    spin: torch.Tensor
    bounce: torch.Tensor
    bounce_pos: torch.Tensor
    bounce_time: torch.Tensor
    net: torch.Tensor


class Landing(NamedTuple):
    """The first table bounce of a trajectory; shapes ``[..., 3]`` and ``[...]``.

    Attributes:
        pos: contact point on the table surface (zeros where ``landed`` is false).
        time: time of the contact [s] (zero where ``landed`` is false).
        landed: whether the ball touched the table at all.
        net_before: whether the ball touched the net before that bounce (or at all, if it never
            landed).
    """

    pos: torch.Tensor
    time: torch.Tensor
    landed: torch.Tensor
    net_before: torch.Tensor


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


def _check_state(state: BallState, name: str = "state") -> BallState:
    if not isinstance(state, BallState):
        raise TypeError(f"{name} must be a BallState, got {type(state).__name__}")
    return make_state(state.pos, state.vel, state.spin)


def _check_params(params: BallParams) -> BallParams:
    if not isinstance(params, BallParams):
        raise TypeError(f"params must be a BallParams, got {type(params).__name__}")
    return params


def _check_result(what: str, *tensors: torch.Tensor) -> None:
    """Raise if the integration left the floating-point range (states within the documented
    ranges never do; extreme :class:`BallParams` can)."""
    if not all(bool(torch.isfinite(t).all()) for t in tensors):
        raise ValueError(
            f"{what}: the ball integration produced non-finite values; the state or the "
            "BallParams are outside the model's range"
        )


def _check_dt(dt: float, name: str = "dt") -> float:
    if not isinstance(dt, int | float) or not math.isfinite(dt) or not 0 < dt <= _MAX_DT:
        raise ValueError(f"{name} must be a number in (0, {_MAX_DT}] s, got {dt!r}")
    return float(dt)


def _check_duration(value: object, name: str) -> float:
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


def _check_steps(n: int, name: str, dt: float) -> int:
    if n > MAX_STEPS:
        raise ValueError(
            f"{name} / dt = {n} steps exceeds MAX_STEPS = {MAX_STEPS}; take a larger dt "
            f"(at most {_MAX_DT} s; got {dt}) or a shorter {name}"
        )
    return n


def _single(state: BallState) -> bool:
    """Whether ``state`` is one float64 ball on the CPU (integrated by :class:`ScalarBall`)."""
    p = state.pos
    return (
        p.dim() == 1 and p.dtype == torch.float64 and p.device.type == "cpu" and not p.requires_grad
    )


def _floats(state: BallState) -> Floats:
    return tuple(torch.cat(tuple(state)).tolist())  # type: ignore[return-value]


def _tensors(s: Floats) -> BallState:
    return BallState(*(torch.tensor(s[i : i + 3], dtype=torch.float64) for i in (0, 3, 6)))


@lru_cache(maxsize=16)
def _scalar(params: BallParams) -> ScalarBall:
    return ScalarBall(params)


def table_point(x: object, y: object) -> torch.Tensor:
    """Centre ``[..., 3]`` of a ball touching the table surface at ``(x, y)`` (each ``[...]``)."""
    xt = as_tensor(x, "x")
    yt = as_tensor(y, "y", dtype=xt.dtype, device=xt.device)
    xt, yt = torch.broadcast_tensors(xt, yt)
    return torch.stack([xt, yt, torch.full_like(xt, geo.TABLE_HEIGHT + geo.BALL_RADIUS)], -1)


# --------------------------------------------------------------------------------------------
# flight


def flight(state: BallState, params: BallParams = DEFAULT_PARAMS) -> torch.Tensor:
    """Acceleration ``[..., 3]`` in free flight: ``-g e_z - k_d |v| v + k_m (w x v)``."""
    v, w = state.vel, state.spin
    acc = (-params.drag) * torch.linalg.vector_norm(v, dim=-1, keepdim=True) * v
    if params.magnus:
        acc = acc + params.magnus * torch.linalg.cross(w, v, dim=-1)
    acc[..., 2] -= params.gravity
    return acc


@lru_cache(maxsize=16)
def _gravity(g: float, dtype: torch.dtype, device: torch.device) -> torch.Tensor:
    return torch.tensor([0.0, 0.0, -g], dtype=dtype, device=device)


def _rk4(state: BallState, h: torch.Tensor, params: BallParams) -> BallState:
    """One classical RK4 step of the flight ODE with a per-ball step ``h`` [...] (may be 0).

    :func:`flight` in few tensor operations (fused multiply-adds, the Magnus factor applied to
    the spin once), because batches of tens of balls cost per operation, not per ball.
    """
    h = h.unsqueeze(-1)
    p, v, w = state
    kd = -params.drag
    mw = params.magnus * w if params.magnus else None
    g = _gravity(params.gravity, v.dtype, v.device)

    def acc(u: torch.Tensor) -> torch.Tensor:
        a = torch.linalg.vector_norm(u, dim=-1, keepdim=True).mul(kd).mul(u)
        if mw is not None:
            a.add_(torch.linalg.cross(mw, u, dim=-1))
        return a.add_(g)

    hh = 0.5 * h
    a1 = acc(v)
    v2 = torch.addcmul(v, hh, a1)
    a2 = acc(v2)
    v3 = torch.addcmul(v, hh, a2)
    a3 = acc(v3)
    v4 = torch.addcmul(v, h, a3)
    a4 = acc(v4)
    h6 = h / 6.0
    new_p = torch.addcmul(p, h6, torch.add(v, v2, alpha=2).add_(v3, alpha=2).add_(v4))
    new_v = torch.addcmul(v, h6, torch.add(a1, a2, alpha=2).add_(a3, alpha=2).add_(a4))
    return BallState(new_p, new_v, w)


# --------------------------------------------------------------------------------------------
# events

# An event maps a state to a scalar ``g`` (positive before contact) and its time derivative.
_Event = Callable[[BallState], tuple[torch.Tensor, torch.Tensor]]
_Propagator = Callable[[BallState, torch.Tensor], BallState]


def _find_root(
    start: BallState,
    hi: torch.Tensor,
    g_start: torch.Tensor,
    g_end: torch.Tensor,
    event: _Event,
    propagate: _Propagator,
    iters: int = 12,
) -> torch.Tensor:
    """Time ``tau`` [...] in ``[0, hi]`` where ``event`` crosses zero along ``propagate``.

    ``g_start > 0 >= g_end`` is assumed where the result is used. Newton steps on ``tau`` use the
    event's time derivative; a step that leaves the current bracket falls back to bisection.
    Callers snap the ball onto the contact surface, so a residual of ~1e-16 s cannot re-trigger.
    """
    lo = torch.zeros_like(hi)
    denom = g_start - g_end
    safe = denom > 0
    tau = torch.where(safe, hi * g_start / torch.where(safe, denom, torch.ones_like(denom)), hi)
    tau = tau.clamp(min=0).minimum(hi)
    for _ in range(iters):
        s = propagate(start, tau)
        g, gdot = event(s)
        if bool((g.abs() < 1e-14).all()):  # at the contact to rounding: Newton has converged
            break
        above = g > 0
        lo = torch.where(above, tau, lo)
        hi = torch.where(above, hi, tau)
        ok_d = gdot != 0
        newton = tau - g / torch.where(ok_d, gdot, torch.ones_like(gdot))
        inside = ok_d & (newton >= lo) & (newton <= hi)
        tau = torch.where(inside, newton, 0.5 * (lo + hi))
    # Newton converges quadratically from either side; a bracket end may stay at its first value
    return tau


class _TableEvent:
    def __init__(self, params: BallParams) -> None:
        self.level = geo.TABLE_HEIGHT + params.radius

    def __call__(self, s: BallState) -> tuple[torch.Tensor, torch.Tensor]:
        return s.pos[..., 2] - self.level, s.vel[..., 2]


class _PlaneEvent:
    """``g = sign * (y - y_plane) - offset``; ``sign`` [...] orients g to be positive at start."""

    def __init__(self, y_plane: torch.Tensor, sign: torch.Tensor, offset: float = 0.0) -> None:
        self.y_plane, self.sign, self.offset = y_plane, sign, offset

    def __call__(self, s: BallState) -> tuple[torch.Tensor, torch.Tensor]:
        return (
            self.sign * (s.pos[..., 1] - self.y_plane) - self.offset,
            self.sign * s.vel[..., 1],
        )


def _table_bounce(s: BallState, params: BallParams) -> BallState:
    """Post-bounce state of balls touching the table (SL law on the contact point's slip)."""
    r = params.radius
    v, w = s.vel, s.spin
    # slip velocity of the contact point r_c = (0, 0, -r): v + w x r_c
    slip_x = v[..., 0] - r * w[..., 1]
    slip_y = v[..., 1] + r * w[..., 0]
    dvx = (params.table_friction_x - 1.0) * slip_x
    dvy = (params.table_friction_y - 1.0) * slip_y
    new_v = torch.stack(
        [v[..., 0] + dvx, v[..., 1] + dvy, -params.table_restitution * v[..., 2]], -1
    )
    # angular impulse of the friction impulse m dv at r_c: I dw = r_c x (m dv), I = kappa m r^2
    kr = params.inertia_factor * r
    new_w = torch.stack([w[..., 0] + dvy / kr, w[..., 1] - dvx / kr, w[..., 2]], -1)
    pos = s.pos.clone()
    pos[..., 2] = geo.TABLE_HEIGHT + r  # exactly on the surface so the event cannot re-trigger
    return BallState(pos, new_v, new_w)


def _net_hit(s: BallState, sign: torch.Tensor, params: BallParams) -> BallState:
    """Post-contact state of balls touching the net face (``sign`` = direction of travel in y)."""
    scale = torch.tensor(
        [params.net_damping, -params.net_restitution, params.net_damping],
        dtype=s.vel.dtype,
        device=s.vel.device,
    )
    pos = s.pos.clone()
    pos[..., 1] = geo.NET_Y - sign * params.radius
    return BallState(pos, s.vel * scale, s.spin * params.net_damping)


def _subset(state: BallState, mask: torch.Tensor) -> BallState:
    """The balls where ``mask`` [...] is true, flattened to ``[k]``."""
    return BallState(state.pos[mask], state.vel[mask], state.spin[mask])


def _scatter(full: torch.Tensor, mask: torch.Tensor, values: torch.Tensor) -> torch.Tensor:
    """A copy of ``full`` [...] with the entries where ``mask`` is true set to ``values`` [k]."""
    out = full.clone()
    out[mask] = values
    return out


def _on_table(pos: torch.Tensor) -> torch.Tensor:
    return (pos[..., 0].abs() <= geo.TABLE_HALF_WIDTH) & (
        pos[..., 1].abs() <= geo.TABLE_HALF_LENGTH
    )


def _at_net(pos: torch.Tensor, params: BallParams) -> torch.Tensor:
    # the ball must clear the net's top by its radius; below the playing surface there is no net
    z = pos[..., 2] - geo.TABLE_HEIGHT
    return (
        (pos[..., 0].abs() <= geo.NET_HALF_WIDTH + params.radius)
        & (z > 0)
        & (z < geo.NET_HEIGHT + params.radius)
    )


def _advance(
    state: BallState, h: torch.Tensor, params: BallParams, max_events: int = 4
) -> tuple[BallState, StepEvents]:
    """Propagate each ball by its own time ``h`` [...] through table and net contacts."""
    trial = _rk4(state, h, params)
    # most steps of most balls touch nothing: tell in a few operations (the same tests as the
    # table and net events below) before any event bookkeeping
    level = geo.TABLE_HEIGHT + params.radius
    z0, z1 = state.pos[..., 2], trial.pos[..., 2]
    toward = -torch.sign(state.vel[..., 1])
    cand = (z0 > level) & (z1 <= level)
    y0, y1 = toward * (state.pos[..., 1] - geo.NET_Y), toward * (trial.pos[..., 1] - geo.NET_Y)
    cand |= (y0 > params.radius) & (y1 <= params.radius)
    if not bool(cand.any()):
        no = torch.zeros(h.shape, dtype=torch.bool, device=h.device)
        return trial, StepEvents(no, torch.zeros_like(state.pos), torch.zeros_like(h), no.clone())
    remaining = h.clone()
    zeros = torch.zeros_like(h)
    bounce = torch.zeros(h.shape, dtype=torch.bool, device=h.device)
    net = torch.zeros_like(bounce)
    bounce_pos = torch.zeros_like(state.pos)
    bounce_time = zeros.clone()
    elapsed = zeros.clone()
    table_event = _TableEvent(params)

    def fly(s: BallState, tau: torch.Tensor) -> BallState:
        return _rk4(s, tau, params)

    for _ in range(max_events + 1):
        active = remaining > 0
        if not bool(active.any()):
            break
        trial = _rk4(state, remaining, params)
        g0_t, _ = table_event(state)
        g1_t, _ = table_event(trial)
        table_cand = active & (g0_t > 0) & (g1_t <= 0)
        sign = torch.sign(state.vel[..., 1])
        net_event = _PlaneEvent(torch.full_like(h, geo.NET_Y), -sign, params.radius)
        g0_n, _ = net_event(state)
        g1_n, _ = net_event(trial)
        net_cand = active & (sign != 0) & (g0_n > 0) & (g1_n <= 0)
        if not bool((table_cand | net_cand).any()):
            state = trial.where(active, state)
            break
        tau_t = torch.full_like(h, math.inf)
        tau_n = torch.full_like(h, math.inf)
        if bool(table_cand.any()):
            m = table_cand
            tau = _find_root(_subset(state, m), remaining[m], g0_t[m], g1_t[m], table_event, fly)
            table_cand = _scatter(table_cand, m, _on_table(fly(_subset(state, m), tau).pos))
            tau_t = _scatter(tau_t, table_cand, tau[table_cand[m]])
        if bool(net_cand.any()):
            m = net_cand
            sub_event = _PlaneEvent(net_event.y_plane[m], net_event.sign[m], params.radius)
            tau = _find_root(_subset(state, m), remaining[m], g0_n[m], g1_n[m], sub_event, fly)
            net_cand = _scatter(net_cand, m, _at_net(fly(_subset(state, m), tau).pos, params))
            tau_n = _scatter(tau_n, net_cand, tau[net_cand[m]])
        use_t = table_cand & (tau_t <= tau_n)
        use_n = net_cand & ~use_t
        hit = use_t | use_n
        tau = torch.where(use_t, tau_t, torch.where(use_n, tau_n, remaining))
        at = fly(state, tau)
        first = use_t & ~bounce
        contact = at.pos.clone()
        contact[..., 2] = geo.TABLE_HEIGHT
        bounce_pos = torch.where(first.unsqueeze(-1), contact, bounce_pos)
        bounce_time = torch.where(first, elapsed + tau, bounce_time)
        bounce = bounce | use_t
        net = net | use_n
        after = _table_bounce(at, params).where(use_t, _net_hit(at, sign, params).where(use_n, at))
        state = after.where(active, state)
        elapsed = elapsed + torch.where(active, tau, zeros)
        remaining = torch.where(hit, remaining - tau, zeros)
    else:
        # more contacts in one step than max_events (a ball trapped at the net): finish in flight
        state = _rk4(state, remaining, params)
    return state, StepEvents(bounce, bounce_pos, bounce_time, net)


def step_events(
    state: BallState, dt: float, params: BallParams = DEFAULT_PARAMS
) -> tuple[BallState, StepEvents]:
    """Advance a batch of balls by ``dt`` seconds and report table/net contacts in the step.

    Args:
        state: :class:`BallState` with fields ``[..., 3]``.
        dt: step [s], ``0 < dt <= 0.05`` (contacts are exact for ``dt <= 10 ms``).
        params: ball constants.

    Returns:
        The new state and the :class:`StepEvents` of the step.
    """
    state = _check_state(state)
    params = _check_params(params)
    dt = _check_dt(dt)
    if _single(state):
        s, bounce, pos, time, net = _scalar(params).advance(_floats(state), dt)
        new = _tensors(s)
        events = StepEvents(
            torch.tensor(bounce),
            torch.tensor(pos, dtype=torch.float64),
            torch.tensor(time, dtype=torch.float64),
            torch.tensor(net),
        )
    else:
        h = torch.full(state.batch_shape, dt, dtype=state.pos.dtype, device=state.pos.device)
        new, events = _advance(state, h, params)
    _check_result("step", *new, events.bounce_pos, events.bounce_time)
    return new, events


def step(state: BallState, dt: float, params: BallParams = DEFAULT_PARAMS) -> BallState:
    """Advance a batch of balls by ``dt`` seconds: RK4 flight with exact table and net contacts.

    Shapes: ``[..., 3]`` fields in and out. See :func:`step_events` for the contacts.
    """
    return step_events(state, dt, params)[0]


def propagate(
    state: BallState,
    duration: object,
    params: BallParams = DEFAULT_PARAMS,
    *,
    dt: float = 0.005,
) -> BallState:
    """Advance each ball by its own time ``duration`` [...] (>= 0), contacts included.

    Each ball takes steps of ``dt`` and one shorter last step, so a ball's result equals
    :func:`simulate`'s sample at that time when the grids agree.

    Args:
        state: :class:`BallState` ``[..., 3]``.
        duration: ``[...]`` (broadcast to the batch) or scalar time [s], at most
            :data:`MAX_DURATION`.
        params: ball constants.
        dt: step [s], ``0 < dt <= 0.05``.

    Returns:
        The :class:`BallState` ``[..., 3]`` after ``duration``.
    """
    state = _check_state(state)
    params = _check_params(params)
    dt = _check_dt(dt)
    d = as_tensor(duration, "duration", dtype=state.pos.dtype, device=state.pos.device)
    if bool((d < 0).any()):
        raise ValueError("duration must be >= 0")
    longest = float(d.max()) if d.numel() else 0.0
    if longest > MAX_DURATION:
        raise ValueError(
            f"duration must be at most MAX_DURATION = {MAX_DURATION:g} s, got {longest:g}"
        )
    d = torch.broadcast_to(d, state.batch_shape)
    n = _check_steps(math.ceil(longest / dt - 1e-9) if d.numel() else 0, "duration", dt)
    if _single(state):
        state = _tensors(_scalar(params).propagate(_floats(state), float(d), dt))
    else:
        for k in range(n):
            state = _advance(state, (d - k * dt).clamp(0.0, dt), params)[0]
    _check_result("propagate", *state)
    return state


def simulate(
    state: BallState,
    duration: float,
    dt: float,
    params: BallParams = DEFAULT_PARAMS,
    *,
    progress: bool = False,
) -> BallTrajectory:
    """Simulate a batch of balls for ``duration`` seconds, sampled every step.

    The step is ``duration / round(duration / dt)`` so that the last sample falls on ``duration``.

    Args:
        state: initial :class:`BallState` ``[..., 3]``.
        duration: simulated time [s], ``0 < duration <= MAX_DURATION``.
        dt: nominal step [s], ``0 < dt <= 0.05``, at most :data:`MAX_STEPS` steps in all.
        params: ball constants.
        progress: show a tqdm bar over steps (batches only).

    Returns:
        :class:`BallTrajectory` with ``S = round(duration / dt) + 1`` samples.
    """
    state = _check_state(state)
    params = _check_params(params)
    dt = _check_dt(dt)
    duration = _check_duration(duration, "duration")
    n = _check_steps(max(1, round(duration / dt)), "duration", dt)
    if _single(state):
        traj = _trajectory(*_scalar(params).simulate(_floats(state), duration, dt))
        _check_result("simulate", traj.pos, traj.vel, traj.spin, traj.bounce_pos, traj.bounce_time)
        return traj
    h_val = duration / n
    h = torch.full(state.batch_shape, h_val, dtype=state.pos.dtype, device=state.pos.device)
    pos, vel, spin = [state.pos], [state.vel], [state.spin]
    no = torch.zeros(state.batch_shape, dtype=torch.bool, device=state.pos.device)
    bounce, bpos, btime, net = [no], [torch.zeros_like(state.pos)], [h * 0], [no]
    for k in tqdm(range(n), disable=not progress, desc="ball", leave=False):
        state, ev = _advance(state, h, params)
        pos.append(state.pos)
        vel.append(state.vel)
        spin.append(state.spin)
        bounce.append(ev.bounce)
        bpos.append(ev.bounce_pos)
        btime.append(torch.where(ev.bounce, ev.bounce_time + k * h_val, ev.bounce_time))
        net.append(ev.net)
    times = torch.arange(n + 1, dtype=state.pos.dtype, device=state.pos.device) * h_val
    traj = BallTrajectory(
        times,
        torch.stack(pos, -2),
        torch.stack(vel, -2),
        torch.stack(spin, -2),
        torch.stack(bounce, -1),
        torch.stack(bpos, -2),
        torch.stack(btime, -1),
        torch.stack(net, -1),
    )
    _check_result("simulate", traj.pos, traj.vel, traj.spin, traj.bounce_pos, traj.bounce_time)
    return traj


def _trajectory(h: float, samples: list[tuple]) -> BallTrajectory:
    """A :class:`BallTrajectory` of one ball from :meth:`ScalarBall.simulate`'s samples."""
    states = torch.tensor([s for s, *_ in samples], dtype=torch.float64)  # [S, 9]
    return BallTrajectory(
        torch.arange(len(samples), dtype=torch.float64) * h,
        states[:, 0:3].contiguous(),
        states[:, 3:6].contiguous(),
        states[:, 6:9].contiguous(),
        torch.tensor([e[1] for e in samples]),
        torch.tensor([e[2] for e in samples], dtype=torch.float64),
        torch.tensor([e[3] for e in samples], dtype=torch.float64),
        torch.tensor([e[4] for e in samples]),
    )


# --------------------------------------------------------------------------------------------
# landing and legality


def landing(traj: BallTrajectory) -> Landing:
    """The first table bounce of each simulated ball. Shapes ``[..., S] -> [...]``.

    ``net_before`` tells whether the net was touched before that bounce (or at all, if the ball
    never landed).
    """
    if not isinstance(traj, BallTrajectory):
        raise TypeError(f"traj must be a BallTrajectory, got {type(traj).__name__}")
    landed = traj.bounce.any(-1)
    first = torch.argmax(traj.bounce.to(torch.int8), dim=-1)  # index of the first true
    pos = torch.gather(
        traj.bounce_pos, -2, first[..., None, None].expand(*first.shape, 1, 3)
    ).squeeze(-2)
    time = torch.gather(traj.bounce_time, -1, first[..., None]).squeeze(-1)
    idx = torch.arange(traj.bounce.shape[-1], device=first.device)
    upto = torch.where(landed[..., None], idx <= first[..., None], torch.ones_like(traj.bounce))
    # a net touch and a bounce in the same step: the step's event order is not kept, so count it
    net_before = (traj.net & upto).any(-1)
    zero = torch.zeros_like(time)
    return Landing(
        torch.where(landed[..., None], pos, torch.zeros_like(pos)),
        torch.where(landed, time, zero),
        landed,
        net_before,
    )


def is_legal_return(traj: BallTrajectory, side: int = geo.OPPONENT_SIDE) -> torch.Tensor:
    """Whether each ball first lands on the given half, clearing the net. ``[..., S] -> [...]``.

    Legal means: the first table contact has ``side * y in (0, 1.37]`` and ``|x| <= 0.7625`` and
    the ball did not touch the net before it.

    Args:
        traj: simulated flight starting after the hit.
        side: ``+1`` (the opponent's half, :data:`geometry.OPPONENT_SIDE`) for the robot's returns,
            ``-1`` (the robot's half) for the opponent's returns.
    """
    if side not in (-1, 1):
        raise ValueError(f"side must be +1 (opponent's half) or -1 (robot's half), got {side!r}")
    land = landing(traj)
    on_half = (side * land.pos[..., 1] > 0) & (side * land.pos[..., 1] <= geo.TABLE_HALF_LENGTH)
    inside = land.pos[..., 0].abs() <= geo.TABLE_HALF_WIDTH
    return land.landed & on_half & inside & ~land.net_before


# --------------------------------------------------------------------------------------------
# plane crossing


def predict_plane_crossing(
    state: BallState,
    y_plane: float | torch.Tensor,
    params: BallParams = DEFAULT_PARAMS,
    *,
    max_time: float = 2.0,
    dt: float = 0.005,
) -> tuple[torch.Tensor, BallState, torch.Tensor]:
    """When and where each ball first crosses the plane ``y = y_plane``, bounces included.

    Used by the robot to predict the ball at its virtual hitting plane (thesis Fig. 4.2).

    Args:
        state: :class:`BallState` ``[..., 3]``.
        y_plane: plane position, a float or a tensor broadcastable to ``[...]``.
        params: ball constants.
        max_time: give up after this many seconds (at most :data:`MAX_DURATION`).
        dt: integration step [s] (the crossing itself is located exactly).

    Returns:
        ``t`` [...] time of the crossing [s], the :class:`BallState` at the crossing, and ``valid``
        [...]: whether the ball crossed within ``max_time`` before falling to the floor. Where
        ``valid`` is false ``t`` is ``max_time`` and the state is the last one simulated.
    """
    state = _check_state(state)
    params = _check_params(params)
    dt = _check_dt(dt)
    max_time = _check_duration(max_time, "max_time")
    _check_steps(math.ceil(max_time / dt - 1e-9), "max_time", dt)
    t_cross, out, valid = _plane_crossing(state, y_plane, params, max_time, dt)
    _check_result("predict_plane_crossing", t_cross, *out)
    return t_cross, out, valid


def _plane_crossing(
    state: BallState, y_plane: float | torch.Tensor, params: BallParams, max_time: float, dt: float
) -> tuple[torch.Tensor, BallState, torch.Tensor]:
    """:func:`predict_plane_crossing` without input checks (also for trial states of solvers,
    which may leave the documented ranges)."""
    yp = as_tensor(y_plane, "y_plane", dtype=state.pos.dtype, device=state.pos.device)
    if _single(state) and yp.dim() == 0:
        t, at, ok = _scalar(params).plane_crossing(_floats(state), float(yp), max_time, dt)
        return torch.tensor(t, dtype=torch.float64), _tensors(at), torch.tensor(ok)
    yp = torch.broadcast_to(yp, state.batch_shape).clone()
    g0 = state.pos[..., 1] - yp
    event = _PlaneEvent(yp, torch.where(g0 >= 0, 1.0, -1.0).to(yp.dtype))

    def fly(s: BallState, tau: torch.Tensor) -> BallState:
        return _advance(s, tau, params)[0]

    shape = state.batch_shape
    done = torch.zeros(shape, dtype=torch.bool, device=yp.device)
    valid = torch.zeros_like(done)
    t_cross = torch.full(shape, float(max_time), dtype=yp.dtype, device=yp.device)
    out = state
    t = 0.0
    n = math.ceil(max_time / dt - 1e-9)
    for k in range(n):
        h_val = min(dt, max_time - k * dt)
        h = torch.full(shape, h_val, dtype=yp.dtype, device=yp.device)
        new, _ = _advance(state, h, params)
        g_start, _ = event(state)
        g_end, _ = event(new)
        crossed = ~done & (g_start > 0) & (g_end <= 0)
        if bool(crossed.any()):
            m = crossed
            sub_event = _PlaneEvent(event.y_plane[m], event.sign[m])
            sub = _subset(state, m)
            tau = _find_root(sub, h[m], g_start[m], g_end[m], sub_event, fly)
            at = fly(sub, tau)
            out = BallState(*(_scatter(o, m, a) for o, a in zip(out, at, strict=True)))
            t_cross = _scatter(t_cross, m, t + tau)
            valid = _scatter(valid, m, at.pos[:, 2] > params.radius)
            done = done | crossed
        fell = ~done & (new.pos[..., 2] <= params.radius)
        out = new.where(fell, out)
        done = done | fell
        t += h_val
        state = new
        if bool(done.all()):
            break
    out = out.where(done, state)
    return t_cross, out, valid


# --------------------------------------------------------------------------------------------
# racket contact


def _unit(n: torch.Tensor, name: str) -> torch.Tensor:
    norm = n.norm(dim=-1, keepdim=True)
    if bool((norm < 1e-12).any()):
        raise ValueError(f"{name} must be non-zero vectors")
    return n / norm


def racket_contact(
    ball_vel: object,
    ball_spin: object,
    racket_vel: object,
    racket_normal: object,
    params: BallParams = DEFAULT_PARAMS,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Ball velocity and spin after a racket contact (SL racket law, Mülling et al., 2011).

    In the racket's frame the ball's normal velocity is reversed and scaled by the restitution
    ``e`` and its tangential velocity kept: ``v_out = v + (1 + e) ((v_r - v) . n) n``; the
    velocity law is symmetric in the sign of ``n``. The SL law has no spin; with
    ``params.racket_spin == "rolling"`` (default) the rubber grips the ball so that it leaves the
    face rolling: ``w_out = (w . n) n + n' x (v_out - v_r) / r`` with ``n'`` the normal oriented
    towards the departing ball (an upward brush gives topspin). With ``"kept"`` the contact is
    frictionless and ``w_out = w``. All arguments ``[..., 3]`` (broadcast); the normal need not
    be unit length.

    Returns:
        ``(vel_out, spin_out)``, each ``[..., 3]``.
    """
    params = _check_params(params)
    v = as_tensor(ball_vel, "ball_vel", min_ndim=1)
    kw = {"dtype": v.dtype, "device": v.device, "min_ndim": 1}
    w = as_tensor(ball_spin, "ball_spin", **kw)
    vr = as_tensor(racket_vel, "racket_vel", **kw)
    n = as_tensor(racket_normal, "racket_normal", **kw)
    for t, name in ((v, "ball_vel"), (w, "ball_spin"), (vr, "racket_vel"), (n, "racket_normal")):
        check_shape(t, name, (3,))
    n = _unit(n, "racket_normal")
    closing = ((vr - v) * n).sum(-1, keepdim=True)
    vel_out = v + (1.0 + params.racket_restitution) * closing * n
    w = torch.broadcast_to(w, vel_out.shape)
    if params.racket_spin == "kept":
        return vel_out, w.clone()
    rel = vel_out - vr
    n = torch.broadcast_to(n, vel_out.shape)
    n_out = n * torch.sign((rel * n).sum(-1, keepdim=True))  # the face the ball leaves from
    spin_out = (w * n).sum(-1, keepdim=True) * n + torch.linalg.cross(n_out, rel) / params.radius
    return vel_out, spin_out


def racket_velocity_for_return(
    ball_vel_in: object,
    desired_vel_out: object,
    params: BallParams = DEFAULT_PARAMS,
    *,
    tangential: object | None = None,
    spin_out: object | None = None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Racket normal and velocity that turn ``ball_vel_in`` into ``desired_vel_out``.

    Inverts :func:`racket_contact`: the velocity change ``dv = v_out - v_in`` lies along the
    normal, so ``n = dv / |dv|``, and its size fixes the racket's normal speed,
    ``v_r . n = v_in . n + |dv| / (1 + e)``. The racket's tangential velocity does not change the
    ball's velocity. It is ``tangential`` projected onto the racket plane, or, given
    ``spin_out`` (``"rolling"`` spin law), the one that makes the ball leave with that spin's
    in-plane part, ``v_r,t = v_out,t + r n x w_out``; by default zero (the slowest racket).

    Args:
        ball_vel_in: ``[..., 3]`` ball velocity just before contact.
        desired_vel_out: ``[..., 3]`` ball velocity wanted just after contact.
        params: ball constants (uses ``racket_restitution``, ``radius``).
        tangential: optional ``[..., 3]`` racket velocity whose in-plane part is kept.
        spin_out: optional ``[..., 3]`` wanted spin after contact; its component along ``n``
            cannot be changed by the racket and is ignored.

    Returns:
        ``(racket_normal, racket_vel)``, each ``[..., 3]``; the normal is a unit vector pointing
        along ``dv`` (towards where the ball is sent).
    """
    params = _check_params(params)
    v_in = as_tensor(ball_vel_in, "ball_vel_in", min_ndim=1)
    kw = {"dtype": v_in.dtype, "device": v_in.device}
    v_out = as_tensor(desired_vel_out, "desired_vel_out", **kw)
    check_shape(v_in, "ball_vel_in", (3,))
    check_shape(v_out, "desired_vel_out", (3,))
    if tangential is not None and spin_out is not None:
        raise ValueError("give at most one of tangential and spin_out")
    if spin_out is not None and params.racket_spin != "rolling":
        raise ValueError('spin_out needs params.racket_spin == "rolling"')
    dv = v_out - v_in
    if bool((dv.norm(dim=-1) < 1e-9).any()):
        raise ValueError(
            "desired_vel_out must differ from ball_vel_in (no contact changes nothing)"
        )
    n = dv / dv.norm(dim=-1, keepdim=True)
    speed = (v_in * n).sum(-1, keepdim=True) + dv.norm(dim=-1, keepdim=True) / (
        1.0 + params.racket_restitution
    )
    racket_vel = speed * n
    if tangential is not None:
        tan = as_tensor(tangential, "tangential", **kw)
        check_shape(tan, "tangential", (3,))
        racket_vel = racket_vel + tan - (tan * n).sum(-1, keepdim=True) * n
    elif spin_out is not None:
        w = as_tensor(spin_out, "spin_out", **kw)
        check_shape(w, "spin_out", (3,))
        v_t = v_out - (v_out * n).sum(-1, keepdim=True) * n
        racket_vel = racket_vel + v_t + params.radius * torch.linalg.cross(n, w.expand_as(n))
    return n, racket_vel


# --------------------------------------------------------------------------------------------
# aiming


def _fly_for(
    pos: torch.Tensor, vel: torch.Tensor, spin: torch.Tensor, t: torch.Tensor, params: BallParams
) -> torch.Tensor:
    """Free-flight position after ``t`` [...] seconds (RK4, steps <= 5 ms, no contacts)."""
    n = max(8, math.ceil(float(t.max()) / 0.005))
    h = t / n
    s = BallState(pos, vel, spin)
    for _ in range(n):
        s = _rk4(s, h, params)
    return s.pos


def _check_flight_time(t: torch.Tensor) -> torch.Tensor:
    if bool((t <= 0).any()) or bool((t > MAX_DURATION).any()):
        raise ValueError(
            f"flight_time must be positive and at most MAX_DURATION = {MAX_DURATION:g} s"
        )
    return t


def aim(
    pos: object,
    target_pos: object,
    flight_time: object,
    params: BallParams = DEFAULT_PARAMS,
    *,
    spin: object | None = None,
    tol: float = 1e-9,
    max_iter: int = 20,
) -> torch.Tensor:
    """Initial velocity that carries a ball from ``pos`` to ``target_pos`` in ``flight_time``.

    A batched shooting method on the free-flight model (gravity, drag, Magnus with constant
    ``spin``): Newton's method on ``p(T; v0) - target = 0`` with a central-difference Jacobian,
    started from the drag-free ballistic solution. Table and net contacts are not modelled on
    the way; check the result with :func:`simulate` and :func:`is_legal_return`.

    Args:
        pos: ``[..., 3]`` start position of the ball centre.
        target_pos: ``[..., 2]`` landing point ``(x, y)`` on the table surface (the ball centre
            then reaches ``z = TABLE_HEIGHT + radius``), or ``[..., 3]`` a ball-centre point.
        flight_time: ``[...]`` or scalar time to reach the target [s], in
            ``(0, MAX_DURATION]``.
        params: ball constants.
        spin: ``[..., 3]`` angular velocity during the flight (default zero).
        tol: stop when every position residual is below this [m].
        max_iter: Newton iterations at most.

    Returns:
        ``v0`` ``[..., 3]``.

    Raises:
        ValueError: for bad shapes/values, or when Newton does not reach ``1e-6`` m.
    """
    v, resid = _aim(pos, target_pos, flight_time, params, spin=spin, tol=tol, max_iter=max_iter)
    worst = float(torch.nan_to_num(resid, nan=math.inf).max()) if resid.numel() else 0.0
    if not worst <= 1e-6:
        raise ValueError(
            f"aim did not converge (max residual {worst:.2e} m); "
            "the target may be unreachable in the given flight_time"
        )
    return v


def _aim(
    pos: object,
    target_pos: object,
    flight_time: object,
    params: BallParams,
    *,
    spin: object | None,
    tol: float,
    max_iter: int,
) -> tuple[torch.Tensor, torch.Tensor]:
    """:func:`aim` without the convergence check: ``v0 [..., 3]`` and the residual ``[...]`` [m].

    Elements whose Newton iteration diverged (residual NaN/inf or large) keep their drag-free
    ballistic guess, so that the velocity is always finite; callers judge them by the residual.
    """
    params = _check_params(params)
    p0 = as_tensor(pos, "pos", min_ndim=1)
    kw = {"dtype": p0.dtype, "device": p0.device}
    tgt = as_tensor(target_pos, "target_pos", min_ndim=1, **kw)
    check_shape(p0, "pos", (3,))
    if tgt.shape[-1] == 2:
        tgt = torch.cat(
            [tgt, torch.full_like(tgt[..., :1], geo.TABLE_HEIGHT + params.radius)], dim=-1
        )
    check_shape(tgt, "target_pos", (3,))
    t = _check_flight_time(as_tensor(flight_time, "flight_time", **kw))
    w = torch.zeros(3, **kw) if spin is None else as_tensor(spin, "spin", min_ndim=1, **kw)
    check_shape(w, "spin", (3,))
    shape = torch.broadcast_shapes(p0.shape, tgt.shape, w.shape, t.shape + (3,))
    p0, tgt, w = (x.expand(shape) for x in (p0, tgt, w))
    t = t.expand(shape[:-1])
    if shape == (3,) and _single(BallState(p0, tgt, w)):
        v1, err1 = _scalar(params).aim(
            tuple(p0.tolist()), tuple(tgt.tolist()), float(t), tuple(w.tolist()), tol, max_iter
        )
        return torch.tensor(v1, dtype=torch.float64), torch.tensor(err1, dtype=torch.float64)
    g = torch.zeros(3, **kw)
    g[2] = params.gravity
    guess = (tgt - p0) / t[..., None] + 0.5 * g * t[..., None]  # drag-free ballistic guess
    v = guess
    eps = 1e-6
    eye = torch.eye(3, **kw)
    pert = torch.cat([torch.zeros(1, 3, **kw), eps * eye, -eps * eye])  # [7, 3]
    for _ in range(max_iter):
        vs = v.unsqueeze(-2) + pert  # [..., 7, 3]
        end = _fly_for(
            p0.unsqueeze(-2), vs, w.unsqueeze(-2), t[..., None].expand(vs.shape[:-1]), params
        )
        resid = end[..., 0, :] - tgt
        # an element stops where it converged, so that it does not depend on the rest of the batch
        active = (torch.nan_to_num(resid, nan=math.inf).abs().amax(-1) >= tol).unsqueeze(-1)
        if not bool(active.any()):
            break
        jac = (end[..., 1:4, :] - end[..., 4:7, :]).transpose(-1, -2) / (2 * eps)  # [..., 3, 3]
        step, info = torch.linalg.solve_ex(jac, resid.unsqueeze(-1))
        bad = (info != 0).unsqueeze(-1) | ~torch.isfinite(step.squeeze(-1))
        # a singular or diverged element restarts from the guess and is judged by its residual
        v = torch.where(active, torch.where(bad, guess, v - step.squeeze(-1)), v)
    else:
        end = _fly_for(p0, v, w, t, params)
        resid = end - tgt
    err = resid.abs().amax(-1)
    ok = torch.isfinite(v).all(-1) & torch.isfinite(err)
    v = torch.where(ok.unsqueeze(-1), v, guess)
    return v, torch.where(ok, err, torch.full_like(err, math.inf))


class BounceAim(NamedTuple):
    """Result of :func:`aim_through_bounce`; shapes ``[..., 3]`` and ``[...]``.

    Attributes:
        vel: initial velocity.
        bounce_x: ``x`` of the bounce on the table.
        flight_time: time from the start to the bounce [s] (as given).
        converged: whether the ball crosses the plane within ``tol`` of the wanted point
            (false where it cannot reach the plane, e.g. because it hits the net).
    """

    vel: torch.Tensor
    bounce_x: torch.Tensor
    flight_time: torch.Tensor
    converged: torch.Tensor


def aim_through_bounce(
    pos: object,
    plane_x: object,
    bounce_y: object,
    flight_time: object,
    params: BallParams = DEFAULT_PARAMS,
    *,
    y_plane: float = geo.HITTING_PLANE_Y,
    spin: object | None = None,
    tol: float = 1e-6,
    max_iter: int = 12,
) -> BounceAim:
    """Initial velocity for a ball that bounces at ``y = bounce_y`` and crosses ``y_plane`` at x.

    The opponent's return (thesis Fig. 4.2): the ball must land on the robot's half and pass the
    robot's virtual hitting plane at the intended lateral position ``plane_x``. For a bounce
    point ``(x_b, bounce_y)`` reached in ``flight_time`` :func:`aim` gives the velocity; Newton's
    method with a finite-difference derivative then adjusts ``x_b`` until the simulated crossing
    (bounce and net included) is at ``plane_x``. Balls that cannot reach the plane are reported,
    not raised.

    Args:
        pos: ``[..., 3]`` start position.
        plane_x: ``[...]`` wanted lateral position on the plane.
        bounce_y: ``[...]`` ``y`` of the bounce on the table.
        flight_time: ``[...]`` time from ``pos`` to the bounce [s].
        params: ball constants.
        y_plane: the plane (default: the robot's hitting plane).
        spin: ``[..., 3]`` spin right after the hit (default zero).
        tol: an element has converged when its crossing is within this of ``plane_x`` [m].
        max_iter: Newton iterations at most.

    Returns:
        :class:`BounceAim` ``(vel, bounce_x, flight_time, converged)``.
    """
    params = _check_params(params)
    p0 = as_tensor(pos, "pos", min_ndim=1)
    check_shape(p0, "pos", (3,))
    kw = {"dtype": p0.dtype, "device": p0.device}
    px = as_tensor(plane_x, "plane_x", **kw)
    by = as_tensor(bounce_y, "bounce_y", **kw)
    ft = _check_flight_time(as_tensor(flight_time, "flight_time", **kw))
    w = torch.zeros(3, **kw) if spin is None else as_tensor(spin, "spin", min_ndim=1, **kw)
    shape = torch.broadcast_shapes(p0.shape[:-1], px.shape, by.shape, ft.shape, w.shape[:-1])
    p0, w = p0.expand(*shape, 3), w.expand(*shape, 3)
    px, by, ft = (x.expand(shape) for x in (px, by, ft))

    def crossing(xb: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Plane crossing ``x``, velocity and validity for bounce points ``xb`` [k, ...]."""
        pk, wk = p0.expand(*xb.shape, 3), w.expand(*xb.shape, 3)
        v0, resid = _aim(pk, torch.stack([xb, by.expand_as(xb)], -1), ft, params, spin=wk,
                         tol=1e-9, max_iter=20)  # fmt: skip
        _, at, valid = _plane_crossing(BallState(pk, v0, wk), y_plane, params, 2.0, 0.01)
        return at.pos[..., 0], v0, valid & (resid < 1e-6)

    # straight-line guess from the start over the bounce to the plane
    frac = (by - p0[..., 1]) / (y_plane - p0[..., 1])
    xb = p0[..., 0] + frac * (px - p0[..., 0])
    step = 1e-5
    for _ in range(max_iter):
        # the bounce point and its finite-difference neighbour in one batch: each element's
        # result does not depend on its batch (see _aim), and the batch costs half as much
        both_x, both_v, both_valid = crossing(torch.stack([xb, xb + step]))
        got, v0, valid = both_x[0], both_v[0], both_valid[0]
        err = got - px
        converged = valid & (err.abs() < tol)
        if bool((converged | ~valid).all()):
            break
        slope = (both_x[1] - got) / step
        slope = torch.where(slope.abs() > 1e-3, slope, torch.ones_like(slope))
        # a trust region of 0.2 m per iteration; converged and unreachable elements stay put
        delta = (err / slope).clamp(-0.2, 0.2)
        xb = torch.where(converged | ~valid, xb, xb - delta)
    return BounceAim(v0, xb, ft.clone(), converged)


# --------------------------------------------------------------------------------------------
# one ball in plain floats

#: A single ball's state as nine floats: position, velocity, spin (each x, y, z).
Floats = tuple[float, float, float, float, float, float, float, float, float]


class ScalarBall:
    """The ball model of this module for one ball, in plain Python floats.

    One ball is what the robot's stroke predicts, aims and judges, and on a batch of one every
    step of the tensor code above is a few dozen tensor operations of a few microseconds each;
    the same arithmetic on floats is ~30 times faster. The methods mirror :func:`_rk4`,
    :func:`_find_root`, :func:`_advance`, :func:`_plane_crossing` and :func:`_fly_for`
    operation for operation (the same equations, events, root finder and tolerances), so that
    the two agree to rounding; ``tests/robots/test_ball.py`` checks it. The public functions of
    this module use it for an unbatched float64 CPU state; batches stay tensors.

    States are :data:`Floats` tuples ``(px, py, pz, vx, vy, vz, wx, wy, wz)``.
    """

    def __init__(self, params: BallParams = DEFAULT_PARAMS) -> None:
        self.params = _check_params(params)
        self._drag = -params.drag
        self._magnus = params.magnus
        self._g = params.gravity
        self.radius = params.radius
        self._level = geo.TABLE_HEIGHT + params.radius
        self._fx = params.table_friction_x - 1.0
        self._fy = params.table_friction_y - 1.0
        self._e = -params.table_restitution
        self._kr = params.inertia_factor * params.radius
        self._net = (params.net_damping, -params.net_restitution, params.net_damping)

    # -- flight --------------------------------------------------------------------------------
    def rk4(self, s: Floats, h: float) -> Floats:
        """One classical RK4 step of length ``h`` (may be 0) in free flight (:func:`_rk4`; the
        drag, Magnus and gravity of the four stages written out)."""
        vx, vy, vz = s[3], s[4], s[5]
        km, kd, g = self._magnus, self._drag, self._g
        wx, wy, wz = km * s[6], km * s[7], km * s[8]  # the Magnus factor on the spin, as _rk4
        hh = 0.5 * h
        c = kd * math.sqrt(vx * vx + vy * vy + vz * vz)
        a1x = c * vx + (wy * vz - wz * vy)
        a1y = c * vy + (wz * vx - wx * vz)
        a1z = c * vz + (wx * vy - wy * vx) - g
        v2x, v2y, v2z = vx + hh * a1x, vy + hh * a1y, vz + hh * a1z
        c = kd * math.sqrt(v2x * v2x + v2y * v2y + v2z * v2z)
        a2x = c * v2x + (wy * v2z - wz * v2y)
        a2y = c * v2y + (wz * v2x - wx * v2z)
        a2z = c * v2z + (wx * v2y - wy * v2x) - g
        v3x, v3y, v3z = vx + hh * a2x, vy + hh * a2y, vz + hh * a2z
        c = kd * math.sqrt(v3x * v3x + v3y * v3y + v3z * v3z)
        a3x = c * v3x + (wy * v3z - wz * v3y)
        a3y = c * v3y + (wz * v3x - wx * v3z)
        a3z = c * v3z + (wx * v3y - wy * v3x) - g
        v4x, v4y, v4z = vx + h * a3x, vy + h * a3y, vz + h * a3z
        c = kd * math.sqrt(v4x * v4x + v4y * v4y + v4z * v4z)
        a4x = c * v4x + (wy * v4z - wz * v4y)
        a4y = c * v4y + (wz * v4x - wx * v4z)
        a4z = c * v4z + (wx * v4y - wy * v4x) - g
        h6 = h / 6.0
        return (
            s[0] + h6 * (vx + 2 * v2x + 2 * v3x + v4x),
            s[1] + h6 * (vy + 2 * v2y + 2 * v3y + v4y),
            s[2] + h6 * (vz + 2 * v2z + 2 * v3z + v4z),
            vx + h6 * (a1x + 2 * a2x + 2 * a3x + a4x),
            vy + h6 * (a1y + 2 * a2y + 2 * a3y + a4y),
            vz + h6 * (a1z + 2 * a2z + 2 * a3z + a4z),
            s[6],
            s[7],
            s[8],
        )

    def fly_for(self, s: Floats, t: float) -> Floats:
        """Free flight for ``t`` seconds in ``max(8, ceil(t / 5 ms))`` RK4 steps (no contacts)."""
        n = max(8, math.ceil(t / 0.005))
        h = t / n
        for _ in range(n):
            s = self.rk4(s, h)
        return s

    # -- events --------------------------------------------------------------------------------
    @staticmethod
    def _root(
        s: Floats,
        hi: float,
        g_start: float,
        g_end: float,
        event: Callable[[Floats], tuple[float, float]],
        fly: Callable[[Floats, float], Floats],
        iters: int = 12,
    ) -> float:
        """:func:`_find_root` for one ball."""
        lo = 0.0
        denom = g_start - g_end
        tau = hi * g_start / denom if denom > 0 else hi
        tau = min(max(tau, 0.0), hi)
        for _ in range(iters):
            g, gdot = event(fly(s, tau))
            if abs(g) < 1e-14:
                break
            if g > 0:
                lo = tau
            else:
                hi = tau
            newton = tau - g / gdot if gdot != 0 else math.nan
            tau = newton if lo <= newton <= hi else 0.5 * (lo + hi)
        return tau

    def _table_event(self, s: Floats) -> tuple[float, float]:
        return s[2] - self._level, s[5]

    def _bounce(self, s: Floats) -> Floats:
        """:func:`_table_bounce` for one ball."""
        r = self.radius
        vx, vy, vz, wx, wy, wz = s[3:]
        dvx = self._fx * (vx - r * wy)
        dvy = self._fy * (vy + r * wx)
        kr = self._kr
        return (s[0], s[1], geo.TABLE_HEIGHT + r, vx + dvx, vy + dvy, self._e * vz,
                wx + dvy / kr, wy - dvx / kr, wz)  # fmt: skip

    def _net_hit(self, s: Floats, sign: float) -> Floats:
        """:func:`_net_hit` for one ball travelling along ``sign`` in ``y``."""
        d, e, _ = self._net
        return (s[0], geo.NET_Y - sign * self.radius, s[2], s[3] * d, s[4] * e, s[5] * d,
                s[6] * d, s[7] * d, s[8] * d)  # fmt: skip

    def advance(
        self, s: Floats, h: float, max_events: int = 4
    ) -> tuple[Floats, bool, tuple[float, float, float], float, bool]:
        """:func:`_advance` for one ball: the state after ``h`` seconds through contacts.

        Returns:
            ``(state, bounce, bounce_pos, bounce_time, net)`` as in :class:`StepEvents`.
        """
        r = self.radius
        remaining, elapsed = h, 0.0
        bounce = net = False
        bounce_pos, bounce_time = (0.0, 0.0, 0.0), 0.0
        rk4, level = self.rk4, self._level
        for _ in range(max_events + 1):
            if not remaining > 0:
                break
            trial = rk4(s, remaining)
            g0_t, g1_t = s[2] - level, trial[2] - level
            table = g0_t > 0 and g1_t <= 0
            sign = math.copysign(1.0, s[4]) if s[4] != 0 else 0.0
            g0_n = -sign * (s[1] - geo.NET_Y) - r
            g1_n = -sign * (trial[1] - geo.NET_Y) - r
            at_net = sign != 0 and g0_n > 0 and g1_n <= 0
            if not (table or at_net):
                s = trial
                break
            tau_t = tau_n = math.inf
            if table:
                tau = self._root(s, remaining, g0_t, g1_t, self._table_event, rk4)
                x, y = rk4(s, tau)[:2]
                table = abs(x) <= geo.TABLE_HALF_WIDTH and abs(y) <= geo.TABLE_HALF_LENGTH
                if table:
                    tau_t = tau
            if at_net:

                def net_event(q: Floats, sign: float = sign) -> tuple[float, float]:
                    return -sign * (q[1] - geo.NET_Y) - r, -sign * q[4]

                tau = self._root(s, remaining, g0_n, g1_n, net_event, rk4)
                q = rk4(s, tau)
                z = q[2] - geo.TABLE_HEIGHT
                at_net = abs(q[0]) <= geo.NET_HALF_WIDTH + r and 0 < z < geo.NET_HEIGHT + r
                if at_net:
                    tau_n = tau
            use_t = table and tau_t <= tau_n
            use_n = at_net and not use_t
            tau = tau_t if use_t else tau_n if use_n else remaining
            at = rk4(s, tau)
            if use_t and not bounce:
                bounce_pos, bounce_time = (at[0], at[1], geo.TABLE_HEIGHT), elapsed + tau
            bounce = bounce or use_t
            net = net or use_n
            s = self._bounce(at) if use_t else self._net_hit(at, sign) if use_n else at
            elapsed += tau
            remaining = remaining - tau if use_t or use_n else 0.0
        else:
            s = rk4(s, remaining)
        return s, bounce, bounce_pos, bounce_time, net

    def propagate(self, s: Floats, duration: float, dt: float = 0.005) -> Floats:
        """:func:`propagate` for one ball: ``duration`` seconds in steps of ``dt``."""
        for k in range(math.ceil(duration / dt - 1e-9)):
            s = self.advance(s, min(max(duration - k * dt, 0.0), dt))[0]
        return s

    def simulate(self, s: Floats, duration: float, dt: float) -> tuple[float, list[tuple]]:
        """:func:`simulate` for one ball.

        Returns:
            The step ``h`` and ``n + 1`` samples ``(state, bounce, bounce_pos, bounce_time,
            net)``, bounce times absolute, the first sample without events.
        """
        n = max(1, round(duration / dt))
        h = duration / n
        out: list[tuple] = [(s, False, (0.0, 0.0, 0.0), 0.0, False)]
        for k in range(n):
            s, bounce, pos, time, net = self.advance(s, h)
            out.append((s, bounce, pos, time + k * h if bounce else time, net))
        return h, out

    def plane_crossing(
        self, s: Floats, y_plane: float, max_time: float = 2.0, dt: float = 0.005
    ) -> tuple[float, Floats, bool]:
        """:func:`predict_plane_crossing` for one ball: ``(t, state at the crossing, valid)``."""
        sign = 1.0 if s[1] - y_plane >= 0 else -1.0

        def event(q: Floats) -> tuple[float, float]:
            return sign * (q[1] - y_plane), sign * q[4]

        def fly(q: Floats, tau: float) -> Floats:
            return self.advance(q, tau)[0]

        t = 0.0
        for k in range(math.ceil(max_time / dt - 1e-9)):
            h = min(dt, max_time - k * dt)
            new = self.advance(s, h)[0]
            g_start, g_end = sign * (s[1] - y_plane), sign * (new[1] - y_plane)
            if g_start > 0 and g_end <= 0:
                tau = self._root(s, h, g_start, g_end, event, fly)
                at = fly(s, tau)
                return t + tau, at, at[2] > self.radius
            if new[2] <= self.radius:
                return float(max_time), new, False
            t += h
            s = new
        return float(max_time), s, False

    # -- aiming --------------------------------------------------------------------------------
    def aim(
        self,
        pos: tuple[float, float, float],
        target: tuple[float, float, float],
        flight_time: float,
        spin: tuple[float, float, float] = (0.0, 0.0, 0.0),
        tol: float = 1e-9,
        max_iter: int = 20,
    ) -> tuple[tuple[float, float, float], float]:
        """:func:`_aim` for one ball: ``(v0, residual [m])`` (``inf`` when it diverged)."""
        t = flight_time
        guess = tuple((b - a) / t + (0.5 * self._g * t if i == 2 else 0.0)
                      for i, (a, b) in enumerate(zip(pos, target, strict=True)))  # fmt: skip
        eps = 1e-6
        tgt = np.array(target)

        def end(v: np.ndarray) -> np.ndarray:
            return np.array(self.fly_for((*pos, *v.tolist(), *spin), t)[:3]) - tgt

        v = np.array(guess)
        for _ in range(max_iter):
            resid = end(v)
            if float(np.nan_to_num(np.abs(resid), nan=math.inf).max()) < tol:
                break
            jac = np.stack([(end(v + d) - end(v - d)) / (2 * eps) for d in np.eye(3) * eps], -1)
            try:
                step = np.linalg.solve(jac, resid)
            except np.linalg.LinAlgError:
                step = np.full(3, math.nan)
            # a singular or diverged iterate restarts from the guess, judged by its residual
            v = v - step if np.isfinite(step).all() else np.array(guess)
        else:
            resid = end(v)
        err = float(np.abs(resid).max())
        if not (np.isfinite(v).all() and math.isfinite(err)):
            return guess, math.inf
        return (float(v[0]), float(v[1]), float(v[2])), err
