"""Window classification baselines: the class of a sequence from a window of observations.

- :class:`WindowSVM`: support vector classification (scikit-learn ``SVC``) of a window;
- :class:`WindowGPC`: multi-class GP classification of a window (gpytorch exact GP on Dirichlet-
  transformed labels, Milios et al. 2018);
- :class:`HMMClassifier`: one Gaussian HMM per class (``hmmlearn``, an optional extra), the class
  of the highest window likelihood.
"""

from __future__ import annotations

from typing import Any

import gpytorch
import numpy as np
import torch
from sklearn.preprocessing import StandardScaler
from sklearn.svm import SVC

from ..validation import as_tensor
from .exact_gp import ExactGPModel, fit_marginal_likelihood
from .windows import (
    as_sequences,
    check_fitted,
    labelled_windows,
    positive_int,
    prediction_windows,
)

__all__ = ["HMMClassifier", "WindowGPC", "WindowSVM"]

_FIT_CALL = "fit(sequences, labels)"


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

    Raises:
        ValueError: ``window`` is not a positive int.
        RuntimeError: ``predict`` before ``fit``.
    """

    def __init__(self, window: int = 5, *, C: float = 10.0, gamma: str | float = "scale") -> None:
        self.window, self.C, self.gamma = positive_int(window, "window"), C, gamma

    def fit(self, sequences: Any, labels: Any) -> WindowSVM:
        seqs = as_sequences(sequences)
        y = _class_labels(labels, len(seqs))
        self.obs_dim, self.num_classes = seqs[0].shape[1], int(y.max()) + 1
        x, yy = labelled_windows(seqs, y, self.window)
        self.scaler = StandardScaler().fit(x.numpy())
        self.svc = SVC(C=self.C, gamma=self.gamma).fit(self.scaler.transform(x.numpy()), yy)
        return self

    def predict(self, z: Any) -> torch.Tensor:
        """Class at every step: ``[..., T, Dz]`` -> ``[..., T]`` (long)."""
        check_fitted(self, "svc", _FIT_CALL)
        x = prediction_windows(z, self.window, self.obs_dim)
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

    Raises:
        ValueError: ``window`` or ``samples`` is not a positive int, ``steps`` or ``seed`` not
            a non-negative int.
        RuntimeError: ``predict`` or ``predict_proba`` before ``fit``.
    """

    def __init__(
        self, window: int = 5, *, steps: int = 100, lr: float = 0.1, samples: int = 256,
        seed: int = 0,
    ) -> None:  # fmt: skip
        self.window, self.lr = positive_int(window, "window"), float(lr)
        self.steps = positive_int(steps, "steps", low=0)
        self.samples = positive_int(samples, "samples")
        self.seed = positive_int(seed, "seed", low=0)

    def fit(self, sequences: Any, labels: Any) -> WindowGPC:
        seqs = as_sequences(sequences)
        y = _class_labels(labels, len(seqs))
        self.obs_dim = seqs[0].shape[1]
        x, yy = labelled_windows(seqs, y, self.window)
        self.scaler = StandardScaler().fit(x.numpy())
        x = torch.as_tensor(self.scaler.transform(x.numpy()))
        lik = gpytorch.likelihoods.DirichletClassificationLikelihood(
            yy, learn_additional_noise=True, dtype=torch.float64
        )
        self.num_classes = lik.num_classes
        batch = torch.Size((lik.num_classes,))
        model = ExactGPModel(x, lik.transformed_targets, lik, batch_shape=batch).double()
        fit_marginal_likelihood(model, lik, x, lik.transformed_targets, self.steps, self.lr)
        self.model, self.likelihood = model, lik
        return self

    @torch.no_grad()
    def predict_proba(self, z: Any) -> torch.Tensor:
        """Class probabilities at every step: ``[..., T, Dz]`` -> ``[..., T, C]``."""
        check_fitted(self, "model", _FIT_CALL)
        x = prediction_windows(z, self.window, self.obs_dim)
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
        ValueError: ``states``, ``iterations`` or ``window`` (unless ``None``) is not a
            positive int, or ``seed`` not a non-negative int.
        RuntimeError: ``predict``, ``predict_proba`` or ``log_likelihood`` before ``fit``.
    """

    def __init__(
        self, states: int = 4, *, window: int | None = 5, iterations: int = 50, seed: int = 0
    ) -> None:
        # checked before the import, so that a bad argument is named with or without hmmlearn
        self.states = positive_int(states, "states (hidden states per class)")
        self.window = None if window is None else positive_int(window, "window")
        self.iterations = positive_int(iterations, "iterations")
        self.seed = positive_int(seed, "seed", low=0)
        try:
            from hmmlearn.hmm import GaussianHMM
        except ImportError as err:  # optional extra
            raise ImportError("HMMClassifier needs the optional package hmmlearn") from err
        self._hmm = GaussianHMM

    def fit(self, sequences: Any, labels: Any) -> HMMClassifier:
        seqs = as_sequences(sequences)
        y = _class_labels(labels, len(seqs))
        self.obs_dim, self.num_classes = seqs[0].shape[1], int(y.max()) + 1
        hmms = []
        for c in range(self.num_classes):
            data = [seqs[j].numpy() for j in range(len(seqs)) if int(y[j]) == c]
            if not data:
                raise ValueError(
                    f"labels must use every class code 0..{self.num_classes - 1}: class {c} "
                    "has no training sequence, so it has no HMM"
                )
            hmm = self._hmm(
                self.states, covariance_type="diag", n_iter=self.iterations,
                random_state=self.seed,
            )  # fmt: skip
            hmm.fit(np.concatenate(data), [len(d) for d in data])
            hmms.append(hmm)
        self.hmms = hmms  # only a completed fit marks the classifier fitted
        return self

    def log_likelihood(self, z: Any) -> torch.Tensor:
        """Window log-likelihood under each class: ``[..., T, Dz]`` -> ``[..., T, C]``."""
        check_fitted(self, "hmms", _FIT_CALL)
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
