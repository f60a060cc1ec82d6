"""Datasets: seeded synthetic generators and loaders for real movement data."""

from .mocap import load_mocap, read_amc, read_asf
from .synthetic import MovementSet, styled_movements, targeted_movements
from .walkers import Standardizer, Walkers, load_walkers, motion_features

__all__ = [
    "MovementSet",
    "Standardizer",
    "Walkers",
    "load_mocap",
    "load_walkers",
    "motion_features",
    "read_amc",
    "read_asf",
    "styled_movements",
    "targeted_movements",
]
