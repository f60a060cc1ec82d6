"""Windows of observations: the features and labelled training rows of every window baseline.

A window baseline sees, at step ``t`` of a ``[T, Dz]`` sequence, the last ``w`` frames
``[z_{t-w+1}, ..., z_t]`` stacked into one ``w Dz`` vector (:func:`window_features`; the first
steps repeat ``z_0``). Training takes whole sequences, each step labelled with its sequence's
target or class; the helpers here check those inputs and build the rows.
"""

from __future__ import annotations

import numbers
from collections.abc import Sequence
from typing import Any

import numpy as np
import torch

from ..validation import as_tensor

__all__ = ["window_features"]


def window_features(z: torch.Tensor, window: int) -> torch.Tensor:
    """Stack the last ``window`` frames at every step.

    Args:
        z: ``[..., T, Dz]``.
        window: ``w >= 1``.

    Returns:
        ``[..., T, w Dz]``: row ``t`` is ``[z_{t-w+1}, ..., z_t]``, frames before the first
        repeated from ``z_0``.
    """
    if not isinstance(window, int) or window < 1:
        raise ValueError(f"window must be a positive int, got {window!r}")
    first = z[..., :1, :].expand(*z.shape[:-2], window - 1, z.shape[-1])
    padded = torch.cat([first, z], dim=-2)
    frames = [padded[..., i : i + z.shape[-2], :] for i in range(window)]
    return torch.cat(frames, dim=-1)


def positive_int(value: object, name: str, *, low: int = 1) -> int:
    """``value`` as an int ``>= low`` (a Python or NumPy integer, not a bool).

    Raises:
        ValueError: anything else, naming ``name``.
    """
    if isinstance(value, bool | np.bool_) or not isinstance(value, numbers.Integral):
        raise ValueError(f"{name} must be an int >= {low}, got {value!r}")
    if value < low:
        raise ValueError(f"{name} must be an int >= {low}, got {value!r}")
    return int(value)


def check_fitted(model: object, attribute: str, fit_call: str) -> None:
    """Raise ``RuntimeError`` unless ``fit`` has set ``attribute`` on ``model``.

    ``fit_call`` is the call to show, e.g. ``"fit(sequences, labels)"``.
    """
    if not hasattr(model, attribute):
        raise RuntimeError(
            f"this {type(model).__name__} is not fitted yet: call {fit_call} before predicting"
        )


def as_sequences(sequences: Any, name: str = "sequences") -> list[torch.Tensor]:
    if isinstance(sequences, torch.Tensor | np.ndarray):
        sequences = list(as_tensor(sequences, name, ndim=3))
    if not isinstance(sequences, Sequence) or len(sequences) == 0:
        raise ValueError(f"{name} must be a non-empty list of [T, Dz] arrays")
    out = [as_tensor(s, f"{name}[{j}]", ndim=2) for j, s in enumerate(sequences)]
    if any(s.shape[1] != out[0].shape[1] for s in out):
        raise ValueError(f"all {name} must have the same number of columns Dz")
    return out


def labelled_windows(
    sequences: list[torch.Tensor], labels: torch.Tensor, window: int
) -> tuple[torch.Tensor, torch.Tensor]:
    """All windows of all sequences ``[sum T_j, w Dz]`` with their sequence's label."""
    if labels.shape[0] != len(sequences):
        raise ValueError(f"need one label per sequence: {labels.shape[0]} for {len(sequences)}")
    x = torch.cat([window_features(s, window) for s in sequences])
    y = torch.cat([labels[j].expand(s.shape[0]) for j, s in enumerate(sequences)])
    return x, y


def prediction_windows(z: Any, window: int, dz: int) -> torch.Tensor:
    z = as_tensor(z, "z", min_ndim=2)
    if z.shape[-1] != dz:
        raise ValueError(f"z must have Dz = {dz} columns like the training data, got {z.shape}")
    return window_features(z, window)
