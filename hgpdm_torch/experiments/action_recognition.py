"""Action recognition from human movement (thesis Sec. 3.6, Table 3.3).

The action is a discrete intention; every method decides after every new frame:

- batch IDDM (Algorithm 3.1) on the last ``n = 4, 5, 6`` frames;
- online IDDM (Algorithm 3.2) with forgetting ``eps = 0.1, 0.2, 0.3``;
  both with the class-conditional first-state prior ``p(x_1 | g)`` by default
  (``--state-prior class``; ``marginal`` is the thesis's prior shared by all g);
- SVM, GP classification and per-class HMMs on the same sliding window (``n = 5``).

Two data sets (``--dataset``):

- ``basic_motions`` (default; ``aeon``, an optional extra): accelerometer and gyroscope
  (Dz = 6) of a smartwatch while a person stands, walks, runs or plays badminton (4 actions, 40
  training and 40 test recordings of 100 frames at 10 Hz), its own train/test split. As in the
  thesis (3 skeletal configurations per second) the frames are subsampled to ~3.3 Hz.
- ``msrc12``: Kinect skeletons of MSRC-12 gestures (:mod:`hgpdm_torch.datasets.msrc12`; ``--data``
  the development archive or a folder of the original recordings), the windows from 3 s before
  to 0.5 s after each action point subsampled to ~3.3 Hz. Features are the joint positions
  relative to the hip centre, reduced by a PCA; statistics and PCA come from the training
  persons only; leave-persons-out cross-validation (``GroupKFold`` over persons), a balanced
  random subset of the training persons' instances per class to fit the models (the thesis used
  ten repetitions per action; every GP is exact, O(N^3) in the training frames).

Reported: accuracy over all decisions (Table 3.3 calls it precision), how often the IDDM's 90%
credible set holds the true action, and the CPU time per decision; for MSRC-12 also the accuracy
of the decision at the end of each instance (its last kept frame, 0.3 s after the action point by
default) and the standard errors of the means over folds. ``meta["confusion"]`` holds each
method's confusion matrix over all decisions (rows true, columns predicted), and
``meta["fits"]`` the ``FitResult.summary()`` of every IDDM fit.
"""

from __future__ import annotations

import argparse
import os
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import torch
from sklearn.model_selection import GroupKFold, StratifiedKFold

from ..baselines import HMMClassifier, WindowGPC, WindowSVM
from ..datasets.msrc12 import MSRC12, PosePCA, kinect_features, load_msrc12_folder, load_msrc12_npz
from ..fitting import FitResult
from ..inference.calibration import fit_temperature
from ..inference.intention import (
    STATE_PRIORS,
    IntentionBelief,
    OnlineIntentionFilter,
    infer_intention,
)
from ..models import IDDM
from ..progress import tqdm
from ..results import ResultTable
from .arguments import int_at_least, output_file, random_seed

if TYPE_CHECKING:
    from matplotlib.figure import Figure

__all__ = [
    "DATASETS",
    "MSRC12_DEV",
    "action_recognition",
    "confusion_figure",
    "load_actions",
    "main",
    "msrc12_recognition",
]

DATASETS = ("basic_motions", "msrc12")
MSRC12_DEV = "../shared/data/msrc12_dev.npz"
"""The shared development archive, relative to the project root."""

# a method maps test sequences [M, T, Dz] to a decision after every frame: [M, T] labels
# (long), or [M, T, K] log class probabilities (the IDDM's beliefs, whose 90% credible sets
# are scored too)
Method = Callable[[torch.Tensor], torch.Tensor]


def load_actions(
    subsample: int = 3,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor, list[str]]:
    """BasicMotions from ``aeon`` (offline): ``(z_train [J, T, 6], y_train [J], z_test, y_test,
    class names)``, every ``subsample``-th frame."""
    try:
        from aeon.datasets import load_basic_motions
    except ImportError as err:  # optional extra
        raise ImportError("the action-recognition experiment needs the optional aeon") from err
    parts = []
    for split in ("train", "test"):
        x, y = load_basic_motions(split=split)
        parts.append((torch.as_tensor(x, dtype=torch.float64).transpose(1, 2), y))
    names = sorted(set(parts[0][1]))
    code = {n: i for i, n in enumerate(names)}
    out = []
    for x, y in parts:
        out += [x[:, ::subsample].contiguous(), torch.tensor([code[v] for v in y])]
    return (*out, names)


def _confusion(pred: torch.Tensor, truth: torch.Tensor, k: int) -> np.ndarray:
    """``[k, k]`` counts (rows true, columns predicted) of ``pred [M, T]`` against ``truth``
    (``[M, 1]`` or ``[M, T]``)."""
    m = np.zeros((k, k), dtype=int)
    np.add.at(m, (truth.expand_as(pred).flatten().numpy(), pred.flatten().numpy()), 1)
    return m


# ------------------------------------------------------------------------------------------
# Shared by both data sets: the fits, the methods and their timed decisions
# ------------------------------------------------------------------------------------------


def _fit_iddm(
    z_train: torch.Tensor,
    y_train: torch.Tensor,
    num_classes: int,
    latent_dim: int,
    fit_steps: int,
    seed: int,
    progress: bool,
    *,
    alpha4: float = 1e-2,
    noise_per_value: bool = False,
) -> tuple[IDDM, FitResult]:
    """The IDDM of Table 3.3: discrete g, linear measurement kernel, MAP fit (L-BFGS) on
    ``z_train [J, T, Dz]`` labelled ``y_train [J]``; transition ``alpha = (0.9, 0.3, 0.1,
    alpha4)``, and with ``noise_per_value`` a process noise per class estimated after the fit
    (:class:`~hgpdm_torch.models.HGPDM`)."""
    torch.manual_seed(seed)
    model = IDDM(
        list(z_train),
        y_train,
        latent_dim,
        intention="discrete",
        measurement="linear",
        num_values=num_classes,
        alpha=(0.9, 0.3, 0.1, alpha4),
        noise_per_value=noise_per_value,
    )
    return model, model.fit(fit_steps, progress=progress)


def _iddm_methods(
    model: IDDM,
    *,
    windows: Sequence[int],
    forgettings: Sequence[float],
    state_prior: str,
    temperatures: dict[str, float] | None = None,
) -> list[tuple[str, Method]]:
    """The IDDM rows of Table 3.3 (batch windows, online forgettings), each returning log
    beliefs ``[M, T, K]``; ``temperatures`` maps a row's name to its evidence temperature
    (default 1, the thesis's inference)."""
    temps = temperatures or {}
    jobs: list[tuple[str, Method]] = []
    for w in windows:
        name = f"IDDM batch n={w}"

        def batch(z: torch.Tensor, w: int = w, temp: float = temps.get(name, 1.0)) -> torch.Tensor:
            return infer_intention(
                model, z, window=w, state_prior=state_prior, temperature=temp
            ).log_prob

        jobs.append((name, batch))
    for eps in forgettings:
        name = f"IDDM online eps={eps}"

        def online(
            z: torch.Tensor, eps: float = eps, temp: float = temps.get(name, 1.0)
        ) -> torch.Tensor:
            f = OnlineIntentionFilter(
                model,
                forgetting=eps,
                batch_size=z.shape[0],
                state_prior=state_prior,
                temperature=temp,
            )
            return torch.stack([f.update(z[:, t]).log_prob for t in range(z.shape[1])], 1)

        jobs.append((name, online))
    return jobs


def _methods(
    model: IDDM,
    z_train: torch.Tensor,
    y_train: torch.Tensor,
    meta: dict[str, Any],
    *,
    windows: Sequence[int],
    forgettings: Sequence[float],
    baseline_window: int,
    seed: int,
    state_prior: str,
    temperatures: dict[str, float] | None = None,
) -> list[tuple[str, Method]]:
    """The methods of Table 3.3, baselines fitted on ``z_train [J, T, Dz]``, ``y_train [J]``;
    the IDDM's first-state prior ``state_prior`` (see :func:`infer_intention`) and evidence
    ``temperatures`` (:func:`_iddm_methods`).

    Returns ``(name, method)`` pairs in table order; a method left out is named in
    ``meta["skipped"]``.
    """
    jobs = _iddm_methods(
        model,
        windows=windows,
        forgettings=forgettings,
        state_prior=state_prior,
        temperatures=temperatures,
    )
    train = list(z_train)
    svm = WindowSVM(baseline_window).fit(train, y_train)
    jobs.append((f"SVM n={baseline_window}", svm.predict))
    gpc = WindowGPC(baseline_window, seed=seed).fit(train, y_train)
    jobs.append((f"GPC n={baseline_window}", gpc.predict))
    try:
        hmm = HMMClassifier(states=3, window=baseline_window, seed=seed).fit(train, y_train)
    except ImportError:
        meta["skipped"] = "HMM (hmmlearn not installed)"
        return jobs
    jobs.append((f"HMM n={baseline_window}", hmm.predict))
    return jobs


# one inner split of the training data: (z_fit [J, T, Dz], y_fit [J], z_val [V, T, Dz], y_val [V])
Split = tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]


def _fit_temperatures(
    splits: Sequence[Split],
    num_classes: int,
    latent_dim: int,
    fit_steps: int,
    seed: int,
    *,
    windows: Sequence[int],
    forgettings: Sequence[float],
    state_prior: str,
    progress: bool = False,
    **iddm: Any,
) -> tuple[dict[str, float], list[dict[str, Any]]]:
    """Evidence temperature of each IDDM row by cross-validation within the training data.

    For each inner split an IDDM is fitted on ``z_fit`` as the row's own model is (``iddm``:
    the keyword arguments of :func:`_fit_iddm` that it was fitted with), its beliefs
    at ``T = 1`` after every frame of the held-out ``z_val`` are pooled over the splits, and
    :func:`~hgpdm_torch.inference.fit_temperature` gives the ``T`` that maximises the
    likelihood of the true classes. For the batch rows this is exact temperature scaling; the
    online filter mixes its state under the belief, so there ``T`` is the scaling that fits the
    untempered beliefs best.

    Returns:
        ``{row name: T}`` and the ``FitResult.summary()`` of the inner fits.
    """
    logs: dict[str, list[torch.Tensor]] = {}
    truths, fits = [], []
    for z_fit, y_fit, z_val, y_val in tqdm(
        splits, disable=not progress, desc="calibration", leave=False
    ):
        dx = min(latent_dim, z_fit.shape[-1])
        model, fit = _fit_iddm(z_fit, y_fit, num_classes, dx, fit_steps, seed, progress, **iddm)
        fits.append(fit.summary())
        rows = _iddm_methods(
            model, windows=windows, forgettings=forgettings, state_prior=state_prior
        )
        for name, run in rows:
            logs.setdefault(name, []).append(run(z_val))
        truths.append(y_val[:, None].expand(-1, z_val.shape[1]))
    truth = torch.cat(truths)
    temps = {name: fit_temperature(torch.cat(parts), truth) for name, parts in logs.items()}
    return temps, fits


def _check_calibration_folds(folds: Any, most: int, what: str) -> None:
    """``folds`` must be an int in ``[2, most]`` (``most``: the number of ``what``)."""
    if isinstance(folds, bool) or not isinstance(folds, int) or not 2 <= folds <= most:
        raise ValueError(
            f"calibration_folds must be None or an int in [2, {most}] (the {what}), got {folds!r}"
        )


def _decide(
    jobs: list[tuple[str, Method]], z_test: torch.Tensor, progress: bool
) -> list[tuple[str, torch.Tensor, float, torch.Tensor | None]]:
    """Every method's decisions ``[M, T]`` on ``z_test [M, T, Dz]``, its CPU ms/decision and,
    for a method that returns log probabilities, the ``[M, T, K]`` mask of its 90% credible
    sets."""
    out = []
    for name, run in tqdm(jobs, disable=not progress, desc="methods", leave=False):
        start = time.process_time()
        result = run(z_test)
        seconds = time.process_time() - start
        credible = None
        if result.is_floating_point():
            credible = IntentionBelief(result.exp(), result, torch.empty(0)).credible_set(0.9)
            result = result.argmax(-1)
        out.append((name, result, 1e3 * seconds / result.numel(), credible))
    return out


def _coverage(credible: torch.Tensor | None, truth: torch.Tensor) -> float | None:
    """% of decisions whose 90% credible set ``[M, T, K]`` holds the true class ``[M]``."""
    if credible is None:
        return None
    hit = credible.gather(-1, truth[:, None, None].expand(-1, credible.shape[1], 1))
    return 100.0 * float(hit.double().mean())


# ------------------------------------------------------------------------------------------
# BasicMotions
# ------------------------------------------------------------------------------------------


def action_recognition(
    *,
    subsample: int = 3,
    latent_dim: int = 3,
    fit_steps: int = 40,
    windows: tuple[int, ...] = (4, 5, 6),
    forgettings: tuple[float, ...] = (0.1, 0.2, 0.3),
    baseline_window: int = 5,
    max_train: int | None = None,
    max_test: int | None = None,
    state_prior: str = "class",
    calibration_folds: int | None = 4,
    alpha4: float = 1.0,
    noise_per_value: bool = True,
    seed: int = 0,
    progress: bool = False,
) -> ResultTable:
    """Run the experiment on BasicMotions; returns a :class:`ResultTable` in the layout of
    Table 3.3.

    Args:
        subsample: keep every n-th frame (3: ~3.3 Hz).
        latent_dim: ``Dx`` of the IDDM (linear measurement kernel, discrete intention).
        fit_steps: L-BFGS steps of the MAP fit.
        windows: batch window sizes.
        forgettings: online ``eps`` values.
        baseline_window: window of SVM, GPC and HMM.
        max_train: use only the first training recordings of each class (smoke runs).
        max_test: use only the first test recordings of each class (smoke runs).
        state_prior: the IDDM's first-state prior, ``"class"`` (default) or ``"marginal"``
            (:func:`~hgpdm_torch.inference.infer_intention`).
        calibration_folds: the IDDM rows' evidence temperatures come from this many stratified
            folds of the training recordings (:func:`_fit_temperatures`; ``meta
            ["temperatures"]``); ``None``: ``T = 1``, the thesis's inference.
        alpha4: the process noise ``alpha_4`` of the IDDM's MAP fit (``alpha = (0.9, 0.3, 0.1,
            alpha4)``).
        noise_per_value: after the fit, give each action its own maximum-likelihood process
            noise ``alpha_4,k`` (``IDDM(noise_per_value=True)``): the activities differ in
            loudness by about two orders of magnitude, and one noise shared by all of them
            makes the transition evidence of a new loud recording favour the wrong action.
            ``alpha4`` and ``noise_per_value`` were chosen by 4-fold cross-validation on the
            training recordings (online IDDM 87.2 +- 2.0 % against the HMM's 86.0 +- 1.9 %;
            with the previous ``alpha4 = 0.01`` and one shared noise, the online IDDM
            reached 60.7 % on the test split). MSRC-12 keeps ``alpha4 = 0.01`` and one noise.
        seed: seed of the model fit, the calibration folds and the baselines.
        progress: tqdm bars.
    """
    z_train, y_train, z_test, y_test, names = load_actions(subsample)
    iddm = {"alpha4": alpha4, "noise_per_value": noise_per_value}

    def first(z: torch.Tensor, y: torch.Tensor, n: int | None):
        if n is None:
            return z, y
        keep = torch.cat([torch.nonzero(y == c).flatten()[:n] for c in range(len(names))])
        return z[keep], y[keep]

    z_train, y_train = first(z_train, y_train, max_train)
    z_test, y_test = first(z_test, y_test, max_test)
    k = len(names)
    model, fit = _fit_iddm(z_train, y_train, k, latent_dim, fit_steps, seed, progress, **iddm)
    temps: dict[str, float] = {}
    inner_fits: list[dict[str, Any]] = []
    if calibration_folds is not None:
        fewest = int(torch.bincount(y_train, minlength=k).min())
        _check_calibration_folds(calibration_folds, fewest, "training recordings of a class")
        folds = StratifiedKFold(calibration_folds, shuffle=True, random_state=seed)
        splits = [
            (z_train[a], y_train[a], z_train[b], y_train[b])
            for a, b in folds.split(z_train[:, 0], y_train)
        ]
        temps, inner_fits = _fit_temperatures(
            splits, k, latent_dim, fit_steps, seed, windows=windows,
            forgettings=forgettings, state_prior=state_prior, progress=progress, **iddm,
        )  # fmt: skip
    table = ResultTable(
        "Table 3.3: action recognition on BasicMotions, accuracy over all decisions",
        ["method", "accuracy [%]", "90% set coverage [%]", "CPU ms/decision"],
        meta={
            "dataset": "basic_motions",
            "classes": names,
            "n_test": len(y_test),
            "frames": z_test.shape[1],
            "subsample": subsample,
            "Dx": latent_dim,
            "state_prior": state_prior,
            "calibration_folds": calibration_folds,
            "temperatures": temps,
            "alpha4": alpha4,
            "noise_per_value": noise_per_value,
            "value_noise": model.value_noise.tolist() if noise_per_value else None,
            "seed": seed,
            "confusion": {},
            "fit": fit.summary(),
            "fits": [fit.summary()],
            "calibration_fits": inner_fits,
        },
    )
    settings = dict(
        windows=windows,
        forgettings=forgettings,
        baseline_window=baseline_window,
        seed=seed,
        state_prior=state_prior,
        temperatures=temps,
    )
    methods = _methods(model, z_train, y_train, table.meta, **settings)
    for name, pred, ms, credible in _decide(methods, z_test, progress):
        acc = 100.0 * float((pred == y_test[:, None]).double().mean())
        cover = _coverage(credible, y_test)
        table.add(
            **{
                "method": name,
                "accuracy [%]": round(acc, 1),
                "90% set coverage [%]": None if cover is None else round(cover, 1),
                "CPU ms/decision": ms,
            }
        )
        table.meta["confusion"][name] = _confusion(pred, y_test[:, None], k).tolist()
    return table


# ------------------------------------------------------------------------------------------
# MSRC-12
# ------------------------------------------------------------------------------------------


def _per_class(
    index: np.ndarray, labels: np.ndarray, n: int | None, rng: np.random.Generator
) -> np.ndarray:
    """At most ``n`` random members of each class among ``index`` (all when ``n`` is None)."""
    if n is None:
        return index
    parts = [rng.permutation(index[labels[index] == c])[:n] for c in np.unique(labels[index])]
    return np.sort(np.concatenate(parts))


def _sem(values: Sequence[float]) -> float | None:
    """Standard error of the mean over folds (None for a single fold)."""
    if len(values) < 2:
        return None
    return float(np.std(values, ddof=1) / np.sqrt(len(values)))


def msrc12_recognition(
    data: MSRC12 | str | Path = MSRC12_DEV,
    *,
    folds: int = 5,
    subsample: int = 3,
    pca: int | float | None = 0.95,
    train_per_class: int | None = 10,
    test_per_class: int | None = None,
    max_persons: int | None = None,
    latent_dim: int = 8,
    fit_steps: int = 100,
    windows: tuple[int, ...] = (4, 5, 6),
    forgettings: tuple[float, ...] = (0.1, 0.2, 0.3),
    baseline_window: int = 5,
    state_prior: str = "class",
    calibration_folds: int | None = 2,
    calibration_per_class: int | None = 20,
    seed: int = 0,
    progress: bool = False,
) -> ResultTable:
    """Table 3.3 on MSRC-12 Kinect gestures with leave-persons-out cross-validation.

    For each of ``folds`` splits of the persons (``GroupKFold``): features
    (:func:`~hgpdm_torch.datasets.kinect_features`, every ``subsample``-th frame counted from
    the action point, so that it is kept), a :class:`~hgpdm_torch.datasets.PosePCA` fitted on
    all frames of the training persons, then ``train_per_class`` random training instances of
    each gesture to fit the IDDM and the baselines, and decisions after every frame of (up to
    ``test_per_class`` random instances per gesture of) the test persons.

    The defaults ``latent_dim = 8``, ``state_prior = "class"`` and ``fit_steps = 100`` were
    chosen on the first fold of the development persons (on it, the full-window batch accuracy
    was 61% with ``Dx = 5`` and the marginal prior, 70% with the class prior, 76% with
    ``Dx = 8`` and the class prior; ``Dx = 3`` and ``Dx = Dz`` were worse), not by nested
    cross-validation: they carry a small optimistic bias.

    Args:
        data: :class:`~hgpdm_torch.datasets.MSRC12` instances, or a path: an ``.npz`` archive
            (:func:`~hgpdm_torch.datasets.load_msrc12_npz`) or a folder of original recordings
            (:func:`~hgpdm_torch.datasets.load_msrc12_folder`, 10 frames/s, 3 s before to 0.5 s
            after the action point).
        folds: number of person folds (at least 2, at most the number of persons).
        subsample: keep every n-th frame (3: ~3.3 Hz at 10 frames/s, as in the thesis).
        pca: :class:`~hgpdm_torch.datasets.PosePCA` ``dim`` (components, variance fraction,
            or None for the 57 centred coordinates).
        train_per_class: training instances per gesture and fold (None: all).
        test_per_class: test instances per gesture and fold (None: all).
        max_persons: use only the first persons (sorted ids; smoke runs).
        latent_dim: ``Dx`` of the IDDM (at most the fold's PCA dimension ``Dz``: the latent
            states start from a PCA of the observations); fit_steps: its L-BFGS steps.
        windows: as :func:`action_recognition`.
        forgettings: as :func:`action_recognition`.
        baseline_window: as :func:`action_recognition`.
        state_prior: as :func:`action_recognition`.
        calibration_folds: the IDDM rows' evidence temperatures of each fold come from this
            many person folds of its training persons (:func:`_fit_temperatures`: for each,
            a PCA and an IDDM on ``train_per_class`` instances per gesture of the other
            training persons, beliefs on up to ``calibration_per_class`` instances per gesture
            of the held-out ones); ``None``: ``T = 1``, the thesis's inference.
        seed: seed of the instance subsets, the fits and the baselines.
        progress: tqdm bars.

    Returns:
        :class:`ResultTable`: per method the accuracy over all decisions and at the last frame
        of each instance (means over folds [%], with their SEM) and the CPU ms per decision.
        ``meta``: ``confusion`` / ``confusion_end`` (summed over folds), ``per_fold``
        accuracies, ``folds`` (persons, sizes, PCA dimension, fit summary and evidence
        temperatures of each fold), ``fits`` (the ``FitResult.summary()`` of every IDDM fit) and
        ``calibration_fits`` (of the calibration splits' fits).

    Raises:
        ValueError: bad ``folds`` (fewer than 2 or more than the persons), or a training fold
            without some gesture.
    """
    if not isinstance(data, MSRC12):
        path = Path(data)
        data = load_msrc12_folder(path) if path.is_dir() else load_msrc12_npz(path)
    if max_persons is not None:
        data = data.subset(np.isin(data.person, data.persons[:max_persons]))
    persons = np.array(data.person)
    if not (isinstance(folds, int) and 2 <= folds <= len(data.persons)):
        raise ValueError(f"folds must be an int in [2, {len(data.persons)}] (persons), got {folds}")
    k, labels = data.num_classes, data.labels.numpy()
    start = data.action_frame % subsample
    features = kinect_features(data.positions)[:, start::subsample]
    rng = np.random.default_rng(seed)
    columns = [
        "method",
        "accuracy [%]",
        "SEM",
        "end accuracy [%]",
        "end SEM",
        "90% set coverage [%]",
        "CPU ms/decision",
    ]
    table = ResultTable(
        f"Table 3.3: action recognition on MSRC-12 Kinect gestures, leave-persons-out CV "
        f"({folds} folds), accuracy over all decisions and at the end of each instance",
        columns,
        meta={
            "dataset": "msrc12",
            "classes": list(data.names),
            "gesture_ids": list(data.gesture_ids),
            "persons": len(data.persons),
            "instances": len(data),
            "frames": features.shape[1],
            "subsample": subsample,
            "fps": data.fps / subsample,
            "pca": pca,
            "Dx": latent_dim,
            "state_prior": state_prior,
            "calibration_folds": calibration_folds,
            "calibration_per_class": calibration_per_class,
            "fit_steps": fit_steps,
            "train_per_class": train_per_class,
            "test_per_class": test_per_class,
            "seed": seed,
            "folds": [],
            "fits": [],
            "calibration_fits": [],
            "confusion": {},
            "confusion_end": {},
            "per_fold": {},
        },
    )
    results: dict[str, dict[str, list[float]]] = {}
    splits = list(GroupKFold(n_splits=folds).split(features, groups=data.groups()))
    settings = dict(
        windows=windows,
        forgettings=forgettings,
        baseline_window=baseline_window,
        seed=seed,
        state_prior=state_prior,
    )
    if calibration_folds is not None:
        fewest = min(len(set(persons[train].tolist())) for train, _ in splits)
        _check_calibration_folds(calibration_folds, fewest, "training persons of a fold")
        if calibration_per_class is not None and not (
            isinstance(calibration_per_class, int) and calibration_per_class >= 1
        ):
            raise ValueError(
                "calibration_per_class must be a positive int or None, got "
                f"{calibration_per_class!r}"
            )
    for fold, (train, test) in enumerate(tqdm(splits, disable=not progress, desc="folds")):
        shared = set(persons[train]) & set(persons[test])
        if shared:  # GroupKFold guarantees this; the table's validity rests on it
            raise RuntimeError(f"fold {fold} shares persons {sorted(shared)}")
        missing = sorted(set(range(k)) - set(labels[train].tolist()))
        if missing:
            lacking = [data.names[c] for c in missing]
            raise ValueError(f"fold {fold}: no training instance of {lacking}")
        prep = PosePCA(pca).fit(features[train])
        z = prep.transform(features)
        train_set = _per_class(train, labels, train_per_class, rng)
        test_set = _per_class(test, labels, test_per_class, rng)
        z_train, y_train = z[train_set], data.labels[train_set]
        z_test, y_test = z[test_set], data.labels[test_set]
        dx = min(latent_dim, prep.dim_)
        model, fit = _fit_iddm(z_train, y_train, k, dx, fit_steps, seed, progress)
        table.meta["fits"].append(fit.summary())
        temps: dict[str, float] = {}
        if calibration_folds is not None:
            inner_rng = np.random.default_rng([seed, fold])  # the outer subsets stay as they were
            inner_splits = []
            for a, b in GroupKFold(n_splits=calibration_folds).split(train, groups=persons[train]):
                lacking = sorted(set(range(k)) - set(labels[train[a]].tolist()))
                if lacking:
                    raise ValueError(
                        f"fold {fold}: a calibration split has no training instance of "
                        f"{[data.names[c] for c in lacking]}; use fewer calibration_folds"
                    )
                inner_prep = PosePCA(pca).fit(features[train[a]])
                zi = inner_prep.transform(features)
                fit_set = _per_class(train[a], labels, train_per_class, inner_rng)
                val_set = _per_class(train[b], labels, calibration_per_class, inner_rng)
                inner_splits.append(
                    (zi[fit_set], data.labels[fit_set], zi[val_set], data.labels[val_set])
                )
            temps, inner_fits = _fit_temperatures(
                inner_splits, k, latent_dim, fit_steps, seed, windows=windows,
                forgettings=forgettings, state_prior=state_prior, progress=progress,
            )  # fmt: skip
            table.meta["calibration_fits"] += inner_fits
        table.meta["folds"].append(
            {
                "test persons": sorted(set(persons[test].tolist())),
                "train persons": sorted(set(persons[train].tolist())),
                "n_train": len(train_set),
                "n_test": len(test_set),
                "Dz": prep.dim_,
                "Dx": dx,
                "explained variance": None
                if prep.explained_variance_ratio_ is None
                else round(float(sum(prep.explained_variance_ratio_)), 4),
                "fit": fit.summary(),
                "temperatures": temps,
            }
        )
        methods = _methods(model, z_train, y_train, table.meta, temperatures=temps, **settings)
        for name, pred, ms, credible in _decide(methods, z_test, progress):
            r = results.setdefault(name, {"all": [], "end": [], "ms": [], "cover": []})
            r["all"].append(100.0 * float((pred == y_test[:, None]).double().mean()))
            r["end"].append(100.0 * float((pred[:, -1] == y_test).double().mean()))
            r["ms"].append(ms)
            r["cover"].append(_coverage(credible, y_test))
            for key, p, truth in (
                ("confusion", pred, y_test[:, None]),
                ("confusion_end", pred[:, -1:], y_test[:, None]),
            ):
                m = _confusion(p, truth, k)
                old = table.meta[key].get(name)
                table.meta[key][name] = (m if old is None else np.asarray(old) + m).tolist()
    for name, r in results.items():
        sem, sem_end = _sem(r["all"]), _sem(r["end"])
        table.add(
            **{
                "method": name,
                "accuracy [%]": round(float(np.mean(r["all"])), 1),
                "SEM": None if sem is None else round(sem, 1),
                "end accuracy [%]": round(float(np.mean(r["end"])), 1),
                "end SEM": None if sem_end is None else round(sem_end, 1),
                "90% set coverage [%]": None
                if r["cover"][0] is None
                else round(float(np.mean(r["cover"])), 1),
                "CPU ms/decision": float(np.mean(r["ms"])),
            }
        )
        table.meta["per_fold"][name] = {key: r[key] for key in ("all", "end")}
    return table


# ------------------------------------------------------------------------------------------
# Figure and command line
# ------------------------------------------------------------------------------------------


def confusion_figure(table: ResultTable, key: str = "confusion") -> Figure:
    """One row-normalised confusion matrix per method (rows true, columns predicted).

    Uses ``matplotlib.figure.Figure`` directly (no pyplot, the backend is left alone).

    Args:
        table: a table of this module (``meta["classes"]`` and ``meta[key]``).
        key: ``"confusion"`` (all decisions) or, for MSRC-12, ``"confusion_end"``.

    Returns:
        The ``matplotlib.figure.Figure``; save it with ``fig.savefig(path)``.
    """
    from matplotlib.figure import Figure

    names, mats = table.meta["classes"], table.meta[key]
    cols = min(4, len(mats))
    rows = -(-len(mats) // cols)
    size = 0.45 * len(names) + 1.6
    fig = Figure(figsize=(cols * size, rows * size + 0.4), layout="constrained")
    axes = fig.subplots(rows, cols, squeeze=False)
    ticks = range(len(names))
    for ax, (method, counts) in zip(axes.flat, mats.items(), strict=False):
        m = np.asarray(counts, dtype=float)
        m = m / np.maximum(m.sum(1, keepdims=True), 1)
        ax.imshow(m, vmin=0, vmax=1, cmap="Blues")
        for i in ticks:
            for j in ticks:
                ax.text(
                    j,
                    i,
                    f"{100 * m[i, j]:.0f}",
                    ha="center",
                    va="center",
                    fontsize=7,
                    color="white" if m[i, j] > 0.5 else "black",
                )
        ax.set_title(method, fontsize=9)
        ax.set_xticks(ticks, names, rotation=90, fontsize=7)
        ax.set_yticks(ticks, names, fontsize=7)
    for ax in list(axes.flat)[len(mats) :]:
        ax.axis("off")
    fig.suptitle(f"{table.title}\n(% of each true class; rows true, columns predicted)", fontsize=9)
    return fig


def _data_path(text: str) -> Path:
    """``--data``: an existing ``.npz`` file or folder."""
    path = Path(text)
    if path.is_dir() or (path.is_file() and path.suffix == ".npz"):
        return path
    if path.exists():
        raise argparse.ArgumentTypeError(f"{text} is neither an .npz file nor a folder")
    raise argparse.ArgumentTypeError(f"{text} does not exist")


def main(argv: list[str]) -> int:
    """``hgpdm action-recognition [--dataset basic_motions|msrc12] [--data PATH] [--folds N]
    [--quick] [--out results.json] [--figure confusion.png] [--seed N]``."""
    parser = argparse.ArgumentParser(
        prog="hgpdm action-recognition",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("--dataset", choices=DATASETS, default="basic_motions")
    parser.add_argument(
        "--data", type=_data_path, help=f"msrc12: .npz archive or folder (default {MSRC12_DEV})"
    )
    parser.add_argument(
        "--folds", type=int_at_least(2), help="msrc12: leave-persons-out folds (default 5)"
    )
    parser.add_argument(
        "--train-per-class",
        type=int_at_least(1),
        help="msrc12: training instances per gesture, fold (default 10)",
    )
    parser.add_argument(
        "--test-per-class",
        type=int_at_least(1),
        help="msrc12: test instances per gesture, fold (default all)",
    )
    parser.add_argument(
        "--latent-dim", type=int_at_least(1), help="Dx of the IDDM (default 3; msrc12: 8)"
    )
    parser.add_argument(
        "--state-prior",
        choices=STATE_PRIORS,
        default="class",
        help="the IDDM's prior of a window's first state (default class)",
    )
    parser.add_argument(
        "--no-calibration",
        action="store_true",
        help="evidence temperature 1 (the thesis's inference) instead of one fitted by "
        "cross-validation within the training data",
    )
    parser.add_argument("--quick", action="store_true", help="small smoke-test sizes")
    parser.add_argument("--out", type=output_file, help="write the table as JSON")
    parser.add_argument("--figure", type=output_file, help="save the confusion matrices")
    parser.add_argument("--seed", type=random_seed, default=0)
    args = parser.parse_args(argv)
    quick = args.quick or os.environ.get("HGPDM_SMOKE") == "1"
    msrc12_only = ("data", "folds", "train_per_class", "test_per_class")
    given = [f"--{o.replace('_', '-')}" for o in msrc12_only if getattr(args, o) is not None]
    if args.dataset == "basic_motions" and given:
        parser.error(f"{', '.join(given)} apply to --dataset msrc12 only")
    if args.dataset == "msrc12" and args.data is None:
        if not Path(MSRC12_DEV).is_file():
            parser.error(f"--dataset msrc12 needs --data (the default {MSRC12_DEV} is absent)")
        args.data = Path(MSRC12_DEV)
    if args.dataset == "basic_motions":
        kwargs: dict[str, Any] = (
            {
                "fit_steps": 10,
                "windows": (4,),
                "forgettings": (0.2,),
                "max_train": 3,
                "max_test": 2,
                "subsample": 5,
            }
            if quick
            else {}
        )
        if args.latent_dim is not None:
            kwargs["latent_dim"] = args.latent_dim
        if args.no_calibration:
            kwargs["calibration_folds"] = None
        elif quick:
            kwargs["calibration_folds"] = 2
        table = action_recognition(
            seed=args.seed, state_prior=args.state_prior, progress=not quick, **kwargs
        )
    else:
        kwargs = {
            "latent_dim": args.latent_dim or 8,
            "state_prior": args.state_prior,
            "folds": args.folds or 5,
            "train_per_class": args.train_per_class or 10,
            "test_per_class": args.test_per_class,
            "calibration_folds": None if args.no_calibration else 2,
        }
        if quick:
            kwargs.update(
                folds=2,
                max_persons=4,
                train_per_class=2,
                test_per_class=1,
                fit_steps=5,
                windows=(4,),
                forgettings=(0.2,),
                subsample=6,
                calibration_per_class=1,
            )
        table = msrc12_recognition(args.data, seed=args.seed, progress=not quick, **kwargs)
        table.meta["data"] = str(args.data)
    print(table.to_markdown())
    if args.out:
        table.to_json(args.out)
    if args.figure:
        confusion_figure(table).savefig(args.figure, dpi=120)
    return 0
