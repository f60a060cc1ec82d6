"""Execution of one hitting movement in the SAPIEN scene: :func:`execute_stroke`.

The stage machine of a movement (awaiting, preparation, hitting, finishing; thesis Fig. 3.5) drives
the simulated arm through :class:`~.stroke_tracker.LimitedTracker`, and the return is judged with
the ball model (:class:`StrokeOutcome`).

Speed (``benchmarks/table_tennis.py``: ~3 times the strokes per second of 1 ms PhysX steps
throughout with the ball in PhysX, ~12 times those of the executor before, with the same
rewards): the arm's reference is still computed every 1 ms, but in blocks of up to 10 ms that
are one matrix product (:meth:`~.stroke_tracker.LimitedTracker.update_many`)
and one PhysX step. Steps are short (1 ms; 2 ms until 30 ms before the hit) from 100 ms before the
planned hit to 20 ms after it, and whenever PhysX simulates the ball: from before it can touch the
arm until it cannot, and through its bounce on the table. Elsewhere the ball is parked and the ball
model flies it in floats (:class:`.ball.ScalarBall`). A ball's prediction, return aim and hitting
IK are cached by the planner, so the 15 strokes of a reward-table row plan once per movement.
``execute_stroke(..., reference=True)`` runs the same stage machine with 1 ms PhysX steps
throughout and the ball in PhysX from the opponent's hit, the simulation without these
shortcuts: the reference of the benchmark and of the reward-agreement tests.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch

from ..wam import DOF
from . import ball as B
from . import geometry as geo
from .scene import TableTennisScene
from .stroke_planner import HitPlan, StrokePlanner
from .stroke_quintic import Quintic
from .stroke_tracker import LimitedTracker

__all__ = ["EARLIEST_START", "StrokeOutcome", "execute_stroke"]


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


EARLIEST_START = -1.0
"""Earliest movement initiation relative to the opponent's hit [s]. The robot's own previous hit
comes 0.6-0.9 s before the opponent's (:class:`.opponent.OpponentConfig` defaults); a movement
cannot begin before it, and an earlier start would only hold the awaiting pose longer."""


def check_start_time(start_time: float, t_cross: float) -> float:
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
    reference: bool = False,
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

    Args:
        scene: the SAPIEN scene (its ball and arm are reset here).
        planner: plans the movement's stages (and caches a ball's plans).
        ball_after_hit: the ball as it leaves the opponent's racket, fields ``[3]``.
        movement: ``"forehand"``, ``"middle"`` or ``"backhand"``.
        start_time: movement initiation relative to the opponent's hit [s].
        reference: 1 ms PhysX steps throughout, the ball in PhysX from the opponent's hit and
            never flown by the ball model (about 3 times slower): the reference that the
            shortcuts above must agree with.

    Raises:
        ValueError: unknown movement, or ``start_time`` outside ``[EARLIEST_START, t_cross)``
            (``t_cross``: when the ball reaches the hitting plane).
    """
    movement = planner.movement(movement)
    if not isinstance(ball_after_hit, B.BallState):
        raise TypeError(f"ball_after_hit must be a BallState, got {type(ball_after_hit).__name__}")
    ball = B.make_state(*ball_after_hit, dtype=torch.float64)
    if ball.pos.shape != (3,):
        raise ValueError("ball_after_hit must be a single ball (fields of shape [3])")
    floats = tuple(torch.cat(tuple(ball)).tolist())
    t_cross, _, valid = planner.crossing(floats)
    if not valid:
        raise ValueError("ball_after_hit never reaches the robot's hitting plane")
    start_time = check_start_time(start_time, t_cross)
    if not isinstance(reference, bool):
        raise TypeError(f"reference must be a bool, got {reference!r}")
    return _Stroke(scene, planner, floats, movement, start_time, t_cross, reference).run()


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
    blocks of one or ``coarse_steps`` control periods (``reference``: one period each, the ball
    in PhysX throughout)."""

    def __init__(
        self,
        scene: TableTennisScene,
        planner: StrokePlanner,
        ball: B.Floats,
        movement: str,
        start_time: float,
        t_cross: float,
        reference: bool = False,
    ) -> None:
        self.scene, self.planner, self.ball0 = scene, planner, ball
        self.reference = reference
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
        if self.reference:
            return self.grid[k : k + 1]
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
            if self.reference:  # PhysX flies the ball from the opponent's hit
                self.scene.set_ball_floats(self.ball0)
                self.ball = None
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
