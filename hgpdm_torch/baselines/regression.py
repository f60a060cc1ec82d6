"""Window regression baselines: a continuous target from a window of observations.

- :class:`WindowGPR`: GP regression (gpytorch ``ExactGP``, RBF kernel with automatic relevance
  determination) from the last ``w`` observations to a continuous target, with ``w`` chosen on a
  validation split of the training sequences (Sec. 3.5.1: the thesis found ``w = 2`` best);
- :class:`WindowRidge`: ridge regression (scikit-learn ``RidgeCV``) from the same windows, the
  linear counterpart of :class:`WindowGPR` (not in the thesis: it shows how much of the target a
  linear read-out of the raw observations already holds);
- :class:`MedianPredictor`: always predicts the median training target (Sec. 3.5.2).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import gpytorch
import torch
from sklearn.linear_model import RidgeCV
from sklearn.preprocessing import StandardScaler

from ..validation import as_tensor
from .exact_gp import ExactGPModel, fit_marginal_likelihood
from .windows import (
    as_sequences,
    check_fitted,
    labelled_windows,
    positive_int,
    prediction_windows,
)

__all__ = ["MedianPredictor", "WindowGPR", "WindowRidge"]


class _WindowRegressor:
    """Regression from a window of observations, the window chosen on a validation split.

    Subclasses implement ``_train(sequences, targets, window)`` (fit state for one window) and
    ``_predict_flat(x [n, w Dz]) -> (mean [n], std [n] or None)``.
    """

    def __init__(self, windows: Sequence[int], val_fraction: float, seed: int) -> None:
        if (
            not isinstance(windows, Sequence)
            or isinstance(windows, str)
            or len(windows) == 0
            or any(isinstance(w, bool) or not isinstance(w, int) or w < 1 for w in windows)
        ):
            raise ValueError(
                f"windows must be a non-empty sequence of positive ints (candidate window "
                f"sizes, e.g. (1, 2, 3)), got {windows!r}"
            )
        if not 0 < val_fraction < 1:
            raise ValueError(f"val_fraction must be in (0, 1), got {val_fraction}")
        self.windows, self.val_fraction, self.seed = tuple(windows), float(val_fraction), int(seed)

    def _train(self, sequences: list[torch.Tensor], targets: torch.Tensor, window: int) -> None:
        raise NotImplementedError

    def _predict_flat(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor | None]:
        raise NotImplementedError

    def fit(self, sequences: Any, targets: Any):
        """Fit on ``J`` sequences ``[T_j, Dz]`` with one target each ``[J]``."""
        seqs = as_sequences(sequences)
        y = as_tensor(targets, "targets", ndim=1)
        if y.shape[0] != len(seqs):
            raise ValueError(f"need one target per sequence: {y.shape[0]} for {len(seqs)}")
        self.obs_dim = seqs[0].shape[1]
        gen = torch.Generator().manual_seed(self.seed)
        perm = torch.randperm(len(seqs), generator=gen).tolist()
        n_val = max(1, round(self.val_fraction * len(seqs)))
        val, train = perm[:n_val], perm[n_val:]
        if len(self.windows) > 1 and len(train) >= 2:
            errors = {}
            for w in self.windows:
                self.window = w
                self._train([seqs[i] for i in train], y[train], w)
                mean = self._predict(torch.stack([seqs[i] for i in val]))[0]
                errors[w] = float((mean - y[val, None]).abs().mean())
            self.validation_mae = errors
            self.window = min(errors, key=errors.get)
        else:
            self.window = self.windows[0]
        self._train(seqs, y, self.window)
        return self

    def _predict(self, z: Any) -> tuple[torch.Tensor, torch.Tensor | None]:
        check_fitted(self, "model", "fit(sequences, targets)")
        x = prediction_windows(z, self.window, self.obs_dim)
        flat = torch.as_tensor(self.scaler.transform(x.reshape(-1, x.shape[-1]).numpy()))
        mean, std = self._predict_flat(flat)
        shape = x.shape[:-1]
        return mean.reshape(shape), None if std is None else std.reshape(shape)


class WindowGPR(_WindowRegressor):
    """GP regression with ARD from a window of observations to a continuous target.

    Args:
        windows: candidate window sizes; the one with the lowest validation MAE is kept.
        val_fraction: fraction of training sequences held out to choose the window.
        steps: Adam steps on the marginal likelihood; lr: its learning rate.
        seed: seed of the validation split.

    Raises:
        ValueError: ``windows`` not positive ints, ``val_fraction`` outside ``(0, 1)``,
            ``steps`` not a non-negative int.
        RuntimeError: ``predict`` before ``fit``.
    """

    def __init__(
        self,
        windows: Sequence[int] = (1, 2, 3, 4),
        *,
        val_fraction: float = 0.25,
        steps: int = 150,
        lr: float = 0.05,
        seed: int = 0,
    ) -> None:
        super().__init__(windows, val_fraction, seed)
        self.steps, self.lr = positive_int(steps, "steps", low=0), float(lr)

    def _train(self, sequences, targets, window) -> None:
        x, y = labelled_windows(sequences, targets, window)
        self.scaler = StandardScaler().fit(x.numpy())
        x = torch.as_tensor(self.scaler.transform(x.numpy()))
        lik = gpytorch.likelihoods.GaussianLikelihood()
        model = ExactGPModel(x, y, lik).double()
        lik.double()
        fit_marginal_likelihood(model, lik, x, y, self.steps, self.lr)
        self.model, self.likelihood = model, lik

    @torch.no_grad()
    def _predict_flat(self, x):
        out = self.likelihood(self.model(x))
        return out.mean, out.variance.sqrt()

    def predict(self, z: Any) -> tuple[torch.Tensor, torch.Tensor]:
        """Predictive mean and std of the target at every step: ``[..., T, Dz]`` -> ``[..., T]``."""
        return self._predict(z)


class WindowRidge(_WindowRegressor):
    """Ridge regression from a window of standardised observations to a continuous target.

    The regularisation strength is chosen by scikit-learn's efficient leave-one-out
    cross-validation (``RidgeCV`` over ``alphas``), the window on a validation split.

    Args:
        windows: candidate window sizes; the one with the lowest validation MAE is kept.
        alphas: candidate ridge penalties.
        val_fraction: fraction of training sequences held out to choose the window.
        seed: seed of the validation split.

    Raises:
        ValueError: ``windows`` not positive ints, ``alphas`` not positive, ``val_fraction``
            outside ``(0, 1)``.
        RuntimeError: ``predict`` before ``fit``.
    """

    def __init__(
        self,
        windows: Sequence[int] = (1, 2, 3, 4),
        *,
        alphas: Sequence[float] = tuple(10.0**k for k in range(-3, 4)),
        val_fraction: float = 0.25,
        seed: int = 0,
    ) -> None:
        super().__init__(windows, val_fraction, seed)
        if len(alphas) == 0 or any(not a > 0 for a in alphas):
            raise ValueError(f"alphas must be positive, got {alphas!r}")
        self.alphas = tuple(float(a) for a in alphas)

    def _train(self, sequences, targets, window) -> None:
        x, y = labelled_windows(sequences, targets, window)
        self.scaler = StandardScaler().fit(x.numpy())
        self.model = RidgeCV(alphas=self.alphas).fit(self.scaler.transform(x.numpy()), y.numpy())

    def _predict_flat(self, x):
        return torch.as_tensor(self.model.predict(x.numpy()), dtype=x.dtype), None

    def predict(self, z: Any) -> torch.Tensor:
        """Predicted target at every step: ``[..., T, Dz]`` -> ``[..., T]``."""
        return self._predict(z)[0]


class MedianPredictor:
    """The model-free baseline: the median of the training targets, at every step.

    Raises:
        ValueError: ``fit`` with no target.
        RuntimeError: ``predict`` before ``fit``.
    """

    def fit(self, sequences: Any, targets: Any) -> MedianPredictor:
        y = as_tensor(targets, "targets", ndim=1)
        if y.numel() == 0:
            raise ValueError("targets must hold at least one value, got none")
        self.median = float(y.median())
        return self

    def predict(self, z: Any) -> torch.Tensor:
        """``[..., T, Dz]`` -> ``[..., T]``."""
        check_fitted(self, "median", "fit(sequences, targets)")
        z = as_tensor(z, "z", min_ndim=2, allow_nan=True)
        return torch.full(z.shape[:-1], self.median, dtype=z.dtype)
