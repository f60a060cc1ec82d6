"""Screening of observation rows before a filter uses them: :class:`ObservationCheck` classifies
each row as usable, missing (all NaN) or bad (partly NaN, +-inf or implausible for the training
data's scale), and :func:`screen_observations` applies it to one update of B streams, turning
bad rows into missing ones. Every filter of the toolkit (GP-ADF, the online intention filter, the
linear IDDM's streams) screens its frames here, so all treat a frame the same way.

Shapes: ``B`` streams, ``Dz`` observed dims.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import torch

from .gp import GPPosterior
from .validation import as_observations, bad_observation, check_outlier_sd

__all__ = ["DEFAULT_OUTLIER_SD", "ObservationCheck", "check_observations", "screen_observations"]


#: Default plausibility threshold of :class:`ObservationCheck`, in training standard deviations.
DEFAULT_OUTLIER_SD = 100.0


@dataclass(frozen=True)
class ObservationCheck:
    r"""Classifies observation rows as usable, missing or bad, from the training data's scale.

    A row ``z [Dz]`` (one stream at one step) is

    - **missing** when every entry is NaN: a prediction-only step, as everywhere in the toolkit;
    - **bad** when it is not missing and some channel ``c`` is NaN (a partly missing row), +-inf,
      or implausible: ``|z_c - center_c| > outlier_sd * spread_c``;
    - **usable** otherwise.

    ``center_c`` is the mean of the measurement GP's training observations in channel ``c`` and
    ``spread_c = sqrt(Var_c + noise * scale_c^2)`` their (population) standard deviation with the
    GP's observation noise in that channel added, so that a channel that is constant in the
    training data does not reject every other value. Both are in the channel's own units, so the
    threshold is relative: rescaling or shifting a channel in training and test data alike
    changes nothing. The default ``outlier_sd = 100`` accepts values far beyond anything the
    model explains (``-5000`` nats under a Gaussian of the training spread) and refuses sensor
    glitches and unit errors long before they can overflow the moment matching (squares of
    ``1e154``).

    Attributes:
        center: ``[Dz]`` training mean per channel (float64).
        spread: ``[Dz]`` ``spread_c`` above (float64).
        outlier_sd: the threshold in units of ``spread``; ``None`` refuses non-finite entries
            and partly missing rows only.
        limit: ``[Dz]`` ``outlier_sd * spread`` (inf for ``None``).
    """

    center: torch.Tensor
    spread: torch.Tensor
    outlier_sd: float | None = DEFAULT_OUTLIER_SD
    limit: torch.Tensor = field(init=False, repr=False)

    def __post_init__(self) -> None:
        sd = math.inf if self.outlier_sd is None else self.outlier_sd
        object.__setattr__(self, "limit", sd * self.spread)

    @classmethod
    def from_measurement(
        cls, measurement: GPPosterior, outlier_sd: float | None = DEFAULT_OUTLIER_SD
    ) -> ObservationCheck:
        """Limits from a measurement GP's training targets (plus its ``offset``), noise, scale.

        Args:
            measurement: GP from ``x`` to ``z`` (e.g. ``model.measurement_posterior()``).
            outlier_sd: positive threshold, or ``None`` to check finiteness only.
        """
        if not isinstance(measurement, GPPosterior):
            raise TypeError(f"measurement must be a GPPosterior, got {type(measurement).__name__}")
        outlier_sd = check_outlier_sd(outlier_sd)
        y = measurement.train_targets.detach().double()
        scale = measurement.scale.detach().double().expand(y.shape[1])
        noise = measurement.noise.detach().double() * scale.pow(2)
        center = y.mean(0) + measurement.offset.detach().double()
        return cls(center, (y.var(0, correction=0) + noise).sqrt(), outlier_sd)

    def usable(self, z: torch.Tensor) -> torch.Tensor:
        """``[...]`` mask of the usable rows of ``z [..., Dz]``: neither missing nor bad."""
        if self.outlier_sd is None:
            return torch.isfinite(z).all(-1)
        center, limit = self.center, self.limit
        if center.dtype != z.dtype or center.device != z.device:
            center, limit = (x.to(dtype=z.dtype, device=z.device) for x in (center, limit))
        return ((z - center).abs() <= limit).all(-1)  # False for NaN and +-inf

    def classify(self, z: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """``missing`` and ``bad`` masks ``[...]`` of the rows of ``z [..., Dz]`` (vectorised)."""
        missing = torch.isnan(z).all(-1)
        return missing, ~(missing | self.usable(z))

    def reason(self, row: torch.Tensor) -> str:
        """Why the bad row ``row [Dz]`` is bad (:meth:`classify`), naming its first offending
        channel: NaN first, then inf, then implausible."""
        row = row.detach().double().cpu()
        nan = torch.isnan(row)
        if bool(nan.any()):
            c = int(torch.nonzero(nan)[0])
            return (
                f"channel {c} is NaN but the row is not all NaN (a missing observation is a row "
                "of NaN; a partly missing row is not supported)"
            )
        inf = torch.isinf(row)
        if bool(inf.any()):
            c = int(torch.nonzero(inf)[0])
            return f"channel {c} is {float(row[c])} (a missing observation is a row of NaN)"
        dev = (row - self.center.cpu()).abs() / self.spread.cpu()
        c = int(torch.nonzero(~(dev <= float(self.outlier_sd or math.inf)))[0])
        return (
            f"channel {c} = {float(row[c]):.6g} is implausible: {float(dev[c]):.3g} training "
            f"standard deviations from the training mean {float(self.center[c]):.6g} "
            f"(outlier_sd = {self.outlier_sd:g}; None disables this check)"
        )

    def first_bad(self, z: torch.Tensor) -> tuple[tuple[int, ...], str] | None:
        """The index of the first bad row of ``z [..., Dz]`` and its :meth:`reason`, or ``None``."""
        _, bad = self.classify(z)
        if not bool(bad.any()):
            return None
        index = tuple(int(i) for i in torch.nonzero(bad)[0])
        return index, self.reason(z[index])


def check_observations(z: Any, dz: int, min_ndim: int) -> torch.Tensor:
    """``z [..., Dz]`` as a floating tensor in its own precision (bad rows are kept: the caller
    classifies them with an :class:`~hgpdm_torch.observations.ObservationCheck`)."""
    z = as_observations(z, min_ndim=min_ndim)
    if z.shape[-1] != dz:
        raise ValueError(f"z must have Dz = {dz} columns (the model's), got {z.shape[-1]}")
    return z


def screen_observations(
    z: Any,
    check: ObservationCheck,
    batch_size: int,
    obs_dim: int,
    *,
    device: torch.device,
    strict: bool,
    where: Callable[[int], str],
) -> tuple[torch.Tensor, torch.Tensor, bool]:
    """One update's observations of B streams, checked; bad rows become missing ones.

    Args:
        z: ``[B, Dz]`` rows (``[Dz]`` for one stream, ``B = 1``); a row of NaN is missing.
        check: classifies the rows: a row that is not missing but has a NaN, an inf or a value
            beyond the check's threshold is bad
            (:meth:`~hgpdm_torch.observations.ObservationCheck.classify`).
        batch_size: the expected number of streams B.
        obs_dim: the expected observation size Dz.
        device: where the streams' state lives (the rows, flags and counts go there).
        strict: raise for a bad row instead of rejecting it.
        where: ``b -> str``, how an error names row ``b`` (e.g. ``"z[3] (stream 3, step 7)"``).

    Returns:
        ``z [B, Dz]`` on ``device`` in its own floating dtype, with the bad rows set to NaN
        (missing); ``rejected [B]`` bool, the bad rows; whether the input was one ``[Dz]`` row.

    Raises:
        ValueError: a wrong shape; with ``strict``, the first bad row, naming it (``where``) and
            its first bad channel. Nothing is changed: the caller's state is not touched here.
    """
    z = check_observations(z, obs_dim, min_ndim=1)
    single = z.dim() == 1
    if single:
        z = z[None]
    if z.shape != (batch_size, obs_dim):
        raise ValueError(
            f"z must have shape [B, Dz] = [{batch_size}, {obs_dim}], got {tuple(z.shape)}"
        )
    z = z.to(device)  # the checks, flags and counts live on the streams' device
    _, rejected = check.classify(z)
    if bool(rejected.any()):
        b = int(torch.nonzero(rejected)[0])
        if strict:
            raise bad_observation(where(b), check.reason(z[b]))
        z = z.masked_fill(rejected[:, None], math.nan)
    return z, rejected, single
