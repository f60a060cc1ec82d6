"""Decision making: anticipatory action selection as optimal stopping (Ch. 4: LSPI, Monte-Carlo
planning, NAC) and delta-safe opponent modeling in repeated games (Ch. 5).

Every name is imported on first use, so importing one part (e.g. the opponent modeling of Ch. 5,
which needs only numpy and scipy) does not load the GP inference behind the planners.
"""

from __future__ import annotations

from .._lazy import lazy_exports

# A name that is also the name of its module is bound now: importing that submodule anywhere
# would otherwise bind the module under the name before the lazy lookup could run.
from .lspi import lspi as lspi
from .nac import nac as nac

_EXPORTS: dict[str, str] = {
    "ACTIONS": ".stopping",
    "AdaptiveLearner": ".opponent",
    "Belief": ".mcp",
    "DeltaSafeResponder": ".opponent",
    "EXPLORATION": ".stopping",
    "EarlyStopping": ".mcp",
    "Episodes": ".stopping",
    "FiniteStageGame": ".games",
    "KLBall": ".opponent",
    "LSPIResult": ".lspi",
    "LinearQ": ".lspi",
    "MCPDecision": ".mcp",
    "MomentBasis": ".basis",
    "MonteCarloPlanner": ".mcp",
    "NACResult": ".nac",
    "ParticleProjector": ".mcp",
    "ParticleUpdate": ".mcp",
    "RPS_REWARD": ".games",
    "RadialBasis": ".basis",
    "SafeResponse": ".opponent",
    "SoftmaxPolicy": ".nac",
    "StoppingProblem": ".stopping",
    "TABLE_TENNIS_REWARD": ".games",
    "Transitions": ".stopping",
    "TreeResponse": ".opponent",
    "WAIT": ".stopping",
    "action_features": ".basis",
    "belief_vector": ".stopping",
    "best_response": ".games",
    "delta_safe_tree": ".opponent",
    "expected_reward": ".games",
    "fictitious_play": ".games",
    "kl_bound": ".opponent",
    "kl_divergence": ".opponent",
    "lstdq": ".lspi",
    "minimax_equilibrium": ".games",
    "minimax_strategy": ".games",
    "natural_gradient": ".nac",
    "sample_counts": ".games",
    "solve_delta_safe": ".opponent",
    "two_sample_z_test": ".opponent",
    "two_stage_rps": ".games",
}

__all__ = sorted([*_EXPORTS, "lspi", "nac"])
__getattr__, __dir__ = lazy_exports(__name__, _EXPORTS)
