"""Aiming: the initial velocity that sends a ball to a target (shooting on the flight model).

:func:`aim` reaches a point in a given flight time (table and net not modelled on the way);
:func:`aim_through_bounce` makes the ball bounce on a line of the table and then cross a plane
at a wanted point (the opponent's return, thesis Fig. 4.2).
"""

from __future__ import annotations

import math
from typing import NamedTuple

import torch

from hgpdm_torch.robots.table_tennis import geometry as geo
from hgpdm_torch.robots.table_tennis.ball_crossing import find_plane_crossing
from hgpdm_torch.robots.table_tennis.ball_dynamics import fly_batch_for
from hgpdm_torch.robots.table_tennis.ball_scalar import is_single_ball, scalar_ball
from hgpdm_torch.robots.table_tennis.ball_state import (
    DEFAULT_PARAMS,
    MAX_DURATION,
    BallParams,
    BallState,
    check_params,
)
from hgpdm_torch.validation import as_tensor, check_shape

__all__ = [
    "BounceAim",
    "aim",
    "aim_through_bounce",
]


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
    params = check_params(params)
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
    if shape == (3,) and is_single_ball(BallState(p0, tgt, w)):
        v1, err1 = scalar_ball(params).aim(
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
        end = fly_batch_for(
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
        end = fly_batch_for(p0, v, w, t, params)
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
    params = check_params(params)
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
        _, at, valid = find_plane_crossing(BallState(pk, v0, wk), y_plane, params, 2.0, 0.01)
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
