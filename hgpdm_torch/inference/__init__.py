"""Inference in the H-GPDM/IDDM: GP-ADF filtering and GP-RTSS smoothing (Ch. 3), variational
Bayes (Ch. 2.3), the MAP baseline (conditional GPDM), and batch and online intention inference
(Algorithms 3.1-3.2)."""

from ..calibration import calibration, fit_temperature, grid_index, temper
from ..intention_belief import IntentionBelief, IntentionModel, IntentionStream
from ..observations import DEFAULT_OUTLIER_SD, ObservationCheck
from .filtering import (
    FilterResult,
    SmootherResult,
    filter_sequence,
    gp_adf_predict,
    gp_adf_update,
    smooth,
)
from .intention import (
    BeliefMixture,
    BeliefMixtureStream,
    FilterBeliefs,
    LinearMeasurement,
    OnlineIntentionFilter,
    SharedTransition,
    batch_bound,
    batch_bound_terms,
    class_state_prior,
    expected_log_conditional,
    infer_intention,
    intention_grid,
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
    "DEFAULT_OUTLIER_SD",
    "FilterResult",
    "ObservationCheck",
    "BeliefMixture",
    "BeliefMixtureStream",
    "FilterBeliefs",
    "IntentionBelief",
    "IntentionModel",
    "IntentionStream",
    "LinearMeasurement",
    "OnlineIntentionFilter",
    "SharedTransition",
    "batch_bound",
    "batch_bound_terms",
    "calibration",
    "fit_temperature",
    "grid_index",
    "temper",
    "class_state_prior",
    "expected_log_conditional",
    "infer_intention",
    "intention_grid",
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
