"""Planning of the hitting movements: poses by IK, and the plan of each stage for one ball.

:class:`StrokePlanner` finds the preparation and awaiting poses of one arm and plans the stages
of a movement (preparation, hitting, finishing quintics); :class:`HitPlan` is the hitting stage
planned for one incoming ball: where, when and how the racket meets it. A ball's prediction,
return aim and hitting IK are cached, so the 15 strokes of a reward-table row plan once per
movement.
"""

from __future__ import annotations

import math
from collections import OrderedDict
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import torch

from ...validation import check_choice
from ..wam import DOF, WAM
from . import ball as B
from . import geometry as geo
from .stroke_config import MOVEMENTS, StrokeConfig
from .stroke_quintic import Quintic, min_quintic_duration

__all__ = ["HitPlan", "StrokePlanner"]

_CACHE_SIZE = 256  # planner cache entries: a reward-table row needs 5 (crossing, return, 3 IK)


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

    def plan_hit(self, name: str, ball_now: B.BallState, t_now: float) -> HitPlan | None:
        """Where, when and how to hit the ball observed at time ``t_now`` (unbatched state).

        The ball's crossing of the hitting plane is predicted, the return is aimed at
        ``config.return_target`` with the first of ``config.return_flight_times`` whose
        simulated flight is legal (the first when none is), the racket law is inverted for the
        racket's normal and velocity, and IK from the preparation pose gives the joint state.
        The ball part depends on the observed ball only and is shared by the three movements;
        both parts are cached (small LRU), so the 15 strokes of a reward-table row predict and
        aim once.

        Returns ``None`` when the ball never reaches the hitting plane.
        """
        name = self.movement(name)
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
