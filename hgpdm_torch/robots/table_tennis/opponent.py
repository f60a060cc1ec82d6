"""A simulated human opponent whose strokes are driven by an intended target (thesis Sec. 3.5, 4.3).

The thesis predicts where a human player will return the ball (the *target*: the lateral position
``x`` at which the ball crosses the robot's virtual hitting plane, Fig. 4.2) from observations of
the incoming ball and of the player's racket, taken every 80 ms (12.5 Hz) during the ~400 ms
before the player hits the ball (Sec. 2.4.3, 3.5). This module generates such strokes:

1. the robot's return (the incoming ball) is aimed onto the opponent's half and flies until it
   crosses the player's contact plane behind the end line (timing varies with that plane);
2. the player picks a forehand or backhand style, and with a small probability changes the target
   late in the stroke;
3. the return is solved backwards with the ball model: a ball that bounces on the robot's half and
   crosses the hitting plane at the aimed ``x`` (:func:`.ball.aim_through_bounce`), and the racket
   normal and velocity at contact that produce it (:func:`.ball.racket_velocity_for_return`);
4. execution noise perturbs that racket state, and the returned ball is computed from the perturbed
   state with :func:`.ball.racket_contact`, so the observed racket is physically consistent with
   where the ball goes; ``targets`` records where it actually crosses;
5. the racket moves ready pose -> backswing -> contact along quintic (minimum-jerk-like) segments
   ending in the contact state, and a late change blends the two plans smoothly.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields
from typing import NamedTuple

import torch

from hgpdm_torch.robots.table_tennis import ball as B
from hgpdm_torch.robots.table_tennis import geometry as geo
from hgpdm_torch.validation import as_tensor, check_choice

from ...progress import tqdm

__all__ = ["FEATURE_NAMES", "OpponentConfig", "RacketTrajectory", "Strokes", "sample_strokes"]

FEATURE_NAMES = [
    *(f"ball_{a}" for a in ("x", "y", "z")),
    *(f"ball_v{a}" for a in ("x", "y", "z")),
    *(f"racket_{a}" for a in ("x", "y", "z")),
    *(f"racket_v{a}" for a in ("x", "y", "z")),
    *(f"racket_n{a}" for a in ("x", "y", "z")),
]
"""Names of the ``Dz = 15`` observation features, in order."""

_STYLES = ("ball_side", "random")


@dataclass(frozen=True)
class OpponentConfig:
    """Settings of the simulated opponent. Lengths in m, times in s, angles in rad.

    Attributes:
        obs_rate: observation rate [Hz] (12.5 in the thesis).
        n_obs: observations per stroke, the last at the hit (6 covers the last 400 ms).
        racket_rate: sampling rate of the full-rate racket trajectory [Hz].
        target_max: targets are drawn uniformly in ``[-target_max, target_max]``.
        robot_hit_x, robot_hit_y, robot_hit_z: ranges of the robot's hitting point.
        incoming_land_x, incoming_land_y: ranges of the incoming ball's bounce on the
            opponent's half.
        incoming_flight_time: range of the incoming ball's time from the robot to that bounce.
        contact_y: range of the plane behind the opponent's end line where the player hits.
        bounce_y: range (deep, short) of the return's bounce ``y`` on the robot's half; wide
            targets bounce short enough that the bounce stays within ``bounce_x_max``.
        bounce_x_max: largest ``|x|`` of the return's bounce (on the straight-line estimate).
        return_flight_time: range of the return's time from the hit to that bounce.
        loft: extra flight time per metre that a bounce lies shorter than ``bounce_y[1]``.
        style_rule: ``"ball_side"`` (forehand when the ball is on the player's right, i.e.
            ``x < forehand_max_x``; the player faces ``-y``) or ``"random"``.
        forehand_max_x: the ``"ball_side"`` threshold.
        backhand_prob: probability of a backhand under ``"random"``.
        swing_duration_mean, swing_duration_std: forward swing (backswing -> contact) time,
            clipped to ``[0.2, 0.4]``: the timing variability of the stroke.
        backswing_duration: time from the ready pose to the backswing pose.
        backswing_noise: standard deviation of the backswing pose per axis.
        target_lean: lateral shift of the backswing pose per unit ``target / target_max``
            (players open their stance early towards the target).
        topspin: range of the topspin the player gives the return [rad/s]; the racket's
            in-plane velocity at contact follows from it (rolling-off racket law).
        exec_normal_noise: execution noise of the racket normal at contact.
        exec_speed_noise: execution noise of the racket velocity at contact, per axis [m/s].
        late_change_prob: probability of a late change to a target on the other side.
        late_change_window: range of the time (before the hit) of a late change.
        ball_pos_noise, ball_vel_noise: sensor noise of the ball observations.
        racket_pos_noise, racket_vel_noise, racket_normal_noise: sensor noise of the racket
            observations (the normal is renormalised after the noise).
        max_rounds: rounds of redrawing strokes whose return is not legal (round r draws
            ``min(2^r, 8)`` candidates per pending stroke).
    """

    obs_rate: float = 12.5
    n_obs: int = 6
    racket_rate: float = 250.0
    target_max: float = geo.TARGET_X_MAX
    robot_hit_x: tuple[float, float] = (-0.4, 0.4)
    robot_hit_y: tuple[float, float] = (-1.9, -1.6)
    robot_hit_z: tuple[float, float] = (0.9, 1.05)
    incoming_land_x: tuple[float, float] = (-0.45, 0.45)
    incoming_land_y: tuple[float, float] = (0.55, 1.05)
    incoming_flight_time: tuple[float, float] = (0.4, 0.5)
    contact_y: tuple[float, float] = (1.5, 1.75)
    bounce_y: tuple[float, float] = (-1.3, -0.9)
    bounce_x_max: float = 0.65
    return_flight_time: tuple[float, float] = (0.5, 0.65)
    loft: float = 1.0
    style_rule: str = "ball_side"
    forehand_max_x: float = 0.05
    backhand_prob: float = 0.5
    swing_duration_mean: float = 0.3
    swing_duration_std: float = 0.03
    backswing_duration: float = 0.25
    backswing_noise: float = 0.05
    target_lean: float = 0.1
    topspin: tuple[float, float] = (20.0, 60.0)
    exec_normal_noise: float = 0.003
    exec_speed_noise: float = 0.05
    late_change_prob: float = 0.1
    late_change_window: tuple[float, float] = (-0.2, -0.1)
    ball_pos_noise: float = 0.01
    ball_vel_noise: float = 0.1
    racket_pos_noise: float = 0.02
    racket_vel_noise: float = 0.2
    racket_normal_noise: float = 0.05
    max_rounds: int = 10

    def __post_init__(self) -> None:
        for f in fields(self):
            value = getattr(self, f.name)
            if isinstance(value, tuple):
                if len(value) != 2 or not all(math.isfinite(v) for v in value):
                    raise ValueError(f"OpponentConfig.{f.name} must be a (low, high) pair")
                if value[0] > value[1]:
                    raise ValueError(f"OpponentConfig.{f.name} must have low <= high, got {value}")
            elif isinstance(value, int | float) and not math.isfinite(value):
                raise ValueError(f"OpponentConfig.{f.name} must be finite, got {value}")
        check_choice(self.style_rule, "style_rule", _STYLES)
        for name in ("obs_rate", "racket_rate", "target_max", "backswing_duration", "bounce_x_max"):
            if getattr(self, name) <= 0:
                raise ValueError(f"OpponentConfig.{name} must be > 0, got {getattr(self, name)}")
        if self.target_max > geo.TARGET_X_MAX:
            raise ValueError(f"OpponentConfig.target_max must be <= {geo.TARGET_X_MAX}")
        if not isinstance(self.n_obs, int) or self.n_obs < 2:
            raise ValueError(f"OpponentConfig.n_obs must be an int >= 2, got {self.n_obs!r}")
        if not isinstance(self.max_rounds, int) or self.max_rounds < 1:
            raise ValueError(
                f"OpponentConfig.max_rounds must be an int >= 1, got {self.max_rounds}"
            )
        for name in ("backhand_prob", "late_change_prob"):
            if not 0 <= getattr(self, name) <= 1:
                raise ValueError(f"OpponentConfig.{name} must lie in [0, 1]")
        noises = [f.name for f in fields(self) if f.name.endswith(("_noise", "_std"))]
        for name in [*noises, "swing_duration_mean"]:
            if getattr(self, name) < 0:
                raise ValueError(f"OpponentConfig.{name} must be >= 0")
        if self.window > self.incoming_flight_time[0]:
            raise ValueError(
                "the observation window (n_obs - 1) / obs_rate must not exceed the incoming "
                "ball's shortest flight time, or the first observation precedes the robot's hit"
            )
        if not self.late_change_window[1] < 0:
            raise ValueError("OpponentConfig.late_change_window must lie before the hit (< 0)")

    @property
    def window(self) -> float:
        """Time from the first observation to the hit [s]."""
        return (self.n_obs - 1) / self.obs_rate

    @property
    def obs_times(self) -> torch.Tensor:
        """``[T]`` observation times relative to the hit, e.g. ``-0.4, -0.32, ..., 0``."""
        k = torch.arange(self.n_obs - 1, -1, -1, dtype=torch.float64)
        return -k / self.obs_rate


class RacketTrajectory(NamedTuple):
    """Racket states at ``R`` times before the hit (full rate, for drawing).

    Attributes:
        times: ``[R]`` times relative to the hit [s].
        pos: ``[n, R, 3]`` racket centre.
        vel: ``[n, R, 3]`` racket velocity.
        normal: ``[n, R, 3]`` unit normal of the hitting face (towards the robot at contact).
    """

    times: torch.Tensor
    pos: torch.Tensor
    vel: torch.Tensor
    normal: torch.Tensor


@dataclass
class Strokes:
    """A batch of ``n`` simulated opponent strokes (``T = n_obs`` observations each).

    Attributes:
        targets: ``[n]`` ``x`` where the returned ball actually crosses the hitting plane.
        intended: ``[n]`` target the player aimed at when the stroke began.
        final_aim: ``[n]`` target aimed at the hit (differs from ``intended`` after a late change).
        late_change: ``[n]`` whether the player changed the target late.
        switch_time: ``[n]`` time of the change relative to the hit (0 where none).
        obs: ``[n, T, Dz]`` noisy observations, features named by ``feature_names``.
        obs_times: ``[T]`` observation times relative to the hit [s].
        hit_time: ``[n]`` time of the player's hit after the robot's hit [s].
        swing_duration: ``[n]`` duration of the forward swing [s].
        style: ``[n]`` long, 0 forehand / 1 backhand.
        incoming: :class:`.ball.BallState` ``[n]`` of the ball right after the robot's hit.
        ball_before_hit: :class:`.ball.BallState` ``[n]`` of the ball at the player's contact.
        ball_after_hit: :class:`.ball.BallState` ``[n]`` right after the player's contact.
        racket: :class:`RacketTrajectory` at ``racket_rate`` over the observation window.
        feature_names: the ``Dz`` feature names.
    """

    targets: torch.Tensor
    intended: torch.Tensor
    final_aim: torch.Tensor
    late_change: torch.Tensor
    switch_time: torch.Tensor
    obs: torch.Tensor
    obs_times: torch.Tensor
    hit_time: torch.Tensor
    swing_duration: torch.Tensor
    style: torch.Tensor
    incoming: B.BallState
    ball_before_hit: B.BallState
    ball_after_hit: B.BallState
    racket: RacketTrajectory
    feature_names: list[str]


# --------------------------------------------------------------------------------------------
# racket motion


def _quintic(
    p0: torch.Tensor, p1: torch.Tensor, v1: torch.Tensor, duration: torch.Tensor, tau: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """Quintic Hermite segment from rest at ``p0`` to ``(p1, v1)``, zero end accelerations.

    Shapes: ``p0, p1, v1`` [m, 3], ``duration`` [m], ``tau`` [m, R] in [0, 1] -> pos, vel
    [m, R, 3].
    """
    t = tau.clamp(0.0, 1.0).unsqueeze(-1)
    t2, t3 = t * t, t * t * t
    h0 = 1 - t3 * (10 - 15 * t + 6 * t2)
    h5 = 1 - h0
    h4 = t3 * (-4 + 7 * t - 3 * t2)
    dh5 = 30 * t2 * (1 - t) ** 2
    dh4 = t2 * (-12 + 28 * t - 15 * t2)
    T = duration[:, None, None]
    p0, p1, v1 = p0[:, None], p1[:, None], v1[:, None]
    pos = h0 * p0 + h5 * p1 + h4 * v1 * T
    vel = dh5 * (p1 - p0) / T + dh4 * v1
    return pos, vel


def _blend(tau: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Smooth step ``10 t^3 - 15 t^4 + 6 t^5`` on ``tau`` clamped to [0, 1], and its derivative."""
    t = tau.clamp(0.0, 1.0)
    return t**3 * (10 - 15 * t + 6 * t**2), 30 * t**2 * (1 - t) ** 2


def _unit(v: torch.Tensor) -> torch.Tensor:
    return v / v.norm(dim=-1, keepdim=True)


def _rotate_z(v: torch.Tensor, angle: torch.Tensor) -> torch.Tensor:
    c, s = torch.cos(angle), torch.sin(angle)
    return torch.stack(
        [c * v[..., 0] - s * v[..., 1], s * v[..., 0] + c * v[..., 1], v[..., 2]], -1
    )


class _Plan(NamedTuple):
    """One planned stroke: ready pose -> backswing -> contact. Shapes [m, 3] / [m]."""

    ready: torch.Tensor
    backswing: torch.Tensor
    contact: torch.Tensor
    contact_vel: torch.Tensor
    ready_normal: torch.Tensor
    backswing_normal: torch.Tensor
    contact_normal: torch.Tensor
    swing: torch.Tensor
    backswing_time: float


def _evaluate(plan: _Plan, t: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Racket pos, vel, normal [m, R, 3] of a plan at times ``t`` [R] relative to the hit."""
    m = plan.contact.shape[0]
    tt = t.expand(m, -1)
    swing = plan.swing[:, None]
    zero = torch.zeros_like(plan.contact)
    tau1 = (tt + swing + plan.backswing_time) / plan.backswing_time
    tau2 = (tt + swing) / swing
    p1, v1 = _quintic(
        plan.ready, plan.backswing, zero, torch.full_like(plan.swing, plan.backswing_time), tau1
    )
    p2, v2 = _quintic(plan.backswing, plan.contact, plan.contact_vel, plan.swing, tau2)
    in_swing = (tau2 > 0).unsqueeze(-1)
    pos = torch.where(in_swing, p2, p1)
    vel = torch.where(in_swing, v2, v1)
    s1, _ = _blend(tau1)
    s2, _ = _blend(tau2)
    n1 = (
        plan.ready_normal[:, None]
        + s1[..., None] * (plan.backswing_normal - plan.ready_normal)[:, None]
    )
    n2 = (
        plan.backswing_normal[:, None]
        + s2[..., None] * (plan.contact_normal - plan.backswing_normal)[:, None]
    )
    return pos, vel, _unit(torch.where(in_swing, n2, n1))


def _racket(
    first: _Plan, final: _Plan, switch: torch.Tensor, late: torch.Tensor, t: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Executed racket [m, R, 3]: ``first`` blended into ``final`` from ``switch`` to the hit."""
    pa, va, na = _evaluate(first, t)
    pb, vb, nb = _evaluate(final, t)
    dur = torch.where(late, -switch, torch.ones_like(switch))[:, None]
    s, ds = _blend((t - switch[:, None]) / dur)
    s = torch.where(late[:, None], s, torch.ones_like(s))
    ds = torch.where(late[:, None], ds / dur, torch.zeros_like(ds))[..., None]
    s = s[..., None]
    pos = pa + s * (pb - pa)
    vel = va + s * (vb - va) + ds * (pb - pa)
    return pos, vel, _unit(na + s * (nb - na))


# --------------------------------------------------------------------------------------------
# sampling


def _uniform(rng: tuple[float, float], m: int, gen: torch.Generator | None) -> torch.Tensor:
    return rng[0] + (rng[1] - rng[0]) * torch.rand(m, generator=gen, dtype=torch.float64)


def _randn(*shape: int, gen: torch.Generator | None) -> torch.Tensor:
    return torch.randn(*shape, generator=gen, dtype=torch.float64)


def _vec(*values: float) -> torch.Tensor:
    # explicit float64: the sampler must not depend on torch's default dtype
    return torch.tensor(values, dtype=torch.float64)


def _bounce_y(
    contact: torch.Tensor, aims: torch.Tensor, u: torch.Tensor, cfg: OpponentConfig
) -> torch.Tensor:
    """Bounce ``y`` [k] for returns from ``contact`` [k, 3] to ``aims`` [k] (u [k] in [0, 1]).

    On the straight line from the contact to the target on the hitting plane, the bounce at
    depth fraction ``f`` lies at ``x = c_x + f (aim - c_x)``; keeping ``|x| <= bounce_x_max``
    bounds ``f`` and so the deepest allowed bounce.
    """
    lateral = aims - contact[:, 0]
    room = cfg.bounce_x_max - torch.sign(lateral) * contact[:, 0]
    # a contact already wider than bounce_x_max (room < 0) gets the shortest bounce
    frac = (room / lateral.abs().clamp_min(1e-9)).clamp(0.0, 1.0)
    span = contact[:, 1] - geo.HITTING_PLANE_Y
    deep = torch.maximum(contact[:, 1] - frac * span, torch.full_like(aims, cfg.bounce_y[0]))
    # a target too wide for the configured range bounces as deep as the side line allows
    short = torch.maximum(deep, torch.full_like(aims, cfg.bounce_y[1]))
    return deep + u * (short - deep)


def _sample(
    intended: torch.Tensor, cfg: OpponentConfig, params: B.BallParams, gen: torch.Generator | None
) -> dict[str, torch.Tensor | B.BallState | RacketTrajectory]:
    """Draw one candidate stroke per entry of ``intended`` [m]; ``legal`` marks usable ones."""
    m = intended.shape[0]
    # 1. the incoming ball: the robot's return onto the opponent's half
    hit = torch.stack(
        [_uniform(r, m, gen) for r in (cfg.robot_hit_x, cfg.robot_hit_y, cfg.robot_hit_z)], -1
    )
    land = torch.stack(
        [_uniform(cfg.incoming_land_x, m, gen), _uniform(cfg.incoming_land_y, m, gen)], -1
    )
    incoming = B.make_state(
        hit, B.aim(hit, land, _uniform(cfg.incoming_flight_time, m, gen), params)
    )
    hit_time, _, reached = B.predict_plane_crossing(
        incoming, _uniform(cfg.contact_y, m, gen), params, max_time=1.5
    )
    # the ball along the observation window; the last observation is the contact
    obs_times = cfg.obs_times
    ball = B.propagate(incoming, (hit_time + obs_times[0]).clamp_min(0.0), params)
    balls = [ball]
    for _ in range(cfg.n_obs - 1):
        ball = B.propagate(ball, 1.0 / cfg.obs_rate, params)
        balls.append(ball)
    reached = reached & (balls[-1].pos[:, 2] > geo.TABLE_HEIGHT + 2 * params.radius)
    # strokes whose ball was not reached are redrawn; a benign stand-in keeps the solvers finite
    stand_in = B.make_state(_vec(0.0, 1.6, 1.0).expand(m, 3), _vec(0.0, 3.0, -1.0).expand(m, 3))
    before = balls[-1].where(reached, stand_in)
    contact = before.pos

    # 2. style and late changes
    if cfg.style_rule == "ball_side":
        style = (contact[:, 0] >= cfg.forehand_max_x).long()
    else:
        style = (torch.rand(m, generator=gen, dtype=torch.float64) < cfg.backhand_prob).long()
    late = torch.rand(m, generator=gen, dtype=torch.float64) < cfg.late_change_prob
    side = torch.where(intended >= 0, 1.0, -1.0).to(intended.dtype)
    other = -side * _uniform((0.3, cfg.target_max), m, gen)
    final_aim = torch.where(late, other, intended)
    switch = torch.where(late, _uniform(cfg.late_change_window, m, gen), torch.zeros_like(intended))

    # 3. returns for the final aim (all) and the first aim (late changers), solved backwards;
    # the topspin axis is horizontal, across the direction towards the aimed point
    idx = torch.nonzero(late).squeeze(-1)
    aims = torch.cat([final_aim, intended[idx]])
    rows = torch.cat([torch.arange(m), idx])
    towards = torch.stack(
        [aims - contact[rows, 0], geo.HITTING_PLANE_Y - contact[rows, 1], torch.zeros_like(aims)],
        -1,
    )
    axis = _unit(torch.linalg.cross(_vec(0.0, 0.0, 1.0).expand_as(towards), towards))
    spin_out = _uniform(cfg.topspin, m, gen)[rows, None] * axis
    bounce_y = _bounce_y(contact[rows], aims, _uniform((0.0, 1.0), m, gen)[rows], cfg)
    # short (wide) bounces are lofted more so that the ball still reaches the hitting plane
    flight = _uniform(cfg.return_flight_time, m, gen)[rows]
    flight = flight + cfg.loft * (cfg.bounce_y[1] - bounce_y).clamp(max=0).neg()
    v_out, _, _, aimed = B.aim_through_bounce(
        contact[rows], aims, bounce_y, flight, params, spin=spin_out, tol=2e-3, max_iter=4
    )
    normal, racket_vel = B.racket_velocity_for_return(
        before.vel[rows], v_out, params, spin_out=spin_out
    )

    # 4. poses: backswing by style (the player faces -y, forehand on the right at -x)
    fore = _vec(-0.35, 0.35, -0.2)
    back = _vec(0.25, 0.25, -0.05)
    offset = torch.where((style == 1)[:, None], back, fore)
    offset = offset + cfg.backswing_noise * _randn(m, 3, gen=gen)
    ready = contact + _vec(0.0, 0.45, 0.0) + cfg.backswing_noise * _randn(m, 3, gen=gen)
    backswing = contact[rows] + offset[rows]
    backswing[:, 0] += cfg.target_lean * aims / cfg.target_max
    # execution noise on the final plan's contact state (the racket really ends there)
    normal[:m] = _unit(normal[:m] + cfg.exec_normal_noise * _randn(m, 3, gen=gen))
    racket_vel[:m] = racket_vel[:m] + cfg.exec_speed_noise * _randn(m, 3, gen=gen)
    vel_after, spin_after = B.racket_contact(
        before.vel, before.spin, racket_vel[:m], normal[:m], params
    )
    # a plan that did not converge can hit the ball faster or spin it harder than a ball flies
    # (B.MAX_SPEED, B.MAX_SPIN): such a stroke is illegal, and its ball is slowed down to fly
    speed, rate = vel_after.norm(dim=-1, keepdim=True), spin_after.norm(dim=-1, keepdim=True)
    fast, spun = speed > B.MAX_SPEED, rate > B.MAX_SPIN
    vel_after = torch.where(fast, vel_after * (0.5 * B.MAX_SPEED / speed), vel_after)
    spin_after = torch.where(spun, spin_after * (0.5 * B.MAX_SPIN / rate), spin_after)
    physical = ~(fast | spun).squeeze(-1)
    after = B.make_state(contact, vel_after, spin_after)

    # 5. the returned ball: where it crosses the hitting plane and whether it is legal
    t_cross, at_plane, crossed = B.predict_plane_crossing(after, geo.HITTING_PLANE_Y, params)
    traj = B.simulate(after, float(t_cross.max()), 0.005, params)
    # (the first plan of a late changer is never executed and need not be reachable)
    legal = reached & physical & aimed[:m] & crossed
    legal = legal & B.is_legal_return(traj, side=geo.ROBOT_SIDE)

    # 6. racket motion: the first plan (late changers) blends into the executed final plan
    swing = (cfg.swing_duration_mean + cfg.swing_duration_std * _randn(m, gen=gen)).clamp(0.2, 0.4)
    turn = torch.where(style == 1, -0.6, 0.6).to(torch.float64)  # ~35 deg, opposite per style
    ready_normal = _unit(_vec(0.0, -1.0, 0.0) + 0.1 * _randn(m, 3, gen=gen))
    first_rows = torch.arange(m)
    first_rows[idx] = m + torch.arange(idx.numel())

    def plan(r: torch.Tensor, base: torch.Tensor) -> _Plan:
        return _Plan(
            ready[base],
            backswing[r],
            contact[base],
            racket_vel[r],
            ready_normal[base],
            _unit(_rotate_z(normal[r], turn[base])),
            normal[r],
            swing[base],
            cfg.backswing_duration,
        )

    base = torch.arange(m)
    final_plan, first_plan = plan(base, base), plan(first_rows, base)
    r_times = torch.linspace(
        float(obs_times[0]), 0.0, round(cfg.window * cfg.racket_rate) + 1, dtype=torch.float64
    )
    r_pos, r_vel, r_normal = _racket(first_plan, final_plan, switch, late, r_times)
    o_pos, o_vel, o_normal = _racket(first_plan, final_plan, switch, late, obs_times)

    # 7. noisy observations
    b_pos = torch.stack([b.pos for b in balls], 1)
    b_vel = torch.stack([b.vel for b in balls], 1)
    T = cfg.n_obs
    obs = torch.cat(
        [
            b_pos + cfg.ball_pos_noise * _randn(m, T, 3, gen=gen),
            b_vel + cfg.ball_vel_noise * _randn(m, T, 3, gen=gen),
            o_pos + cfg.racket_pos_noise * _randn(m, T, 3, gen=gen),
            o_vel + cfg.racket_vel_noise * _randn(m, T, 3, gen=gen),
            _unit(o_normal + cfg.racket_normal_noise * _randn(m, T, 3, gen=gen)),
        ],
        -1,
    )
    return {
        "targets": at_plane.pos[:, 0],
        "intended": intended,
        "final_aim": final_aim,
        "late_change": late,
        "switch_time": switch,
        "obs": obs,
        "hit_time": hit_time,
        "swing_duration": swing,
        "style": style,
        "incoming": incoming,
        "ball_before_hit": before,
        "ball_after_hit": after,
        "racket": RacketTrajectory(r_times, r_pos, r_vel, r_normal),
        "legal": legal,
    }


def _check_targets(targets: object, n: int, cfg: OpponentConfig) -> torch.Tensor:
    t = as_tensor(targets, "targets", dtype=torch.float64, ndim=1)
    if t.shape[0] != n:
        raise ValueError(f"targets must have length n={n}, got {t.shape[0]}")
    if bool((t.abs() > cfg.target_max).any()):
        raise ValueError(
            f"targets must lie within +-{cfg.target_max} m of the hitting plane centre"
        )
    return t.cpu()


def sample_strokes(
    n: int,
    *,
    config: OpponentConfig | None = None,
    targets: object | None = None,
    generator: torch.Generator | None = None,
    params: B.BallParams = B.DEFAULT_PARAMS,
    progress: bool = False,
) -> Strokes:
    """Sample ``n`` opponent strokes with their observations and returned balls.

    Args:
        n: number of strokes (>= 1).
        config: :class:`OpponentConfig` (default settings when ``None``).
        targets: ``[n]`` intended targets on the hitting plane within ``+-config.target_max``;
            drawn uniformly when ``None``.
        generator: CPU ``torch.Generator`` for reproducible draws.
        params: ball constants.
        progress: show a tqdm bar over the redraw rounds.

    Returns:
        :class:`Strokes`, float64 on the CPU.

    Raises:
        ValueError: for ``n < 1``, targets of the wrong length or out of range, or a bad config.
        RuntimeError: when some strokes still have no legal return after ``config.max_rounds``
            rounds (the config's ranges are inconsistent; with the defaults 65-90% of the
            candidates are legal, at least a third even for targets near +-1 m, so the 63
            candidates of 10 rounds all fail with probability below 1e-9 per stroke).

    Candidates whose incoming ball is not reached, whose return cannot be aimed at the target,
    or whose noisy return is not legal are redrawn (everything but the intended target), with
    2, 4, then 8 candidates per pending stroke in later rounds; the result depends only on the
    generator's state, not on torch's default dtype.
    """
    cfg = OpponentConfig() if config is None else config
    if not isinstance(cfg, OpponentConfig):
        raise TypeError(f"config must be an OpponentConfig, got {type(cfg).__name__}")
    if isinstance(n, bool) or not isinstance(n, int) or n < 1:
        raise ValueError(f"n must be an int >= 1, got {n!r}")
    if generator is not None and not isinstance(generator, torch.Generator):
        raise TypeError(f"generator must be a torch.Generator, got {type(generator).__name__}")
    if targets is None:
        intended = _uniform((-cfg.target_max, cfg.target_max), n, generator)
    else:
        intended = _check_targets(targets, n, cfg)
    pending = torch.arange(n)
    parts: list[tuple[torch.Tensor, dict]] = []
    for r in tqdm(range(cfg.max_rounds), disable=not progress, desc="strokes", leave=False):
        # Rejection sampling with growing oversampling: round r draws 2^r candidates (at most
        # 8) for every stroke still pending and keeps the first legal one, so a target that
        # only few contact points can serve (a wide target far from the ball) still gets one.
        copies = min(2**r, 8)
        rows = pending.repeat(copies)
        draw = _sample(intended[rows], cfg, params, generator)
        ok = draw.pop("legal")
        first = torch.zeros(rows.numel(), dtype=torch.bool)
        taken = torch.zeros(n, dtype=torch.bool)
        for i in torch.nonzero(ok).flatten().tolist():
            if not taken[rows[i]]:
                taken[rows[i]] = first[i] = True
        parts.append((rows[first], _select(draw, first)))
        pending = pending[~taken[pending]]
        if pending.numel() == 0:
            break
    else:
        raise RuntimeError(
            f"{pending.numel()} of {n} strokes had no legal return after {cfg.max_rounds} rounds; "
            "check the config's ranges"
        )
    order = torch.argsort(torch.cat([idx for idx, _ in parts]))
    merged = {key: _cat([d[key] for _, d in parts], order) for key in parts[0][1]}
    racket = merged.pop("racket")
    return Strokes(
        **merged,
        obs_times=cfg.obs_times,
        racket=racket,
        feature_names=list(FEATURE_NAMES),
    )


def _select(draw: dict, ok: torch.Tensor) -> dict:
    out = {}
    for key, value in draw.items():
        if isinstance(value, B.BallState):
            out[key] = B.BallState(*(x[ok] for x in value))
        elif isinstance(value, RacketTrajectory):
            out[key] = RacketTrajectory(value.times, *(x[ok] for x in value[1:]))
        else:
            out[key] = value[ok]
    return out


def _cat(values: list, order: torch.Tensor) -> object:
    first = values[0]
    if isinstance(first, B.BallState):
        return B.BallState(*(torch.cat(parts)[order] for parts in zip(*values, strict=True)))
    if isinstance(first, RacketTrajectory):
        return RacketTrajectory(
            first.times,
            *(torch.cat(parts)[order] for parts in zip(*(v[1:] for v in values), strict=True)),
        )
    return torch.cat(values)[order]
