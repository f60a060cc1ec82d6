"""Time of Algorithm 2.2 per window (VB over all K values of g in one batched optimisation).

``python -m benchmarks variational [--quick]``. Writes ``benchmarks/results/variational.json``.
Target (issue 4): <= 100 ms per window at T = 5 and 10, K = 4, N = 300 training frames, one
core. Also reported: the cost of one free energy + gradient evaluation (all K at once) and the
number of L-BFGS iterations used (each takes one or more evaluations in its line search).
"""

from __future__ import annotations

import platform
import time
from pathlib import Path

import torch

from hgpdm_torch.datasets import styled_movements
from hgpdm_torch.experiments.table import ResultTable
from hgpdm_torch.inference.variational import VariationalInference, window_mask
from hgpdm_torch.models import HGPDM

RESULTS = Path(__file__).parent / "results"


def run(n_frames: int, lengths: list[int], steps: int, windows: int) -> ResultTable:
    table = ResultTable(
        f"VB inference (Alg. 2.2) per window: K=4, Dx=3, Dz=12, rbf measurement, float64, "
        f"1 thread, L-BFGS <= {steps} iterations",
        ["N", "T", "per window [ms]", "F+grad [ms]", "iterations", "init [ms]"],
        meta={
            "torch": torch.__version__,
            "machine": platform.processor() or platform.machine(),
            "threads": torch.get_num_threads(),
        },
    )
    length = 25
    data = styled_movements(4, max(n_frames // (4 * length), 1), length, 12, seed=0)
    model = HGPDM(data.sequences, data.labels, 3)
    model.fit(30)
    vb = VariationalInference(model)
    N = model.observations.shape[0]
    test = styled_movements(4, 1, 40, 12, seed=1)
    for T in lengths:
        zs = [s[i : i + T] for s in test.sequences for i in range(0, 40 - T, 7)][:windows]
        times, evals, inits = [], [], []
        for z in zs:
            start = time.perf_counter()
            res = vb.infer(z, steps=steps)
            times.append(time.perf_counter() - start)
            evals.append(len(res.history) - 1)
            zz, obs = window_mask(z, 12)
            start = time.perf_counter()
            loc, cov, _, _ = vb.initial_guess(zz, vb.values)
            inits.append(time.perf_counter() - start)
        z, obs = window_mask(zs[0], 12)
        loc = loc.clone().requires_grad_(True)
        tril = torch.linalg.cholesky(cov).requires_grad_(True)

        def evaluate(z=z, obs=obs, loc=loc, tril=tril) -> None:
            vb._free_energy(z, obs, loc, tril, vb.values, None, None).sum().backward()

        evaluate()
        start = time.perf_counter()
        for _ in range(3):
            evaluate()
        t_eval = (time.perf_counter() - start) / 3
        times.sort()
        table.add(
            **{
                "N": N,
                "T": T,
                "per window [ms]": 1e3 * times[len(times) // 2],
                "F+grad [ms]": 1e3 * t_eval,
                "iterations": sum(evals) / len(evals),
                "init [ms]": 1e3 * sum(inits) / len(inits),
            }
        )
        print(table.rows[-1], flush=True)
    return table


def main(argv: list[str]) -> int:
    quick = "--quick" in argv
    torch.set_num_threads(1)
    torch.set_default_dtype(torch.float64)
    if quick:
        table = run(100, [5], steps=5, windows=1)
    else:
        table = run(300, [5, 10], steps=50, windows=4)
    table.meta["median over windows"] = True
    print(table.to_markdown())
    table.to_json(RESULTS / ("variational_quick.json" if quick else "variational.json"))
    return 0
