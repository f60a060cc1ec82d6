"""Cross-validation folds and the held-out loop that every selection of the toolkit runs.

A selection by cross-validation (:func:`~hgpdm_torch.model_selection.cross_validate` over model
options, :class:`~hgpdm_torch.models.LinearIDDM`'s belief options, the evidence temperatures of
the action-recognition rows, the IDDM configuration of the target prediction) splits the training
items into folds, fits each candidate on the training part of every fold, evaluates it on the
held-out part and keeps the candidate whose pooled held-out score is best. The pieces they share
live here:

- the folds: :func:`interleaved_folds` (item ``j`` held out in fold ``j mod k``),
  :func:`contiguous_folds` (runs of consecutive items) or any scikit-learn splitter through
  :func:`checked_splits` (grouped and checked: no group on both sides, no empty part, every
  class of a discrete label trained on);
- the loop: :func:`held_out` runs ``fit_predict(fold, train, test)`` for every fold (or, for
  folds that carry their own data, ``fit_predict(fold, *data)``), with a progress bar and the
  fold named in any error; in this process, or on an :class:`~hgpdm_torch.parallel.Executor`
  (local processes, a Ray cluster) with the same results in the same order;
- the choice: :func:`best_index` (the first best score; ties go to the earlier candidate).

A split is a pair ``(train, test)`` of lists of item indices.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterator, Sequence
from typing import Any, TypeVar

import numpy as np

from . import settings
from .parallel import Executor
from .progress import tqdm

__all__ = [
    "Split",
    "best_index",
    "checked_splits",
    "contiguous_folds",
    "held_out",
    "interleaved_folds",
]

Split = tuple[list[int], list[int]]
Out = TypeVar("Out")


def _check_folds(num: int, folds: int) -> None:
    if isinstance(folds, bool) or not isinstance(folds, int) or not 2 <= folds <= num:
        raise ValueError(f"folds must be an int in [2, {num}] (the number of items), got {folds!r}")


def interleaved_folds(num: int, folds: int) -> list[Split]:
    """``folds`` splits of ``num`` items, item ``j`` held out in split ``j mod folds``.

    Raises:
        ValueError: ``folds`` not an int in ``[2, num]``.
    """
    _check_folds(num, folds)
    return [
        ([j for j in range(num) if j % folds != k], [j for j in range(num) if j % folds == k])
        for k in range(folds)
    ]


def contiguous_folds(num: int, folds: int) -> list[Split]:
    """``folds`` splits of ``num`` items into runs of consecutive items, the first ``num mod
    folds`` runs one item longer (the sizes of ``torch.tensor_split``).

    Raises:
        ValueError: ``folds`` not an int in ``[2, num]``.
    """
    _check_folds(num, folds)
    size, extra = divmod(num, folds)
    out, start = [], 0
    for k in range(folds):
        stop = start + size + (k < extra)
        out.append(([*range(start), *range(stop, num)], list(range(start, stop))))
        start = stop
    return out


def checked_splits(
    splitter: Any, groups: np.ndarray, labels: np.ndarray | None = None, discrete: bool = False
) -> list[Split]:
    """The splits of a scikit-learn ``splitter`` over ``groups [J]`` (``labels [J]`` as its
    ``y``), checked: both parts non-empty, no group on both sides and, for integer labels of a
    discrete g (``discrete``), every test class present in the training part.

    Raises:
        ValueError: no split, an empty part, a group on both sides, or a test class that is not
            trained on (each naming the fold and what to use instead).
    """
    num = groups.shape[0]
    y = labels if labels is not None and labels.ndim == 1 else None
    splits = [
        (np.asarray(train).tolist(), np.asarray(test).tolist())
        for train, test in splitter.split(np.zeros((num, 1)), y, groups)
    ]
    if not splits:
        raise ValueError(f"splitter {splitter!r} produced no folds")
    check_classes = discrete and y is not None and np.issubdtype(y.dtype, np.integer)
    for k, (train, test) in enumerate(splits):
        if not train or not test:
            raise ValueError(f"fold {k} of {splitter!r} has an empty training or test part")
        shared = set(groups[train].tolist()) & set(groups[test].tolist())
        if shared:
            raise ValueError(
                f"fold {k} of {splitter!r} puts groups {sorted(shared)} in both the training and "
                "the test part; use a group splitter (LeaveOneGroupOut, GroupKFold, ...)"
            )
        missing = set(y[test].tolist()) - set(y[train].tolist()) if check_classes else set()
        if missing:
            raise ValueError(
                f"fold {k}: labels {sorted(missing)} occur in the test part but not in the "
                "training part, so a discrete-g model cannot represent them; group the splits "
                "so that every class is trained on (e.g. StratifiedGroupKFold)"
            )
    return splits


def held_out(
    splits: Sequence[tuple[Any, ...]],
    fit_predict: Callable[..., Out],
    *,
    executor: Executor | None = None,
    progress: bool = False,
    desc: str = "folds",
    context: str = "",
    item: str = "fold",
) -> list[Out]:
    """``[fit_predict(k, *split) for k, split in enumerate(splits)]``.

    For index splits ``(train, test)``, ``fit_predict(k, train, test)`` fits on the items
    ``train`` and evaluates on the held-out items ``test`` of fold ``k`` (whatever it returns:
    scores, predictions, log beliefs); folds that carry their own data (e.g. features whose PCA
    was fitted on the fold's training part) pass it instead. An error ``fit_predict`` raises
    gets a note naming the fold (and ``context``, e.g. the candidate).

    Args:
        splits: the folds, e.g. from :func:`interleaved_folds` or :func:`checked_splits`, or
            tuples of each fold's data.
        fit_predict: ``(fold index, *split) -> result``.
        executor: run the folds on it (:func:`~hgpdm_torch.parallel.get_executor`: local
            processes or a Ray cluster), the results still in fold order: the same as here for a
            ``fit_predict`` whose randomness is its own (e.g. seeded per fold). ``fit_predict``
            and the splits must then pickle (a module-level function or a ``functools.partial``
            of one; Ray also takes closures). Every fold runs in this process's toolkit settings
            and default dtype (:func:`~hgpdm_torch.settings.snapshot`), which a worker does not
            inherit; any other process-wide state it must not read (see
            :mod:`hgpdm_torch.parallel`). ``None``: one after the other in this process.
        progress: show a progress bar over the folds.
        desc: the bar's label.
        context: what the error note names besides the fold.
        item: what the note calls the ``k``-th split (default ``"fold"``).
    """
    jobs, fold = list(enumerate(splits)), _Fold(fit_predict, settings.snapshot())
    results: Iterator[Out] = map(fold, jobs) if executor is None else executor.map(fold, jobs)
    out = []
    for k in tqdm(range(len(jobs)), disable=not progress, desc=desc, leave=False):
        try:
            out.append(next(results))
        except Exception as err:
            err.add_note(f"cross-validation: {context + ', ' if context else ''}{item} {k}")
            raise
    return out


class _Fold:
    """``(k, split) -> fit_predict(k, *split)`` in the caller's settings: one fold as an
    executor's job (picklable whenever ``fit_predict`` is)."""

    def __init__(self, fit_predict: Callable[..., Any], snap: settings.Snapshot) -> None:
        self.fit_predict, self.snap = fit_predict, snap

    def __call__(self, job: tuple[int, tuple[Any, ...]]) -> Any:
        k, split = job
        with self.snap.applied():
            return self.fit_predict(k, *split)


def best_index(scores: Sequence[float], greater_is_better: bool = False) -> int:
    """The index of the best of ``scores`` (lowest, or highest with ``greater_is_better``); ties
    go to the earliest.

    Raises:
        ValueError: no score, or a score that is NaN.
    """
    values = np.asarray(scores, dtype=float)
    if values.size == 0:
        raise ValueError("best_index needs at least one score")
    if any(math.isnan(v) for v in values.tolist()):
        raise ValueError(f"scores must not be NaN, got {values.tolist()}")
    return int(np.argmax(values) if greater_is_better else np.argmin(values))
