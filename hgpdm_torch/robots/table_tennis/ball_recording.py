"""Recorded flights: :func:`simulate` samples a flight every step, and what a recording tells.

A :class:`BallTrajectory` holds the sampled states and contacts; :func:`landing` reads its first
table bounce and :func:`is_legal_return` whether that bounce is a legal return.
"""

from __future__ import annotations

from typing import NamedTuple

import torch

from hgpdm_torch.robots.table_tennis import geometry as geo
from hgpdm_torch.robots.table_tennis.ball_events import advance_events
from hgpdm_torch.robots.table_tennis.ball_scalar import is_single_ball, scalar_ball, state_floats
from hgpdm_torch.robots.table_tennis.ball_state import (
    DEFAULT_PARAMS,
    BallParams,
    BallState,
    check_flight,
    check_result,
)

from ...progress import tqdm

__all__ = [
    "BallTrajectory",
    "Landing",
    "is_legal_return",
    "landing",
    "simulate",
]


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
    state, params, dt, duration, n = check_flight(
        state, params, dt, duration, "duration", lambda r: max(1, round(r))
    )
    if is_single_ball(state):
        traj = _trajectory(*scalar_ball(params).simulate(state_floats(state), duration, dt))
        check_result("simulate", traj.pos, traj.vel, traj.spin, traj.bounce_pos, traj.bounce_time)
        return traj
    h_val = duration / n
    h = torch.full(state.batch_shape, h_val, dtype=state.pos.dtype, device=state.pos.device)
    pos, vel, spin = [state.pos], [state.vel], [state.spin]
    no = torch.zeros(state.batch_shape, dtype=torch.bool, device=state.pos.device)
    bounce, bpos, btime, net = [no], [torch.zeros_like(state.pos)], [h * 0], [no]
    for k in tqdm(range(n), disable=not progress, desc="ball", leave=False):
        state, ev = advance_events(state, h, params)
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
    check_result("simulate", traj.pos, traj.vel, traj.spin, traj.bounce_pos, traj.bounce_time)
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
