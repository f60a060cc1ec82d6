"""Features of Kinect skeletons (:data:`~hgpdm_torch.datasets.msrc12.JOINTS`, Kinect SDK v1):
:func:`kinect_features` (joint positions relative to the hip centre) and :class:`PosePCA`
(frame statistics and a PCA fitted on training frames only, so that no test person shapes the
features).
"""

from __future__ import annotations

import numbers
from collections.abc import Sequence
from typing import Any

import torch
from sklearn.decomposition import PCA

from ..validation import as_tensor
from .msrc12 import JOINTS
from .walkers import Standardizer

__all__ = ["PosePCA", "kinect_features"]


def kinect_features(
    positions: Any, joints: Sequence[int | str] | None = None, *, include_hip: bool = False
) -> torch.Tensor:
    """Joint positions relative to the hip centre, flattened per frame.

    The hip centre (joint 0) is subtracted from every joint in every frame, which removes where
    the person stands (and walks) in front of the camera but keeps the body's orientation to it.

    Args:
        positions: ``[..., T, 20, 3]`` joint positions (joints as in :data:`JOINTS`).
        joints: the joints to keep, by index or name (default: all but the hip centre, or all 20
            with ``include_hip``).
        include_hip: with ``joints=None``, keep the hip centre too (three columns that are
            zero: 60 instead of 57 columns).

    Returns:
        ``[..., T, 3 J]`` (float64): ``x y z`` of the first kept joint, then of the second, ...

    Raises:
        ValueError: ``positions`` not finite ``[..., 20, 3]``, an unknown or repeated joint.
    """
    x = as_tensor(positions, "positions", dtype=torch.float64, min_ndim=3)
    if x.shape[-2:] != (len(JOINTS), 3):
        raise ValueError(f"positions must be [..., T, 20, 3], got shape {tuple(x.shape)}")
    if joints is None:
        index = list(range(0 if include_hip else 1, len(JOINTS)))
    else:
        index = []
        for j in joints:
            if isinstance(j, str) and j in JOINTS:
                index.append(JOINTS.index(j))
            elif isinstance(j, numbers.Integral) and 0 <= j < len(JOINTS):
                index.append(int(j))
            else:
                raise ValueError(f"joints must be indices 0-19 or names in JOINTS, got {j!r}")
        if not index or len(set(index)) != len(index):
            raise ValueError(f"joints must be a non-empty list of distinct joints, got {joints}")
    rel = x - x[..., :1, :]
    return rel[..., index, :].flatten(-2)


class PosePCA:
    """Frame statistics and a PCA, fitted on training frames only.

    :meth:`fit` centres the training frames (and, with ``standardize``, drops the channels
    constant in training and scales the others to unit variance, with
    :class:`~hgpdm_torch.datasets.Standardizer`), then fits scikit-learn's ``PCA`` (full SVD,
    deterministic) on them. :meth:`transform` applies the same maps to any frames.

    Args:
        dim: components to keep: an int ``d >= 1``, a fraction in ``(0, 1)`` of the training
            variance to explain (the smallest ``d`` that does), or ``None`` (no PCA: the
            centred, optionally standardised, features).
        standardize: scale channels to unit training variance before the PCA (with positions
            in metres the default ``False`` keeps large movements large).

    Attributes (after :meth:`fit`):
        dim_: the output dimension.
        explained_variance_ratio_: ``[dim_]`` share of the training variance of each component
            (``None`` without PCA).
    """

    def __init__(self, dim: int | float | None = None, *, standardize: bool = False) -> None:
        if dim is not None and not (
            (isinstance(dim, numbers.Integral) and dim >= 1)
            or (isinstance(dim, float) and 0.0 < dim < 1.0)
        ):
            raise ValueError(f"dim must be an int >= 1, a fraction in (0, 1) or None, got {dim!r}")
        self.dim, self.standardize = dim, bool(standardize)

    def _prepare(self, x: torch.Tensor) -> torch.Tensor:
        if self.standardize:
            return self.scaler_.transform(x)
        return x - self.mean_.to(x)

    def fit(self, x: Any) -> PosePCA:
        """Fit on training frames ``[..., F]`` (e.g. ``[n, T, F]`` features of the training
        instances: every frame counts once)."""
        x = as_tensor(x, "x", dtype=torch.float64, min_ndim=1)
        frames = x.reshape(-1, x.shape[-1])
        if frames.shape[0] < 2:
            raise ValueError(f"x must hold at least 2 frames, got shape {tuple(x.shape)}")
        self.features_ = frames.shape[1]
        if self.standardize:
            self.scaler_ = Standardizer().fit(frames)
        else:
            self.mean_ = frames.mean(0)
        u = self._prepare(frames)
        if self.dim is None:
            self.pca_, self.dim_, self.explained_variance_ratio_ = None, u.shape[1], None
            return self
        if isinstance(self.dim, numbers.Integral) and self.dim > min(u.shape):
            raise ValueError(f"dim = {self.dim} exceeds min(frames, features) = {min(u.shape)}")
        self.pca_ = PCA(self.dim, svd_solver="full").fit(u.cpu().numpy())
        self.dim_ = int(self.pca_.n_components_)
        self.explained_variance_ratio_ = self.pca_.explained_variance_ratio_.tolist()
        return self

    def transform(self, x: Any) -> torch.Tensor:
        """``[..., F]`` -> ``[..., dim_]`` (float64, on the input's device)."""
        if not hasattr(self, "dim_"):
            raise RuntimeError("call fit before transform")
        x = as_tensor(x, "x", dtype=torch.float64, min_ndim=1)
        if x.shape[-1] != self.features_:
            raise ValueError(f"x must have {self.features_} features, got shape {tuple(x.shape)}")
        u = self._prepare(x)
        if self.pca_ is None:
            return u
        mean = torch.as_tensor(self.pca_.mean_, dtype=u.dtype, device=u.device)
        comp = torch.as_tensor(self.pca_.components_, dtype=u.dtype, device=u.device)
        return (u - mean) @ comp.T
