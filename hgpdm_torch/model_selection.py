"""Cross-validation over model options with splits grouped by sequence, trial or person.

:func:`cross_validate` fits a model class (:class:`~hgpdm_torch.models.GPDM`, ``HGPDM``, ``IDDM``
or a subclass) once per option set of a grid and per split of the sequences, scores every fit on
its held-out sequences and returns a :class:`CVResult`: a :class:`ResultTable` with one row per
option set (mean score, its standard error across folds, fits that did not converge), the
per-fold scores and the best option set. Splits come from any scikit-learn group splitter
(``LeaveOneGroupOut``, ``GroupKFold``, ``LeavePGroupsOut``, ``StratifiedGroupKFold``), so that no
trial or person contributes to both the training and the test part of a fold
(docs/design/evaluation.md#cross-validation-grouped-by-trial-or-person).

:func:`forecast_rmse` builds the score of the thesis's forecasting protocol (Tables 2.1-2.4):
the RMSE of VB next-frame forecasts over sliding windows of the test sequences.

Example:
    >>> from sklearn.model_selection import GroupKFold                     # doctest: +SKIP
    >>> cv = cross_validate(HGPDM, data.sequences, forecast_rmse(5), labels=data.labels,
    ...                     groups=person, grid={"latent_dim": [2, 3, 4]},
    ...                     splitter=GroupKFold(3), fit_steps=60)          # doctest: +SKIP
    >>> print(cv.table); cv.best_options                                 # doctest: +SKIP
"""

from __future__ import annotations

import inspect
import math
import warnings
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from functools import partial
from typing import Any

import numpy as np
import torch
from sklearn.model_selection import LeaveOneGroupOut, ParameterGrid

from .crossval import best_index, checked_splits, held_out
from .fitting import ConvergenceWarning
from .inference.variational import VariationalInference
from .parallel import Executor
from .results import ResultTable
from .validation import as_tensor

__all__ = ["CVResult", "cross_validate", "forecast_rmse"]

# score(fitted model, test sequences [T_j, Dz], their labels or None) -> float
Score = Callable[[Any, list[torch.Tensor], Any], float]


@dataclass
class CVResult:
    """What :func:`cross_validate` found.

    Attributes:
        table: one row per option set: the grid options, ``score`` (mean over folds), ``sem``
            (standard error of that mean across folds; ``None`` with a single fold), ``folds``
            and ``not converged`` (fits whose result said ``converged=False``). ``meta`` holds
            the settings (model class, fixed options, splitter, fit steps, seed) and, under
            ``"fits"``, per option set and fold the fit's ``converged``, ``reason`` and
            ``final_loss`` (``None`` where ``fit`` returned a bare loss history).
        options: the option sets, in the order of the table rows.
        fold_scores: ``[option set][fold]`` scores.
        splits: ``(train, test)`` sequence indices of each fold.
        best_options: the option set with the best mean score (the first one on ties).
        best_score: its mean score.
        greater_is_better: whether a higher score is better.
    """

    table: ResultTable
    options: list[dict[str, Any]]
    fold_scores: list[list[float]]
    splits: list[tuple[list[int], list[int]]]
    best_options: dict[str, Any]
    best_score: float
    greater_is_better: bool

    def __str__(self) -> str:
        return str(self.table)


def _constructor_parameters(model_class: type) -> tuple[str, dict[str, Any], bool]:
    """Keyword arguments ``model_class(...)`` accepts, with defaults.

    Walks the MRO while ``__init__`` forwards ``**kwargs`` (an ``HGPDM`` passes ``measurement``
    on to ``GPDM.__init__``). Returns the name of the first (data) parameter, the named
    parameters and whether any keyword remains acceptable (``**kwargs`` never closed).
    """
    data_name, params = None, {}
    for cls in model_class.__mro__:
        if "__init__" not in vars(cls):
            continue
        signature = inspect.signature(vars(cls)["__init__"])
        named = [
            p
            for p in list(signature.parameters.values())[1:]
            if p.kind not in (p.VAR_POSITIONAL, p.VAR_KEYWORD)
        ]
        if data_name is None and named:
            data_name = named[0].name
        for p in named:
            params.setdefault(p.name, p.default)
        if not any(p.kind is p.VAR_KEYWORD for p in signature.parameters.values()):
            return data_name or "sequences", params, False
    return data_name or "sequences", params, True


def _check_options(
    grid: Mapping[str, Sequence[Any]],
    fixed: Mapping[str, Any],
    allowed: dict[str, Any],
    reserved: set[str],
    open_kwargs: bool,
    model_class: type,
) -> None:
    for arg, mapping in (("grid", grid), ("fixed", fixed)):
        if not isinstance(mapping, Mapping):
            raise TypeError(
                f"{arg} must be a mapping of option names, got {type(mapping).__name__}"
            )
        for name in mapping:
            if not isinstance(name, str):
                raise TypeError(f"{arg} keys must be option names (str), got {name!r}")
            if name in reserved:
                raise ValueError(
                    f"{arg}[{name!r}] is supplied by cross_validate from the data; remove it"
                )
            if not open_kwargs and name not in allowed:
                raise ValueError(
                    f"unknown option {name!r} in {arg} for {model_class.__name__}; expected "
                    f"one of {', '.join(sorted(set(allowed) - reserved))}"
                )
    for name, values in grid.items():
        if isinstance(values, str | bytes) or not isinstance(values, Sequence | np.ndarray):
            raise TypeError(f"grid[{name!r}] must be a list of values, got {values!r}")
        if len(values) == 0:
            raise ValueError(f"grid[{name!r}] is empty; give at least one value")
    both = sorted(set(grid) & set(fixed))
    if both:
        raise ValueError(f"options {both} are in both grid and fixed; keep each in one")


def _as_index_array(values: Any, name: str, count: int) -> np.ndarray:
    """Per-sequence labels or groups as a NumPy array with ``count`` rows."""
    array = np.asarray(values.detach().cpu() if isinstance(values, torch.Tensor) else values)
    if array.ndim == 0 or array.shape[0] != count:
        raise ValueError(
            f"{name} must have one entry per sequence ({count}), got shape {array.shape}"
        )
    return array


def _subset(labels: Any, label_array: np.ndarray | None, index: list[int]) -> Any:
    """Rows ``index`` of ``labels``: a tensor stays a tensor, anything else a NumPy array."""
    if labels is None:
        return None
    if isinstance(labels, torch.Tensor):
        return labels[torch.as_tensor(index, device=labels.device)]
    return label_array[index]


def _cell(value: Any) -> Any:
    """A table cell that JSON can hold: scalars as they are, anything else as its repr."""
    if isinstance(value, np.generic):
        value = value.item()
    return value if value is None or isinstance(value, bool | int | float | str) else repr(value)


def _fit_report(fit: Any) -> dict[str, Any]:
    """``converged``, ``reason`` and ``final_loss`` of a ``FitResult`` or a loss history."""
    if hasattr(fit, "converged"):
        return {
            "converged": bool(fit.converged),
            "reason": str(fit.reason),
            "final_loss": float(fit.final_loss),
        }
    history = list(fit) if fit is not None else []
    return {
        "converged": None,
        "reason": None,
        "final_loss": float(history[-1]) if history else None,
    }


def cross_validate(
    model_class: type,
    sequences: Sequence[Any] | torch.Tensor,
    score: Score,
    *,
    labels: Any = None,
    groups: Any = None,
    grid: Mapping[str, Sequence[Any]] | None = None,
    fixed: Mapping[str, Any] | None = None,
    splitter: Any = None,
    fit_steps: int = 100,
    fit_kwargs: Mapping[str, Any] | None = None,
    greater_is_better: bool = False,
    seed: int = 0,
    executor: Executor | None = None,
    progress: bool = False,
) -> CVResult:
    """Cross-validate a model class over a grid of constructor options with grouped splits.

    For every option set of ``grid`` (expanded by :class:`sklearn.model_selection.ParameterGrid`)
    and every fold of ``splitter``, builds ``model_class(train_sequences, intentions=
    train_labels, **fixed, **options)`` (``intentions`` only for classes that take it), calls
    ``fit(steps=fit_steps, **fit_kwargs)`` after ``torch.manual_seed(seed)`` and records
    ``score(model, test_sequences, test_labels)``. The loop is sequential and deterministic;
    the caller's (CPU) torch random state is restored afterwards. Per-fit ``ConvergenceWarning``\\ s
    are silenced: non-convergence is counted in the table instead.

    Args:
        model_class: the model class, e.g. ``GPDM``, ``HGPDM``, ``IDDM`` or a subclass; its first
            constructor argument takes the training sequences.
        sequences: J sequences ``[T_j, Dz]`` (a list, or a ``[J, T, Dz]`` tensor).
        score: ``score(model, test_sequences, test_labels) -> float`` for a fitted model;
            ``test_labels`` is ``labels`` of the test sequences (``None`` without labels).
            See :func:`forecast_rmse`.
        labels: per-sequence exogenous variable g, ``[J]`` or ``[J, Dg]``; required by classes
            with an ``intentions`` argument (HGPDM, IDDM) and passed to the score in any case.
            Also the ``y`` of the splitter when 1-D (for ``StratifiedGroupKFold``).
        groups: ``[J]`` group ids (trial, person); no group is split across the training and
            test parts of a fold. Default: every sequence its own group.
        grid: option name -> list of values to try, e.g. ``{"latent_dim": [2, 3],
            "measurement": ["rbf", "linear"]}``. Default: the single option set ``{}``.
        fixed: options passed to every model (e.g. ``{"intention": "discrete"}``).
        splitter: a scikit-learn splitter, called as ``splitter.split(X, y, groups)``;
            default ``LeaveOneGroupOut()``.
        fit_steps: optimizer steps per fit (>= 1).
        fit_kwargs: further keyword arguments of ``model.fit`` (e.g. ``{"optimizer": "adam"}``).
        greater_is_better: whether a higher score is better (default: lower, e.g. an RMSE).
        seed: seed set by ``torch.manual_seed`` before building and fitting each model.
        executor: fit the (option set, fold) pairs on it, all at once
            (:func:`~hgpdm_torch.parallel.get_executor`: local processes or a Ray cluster); the
            table is the serial run's, each fit being seeded on its own. ``model_class`` and
            ``score`` must then pickle (a module-level class or function, e.g.
            :func:`forecast_rmse`'s; Ray also takes closures). ``None``: in this process.
        progress: show a progress bar over the fits.

    Returns:
        A :class:`CVResult`.

    Raises:
        TypeError: for a non-class ``model_class``, a non-callable ``score``, a splitter without
            ``split``, non-list grid values, or a score that is not a real number.
        ValueError: for unknown option names (the constructor's keywords, including those it
            forwards through ``**kwargs`` to its base classes), empty grid values, ``fit_steps``
            < 1, ``labels``/``groups`` whose length is not J, fewer than 2 groups, a fold whose
            training part lacks a class of a discrete g that occurs in its test part, a fold
            that puts one group on both sides, or a non-finite score (naming options and fold).
    """
    if not isinstance(model_class, type):
        raise TypeError(f"model_class must be a model class, got {model_class!r}")
    if not callable(score):
        raise TypeError(f"score must be callable as score(model, sequences, labels), got {score!r}")
    if not isinstance(fit_steps, int) or isinstance(fit_steps, bool) or fit_steps < 1:
        raise ValueError(f"fit_steps must be a positive int, got {fit_steps!r}")
    if not isinstance(seed, int) or isinstance(seed, bool):
        raise TypeError(f"seed must be an int, got {seed!r}")
    grid = {} if grid is None else grid
    fixed = {} if fixed is None else fixed
    fit_kwargs = dict(fit_kwargs or {})
    if "steps" in fit_kwargs:
        raise ValueError("fit_kwargs must not contain 'steps'; use fit_steps")
    splitter = LeaveOneGroupOut() if splitter is None else splitter
    if isinstance(splitter, str | bytes) or not callable(getattr(splitter, "split", None)):
        raise TypeError(f"splitter must have a split(X, y, groups) method, got {splitter!r}")

    data_name, params, open_kwargs = _constructor_parameters(model_class)
    takes_labels = "intentions" in params
    reserved = {data_name, "intentions"} if takes_labels else {data_name}
    _check_options(grid, fixed, params, reserved, open_kwargs, model_class)
    option_sets = list(ParameterGrid(dict(grid)))

    if isinstance(sequences, torch.Tensor):
        if sequences.dim() != 3:
            raise ValueError(
                f"sequences as a tensor must have shape [J, T, Dz], got {tuple(sequences.shape)}"
            )
        sequences = list(sequences)
    if isinstance(sequences, str) or not isinstance(sequences, Sequence):
        raise TypeError(
            f"sequences must be a list of [T, Dz] arrays, got {type(sequences).__name__}"
        )
    num = len(sequences)
    if labels is None and takes_labels:
        raise ValueError(f"labels is required: {model_class.__name__} takes intentions")
    label_array = None if labels is None else _as_index_array(labels, "labels", num)
    group_array = np.arange(num) if groups is None else _as_index_array(groups, "groups", num)
    if group_array.ndim != 1:
        raise ValueError(f"groups must be a [J] vector of group ids, got shape {group_array.shape}")
    num_groups = len(np.unique(group_array))
    if num_groups < 2:
        raise ValueError(f"groups must hold at least 2 distinct groups to split, got {num_groups}")

    discrete = takes_labels and any(
        {**params, **fixed, **options}.get("intention", "discrete") == "discrete"
        for options in option_sets
    )
    splits = checked_splits(splitter, group_array, label_array, discrete)

    job = partial(
        _fit_and_score, model_class, sequences, labels, label_array, takes_labels, fixed, score,
        fit_steps, fit_kwargs, seed,
    )  # fmt: skip
    pairs = [(options, k, *split) for options in option_sets for k, split in enumerate(splits)]
    with torch.random.fork_rng(devices=[]):
        results = held_out(
            pairs, job, executor=executor, progress=progress, desc="cross-validate",
            context="cross_validate", item="(option set, fold) pair",
        )  # fmt: skip
    per_set = [results[i : i + len(splits)] for i in range(0, len(results), len(splits))]
    fold_scores = [[value for value, _ in part] for part in per_set]
    fits = [[report for _, report in part] for part in per_set]

    table = ResultTable(
        f"Cross-validation of {model_class.__name__}: mean score over {len(splits)} folds "
        f"({'higher' if greater_is_better else 'lower'} is better)",
        [*grid, "score", "sem", "folds", "not converged"],
        meta={
            "model_class": f"{model_class.__module__}.{model_class.__qualname__}",
            "fixed": {name: _cell(v) for name, v in fixed.items()},
            "splitter": repr(splitter),
            "fit_steps": fit_steps,
            "fit_kwargs": {name: _cell(v) for name, v in fit_kwargs.items()},
            "seed": seed,
            "greater_is_better": greater_is_better,
            "fits": fits,
        },
    )
    means = []
    for options, scores, reports in zip(option_sets, fold_scores, fits, strict=True):
        n = len(scores)
        mean = float(np.mean(scores))
        means.append(mean)
        table.add(
            **{name: _cell(v) for name, v in options.items()},
            score=mean,
            sem=float(np.std(scores, ddof=1) / math.sqrt(n)) if n > 1 else None,
            folds=n,
            **{"not converged": sum(r["converged"] is False for r in reports)},
        )
    best = best_index(means, greater_is_better)
    return CVResult(
        table=table,
        options=option_sets,
        fold_scores=fold_scores,
        splits=splits,
        best_options=dict(option_sets[best]),
        best_score=means[best],
        greater_is_better=greater_is_better,
    )


def _fit_and_score(
    model_class: type,
    sequences: Sequence[Any],
    labels: Any,
    label_array: np.ndarray | None,
    takes_labels: bool,
    fixed: Mapping[str, Any],
    score: Score,
    fit_steps: int,
    fit_kwargs: Mapping[str, Any],
    seed: int,
    pair: int,
    options: dict[str, Any],
    k: int,
    train: list[int],
    test: list[int],
) -> tuple[float, dict[str, Any]]:
    """One fit of :func:`cross_validate`: fold ``k`` of one option set, fitted on ``train`` after
    ``torch.manual_seed(seed)`` and scored on ``test`` (module-level, so that it pickles to an
    executor; ``pair`` is its index among all fits)."""
    context = f"options {options}, fold {k}"
    try:
        data = {"intentions": _subset(labels, label_array, train)} if takes_labels else {}
        torch.manual_seed(seed)
        with warnings.catch_warnings():
            model = model_class([sequences[i] for i in train], **data, **fixed, **options)
            warnings.simplefilter("ignore", ConvergenceWarning)
            fit = model.fit(steps=fit_steps, **fit_kwargs)
            value = score(model, [sequences[i] for i in test], _subset(labels, label_array, test))
    except Exception as err:
        err.add_note(f"cross_validate: {context}")
        raise
    try:
        value = float(value)
    except (TypeError, ValueError, RuntimeError) as err:
        raise TypeError(f"score must return a real number, got {value!r} ({context})") from err
    if not math.isfinite(value):
        raise ValueError(f"score returned {value} for {context}; expected finite")
    return value, _fit_report(fit)


def forecast_rmse(
    window: int = 5, *, stride: int = 1, batch_size: int = 32, **infer_kwargs: Any
) -> Score:
    """A score for :func:`cross_validate`: RMSE of VB next-frame forecasts (lower is better).

    Every test sequence is cut into windows ``z_{i:i+T}`` (``T = window``, every ``stride``
    frames); :meth:`VariationalInference.forecast` predicts ``z_{i+T}`` from each, inferring g
    for an H-GPDM (the "VB H-GPDM" protocol of Tables 2.1-2.4). The score is the root mean
    squared error over all windows and observed dims, in observation units.

    Args:
        window: T, frames per window (>= 2).
        stride: frames between window starts (>= 1).
        batch_size: windows per VB call (bounds the memory of the psi statistics).
        **infer_kwargs: passed to :meth:`VariationalInference.infer` (e.g. ``steps``).

    Returns:
        ``score(model, sequences, labels) -> float``; sequences shorter than ``window + 1``
        frames contribute no window, and a test part without any window raises ``ValueError``.
    """
    for name, value, low in (
        ("window", window, 2),
        ("stride", stride, 1),
        ("batch_size", batch_size, 1),
    ):
        if not isinstance(value, int) or isinstance(value, bool) or value < low:
            raise ValueError(f"{name} must be an int >= {low}, got {value!r}")

    return partial(
        _forecast_rmse, window=window, stride=stride, batch_size=batch_size, **infer_kwargs
    )


def _forecast_rmse(
    model: Any,
    sequences: list[torch.Tensor],
    labels: Any = None,
    *,
    window: int,
    stride: int,
    batch_size: int,
    **infer_kwargs: Any,
) -> float:
    """:func:`forecast_rmse`'s score (module-level, so that it pickles to an executor)."""
    dtype = model.latent.dtype
    seqs = [as_tensor(s, f"sequences[{j}]", ndim=2, dtype=dtype) for j, s in enumerate(sequences)]
    # [W_j, T + 1, Dz]: windows of T frames, each with the frame that follows it
    parts = [s.unfold(0, window + 1, stride).transpose(-1, -2) for s in seqs if len(s) > window]
    if not parts:
        raise ValueError(f"no test sequence has more than window={window} frames to forecast")
    windows = torch.cat(parts)
    vb = VariationalInference(model)
    means = [
        vb.forecast(windows[i : i + batch_size, :window], **infer_kwargs)[0]
        for i in range(0, windows.shape[0], batch_size)
    ]
    return float((torch.cat(means) - windows[:, window]).pow(2).mean().sqrt())
