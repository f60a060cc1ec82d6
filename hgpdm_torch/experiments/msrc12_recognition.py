"""Action recognition on MSRC-12 Kinect gestures (thesis Sec. 3.6, Table 3.3's methods):
leave-persons-out cross-validation over the development archive or the original recordings
(``hgpdm action-recognition --dataset msrc12``)."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from sklearn.model_selection import GroupKFold

from ..datasets.kinect_features import PosePCA, kinect_features
from ..datasets.msrc12 import MSRC12, load_msrc12_folder, load_msrc12_npz
from ..progress import tqdm
from ..results import ResultTable
from .action_methods import TableRows, check_calibration_folds, confusion, coverage, run_fold
from .intervals import mean_sem

if TYPE_CHECKING:
    import torch

__all__ = ["MSRC12_DEV", "msrc12_recognition"]

MSRC12_DEV = "../shared/data/msrc12_dev.npz"
"""The shared development archive, relative to the project root."""


def _per_class(
    index: np.ndarray, labels: np.ndarray, n: int | None, rng: np.random.Generator
) -> np.ndarray:
    """At most ``n`` random members of each class among ``index`` (all when ``n`` is None)."""
    if n is None:
        return index
    parts = [rng.permutation(index[labels[index] == c])[:n] for c in np.unique(labels[index])]
    return np.sort(np.concatenate(parts))


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
            many person folds of its training persons (:func:`fit_temperatures`: for each,
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
    rows = TableRows(windows, forgettings, baseline_window, state_prior, seed)
    if calibration_folds is not None:
        fewest = min(len(set(persons[train].tolist())) for train, _ in splits)
        check_calibration_folds(calibration_folds, fewest, "training persons of a fold")
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
        inner_splits = None
        if calibration_folds is not None:
            inner_splits = _calibration_splits(
                data, features, train, fold, pca, calibration_folds, train_per_class,
                calibration_per_class, seed,
            )  # fmt: skip
        # the calibration IDDMs take latent_dim, each clipped to its own split's PCA
        run = run_fold(
            z_train, y_train, z_test, k, dx, fit_steps, rows, table.meta,
            splits=inner_splits, calibration_dim=latent_dim, progress=progress,
        )  # fmt: skip
        fit = run.fit
        table.meta["fits"].append(fit.summary())
        table.meta["calibration_fits"] += run.calibration_fits
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
                "temperatures": run.temperatures,
            }
        )
        for name, pred, ms, credible in run.decisions:
            _record(results, table.meta, name, pred, ms, credible, y_test, k)
    for name, r in results.items():
        sem, sem_end = mean_sem(r["all"])[1], mean_sem(r["end"])[1]
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


def _calibration_splits(
    data: MSRC12, features: torch.Tensor, train: np.ndarray, fold: int, pca: Any,
    calibration_folds: int, train_per_class: int | None, calibration_per_class: int | None,
    seed: int,
) -> list[tuple[torch.Tensor, ...]]:  # fmt: skip
    """The calibration splits of outer fold ``fold`` (its training instances ``train``):
    ``calibration_folds`` person folds, each with its own PCA fitted on its fitting persons,
    ``(z_fit, y_fit, z_val, y_val)`` of balanced subsets (:func:`fit_temperatures`)."""
    k, labels, persons = data.num_classes, data.labels.numpy(), np.array(data.person)
    inner_rng = np.random.default_rng([seed, fold])  # the outer subsets stay as they were
    inner_splits = []
    for a, b in GroupKFold(n_splits=calibration_folds).split(train, groups=persons[train]):
        lacking = sorted(set(range(k)) - set(labels[train[a]].tolist()))
        if lacking:
            raise ValueError(
                f"fold {fold}: a calibration split has no training instance of "
                f"{[data.names[c] for c in lacking]}; use fewer calibration_folds"
            )
        zi = PosePCA(pca).fit(features[train[a]]).transform(features)
        fit_set = _per_class(train[a], labels, train_per_class, inner_rng)
        val_set = _per_class(train[b], labels, calibration_per_class, inner_rng)
        inner_splits.append((zi[fit_set], data.labels[fit_set], zi[val_set], data.labels[val_set]))
    return inner_splits


def _record(
    results: dict[str, dict[str, list]], meta: dict[str, Any], name: str, pred: torch.Tensor,
    ms: float, credible: torch.Tensor | None, y_test: torch.Tensor, k: int,
) -> None:  # fmt: skip
    """One method's decisions ``pred [M, T]`` on a fold's test instances: its accuracies (all
    decisions, the last), CPU time and coverage into ``results[name]``, its confusion matrices
    added into ``meta``."""
    r = results.setdefault(name, {"all": [], "end": [], "ms": [], "cover": []})
    r["all"].append(100.0 * float((pred == y_test[:, None]).double().mean()))
    r["end"].append(100.0 * float((pred[:, -1] == y_test).double().mean()))
    r["ms"].append(ms)
    r["cover"].append(coverage(credible, y_test))
    for key, p, truth in (
        ("confusion", pred, y_test[:, None]),
        ("confusion_end", pred[:, -1:], y_test[:, None]),
    ):
        m = confusion(p, truth, k)
        old = meta[key].get(name)
        meta[key][name] = (m if old is None else np.asarray(old) + m).tolist()


# ------------------------------------------------------------------------------------------
# Figure and command line
# ------------------------------------------------------------------------------------------
