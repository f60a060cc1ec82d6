"""The joint reference of a stroke: a tracker with saturated acceleration and velocity.

:class:`LimitedTracker` turns a planned trajectory into the reference of the arm's PD drives; a
plan that needs more than the joint limits allow is followed with a lag, which is what makes the
racket miss balls out of a movement's reach.
"""

from __future__ import annotations

import numpy as np

from ..wam import DOF

__all__ = ["LimitedTracker"]

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
