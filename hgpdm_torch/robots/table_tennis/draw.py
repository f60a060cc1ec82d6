"""Matplotlib drawings of the table-tennis setup: table, arm, racket, ball paths, hitting regions.

The scene is drawn in the world frame of :mod:`.geometry` on 3-D axes (``projection="3d"``); the
arm is drawn from forward kinematics (:meth:`..wam.WAM.frame_positions`), so a drawing shows what
the kinematic model computes, not a picture. :func:`plot_hitting_regions` draws the analogue of
the thesis's Fig. 3.8: the success rate of each movement versus the target ``x`` on the hitting
plane (from :func:`.trials.hitting_regions`).
"""

from __future__ import annotations

import math

import numpy as np
import torch
from matplotlib.axes import Axes

from ..wam import RACKET_RADIUS, WAM
from . import geometry as geo
from .strokes import MOVEMENTS, StrokeOutcome

__all__ = ["MOVEMENT_COLORS", "draw_arm", "draw_stroke", "draw_table", "plot_hitting_regions"]

MOVEMENT_COLORS = {"forehand": "tab:red", "middle": "tab:green", "backhand": "tab:blue"}
"""Colour of each movement in every drawing."""


def _check_3d(ax: Axes) -> None:
    if not hasattr(ax, "plot3D"):
        raise TypeError("ax must be a 3-D axes (fig.add_subplot(projection='3d'))")


def draw_table(ax: Axes, *, hitting_plane: bool = True) -> None:
    """Table top, net and (optionally) the robot's virtual hitting plane.

    On 3-D axes the scene is drawn in the world frame; on 2-D axes as a top view (x, y).
    """
    w, h, z = geo.TABLE_HALF_WIDTH, geo.TABLE_HALF_LENGTH, geo.TABLE_HEIGHT
    top = np.array([[-w, -h, z], [w, -h, z], [w, h, z], [-w, h, z], [-w, -h, z]])
    n, nz = geo.NET_HALF_WIDTH, z + geo.NET_HEIGHT
    y, x = geo.HITTING_PLANE_Y, geo.TARGET_X_MAX
    if not hasattr(ax, "plot3D"):
        ax.plot(top[:, 0], top[:, 1], color="tab:brown", lw=1.5)
        ax.plot([0, 0], [-h, h], color="tab:brown", lw=0.5)
        ax.plot([-n, n], [0, 0], color="k", lw=1)
        if hitting_plane:
            ax.plot([-x, x], [y, y], color="gray", ls="--", lw=0.8)
        ax.set_aspect("equal")
        ax.set_xlabel("x [m]")
        ax.set_ylabel("y [m]")
        return
    ax.plot3D(*top.T, color="tab:brown", lw=1.5)
    ax.plot3D([0, 0], [-h, h], [z, z], color="tab:brown", lw=0.5)  # centre line
    net = np.array([[-n, 0, z], [-n, 0, nz], [n, 0, nz], [n, 0, z]])
    ax.plot3D(*net.T, color="k", lw=1)
    if hitting_plane:
        plane = np.array([[-x, y, 0.5], [x, y, 0.5], [x, y, 1.3], [-x, y, 1.3], [-x, y, 0.5]])
        ax.plot3D(*plane.T, color="gray", ls="--", lw=0.8)
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    ax.set_zlabel("z [m]")


def draw_arm(ax: Axes, wam: WAM, q: object, *, color: str = "k", alpha: float = 1.0) -> None:
    """The arm at joint angles ``q`` ``[7]``: its link frames joined up, and the racket disc."""
    _check_3d(ax)
    q_t = torch.as_tensor(np.asarray(q, dtype=np.float64))
    if q_t.shape != (7,):
        raise ValueError(f"q must have shape [7], got {tuple(q_t.shape)}")
    pts = wam.frame_positions(q_t).numpy()
    ax.plot3D(*pts[:-1].T, color=color, lw=3, alpha=alpha, marker="o", ms=3)
    ax.plot3D(*pts[-2:].T, color=color, lw=1.5, alpha=alpha)  # handle to the racket centre
    pose = wam.fk(q_t)
    rot = pose.rotation.numpy()
    phi = np.linspace(0, 2 * math.pi, 41)
    rim = pose.position.numpy()[:, None] + RACKET_RADIUS * (
        rot[:, :1] * np.cos(phi) + rot[:, 1:2] * np.sin(phi)
    )
    ax.plot3D(*rim, color=color, lw=1.5, alpha=alpha)


def draw_stroke(
    ax: Axes,
    outcome: StrokeOutcome,
    wam: WAM | None = None,
    *,
    color: str = "tab:red",
    label: str | None = None,
) -> None:
    """Racket and ball paths of a simulated stroke, and the arm at the hit when ``wam`` is given.

    Args:
        ax: 3-D axes.
        outcome: the :class:`.strokes.StrokeOutcome` of :func:`.strokes.execute_stroke`.
        wam: the arm's kinematics, to draw the arm at the moment closest to the hit.
        color: colour of the racket path and the arm.
        label: legend label of the racket path.
    """
    _check_3d(ax)
    if not isinstance(outcome, StrokeOutcome):
        raise TypeError(f"outcome must be a StrokeOutcome, got {type(outcome).__name__}")
    ball = outcome.ball_path
    ax.plot3D(*ball.T, color="orange", lw=1, label="ball")
    ax.plot3D(*outcome.racket_path.T, color=color, lw=1.5, label=label)
    if outcome.hit:
        land = outcome.landing
        if np.isfinite(land).all():
            ax.scatter([land[0]], [land[1]], [geo.TABLE_HEIGHT], color="orange", marker="x")
    if wam is not None and len(outcome.joint_path):
        n = min(len(outcome.racket_path), len(ball))
        gap = np.linalg.norm(outcome.racket_path[:n] - ball[:n], axis=1)
        k = int(np.nanargmin(gap)) if np.isfinite(gap).any() else n - 1
        draw_arm(ax, wam, outcome.joint_path[k], color=color, alpha=0.8)


def plot_hitting_regions(
    ax: Axes,
    centers: np.ndarray,
    rates: dict[str, np.ndarray],
    counts: np.ndarray | None = None,
    *,
    start_time: float | None = None,
) -> None:
    """Success rate of each movement versus target ``x`` (the thesis's Fig. 3.8 analogue).

    Args:
        ax: 2-D axes.
        centers: ``[K]`` bin centres of the target ``x`` [m].
        rates: movement name -> ``[K]`` success rate in each bin (NaN for empty bins).
        counts: optional ``[K]`` trials per bin, shown as a faint bar chart on a twin axis.
        start_time: movement start relative to the opponent's hit [s], for the title.
    """
    centers = np.asarray(centers, dtype=np.float64)
    for name in rates:
        if name not in MOVEMENTS:
            raise ValueError(f"unknown movement {name!r} in rates; expected one of {MOVEMENTS}")
        r = np.asarray(rates[name], dtype=np.float64)
        if r.shape != centers.shape:
            raise ValueError(f"rates[{name!r}] must have shape {centers.shape}, got {r.shape}")
        ax.plot(centers, r, marker="o", color=MOVEMENT_COLORS[name], label=name)
        ax.fill_between(centers, 0, np.nan_to_num(r), color=MOVEMENT_COLORS[name], alpha=0.12)
    if counts is not None:
        twin = ax.twinx()
        width = float(np.min(np.diff(centers))) if centers.size > 1 else 0.2
        twin.bar(centers, counts, width=0.9 * width, color="gray", alpha=0.15)
        twin.set_ylabel("trials per bin")
        ax.set_zorder(twin.get_zorder() + 1)  # the curves in front of the bars
        ax.patch.set_visible(False)
    ax.axvspan(-geo.TABLE_HALF_WIDTH, geo.TABLE_HALF_WIDTH, color="tab:brown", alpha=0.06)
    ax.set_xlim(-geo.TARGET_X_MAX - 0.1, geo.TARGET_X_MAX + 0.1)
    ax.set_ylim(-0.02, 1.02)
    ax.set_xlabel("target x on the hitting plane [m]")
    ax.set_ylabel("success rate")
    when = "" if start_time is None else f", started {-1000 * start_time:.0f} ms before the hit"
    ax.set_title(f"Hitting regions{when}")
    ax.legend(loc="upper left")
