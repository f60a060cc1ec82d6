"""Delta-safe opponent modelling and strategy learning in repeated games (thesis Ch. 5).

The opponent's stationary strategy is modelled by the KL ball around its empirical distribution,
``Omega(delta) = {pi_j : KL(pi~_j || pi_j) <= eps(delta)}``, which holds the true strategy with
probability at least ``1 - delta`` (Sec. 5.2.1). Player i answers with the generalised best
response of Problem (38), ``max_pi_i min_{pi_j in Omega} pi_i^T R pi_j``; its value is a lower
bound on the true expected reward with the same probability.

Two solvers of Problem (38) share one exact inner step, the worst opponent in the ball, found
through its 1-D concave dual (derived in :mod:`~hgpdm_torch.decision.opponent.kl_ball`):

- :class:`DeltaSafeResponder`: projected sub-gradient ascent with warm start, as in the thesis,
  for online play;
- :func:`solve_delta_safe`: Kelley's cutting planes with an LP master, which certifies the
  optimal value to a given gap; the reference the tests hold the online solver to.

On top: the two-sample z-tests and the adaptive learner of Algorithm 5.1, and delta-safe
backward induction on finite-stage stochastic games (Sec. 5.3).

The code is split by concept; this package re-exports the public names of its modules, so that
``from hgpdm_torch.decision.opponent import DeltaSafeResponder`` works as before:

* :mod:`~hgpdm_torch.decision.opponent.kl_ball`: the KL ball, its radius and its exact worst case
  (with the derivation of the inner problem's dual);
* :mod:`~hgpdm_torch.decision.opponent.cutting_planes`: the certified reference solver and the
  solution type :class:`SafeResponse`;
* :mod:`~hgpdm_torch.decision.opponent.responder`: the online sub-gradient solver;
* :mod:`~hgpdm_torch.decision.opponent.change_detection`: the two-sample z-tests;
* :mod:`~hgpdm_torch.decision.opponent.adaptive`: the adaptive learner of Algorithm 5.1;
* :mod:`~hgpdm_torch.decision.opponent.tree`: delta-safe backward induction on game trees.

Imports flow one way: ``kl_ball`` <- ``cutting_planes`` <- ``responder`` <- ``adaptive``,
``tree``; ``change_detection`` <- ``adaptive``.
"""

from __future__ import annotations

from hgpdm_torch.decision.opponent.adaptive import AdaptiveLearner
from hgpdm_torch.decision.opponent.change_detection import two_sample_z_test
from hgpdm_torch.decision.opponent.cutting_planes import SafeResponse, solve_delta_safe
from hgpdm_torch.decision.opponent.kl_ball import KLBall, kl_bound, kl_divergence
from hgpdm_torch.decision.opponent.responder import DeltaSafeResponder
from hgpdm_torch.decision.opponent.tree import TreeResponse, delta_safe_tree

__all__ = [
    "AdaptiveLearner",
    "DeltaSafeResponder",
    "KLBall",
    "SafeResponse",
    "TreeResponse",
    "delta_safe_tree",
    "kl_bound",
    "kl_divergence",
    "solve_delta_safe",
    "two_sample_z_test",
]
