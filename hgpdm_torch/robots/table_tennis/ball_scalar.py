"""One ball in plain Python floats: :class:`ScalarBall`, the fast path of an unbatched state.

A single float64 ball on the CPU is what the robot's stroke predicts, aims and judges; the public
functions of :mod:`hgpdm_torch.robots.table_tennis.ball` hand such a state to :class:`ScalarBall`
(through the private bridges at the end of this module) and keep batches as tensors.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from functools import lru_cache

import numpy as np
import torch

from hgpdm_torch.robots.table_tennis import geometry as geo
from hgpdm_torch.robots.table_tennis.ball_state import (
    DEFAULT_PARAMS,
    BallParams,
    BallState,
    check_params,
)

__all__ = [
    "Floats",
    "ScalarBall",
]

#: A single ball's state as nine floats: position, velocity, spin (each x, y, z).
Floats = tuple[float, float, float, float, float, float, float, float, float]


class ScalarBall:
    """The ball model of :mod:`.ball` for one ball, in plain Python floats.

    One ball is what the robot's stroke predicts, aims and judges, and on a batch of one every
    step of the tensor code is a few dozen tensor operations of a few microseconds each; the
    same arithmetic on floats is ~30 times faster. The methods mirror :func:`rk4_step`,
    :func:`find_event_root`, :func:`advance_events`, :func:`find_plane_crossing` and
    :func:`fly_batch_for` operation for operation (the same equations, events, root finder and
    tolerances), so that the two agree to rounding; ``tests/robots/test_ball.py`` checks it. The
    public functions of the ball model use it for an unbatched float64 CPU state; batches stay
    tensors.

    States are :data:`Floats` tuples ``(px, py, pz, vx, vy, vz, wx, wy, wz)``.
    """

    def __init__(self, params: BallParams = DEFAULT_PARAMS) -> None:
        self.params = check_params(params)
        self._drag = -params.drag
        self._magnus = params.magnus
        self._g = params.gravity
        self.radius = params.radius
        self._level = geo.TABLE_HEIGHT + params.radius
        self._fx = params.table_friction_x - 1.0
        self._fy = params.table_friction_y - 1.0
        self._e = -params.table_restitution
        self._kr = params.inertia_factor * params.radius
        self._net = (params.net_damping, -params.net_restitution, params.net_damping)

    # -- flight --------------------------------------------------------------------------------
    def rk4(self, s: Floats, h: float) -> Floats:
        """One classical RK4 step of length ``h`` (may be 0) in free flight (:func:`rk4_step`; the
        drag, Magnus and gravity of the four stages written out)."""
        vx, vy, vz = s[3], s[4], s[5]
        km, kd, g = self._magnus, self._drag, self._g
        wx, wy, wz = km * s[6], km * s[7], km * s[8]  # the Magnus factor on the spin, as rk4_step
        hh = 0.5 * h
        c = kd * math.sqrt(vx * vx + vy * vy + vz * vz)
        a1x = c * vx + (wy * vz - wz * vy)
        a1y = c * vy + (wz * vx - wx * vz)
        a1z = c * vz + (wx * vy - wy * vx) - g
        v2x, v2y, v2z = vx + hh * a1x, vy + hh * a1y, vz + hh * a1z
        c = kd * math.sqrt(v2x * v2x + v2y * v2y + v2z * v2z)
        a2x = c * v2x + (wy * v2z - wz * v2y)
        a2y = c * v2y + (wz * v2x - wx * v2z)
        a2z = c * v2z + (wx * v2y - wy * v2x) - g
        v3x, v3y, v3z = vx + hh * a2x, vy + hh * a2y, vz + hh * a2z
        c = kd * math.sqrt(v3x * v3x + v3y * v3y + v3z * v3z)
        a3x = c * v3x + (wy * v3z - wz * v3y)
        a3y = c * v3y + (wz * v3x - wx * v3z)
        a3z = c * v3z + (wx * v3y - wy * v3x) - g
        v4x, v4y, v4z = vx + h * a3x, vy + h * a3y, vz + h * a3z
        c = kd * math.sqrt(v4x * v4x + v4y * v4y + v4z * v4z)
        a4x = c * v4x + (wy * v4z - wz * v4y)
        a4y = c * v4y + (wz * v4x - wx * v4z)
        a4z = c * v4z + (wx * v4y - wy * v4x) - g
        h6 = h / 6.0
        return (
            s[0] + h6 * (vx + 2 * v2x + 2 * v3x + v4x),
            s[1] + h6 * (vy + 2 * v2y + 2 * v3y + v4y),
            s[2] + h6 * (vz + 2 * v2z + 2 * v3z + v4z),
            vx + h6 * (a1x + 2 * a2x + 2 * a3x + a4x),
            vy + h6 * (a1y + 2 * a2y + 2 * a3y + a4y),
            vz + h6 * (a1z + 2 * a2z + 2 * a3z + a4z),
            s[6],
            s[7],
            s[8],
        )

    def fly_for(self, s: Floats, t: float) -> Floats:
        """Free flight for ``t`` seconds in ``max(8, ceil(t / 5 ms))`` RK4 steps (no contacts)."""
        n = max(8, math.ceil(t / 0.005))
        h = t / n
        for _ in range(n):
            s = self.rk4(s, h)
        return s

    # -- events --------------------------------------------------------------------------------
    @staticmethod
    def _root(
        s: Floats,
        hi: float,
        g_start: float,
        g_end: float,
        event: Callable[[Floats], tuple[float, float]],
        fly: Callable[[Floats, float], Floats],
        iters: int = 12,
    ) -> float:
        """:func:`find_event_root` for one ball."""
        lo = 0.0
        denom = g_start - g_end
        tau = hi * g_start / denom if denom > 0 else hi
        tau = min(max(tau, 0.0), hi)
        for _ in range(iters):
            g, gdot = event(fly(s, tau))
            if abs(g) < 1e-14:
                break
            if g > 0:
                lo = tau
            else:
                hi = tau
            newton = tau - g / gdot if gdot != 0 else math.nan
            tau = newton if lo <= newton <= hi else 0.5 * (lo + hi)
        return tau

    def _table_event(self, s: Floats) -> tuple[float, float]:
        return s[2] - self._level, s[5]

    def _bounce(self, s: Floats) -> Floats:
        """:func:`table_bounce` for one ball."""
        r = self.radius
        vx, vy, vz, wx, wy, wz = s[3:]
        dvx = self._fx * (vx - r * wy)
        dvy = self._fy * (vy + r * wx)
        kr = self._kr
        return (s[0], s[1], geo.TABLE_HEIGHT + r, vx + dvx, vy + dvy, self._e * vz,
                wx + dvy / kr, wy - dvx / kr, wz)  # fmt: skip

    def _net_hit(self, s: Floats, sign: float) -> Floats:
        """:func:`net_hit` for one ball travelling along ``sign`` in ``y``."""
        d, e, _ = self._net
        return (s[0], geo.NET_Y - sign * self.radius, s[2], s[3] * d, s[4] * e, s[5] * d,
                s[6] * d, s[7] * d, s[8] * d)  # fmt: skip

    def advance(
        self, s: Floats, h: float, max_events: int = 4
    ) -> tuple[Floats, bool, tuple[float, float, float], float, bool]:
        """:func:`advance_events` for one ball: the state after ``h`` seconds through contacts.

        Returns:
            ``(state, bounce, bounce_pos, bounce_time, net)`` as in :class:`StepEvents`.
        """
        r = self.radius
        remaining, elapsed = h, 0.0
        bounce = net = False
        bounce_pos, bounce_time = (0.0, 0.0, 0.0), 0.0
        rk4, level = self.rk4, self._level
        for _ in range(max_events + 1):
            if not remaining > 0:
                break
            trial = rk4(s, remaining)
            g0_t, g1_t = s[2] - level, trial[2] - level
            table = g0_t > 0 and g1_t <= 0
            sign = math.copysign(1.0, s[4]) if s[4] != 0 else 0.0
            g0_n = -sign * (s[1] - geo.NET_Y) - r
            g1_n = -sign * (trial[1] - geo.NET_Y) - r
            at_net = sign != 0 and g0_n > 0 and g1_n <= 0
            if not (table or at_net):
                s = trial
                break
            tau_t = tau_n = math.inf
            if table:
                tau = self._root(s, remaining, g0_t, g1_t, self._table_event, rk4)
                x, y = rk4(s, tau)[:2]
                table = abs(x) <= geo.TABLE_HALF_WIDTH and abs(y) <= geo.TABLE_HALF_LENGTH
                if table:
                    tau_t = tau
            if at_net:

                def net_event(q: Floats, sign: float = sign) -> tuple[float, float]:
                    return -sign * (q[1] - geo.NET_Y) - r, -sign * q[4]

                tau = self._root(s, remaining, g0_n, g1_n, net_event, rk4)
                q = rk4(s, tau)
                z = q[2] - geo.TABLE_HEIGHT
                at_net = abs(q[0]) <= geo.NET_HALF_WIDTH + r and 0 < z < geo.NET_HEIGHT + r
                if at_net:
                    tau_n = tau
            use_t = table and tau_t <= tau_n
            use_n = at_net and not use_t
            tau = tau_t if use_t else tau_n if use_n else remaining
            at = rk4(s, tau)
            if use_t and not bounce:
                bounce_pos, bounce_time = (at[0], at[1], geo.TABLE_HEIGHT), elapsed + tau
            bounce = bounce or use_t
            net = net or use_n
            s = self._bounce(at) if use_t else self._net_hit(at, sign) if use_n else at
            elapsed += tau
            remaining = remaining - tau if use_t or use_n else 0.0
        else:
            s = rk4(s, remaining)
        return s, bounce, bounce_pos, bounce_time, net

    def propagate(self, s: Floats, duration: float, dt: float = 0.005) -> Floats:
        """:func:`propagate` for one ball: ``duration`` seconds in steps of ``dt``."""
        for k in range(math.ceil(duration / dt - 1e-9)):
            s = self.advance(s, min(max(duration - k * dt, 0.0), dt))[0]
        return s

    def simulate(self, s: Floats, duration: float, dt: float) -> tuple[float, list[tuple]]:
        """:func:`simulate` for one ball.

        Returns:
            The step ``h`` and ``n + 1`` samples ``(state, bounce, bounce_pos, bounce_time,
            net)``, bounce times absolute, the first sample without events.
        """
        n = max(1, round(duration / dt))
        h = duration / n
        out: list[tuple] = [(s, False, (0.0, 0.0, 0.0), 0.0, False)]
        for k in range(n):
            s, bounce, pos, time, net = self.advance(s, h)
            out.append((s, bounce, pos, time + k * h if bounce else time, net))
        return h, out

    def plane_crossing(
        self, s: Floats, y_plane: float, max_time: float = 2.0, dt: float = 0.005
    ) -> tuple[float, Floats, bool]:
        """:func:`predict_plane_crossing` for one ball: ``(t, state at the crossing, valid)``."""
        sign = 1.0 if s[1] - y_plane >= 0 else -1.0

        def event(q: Floats) -> tuple[float, float]:
            return sign * (q[1] - y_plane), sign * q[4]

        def fly(q: Floats, tau: float) -> Floats:
            return self.advance(q, tau)[0]

        t = 0.0
        for k in range(math.ceil(max_time / dt - 1e-9)):
            h = min(dt, max_time - k * dt)
            new = self.advance(s, h)[0]
            g_start, g_end = sign * (s[1] - y_plane), sign * (new[1] - y_plane)
            if g_start > 0 and g_end <= 0:
                tau = self._root(s, h, g_start, g_end, event, fly)
                at = fly(s, tau)
                return t + tau, at, at[2] > self.radius
            if new[2] <= self.radius:
                return float(max_time), new, False
            t += h
            s = new
        return float(max_time), s, False

    # -- aiming --------------------------------------------------------------------------------
    def aim(
        self,
        pos: tuple[float, float, float],
        target: tuple[float, float, float],
        flight_time: float,
        spin: tuple[float, float, float] = (0.0, 0.0, 0.0),
        tol: float = 1e-9,
        max_iter: int = 20,
    ) -> tuple[tuple[float, float, float], float]:
        """:func:`_aim` for one ball: ``(v0, residual [m])`` (``inf`` when it diverged)."""
        t = flight_time
        guess = tuple((b - a) / t + (0.5 * self._g * t if i == 2 else 0.0)
                      for i, (a, b) in enumerate(zip(pos, target, strict=True)))  # fmt: skip
        eps = 1e-6
        tgt = np.array(target)

        def end(v: np.ndarray) -> np.ndarray:
            return np.array(self.fly_for((*pos, *v.tolist(), *spin), t)[:3]) - tgt

        v = np.array(guess)
        for _ in range(max_iter):
            resid = end(v)
            if float(np.nan_to_num(np.abs(resid), nan=math.inf).max()) < tol:
                break
            jac = np.stack([(end(v + d) - end(v - d)) / (2 * eps) for d in np.eye(3) * eps], -1)
            try:
                step = np.linalg.solve(jac, resid)
            except np.linalg.LinAlgError:
                step = np.full(3, math.nan)
            # a singular or diverged iterate restarts from the guess, judged by its residual
            v = v - step if np.isfinite(step).all() else np.array(guess)
        else:
            resid = end(v)
        err = float(np.abs(resid).max())
        if not (np.isfinite(v).all() and math.isfinite(err)):
            return guess, math.inf
        return (float(v[0]), float(v[1]), float(v[2])), err


# --------------------------------------------------------------------------------------------
# bridges between a BallState and floats


def is_single_ball(state: BallState) -> bool:
    """Whether ``state`` is one float64 ball on the CPU (integrated by :class:`ScalarBall`)."""
    p = state.pos
    return (
        p.dim() == 1 and p.dtype == torch.float64 and p.device.type == "cpu" and not p.requires_grad
    )


def state_floats(state: BallState) -> Floats:
    return tuple(torch.cat(tuple(state)).tolist())  # type: ignore[return-value]


def floats_to_state(s: Floats) -> BallState:
    return BallState(*(torch.tensor(s[i : i + 3], dtype=torch.float64) for i in (0, 3, 6)))


@lru_cache(maxsize=16)
def scalar_ball(params: BallParams) -> ScalarBall:
    return ScalarBall(params)
