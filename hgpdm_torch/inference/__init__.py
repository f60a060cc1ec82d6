"""Inference in the H-GPDM/IDDM: GP-ADF filtering and GP-RTSS smoothing (Ch. 3)."""

from .filtering import (
    FilterResult,
    SmootherResult,
    filter_sequence,
    gp_adf_predict,
    gp_adf_update,
    smooth,
)

__all__ = [
    "FilterResult",
    "SmootherResult",
    "filter_sequence",
    "gp_adf_predict",
    "gp_adf_update",
    "smooth",
]
