"""BasicMotions (``aeon``, an optional extra): accelerometer and gyroscope (Dz = 6) of a smartwatch
while a person stands, walks, runs or plays badminton; 4 actions, 40 training and 40 test
recordings of 100 frames at 10 Hz, with the data set's own train/test split."""

from __future__ import annotations

import numbers

import torch

__all__ = ["load_basic_motions"]


def load_basic_motions(
    subsample: int = 3,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor, list[str]]:
    """BasicMotions from ``aeon`` (offline): ``(z_train [J, T, 6], y_train [J], z_test, y_test,
    class names)``, every ``subsample``-th frame.

    Raises:
        ValueError: ``subsample`` not an int >= 1.
        ImportError: ``aeon`` is not installed.
    """
    if isinstance(subsample, bool) or not isinstance(subsample, numbers.Integral) or subsample < 1:
        raise ValueError(
            f"subsample must be an int >= 1 (keep every n-th frame), got {subsample!r}"
        )
    subsample = int(subsample)
    try:
        from aeon.datasets import load_basic_motions as aeon_basic_motions
    except ImportError as err:  # optional extra
        raise ImportError("the action-recognition experiment needs the optional aeon") from err
    parts = []
    for split in ("train", "test"):
        x, y = aeon_basic_motions(split=split)
        parts.append((torch.as_tensor(x, dtype=torch.float64).transpose(1, 2), y))
    names = sorted(set(parts[0][1]))
    code = {n: i for i, n in enumerate(names)}
    out = []
    for x, y in parts:
        out += [x[:, ::subsample].contiguous(), torch.tensor([code[v] for v in y])]
    return (*out, names)
