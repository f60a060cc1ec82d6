"""Run experiment code with float64 as torch's default dtype (the GP code needs it)."""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager

import torch

from ..settings import default_dtype

__all__ = ["float64_default"]


@contextmanager
def float64_default() -> Iterator[None]:
    """Context in which ``torch.get_default_dtype()`` is float64; the previous one is restored."""
    with default_dtype(torch.float64):
        yield
