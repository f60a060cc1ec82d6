"""Quintic joint trajectories: the segments every stage of a hitting movement follows.

A :class:`Quintic` joins two joint states (position, velocity, acceleration) per joint;
:func:`min_quintic_duration` is the shortest rest-to-rest one within velocity and acceleration
limits.
"""

from __future__ import annotations

import math

import numpy as np

from ..wam import DOF

__all__ = ["Quintic", "min_quintic_duration"]

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
