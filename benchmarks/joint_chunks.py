"""Chunking of the joint ``q(z_{1:T})`` in forecasts (thesis App. 2.B): the seconds per window
and candidate of :func:`~hgpdm_torch.inference.variational.prediction.predict_observations`
with the library's chunk bound (``_JOINT_ENTRIES``) against one batch of the same windows, in
the same process (issue 30: the Weird Walking command's forecasts).

``python -m benchmarks joint_chunks [--quick]`` (about a minute on 2 cores). Writes
``benchmarks/results/joint_chunks.json``.

An H-GPDM with four styles and Dx = 10 is built on synthetic movements (no fit: the cost does
not depend on the hyperparameters) with 56 channels, as Weird Walking's frames, and 112, as its
frames beside the previous frame; VB infers ``q(x)`` of 24 windows of T = 10 rows with a
missing row appended (the forecast problem), once. Then the windows' rows are predicted under
all four candidates' ``q(x)`` (96 joint covariances of ``(T + 1) Dz`` rows) with chunks of at
most ``_JOINT_ENTRIES`` numbers, with one batch, and with a few other bounds, best of three.
"""

from __future__ import annotations

import sys
import time
from collections.abc import Callable
from unittest import mock

import torch

from benchmarks._common import RESULTS, environment
from hgpdm_torch.datasets import styled_movements
from hgpdm_torch.inference.variational import VariationalInference, prediction
from hgpdm_torch.inference.variational.window import window_mask
from hgpdm_torch.models import HGPDM
from hgpdm_torch.results import ResultTable


def _seconds(fn: Callable[..., object], args: tuple, repeats: int) -> float:
    """Best wall time of ``fn(*args)`` over ``repeats`` calls."""
    best = float("inf")
    for _ in range(repeats):
        start = time.perf_counter()
        fn(*args)
        best = min(best, time.perf_counter() - start)
    return best


def main(argv: list[str]) -> int:
    quick = "--quick" in argv
    torch.set_default_dtype(torch.float64)
    windows, T, repeats = (8, 5, 1) if quick else (24, 10, 3)
    ONE_BATCH = 1e15  # more than any batch here
    bounds = (prediction._JOINT_ENTRIES, 5e5, 8e6, 3.2e7, ONE_BATCH)
    table = ResultTable(
        "Forecast of a window's missing row from the joint q(z): seconds per window and "
        f"candidate by chunk bound, {torch.get_num_threads()} threads",
        ["Dz", "joint rows", "chunk bound", "matrices per chunk", "ms per matrix", "vs one batch"],
        meta={
            **environment(),
            "quick": quick,
            "windows": windows,
            "T": T,
            "candidates": 4,
            "library bound": prediction._JOINT_ENTRIES,
        },
    )
    for dz in (56, 112):
        data = styled_movements(4, 2, 40, dz, seed=0)
        model = HGPDM(data.sequences, data.labels, 10)
        vb = VariationalInference(model, measurement_points=150)
        z = torch.cat([s[None, i : i + T] for s in data.sequences for i in (0, 10, 20)])[:windows]
        z = torch.cat([z, torch.full_like(z[:, :1], float("nan"))], 1)
        res = vb.infer(z, prune=None)
        padded, observed = window_mask(z, vb.obs_dim, vb.window.x1_mean)
        args = (vb.window, padded[:, None], observed[:, None], res.mean, res.cov)
        n = (T + 1) * dz
        times = {}
        for bound in bounds:
            with mock.patch.object(prediction, "_JOINT_ENTRIES", bound):
                times[bound] = _seconds(prediction.predict_observations, args, repeats)
        count = res.mean.shape[0] * res.mean.shape[1]
        for bound in bounds:
            table.add(
                **{
                    "Dz": dz,
                    "joint rows": n,
                    "chunk bound": "one batch" if bound == ONE_BATCH else f"{bound:.0e}",
                    "matrices per chunk": min(count, max(1, int(bound // n**2))),
                    "ms per matrix": 1e3 * times[bound] / count,
                    "vs one batch": times[bound] / times[ONE_BATCH],
                }
            )
    print(table.to_markdown(".3g"))
    table.to_json(RESULTS / f"joint_chunks{'_quick' if quick else ''}.json")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
