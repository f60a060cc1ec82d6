"""Action recognition from human movement (thesis Sec. 3.6, Table 3.3).

Real multivariate movement data shipped with ``aeon`` (an optional extra): *BasicMotions*,
accelerometer and gyroscope (Dz = 6) of a smartwatch while a person stands, walks, runs or plays
badminton (4 actions, 40 training and 40 test recordings of 100 frames at 10 Hz). As in the
thesis (3 skeletal configurations per second) the frames are subsampled to ~3.3 Hz. The action is
a discrete intention; every method decides after every new frame:

- batch IDDM (Algorithm 3.1) on the last ``n = 4, 5, 6`` frames;
- online IDDM (Algorithm 3.2) with forgetting ``eps = 0.1, 0.2, 0.3``;
- SVM, GP classification and per-class HMMs on the same sliding window (``n = 5``).

Reported: accuracy over all decisions (Table 3.3 calls it precision) and the CPU time per
decision; ``meta["confusion"]`` holds each method's confusion matrix (rows true, columns
predicted).
"""

from __future__ import annotations

import argparse
import os
import time
from collections.abc import Callable
from typing import Any

import numpy as np
import torch
from tqdm.auto import tqdm

from ..baselines import HMMClassifier, WindowGPC, WindowSVM
from ..inference.intention import OnlineIntentionFilter, infer_intention
from ..models import IDDM
from .table import ResultTable

__all__ = ["action_recognition", "load_actions", "main"]


def load_actions(subsample: int = 3) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor,
                                              torch.Tensor, list[str]]:  # fmt: skip
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


def _confusion(pred: torch.Tensor, truth: torch.Tensor, k: int) -> list[list[int]]:
    m = np.zeros((k, k), dtype=int)
    np.add.at(m, (truth.expand_as(pred).flatten().numpy(), pred.flatten().numpy()), 1)
    return m.tolist()


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
    seed: int = 0,
    progress: bool = False,
) -> ResultTable:
    """Run the experiment; returns a :class:`ResultTable` in the layout of Table 3.3.

    Args:
        subsample: keep every n-th frame (3: ~3.3 Hz).
        latent_dim: ``Dx`` of the IDDM (linear measurement kernel, discrete intention).
        fit_steps: L-BFGS steps of the MAP fit.
        windows: batch window sizes; forgettings: online ``eps`` values.
        baseline_window: window of SVM, GPC and HMM.
        max_train, max_test: use only the first recordings of each class (smoke runs).
        seed: seed of the model fit and the baselines.
        progress: tqdm bars.
    """
    z_train, y_train, z_test, y_test, names = load_actions(subsample)

    def first(z: torch.Tensor, y: torch.Tensor, n: int | None):
        if n is None:
            return z, y
        keep = torch.cat([torch.nonzero(y == c).flatten()[:n] for c in range(len(names))])
        return z[keep], y[keep]

    z_train, y_train = first(z_train, y_train, max_train)
    z_test, y_test = first(z_test, y_test, max_test)
    k = len(names)
    torch.manual_seed(seed)
    model = IDDM(
        list(z_train), y_train, latent_dim, intention="discrete", measurement="linear",
        alpha=(0.9, 0.3, 0.1, 1e-2),
    )  # fmt: skip
    fit = model.fit(fit_steps, progress=progress)
    table = ResultTable(
        "Table 3.3: action recognition on BasicMotions, accuracy over all decisions",
        ["method", "accuracy [%]", "CPU ms/decision"],
        meta={"classes": names, "n_test": len(y_test), "frames": z_test.shape[1],
              "subsample": subsample, "Dx": latent_dim, "seed": seed, "confusion": {},
              "fit": fit.summary()},
    )  # fmt: skip
    decisions = z_test.shape[0] * z_test.shape[1]

    def record(name: str, run: Callable[[], torch.Tensor]) -> None:
        start = time.process_time()
        pred = run()
        ms = 1e3 * (time.process_time() - start) / decisions
        acc = 100.0 * float((pred == y_test[:, None]).double().mean())
        table.add(**{"method": name, "accuracy [%]": round(acc, 1), "CPU ms/decision": ms})
        table.meta["confusion"][name] = _confusion(pred, y_test[:, None], k)

    jobs: list[tuple[str, Callable[[], torch.Tensor]]] = []
    for w in windows:
        jobs.append((f"IDDM batch n={w}", lambda w=w: infer_intention(model, z_test, window=w)
                     .prob.argmax(-1)))  # fmt: skip
    for eps in forgettings:

        def online(eps: float = eps) -> torch.Tensor:
            f = OnlineIntentionFilter(model, forgetting=eps, batch_size=z_test.shape[0])
            return torch.stack([f.update(z_test[:, t]).prob.argmax(-1) for t in
                                range(z_test.shape[1])], 1)  # fmt: skip

        jobs.append((f"IDDM online eps={eps}", online))
    svm = WindowSVM(baseline_window).fit(list(z_train), y_train)
    jobs.append((f"SVM n={baseline_window}", lambda: svm.predict(z_test)))
    gpc = WindowGPC(baseline_window, seed=seed).fit(list(z_train), y_train)
    jobs.append((f"GPC n={baseline_window}", lambda: gpc.predict(z_test)))
    try:
        hmm = HMMClassifier(states=3, window=baseline_window, seed=seed).fit(list(z_train), y_train)
        jobs.append((f"HMM n={baseline_window}", lambda: hmm.predict(z_test)))
    except ImportError:
        table.meta["skipped"] = "HMM (hmmlearn not installed)"
    for name, run in tqdm(jobs, disable=not progress, desc="methods"):
        record(name, run)
    return table


def main(argv: list[str]) -> int:
    """``hgpdm action-recognition [--quick] [--out results.json] [--seed N]``."""
    parser = argparse.ArgumentParser(prog="hgpdm action-recognition", description=__doc__)
    parser.add_argument("--quick", action="store_true", help="small smoke-test sizes")
    parser.add_argument("--out", help="write the table as JSON")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)
    quick = args.quick or os.environ.get("HGPDM_SMOKE") == "1"
    kwargs: dict[str, Any] = (
        {
            "fit_steps": 10,
            "windows": (4,),
            "forgettings": (0.2,),
            "max_train": 3,
            "max_test": 2,
            "subsample": 5,
        }  # fmt: skip
        if quick
        else {}
    )
    table = action_recognition(seed=args.seed, progress=not quick, **kwargs)
    print(table.to_markdown())
    if args.out:
        table.to_json(args.out)
    return 0
