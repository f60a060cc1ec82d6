"""Next-frame forecasters, the baselines of a dynamics model's one-step predictions.

Why these baselines: docs/design/evaluation.md#baselines-on-the-same-features.

Fitted on whole sequences, they predict the frame after each of ``[W, T, Dz]`` windows:

- :class:`LastFrameForecaster`: repeat the last frame;
- :class:`RidgeAR`: linear autoregression on the last ``k`` frames (ridge regression), with ``k``
  and the penalty chosen by cross-validation grouped by training sequence.
"""

from __future__ import annotations

import math
import numbers
from collections.abc import Sequence
from typing import Any

import numpy as np
import torch
from sklearn.linear_model import Ridge
from sklearn.model_selection import GridSearchCV, GroupKFold

from ..validation import as_tensor
from .windows import as_sequences, window_features

__all__ = ["LastFrameForecaster", "RidgeAR"]


class BaseForecaster:
    """Predicts ``z_{t+1}`` from a window ending at ``z_t``, using its last ``order_`` frames."""

    order_: int = 1
    obs_dim: int | None = None

    def _windows(self, windows: Any) -> torch.Tensor:
        z = as_tensor(windows, "windows", min_ndim=2)
        if self.obs_dim is not None and z.shape[-1] != self.obs_dim:
            raise ValueError(
                f"windows must have Dz = {self.obs_dim} columns like the training data, "
                f"got shape {tuple(z.shape)}"
            )
        if z.shape[-2] < self.order_:
            raise ValueError(
                f"windows must have at least order_ = {self.order_} frames, got {z.shape[-2]}"
            )
        return z


class LastFrameForecaster(BaseForecaster):
    """The persistence forecast ``z_{t+1} = z_t``: what any dynamics model must beat."""

    def fit(self, sequences: Any) -> LastFrameForecaster:
        """Record ``Dz`` of the ``[T_j, Dz]`` training sequences (nothing is learned)."""
        self.obs_dim = as_sequences(sequences)[0].shape[1]
        return self

    def predict(self, windows: Any) -> torch.Tensor:
        """The last frame of each window: ``[..., T, Dz]`` -> ``[..., Dz]``."""
        return self._windows(windows)[..., -1, :].clone()


def _lagged(
    sequences: list[torch.Tensor], order: int, start: int
) -> tuple[torch.Tensor, torch.Tensor, np.ndarray]:
    """Autoregression rows for the targets ``z_t``, ``t >= start >= order``, of every sequence.

    Returns:
        inputs ``[n, order Dz]`` (``[z_{t-order}, ..., z_{t-1}]``, as :func:`window_features`
        stacks them), targets ``[n, Dz]`` and the sequence index of every row ``[n]``.
    """
    x = torch.cat([window_features(s, order)[start - 1 : -1] for s in sequences])
    y = torch.cat([s[start:] for s in sequences])
    groups = np.repeat(np.arange(len(sequences)), [max(0, s.shape[0] - start) for s in sequences])
    return x, y, groups


_AR_ALPHAS = tuple(10.0 ** (k / 2) for k in range(-6, 7))  # np.logspace(-3, 3, 13)


class RidgeAR(BaseForecaster):
    """Linear autoregression ``z_{t+1} = A [z_{t-k+1}, ..., z_t] + b``, fitted by ridge regression
    (scikit-learn ``Ridge``: the intercept ``b`` is not penalised).

    :meth:`fit` chooses the order ``k`` and the penalty ``alpha`` by cross-validation grouped by
    training sequence (``GroupKFold``: a sequence is never split between training and
    validation). Every candidate is scored on the same targets (frames ``t >= max(orders)``),
    by the mean squared error over all ``Dz`` outputs. The order is chosen by a one standard
    error rule (Hastie et al., *Elements of Statistical Learning*, Sec. 7.10) on paired
    differences: the smallest order whose best validation error exceeds the overall best by no
    more than the standard error of that excess over the folds (pairing removes the spread
    between folds of unequal difficulty, e.g. one subject harder than the other); the lowest
    mean validation error alone tends to over-select the order (on a simulated VAR(2) it
    sometimes picks 3). The penalty is the best one for the chosen order. The model is then
    refitted on all the training frames.

    The penalty treats all inputs alike: fit on standardised features (e.g.
    :class:`~hgpdm_torch.datasets.Standardizer`).

    Attributes (after :meth:`fit`):
        order_: the chosen order ``k``; alpha_: the chosen penalty.
        coef_: ``[Dz, k Dz]``, the columns ordered as the inputs (oldest frame first);
        intercept_: ``[Dz]``.
        cv_mse_: ``[len(orders), len(alphas)]`` mean validation MSE of every candidate
            (``None`` when there was one candidate);
        cv_se_: ``[len(orders)]`` standard error over folds of each order's excess error over
            the best (``None`` also with ``one_standard_error=False``).
    """

    def fit(
        self,
        sequences: Any,
        orders: Sequence[int] = (1, 2, 3, 4, 5),
        alphas: Sequence[float] | np.ndarray = _AR_ALPHAS,
        *,
        folds: int = 5,
        one_standard_error: bool = True,
    ) -> RidgeAR:
        """Fit on ``J`` sequences ``[T_j, Dz]``.

        Args:
            sequences: the training sequences (a list, or one ``[J, T, Dz]`` array).
            orders: candidate orders ``k >= 1``.
            alphas: candidate ridge penalties ``> 0``.
            folds: number of grouped folds (at most the number of sequences; as many as there
                are sequences is leave-one-sequence-out).
            one_standard_error: choose the order by the paired one standard error rule
                (default) or take the candidate with the lowest mean validation error.

        Raises:
            ValueError: bad ``orders``/``alphas``/``folds``, sequences of different ``Dz``, fewer
                than 2 sequences longer than ``max(orders)`` frames when there is a choice to
                make, or no sequence longer than the chosen order.
        """
        seqs = as_sequences(sequences)
        orders = tuple(orders)
        if len(orders) == 0 or any(
            not isinstance(k, numbers.Integral) or isinstance(k, bool) or k < 1 for k in orders
        ):
            raise ValueError(f"orders must be positive ints, got {orders!r}")
        orders = tuple(int(k) for k in orders)
        alphas = np.asarray(alphas, dtype=np.float64).ravel()
        if alphas.size == 0 or not bool(np.all(np.isfinite(alphas) & (alphas > 0))):
            raise ValueError(f"alphas must be positive finite numbers, got {alphas!r}")
        if not isinstance(folds, numbers.Integral) or isinstance(folds, bool) or folds < 2:
            raise ValueError(f"folds must be an int >= 2, got {folds!r}")
        self.obs_dim = seqs[0].shape[1]
        self.cv_mse_ = self.cv_se_ = None
        if len(orders) * alphas.size == 1:
            self.order_, self.alpha_ = orders[0], float(alphas[0])
        else:
            self._select(seqs, orders, alphas, int(folds), one_standard_error)
        usable = [s for s in seqs if s.shape[0] > self.order_]
        if not usable:
            raise ValueError(f"sequences must have more than order = {self.order_} frames")
        x, y, _ = _lagged(usable, self.order_, self.order_)
        model = Ridge(alpha=self.alpha_).fit(x.numpy(), y.numpy())
        self.coef_ = torch.as_tensor(model.coef_, dtype=torch.float64).reshape(self.obs_dim, -1)
        self.intercept_ = torch.as_tensor(model.intercept_, dtype=torch.float64).reshape(-1)
        return self

    def _select(
        self,
        seqs: list[torch.Tensor],
        orders: tuple[int, ...],
        alphas: np.ndarray,
        folds: int,
        one_standard_error: bool,
    ) -> None:
        """Grouped cross-validation over ``orders x alphas``; sets ``order_``, ``alpha_``,
        ``cv_mse_`` and ``cv_se_``."""
        start = max(orders)
        usable = [s for s in seqs if s.shape[0] > start]
        if len(usable) < 2:
            raise ValueError(
                f"sequences: grouped cross-validation needs at least 2 sequences longer than "
                f"max(orders) = {start} frames, got {len(usable)}"
            )
        splitter = GroupKFold(n_splits=min(folds, len(usable)))
        fold_mse = []  # per order: [len(alphas), folds]
        for k in orders:
            x, y, groups = _lagged(usable, k, start)
            search = GridSearchCV(
                Ridge(),
                {"alpha": list(alphas)},
                scoring="neg_mean_squared_error",
                cv=splitter,
                refit=False,
            )
            search.fit(x.numpy(), y.numpy(), groups=groups)
            splits = [f"split{i}_test_score" for i in range(splitter.n_splits)]
            fold_mse.append(-np.stack([search.cv_results_[name] for name in splits], axis=1))
        mse = np.stack(fold_mse)  # [orders, alphas, folds]
        self.cv_mse_ = mse.mean(-1)
        best_alpha = self.cv_mse_.argmin(1)  # per order
        i = int(self.cv_mse_.min(1).argmin())
        if one_standard_error:
            # each order's best candidate against the overall best, fold by fold
            diff = mse[np.arange(len(orders)), best_alpha] - mse[i, best_alpha[i]]  # [orders, F]
            se = diff.std(-1, ddof=1) / math.sqrt(diff.shape[-1])
            self.cv_se_ = se
            within = np.flatnonzero(diff.mean(-1) <= se)
            i = int(min(within, key=lambda o: orders[o]))
        self.order_, self.alpha_ = orders[i], float(alphas[best_alpha[i]])

    def predict(self, windows: Any) -> torch.Tensor:
        """The next frame after each window, from its last ``order_`` frames:
        ``[..., T, Dz]`` -> ``[..., Dz]`` (``T >= order_``)."""
        z = self._windows(windows)
        x = window_features(z[..., -self.order_ :, :], self.order_)[..., -1, :]
        return x @ self.coef_.to(x).T + self.intercept_.to(x)
