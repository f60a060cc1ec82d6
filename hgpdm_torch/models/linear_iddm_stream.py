"""Online beliefs of a fitted :class:`~hgpdm_torch.models.LinearIDDM` for B streams that advance
one frame per update (:meth:`~hgpdm_torch.models.LinearIDDM.stream`): the batch beliefs of
:meth:`~hgpdm_torch.models.LinearIDDM.beliefs`, frame by frame, with the online filter's treatment
of missing and bad frames.
"""

from __future__ import annotations

import numbers
from typing import TYPE_CHECKING, Any

import torch

from ..intention_belief import IntentionBelief, belief_step, flagged_belief
from ..observations import screen_observations

if TYPE_CHECKING:  # linear_iddm imports this module
    from .linear_iddm import LinearIDDM

__all__ = ["LinearIDDMStream"]


class LinearIDDMStream:
    """Online beliefs of a fitted :class:`LinearIDDM` for B streams (:meth:`LinearIDDM.stream`).

    Every :meth:`update` brings the next frame of all B streams, which therefore share their
    frame index (the phase). The frames are taken as by
    :class:`~hgpdm_torch.inference.OnlineIntentionFilter`, through the same code
    (:func:`~hgpdm_torch.observations.screen_observations`): a row of NaN is a
    missing frame; a bad row (an inf, a NaN in some dimensions only, or more than the model's
    ``outlier_sd`` training standard deviations from the training mean in a dimension) is
    *rejected*: it counts as missing, ``belief.rejected`` flags it and ``rejected_count``
    counts it (``strict``: a ``ValueError`` naming the stream, frame and dimension, with no
    state changed). A missing or rejected frame is missing for its stream alone: the
    transitions into and out of it carry no evidence. A frame whose transition's density
    overflows the arithmetic (possible only with ``outlier_sd=None``) is rejected too. The
    belief follows Algorithm 3.2 (:func:`~hgpdm_torch.intention_belief.belief_step`):
    with ``forgetting > 0`` every stream's log belief decays at every frame after the first,
    its row missing or not.

    Stream isolation: every stream's transition is computed at every frame (an unusable one at
    the training mean, and discarded), so nothing one stream receives changes another's belief,
    not even its rounding.

    Attributes:
        log_weights: ``[B, K]`` log belief (normalised after the first frame).
        previous: ``[B, Dz]`` each stream's last usable frame; ``has_previous [B]``: whether
            it was the frame just before.
        frames: frames given so far (the next frame's index).
        rejected_count: ``[B]`` int64, rejected frames of each stream since :meth:`reset`.
        check: the :class:`~hgpdm_torch.observations.ObservationCheck` in use.
    """

    def __init__(
        self, model: LinearIDDM, batch_size: int, grid: Any, log_prior: Any, *,
        strict: bool = False,
    ) -> None:  # fmt: skip
        model._check_fitted()
        if isinstance(batch_size, bool) or not isinstance(batch_size, numbers.Integral) or (
            batch_size < 1
        ):  # fmt: skip
            raise ValueError(f"batch_size must be a positive int, got {batch_size!r}")
        if not isinstance(strict, bool):
            raise TypeError(f"strict must be a bool, got {strict!r}")
        self.model, self.batch_size, self.strict = model, int(batch_size), strict
        self.values = model.grid(grid)
        self._feats = model._features(self.values)
        self._prior = model._log_prior(log_prior, len(self.values))
        self.check = model._observation_check()
        self.reset()

    def reset(self) -> None:
        """Start every stream again at frame 0 with the prior belief."""
        b, d = self.batch_size, self.model.obs_dim
        device = self.model.coef.device
        self.frames = 0
        self.previous = torch.zeros(b, d, dtype=self.model.dtype, device=device)
        self.has_previous = torch.zeros(b, dtype=torch.bool, device=device)
        self.log_weights = self._prior.expand(b, -1).clone()
        self.rejected_count = torch.zeros(b, dtype=torch.long, device=device)

    def _where(self, b: int) -> str:
        return f"z[{b}] (stream {b}, frame {self.frames})"

    def repeat(self, index: int, num: int) -> LinearIDDMStream:
        """A new stream object holding ``num`` copies of stream ``index`` (its belief, last frame
        and frame count): the particles of a look-ahead (Monte-Carlo planning) start there."""
        _check_index(index, self.batch_size)
        if isinstance(num, bool) or not isinstance(num, numbers.Integral) or num < 1:
            raise ValueError(f"num must be a positive int, got {num!r}")
        out = object.__new__(LinearIDDMStream)
        out.__dict__.update(self.__dict__)
        out.batch_size = int(num)
        for name in ("previous", "has_previous", "log_weights", "rejected_count"):
            value = getattr(self, name)[index]
            setattr(out, name, value.expand(num, *value.shape).clone())
        return out

    def sample_next(self, generator: torch.Generator | None = None) -> torch.Tensor:
        """``[B, Dz]``: each stream's next frame drawn from the model given its belief, with
        ``g ~ p(g | z_{0:t})`` over the grid and ``z_{t+1} ~ p(z_{t+1} | z_t, g, data)``
        (:meth:`LinearIDDM.sample_next`). Every stream needs its last frame (``has_previous``)
        and a transition after it."""
        if self.frames == 0 or not bool(self.has_previous.all()):
            raise ValueError(
                "sample_next needs every stream's frame just before (update them with a usable "
                "frame first)"
            )
        prob = self.log_weights.softmax(-1)
        draw_on = prob.device if generator is None else generator.device
        k = torch.multinomial(prob.to(draw_on), 1, generator=generator)[:, 0].to(prob.device)
        return self.model.sample_next(self.previous, self.values[k], self.frames - 1, generator)

    def update(self, z: Any) -> IntentionBelief:
        """Add the next frame ``z [B, Dz]`` (``[Dz]`` for one stream) of every stream.

        Returns:
            The belief ``[B, K]`` after it (``[K]``, with a scalar ``rejected``, for a ``[Dz]``
            row, as :meth:`~hgpdm_torch.inference.OnlineIntentionFilter.update`), with
            ``rejected [B]``: the streams whose frame was bad and taken as missing.

        Raises:
            ValueError: a row of the wrong size, (``phase=True``) a frame past the longest
                training sequence, or (``strict``) a bad frame; the streams are then left as
                they were.
        """

        model = self.model
        if model.phase and self.frames > model.num_phases:
            raise ValueError(
                f"frame {self.frames} has no transition: the training sequences had at most "
                f"{model.num_phases + 1} frames (phase=True); reset() the streams"
            )
        z, rejected, single = screen_observations(
            z, self.check, self.batch_size, model.obs_dim, device=model.coef.device,
            strict=self.strict, where=self._where,
        )  # fmt: skip
        z = z.to(model.dtype)
        good = torch.isfinite(z).all(-1)  # neither missing nor rejected
        log_weights = self.log_weights
        if self.frames > 0:  # the transition from the previous frame, for every stream
            use = good & self.has_previous
            fill = model.obs_mean.expand_as(z)
            a = torch.where(use[:, None], self.previous, fill)
            b = torch.where(use[:, None], z, fill)
            evidence = model._log_predictive(a, b, self._feats, self.frames - 1)
            overflow = use & ~torch.isfinite(evidence).all(-1)
            if bool(overflow.any()):  # outlier_sd=None let a frame through that overflows
                bad = int(torch.nonzero(overflow)[0])
                if self.strict:
                    raise ValueError(
                        f"{self._where(bad)} cannot be used: the density of its transition is "
                        f"not finite (the frame overflows {model.dtype} arithmetic); rescale "
                        "the observations or keep outlier_sd finite"
                    )
                rejected, good, use = rejected | overflow, good & ~overflow, use & ~overflow
            # every stream forgets at every frame, its row missing or not
            log_weights = belief_step(
                log_weights, evidence, use, model.forgetting, model.temperature
            )
        self.log_weights = log_weights
        self.previous = torch.where(good[:, None], z, self.previous)
        self.has_previous = good
        self.rejected_count += rejected
        self.frames += 1
        return flagged_belief(
            self.log_weights, self.values, model.intention == "continuous", single, rejected
        )


def _check_index(index: int, size: int) -> None:
    if isinstance(index, bool) or not isinstance(index, numbers.Integral) or not (
        0 <= index < size
    ):  # fmt: skip
        raise ValueError(f"index must be an int in [0, {size}), got {index!r}")
