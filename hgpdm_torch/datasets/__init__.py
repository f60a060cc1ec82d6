"""Datasets: seeded synthetic generators and loaders for real movement data."""

from .mocap import load_mocap, read_amc, read_asf
from .synthetic import MovementSet, styled_movements, targeted_movements

__all__ = [
    "MovementSet",
    "load_mocap",
    "read_amc",
    "read_asf",
    "styled_movements",
    "targeted_movements",
]
