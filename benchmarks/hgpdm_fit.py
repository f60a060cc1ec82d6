"""Time of one loss + gradient evaluation and of a MAP fit of the H-GPDM versus N frames.

``python -m benchmarks hgpdm_fit [--quick]``. Writes ``benchmarks/results/hgpdm_fit.json``.
Each time is also given relative to one dense float64 Cholesky of an N x N matrix measured in the
same process (the unavoidable core of Eq. 6), so the ratio is comparable across machines.
"""

from __future__ import annotations

import time

import torch

from benchmarks._common import RESULTS, best_of, environment
from hgpdm_torch.datasets import styled_movements
from hgpdm_torch.experiments.table import ResultTable
from hgpdm_torch.models import HGPDM


def run(sizes: list[int], fit_steps: int, fit_max_n: int) -> ResultTable:
    table = ResultTable(
        "H-GPDM MAP learning cost (discrete g, K=4, Dx=3, Dz=12, float64, 1 thread)",
        ["N frames", "loss+grad [ms]", "x Cholesky", "fit [s]", "fit steps"],
        meta={
            **environment(),
        },
    )
    for n in sizes:
        length = 25
        data = styled_movements(4, max(n // (4 * length), 1), length, 12, seed=0)
        model = HGPDM(data.sequences, data.labels, 3)
        n_frames = model.observations.shape[0]

        def loss_grad(model=model):
            model.zero_grad()
            model.loss().backward()

        loss_grad()
        reps = 5 if n_frames <= 500 else 2
        t_eval = best_of(loss_grad, reps)
        a = torch.randn(n_frames, n_frames, dtype=torch.float64)
        spd = a @ a.T + n_frames * torch.eye(n_frames, dtype=torch.float64)
        t_chol = best_of(lambda spd=spd: torch.linalg.cholesky(spd), reps)
        row = {"N frames": n_frames, "loss+grad [ms]": 1e3 * t_eval, "x Cholesky": t_eval / t_chol}
        if n_frames <= fit_max_n:
            start = time.perf_counter()
            model.fit(fit_steps)
            row.update({"fit [s]": time.perf_counter() - start, "fit steps": fit_steps})
        table.add(**row)
        print(table.rows[-1], flush=True)
    return table


def main(argv: list[str]) -> int:
    quick = "--quick" in argv
    torch.set_num_threads(1)
    if quick:
        table = run([100, 200], fit_steps=5, fit_max_n=200)
    else:
        table = run([100, 250, 500, 1000, 2000], fit_steps=50, fit_max_n=1000)
    print(table.to_markdown())
    table.to_json(RESULTS / ("hgpdm_fit_quick.json" if quick else "hgpdm_fit.json"))
    return 0
