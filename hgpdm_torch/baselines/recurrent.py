"""A small recurrent forecaster: what a user would try after ridge regression.

Why this baseline: docs/design/evaluation.md#baselines-on-the-same-features.

:class:`GRUForecaster` reads a window ``z_{t-T+1:t}`` with a one-layer GRU (``torch.nn.GRU``)
and predicts the change ``z_{t+1} - z_t`` from its last hidden state through a linear layer, so
that an untrained network starts at the persistence forecast. It is trained full-batch with Adam
on every window of length T of the training sequences; the hidden size and the number of epochs
(early stopping) are chosen by cross-validation grouped by training sequence, then the network is
refitted on all windows for the chosen number of epochs.
"""

from __future__ import annotations

import math
import numbers
from collections.abc import Sequence
from typing import Any

import numpy as np
import torch
from sklearn.model_selection import GroupKFold
from torch import nn

from .forecasting import BaseForecaster
from .windows import as_sequences

__all__ = ["GRUForecaster"]


class _GRUNet(nn.Module):
    def __init__(self, dz: int, hidden: int) -> None:
        super().__init__()
        self.gru = nn.GRU(dz, hidden, batch_first=True)
        self.out = nn.Linear(hidden, dz)
        nn.init.zeros_(self.out.weight)
        nn.init.zeros_(self.out.bias)

    def forward(self, z: torch.Tensor) -> torch.Tensor:
        h, _ = self.gru(z)
        return z[:, -1] + self.out(h[:, -1])


def _training_windows(
    seqs: list[torch.Tensor], length: int
) -> tuple[torch.Tensor, torch.Tensor, np.ndarray]:
    """Every window ``[n, T, Dz]`` of every sequence, its next frame ``[n, Dz]`` and sequence."""
    z, nxt, groups = [], [], []
    for j, s in enumerate(seqs):
        n = s.shape[0] - length
        if n <= 0:
            continue
        z.append(s.unfold(0, length, 1)[:n].transpose(1, 2))
        nxt.append(s[length:])
        groups.append(np.full(n, j))
    if not z:
        raise ValueError(f"sequences: none is longer than the window, {length} frames")
    return torch.cat(z), torch.cat(nxt), np.concatenate(groups)


class GRUForecaster(BaseForecaster):
    """Next-frame forecaster: a GRU over the window, hidden size and epochs by grouped CV.

    Args:
        hidden_sizes: candidate hidden sizes.
        max_epochs: the most full-batch Adam steps (the early-stopping horizon).
        folds: grouped folds of the selection (at most the number of training sequences).
        lr: Adam's learning rate.
        weight_decay: Adam's L2 penalty.
        seed: seed of the weight initialisation (the global RNG is left untouched).
        dtype: the network's precision (float32: a baseline need not be exact, and it trains
            about twice as fast on a CPU); predictions are returned in the windows' dtype.

    Attributes (after :meth:`fit`):
        window_: the training window length T; hidden_: chosen hidden size; epochs_: chosen
        number of epochs; cv_mse_: ``[len(hidden_sizes), max_epochs]`` mean validation MSE.
    """

    def __init__(
        self,
        hidden_sizes: Sequence[int] = (16, 64),
        max_epochs: int = 200,
        *,
        folds: int = 3,
        dtype: torch.dtype = torch.float32,
        lr: float = 1e-2,
        weight_decay: float = 1e-4,
        seed: int = 0,
    ) -> None:
        sizes = tuple(hidden_sizes)
        if not sizes or any(
            not isinstance(h, numbers.Integral) or isinstance(h, bool) or h < 1 for h in sizes
        ):
            raise ValueError(f"hidden_sizes must be positive ints, got {hidden_sizes!r}")
        for name, v, low in (("max_epochs", max_epochs, 1), ("folds", folds, 2)):
            if not isinstance(v, numbers.Integral) or isinstance(v, bool) or v < low:
                raise ValueError(f"{name} must be an int >= {low}, got {v!r}")
        for name, v in (("lr", lr), ("weight_decay", weight_decay)):
            if not (isinstance(v, numbers.Real) and 0 <= v < math.inf) or (name == "lr" and v == 0):
                raise ValueError(f"{name} must be a finite number >= 0 (lr > 0), got {v!r}")
        self.hidden_sizes, self.max_epochs, self.folds = sizes, int(max_epochs), int(folds)
        self.lr, self.weight_decay, self.seed = float(lr), float(weight_decay), int(seed)
        self.dtype = dtype

    def _train(
        self,
        hidden: int,
        epochs: int,
        z: torch.Tensor,
        nxt: torch.Tensor,
        val: tuple[torch.Tensor, torch.Tensor] | None = None,
    ) -> tuple[_GRUNet, list[float]]:
        """Train a network; the validation MSE after every epoch when ``val`` is given."""
        with torch.random.fork_rng(devices=[]):
            torch.manual_seed(self.seed)
            net = _GRUNet(z.shape[-1], hidden).to(z)
        opt = torch.optim.Adam(net.parameters(), lr=self.lr, weight_decay=self.weight_decay)
        curve = []
        for _ in range(epochs):
            opt.zero_grad()
            loss = (net(z) - nxt).pow(2).mean()
            loss.backward()
            opt.step()
            if val is not None:
                with torch.no_grad():
                    curve.append(float((net(val[0]) - val[1]).pow(2).mean()))
        return net, curve

    def fit(self, sequences: Any, window: int) -> GRUForecaster:
        """Fit on ``J`` sequences ``[T_j, Dz]`` with windows of ``window`` frames.

        Raises:
            ValueError: bad ``window``, fewer than 2 sequences longer than the window (no
                grouped selection possible), or sequences of different ``Dz``.
        """
        seqs = as_sequences(sequences)
        if not isinstance(window, numbers.Integral) or isinstance(window, bool) or window < 1:
            raise ValueError(f"window must be a positive int, got {window!r}")
        self.window_ = self.order_ = int(window)
        self.obs_dim = seqs[0].shape[1]
        z, nxt, groups = _training_windows(seqs, self.window_)
        z, nxt = z.to(self.dtype), nxt.to(self.dtype)
        n_groups = len(np.unique(groups))
        if n_groups < 2:
            raise ValueError("sequences: grouped cross-validation needs at least 2 sequences")
        splitter = GroupKFold(n_splits=min(self.folds, n_groups))
        curves = np.zeros((len(self.hidden_sizes), self.max_epochs))
        for tr, va in splitter.split(z, groups=groups):
            tr_t, va_t = torch.as_tensor(tr), torch.as_tensor(va)
            for i, hidden in enumerate(self.hidden_sizes):
                _, curve = self._train(
                    hidden, self.max_epochs, z[tr_t], nxt[tr_t], (z[va_t], nxt[va_t])
                )
                curves[i] += np.asarray(curve) / splitter.n_splits
        self.cv_mse_ = curves
        i, e = np.unravel_index(int(np.nanargmin(curves)), curves.shape)
        self.hidden_, self.epochs_ = self.hidden_sizes[int(i)], int(e) + 1
        self.net_, _ = self._train(self.hidden_, self.epochs_, z, nxt)
        return self

    def predict(self, windows: Any) -> torch.Tensor:
        """The next frame after each window, from its last ``window_`` frames:
        ``[..., T, Dz]`` -> ``[..., Dz]`` (``T >= window_``)."""
        z = self._windows(windows)
        lead = z.shape[:-2]
        flat = z[..., -self.window_ :, :].reshape(-1, self.window_, z.shape[-1])
        with torch.no_grad():
            out = self.net_(flat.to(next(self.net_.parameters())))
        return out.to(z).reshape(*lead, z.shape[-1])
