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
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import torch
from sklearn.model_selection import StratifiedKFold

from ..datasets.basic_motions import load_basic_motions
from ..inference.intention import STATE_PRIORS
from ..results import ResultTable
from .action_methods import TableRows, check_calibration_folds, confusion, coverage, run_fold
from .arguments import int_at_least, output_file, random_seed, smoke_run
from .msrc12_recognition import MSRC12_DEV, msrc12_recognition

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
#: BasicMotions' loader, under the name this experiment has always exported
load_actions = load_basic_motions


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
            folds of the training recordings (:func:`fit_temperatures`; ``meta
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
    z_train, y_train, z_test, y_test, names = load_basic_motions(subsample)
    iddm = {"alpha4": alpha4, "noise_per_value": noise_per_value}

    def first(z: torch.Tensor, y: torch.Tensor, n: int | None):
        if n is None:
            return z, y
        keep = torch.cat([torch.nonzero(y == c).flatten()[:n] for c in range(len(names))])
        return z[keep], y[keep]

    z_train, y_train = first(z_train, y_train, max_train)
    z_test, y_test = first(z_test, y_test, max_test)
    k = len(names)
    splits = None
    if calibration_folds is not None:
        fewest = int(torch.bincount(y_train, minlength=k).min())
        check_calibration_folds(calibration_folds, fewest, "training recordings of a class")
        folds = StratifiedKFold(calibration_folds, shuffle=True, random_state=seed)
        splits = [
            (z_train[a], y_train[a], z_train[b], y_train[b])
            for a, b in folds.split(z_train[:, 0], y_train)
        ]
    rows = TableRows(windows, forgettings, baseline_window, state_prior, seed)
    notes: dict[str, Any] = {}  # the methods' notes, after the table's own
    run = run_fold(z_train, y_train, z_test, k, latent_dim, fit_steps, rows, notes,
                   splits=splits, progress=progress, **iddm)  # fmt: skip
    model, fit = run.model, run.fit
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
            "temperatures": run.temperatures,
            "alpha4": alpha4,
            "noise_per_value": noise_per_value,
            "value_noise": model.value_noise.tolist() if noise_per_value else None,
            "seed": seed,
            "confusion": {},
            "fit": fit.summary(),
            "fits": [fit.summary()],
            "calibration_fits": run.calibration_fits,
            **notes,
        },
    )
    for name, pred, ms, credible in run.decisions:
        acc = 100.0 * float((pred == y_test[:, None]).double().mean())
        cover = coverage(credible, y_test)
        table.add(
            **{
                "method": name,
                "accuracy [%]": round(acc, 1),
                "90% set coverage [%]": None if cover is None else round(cover, 1),
                "CPU ms/decision": ms,
            }
        )
        table.meta["confusion"][name] = confusion(pred, y_test[:, None], k).tolist()
    return table


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
    quick = args.quick or smoke_run()
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
