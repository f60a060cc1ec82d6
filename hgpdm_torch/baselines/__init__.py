"""Discriminative and forecasting baselines that IDDM inference and the dynamics models must beat.

Window baselines map a sliding window of observations to the intention, for the experiments of
thesis Sec. 3.5-3.6: every model is fitted on whole training sequences (each step labelled with
its sequence's intention) and predicts at every step of ``[M, T, Dz]`` test sequences from the
window ending there (the first steps use the frames available, padded by repeating the first one).
Next-frame forecasters are the baselines of a dynamics model's one-step predictions
(docs/design/evaluation.md#baselines-on-the-same-features).

The baselines are split by concept into the modules below; this package re-exports their public
names (``from hgpdm_torch.baselines import WindowGPR``):

* :mod:`~hgpdm_torch.baselines.windows`: :func:`window_features` and the labelled training rows;
* :mod:`~hgpdm_torch.baselines.exact_gp`: the exact GP shared by the GP baselines;
* :mod:`~hgpdm_torch.baselines.regression`: a continuous target (:class:`WindowGPR`,
  :class:`WindowRidge`, :class:`MedianPredictor`);
* :mod:`~hgpdm_torch.baselines.classification`: a class (:class:`WindowSVM`, :class:`WindowGPC`,
  :class:`HMMClassifier`);
* :mod:`~hgpdm_torch.baselines.forecasting`: the next frame (:class:`LastFrameForecaster`,
  :class:`RidgeAR`);
* :mod:`~hgpdm_torch.baselines.recurrent`: the next frame by a GRU (:class:`GRUForecaster`);
* :mod:`~hgpdm_torch.baselines.promp`: a probabilistic movement primitive conditioned on a
  movement's prefix, its phase estimated (:class:`ProMP`); a continuous target from it
  (:class:`ProMPRegressor`), a class by each class's prefix likelihood (:class:`ProMPClassifier`).
"""

from __future__ import annotations

from .classification import HMMClassifier, WindowGPC, WindowSVM
from .forecasting import LastFrameForecaster, RidgeAR
from .promp import PrefixPosterior, ProMP, ProMPClassifier, ProMPRegressor
from .recurrent import GRUForecaster
from .regression import MedianPredictor, WindowGPR, WindowRidge
from .windows import window_features

__all__ = [
    "GRUForecaster",
    "HMMClassifier",
    "LastFrameForecaster",
    "MedianPredictor",
    "PrefixPosterior",
    "ProMP",
    "ProMPClassifier",
    "ProMPRegressor",
    "RidgeAR",
    "WindowGPC",
    "WindowGPR",
    "WindowRidge",
    "WindowSVM",
    "window_features",
]
