"""The shared world frame and ITTF geometry of the table-tennis scene (thesis Sec. 3.5, 4.3).

World frame: the origin is on the floor below the centre of the table; ``x`` is lateral (across
the 1.525 m width), ``y`` runs along the table from the robot's side (``y < 0``) to the human
opponent's side (``y > 0``), and ``z`` points up. All lengths are in metres, masses in kg.

The robot's *virtual hitting plane* (thesis Fig. 2.4/4.2, after Mülling et al., 2011) is the plane
``y = HITTING_PLANE_Y``, 0.8 m behind the robot's end line; the opponent's *target* is the lateral
position ``x`` at which the returned ball crosses it.
"""

from __future__ import annotations

__all__ = [
    "BALL_MASS",
    "BALL_RADIUS",
    "GRAVITY",
    "HITTING_PLANE_OFFSET",
    "HITTING_PLANE_Y",
    "NET_HALF_WIDTH",
    "NET_HEIGHT",
    "NET_OVERHANG",
    "NET_Y",
    "OPPONENT_SIDE",
    "ROBOT_SIDE",
    "TABLE_HALF_LENGTH",
    "TABLE_HALF_WIDTH",
    "TABLE_HEIGHT",
    "TABLE_LENGTH",
    "TABLE_WIDTH",
    "TARGET_X_MAX",
]

TABLE_LENGTH = 2.74
"""ITTF table length along ``y`` [m]."""

TABLE_WIDTH = 1.525
"""ITTF table width along ``x`` [m]."""

TABLE_HALF_LENGTH = TABLE_LENGTH / 2
"""Distance from the net to either end line along ``y`` (1.37 m)."""

TABLE_HALF_WIDTH = TABLE_WIDTH / 2
"""Distance from the centre line to either side line along ``x`` (0.7625 m)."""

TABLE_HEIGHT = 0.76
"""Height of the playing surface above the floor [m]."""

NET_Y = 0.0
"""The net stands in the plane ``y = 0``, halfway along the table."""

NET_HEIGHT = 0.1525
"""Height of the net's top above the playing surface [m]."""

NET_OVERHANG = 0.1525
"""How far the net posts stand outside each side line [m]."""

NET_HALF_WIDTH = TABLE_HALF_WIDTH + NET_OVERHANG
"""Half the net's length along ``x``, post to post (0.915 m)."""

HITTING_PLANE_OFFSET = 0.8
"""Distance of the robot's virtual hitting plane behind the robot's end line [m]."""

HITTING_PLANE_Y = -(TABLE_HALF_LENGTH + HITTING_PLANE_OFFSET)
"""``y`` of the robot's virtual hitting plane (-2.17 m)."""

TARGET_X_MAX = 1.2
"""Intended targets are lateral positions ``x`` on the hitting plane within ``+-TARGET_X_MAX``."""

ROBOT_SIDE = -1
"""Sign of ``y`` on the robot's half of the table."""

OPPONENT_SIDE = 1
"""Sign of ``y`` on the human opponent's half of the table."""

BALL_MASS = 0.0027
"""ITTF ball mass (2.7 g) [kg]."""

BALL_RADIUS = 0.02
"""ITTF ball radius (40 mm diameter) [m]."""

GRAVITY = 9.802
"""Gravitational acceleration used by the SL table-tennis simulator lineage [m/s^2]."""
