"""The robot's three hitting movements: forehand, middle and backhand (thesis Sec. 3.5.1, 4.3.1).

A movement follows the stages of a table-tennis stroke (thesis Fig. 3.5): the arm waits in the
*awaiting* pose; when the movement is initiated it swings to the movement's *preparation* pose
(a rest-to-rest quintic, as fast as the joint velocity and acceleration limits allow); once the
incoming ball is predictable from its flight (``predict_delay`` after the opponent's hit), and no
earlier than ``hit_duration`` before the ball reaches the virtual hitting plane and no earlier
than the arm has reached the preparation pose (the stage order of Fig. 3.5; optional), the
*hitting* stage plans a quintic from the arm's current state to the joint state that puts the
racket on the ball at the plane with the racket velocity and normal that return the ball to the
opponent's court (inverting the racket law of :mod:`.ball`); a *finishing* quintic brings the arm
to rest.

The reference that drives the simulated arm is the plan passed through a joint-space tracker whose
acceleration and velocity saturate at the limits, and the PD drives are force-limited at the
joint torque limits. A plan that needs more than the limits allow is therefore not followed, the
racket misses the ball, and the hitting region of each movement emerges from its preparation pose,
the limits and the time left - nothing states where a movement can hit. With the defaults and a
start 240 ms before the opponent's hit, the forehand returns balls crossing the plane at about
x in [0.15, 0.85] m, the middle movement [-0.25, 0.35] m and the backhand [-0.85, -0.2] m; beyond
+-0.85 m the elbow would need more than its acceleration limit, and beyond +-1.0 m the arm is too
short (see ``benchmarks/table_tennis.py`` and notebook 05 for the measured curves). Because the
preparation to a side pose takes 0.65-0.9 s, the side movements lose balls when started after
about 160 ms before the opponent's hit, and any movement fails when started too late.

The preparation poses are found by IK from several seeds; the one reachable fastest from the
middle pose wins, and the awaiting pose is the solution whose slowest move to a preparation pose
is quickest. The joint acceleration limits are our choice (the WAM's data sheet gives torque
limits, which the drives enforce); the joint velocity limits are the URDF's.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import torch

from ...validation import check_choice
from ..wam import DOF, WAM
from . import ball as B
from . import geometry as geo
from .scene import TableTennisScene

__all__ = [
    "MOVEMENTS",
    "HitPlan",
    "LimitedTracker",
    "Quintic",
    "StrokeConfig",
    "StrokeOutcome",
    "StrokePlanner",
    "execute_stroke",
    "min_quintic_duration",
]

MOVEMENTS = ("forehand", "middle", "backhand")


@dataclass(frozen=True)
class StrokeConfig:
    """Settings of the hitting movements.

    Attributes:
        awaiting_position: racket centre of the awaiting pose (world, m).
        prep_x: racket ``x`` of each movement's preparation pose (forehand on the robot's right).
        prep_height: racket centre height of the preparation poses (m).
        prep_backswing: how far behind the hitting plane the racket waits in preparation (m).
        face: which racket face each movement hits with (+1: normal towards the opponent).
        acceleration_limit: joint acceleration limits (rad/s^2); velocity and torque limits come
            from the URDF.
        predict_delay: time after the opponent's hit from which the ball's flight is known (s).
        hit_duration: longest hitting stage (s): the swing starts this long before the ball
            reaches the hitting plane (from wherever the preparation has brought the arm), or
            later when the ball is predictable only later.
        hit_from_preparation: whether the hitting stage waits until the preparation pose is
            reached (the strict stage order of thesis Fig. 3.5) instead of starting from the
            arm's state on the way there.
        finish_duration: time to bring the arm to rest after the hit (s).
        return_target: ``(x, y)`` on the opponent's court where returns are aimed (m).
        return_flight_times: candidate flight times of the return (s); the first legal one in
            the simulated model wins.
    """

    awaiting_position: tuple[float, float, float] = (0.0, -2.3, 0.7)
    prep_x: dict[str, float] = field(
        default_factory=lambda: {"forehand": 0.6, "middle": 0.0, "backhand": -0.6}
    )
    prep_height: float = 0.75
    prep_backswing: float = 0.2
    face: dict[str, float] = field(
        default_factory=lambda: {"forehand": 1.0, "middle": 1.0, "backhand": -1.0}
    )
    acceleration_limit: tuple[float, ...] = (25.0, 25.0, 30.0, 30.0, 50.0, 50.0, 50.0)
    predict_delay: float = 0.16
    hit_duration: float = 0.35
    hit_from_preparation: bool = True
    finish_duration: float = 0.3
    return_target: tuple[float, float] = (0.0, 0.8)
    return_flight_times: tuple[float, ...] = (0.55, 0.65, 0.75, 0.85)

    def __post_init__(self) -> None:
        for d in (self.prep_x, self.face):
            if set(d) != set(MOVEMENTS):
                raise ValueError(f"prep_x and face must have the keys {MOVEMENTS}, got {set(d)}")
        if len(self.acceleration_limit) != DOF or min(self.acceleration_limit) <= 0:
            raise ValueError(f"acceleration_limit must be {DOF} positive values")
        for name in ("predict_delay", "hit_duration", "finish_duration"):
            if not getattr(self, name) > 0:
                raise ValueError(f"{name} must be positive, got {getattr(self, name)!r}")


class Quintic:
    """Per-joint quintic polynomials with position, velocity, acceleration boundary values.

    Args:
        t0: start time (s).
        duration: ``T > 0`` (s).
        q0, v0, a0, q1, v1, a1: ``[7]`` boundary values at ``t0`` and ``t0 + T``.
    """

    def __init__(
        self,
        t0: float,
        duration: float,
        q0: np.ndarray,
        v0: np.ndarray,
        a0: np.ndarray,
        q1: np.ndarray,
        v1: np.ndarray,
        a1: np.ndarray,
    ) -> None:
        if not duration > 0:
            raise ValueError(f"duration must be positive, got {duration}")
        self.t0, self.duration = float(t0), float(duration)
        T = self.duration
        c0, c1, c2 = q0, v0 * T, a0 * T * T / 2
        # Solve for the normalised coefficients of s^3, s^4, s^5 (s = (t - t0) / T in [0, 1]).
        r0 = q1 - c0 - c1 - c2
        r1 = v1 * T - c1 - 2 * c2
        r2 = a1 * T * T - 2 * c2
        c3 = 10 * r0 - 4 * r1 + 0.5 * r2
        c4 = -15 * r0 + 7 * r1 - r2
        c5 = 6 * r0 - 3 * r1 + 0.5 * r2
        self.c = np.stack([c0, c1, c2, c3, c4, c5])  # [6, 7]

    def __call__(self, t: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Position, velocity and acceleration ``[7]`` each at time ``t`` (clamped to the ends)."""
        T = self.duration
        s = min(max((t - self.t0) / T, 0.0), 1.0)
        c = self.c
        pos = c[0] + s * (c[1] + s * (c[2] + s * (c[3] + s * (c[4] + s * c[5]))))
        vel = (c[1] + s * (2 * c[2] + s * (3 * c[3] + s * (4 * c[4] + s * 5 * c[5])))) / T
        acc = (2 * c[2] + s * (6 * c[3] + s * (12 * c[4] + s * 20 * c[5]))) / (T * T)
        return pos, vel, acc

    def peak_acceleration(self, n: int = 64) -> np.ndarray:
        """Largest |acceleration| of each joint ``[7]`` over the segment (sampled)."""
        ts = self.t0 + np.linspace(0.0, self.duration, n)
        return np.max(np.abs(np.stack([self(t)[2] for t in ts])), axis=0)


def min_quintic_duration(
    q0: np.ndarray, q1: np.ndarray, velocity_limit: np.ndarray, acceleration_limit: np.ndarray
) -> float:
    """Shortest rest-to-rest quintic from ``q0`` to ``q1`` ([7] each) within the limits.

    A rest-to-rest quintic over distance d and time T peaks at velocity 15 d / (8 T) and at
    acceleration 10 d / (sqrt(3) T^2).
    """
    d = np.abs(q1 - q0)
    t_v = 15.0 * d / (8.0 * velocity_limit)
    t_a = np.sqrt(10.0 * d / (math.sqrt(3.0) * acceleration_limit))
    return float(max(np.max(t_v), np.max(t_a), 1e-3))


@dataclass(frozen=True)
class HitPlan:
    """The hitting stage planned for one incoming ball.

    Attributes:
        t_start: time the swing starts (s, relative to the opponent's hit).
        t_hit: time the ball reaches the hitting plane.
        ball_in: ball state predicted at the plane.
        q_hit: ``[7]`` joint angles at the hit; ``qd_hit``: ``[7]`` joint velocities.
        racket_normal, racket_velocity: ``[3]`` wanted at the hit.
        reachable: whether IK put the racket on the ball with the wanted normal.
    """

    t_start: float
    t_hit: float
    ball_in: B.BallState
    q_hit: np.ndarray
    qd_hit: np.ndarray
    racket_normal: np.ndarray
    racket_velocity: np.ndarray
    reachable: bool


class StrokePlanner:
    """Poses and plans of the three hitting movements for one arm.

    Args:
        wam: the arm's kinematics (default ``WAM()``).
        config: movement settings.
        ball_params: ball model used for predictions and aiming.
    """

    def __init__(
        self,
        wam: WAM | None = None,
        config: StrokeConfig | None = None,
        ball_params: B.BallParams = B.DEFAULT_PARAMS,
    ) -> None:
        self.wam = WAM() if wam is None else wam
        self.config = StrokeConfig() if config is None else config
        self.ball_params = ball_params
        self.velocity_limit = self.wam.velocity_limit.numpy()
        self.acceleration_limit = np.asarray(self.config.acceleration_limit, dtype=np.float64)
        self.effort_limit = self.wam.effort_limit.numpy()
        # An elbow-down hanging posture with the racket face towards the opponent seeds the IK.
        nominal = np.array([1.57, -1.5, 0.0, 2.6, -1.0, 0.0, -0.7])
        n = torch.tensor([0.0, 1.0, 0.2], dtype=torch.float64)
        self.prep: dict[str, np.ndarray] = {}
        # the middle pose first; the side poses are sought near it (quick to switch between)
        for m in ("middle", "forehand", "backhand"):
            pos = torch.tensor(
                [
                    self.config.prep_x[m],
                    geo.HITTING_PLANE_Y - self.config.prep_backswing,
                    self.config.prep_height,
                ],
                dtype=torch.float64,
            )
            near = self.prep.get("middle", nominal)
            seeds = torch.cat([self._seeds(near), self._seeds(nominal)])
            self.prep[m] = self._solve(pos, self.config.face[m] * n, seeds, [near])
        self.prep = {m: self.prep[m] for m in MOVEMENTS}
        # The awaiting pose sits between the preparation poses in joint space: of the solutions
        # near their mean, the one from which the slowest preparation is quickest.
        centre = np.mean(list(self.prep.values()), axis=0)
        pos = torch.tensor(self.config.awaiting_position, dtype=torch.float64)
        self.awaiting = self._solve(pos, n, self._seeds(centre), list(self.prep.values()), centre)

    def _seeds(self, base: np.ndarray) -> torch.Tensor:
        """``[15, 7]`` IK seeds: ``base`` ``[7]`` turned about joint 1, forearm roll flipped."""
        turn = torch.tensor([-0.6, -0.3, 0.0, 0.3, 0.6], dtype=torch.float64)
        roll = torch.tensor([0.0, 3.0, -3.0], dtype=torch.float64)
        seeds = torch.as_tensor(base, dtype=torch.float64).repeat(15, 1)
        seeds[:, 0] += turn.repeat_interleave(3)
        seeds[:, 6] += roll.repeat(5)
        return torch.minimum(torch.maximum(seeds, self.wam.lower), self.wam.upper)

    def _solve(
        self,
        pos: torch.Tensor,
        normal: torch.Tensor,
        seeds: torch.Tensor,
        others: list[np.ndarray],
        rest: np.ndarray | None = None,
    ) -> np.ndarray:
        """IK from every seed ``[S, 7]``; the solution with the quickest slowest move to ``others``.

        The cost of a solution is the longest rest-to-rest move (within the velocity and
        acceleration limits) between it and the poses in ``others`` (each ``[7]``); the IK's null
        space pulls towards ``rest`` (default ``others[0]``).
        """
        q_rest = torch.as_tensor(others[0] if rest is None else rest, dtype=torch.float64)
        res = self.wam.ik(pos.expand(len(seeds), 3), normal, seeds, q_rest=q_rest, max_iter=300)
        if not bool(res.success.any()):
            raise RuntimeError(
                f"no IK solution for the pose at {pos.tolist()} (error "
                f"{float(res.position_error.min()):.3g} m); check StrokeConfig poses against "
                "the reach"
            )
        vmax, amax = self.velocity_limit, self.acceleration_limit
        cost = [
            max(min_quintic_duration(o, q, vmax, amax) for o in others) if ok else math.inf
            for q, ok in zip(res.q.numpy(), res.success.tolist(), strict=True)
        ]
        return res.q[int(np.argmin(cost))].numpy()

    def movement(self, name: str) -> str:
        """Validate a movement name."""
        return check_choice(name, "movement", MOVEMENTS)

    def preparation(self, name: str, t_start: float, q_from: np.ndarray) -> Quintic:
        """Rest-to-rest swing from ``q_from`` to the movement's preparation pose."""
        q1 = self.prep[self.movement(name)]
        T = min_quintic_duration(q_from, q1, self.velocity_limit, self.acceleration_limit)
        z = np.zeros(DOF)
        return Quintic(t_start, T, q_from, z, z, q1, z, z)

    def plan_hit(self, name: str, ball_now: B.BallState, t_now: float) -> HitPlan | None:
        """Where, when and how to hit the ball observed at time ``t_now`` (unbatched state).

        Returns ``None`` when the ball never reaches the hitting plane.
        """
        name = self.movement(name)
        cfg = self.config
        t_c, at, valid = B.predict_plane_crossing(
            ball_now, geo.HITTING_PLANE_Y, self.ball_params, dt=0.01
        )
        if not bool(valid):
            return None
        hit_pos = at.pos
        # Outgoing velocity: aim at the return target; keep the first flight time that is legal.
        flight = torch.tensor(cfg.return_flight_times, dtype=torch.float64)
        target = torch.tensor(cfg.return_target, dtype=torch.float64).expand(len(flight), 2)
        v_out = B.aim(hit_pos.expand(len(flight), 3), target, flight, self.ball_params)
        traj = B.simulate(
            B.make_state(hit_pos.expand(len(flight), 3), v_out, at.spin.expand(len(flight), 3)),
            float(flight.max()) + 0.2,
            0.01,
            self.ball_params,
        )
        legal = B.is_legal_return(traj)
        k = int(torch.argmax(legal.to(torch.int8)))
        normal, racket_vel = B.racket_velocity_for_return(at.vel, v_out[k], self.ball_params)
        face = cfg.face[name]
        prep = torch.as_tensor(self.prep[name])
        ik = self.wam.ik(hit_pos, face * normal, prep, q_rest=prep, max_iter=150)
        q_hit = ik.q
        qd_hit = self.wam.joint_velocity(q_hit, racket_vel)
        t_hit = t_now + float(t_c)
        return HitPlan(
            t_start=max(t_now, t_hit - cfg.hit_duration),
            t_hit=t_hit,
            ball_in=at,
            q_hit=q_hit.numpy(),
            qd_hit=qd_hit.numpy(),
            racket_normal=normal.numpy(),
            racket_velocity=racket_vel.numpy(),
            reachable=bool(ik.position_error < 0.01) and bool(legal.any()),
        )

    def swing(self, plan: HitPlan, t_start: float, q0: np.ndarray, v0: np.ndarray) -> Quintic:
        """The hitting quintic from the arm's state at ``t_start`` to the planned hit."""
        z = np.zeros(DOF)
        return Quintic(
            t_start, max(plan.t_hit - t_start, 1e-3), q0, v0, z, plan.q_hit, plan.qd_hit, z
        )

    def finish(self, plan: HitPlan) -> Quintic:
        """Follow-through after the hit: from the hit state to rest, within the joint limits."""
        T = self.config.finish_duration
        q_end = plan.q_hit + plan.qd_hit * T / 2
        q_end = np.clip(q_end, self.wam.lower.numpy(), self.wam.upper.numpy())
        z = np.zeros(DOF)
        return Quintic(plan.t_hit, T, plan.q_hit, plan.qd_hit, z, q_end, z, z)


class LimitedTracker:
    """Joint reference that follows a plan with saturated acceleration and velocity.

    ``a = clip(a_plan + kp (q_plan - q) + kd (v_plan - v), +-a_max)``, integrated per step with
    ``v`` clipped to ``+-v_max``: a feasible plan is followed exactly, an infeasible one lags.
    """

    def __init__(self, q: np.ndarray, v_max: np.ndarray, a_max: np.ndarray) -> None:
        self.q, self.v = q.astype(np.float64).copy(), np.zeros(DOF)
        self.v_max, self.a_max = v_max, a_max
        self.kp, self.kd = 400.0, 40.0

    def update(self, target: tuple[np.ndarray, np.ndarray, np.ndarray], dt: float) -> None:
        """Advance by ``dt`` towards the plan's (position, velocity, acceleration) ``target``."""
        q_p, v_p, a_p = target
        a = a_p + self.kp * (q_p - self.q) + self.kd * (v_p - self.v)
        a = np.clip(a, -self.a_max, self.a_max)
        v_new = np.clip(self.v + a * dt, -self.v_max, self.v_max)
        self.q = self.q + 0.5 * (self.v + v_new) * dt
        self.v = v_new


@dataclass(frozen=True)
class StrokeOutcome:
    """Result of one simulated stroke.

    Attributes:
        success: the ball was returned legally (first bounce on the opponent's half).
        hit: the racket touched the ball.
        landing: ``[2]`` first bounce ``(x, y)`` of the return (NaN where there was none).
        t_hit: planned time of the hit (s, relative to the opponent's hit; NaN if none).
        racket_path: ``[S, 3]`` racket centre every 10 ms; ``ball_path``: ``[S', 3]`` ball at
            the same times (NaN before the opponent's hit), then the return flight of the ball
            model every 10 ms.
        joint_path: ``[S, 7]`` simulated joint angles every 10 ms (to draw the arm).
    """

    success: bool
    hit: bool
    landing: np.ndarray
    t_hit: float
    racket_path: np.ndarray
    ball_path: np.ndarray
    joint_path: np.ndarray


_PARKED_BALL = B.BallState(
    torch.tensor([3.0, 3.0, geo.BALL_RADIUS]), torch.zeros(3), torch.zeros(3)
)


def execute_stroke(
    scene: TableTennisScene,
    planner: StrokePlanner,
    ball_after_hit: B.BallState,
    movement: str,
    start_time: float,
) -> StrokeOutcome:
    """Simulate one hitting movement in the SAPIEN scene.

    Time 0 is the opponent's hit, when the ball leaves the opponent's racket in state
    ``ball_after_hit`` (unbatched); the movement is initiated at ``start_time`` (negative:
    before the opponent's hit). After the racket contact the return flight is finished with the
    ball model of :mod:`.ball` (the scene's ball follows it to millimetres) to judge legality.

    Raises:
        ValueError: unknown movement, or ``start_time`` not before the ball reaches the plane.
    """
    movement = planner.movement(movement)
    cfg = planner.config
    t_cross, _, valid = B.predict_plane_crossing(
        ball_after_hit, geo.HITTING_PLANE_Y, planner.ball_params, dt=0.01
    )
    if not bool(valid):
        raise ValueError("ball_after_hit never reaches the robot's hitting plane")
    if not math.isfinite(start_time) or start_time >= float(t_cross):
        raise ValueError(
            f"start_time {start_time!r} s must come before the ball reaches the hitting plane "
            f"({float(t_cross):.3f} s after the opponent's hit)"
        )
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
            plan = planner.plan_hit(movement, scene.ball_state(), t)
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
        after = scene.ball_state()
        # every return lands within 1.2 s (the planned flights take at most ~0.9 s)
        traj = B.simulate(after, 1.2, 0.01, planner.ball_params)
        land = B.landing(traj)
        if bool(land.landed):
            landing = land.pos[:2].numpy()
        success = bool(B.is_legal_return(traj))
        ball_path.extend(traj.pos[::1].numpy())
    return StrokeOutcome(
        success=success,
        hit=hit,
        landing=landing,
        t_hit=math.nan if plan is None else plan.t_hit,
        racket_path=np.asarray(racket_path).reshape(-1, 3),
        ball_path=np.asarray(ball_path).reshape(-1, 3),
        joint_path=np.asarray(joint_path).reshape(-1, DOF),
    )
