"""When and where a ball crosses a vertical plane ``y = const``, bounces included.

The robot predicts the ball at its virtual hitting plane with :func:`predict_plane_crossing`
(thesis Fig. 4.2); the crossing is located exactly inside a step, as the contact events are.
"""

from __future__ import annotations

import math

import torch

from hgpdm_torch.robots.table_tennis.ball_events import (
    PlaneEvent,
    advance_events,
    find_event_root,
    scatter_masked,
    subset_state,
)
from hgpdm_torch.robots.table_tennis.ball_scalar import (
    floats_to_state,
    is_single_ball,
    scalar_ball,
    state_floats,
)
from hgpdm_torch.robots.table_tennis.ball_state import (
    DEFAULT_PARAMS,
    BallParams,
    BallState,
    check_flight,
    check_result,
)
from hgpdm_torch.validation import as_tensor

__all__ = ["predict_plane_crossing"]


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
    state, params, dt, max_time, _ = check_flight(
        state, params, dt, max_time, "max_time", lambda r: math.ceil(r - 1e-9)
    )
    t_cross, out, valid = find_plane_crossing(state, y_plane, params, max_time, dt)
    check_result("predict_plane_crossing", t_cross, *out)
    return t_cross, out, valid


def find_plane_crossing(
    state: BallState, y_plane: float | torch.Tensor, params: BallParams, max_time: float, dt: float
) -> tuple[torch.Tensor, BallState, torch.Tensor]:
    """:func:`predict_plane_crossing` without input checks (also for trial states of solvers,
    which may leave the documented ranges)."""
    yp = as_tensor(y_plane, "y_plane", dtype=state.pos.dtype, device=state.pos.device)
    if is_single_ball(state) and yp.dim() == 0:
        t, at, ok = scalar_ball(params).plane_crossing(state_floats(state), float(yp), max_time, dt)
        return torch.tensor(t, dtype=torch.float64), floats_to_state(at), torch.tensor(ok)
    yp = torch.broadcast_to(yp, state.batch_shape).clone()
    g0 = state.pos[..., 1] - yp
    event = PlaneEvent(yp, torch.where(g0 >= 0, 1.0, -1.0).to(yp.dtype))

    def fly(s: BallState, tau: torch.Tensor) -> BallState:
        return advance_events(s, tau, params)[0]

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
        new, _ = advance_events(state, h, params)
        g_start, _ = event(state)
        g_end, _ = event(new)
        crossed = ~done & (g_start > 0) & (g_end <= 0)
        if bool(crossed.any()):
            m = crossed
            sub_event = PlaneEvent(event.y_plane[m], event.sign[m])
            sub = subset_state(state, m)
            tau = find_event_root(sub, h[m], g_start[m], g_end[m], sub_event, fly)
            at = fly(sub, tau)
            out = BallState(*(scatter_masked(o, m, a) for o, a in zip(out, at, strict=True)))
            t_cross = scatter_masked(t_cross, m, t + tau)
            valid = scatter_masked(valid, m, at.pos[:, 2] > params.radius)
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
