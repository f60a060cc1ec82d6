"""The belief over K intention values, its online recursion and the interfaces that give it.

- :class:`IntentionBelief`: what batch and online inference report, GP or linear, one stream or
  a mixture: values, probabilities, mean and sd of a continuous g, entropy, credible sets, and
  the mixture of several beliefs (:meth:`IntentionBelief.mixture`).
- :func:`belief_step`: Algorithm 3.2, lines 10-11, the forgetful, tempered update every online
  belief of the toolkit uses.
- :class:`IntentionStream` and :class:`IntentionModel`: the one streaming protocol. A stream
  (``update(z) -> IntentionBelief``, ``reset()``) is what
  :class:`~hgpdm_torch.inference.intention.OnlineIntentionFilter` is for a GP model,
  :class:`~hgpdm_torch.models.LinearIDDM`'s ``stream()`` for the linear model and
  :class:`~hgpdm_torch.inference.BeliefMixture`'s for a mixture; a model (``grid``,
  ``beliefs``, ``stream``) is a fitted ``LinearIDDM``, a GP model through
  :class:`~hgpdm_torch.inference.intention.FilterBeliefs`, or a ``BeliefMixture`` of any of
  them. Code written against the protocol runs on every model.

Shapes: ``B`` streams, ``K`` intention values, ``Dg`` intention dims.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, Protocol, runtime_checkable

import torch

from .calibration import credible_set
from .gaussian import mixture_moments

__all__ = [
    "IntentionBelief",
    "IntentionModel",
    "IntentionStream",
    "belief_step",
    "flagged_belief",
]


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
        total = torch.logsumexp(log_weights, -1, keepdim=True)
        prob = (log_weights - total).exp()
        if not continuous:
            return cls(prob, log_weights - total, values)
        # centred second moment: E[g^2] - E[g]^2 would cancel for a grid far from 0; the
        # moments before log_prob (the same difference again), which keeps a batched online
        # update's peak memory one [B, K] tensor lower
        mean, cov = mixture_moments(prob, values)
        std = cov.diagonal(dim1=-2, dim2=-1).sqrt()
        return cls(prob, log_weights - total, values, mean, std)

    def credible_set(self, level: float = 0.9) -> torch.Tensor:
        """``[..., K]`` mask of the smallest set of values holding at least ``level`` mass."""
        return credible_set(self.prob, level)

    def entropy(self) -> torch.Tensor:
        """``[...]`` entropy ``-sum_k p_k log p_k`` in nats (0 for a certain belief, ``log K``
        for a uniform one); a value of zero probability adds nothing."""
        return -torch.where(self.prob > 0, self.prob * self.log_prob, 0.0).sum(-1)

    @classmethod
    def mixture(
        cls,
        beliefs: Sequence[IntentionBelief],
        weights: Sequence[float] | torch.Tensor,
        values: torch.Tensor | None = None,
    ) -> IntentionBelief:
        """The linear opinion pool ``sum_m w_m p_m`` of beliefs over the same values.

        Args:
            beliefs: M beliefs with equal ``[..., K]`` shapes over the same values, all for a
                discrete or all for a continuous g, on one device.
            weights: ``[M]`` non-negative weights summing to one.
            values: ``[K, Dg]`` the values the mixture reports (default the first belief's).

        Returns:
            The mixed belief (``log sum_m w_m p_m``, its mean and sd for a continuous g).

        Raises:
            ValueError: beliefs of different shapes, kinds of g or devices (naming them).
        """
        first = beliefs[0]
        for m, b in enumerate(beliefs):
            if b.log_prob.shape != first.log_prob.shape or (b.mean is None) != (
                first.mean is None
            ):  # fmt: skip
                raise ValueError(
                    f"belief {m} ({tuple(b.log_prob.shape)}, "
                    f"{'continuous' if b.mean is not None else 'discrete'} g) does not match "
                    f"belief 0 ({tuple(first.log_prob.shape)}, "
                    f"{'continuous' if first.mean is not None else 'discrete'} g): a mixture "
                    "needs beliefs about the same intention on the same grid"
                )
        devices = {b.log_prob.device for b in beliefs}
        if len(devices) > 1:
            raise ValueError(
                f"the beliefs lie on different devices {sorted(map(str, devices))}: compute "
                "them on one device"
            )
        log_w = torch.as_tensor(weights, dtype=first.log_prob.dtype,
                                device=first.log_prob.device).log()  # fmt: skip
        stacked = torch.stack([b.log_prob for b in beliefs], -1)  # [..., K, M]
        mixed = torch.logsumexp(stacked + log_w, -1)
        values = first.values if values is None else values
        return cls.from_log(mixed, values, first.mean is not None)


@runtime_checkable
class IntentionStream(Protocol):
    """Online beliefs of B streams, one frame of each per :meth:`update` (module docstring)."""

    def update(self, z: Any) -> IntentionBelief:
        """Add the next frame ``z [B, Dz]`` (``[Dz]``: one stream); the belief ``[B, K]``."""
        ...

    def reset(self) -> None:
        """Start every stream again at its prior."""
        ...


@runtime_checkable
class IntentionModel(Protocol):
    """A fitted model's beliefs over a grid of intention values (module docstring)."""

    def grid(self, values: Any = None) -> torch.Tensor:
        """``[K, Dg]`` intention values (the model's default grid for ``None``)."""
        ...

    def beliefs(self, obs: Any, grid: Any = None, log_prior: Any = None) -> IntentionBelief:
        """The belief after every frame of ``obs [B, T, Dz]`` (or ``[T, Dz]``)."""
        ...

    def stream(
        self, batch_size: int = 1, grid: Any = None, log_prior: Any = None
    ) -> IntentionStream:
        """Online beliefs for ``batch_size`` streams."""
        ...


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
