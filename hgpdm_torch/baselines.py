"""Discriminative baselines that map a sliding window of observations to the intention.

Used by the experiments of thesis Sec. 3.5-3.6 to compare with IDDM inference:

- :class:`WindowGPR`: GP regression (gpytorch ``ExactGP``, RBF kernel with automatic relevance
  determination) from the last ``w`` observations to a continuous target, with ``w`` chosen on a
  validation split of the training sequences (Sec. 3.5.1: the thesis found ``w = 2`` best);
- :class:`WindowRidge`: ridge regression (scikit-learn ``RidgeCV``) from the same windows, the
  linear counterpart of :class:`WindowGPR` (not in the thesis: it shows how much of the target a
  linear read-out of the raw observations already holds);
- :class:`MedianPredictor`: always predicts the median training target (Sec. 3.5.2);
- :class:`WindowSVM`: support vector classification (scikit-learn ``SVC``) of a window;
- :class:`WindowGPC`: multi-class GP classification of a window (gpytorch exact GP on Dirichlet-
  transformed labels, Milios et al. 2018);
- :class:`HMMClassifier`: one Gaussian HMM per class (``hmmlearn``, an optional extra), the class
  of the highest window likelihood.

Every model is fitted on whole training sequences (each step labelled with its sequence's
intention) and predicts at every step of ``[M, T, Dz]`` test sequences from the window ending
there (the first steps use the frames available, padded by repeating the first one).

Next-frame forecasters, the baselines of a dynamics model's one-step predictions (DESIGN 10):
fitted on whole sequences, they predict the frame after each of ``[W, T, Dz]`` windows:

- :class:`LastFrameForecaster`: repeat the last frame;
- :class:`RidgeAR`: linear autoregression on the last ``k`` frames (ridge regression), with ``k``
  and the penalty chosen by cross-validation grouped by training sequence.
"""

from __future__ import annotations

import math
import numbers
from collections.abc import Sequence
from typing import Any

import gpytorch
import numpy as np
import torch
from sklearn.linear_model import Ridge, RidgeCV
from sklearn.model_selection import GridSearchCV, GroupKFold
from sklearn.preprocessing import StandardScaler
from sklearn.svm import SVC

from .validation import as_tensor

__all__ = [
    "HMMClassifier",
    "LastFrameForecaster",
    "MedianPredictor",
    "RidgeAR",
    "WindowGPC",
    "WindowGPR",
    "WindowRidge",
    "WindowSVM",
    "window_features",
]


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


def _sequences(sequences: Any, name: str = "sequences") -> list[torch.Tensor]:
    if isinstance(sequences, torch.Tensor | np.ndarray):
        sequences = list(as_tensor(sequences, name, ndim=3))
    if not isinstance(sequences, Sequence) or len(sequences) == 0:
        raise ValueError(f"{name} must be a non-empty list of [T, Dz] arrays")
    out = [as_tensor(s, f"{name}[{j}]", ndim=2) for j, s in enumerate(sequences)]
    if any(s.shape[1] != out[0].shape[1] for s in out):
        raise ValueError(f"all {name} must have the same number of columns Dz")
    return out


def _labelled_windows(
    sequences: list[torch.Tensor], labels: torch.Tensor, window: int
) -> tuple[torch.Tensor, torch.Tensor]:
    """All windows of all sequences ``[sum T_j, w Dz]`` with their sequence's label."""
    if labels.shape[0] != len(sequences):
        raise ValueError(f"need one label per sequence: {labels.shape[0]} for {len(sequences)}")
    x = torch.cat([window_features(s, window) for s in sequences])
    y = torch.cat([labels[j].expand(s.shape[0]) for j, s in enumerate(sequences)])
    return x, y


def _test_windows(z: Any, window: int, dz: int) -> torch.Tensor:
    z = as_tensor(z, "z", min_ndim=2)
    if z.shape[-1] != dz:
        raise ValueError(f"z must have Dz = {dz} columns like the training data, got {z.shape}")
    return window_features(z, window)


# ------------------------------------------------------------------------------------------
# Regression
# ------------------------------------------------------------------------------------------


class _ExactGP(gpytorch.models.ExactGP):
    def __init__(
        self, x: torch.Tensor, y: torch.Tensor, likelihood, batch_shape: torch.Size | None = None
    ):
        super().__init__(x, y, likelihood)
        batch_shape = batch_shape or torch.Size()
        self.mean_module = gpytorch.means.ConstantMean(batch_shape=batch_shape)
        self.covar_module = gpytorch.kernels.ScaleKernel(
            gpytorch.kernels.RBFKernel(ard_num_dims=x.shape[-1], batch_shape=batch_shape),
            batch_shape=batch_shape,
        )

    def forward(self, x: torch.Tensor) -> gpytorch.distributions.MultivariateNormal:
        return gpytorch.distributions.MultivariateNormal(self.mean_module(x), self.covar_module(x))


def _fit_marginal_likelihood(model, likelihood, x, y, steps: int, lr: float) -> None:
    """Maximise the exact marginal likelihood with Adam (the standard gpytorch routine)."""
    model.train()
    likelihood.train()
    opt = torch.optim.Adam(model.parameters(), lr=lr)
    mll = gpytorch.mlls.ExactMarginalLogLikelihood(likelihood, model)
    for _ in range(steps):
        opt.zero_grad()
        loss = -mll(model(x), y).sum()
        loss.backward()
        opt.step()
    model.eval()
    likelihood.eval()


class _WindowRegressor:
    """Regression from a window of observations, the window chosen on a validation split.

    Subclasses implement ``_train(sequences, targets, window)`` (fit state for one window) and
    ``_predict_flat(x [n, w Dz]) -> (mean [n], std [n] or None)``.
    """

    def __init__(self, windows: Sequence[int], val_fraction: float, seed: int) -> None:
        if len(windows) == 0 or any(not isinstance(w, int) or w < 1 for w in windows):
            raise ValueError(f"windows must be positive ints, got {windows!r}")
        if not 0 < val_fraction < 1:
            raise ValueError(f"val_fraction must be in (0, 1), got {val_fraction}")
        self.windows, self.val_fraction, self.seed = tuple(windows), float(val_fraction), int(seed)

    def _train(self, sequences: list[torch.Tensor], targets: torch.Tensor, window: int) -> None:
        raise NotImplementedError

    def _predict_flat(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor | None]:
        raise NotImplementedError

    def fit(self, sequences: Any, targets: Any):
        """Fit on ``J`` sequences ``[T_j, Dz]`` with one target each ``[J]``."""
        seqs = _sequences(sequences)
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
        x = _test_windows(z, self.window, self.obs_dim)
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
        self.steps, self.lr = int(steps), float(lr)

    def _train(self, sequences, targets, window) -> None:
        x, y = _labelled_windows(sequences, targets, window)
        self.scaler = StandardScaler().fit(x.numpy())
        x = torch.as_tensor(self.scaler.transform(x.numpy()))
        lik = gpytorch.likelihoods.GaussianLikelihood()
        model = _ExactGP(x, y, lik).double()
        lik.double()
        _fit_marginal_likelihood(model, lik, x, y, self.steps, self.lr)
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
        x, y = _labelled_windows(sequences, targets, window)
        self.scaler = StandardScaler().fit(x.numpy())
        self.model = RidgeCV(alphas=self.alphas).fit(self.scaler.transform(x.numpy()), y.numpy())

    def _predict_flat(self, x):
        return torch.as_tensor(self.model.predict(x.numpy()), dtype=x.dtype), None

    def predict(self, z: Any) -> torch.Tensor:
        """Predicted target at every step: ``[..., T, Dz]`` -> ``[..., T]``."""
        return self._predict(z)[0]


class MedianPredictor:
    """The model-free baseline: the median of the training targets, at every step."""

    def fit(self, sequences: Any, targets: Any) -> MedianPredictor:
        self.median = float(as_tensor(targets, "targets", ndim=1).median())
        return self

    def predict(self, z: Any) -> torch.Tensor:
        """``[..., T, Dz]`` -> ``[..., T]``."""
        z = as_tensor(z, "z", min_ndim=2, allow_nan=True)
        return torch.full(z.shape[:-1], self.median, dtype=z.dtype)


# ------------------------------------------------------------------------------------------
# Classification
# ------------------------------------------------------------------------------------------


def _class_labels(labels: Any, num: int) -> torch.Tensor:
    y = torch.as_tensor(np.asarray(labels))
    if y.dim() != 1 or y.shape[0] != num or y.is_floating_point():
        raise ValueError(f"labels must be [J] integer codes, one per sequence, got {y.shape}")
    if bool((y < 0).any()):
        raise ValueError("labels must be non-negative class codes")
    return y.long()


class WindowSVM:
    """SVM (RBF kernel, scikit-learn ``SVC``) on a standardised window of observations.

    Args:
        window: window size w.
        C: the ``SVC`` regularisation parameter.
        gamma: the ``SVC`` RBF kernel width (``"scale"``, ``"auto"`` or a float).
    """

    def __init__(self, window: int = 5, *, C: float = 10.0, gamma: str | float = "scale") -> None:
        self.window, self.C, self.gamma = int(window), C, gamma

    def fit(self, sequences: Any, labels: Any) -> WindowSVM:
        seqs = _sequences(sequences)
        y = _class_labels(labels, len(seqs))
        self.obs_dim, self.num_classes = seqs[0].shape[1], int(y.max()) + 1
        x, yy = _labelled_windows(seqs, y, self.window)
        self.scaler = StandardScaler().fit(x.numpy())
        self.svc = SVC(C=self.C, gamma=self.gamma).fit(self.scaler.transform(x.numpy()), yy)
        return self

    def predict(self, z: Any) -> torch.Tensor:
        """Class at every step: ``[..., T, Dz]`` -> ``[..., T]`` (long)."""
        x = _test_windows(z, self.window, self.obs_dim)
        flat = self.scaler.transform(x.reshape(-1, x.shape[-1]).numpy())
        return torch.as_tensor(self.svc.predict(flat)).reshape(x.shape[:-1]).long()


class WindowGPC:
    """Multi-class GP classification of a window (gpytorch, Dirichlet-transformed labels).

    One exact GP per class with an ARD RBF kernel regresses the log of Dirichlet-smoothed
    one-hot labels with per-point heteroscedastic noise (``DirichletClassificationLikelihood``);
    class probabilities are Monte-Carlo averages of the softmax of the GP samples.

    Args:
        window: window size w.
        steps: Adam steps on the marginal likelihood.
        lr: Adam learning rate.
        samples: posterior samples for the class probabilities.
        seed: seed of the posterior samples.
    """

    def __init__(
        self, window: int = 5, *, steps: int = 100, lr: float = 0.1, samples: int = 256,
        seed: int = 0,
    ) -> None:  # fmt: skip
        self.window, self.steps, self.lr = int(window), int(steps), float(lr)
        self.samples, self.seed = int(samples), int(seed)

    def fit(self, sequences: Any, labels: Any) -> WindowGPC:
        seqs = _sequences(sequences)
        y = _class_labels(labels, len(seqs))
        self.obs_dim = seqs[0].shape[1]
        x, yy = _labelled_windows(seqs, y, self.window)
        self.scaler = StandardScaler().fit(x.numpy())
        x = torch.as_tensor(self.scaler.transform(x.numpy()))
        lik = gpytorch.likelihoods.DirichletClassificationLikelihood(
            yy, learn_additional_noise=True, dtype=torch.float64
        )
        self.num_classes = lik.num_classes
        batch = torch.Size((lik.num_classes,))
        model = _ExactGP(x, lik.transformed_targets, lik, batch_shape=batch).double()
        _fit_marginal_likelihood(model, lik, x, lik.transformed_targets, self.steps, self.lr)
        self.model, self.likelihood = model, lik
        return self

    @torch.no_grad()
    def predict_proba(self, z: Any) -> torch.Tensor:
        """Class probabilities at every step: ``[..., T, Dz]`` -> ``[..., T, C]``."""
        x = _test_windows(z, self.window, self.obs_dim)
        flat = torch.as_tensor(self.scaler.transform(x.reshape(-1, x.shape[-1]).numpy()))
        f = self.model(flat)  # batch of C GPs over the M points
        gen = torch.Generator().manual_seed(self.seed)
        eps = torch.randn(self.samples, *f.mean.shape, generator=gen, dtype=f.mean.dtype)
        draws = f.mean + f.variance.sqrt() * eps  # marginal samples [S, C, M]
        prob = draws.softmax(1).mean(0).T
        return prob.reshape(*x.shape[:-1], self.num_classes)

    def predict(self, z: Any) -> torch.Tensor:
        """Most probable class at every step: ``[..., T]`` (long)."""
        return self.predict_proba(z).argmax(-1)


class HMMClassifier:
    """Per-class Gaussian HMMs (``hmmlearn``): the class whose HMM best explains the window.

    Args:
        states: hidden states per class HMM.
        window: frames scored at each step (``None``: all frames so far).
        iterations: Baum-Welch iterations; seed: initialisation seed.

    Raises:
        ImportError: when the optional ``hmmlearn`` package is missing.
    """

    def __init__(
        self, states: int = 4, *, window: int | None = 5, iterations: int = 50, seed: int = 0
    ) -> None:
        try:
            from hmmlearn.hmm import GaussianHMM
        except ImportError as err:  # optional extra
            raise ImportError("HMMClassifier needs the optional package hmmlearn") from err
        self._hmm = GaussianHMM
        self.states, self.window = int(states), window
        self.iterations, self.seed = int(iterations), int(seed)

    def fit(self, sequences: Any, labels: Any) -> HMMClassifier:
        seqs = _sequences(sequences)
        y = _class_labels(labels, len(seqs))
        self.obs_dim, self.num_classes = seqs[0].shape[1], int(y.max()) + 1
        self.hmms = []
        for c in range(self.num_classes):
            data = [seqs[j].numpy() for j in range(len(seqs)) if int(y[j]) == c]
            hmm = self._hmm(
                self.states, covariance_type="diag", n_iter=self.iterations,
                random_state=self.seed,
            )  # fmt: skip
            hmm.fit(np.concatenate(data), [len(d) for d in data])
            self.hmms.append(hmm)
        return self

    def log_likelihood(self, z: Any) -> torch.Tensor:
        """Window log-likelihood under each class: ``[..., T, Dz]`` -> ``[..., T, C]``."""
        z = as_tensor(z, "z", min_ndim=2)
        if z.shape[-1] != self.obs_dim:
            raise ValueError(f"z must have Dz = {self.obs_dim} columns, got {z.shape}")
        flat = z.reshape(-1, *z.shape[-2:]).numpy()
        T = flat.shape[1]
        out = np.empty((flat.shape[0], T, self.num_classes))
        for i, seq in enumerate(flat):
            for t in range(T):
                start = 0 if self.window is None else max(0, t - self.window + 1)
                out[i, t] = [h.score(seq[start : t + 1]) for h in self.hmms]
        return torch.as_tensor(out).reshape(*z.shape[:-1], self.num_classes)

    def predict_proba(self, z: Any) -> torch.Tensor:
        """Posterior class probabilities under a uniform prior: ``[..., T, C]``."""
        return self.log_likelihood(z).softmax(-1)

    def predict(self, z: Any) -> torch.Tensor:
        """Most likely class at every step: ``[..., T]`` (long)."""
        return self.log_likelihood(z).argmax(-1)


# ------------------------------------------------------------------------------------------
# Next-frame forecasting
# ------------------------------------------------------------------------------------------


class _Forecaster:
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


class LastFrameForecaster(_Forecaster):
    """The persistence forecast ``z_{t+1} = z_t``: what any dynamics model must beat."""

    def fit(self, sequences: Any) -> LastFrameForecaster:
        """Record ``Dz`` of the ``[T_j, Dz]`` training sequences (nothing is learned)."""
        self.obs_dim = _sequences(sequences)[0].shape[1]
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


class RidgeAR(_Forecaster):
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
        seqs = _sequences(sequences)
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
