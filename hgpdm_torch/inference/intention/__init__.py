r"""Intention inference: batch (Algorithm 3.1) and online (Algorithm 3.2).

Both algorithms score every value of a discrete or discretised intention ``g`` (a grid of K
values) with a variational bound built from Gaussian (moment-matched) smoothing distributions
``q`` of the latent states (thesis Sec. 3.3-3.4):

- **batch** (:func:`infer_intention`, Algorithm 3.1): for each ``g`` the GP-RTSS smoother gives
  ``q_g(x_{1:T})`` and the bound of Eq. 22 is evaluated in full,
  ``B(g) = log p(g) + E_q[log p(x_1)] + sum_t E_q[log p(z_t | x_t)] + sum_t Q_t(g) + H(q_g)``.
- **online** (:class:`OnlineIntentionFilter`, Algorithm 3.2): one Gaussian ``q`` over the
  latent state shared by all ``g`` and the recursion ``B_t(g) = E_t(g) + (1 - eps) B_{t-1}(g)``
  with the forgetting factor ``eps``; the evidence is the GP-ADF predictive likelihood
  (default) or the thesis's ``Q_{t-1}(g)``. It runs on every model the toolkit fits: the IDDM
  through the fast :class:`SharedTransition`, any other kernel (H-GPDM, user kernels) through
  :class:`GenericTransition`, a plain GPDM as one value (GP-ADF).

``Q_t(g) = E_q[log p(x_{t+1} | x_t, g)]`` (Sec. 3.3.2 and
docs/design/math.md#the-transition-term-in-kl-form) is evaluated by statistical linearisation
(:func:`expected_log_conditional`).

Observations: a row of NaN is a missing observation everywhere. Other rows that the filter
cannot use (+-inf, partly NaN, or more than ``outlier_sd`` = 100 training standard deviations
from the training mean in a channel; :class:`~hgpdm_torch.observations.ObservationCheck`)
make the batch algorithm raise a ``ValueError`` naming the window, step and channel; the online
filter rejects them for their stream only and restarts a stream whose update fails numerically,
without touching the others.

One module per concept; this package re-exports their public names, so that
``from hgpdm_torch.inference.intention import OnlineIntentionFilter`` works as before:

- :mod:`~hgpdm_torch.inference.intention.grid`: the intention grid (the belief over it,
  :class:`IntentionBelief`, lives in :mod:`hgpdm_torch.intention_belief`);
- :mod:`~hgpdm_torch.inference.intention.state_prior`: the first state's prior (marginal or per
  class);
- :mod:`~hgpdm_torch.inference.intention.linearisation`: ``E_q[log q~(y | x)]``;
- :mod:`~hgpdm_torch.inference.intention.transition`: the transition moments for K values at
  one input Gaussian: the IDDM's fast path (:meth:`GPPosterior.shared_moments
  <hgpdm_torch.gp.GPPosterior.shared_moments>`) or the generic one for any model, on the exact
  GP or its sparse DTC approximation (:meth:`GPPosterior.sparse
  <hgpdm_torch.gp.GPPosterior.sparse>`, Sec. 3.3.3), and the precision check of a lower dtype;
- :mod:`~hgpdm_torch.inference.intention.measurement`: the GP-ADF measurement update
  (closed form for a linear kernel);
- :mod:`~hgpdm_torch.inference.intention.streams`: B streams isolated from each other;
- :mod:`~hgpdm_torch.inference.intention.options`: the filter's choices in groups
  (:class:`BeliefUpdate`, :class:`Evidence`, :class:`StatePrior`, :class:`TransitionPath`,
  :class:`ObservationPolicy`);
- :mod:`~hgpdm_torch.inference.intention.online`: :class:`OnlineIntentionFilter`;
- :mod:`~hgpdm_torch.inference.intention.batch`: :func:`infer_intention` and the bound's terms;
- :mod:`~hgpdm_torch.inference.intention.mixture`: :class:`BeliefMixture`, the weighted mixture
  of several models' beliefs (e.g. :class:`~hgpdm_torch.models.LinearIDDM` variants);
- :mod:`~hgpdm_torch.inference.intention.member`: :class:`FilterBeliefs`, a GP model's online
  beliefs as a member of such a mixture.

Imports flow one way: ``grid``, ``state_prior``, ``linearisation``, ``measurement``,
``transition`` (on :mod:`hgpdm_torch.gp` and :mod:`hgpdm_torch.gp_shared`), ``options`` (on
``state_prior`` and ``transition``), ``streams`` <- ``online`` <- ``member``; ``batch`` uses the
first three; ``mixture`` none of them (the belief type is :mod:`hgpdm_torch.intention_belief`'s).

Shapes: ``B`` streams, ``K`` intention values, ``T`` steps, ``Dx`` latent, ``Dz`` observed,
``Dg`` intention dims, ``N`` transition training points.
"""

from ...gp_shared import SharedTransition
from ...intention_belief import IntentionBelief
from . import options
from .batch import batch_bound, batch_bound_terms, infer_intention
from .grid import intention_grid
from .linearisation import expected_log_conditional
from .measurement import LinearMeasurement
from .member import FilterBeliefs
from .mixture import BeliefMixture, BeliefMixtureStream
from .online import OnlineIntentionFilter
from .options import *  # noqa: F403 (the option groups: options.__all__, listed once)
from .state_prior import STATE_PRIORS, class_state_prior
from .transition import (
    EVIDENCE_LIMIT,
    PRECISION_LIMIT,
    TRANSITIONS,
    GenericTransition,
    transition_moments,
)

__all__ = [
    *options.__all__,
    "BeliefMixture",
    "BeliefMixtureStream",
    "GenericTransition",
    "IntentionBelief",
    "LinearMeasurement",
    "OnlineIntentionFilter",
    "EVIDENCE_LIMIT",
    "FilterBeliefs",
    "PRECISION_LIMIT",
    "SharedTransition",
    "STATE_PRIORS",
    "TRANSITIONS",
    "batch_bound",
    "batch_bound_terms",
    "class_state_prior",
    "expected_log_conditional",
    "infer_intention",
    "intention_grid",
    "transition_moments",
]
