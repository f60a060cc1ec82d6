"""*Walkers* on real CMU motion capture (thesis Sec. 2.4.1, Tables 2.1-2.2).

Protocol: walks of subjects 07 and 35 (``../shared/data/cmu``, see its README), Taylor-style
features at 15 frames/s (:func:`~hgpdm_torch.datasets.load_walkers`), channels constant in
training dropped and the rest standardised with training statistics only. The thesis's test
trials are held back, so the evaluation is a grouped cross-validation over the trials that are
there: in fold f each subject's trials are rotated so that one block is tested and the next
``train_per_subject`` trials train (subject 07 has two walks: one trains, one tests); no trial
is on both sides of a fold, every trial is tested at least once.

Per fold an H-GPDM (g = subject) and a GPDM are fitted (MAP, :meth:`GPDM.fit`); every test
trial is cut into sliding windows of T frames and each method forecasts the next frame:

- VB H-GPDM: Algorithm 2.2 over both subjects, the ML subject's forecast; its recognition
  accuracy, the 90%-set coverage of the subject posterior and its expected calibration error;
- oracle H-GPDM (true subject given): VB and MAP; GPDM: VB and MAP;
- the VB forecasts again with the window's deviation from the model's reconstruction carried
  forward as an AR(1) process (``forecast(..., residual="ar1")``, coefficient estimated from
  each window alone; not in the thesis);
- baselines: repeat the last frame; ridge AR(k) with k and the ridge strength chosen by
  cross-validation grouped by training trial (:class:`~hgpdm_torch.baselines.RidgeAR`).

RMSE is over all standardised channels of all windows; the table gives the mean over folds
with its standard error, and per subject. ``HGPDM_SMOKE=1`` shrinks the run.
"""

from __future__ import annotations

import argparse
import math
import os
import time
from pathlib import Path
from typing import Any

import numpy as np
import torch
from tqdm.auto import tqdm

from ..baselines import LastFrameForecaster, RidgeAR
from ..datasets.walkers import Standardizer, Walkers, load_walkers
from ..inference.calibration import calibration
from ..inference.map import MAPInference
from ..inference.variational import VariationalInference
from ..models import GPDM, HGPDM
from .arguments import output_file
from .style_recognition import chunked_forecast, forecast_windows
from .table import ResultTable

__all__ = ["METHODS", "main", "walker_folds", "walkers"]

SMOKE = os.environ.get("HGPDM_SMOKE", "0") == "1"
METHODS = (
    "VB H-GPDM",
    "oracle VB",
    "oracle MAP",
    "GPDM VB",
    "GPDM MAP",
    "VB H-GPDM + AR(1) residual",
    "oracle VB + AR(1) residual",
    "GPDM VB + AR(1) residual",
    "repeat last frame",
    "ridge AR (CV)",
)


def walker_folds(
    subject: Any, folds: int = 5, train_per_subject: int = 3
) -> list[tuple[list[int], list[int]]]:
    """Grouped folds over trials, balanced across subjects.

    For each subject with n trials (in order), block size ``b = max(1, min(n // folds, n - 1))``;
    fold f tests its trials ``f b .. f b + b - 1`` (cyclically) and trains on the next
    ``min(train_per_subject, n - b)`` trials after that block.

    Args:
        subject: ``[J]`` subject code per trial.
        folds: number of folds (>= 1).
        train_per_subject: training trials per subject and fold (>= 1).

    Returns:
        ``(train, test)`` trial indices per fold; disjoint within a fold.
    """
    codes = np.asarray(subject).reshape(-1)
    if not isinstance(folds, int) or folds < 1:
        raise ValueError(f"folds must be a positive int, got {folds!r}")
    if not isinstance(train_per_subject, int) or train_per_subject < 1:
        raise ValueError(f"train_per_subject must be a positive int, got {train_per_subject!r}")
    out = []
    for f in range(folds):
        train, test = [], []
        for s in np.unique(codes):
            idx = np.flatnonzero(codes == s).tolist()
            n = len(idx)
            if n < 2:
                raise ValueError(f"subject {s} has {n} trial; each subject needs at least 2")
            b = max(1, min(n // folds, n - 1))  # at least one trial left to train on
            k = min(train_per_subject, n - b)
            test += [idx[(f * b + i) % n] for i in range(b)]
            train += [idx[(f * b + b + i) % n] for i in range(k)]
        out.append((sorted(train), sorted(test)))
    return out


def _rmse(pred: torch.Tensor, truth: torch.Tensor, keep: torch.Tensor | None = None) -> float:
    err = pred - truth if keep is None else pred[keep] - truth[keep]
    return float(err.pow(2).mean().sqrt()) if err.numel() else math.nan


def _mean_sem(values: list[float]) -> tuple[float, float | None]:
    v = np.asarray([x for x in values if not math.isnan(x)])
    sem = float(v.std(ddof=1) / math.sqrt(len(v))) if len(v) > 1 else None
    return float(v.mean()), sem


def walkers(
    data: Walkers | None = None,
    *,
    folder: str | Path = "../shared/data/cmu",
    lengths: tuple[int, ...] = (5, 10),
    latent_dim: int = 3,
    fit_steps: int = 300,
    folds: int = 5,
    train_per_subject: int = 3,
    stride: int = 2,
    model_options: dict[str, Any] | None = None,
    sharing: float = 0.0,
    progress: bool = False,
) -> ResultTable:
    """Tables 2.1-2.2 on the real Walkers trials, with baselines (see the module docstring).

    Args:
        data: the trials (default :func:`load_walkers` of ``folder``).
        folder: where the CMU files are.
        lengths: window lengths T.
        latent_dim: Dx of both models.
        fit_steps: maximum MAP steps per fit.
        folds: see :func:`walker_folds`.
        train_per_subject: see :func:`walker_folds`.
        stride: step between windows.
        model_options: further constructor arguments of both models (e.g.
            ``{"back_constraint": "kernel"}``, ``{"learn_noise": True}``).
        sharing: the H-GPDM's share of dynamics common to both subjects
            (:class:`~hgpdm_torch.models.HGPDM`; 0 is the thesis's independent dynamics).
        progress: progress bar over folds.

    Returns:
        A :class:`ResultTable`: one row per window length and method; ``meta`` holds the
        per-fold numbers, the fits' convergence and the folds.
    """
    if data is None:
        data = load_walkers(folder)
    splits = walker_folds(data.subject, folds, train_per_subject)
    options = dict(model_options or {})
    per: dict[tuple[int, str], list[dict[str, float]]] = {}
    meta: dict[str, Any] = {
        "latent_dim": latent_dim,
        "model_options": {k: str(v) for k, v in options.items()},
        "sharing": sharing,
        "fit_steps": fit_steps,
        "stride": stride,
        "fps": data.fps,
        "subjects": list(data.subject_ids),
        "folds": [
            {"train": [data.trials[i] for i in tr], "test": [data.trials[i] for i in te]}
            for tr, te in splits
        ],
        "fits": [],
        "calibration": {},
    }
    for train, test in tqdm(splits, disable=not progress, desc="walkers"):
        std = Standardizer().fit([data.sequences[i] for i in train])
        tr = [std.transform(data.sequences[i]) for i in train]
        te = [std.transform(data.sequences[i]) for i in test]
        y_tr, y_te = data.subject[train], data.subject[test]
        start = time.perf_counter()
        hg = HGPDM(tr, y_tr, latent_dim, sharing=sharing, **options)
        gp = GPDM(tr, latent_dim, **options)
        fits = {name: m.fit(fit_steps).summary() for name, m in (("H-GPDM", hg), ("GPDM", gp))}
        meta["fits"].append({**fits, "seconds": time.perf_counter() - start})
        last, ridge = LastFrameForecaster().fit(tr), RidgeAR().fit(tr)
        vb_hg, vb_gp = VariationalInference(hg), VariationalInference(gp)
        for T in lengths:
            z, nxt, y = forecast_windows(te, y_te, T, stride)
            mean, g_ml, post = chunked_forecast(vb_hg, z)
            preds = {
                "VB H-GPDM": mean,
                "oracle VB": chunked_forecast(vb_hg, z, y[:, None])[0],
                "oracle MAP": chunked_forecast(MAPInference(hg), z, y[:, None])[0],
                "GPDM VB": chunked_forecast(vb_gp, z)[0],
                "GPDM MAP": chunked_forecast(MAPInference(gp), z)[0],
                "VB H-GPDM + AR(1) residual": chunked_forecast(vb_hg, z, residual="ar1")[0],
                "oracle VB + AR(1) residual": chunked_forecast(
                    vb_hg, z, y[:, None], residual="ar1"
                )[0],
                "GPDM VB + AR(1) residual": chunked_forecast(vb_gp, z, residual="ar1")[0],
                "repeat last frame": last.predict(z),
                "ridge AR (CV)": ridge.predict(z),
            }
            truth = vb_hg.values[y.to(vb_hg.values.device)]
            cal = calibration(post, (vb_hg.values[None, :] == truth[:, None]).long().argmax(-1))
            meta["calibration"].setdefault(str(T), []).append(cal)
            acc = float((vb_hg.values[g_ml] == y).double().mean())
            for name, pred in preds.items():
                row = {"rmse": _rmse(pred, nxt)}
                for s, sid in enumerate(data.subject_ids):
                    row[sid] = _rmse(pred, nxt, y == s)
                if name == "VB H-GPDM":
                    row.update(accuracy=acc, **cal)
                per.setdefault((T, name), []).append(row)
        meta.setdefault("ridge_order", []).append(ridge.order_)
    columns = ["T", "method", "RMSE", "SEM"]
    columns += [f"RMSE {sid}" for sid in data.subject_ids]
    columns += ["x GPDM VB", "accuracy", "90% set coverage", "ECE"]
    table = ResultTable(
        "Walkers (Tables 2.1-2.2): next-pose RMSE (standardised), mean over grouped folds",
        columns,
        meta=meta,
    )
    for T in lengths:
        ref = _mean_sem([r["rmse"] for r in per[(T, "GPDM VB")]])[0]
        for name in METHODS:
            rows = per[(T, name)]
            mean, sem = _mean_sem([r["rmse"] for r in rows])
            cells: dict[str, Any] = {"T": T, "method": name, "RMSE": mean, "SEM": sem}
            for sid in data.subject_ids:
                cells[f"RMSE {sid}"] = _mean_sem([r[sid] for r in rows])[0]
            cells["x GPDM VB"] = mean / ref
            if name == "VB H-GPDM":
                cells["accuracy"] = _mean_sem([r["accuracy"] for r in rows])[0]
                cells["90% set coverage"] = _mean_sem([r["coverage"] for r in rows])[0]
                cells["ECE"] = _mean_sem([r["ece"] for r in rows])[0]
            table.add(**cells)
        meta.setdefault("per_fold", {})[str(T)] = {n: per[(T, n)] for n in METHODS}
    return table


def main(argv: list[str]) -> int:
    """``hgpdm walkers [--data DIR] [--lengths 5 10] [--latent-dim 3] [--fit-steps 300]
    [--folds 5] [--out table.json]``."""
    parser = argparse.ArgumentParser(prog="hgpdm walkers", description=__doc__)
    parser.add_argument("--data", type=Path, default=Path("../shared/data/cmu"))
    parser.add_argument("--lengths", nargs="+", type=_positive, default=[5, 10])
    parser.add_argument("--latent-dim", type=_positive, default=3)
    parser.add_argument("--fit-steps", type=_positive, default=60 if SMOKE else 300)
    parser.add_argument("--folds", type=_positive, default=2 if SMOKE else 5)
    parser.add_argument("--train-per-subject", type=_positive, default=1 if SMOKE else 3)
    parser.add_argument("--stride", type=_positive, default=4 if SMOKE else 2)
    parser.add_argument("--back-constraint", choices=("kernel", "mlp"), default=None)
    parser.add_argument("--learn-noise", action="store_true", help="learn alpha_4 (MAP)")
    parser.add_argument(
        "--sharing",
        type=float,
        default=0.0,
        help="H-GPDM: share of the dynamics common to both subjects, in [0, 1) (default 0)",
    )
    parser.add_argument(
        "--fixed-measurement-width",
        action="store_true",
        help="keep the RBF measurement width at its initial value (no length-scale collapse)",
    )
    parser.add_argument("--out", type=output_file, default=None, help="write the table as JSON")
    parser.add_argument("--progress", action="store_true")
    args = parser.parse_args(argv)
    options: dict[str, Any] = {
        "learn_noise": args.learn_noise,
        "learn_measurement_width": not args.fixed_measurement_width,
    }
    if args.back_constraint is not None:
        options["back_constraint"] = args.back_constraint
    if not 0.0 <= args.sharing < 1.0:
        parser.error(f"--sharing must lie in [0, 1), got {args.sharing}")
    if not args.data.is_dir():
        parser.error(f"--data {args.data} is not a folder (it needs the CMU files, see README)")
    torch.set_default_dtype(torch.float64)
    table = walkers(
        folder=args.data,
        lengths=tuple(args.lengths),
        latent_dim=args.latent_dim,
        fit_steps=args.fit_steps,
        folds=args.folds,
        train_per_subject=args.train_per_subject,
        stride=args.stride,
        model_options=options,
        sharing=args.sharing,
        progress=args.progress,
    )
    print(table.to_markdown(".3f"))
    if args.out is not None:
        table.to_json(args.out)
    return 0


def _positive(text: str) -> int:
    value = int(text)
    if value < 1:
        raise argparse.ArgumentTypeError(f"expected a positive integer, got {text}")
    return value
