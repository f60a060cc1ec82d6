"""A mixture of several intention models' beliefs over one grid (a linear opinion pool).

Models that make different assumptions err on different streams. Averaging their beliefs,
``p(g | z_{0:t}) = sum_m w_m p_m(g | z_{0:t})`` with fixed weights ``w_m >= 0`` summing to 1, is
Bayesian model averaging with the model probabilities held at the weights instead of updated by
each stream's evidence (which, over many observed dimensions, would soon pick one model per
stream and lose the averaging). Its mean is the weighted mean of the members' means; its spread
adds how much they disagree. On the table-tennis strokes, the equal mixture of a
:class:`~hgpdm_torch.models.LinearIDDM` without and with the rank-1 interaction predicts the
target better at 80 ms than either alone (docs, target prediction).

Shapes: ``B`` streams, ``T`` frames, ``K`` intention values, ``M`` members.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np
import torch

from ...intention_belief import IntentionBelief, IntentionModel

__all__ = ["BeliefMixture", "BeliefMixtureStream"]


class BeliefMixture:
    """The weighted mixture of the beliefs of fitted intention models over a shared grid.

    Args:
        models: ``M >= 1`` fitted models with ``beliefs(obs, grid, log_prior)``,
            ``stream(batch_size, grid, log_prior)`` and ``grid(values)``, as
            :class:`~hgpdm_torch.models.LinearIDDM` has; all score the same intention over the
            same values: their value sets (``grid()``, the codes of a discrete g or the default
            grid over the training range of a continuous one) must agree, to rounding.
        weights: ``[M]`` non-negative finite weights, not all zero (a list, array or tensor;
            normalised to sum 1); default equal.

    Raises:
        TypeError: a member without those methods.
        ValueError: bad weights, or members with different value sets (naming them and their
            values, whatever their order: a member scored on a part of its values only would
            renormalise its belief over that part without a word).
    """

    def __init__(self, models: Sequence[Any], weights: Sequence[float] | None = None) -> None:
        if not isinstance(models, Sequence) or isinstance(models, str) or not models:
            raise TypeError("models must be a non-empty sequence of fitted intention models")
        for m, model in enumerate(models):
            if not isinstance(model, IntentionModel):
                needed = ("beliefs", "stream", "grid")
                missing = [a for a in needed if not callable(getattr(model, a, None))]
                raise TypeError(
                    f"models[{m}] ({type(model).__name__}) has no {', '.join(missing)} method: "
                    "a member must give beliefs over a grid (e.g. a LinearIDDM)"
                )
        if weights is None:
            weights = [1.0] * len(models)
        if isinstance(weights, str | bytes) or (
            isinstance(weights, Sequence) and any(isinstance(w, bool | str) for w in weights)
        ):  # fmt: skip
            raise ValueError(f"weights must be {len(models)} numbers, got {weights!r}")
        if isinstance(weights, torch.Tensor):
            weights = weights.detach().cpu().numpy()
        try:
            w = np.asarray(weights, dtype=np.float64)
        except (TypeError, ValueError, OverflowError):
            raise ValueError(f"weights must be {len(models)} numbers, got {weights!r}") from None
        if w.shape != (len(models),):
            raise ValueError(
                f"weights must be [M = {len(models)}] (one per model), got shape {w.shape}"
            )
        if not (np.isfinite(w).all() and (w >= 0).all() and (w > 0).any()):
            raise ValueError(f"weights must be finite and >= 0, not all zero, got {weights!r}")
        w = w / w.max()  # then the sum cannot overflow
        _check_value_sets(models)
        self.models = list(models)
        self.weights = (w / w.sum()).tolist()

    def grid(self, values: Any = None) -> torch.Tensor:
        """``[K, Dg]`` intention values: the first member's :meth:`grid` (its default grid when
        ``values`` is None)."""
        return self.models[0].grid(values)

    def beliefs(self, obs: Any, grid: Any = None, log_prior: Any = None) -> IntentionBelief:
        """The mixture of the members' beliefs after every frame.

        Args:
            obs: ``[B, T, Dz]`` or ``[T, Dz]`` streams, as each member's ``beliefs`` takes them.
            grid: intention values (default :meth:`grid`), passed to every member.
            log_prior: ``[K]`` log prior over the grid, passed to every member.

        Returns:
            :class:`~hgpdm_torch.inference.IntentionBelief` with ``[B, T, K]`` (or ``[T, K]``)
            probabilities ``sum_m w_m p_m`` and, for a continuous g, its mean and sd.
        """
        values = self.grid(grid)
        return self._mix([m.beliefs(obs, values, log_prior) for m in self.models], values)

    def stream(
        self, batch_size: int = 1, grid: Any = None, log_prior: Any = None
    ) -> BeliefMixtureStream:
        """An online mixture for ``batch_size`` streams: every member's own stream, advanced
        together (the same beliefs as :meth:`beliefs`, frame by frame)."""
        values = self.grid(grid)
        return BeliefMixtureStream(
            self, [m.stream(batch_size, values, log_prior) for m in self.models], values
        )

    def _mix(self, beliefs: list[IntentionBelief], values: torch.Tensor) -> IntentionBelief:
        """``log sum_m w_m p_m`` of the members' beliefs ``[..., K]`` over ``values``."""
        return IntentionBelief.mixture(beliefs, self.weights, values)  # belief m: models[m]'s


class BeliefMixtureStream:
    """Online beliefs of a :class:`BeliefMixture` (:meth:`BeliefMixture.stream`)."""

    def __init__(
        self, mixture: BeliefMixture, streams: list[Any], values: torch.Tensor
    ) -> None:  # fmt: skip
        self.mixture, self.streams, self.values = mixture, streams, values

    def reset(self) -> None:
        """Start every stream of every member again at its prior."""
        for s in self.streams:
            s.reset()

    def repeat(self, index: int, num: int) -> BeliefMixtureStream:
        """``num`` copies of stream ``index`` in every member (the particles of a look-ahead)."""
        return BeliefMixtureStream(
            self.mixture, [s.repeat(index, num) for s in self.streams], self.values
        )

    def sample_next(self, generator: torch.Generator | None = None) -> torch.Tensor:
        """``[B, Dz]``: each stream's next frame from one member drawn by the mixture weights,
        that member's ``sample_next`` (so ``g`` follows the mixed belief)."""
        draws = torch.stack([s.sample_next(generator) for s in self.streams])  # [M, B, Dz]
        weights = torch.tensor(self.mixture.weights, dtype=torch.float64)
        on = weights.device if generator is None else generator.device
        member = torch.multinomial(weights.to(on), draws.shape[1], replacement=True,
                                   generator=generator).to(draws.device)  # fmt: skip
        return draws[member, torch.arange(draws.shape[1], device=draws.device)]

    def update(self, z: Any) -> IntentionBelief:
        """Add the next frame ``z [B, Dz]`` (``[Dz]`` for one stream) to every member; returns
        the mixed belief ``[B, K]`` (``[K]``). ``rejected`` flags a stream whose frame any
        member rejected (members with another rule, e.g. another dtype's range, may have used
        it).

        Raises:
            Exception: whatever a member's ``update`` raises (a frame past its training
                length, a row of the wrong size); every member's streams are then left as
                they were.
        """
        saved = [_snapshot(s) for s in self.streams]
        try:
            beliefs = [s.update(z) for s in self.streams]
            out = self.mixture._mix(beliefs, self.values)
        except Exception:
            for stream, state in zip(self.streams, saved, strict=True):
                stream.__dict__.update(state)
            raise
        flags = [b.rejected for b in beliefs if b.rejected is not None]
        if flags:
            out.rejected = torch.stack(flags).any(0)
        return out


def _check_value_sets(models: Sequence[Any]) -> None:
    """Raise unless every member's value set (its default ``grid()`` ``[K, Dg]``; a member
    without one, e.g. a multi-dimensional continuous g, takes any grid) is the first such
    member's: the same shape and, in float64, the same values up to ``1e-5`` relative (a
    float32 member's grid rounds)."""
    sets = []
    for m, model in enumerate(models):
        try:
            values = model.grid()
        except ValueError:  # no default value set: it scores the grid it is given
            continue
        sets.append((m, values.detach().to("cpu", torch.float64)))
    for m, values in sets[1:]:
        first, ref = sets[0]
        scale = float(ref.abs().max()) if ref.numel() else 1.0
        if values.shape != ref.shape or not torch.allclose(
            values, ref, rtol=1e-5, atol=1e-5 * max(scale, 1.0)
        ):  # fmt: skip
            raise ValueError(
                f"models[{first}] and models[{m}] score different intention values: "
                f"models[{first}] {_describe(ref)}, models[{m}] {_describe(values)}; the "
                "members of a mixture must score the same values (fit them on the same codes, "
                "or on the same range of a continuous g)"
            )


def _describe(values: torch.Tensor) -> str:
    """A value set ``[K, Dg]`` in words: its values when few, else its size and range."""
    if len(values) <= 8:
        return f"{len(values)} values {values.squeeze(-1).tolist()}"
    lo, hi = values.min(0).values.tolist(), values.max(0).values.tolist()
    if values.shape[1] == 1:
        return f"{len(values)} values over [{lo[0]:.6g}, {hi[0]:.6g}]"
    return f"{len(values)} values over {lo} .. {hi}"


def _snapshot(stream: Any) -> dict[str, Any]:
    """A member stream's attributes, tensors cloned (an update may change them in place)."""
    return {k: v.clone() if isinstance(v, torch.Tensor) else v for k, v in vars(stream).items()}
