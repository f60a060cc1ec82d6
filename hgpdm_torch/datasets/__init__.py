"""Datasets: seeded synthetic generators and loaders for real movement data."""

from .basic_motions import load_basic_motions
from .cmu import PROTOCOLS, MotionTrials, Protocol, load_protocol, load_trials
from .kinect_features import PosePCA, kinect_features
from .mocap import load_mocap, read_amc, read_asf
from .msrc12 import (
    MSRC12,
    MissingTagstreamError,
    MSRC12Recording,
    load_msrc12_folder,
    load_msrc12_npz,
    read_msrc12_recording,
)
from .synthetic import MovementSet, styled_movements, targeted_movements
from .walkers import FRAME_FEATURES, Standardizer, frame_features, motion_features

__all__ = [
    "FRAME_FEATURES",
    "MSRC12",
    "MSRC12Recording",
    "MotionTrials",
    "MissingTagstreamError",
    "MovementSet",
    "PROTOCOLS",
    "PosePCA",
    "Protocol",
    "Standardizer",
    "frame_features",
    "kinect_features",
    "load_basic_motions",
    "load_mocap",
    "load_msrc12_folder",
    "load_msrc12_npz",
    "load_protocol",
    "load_trials",
    "motion_features",
    "read_amc",
    "read_asf",
    "read_msrc12_recording",
    "styled_movements",
    "targeted_movements",
]
