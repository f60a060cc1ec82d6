"""Datasets: seeded synthetic generators and loaders for real movement data."""

from .basic_motions import load_basic_motions
from .bvh import BvhMotion, BvhSkeleton, load_bvh, read_bvh
from .c3d import C3D_GAPS, C3dMarkers, MarkerTrials, load_c3d, read_c3d
from .cmu import PROTOCOLS, MotionTrials, Protocol, load_protocol, load_trials
from .kinect_features import PosePCA, kinect_features
from .mocap import MAX_ANGLE_DEGREES, load_mocap, read_amc, read_asf
from .msrc12 import (
    MAX_POSITION_M,
    MSRC12,
    MissingTagstreamError,
    MSRC12Recording,
    load_msrc12_folder,
    load_msrc12_npz,
    read_msrc12_recording,
)
from .synthetic import MovementSet, styled_movements, targeted_movements
from .walkers import (
    FRAME_FEATURES,
    FoundTrials,
    MissingTrialsError,
    Standardizer,
    find_trials,
    frame_features,
    motion_features,
    protocol_trials,
)

__all__ = [
    "C3D_GAPS",
    "FRAME_FEATURES",
    "MAX_ANGLE_DEGREES",
    "MAX_POSITION_M",
    "BvhMotion",
    "BvhSkeleton",
    "C3dMarkers",
    "FoundTrials",
    "MarkerTrials",
    "MSRC12",
    "MSRC12Recording",
    "MotionTrials",
    "MissingTagstreamError",
    "MissingTrialsError",
    "MovementSet",
    "PROTOCOLS",
    "PosePCA",
    "Protocol",
    "Standardizer",
    "find_trials",
    "frame_features",
    "kinect_features",
    "load_basic_motions",
    "load_bvh",
    "load_c3d",
    "load_mocap",
    "load_msrc12_folder",
    "load_msrc12_npz",
    "load_protocol",
    "load_trials",
    "motion_features",
    "protocol_trials",
    "read_amc",
    "read_asf",
    "read_bvh",
    "read_c3d",
    "read_msrc12_recording",
    "styled_movements",
    "targeted_movements",
]
