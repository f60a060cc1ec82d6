"""The belief over K intention values and its online recursion: :class:`IntentionBelief` (what
batch and online inference, GP or linear, report) and :func:`belief_step` (Algorithm 3.2, lines
10-11: the forgetful, tempered belief update every online belief of the toolkit uses).

Shapes: ``B`` streams, ``K`` intention values, ``Dg`` intention dims.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from .calibration import credible_set
from .gaussian import mixture_moments

__all__ = ["IntentionBelief", "belief_step", "flagged_belief"]


@dataclass
class IntentionBelief:
    """A posterior over K intention values.

    Attributes:
        prob: ``[..., K]`` posterior probabilities.
        log_prob: ``[..., K]`` their logs (normalised).
        values: ``[K, Dg]`` the intention values (codes for a discrete g).
        mean: ``[..., Dg]`` posterior mean of a continuous g (``None`` for a discrete g).
        std: ``[..., Dg]`` posterior standard deviation of a continuous g (or ``None``).
        rejected: (online updates only: :meth:`OnlineIntentionFilter.update`,
            :meth:`LinearIDDMStream.update`, a mixture's stream; else ``None``) ``[B]`` bool
            (``[]`` for one ``[Dz]`` observation): the stream's observation of this update was
            bad (:class:`~hgpdm_torch.observations.ObservationCheck`) and was treated as
            missing. :func:`~hgpdm_torch.decision.sources.track_beliefs` gathers them per
            decision time (``BeliefTrack.rejected``).
        reset_streams: (:meth:`OnlineIntentionFilter.update` only) ``[B]`` bool: the stream
            failed numerically in this update (or held a non-finite state) and was restarted
            at the prior.
    """

    prob: torch.Tensor
    log_prob: torch.Tensor
    values: torch.Tensor
    mean: torch.Tensor | None = None
    std: torch.Tensor | None = None
    rejected: torch.Tensor | None = None
    reset_streams: torch.Tensor | None = None

    @classmethod
    def from_log(
        cls, log_weights: torch.Tensor, values: torch.Tensor, continuous: bool
    ) -> IntentionBelief:
        """Normalise unnormalised log weights ``[..., K]`` over ``values [K, Dg]``."""
        log_prob = log_weights - torch.logsumexp(log_weights, -1, keepdim=True)
        prob = log_prob.exp()
        if not continuous:
            return cls(prob, log_prob, values)
        # centred second moment: E[g^2] - E[g]^2 would cancel for a grid far from 0
        mean, cov = mixture_moments(prob, values)
        return cls(prob, log_prob, values, mean, cov.diagonal(dim1=-2, dim2=-1).sqrt())

    def credible_set(self, level: float = 0.9) -> torch.Tensor:
        """``[..., K]`` mask of the smallest set of values holding at least ``level`` mass."""
        return credible_set(self.prob, level)


def belief_step(
    log_belief: torch.Tensor,
    evidence: torch.Tensor,
    observed: torch.Tensor,
    forgetting: float,
    temperature: float,
) -> torch.Tensor:
    """Algorithm 3.2, lines 10-11: ``B_t = (1 - eps) B_{t-1} + E_t / T`` where the stream's step
    was observed (``B_t = (1 - eps) B_{t-1}`` where not), normalised.

    Args:
        log_belief: ``[S, K]`` log belief ``B_{t-1}`` (normalised or not; ``-inf`` excludes a
            value).
        evidence: ``[S, K]`` evidence ``E_t(g)`` of this step; read only where ``observed``
            (elsewhere it may be anything, NaN included).
        observed: ``[S]`` bool, the streams whose step carries evidence.
        forgetting: ``eps`` in ``[0, 1)``.
        temperature: ``T > 0``.

    Returns:
        ``[S, K]`` normalised log belief ``B_t``.
    """
    new = (1.0 - forgetting) * log_belief
    evidence = evidence / temperature
    new = new + torch.where(observed[:, None], evidence, torch.zeros_like(evidence))
    return new - torch.logsumexp(new, -1, keepdim=True)


def flagged_belief(
    log_belief: torch.Tensor,
    values: torch.Tensor,
    continuous: bool,
    single: bool,
    rejected: torch.Tensor,
    reset: torch.Tensor | None = None,
) -> IntentionBelief:
    """The belief an online ``update`` returns: over ``log_belief [B, K]`` and ``values
    [K, Dg]``, with the flags ``rejected`` (and ``reset_streams``) ``[B]``; for one ``[Dz]``
    row (``single``) ``[K]`` with ``[]`` flags."""
    if single:
        log_belief, rejected = log_belief[0], rejected[0]
        reset = None if reset is None else reset[0]
    out = IntentionBelief.from_log(log_belief, values, continuous)
    out.rejected, out.reset_streams = rejected, reset
    return out
