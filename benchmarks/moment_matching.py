"""Cost of moment-matching GP prediction and of one GP-ADF step versus N, streams B, intentions K.

``python -m benchmarks moment_matching [--quick]``. Writes
``benchmarks/results/moment_matching.json`` (``moment_matching_quick.json`` with ``--quick``).

Setting: IDDM transition GP over ``[x, g]`` (Dx = 3) with the tensor-product kernel
(``iddm_continuous``, Dg = 1) or the discrete-g kernel (``iddm_discrete``, N/K points per code),
float64, one thread. For each (N, B, K):

- ``shared``: one :meth:`GPPosterior.predict_gaussian` call for B input Gaussians and all K
  intentions (``mu [B, 1, Dx]``, ``g [1, K, Dg]``): the N x N expectation over x is computed once
  per stream and shared by the K intentions
  (docs/design/speed.md#intentions-share-the-input-expectation);
- ``loop``: the naive alternative measured in the same process, one call per intention
  (B streams batched, K calls), each redoing the N x N work; ``x faster`` = loop / shared;
- ``filter step``: one :func:`gp_adf_predict` + :func:`gp_adf_update` (linear measurement,
  Dz = 4) for K x B distinct state Gaussians, as in :func:`filter_sequence` with all K at once;
- ``path``: ``shared`` on the fused psi2 path (``settings.moment_path``, the default; the other
  columns are timed on it) and on the materialised one it replaced, in turn in this process,
  with ``floor`` (the call's operation count, :meth:`GenericTransition.operations`, at this
  device's rates, ``meta["rates"]``), ``x floor`` and ``peak MB/stream`` (peak allocation of
  one call over B); per kernel and path, ``streams at 30 Hz``: the largest B whose call at the
  largest N and K takes at most 33 ms.

Options (:func:`benchmarks._common.parse_options`): ``--device``, ``--dtype`` and
``--gpu-sizes``: N = 500, K = 25, B = 1, 4, 16, ..., 1024 streams.
"""

from __future__ import annotations

import torch

from benchmarks._common import (
    Options,
    best_of,
    largest_fitting,
    measure_rates,
    parse_options,
    peak_bytes,
)
from hgpdm_torch import settings
from hgpdm_torch.gp import GPPosterior
from hgpdm_torch.inference.filtering import gp_adf_predict, gp_adf_update
from hgpdm_torch.inference.intention import GenericTransition
from hgpdm_torch.kernels import measurement_kernel, transition_kernel
from hgpdm_torch.results import ResultTable

DX, DZ = 3, 4


def _posteriors(opts: Options, kind: str, n: int, k: int, gen: torch.Generator):
    kernel = transition_kernel(kind, DX, num_values=k, alpha=(0.9, 0.5, 0.1, 1e-3))
    x = torch.randn(n, DX, generator=gen, dtype=torch.float64)
    if kind == "iddm_discrete":
        g_col = torch.arange(n, dtype=torch.float64)[:, None] % k
        values = torch.arange(k, dtype=torch.float64)[:, None]
    else:
        g_col = torch.rand(n, 1, generator=gen, dtype=torch.float64) * 2 - 1
        values = torch.linspace(-1, 1, k, dtype=torch.float64)[:, None]
    y = torch.tanh(x) + 0.3 * g_col
    c = torch.randn(DX, DZ, generator=gen, dtype=torch.float64)
    x, g_col, y, c, values = (v.to(opts.device, opts.dtype) for v in (x, g_col, y, c, values))
    kernel = kernel.to(opts.device, opts.dtype)
    trans = GPPosterior(kernel, torch.cat([x, g_col], -1), y, 1e-3)
    linear = measurement_kernel("linear").to(opts.device, opts.dtype)
    meas = GPPosterior(linear, x, x @ c, 1e-2)
    return trans, meas, values


def run(
    opts: Options, sizes: list[int], configs: list[tuple[int, int]], repeats: int
) -> ResultTable:
    rates = measure_rates(opts.device, opts.dtype)
    table = ResultTable(
        f"Moment matching (Dx=3, {str(opts.dtype).removeprefix('torch.')}, 1 thread, device "
        f"{opts.device}): predict_gaussian for B streams x K intentions, shared vs a "
        "per-intention loop, and one GP-ADF filter step",
        [
            "kernel", "N", "B", "K", "path", "shared [ms]", "floor [ms]", "x floor",
            "peak MB/stream", "streams at 30 Hz", "loop [ms]", "x faster", "filter step [ms]",
        ],
        meta={**opts.meta(), "repeats (best of)": repeats, "rates": rates.as_dict()},
    )  # fmt: skip

    def randn(*shape: int) -> torch.Tensor:  # drawn on the CPU: the same data on every device
        return torch.randn(*shape, generator=gen, dtype=torch.float64).to(opts.device, opts.dtype)

    gen = torch.Generator().manual_seed(0)
    for kind in ("iddm_continuous", "iddm_discrete"):
        for n in sizes:
            for b, k in configs:
                trans, meas, values = _posteriors(opts, kind, n, k, gen)
                mu = 0.3 * randn(b, 1, DX)
                a = 0.2 * randn(b, 1, DX, DX)
                eye = torch.eye(DX, dtype=opts.dtype, device=opts.device)
                sigma = a @ a.transpose(-1, -2) + 0.01 * eye
                g = values[None]  # [1, K, 1]

                def shared(mu=mu, sigma=sigma, g=g, trans=trans):
                    trans.predict_gaussian(mu, sigma, g=g, include_noise=True)

                def loop(mu=mu[:, 0], sigma=sigma[:, 0], values=values, trans=trans):
                    for v in values:
                        trans.predict_gaussian(
                            mu, sigma, g=v.expand(len(mu), 1), include_noise=True
                        )

                # K x B distinct states, as after the first step of a filter over all K
                mu_kb = mu[:, 0].expand(k, b, DX) + 0.01 * randn(k, b, DX)
                sig_kb = sigma[:, 0].expand(k, b, DX, DX)
                z = randn(b, DZ)

                def step(
                    mu_kb=mu_kb, sig_kb=sig_kb, g=values[:, None], z=z, trans=trans, meas=meas
                ):
                    m, s, _ = gp_adf_predict(trans, mu_kb, sig_kb, g=g)
                    gp_adf_update(meas, m, s, z)

                ops = GenericTransition(trans, values).operations(b) * b
                with torch.no_grad():
                    shared(), loop(), step()  # warm-up (and kinv cache)
                    t_loop = best_of(loop, repeats, opts.device)
                    t_step = best_of(step, repeats, opts.device)
                    for path in settings.moment_path.choices:
                        with settings.moment_path(path):
                            t_shared = best_of(shared, repeats, opts.device)
                            peak = peak_bytes(shared, opts.device)
                        row = {"kernel": kind, "N": n, "B": b, "K": k, "path": path,
                               "shared [ms]": 1e3 * t_shared,
                               "floor [ms]": rates.floor_ms(ops),
                               "x floor": 1e3 * t_shared / rates.floor_ms(ops),
                               "peak MB/stream": peak / b / 1e6}  # fmt: skip
                        if path == "fused":  # the default: the loop and the filter step
                            row.update({"loop [ms]": 1e3 * t_loop, "x faster": t_loop / t_shared,
                                        "filter step [ms]": 1e3 * t_step})  # fmt: skip
                        table.add(**row)
                        print(table.rows[-1], flush=True)
        # how many streams one call serves within a 30 Hz frame, at the largest N and K
        trans, _, values = _posteriors(opts, kind, sizes[-1], configs[-1][1], gen)
        for path in settings.moment_path.choices:

            def fits(b: int, trans=trans, values=values) -> bool:
                mu = 0.3 * randn(b, 1, DX)
                a = 0.2 * randn(b, 1, DX, DX)
                eye = torch.eye(DX, dtype=opts.dtype, device=opts.device)
                sigma = a @ a.transpose(-1, -2) + 0.01 * eye

                def call() -> None:
                    trans.predict_gaussian(mu, sigma, g=values[None], include_noise=True)

                return best_of(call, 2, opts.device) <= 1 / 30

            with torch.no_grad(), settings.moment_path(path):
                table.add(kernel=kind, N=sizes[-1], K=configs[-1][1], path=path,
                          **{"streams at 30 Hz": largest_fitting(fits)})  # fmt: skip
            print(table.rows[-1], flush=True)
    return table


def main(argv: list[str]) -> int:
    opts = parse_options(argv, "python -m benchmarks moment_matching")
    torch.set_num_threads(1)
    if opts.quick:
        table = run(opts, [50, 100], [(1, 5), (4, 5)], repeats=2)
    elif opts.gpu_sizes:
        table = run(opts, [500], [(b, 25) for b in (1, 4, 16, 64, 256, 1024)], repeats=5)
    else:
        table = run(opts, [100, 250, 500], [(1, 1), (1, 25), (8, 25)], repeats=5)
    print(table.to_markdown())
    table.to_json(opts.results_file("moment_matching"))
    return 0
