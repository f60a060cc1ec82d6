"""The intention grid: set-up shared by batch and online inference.

Both algorithms score K values of the intention ``g`` (:func:`intention_grid`: the codes of a
discrete g, or a grid over a continuous one; a plain :class:`~hgpdm_torch.models.GPDM` has no g
and is one value) and report an :class:`~hgpdm_torch.intention_belief.IntentionBelief` over
them.

Shapes: ``K`` intention values, ``Dg`` intention dims, ``Dz`` observed dims.
"""

from __future__ import annotations

import numbers
from typing import Any

import torch

from ...models.gpdm import GPDM
from ...models.hgpdm import HGPDM
from ...validation import as_tensor

__all__ = ["intention_grid"]


def intention_grid(model: GPDM, intentions: Any = None, num: int = 25) -> torch.Tensor:
    """The K intention values to score, ``[K, Dg]`` (codes ``[K, 1]`` for a discrete g).

    Args:
        model: a fitted :class:`~hgpdm_torch.models.HGPDM` / ``IDDM``, or a plain
            :class:`~hgpdm_torch.models.GPDM`: no g, one value (``[1, 0]``, ``intentions=None``).
        intentions: ``[K]`` or ``[K, Dg]`` values (continuous g) or integer codes (discrete g);
            default: all codes, or ``num`` evenly spaced values over the training range
            (``Dg = 1`` only).
        num: default grid size for a continuous g, at least 2 (a grid spans the training
            range from its smallest to its largest value).

    Raises:
        TypeError: ``model`` is not a GPDM, or ``num`` not an int.
        ValueError: ``num < 2``; ``intentions`` given for a plain GPDM, empty, with the wrong
            number of columns, or not codes ``0 .. K-1`` of a discrete g.
    """
    if not isinstance(model, GPDM):
        raise TypeError(f"model must be a GPDM/HGPDM/IDDM, got {type(model).__name__}")
    if isinstance(num, bool) or not isinstance(num, numbers.Integral):
        raise TypeError(f"num must be an int >= 2 (the grid size), got {num!r}")
    if num < 2:
        raise ValueError(
            f"num must be at least 2: the grid runs from the smallest to the largest training "
            f"intention, got {num}"
        )
    dtype, device = model.latent.dtype, model.latent.device
    if not isinstance(model, HGPDM):  # no exogenous variable: one value, no columns
        if intentions is not None:
            raise ValueError("a GPDM has no intention g: pass intentions=None (K = 1)")
        return torch.zeros(1, 0, dtype=dtype, device=device)
    if intentions is None:
        if model.intention == "discrete":
            return torch.arange(model.num_values, dtype=dtype, device=device)[:, None]
        if model.intention_dim != 1:
            raise ValueError("a multi-dimensional continuous g needs an explicit intentions grid")
        g = model.intentions[:, 0]
        grid = torch.linspace(float(g.min()), float(g.max()), int(num), dtype=dtype, device=device)
        return grid[:, None]
    values = as_tensor(intentions, "intentions", dtype=dtype, device=device)
    if values.dim() == 1:
        values = values[:, None]
    if values.dim() != 2 or values.shape[0] == 0:
        raise ValueError(
            f"intentions must be a non-empty [K] or [K, Dg] grid, got {tuple(values.shape)}"
        )
    if values.shape[1] != model.intention_dim:
        raise ValueError(
            f"intentions must have Dg = {model.intention_dim} columns, got {values.shape[1]}"
        )
    if model.intention == "discrete":
        codes = values[:, 0]
        if bool((codes != codes.round()).any()) or bool(
            ((codes < 0) | (codes >= model.num_values)).any()
        ):
            raise ValueError(
                f"discrete intentions must be integer codes in [0, {model.num_values - 1}]"
            )
    return values


def check_chunk_size(chunk_size: Any) -> int | None:
    if chunk_size is None:
        return None
    if (
        isinstance(chunk_size, bool)
        or not isinstance(chunk_size, numbers.Integral)
        or int(chunk_size) < 1
    ):
        raise ValueError(f"chunk_size must be a positive int or None, got {chunk_size!r}")
    return int(chunk_size)
