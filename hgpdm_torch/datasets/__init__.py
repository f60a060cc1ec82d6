"""Datasets: seeded synthetic generators and loaders for real movement data."""

from .synthetic import MovementSet, styled_movements, targeted_movements

__all__ = ["MovementSet", "styled_movements", "targeted_movements"]
