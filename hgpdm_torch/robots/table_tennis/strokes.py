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

Speed (``benchmarks/table_tennis.py``: ~12 times the strokes per second of 1 ms PhysX steps
throughout, with the same rewards): the arm's reference is still computed every 1 ms, but in blocks
of up to 10 ms that are one matrix product (:meth:`LimitedTracker.update_many`) and one PhysX step.
Steps are short (1 ms; 2 ms until 30 ms before the hit) from 100 ms before the planned hit to 20 ms
after it, and whenever PhysX simulates the ball: from before it can touch the arm until it cannot,
and through its bounce on the table. Elsewhere the ball is parked and the ball model flies it in
floats (:class:`.ball.ScalarBall`). A ball's prediction, return aim and hitting IK are cached by
the planner, so the 15 strokes of a reward-table row plan once per movement.
``execute_stroke(..., legacy=True)`` keeps the previous implementation as the reference of the
benchmark and of the agreement tests.
"""

from __future__ import annotations

import math
from collections import OrderedDict
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
import torch

from ...validation import check_choice
from ..wam import DOF, WAM
from . import ball as B
from . import geometry as geo
from .scene import TableTennisScene

__all__ = [
    "EARLIEST_START",
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
_CACHE_SIZE = 256  # planner cache entries: a reward-table row needs 5 (crossing, return, 3 IK)


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


_POWERS = np.arange(6)


class Quintic:
    """Per-joint quintic polynomials with position, velocity, acceleration boundary values.

    Args:
        t0: start time (s).
        duration: ``T > 0`` (s).
        q0: ``[7]`` joint positions at ``t0``.
        v0: ``[7]`` joint velocities at ``t0``.
        a0: ``[7]`` joint accelerations at ``t0``.
        q1: ``[7]`` joint positions at ``t0 + T``.
        v1: ``[7]`` joint velocities at ``t0 + T``.
        a1: ``[7]`` joint accelerations at ``t0 + T``.
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
        # position, velocity and acceleration coefficients of s^0..s^5 side by side: [6, 21]
        vel, acc = np.zeros_like(self.c), np.zeros_like(self.c)
        vel[:5] = self.c[1:] * np.arange(1.0, 6.0)[:, None] / T
        acc[:4] = self.c[2:] * np.array([2.0, 6.0, 12.0, 20.0])[:, None] / (T * T)
        self._c3 = np.concatenate([self.c, vel, acc], axis=1)

    def __call__(self, t: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Position, velocity and acceleration ``[7]`` each at time ``t`` (clamped to the ends)."""
        T = self.duration
        s = min(max((t - self.t0) / T, 0.0), 1.0)
        c = self.c
        pos = c[0] + s * (c[1] + s * (c[2] + s * (c[3] + s * (c[4] + s * c[5]))))
        vel = (c[1] + s * (2 * c[2] + s * (3 * c[3] + s * (4 * c[4] + s * 5 * c[5])))) / T
        acc = (2 * c[2] + s * (6 * c[3] + s * (12 * c[4] + s * 20 * c[5]))) / (T * T)
        return pos, vel, acc

    def at(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """:meth:`__call__` at many times ``t`` ``[n]``: position, velocity, acceleration
        ``[n, 7]`` each."""
        s = np.minimum(np.maximum((t - self.t0) / self.duration, 0.0), 1.0)
        out = (s[:, None] ** _POWERS) @ self._c3  # [n, 21]
        return out[:, :DOF], out[:, DOF : 2 * DOF], out[:, 2 * DOF :]

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
        self.scalar = B.ScalarBall(ball_params)
        self._cache: OrderedDict[tuple, object] = OrderedDict()
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

    def plan_hit(
        self, name: str, ball_now: B.BallState, t_now: float, *, legacy: bool = False
    ) -> HitPlan | None:
        """Where, when and how to hit the ball observed at time ``t_now`` (unbatched state).

        The ball's crossing of the hitting plane is predicted, the return is aimed at
        ``config.return_target`` with the first of ``config.return_flight_times`` whose
        simulated flight is legal (the first when none is), the racket law is inverted for the
        racket's normal and velocity, and IK from the preparation pose gives the joint state.
        The ball part depends on the observed ball only and is shared by the three movements;
        both parts are cached (small LRU), so the 15 strokes of a reward-table row predict and
        aim once. ``legacy=True`` runs the previous, uncached implementation on batched tensors
        (kept for :func:`execute_stroke`'s ``legacy`` option).

        Returns ``None`` when the ball never reaches the hitting plane.
        """
        name = self.movement(name)
        if legacy:
            return self._plan_hit_legacy(name, ball_now, t_now)
        ball = B.make_state(*ball_now)
        if ball.pos.shape != (3,):
            raise ValueError("ball_now must be a single ball (fields of shape [3])")
        return self._plan(name, tuple(torch.cat(tuple(ball)).tolist()), t_now)

    def _memo(self, key: tuple, compute: Callable[[], object]) -> object:
        """``compute()``, cached under ``key`` (LRU of ``_CACHE_SIZE`` entries)."""
        if key in self._cache:
            self._cache.move_to_end(key)
            return self._cache[key]
        value = compute()
        self._cache[key] = value
        if len(self._cache) > _CACHE_SIZE:
            self._cache.popitem(last=False)
        return value

    def crossing(self, ball: B.Floats) -> tuple[float, B.Floats, bool]:
        """When and where the ball (nine floats) crosses the hitting plane (cached)."""
        return self._memo(  # type: ignore[return-value]
            ("crossing", ball),
            lambda: self.scalar.plane_crossing(ball, geo.HITTING_PLANE_Y, 2.0, 0.01),
        )

    def _return(self, ball: B.Floats) -> tuple | None:
        """The movement-independent part of a plan: ``(t_c, at, normal, racket_vel, legal)``."""
        t_c, at, valid = self.crossing(ball)
        if not valid:
            return None
        cfg = self.config
        hit_pos, spin = at[:3], at[6:]
        target = (*cfg.return_target, geo.TABLE_HEIGHT + self.ball_params.radius)
        duration = max(cfg.return_flight_times) + 0.2
        first, legal = None, False
        for flight in cfg.return_flight_times:  # the first legal flight time wins
            v_out, err = self.scalar.aim(hit_pos, target, flight)  # aimed spin-free
            if not err <= 1e-6:
                raise ValueError(
                    f"aim did not converge (max residual {err:.2e} m); "
                    "the target may be unreachable in the given flight_time"
                )
            first = v_out if first is None else first
            out = B.make_state(
                *(torch.tensor(x, dtype=torch.float64) for x in (hit_pos, v_out, spin))
            )
            if bool(B.is_legal_return(B.simulate(out, duration, 0.01, self.ball_params))):
                first, legal = v_out, True
                break
        normal, racket_vel = B.racket_velocity_for_return(
            torch.tensor(at[3:6], dtype=torch.float64),
            torch.tensor(first, dtype=torch.float64),
            self.ball_params,
        )
        return t_c, at, normal, racket_vel, legal

    def _plan(self, name: str, ball: B.Floats, t_now: float) -> HitPlan | None:
        """:meth:`plan_hit` for a ball given as nine floats."""
        ret = self._memo(("return", ball), lambda: self._return(ball))
        if ret is None:
            return None
        t_c, at, normal, racket_vel, legal = ret  # type: ignore[misc]

        def joints() -> tuple[np.ndarray, np.ndarray, float]:
            prep = torch.as_tensor(self.prep[name])
            hit_pos = torch.tensor(at[:3], dtype=torch.float64)
            ik = self.wam.ik(hit_pos, self.config.face[name] * normal, prep, q_rest=prep,
                             max_iter=150)  # fmt: skip
            qd = self.wam.joint_velocity(ik.q, racket_vel)
            return ik.q.numpy(), qd.numpy(), float(ik.position_error)

        q_hit, qd_hit, error = self._memo(("joints", name, ball), joints)  # type: ignore[misc]
        t_hit = t_now + t_c
        return HitPlan(
            t_start=max(t_now, t_hit - self.config.hit_duration),
            t_hit=t_hit,
            ball_in=B.BallState(
                *(torch.tensor(at[i : i + 3], dtype=torch.float64) for i in (0, 3, 6))
            ),
            q_hit=q_hit,
            qd_hit=qd_hit,
            racket_normal=normal.numpy(),
            racket_velocity=racket_vel.numpy(),
            reachable=error < 0.01 and legal,
        )

    def _plan_hit_legacy(self, name: str, ball_now: B.BallState, t_now: float) -> HitPlan | None:
        """The previous :meth:`plan_hit`: batched tensor code on a batch of one, no cache."""
        cfg = self.config
        one = B.BallState(*(x.unsqueeze(0) for x in ball_now))
        t_c, at, valid = B.predict_plane_crossing(
            one, geo.HITTING_PLANE_Y, self.ball_params, dt=0.01
        )
        if not bool(valid):
            return None
        t_c, at = t_c[0], B.BallState(*(x[0] for x in at))
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
        ik = self.wam.ik(hit_pos[None], face * normal, prep, q_rest=prep, max_iter=150)
        q_hit = ik.q[0]
        qd_hit = self.wam.joint_velocity(q_hit[None], racket_vel[None])[0]
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


_BLOCKS: dict[tuple, tuple[np.ndarray, ...]] = {}  # LimitedTracker.update_many's matrices


class LimitedTracker:
    """Joint reference that follows a plan with saturated acceleration and velocity.

    ``a = clip(a_plan + kp (q_plan - q) + kd (v_plan - v), +-a_max)``, integrated per step with
    ``v`` clipped to ``+-v_max``: a feasible plan is followed exactly, an infeasible one lags.
    """

    def __init__(self, q: np.ndarray, v_max: np.ndarray, a_max: np.ndarray) -> None:
        self.q, self.v = q.astype(np.float64).copy(), np.zeros(DOF)
        self.v_max, self.a_max = v_max, a_max
        self.kp, self.kd = 400.0, 40.0
        self._qv = np.empty((2, DOF))
        self._mats: dict[tuple[int, float], tuple[np.ndarray, ...]] = {}

    def update(self, target: tuple[np.ndarray, np.ndarray, np.ndarray], dt: float) -> None:
        """Advance by ``dt`` towards the plan's (position, velocity, acceleration) ``target``."""
        q_p, v_p, a_p = target
        a = a_p + self.kp * (q_p - self.q) + self.kd * (v_p - self.v)
        a = np.minimum(np.maximum(a, -self.a_max), self.a_max)  # np.clip, without its overhead
        v_new = np.minimum(np.maximum(self.v + a * dt, -self.v_max), self.v_max)
        self.q = self.q + 0.5 * (self.v + v_new) * dt
        self.v = v_new

    def update_many(
        self,
        q_p: np.ndarray,
        v_p: np.ndarray,
        a_p: np.ndarray,
        dt: float,
        u: np.ndarray | None = None,
    ) -> None:
        """``n`` calls of :meth:`update` at once: targets ``[n, 7]`` each, step ``dt``.

        Unsaturated, one update is linear and acts on each joint alone, ``x' = A x + b u`` with
        ``x = (q, v)`` and ``u = a_plan + kp q_plan + kd v_plan``; ``n`` of them are two small
        matrix products (matrices cached per ``(n, dt)``). The joints where some step would
        saturate are then stepped one by one, so the result is :meth:`update`'s to rounding.
        ``u`` ``[n, 7]`` may be given precomputed.
        """
        n = q_p.shape[0]
        mats = self._mats.get((n, dt))
        if mats is None:
            key = (n, dt, self.kp, self.kd, self.v_max.tobytes(), self.a_max.tobytes())
            if key not in _BLOCKS:
                _BLOCKS[key] = self._block_matrices(n, dt)
            mats = self._mats[(n, dt)] = _BLOCKS[key]
        from_state, from_u, limit = mats
        if u is None:
            u = a_p + self.kp * q_p + self.kd * v_p
        # rows: q_1..q_n, v_1..v_n, a_0..a_(n-1)
        qv = self._qv
        qv[0], qv[1] = self.q, self.v
        x = from_state @ qv + from_u @ u
        over = (np.abs(x[n:]) > limit).any(0)
        q, v = x[n - 1], x[2 * n - 1]
        if over.any():
            q, v = q.copy(), v.copy()
            kp, kd, half = self.kp, self.kd, 0.5 * dt
            for j in np.flatnonzero(over).tolist():
                qj, vj = float(self.q[j]), float(self.v[j])
                a_max, v_max = float(self.a_max[j]), float(self.v_max[j])
                for i in range(n):
                    a = (
                        float(a_p[i, j])
                        + kp * (float(q_p[i, j]) - qj)
                        + kd * (float(v_p[i, j]) - vj)
                    )
                    a = min(max(a, -a_max), a_max)
                    w = min(max(vj + a * dt, -v_max), v_max)
                    qj, vj = qj + half * (vj + w), w
                q[j], v[j] = qj, vj
        self.q, self.v = q, v

    def _block_matrices(self, n: int, dt: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``[3n, 2]`` and ``[3n, n]`` maps from ``(q, v)`` and ``u`` to ``q_j, v_j, a_j``, and
        the ``[2n, 7]`` limits of the ``v_j`` and ``a_j`` rows."""
        kp, kd = self.kp, self.kd
        step = np.array(
            [[1 - 0.5 * kp * dt * dt, dt - 0.5 * kd * dt * dt], [-kp * dt, 1 - kd * dt]]
        )
        gain = np.array([0.5 * dt * dt, dt])
        from_state, from_u = np.zeros((3 * n, 2)), np.zeros((3 * n, n))
        x_state, x_u = np.eye(2), np.zeros((2, n))  # x_j = x_state x_0 + x_u u
        for j in range(n):
            # a_j = u_j - kp q_j - kd v_j, then x_(j+1) = step x_j + gain u_j
            from_state[2 * n + j] = -kp * x_state[0] - kd * x_state[1]
            from_u[2 * n + j] = -kp * x_u[0] - kd * x_u[1]
            from_u[2 * n + j, j] += 1.0
            x_state, x_u = step @ x_state, step @ x_u
            x_u[:, j] += gain
            from_state[j], from_state[n + j] = x_state
            from_u[j], from_u[n + j] = x_u
        limit = np.concatenate([np.tile(self.v_max, (n, 1)), np.tile(self.a_max, (n, 1))])
        return from_state, from_u, limit


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

EARLIEST_START = -1.0
"""Earliest movement initiation relative to the opponent's hit [s]. The robot's own previous hit
comes 0.6-0.9 s before the opponent's (:class:`.opponent.OpponentConfig` defaults); a movement
cannot begin before it, and an earlier start would only hold the awaiting pose longer."""


def _check_start_time(start_time: float, t_cross: float) -> float:
    if (
        isinstance(start_time, bool)
        or not isinstance(start_time, int | float)
        or not EARLIEST_START <= start_time < t_cross
    ):
        raise ValueError(
            f"start_time must lie in [EARLIEST_START = {EARLIEST_START:g}, {t_cross:.3f}) s "
            "relative to the opponent's hit (before the ball reaches the hitting plane), got "
            f"{start_time!r}"
        )
    return float(start_time)


def execute_stroke(
    scene: TableTennisScene,
    planner: StrokePlanner,
    ball_after_hit: B.BallState,
    movement: str,
    start_time: float,
    *,
    legacy: bool = False,
) -> StrokeOutcome:
    """Simulate one hitting movement in the SAPIEN scene.

    Time 0 is the opponent's hit, when the ball leaves the opponent's racket in state
    ``ball_after_hit`` (unbatched); the movement is initiated at ``start_time`` (negative:
    before the opponent's hit). After the racket contact the return flight is finished with the
    ball model of :mod:`.ball` (the scene's ball follows it to millimetres) to judge legality.

    The arm's reference is computed every ``scene.dt`` (1 ms) as it always was. PhysX takes
    steps of up to ``scene.config.coarse_timestep`` (10 ms; they end where a stage of the
    movement may begin) while the ball is parked and flown by the ball model, and steps of
    ``scene.dt`` while PhysX simulates the ball: from before it can touch any part of the arm
    (:meth:`~.scene.TableTennisScene.arm_clear_of`) until it cannot any more, and from just
    before its bounce on the table until it has left it. Around the planned hit (100 ms before
    to 20 ms after) the steps are short too, so that the racket meets the ball as with 1 ms
    steps throughout. Predictions, aims and IK of a ball are cached by the planner.
    ``tests/robots/test_strokes.py`` checks that the rewards are those of 1 ms steps.

    ``legacy=True`` runs the previous implementation instead: 1 ms PhysX steps throughout, the
    ball in PhysX from the opponent's hit, the tracker and the drive targets updated per step in
    Python, and uncached planning on batched tensors. It stays only as the reference of the
    speed benchmark (``benchmarks/table_tennis.py``) and of the reward-agreement tests.

    Raises:
        ValueError: unknown movement, or ``start_time`` outside ``[EARLIEST_START, t_cross)``
            (``t_cross``: when the ball reaches the hitting plane).
    """
    movement = planner.movement(movement)
    if not isinstance(ball_after_hit, B.BallState):
        raise TypeError(f"ball_after_hit must be a BallState, got {type(ball_after_hit).__name__}")
    if legacy:
        return _execute_stroke_legacy(scene, planner, ball_after_hit, movement, start_time)
    ball = B.make_state(*ball_after_hit, dtype=torch.float64)
    if ball.pos.shape != (3,):
        raise ValueError("ball_after_hit must be a single ball (fields of shape [3])")
    floats = tuple(torch.cat(tuple(ball)).tolist())
    t_cross, _, valid = planner.crossing(floats)
    if not valid:
        raise ValueError("ball_after_hit never reaches the robot's hitting plane")
    start_time = _check_start_time(start_time, t_cross)
    return _Stroke(scene, planner, floats, movement, start_time, t_cross).run()


# The stroke loop's use of PhysX (see execute_stroke). PhysX simulates the ball from
# _BEFORE_BOUNCE s before it can touch the table until it rises _AFTER_BOUNCE m above it (the
# contact itself is PhysX's, as with 1 ms steps throughout: a ball model that does the bounce
# exactly lands 2-20 mm away from PhysX's ball at the hitting plane, which decides strokes at the
# racket's rim), and the arm takes steps of at most 2 ms from _FINE_BEFORE_HIT s before the
# planned hit, of 1 ms from 30 ms before it to _FINE_AFTER_HIT s after it (the PD drives forget
# the tracking error of longer steps within ~0.1 s, so the racket meets the ball as with 1 ms
# steps throughout, within millimetres).
_BEFORE_BOUNCE = 0.003
_AFTER_BOUNCE = 0.02
_FINE_BEFORE_HIT = 0.1
_FINE_AFTER_HIT = 0.02


def _near_table(b: tuple[float, ...], horizon: float) -> bool:
    """Whether the ball ``b`` (nine floats) may touch the table within ``horizon`` seconds, or
    left it less than ``_AFTER_BOUNCE`` m ago."""
    if abs(b[0]) > geo.TABLE_HALF_WIDTH + 0.05 or abs(b[1]) > geo.TABLE_HALF_LENGTH + 0.05:
        return False
    above = b[2] - (geo.TABLE_HEIGHT + geo.BALL_RADIUS)
    if b[5] >= 0:
        return -0.01 <= above < _AFTER_BOUNCE
    # falling at |vz| and at most g (< 10 m/s^2) faster, with 2 mm in hand
    return -0.01 <= above <= -b[5] * horizon + 5.0 * horizon * horizon + 0.002


class _Stroke:
    """One stroke of :func:`execute_stroke`: the stage machine of the movement, stepped in
    blocks of one or ``coarse_steps`` control periods."""

    def __init__(
        self,
        scene: TableTennisScene,
        planner: StrokePlanner,
        ball: B.Floats,
        movement: str,
        start_time: float,
        t_cross: float,
    ) -> None:
        self.scene, self.planner, self.ball0 = scene, planner, ball
        self.movement, self.start_time = movement, start_time
        self.t_end = t_cross + 0.15
        self.tracker = LimitedTracker(
            planner.awaiting, planner.velocity_limit, planner.acceleration_limit
        )
        self.prep: Quintic | None = None
        self.plan: HitPlan | None = None
        self.swing: Quintic | None = None
        self.finish: Quintic | None = None
        self.ball: B.Floats | None = None  # the model's ball while it is parked in PhysX
        self.recheck = 0  # control period from which the ball in PhysX may be parked again
        self.clear_until = -math.inf  # the ball cannot touch the arm before this time
        self.grid: list[float] = []  # times of the control periods
        self._refs: dict[int, tuple[np.ndarray, ...]] = {}  # plan segments on the grid
        self.in_play = False

    def _segment(self, t: float) -> Quintic | None:
        """The plan segment the reference follows at ``t`` (``None``: hold the awaiting pose)."""
        if self.swing is not None:
            return self.swing if t < self.plan.t_hit else self.finish  # type: ignore[union-attr]
        return self.prep

    def _thresholds(self) -> list[float]:
        """Times at which a stage may change (a block must not step over one)."""
        cfg = self.planner.config
        out = [self.t_end]
        if not self.in_play:
            out.append(0.0)
        if self.prep is None:
            out.append(self.start_time)
        elif self.plan is None:
            out.append(cfg.predict_delay)
        if self.plan is not None:
            out.append(self.plan.t_hit)
            if self.swing is None:
                out.append(self.plan.t_start)
                if cfg.hit_from_preparation and self.prep is not None:
                    out.append(self.prep.t0 + self.prep.duration)
        return out

    def _block(self, k: int) -> list[float]:
        """Times of the next block of control periods, and the ball handed between the model
        and PhysX.

        A block is as long as possible up to ``coarse_steps`` periods: it ends before a stage
        may change and on the 10 ms record grid, it is one period around the planned hit, and
        while the ball is in play, the ball can neither touch the arm nor the table within it.
        Else the block is one period and PhysX simulates the ball (it takes it from the model
        where it had it); the arm is checked again ``coarse_steps // 2`` periods later.
        """
        scene, dt = self.scene, self.scene.dt
        m = scene.config.coarse_steps
        times = self.grid[k : k + min(m, 10 - k % 10)]
        t = times[0]
        for x in self._thresholds():
            if t < x <= times[-1]:  # the stage may change at the first time >= x
                del times[sum(u < x for u in times) :]
        if self.plan is not None and -_FINE_BEFORE_HIT <= t - self.plan.t_hit <= _FINE_AFTER_HIT:
            # up to 2 ms steps at first, 1 ms in the last 30 ms before the hit
            del times[1 if t - self.plan.t_hit >= -0.03 else 2 :]
        if not self.in_play:
            return times
        model = self.ball is not None
        if not model and k < self.recheck:
            return [t]
        b: tuple[float, ...] = self.ball if self.ball is not None else scene.ball_floats()
        near = _near_table(b, len(times) * dt + _BEFORE_BOUNCE)
        end = times[-1] + dt  # when the block ends
        if not near:
            if model and end <= self.clear_until:
                return times
            speed = math.sqrt(b[3] * b[3] + b[4] * b[4] + b[5] * b[5])
            ahead = 4 * m * dt  # far from the arm, one check covers four blocks
            if scene.arm_clear_of(b, speed, ahead):
                self.clear_until = t + ahead
            if end <= self.clear_until or scene.arm_clear_of(b, speed, len(times) * dt):
                if not model:  # the model takes the ball back from PhysX
                    self.ball = b  # type: ignore[assignment]
                    scene.park_ball()
                return times
            self.recheck = k + max(1, m // 2)
        if model:
            scene.set_ball_floats(b)
            self.ball = None
        return [t]

    def _stages(self, t: float) -> bool:
        """Advance the stage machine at ``t`` as the control loop always did; False: stop."""
        planner, cfg = self.planner, self.planner.config
        tracker = self.tracker
        if not self.in_play and t >= 0.0:
            self.in_play, self.ball = True, self.ball0
        if self.prep is None and t >= self.start_time:
            self.prep = planner.preparation(self.movement, t, tracker.q)
        if self.plan is None and self.prep is not None and self.in_play and t >= cfg.predict_delay:
            seen = self.ball if self.ball is not None else self.scene.ball_floats()
            self.plan = planner._plan(self.movement, seen, t)
            if self.plan is None:
                return False
        # The hitting stage replans from the arm's current state; unless configured to wait for
        # the preparation pose, also when the preparation is not finished yet.
        prep, plan = self.prep, self.plan
        ready = prep is not None and (not cfg.hit_from_preparation or t >= prep.t0 + prep.duration)
        if plan is not None and self.swing is None and ready and t >= plan.t_start:
            if t < plan.t_hit:
                self.swing = planner.swing(plan, t, tracker.q, tracker.v)
                self.finish = planner.finish(plan)
        return True

    def _reference(self, seg: Quintic, k: int) -> tuple[np.ndarray, ...]:
        """The plan segment ``seg`` on the control grid from period ``k`` on: its position,
        velocity and acceleration and the tracker's input ``u``, ``[S, 7]`` each, evaluated at
        once when the segment begins (cached by segment)."""
        ref = self._refs.get(id(seg))
        if ref is None:
            q_p, v_p, a_p = seg.at(np.asarray(self.grid[k:]))
            u = a_p + self.tracker.kp * q_p + self.tracker.kd * v_p
            ref = self._refs[id(seg)] = (k, q_p, v_p, a_p, u)
        return ref

    def run(self) -> StrokeOutcome:
        scene, planner, tracker = self.scene, self.planner, self.tracker
        dt = scene.dt
        model = planner.scalar
        scene.set_robot(planner.awaiting)
        scene.park_ball()
        m = scene.config.coarse_steps
        hold = tuple(np.broadcast_to(x, (m, DOF)) for x in (planner.awaiting, 0.0, 0.0))
        hold_u = tracker.kp * hold[0]
        contact_time = math.nan
        racket_path, ball_path, joint_path = [], [], []
        # the control grid, accumulated as the 1 ms control loop always did (t += dt)
        t0 = min(self.start_time, 0.0)
        steps = math.ceil((self.t_end - t0) / dt) + 2
        self.grid = np.cumsum(np.concatenate([[t0], np.full(steps, dt)])).tolist()
        k = 0
        t = t0
        b: B.Floats | None = None
        while t < self.t_end:
            if not self._stages(t):
                break
            n = len(self._block(k))
            seg = self._segment(t)
            if seg is None:
                q_p, v_p, a_p, u = (*(x[:n] for x in hold), hold_u[:n])
            else:
                k0, *rows = self._reference(seg, k)
                q_p, v_p, a_p, u = (x[k - k0 : k - k0 + n] for x in rows)
            if n == 1:
                tracker.update((q_p[0], v_p[0], a_p[0]), dt)
            else:
                tracker.update_many(q_p, v_p, a_p, dt, u)
            scene.set_targets(tracker.q, tracker.v)
            scene.step(n)
            k += n
            t = self.grid[k]
            if self.in_play:
                if self.ball is not None:
                    b = self.ball = model.advance(self.ball, n * dt)[0]
                else:
                    b = scene.ball_floats()
                if math.isnan(contact_time) and b[4] > 0 and b[1] < 0:
                    contact_time = t
                if not math.isnan(contact_time) and t >= contact_time + 0.01:
                    break
                if b[2] < 2 * geo.BALL_RADIUS:
                    break
            if k % 10 == 0:
                racket_path.append(scene.racket_pose()[0])
                ball_path.append(np.array(b[:3]) if self.in_play else np.full(3, np.nan))
                joint_path.append(scene.robot_state()[0])
        after = None
        if not math.isnan(contact_time) and b is not None:
            after = B.BallState(
                *(torch.tensor(b[i : i + 3], dtype=torch.float64) for i in (0, 3, 6))
            )
        return _outcome(planner, self.plan, after, racket_path, ball_path, joint_path)


def _outcome(
    planner: StrokePlanner,
    plan: HitPlan | None,
    after: B.BallState | None,
    racket_path: list,
    ball_path: list,
    joint_path: list,
) -> StrokeOutcome:
    """Judge the return of a stroke whose ball left the racket in state ``after`` (None: the
    racket never touched it)."""
    landing = np.full(2, np.nan)
    success = False
    if after is not None:
        # every return lands within 1.2 s (the planned flights take at most ~0.9 s)
        traj = B.simulate(after, 1.2, 0.01, planner.ball_params)
        land = B.landing(traj)
        if bool(land.landed):
            landing = land.pos[..., :2].reshape(2).numpy()
        success = bool(B.is_legal_return(traj))
        ball_path.extend(traj.pos.reshape(-1, 3).numpy())
    return StrokeOutcome(
        success=success,
        hit=after is not None,
        landing=landing,
        t_hit=math.nan if plan is None else plan.t_hit,
        racket_path=np.asarray(racket_path).reshape(-1, 3),
        ball_path=np.asarray(ball_path).reshape(-1, 3),
        joint_path=np.asarray(joint_path).reshape(-1, DOF),
    )


def _execute_stroke_legacy(
    scene: TableTennisScene,
    planner: StrokePlanner,
    ball_after_hit: B.BallState,
    movement: str,
    start_time: float,
) -> StrokeOutcome:
    """The previous :func:`execute_stroke` (see its ``legacy`` option), unchanged but for the
    start-time check; its single-ball tensor calls run on a batch of one, as they did before
    unbatched states took the float path of :mod:`.ball`."""
    cfg = planner.config
    t_cross, _, valid = B.predict_plane_crossing(
        B.BallState(*(x.unsqueeze(0) for x in ball_after_hit)),
        geo.HITTING_PLANE_Y,
        planner.ball_params,
        dt=0.01,
    )
    if not bool(valid):
        raise ValueError("ball_after_hit never reaches the robot's hitting plane")
    start_time = _check_start_time(start_time, float(t_cross))
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
            plan = planner.plan_hit(movement, scene.ball_state(), t, legacy=True)
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
