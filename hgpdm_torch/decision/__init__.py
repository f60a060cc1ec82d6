"""Decision making: repeated games and delta-safe opponent modeling (Ch. 5)."""

from .games import (
    RPS_REWARD,
    TABLE_TENNIS_REWARD,
    FiniteStageGame,
    best_response,
    expected_reward,
    fictitious_play,
    minimax_strategy,
    sample_counts,
    two_stage_rps,
)
from .opponent import (
    AdaptiveLearner,
    DeltaSafeResponder,
    KLBall,
    SafeResponse,
    TreeResponse,
    delta_safe_tree,
    kl_bound,
    kl_divergence,
    solve_delta_safe,
    two_sample_z_test,
)

__all__ = [
    "AdaptiveLearner",
    "DeltaSafeResponder",
    "FiniteStageGame",
    "KLBall",
    "RPS_REWARD",
    "SafeResponse",
    "TABLE_TENNIS_REWARD",
    "TreeResponse",
    "best_response",
    "delta_safe_tree",
    "expected_reward",
    "fictitious_play",
    "kl_bound",
    "kl_divergence",
    "minimax_strategy",
    "sample_counts",
    "solve_delta_safe",
    "two_sample_z_test",
    "two_stage_rps",
]
