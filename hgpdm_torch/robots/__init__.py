"""Robots: the Barrett WAM arm (kinematics) and the table-tennis setup. Knows nothing of GPs."""

from .wam import WAM, IKResult, RacketPose

__all__ = ["IKResult", "RacketPose", "WAM"]
