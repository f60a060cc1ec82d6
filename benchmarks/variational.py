"""Time of Algorithm 2.2 per window (VB over all K values of g in one batched optimisation).

``python -m benchmarks variational [--quick]``. Writes ``benchmarks/results/variational.json``.
Target (issue 4): <= 100 ms per window at T = 5 and 10, K = 4, N = 300 training frames, one
core. ``--device`` and ``--dtype`` (:func:`benchmarks._common.parse_options`) choose where and in
which precision the model (fitted on the CPU) runs. Reported per window length T:

- ``single [ms]``: one window per call (median over windows);
- ``batched [ms]``: all windows in one call, divided by their number;
- ``old [ms]``: the previous path (GP-RTSS start, L-BFGS on F only, 50 iterations), measured in
  the same process on one window (skipped with ``--quick``), and the ratio to ``single``;
- ``LM iters``: Levenberg-Marquardt iterations of the Laplace start with the default pruning
  (the largest over the batch); ``accuracy``: windows whose ML style is the true one.

Test windows come from the same generated set as the training sequences (a held-out split):
``styled_movements`` draws its observation map from the seed, so a set drawn with another seed
has another map and cannot be recognised by any model of the first.
"""

from __future__ import annotations

import time

import torch

from benchmarks._common import Options, parse_options
from hgpdm_torch.datasets import styled_movements
from hgpdm_torch.inference.variational import VariationalInference, window_mask
from hgpdm_torch.inference.variational.laplace import map_states
from hgpdm_torch.models import HGPDM
from hgpdm_torch.results import ResultTable


def run(opts: Options, per_style: int, lengths: list[int], windows: int, old: bool) -> ResultTable:
    table = ResultTable(
        "VB inference (Alg. 2.2) per window: K=4, Dx=3, Dz=12, rbf measurement, "
        f"{str(opts.dtype).removeprefix('torch.')}, 1 thread, device {opts.device}; Laplace "
        "start (LM) + closed-form F",
        ["N", "T", "single [ms]", "batched [ms]", "old [ms]", "speed-up", "LM iters", "accuracy"],
        meta=opts.meta(),
    )
    data = styled_movements(4, per_style + 1, 38, 12, seed=0)
    train, test = data.split(1.0 / (per_style + 1), seed=0)
    model = HGPDM(train.sequences, train.labels, 3, dtype=opts.dtype)
    model.fit(60, warn=False)  # a step budget: the per-window VB time does not depend on it
    model = model.to(opts.device)
    vb = VariationalInference(model)
    N = model.observations.shape[0]
    for T in lengths:
        zs, ys = [], []
        for seq, label in zip(test.sequences, test.labels, strict=True):
            for i in range(0, seq.shape[0] - T, 6):
                zs.append(seq[i : i + T].to(opts.device, opts.dtype))
                ys.append(int(label))
        zs, ys = zs[:windows], torch.tensor(ys[:windows])
        vb.infer(zs[0])  # warm-up
        single = []
        for z in zs:
            opts.synchronize()
            start = time.perf_counter()
            vb.infer(z)
            opts.synchronize()
            single.append(time.perf_counter() - start)
        single.sort()
        batch = torch.stack(zs)
        start = time.perf_counter()
        res = vb.infer(batch)
        t_batch = (time.perf_counter() - start) / len(zs)
        zz, obs = window_mask(batch, 12, vb.window.x1_mean)
        x0 = vb.initial_guess(zz, vb.values)[0]
        _, lm = map_states(vb.window, zz, obs, x0, vb.values, None, max_iter=30, prune=50.0)
        t_old = None
        if old:
            start = time.perf_counter()
            vb.infer(zs[0], newton_steps=0, steps=50, init="smoother")
            t_old = time.perf_counter() - start
        t_single = single[len(single) // 2]
        table.add(
            **{
                "N": N,
                "T": T,
                "single [ms]": 1e3 * t_single,
                "batched [ms]": 1e3 * t_batch,
                "old [ms]": None if t_old is None else 1e3 * t_old,
                "speed-up": None if t_old is None else t_old / t_single,
                "LM iters": len(lm) - 1,
                "accuracy": float((res.g_ml.cpu() == ys).double().mean()),
            }
        )
        print(table.rows[-1], flush=True)
    return table


def main(argv: list[str]) -> int:
    opts = parse_options(argv, "python -m benchmarks variational")
    torch.set_num_threads(1)
    torch.set_default_dtype(torch.float64)
    if opts.quick:
        table = run(opts, 1, [5], windows=2, old=False)
    else:
        table = run(opts, 2, [5, 10], windows=24, old=True)
    table.meta["single: median over windows"] = True
    print(table.to_markdown())
    table.to_json(opts.results_file("variational"))
    return 0
