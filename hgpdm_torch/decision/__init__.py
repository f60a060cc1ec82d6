"""Decision making: anticipatory action selection as optimal stopping (Ch. 4: LSPI, Monte-Carlo
planning, NAC) and delta-safe opponent modeling in repeated games (Ch. 5)."""

from .basis import RadialBasis, action_features
from .games import (
    RPS_REWARD,
    TABLE_TENNIS_REWARD,
    FiniteStageGame,
    best_response,
    expected_reward,
    fictitious_play,
    minimax_equilibrium,
    minimax_strategy,
    sample_counts,
    two_stage_rps,
)
from .lspi import LinearQ, LSPIResult, lspi, lstdq
from .mcp import Belief, MCPDecision, MonteCarloPlanner, ParticleUpdate
from .nac import NACResult, SoftmaxPolicy, nac, natural_gradient
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
from .stopping import (
    ACTIONS,
    EXPLORATION,
    WAIT,
    Episodes,
    StoppingProblem,
    Transitions,
    belief_vector,
)

__all__ = [
    "ACTIONS",
    "Belief",
    "EXPLORATION",
    "Episodes",
    "LSPIResult",
    "LinearQ",
    "MCPDecision",
    "MonteCarloPlanner",
    "ParticleUpdate",
    "NACResult",
    "RadialBasis",
    "SoftmaxPolicy",
    "StoppingProblem",
    "Transitions",
    "WAIT",
    "action_features",
    "belief_vector",
    "lspi",
    "lstdq",
    "minimax_equilibrium",
    "nac",
    "natural_gradient",
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
