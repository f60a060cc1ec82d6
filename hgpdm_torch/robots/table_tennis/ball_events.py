"""Event-located stepping: advancing balls through table and net contacts.

Table and net contacts are events located inside a step to machine precision (a safeguarded
Newton search on the RK4 flow), so results do not depend on the step size for ``dt <= 10 ms``.
:func:`step_events`, :func:`step` and :func:`propagate` advance a batch of balls (or one ball,
through :class:`~hgpdm_torch.robots.table_tennis.ball_scalar.ScalarBall`) and report the
contacts as :class:`StepEvents`.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import NamedTuple

import torch

from hgpdm_torch.robots.table_tennis import geometry as geo
from hgpdm_torch.robots.table_tennis.ball_contact import net_hit, table_bounce
from hgpdm_torch.robots.table_tennis.ball_dynamics import rk4_step
from hgpdm_torch.robots.table_tennis.ball_scalar import (
    floats_to_state,
    is_single_ball,
    scalar_ball,
    state_floats,
)
from hgpdm_torch.robots.table_tennis.ball_state import (
    DEFAULT_PARAMS,
    MAX_DURATION,
    BallParams,
    BallState,
    check_dt,
    check_params,
    check_result,
    check_state,
    check_steps,
)
from hgpdm_torch.validation import as_tensor

__all__ = [
    "StepEvents",
    "propagate",
    "step",
    "step_events",
]


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


# An event maps a state to a scalar ``g`` (positive before contact) and its time derivative.
_Event = Callable[[BallState], tuple[torch.Tensor, torch.Tensor]]
_Propagator = Callable[[BallState, torch.Tensor], BallState]


def find_event_root(
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


class PlaneEvent:
    """``g = sign * (y - y_plane) - offset``; ``sign`` [...] orients g to be positive at start."""

    def __init__(self, y_plane: torch.Tensor, sign: torch.Tensor, offset: float = 0.0) -> None:
        self.y_plane, self.sign, self.offset = y_plane, sign, offset

    def __call__(self, s: BallState) -> tuple[torch.Tensor, torch.Tensor]:
        return (
            self.sign * (s.pos[..., 1] - self.y_plane) - self.offset,
            self.sign * s.vel[..., 1],
        )


def subset_state(state: BallState, mask: torch.Tensor) -> BallState:
    """The balls where ``mask`` [...] is true, flattened to ``[k]``."""
    return BallState(state.pos[mask], state.vel[mask], state.spin[mask])


def scatter_masked(full: torch.Tensor, mask: torch.Tensor, values: torch.Tensor) -> torch.Tensor:
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


def advance_events(
    state: BallState, h: torch.Tensor, params: BallParams, max_events: int = 4
) -> tuple[BallState, StepEvents]:
    """Propagate each ball by its own time ``h`` [...] through table and net contacts."""
    trial = rk4_step(state, h, params)
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
        return rk4_step(s, tau, params)

    for _ in range(max_events + 1):
        active = remaining > 0
        if not bool(active.any()):
            break
        trial = rk4_step(state, remaining, params)
        g0_t, _ = table_event(state)
        g1_t, _ = table_event(trial)
        table_cand = active & (g0_t > 0) & (g1_t <= 0)
        sign = torch.sign(state.vel[..., 1])
        net_event = PlaneEvent(torch.full_like(h, geo.NET_Y), -sign, params.radius)
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
            tau = find_event_root(
                subset_state(state, m), remaining[m], g0_t[m], g1_t[m], table_event, fly
            )
            table_cand = scatter_masked(
                table_cand, m, _on_table(fly(subset_state(state, m), tau).pos)
            )
            tau_t = scatter_masked(tau_t, table_cand, tau[table_cand[m]])
        if bool(net_cand.any()):
            m = net_cand
            sub_event = PlaneEvent(net_event.y_plane[m], net_event.sign[m], params.radius)
            tau = find_event_root(
                subset_state(state, m), remaining[m], g0_n[m], g1_n[m], sub_event, fly
            )
            net_cand = scatter_masked(
                net_cand, m, _at_net(fly(subset_state(state, m), tau).pos, params)
            )
            tau_n = scatter_masked(tau_n, net_cand, tau[net_cand[m]])
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
        after = table_bounce(at, params).where(use_t, net_hit(at, sign, params).where(use_n, at))
        state = after.where(active, state)
        elapsed = elapsed + torch.where(active, tau, zeros)
        remaining = torch.where(hit, remaining - tau, zeros)
    else:
        # more contacts in one step than max_events (a ball trapped at the net): finish in flight
        state = rk4_step(state, remaining, params)
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
    state = check_state(state)
    params = check_params(params)
    dt = check_dt(dt)
    if is_single_ball(state):
        s, bounce, pos, time, net = scalar_ball(params).advance(state_floats(state), dt)
        new = floats_to_state(s)
        events = StepEvents(
            torch.tensor(bounce),
            torch.tensor(pos, dtype=torch.float64),
            torch.tensor(time, dtype=torch.float64),
            torch.tensor(net),
        )
    else:
        h = torch.full(state.batch_shape, dt, dtype=state.pos.dtype, device=state.pos.device)
        new, events = advance_events(state, h, params)
    check_result("step", *new, events.bounce_pos, events.bounce_time)
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
    state = check_state(state)
    params = check_params(params)
    dt = check_dt(dt)
    d = as_tensor(duration, "duration", dtype=state.pos.dtype, device=state.pos.device)
    if bool((d < 0).any()):
        raise ValueError("duration must be >= 0")
    longest = float(d.max()) if d.numel() else 0.0
    if longest > MAX_DURATION:
        raise ValueError(
            f"duration must be at most MAX_DURATION = {MAX_DURATION:g} s, got {longest:g}"
        )
    d = torch.broadcast_to(d, state.batch_shape)
    n = check_steps(math.ceil(longest / dt - 1e-9) if d.numel() else 0, "duration", dt)
    if is_single_ball(state):
        state = floats_to_state(scalar_ball(params).propagate(state_floats(state), float(d), dt))
    else:
        for k in range(n):
            state = advance_events(state, (d - k * dt).clamp(0.0, dt), params)[0]
    check_result("propagate", *state)
    return state
