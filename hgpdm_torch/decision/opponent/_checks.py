"""Argument checks shared by the delta-safe modules of :mod:`hgpdm_torch.decision.opponent`
(a private module: its names are not re-exported)."""

from __future__ import annotations

import math
import numbers

import numpy as np
import torch


def as_scalar(value: object, name: str, *, integer: bool = False) -> float:
    """``value`` as a Python float (int if ``integer``): Python and NumPy scalars and 0-dim NumPy
    arrays or torch tensors are accepted, booleans are not."""
    kind = "an integer" if integer else "a real number"
    if isinstance(value, torch.Tensor | np.ndarray):
        if value.ndim != 0:
            raise TypeError(f"{name} must be {kind}, got an array of shape {tuple(value.shape)}")
        value = value.item()
    wanted = numbers.Integral if integer else numbers.Real
    if isinstance(value, bool | np.bool_) or not isinstance(value, wanted):
        raise TypeError(f"{name} must be {kind}, got {type(value).__name__}")
    return int(value) if integer else float(value)


def as_integer(value: object, name: str, low: int) -> int:
    """``value`` as an int, at least ``low`` (``TypeError`` / ``ValueError`` naming ``name``)."""
    number = as_scalar(value, name, integer=True)
    if number < low:
        raise ValueError(f"{name} must be an integer >= {low}, got {value!r}")
    return int(number)


def check_tol(tol: object) -> float:
    """A solver tolerance: a positive finite float."""
    value = as_scalar(tol, "tol")
    if not (math.isfinite(value) and value > 0):
        raise ValueError(f"tol must be positive and finite, got {tol}")
    return value


def check_open_probability(value: object, name: str) -> float:
    """A probability strictly between 0 and 1, as a float."""
    p = as_scalar(value, name)
    if not 0.0 < p < 1.0:
        raise ValueError(f"{name} must lie in (0, 1), got {value}")
    return p


def check_delta(delta: float) -> float:
    """The risk level delta of a delta-safe response, in (0, 1)."""
    return check_open_probability(delta, "delta")
