"""Which ProMP library the baseline builds on: mp_pytorch (the toolkit's
:class:`~hgpdm_torch.baselines.ProMP`) against ``movement_primitives``' ProMP, on the strokes
of ``hgpdm target-prediction`` (issue 52).

``OMP_NUM_THREADS=1 python -m benchmarks promp_libraries [--quick]`` (``pip install
movement-primitives`` first; without it only the toolkit's rows are written). Writes
``benchmarks/results/promp_libraries.json``.

Seed 0's strokes (100 training, 126 test, 6 observations each, channels standardised on the
training strokes); each library fits a ProMP with the same number of basis functions per channel
and predicts the target after the observations up to 320, 240, 160 and 80 ms before the hit:

- the toolkit: the observations jointly with the target (augmented weights, Ledoit-Wolf
  covariance, ridge 0.01), the prefix conditioned on at once in information form, the durations
  known (all strokes have 6 observations), all test strokes in one batch;
- ``movement_primitives``: the target as a 16th channel constant over the stroke (its ProMP has
  no per-movement quantities), the weight distribution by its EM (``imitate``), the prefix
  conditioned on one frame at a time (``condition_position``, the only conditioning it offers)
  with the toolkit's fitted observation noise and an uninformative one (1e12) for the target,
  one test stroke at a time.

MAE [cm] with its SEM over the test strokes; CPU seconds of the fit and ms per decision.
"""

from __future__ import annotations

import sys
import time

import numpy as np
import torch

from benchmarks._common import parse_options
from hgpdm_torch.baselines import ProMP
from hgpdm_torch.experiments.target_prediction import HORIZONS_MS
from hgpdm_torch.results import ResultTable
from hgpdm_torch.robots.table_tennis.opponent import sample_strokes

STEPS = (1, 2, 3, 4)  # the observation index of each horizon


def _scores(pred: np.ndarray, truth: np.ndarray) -> dict[str, str]:
    """``MAE +- SEM`` [cm] per horizon of ``pred [n, 4]``."""
    err = 100 * np.abs(pred - truth[:, None])
    sem = err.std(0, ddof=1) / np.sqrt(len(err))
    return {f"{h} ms": f"{m:.1f} +- {s:.1f}" for h, m, s in zip(HORIZONS_MS, err.mean(0), sem,
                                                                  strict=True)}  # fmt: skip


def _ours(z_train, y_train, z_test, num_basis: int) -> tuple[np.ndarray, float, float]:
    start = time.process_time()
    model = ProMP(num_basis, reg=0.01).fit(list(z_train), y_train)
    fit = time.process_time() - start
    start = time.process_time()
    pred = [model.condition(z_test[:, : s + 1]).mean[:, 0] for s in STEPS]
    ms = 1e3 * (time.process_time() - start) / (len(z_test) * len(STEPS))
    return torch.stack(pred, 1).numpy(), fit, ms, model.noise.numpy()


def _movement_primitives(z_train, y_train, z_test, num_basis: int, noise: np.ndarray):
    from movement_primitives.promp import ProMP as LibraryProMP

    frames = z_train.shape[1]
    demos = np.concatenate([z_train, np.repeat(y_train[:, None, None], frames, 1)], 2)
    model = LibraryProMP(demos.shape[2], num_basis)
    start = time.process_time()
    model.imitate(np.tile(np.linspace(0, 1, frames), (len(demos), 1)), demos)
    fit = time.process_time() - start
    cov = np.diag(np.concatenate([noise, [1e12]]))  # the target is never observed
    start = time.process_time()
    pred = np.zeros((len(z_test), len(STEPS)))
    for i, stroke in enumerate(z_test):
        cond = model
        for s in range(STEPS[-1] + 1):
            seen = np.concatenate([stroke[s], [0.0]])
            cond = cond.condition_position(seen, cov, t=s / (frames - 1), t_max=1.0)
            if s in STEPS:
                pred[i, STEPS.index(s)] = cond.mean_trajectory(np.linspace(0, 1, frames))[-1, -1]
    ms = 1e3 * (time.process_time() - start) / (len(z_test) * len(STEPS))
    return pred, fit, ms


def main(argv: list[str]) -> int:
    opts = parse_options(argv, "promp_libraries")
    n_train, n_test = (30, 20) if opts.quick else (100, 126)
    strokes = sample_strokes(n_train + n_test, generator=torch.Generator().manual_seed(0))
    obs, y = strokes.obs.double(), strokes.targets.double()
    flat = obs[:n_train].reshape(-1, obs.shape[-1])
    z = ((obs - flat.mean(0)) / flat.std(0)).numpy()
    z_train, z_test = z[:n_train], z[n_train:]
    y_train, y_test = y[:n_train].numpy(), y[n_train:].numpy()
    try:
        import movement_primitives  # noqa: F401

        peer = True
    except ImportError:
        peer = False
    table = ResultTable(
        "ProMP libraries on the target-prediction strokes (seed 0): target MAE +- SEM [cm]",
        [
            "library",
            "basis per channel",
            *(f"{h} ms" for h in HORIZONS_MS),
            "fit [s]",
            "ms/decision",
        ],  # fmt: skip
        meta={"n_train": n_train, "n_test": n_test, "movement_primitives": peer},
    )
    for nb in (4, 6):
        pred, fit, ms, noise = _ours(torch.as_tensor(z_train), torch.as_tensor(y_train),
                                     torch.as_tensor(z_test), nb)  # fmt: skip
        table.add(library="mp_pytorch (hgpdm_torch.baselines.ProMP)", **{"basis per channel": nb},
                  **_scores(pred, y_test), **{"fit [s]": fit, "ms/decision": ms})  # fmt: skip
        if peer:
            pred, fit, ms = _movement_primitives(z_train, y_train, z_test, nb, noise)
            table.add(library="movement_primitives", **{"basis per channel": nb},
                      **_scores(pred, y_test), **{"fit [s]": fit, "ms/decision": ms})  # fmt: skip
    if not peer:
        print("movement_primitives is not installed: only the toolkit's rows", file=sys.stderr)
    print(table.to_markdown(".3g"))
    table.to_json(opts.results_file("promp_libraries"))
    return 0


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))
