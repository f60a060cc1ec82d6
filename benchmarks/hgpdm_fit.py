"""Time of one loss + gradient evaluation and of a MAP fit of the H-GPDM versus N frames.

``python -m benchmarks hgpdm_fit [--quick]``. Writes ``benchmarks/results/hgpdm_fit.json``.
Each time is also given relative to one dense float64 Cholesky of an N x N matrix measured in the
same process (the unavoidable core of Eq. 6), so the ratio is comparable across machines.

Options (:func:`benchmarks._common.parse_options`): ``--device`` and ``--dtype`` (the model's;
float32 runs with the process noise alpha_4 = ``FLOAT32_NOISE``, 0.1, instead of 1e-4);
``--gpu-sizes``: the GPDM (no g) loss + gradient at N = 1,000, 2,000, 5,000, 10,000 frames (no
fit).
"""

from __future__ import annotations

import time

import torch

from benchmarks._common import FLOAT32_NOISE, Options, best_of, parse_options
from hgpdm_torch.datasets import styled_movements
from hgpdm_torch.kernels import ALPHA_BAR
from hgpdm_torch.models import GPDM, HGPDM
from hgpdm_torch.results import ResultTable


def run(opts: Options, sizes: list[int], fit_steps: int, fit_max_n: int) -> ResultTable:
    dtype, device = opts.dtype, opts.device
    kind = "GPDM (no g)" if opts.gpu_sizes else "H-GPDM (discrete g, K=4)"
    table = ResultTable(
        f"{kind} MAP learning cost (Dx=3, Dz=12, {str(dtype).removeprefix('torch.')}, "
        f"1 thread, device {device})",
        ["N frames", "loss+grad [ms]", "x Cholesky", "fit [s]", "fit steps"],
        meta=opts.meta(),
    )
    for n in sizes:
        length = 25
        data = styled_movements(4, max(n // (4 * length), 1), length, 12, seed=0)
        seqs = [s.to(device) for s in data.sequences]
        # float32: the process noise FLOAT32_NOISE, else K_x of these thousands of near-repeated
        # frames is not positive definite in its digits (seen at N = 2,000 on an H100)
        alpha = ALPHA_BAR if dtype == torch.float64 else (*ALPHA_BAR[:3], FLOAT32_NOISE)
        if opts.gpu_sizes:
            model = GPDM(seqs, 3, dtype=dtype, alpha=alpha)
        else:
            model = HGPDM(seqs, data.labels, 3, dtype=dtype, alpha=alpha)
        n_frames = model.observations.shape[0]

        def loss_grad(model=model):
            model.zero_grad()
            model.loss().backward()

        loss_grad()
        reps = 5 if n_frames <= 500 else 2
        t_eval = best_of(loss_grad, reps, device)
        a = torch.randn(n_frames, n_frames, dtype=dtype, device=device)
        spd = a @ a.T + n_frames * torch.eye(n_frames, dtype=dtype, device=device)
        t_chol = best_of(lambda spd=spd: torch.linalg.cholesky(spd), reps, device)
        row = {"N frames": n_frames, "loss+grad [ms]": 1e3 * t_eval, "x Cholesky": t_eval / t_chol}
        if n_frames <= fit_max_n:
            start = time.perf_counter()
            model.fit(fit_steps, warn=False)  # timed for a fixed step count, not to convergence
            row.update({"fit [s]": time.perf_counter() - start, "fit steps": fit_steps})
        table.add(**row)
        print(table.rows[-1], flush=True)
    return table


def main(argv: list[str]) -> int:
    opts = parse_options(argv, "python -m benchmarks hgpdm_fit")
    torch.set_num_threads(1)
    if opts.quick:
        table = run(opts, [100, 200], fit_steps=5, fit_max_n=200)
    elif opts.gpu_sizes:
        table = run(opts, [1000, 2000, 5000, 10000], fit_steps=0, fit_max_n=0)
    else:
        table = run(opts, [100, 250, 500, 1000, 2000], fit_steps=50, fit_max_n=1000)
    print(table.to_markdown())
    table.to_json(opts.results_file("hgpdm_fit"))
    return 0
