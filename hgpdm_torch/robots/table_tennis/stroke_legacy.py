"""The previous stroke executor, kept as the reference of the current one.

:func:`execute_stroke_legacy` and :func:`plan_hit_legacy` are this implementation: 1 ms PhysX steps
throughout, the ball in PhysX from the opponent's hit, the tracker and the drive targets updated per
step in Python, and uncached planning on batched tensors (its single-ball tensor calls run on a
batch of one). It is not used to compute rewards; it exists only as the baseline of the speed
benchmark (``benchmarks/table_tennis.py``) and of the reward-agreement tests
(``tests/robots/test_strokes.py``), which check that the fast executor of
:mod:`~hgpdm_torch.robots.table_tennis.stroke_execution` returns the same rewards.
"""

from __future__ import annotations

import math

import numpy as np
import torch

from ..wam import DOF
from . import ball as B
from . import geometry as geo
from .scene import TableTennisScene
from .stroke_execution import StrokeOutcome, check_start_time
from .stroke_planner import HitPlan, StrokePlanner
from .stroke_quintic import Quintic
from .stroke_tracker import LimitedTracker

__all__ = ["execute_stroke_legacy", "plan_hit_legacy"]

_PARKED_BALL = B.BallState(
    torch.tensor([3.0, 3.0, geo.BALL_RADIUS]), torch.zeros(3), torch.zeros(3)
)


def plan_hit_legacy(
    planner: StrokePlanner, name: str, ball_now: B.BallState, t_now: float
) -> HitPlan | None:
    """The previous :meth:`~.stroke_planner.StrokePlanner.plan_hit`: batched tensor code on a
    batch of one, no cache."""
    cfg = planner.config
    one = B.BallState(*(x.unsqueeze(0) for x in ball_now))
    t_c, at, valid = B.predict_plane_crossing(
        one, geo.HITTING_PLANE_Y, planner.ball_params, dt=0.01
    )
    if not bool(valid):
        return None
    t_c, at = t_c[0], B.BallState(*(x[0] for x in at))
    hit_pos = at.pos
    # Outgoing velocity: aim at the return target; keep the first flight time that is legal.
    flight = torch.tensor(cfg.return_flight_times, dtype=torch.float64)
    target = torch.tensor(cfg.return_target, dtype=torch.float64).expand(len(flight), 2)
    v_out = B.aim(hit_pos.expand(len(flight), 3), target, flight, planner.ball_params)
    traj = B.simulate(
        B.make_state(hit_pos.expand(len(flight), 3), v_out, at.spin.expand(len(flight), 3)),
        float(flight.max()) + 0.2,
        0.01,
        planner.ball_params,
    )
    legal = B.is_legal_return(traj)
    k = int(torch.argmax(legal.to(torch.int8)))
    normal, racket_vel = B.racket_velocity_for_return(at.vel, v_out[k], planner.ball_params)
    face = cfg.face[name]
    prep = torch.as_tensor(planner.prep[name])
    ik = planner.wam.ik(hit_pos[None], face * normal, prep, q_rest=prep, max_iter=150)
    q_hit = ik.q[0]
    qd_hit = planner.wam.joint_velocity(q_hit[None], racket_vel[None])[0]
    t_hit = t_now + float(t_c)
    return HitPlan(
        t_start=max(t_now, t_hit - cfg.hit_duration),
        t_hit=t_hit,
        ball_in=at,
        q_hit=q_hit.numpy(),
        qd_hit=qd_hit.numpy(),
        racket_normal=normal.numpy(),
        racket_velocity=racket_vel.numpy(),
        reachable=bool(ik.position_error[0] < 0.01) and bool(legal.any()),
    )


def execute_stroke_legacy(
    scene: TableTennisScene,
    planner: StrokePlanner,
    ball_after_hit: B.BallState,
    movement: str,
    start_time: float,
) -> StrokeOutcome:
    """The previous :func:`.stroke_execution.execute_stroke`, with its arguments and checks,
    unchanged but for the start-time check; its single-ball tensor calls run on a batch of one,
    as they did before unbatched states took the float path of :mod:`.ball`."""
    movement = planner.movement(movement)
    if not isinstance(ball_after_hit, B.BallState):
        raise TypeError(f"ball_after_hit must be a BallState, got {type(ball_after_hit).__name__}")
    cfg = planner.config
    t_cross, _, valid = B.predict_plane_crossing(
        B.BallState(*(x.unsqueeze(0) for x in ball_after_hit)),
        geo.HITTING_PLANE_Y,
        planner.ball_params,
        dt=0.01,
    )
    if not bool(valid):
        raise ValueError("ball_after_hit never reaches the robot's hitting plane")
    start_time = check_start_time(start_time, float(t_cross))
    dt = scene.dt
    tracker = LimitedTracker(planner.awaiting, planner.velocity_limit, planner.acceleration_limit)
    scene.set_robot(planner.awaiting)
    scene.set_ball(_PARKED_BALL)
    t = min(start_time, 0.0)
    ball_in_play = False
    prep: Quintic | None = None
    plan: HitPlan | None = None
    swing: Quintic | None = None
    finish: Quintic | None = None
    hold = (planner.awaiting, np.zeros(DOF), np.zeros(DOF))
    contact_time = math.nan
    racket_path, ball_path, joint_path = [], [], []
    t_end = float(t_cross) + 0.15
    k = 0
    while t < t_end:
        if not ball_in_play and t >= 0.0:
            scene.set_ball(ball_after_hit)
            ball_in_play = True
        if prep is None and t >= start_time:
            prep = planner.preparation(movement, t, tracker.q)
        if plan is None and prep is not None and ball_in_play and t >= cfg.predict_delay:
            plan = plan_hit_legacy(planner, movement, scene.ball_state(), t)
            if plan is None:
                break
        # The hitting stage replans from the arm's current state; unless configured to wait for
        # the preparation pose, also when the preparation is not finished yet.
        ready = prep is not None and (not cfg.hit_from_preparation or t >= prep.t0 + prep.duration)
        if plan is not None and swing is None and ready and t >= plan.t_start:
            if t < plan.t_hit:
                swing = planner.swing(plan, t, tracker.q, tracker.v)
                finish = planner.finish(plan)
        if swing is not None and finish is not None:
            target = swing(t) if t < plan.t_hit else finish(t)
        elif prep is not None:
            target = prep(t)
        else:
            target = hold
        tracker.update(target, dt)
        scene.set_targets(tracker.q, tracker.v)
        scene.step()
        t += dt
        k += 1
        ball_pos, ball_vel, _ = scene.ball_arrays()
        if ball_in_play:
            if math.isnan(contact_time) and ball_vel[1] > 0 and ball_pos[1] < 0:
                contact_time = t
            if not math.isnan(contact_time) and t >= contact_time + 0.01:
                break
            if ball_pos[2] < 2 * geo.BALL_RADIUS:
                break
        if k % 10 == 0:
            racket_path.append(scene.racket_pose()[0])
            ball_path.append(ball_pos if ball_in_play else np.full(3, np.nan))
            joint_path.append(scene.robot_state()[0])
    landing = np.full(2, np.nan)
    success = False
    hit = not math.isnan(contact_time)
    if hit:
        after = B.BallState(*(x.unsqueeze(0) for x in scene.ball_state()))
        # every return lands within 1.2 s (the planned flights take at most ~0.9 s)
        traj = B.simulate(after, 1.2, 0.01, planner.ball_params)
        land = B.landing(traj)
        if bool(land.landed):
            landing = land.pos[0, :2].numpy()
        success = bool(B.is_legal_return(traj))
        ball_path.extend(traj.pos[0].numpy())
    return StrokeOutcome(
        success=success,
        hit=hit,
        landing=landing,
        t_hit=math.nan if plan is None else plan.t_hit,
        racket_path=np.asarray(racket_path).reshape(-1, 3),
        ball_path=np.asarray(ball_path).reshape(-1, 3),
        joint_path=np.asarray(joint_path).reshape(-1, DOF),
    )
