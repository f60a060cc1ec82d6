"""Inference in the H-GPDM/IDDM: GP-ADF filtering and GP-RTSS smoothing (Ch. 3), variational
Bayes (Ch. 2.3) and the MAP baseline (conditional GPDM)."""

from .filtering import (
    FilterResult,
    SmootherResult,
    filter_sequence,
    gp_adf_predict,
    gp_adf_update,
    smooth,
)
from .map import MAPInference, MAPResult
from .variational import (
    MeanFieldGuide,
    VariationalInference,
    VBResult,
    batched_lbfgs,
    condition_gaussian,
)

__all__ = [
    "FilterResult",
    "MAPInference",
    "MAPResult",
    "MeanFieldGuide",
    "VBResult",
    "VariationalInference",
    "batched_lbfgs",
    "condition_gaussian",
    "SmootherResult",
    "filter_sequence",
    "gp_adf_predict",
    "gp_adf_update",
    "smooth",
]
