"""Latency and throughput of IDDM intention inference on the thesis-sized problem (Sec. 3.5).

``python -m benchmarks online_intention [--quick]``. Writes
``benchmarks/results/online_intention.json`` (``online_intention_quick.json`` with ``--quick``).

Setting: an IDDM with N = 500 transition pairs (100 movements of 6 frames, a continuous target
per movement), Dz = 15, Dx = 4, linear measurement kernel, K = 25 grid values, one CPU thread.

- ``online 1 stream``: p50/p99 latency of one :meth:`OnlineIntentionFilter.update` (Algorithm
  3.2), float64 and float32, default (predictive) and thesis (``evidence="bound"``) evidence;
  the thesis reports 70 ms per observation, the target here is p50 <= 5 ms in float64;
- ``online B streams``: time per stream of one batched update of B streams, and the same B
  updates as a Python loop over B single-stream filters (``x loop`` = loop / batched; target
  >= 3x at B = 256);
- ``online batched`` by ``path``: the whole predictive step by the compiled kernel
  (``native``, :mod:`hgpdm_torch.inference.intention.compiled`; the default where it runs), its
  fused psi2 contraction alone with the rest of the step in torch (``native psi2``), the
  contraction in torch (``fused``, ``settings.native_kernels(False)``) and the materialised
  path it replaced (``settings.moment_path``), timed in turn in this process, each with
  ``floor [ms/stream]`` (the step's operation count, :meth:`OnlineIntentionFilter.operations`,
  at this device's rates: a large GEMM and a large exponential timed in this process, recorded
  in ``meta["rates"]``), ``x floor`` (time over floor) and ``peak MB/stream`` (peak allocation
  of one update over B, the compiled kernel's work space included); each path at its own
  default chunk of streams; at the largest B also
  ``marginal KB/stream``, what each further stream adds to the peak (the peaks at 2B and B
  apart, over B): the rest of the peak is the fixed working set of one chunk of streams;
- ``streams at 30 Hz`` by path: the largest B whose whole update fits in 33 ms;
- ``online sparse M``: the sparse pseudo-input transition (Sec. 3.3.3; M pseudo-inputs on
  ``round(sqrt(M))`` intention values), one stream and B = 256 streams (``x exact loop``: the
  batched sparse update against the loop of exact single-stream updates), and the mean shift of
  the posterior over g against the exact filter;
- ``batch window 4``: :func:`infer_intention` (Algorithm 3.1) on the last 4 observations, the
  per-observation cost of the sliding-window batch algorithm (thesis: 300 ms);
- ``online phase + scales``: the phase-aware IDDM with a process noise per latent dim
  (:data:`~hgpdm_torch.decision.beliefs.PHASE_IDDM`'s ``phase_width`` and
  ``scale_transitions``, fitted on the same movements), one stream and B = 256 streams;
  ``x plain`` is its time over the plain model's in the same process (target <= 2).

Times are CPU time of the (single-threaded) process, ``time.process_time``: on a shared machine
wall-clock latency also counts the time other processes hold the core. On an accelerator
(``--device cuda``) they are wall time after a synchronisation.

Options (:func:`benchmarks._common.parse_options`): ``--device``, ``--dtype`` (the filters'
computation dtype; the model stays float64; the Q-bound row stays float64) and ``--gpu-sizes``:
B = 1, 4, ..., 4096 streams (N = 500, K = 25), the Python loop only up to B = 16, the
materialised path up to B = 1,024.
``--quick`` runs N = 150 and B up to 64 (the floor and memory columns included).
"""

from __future__ import annotations

import contextlib
from collections.abc import Iterator
from typing import Any

import numpy as np
import torch

from benchmarks._common import (
    FLOAT32_NOISE,
    Options,
    Rates,
    largest_fitting,
    measure_rates,
    parse_options,
    peak_bytes,
)
from hgpdm_torch import native, settings
from hgpdm_torch.datasets import targeted_movements
from hgpdm_torch.decision.beliefs import PHASE_IDDM
from hgpdm_torch.inference.intention import OnlineIntentionFilter, infer_intention
from hgpdm_torch.models import IDDM
from hgpdm_torch.results import ResultTable

N_SEQ, FRAMES, DZ, DX, K = 100, 6, 15, 4, 25


def build_model(
    fit_steps: int,
    device: torch.device | str = "cpu",
    noise: float = 1e-2,
    movements: int = N_SEQ,
    **options: Any,
) -> tuple[IDDM, torch.Tensor, torch.Tensor]:
    """The thesis-sized IDDM (``movements`` of FRAMES frames, N = 5 ``movements`` transitions;
    process noise ``noise``; other :class:`IDDM` ``options``; fitted on the CPU, then moved to
    ``device``), the intention grid and test streams ``[S, T, Dz]``."""
    data = targeted_movements(movements + 40, FRAMES + 6, DZ, noise=0.05, seed=0)
    seqs = [s[:FRAMES] for s in data.sequences[:movements]]
    model = IDDM(
        seqs, data.labels[:movements], DX, intention="continuous", measurement="linear",
        alpha=(0.9, 0.3, 0.1, noise), alpha_g=(4.0, 0.1), **options,
    )  # fmt: skip
    model.fit(fit_steps, warn=False)  # a step budget: the timings do not depend on the fit
    grid = torch.linspace(-1.2, 1.2, K, dtype=torch.float64)
    streams = torch.stack(data.sequences[movements:])
    return model.to(device), grid.to(device), streams.to(device)


def _percentiles(times: list[float]) -> tuple[float, float]:
    a = 1e3 * np.asarray(times)
    return float(np.percentile(a, 50)), float(np.percentile(a, 99))


def single_stream(
    opts: Options, model, grid, streams, dtype, evidence: str, repeats: int, inducing=None
):
    f = OnlineIntentionFilter(
        model, grid, forgetting=0.2, evidence=evidence, dtype=dtype, inducing=inducing
    )
    times = []
    for r in range(repeats):
        f.reset()
        z = streams[r % len(streams)].to(dtype)
        f.update(z[0])  # initialisation step (no transition), not timed
        for t in range(1, z.shape[0]):
            start = opts.clock()
            f.update(z[t])
            times.append(opts.clock() - start)
    return _percentiles(times)


def loop_ms(opts: Options, model, grid, streams, B: int, inducing=None) -> float:
    """ms per stream of the same update as a Python loop over B single-stream filters."""
    z = streams[torch.arange(B, device=streams.device) % len(streams)]
    options = {"forgetting": 0.2, "inducing": inducing, "dtype": opts.dtype}
    singles = [OnlineIntentionFilter(model, grid, **options) for _ in range(B)]
    for b, s in enumerate(singles):
        s.update(z[b, 0])
    loops = []
    for t in range(1, 4):
        start = opts.clock()
        for b, s in enumerate(singles):
            s.update(z[b, t])
        loops.append(opts.clock() - start)
    return 1e3 * min(loops) / B


def batched(opts: Options, model, grid, streams, B: int, inducing=None) -> float:
    """ms per stream of one batched update of B streams."""
    z = streams[torch.arange(B, device=streams.device) % len(streams)]
    options = {"forgetting": 0.2, "inducing": inducing, "dtype": opts.dtype}
    return _update_ms(opts, OnlineIntentionFilter(model, grid, batch_size=B, **options), z) / B


def _update_ms(opts: Options, f: OnlineIntentionFilter, z: torch.Tensor, updates: int = 3):
    """Best of ``updates`` timed updates [ms] of the filter ``f`` (after one untimed first
    observation, which only initialises the streams) on the observations ``z [B, T, Dz]``."""
    f.update(z[:, 0])
    times = []
    for t in range(1, 1 + updates):
        start = opts.clock()
        f.update(z[:, t])
        times.append(opts.clock() - start)
    return 1e3 * min(times)


def paths(opts: Options) -> list[str]:
    """The paths timed in turn, the default first: ``native`` (the whole predictive step by the
    compiled kernel, :mod:`hgpdm_torch.native`, where it runs: float64 on a CPU with AVX-512;
    :mod:`hgpdm_torch.inference.intention.compiled`), ``native psi2`` (its contraction only, the
    rest of the step in torch), ``fused`` (all in torch) and ``materialised``."""
    compiled = opts.device.type == "cpu" and opts.dtype == torch.float64 and native.available()
    return ["native", "native psi2"] * compiled + ["fused", "materialised"]


@contextlib.contextmanager
def on_path(path: str) -> Iterator[None]:
    """Settings of one of :func:`paths` (``native psi2``: also :func:`path_filter`)."""
    fused = "materialised" if path == "materialised" else "fused"
    with settings.moment_path(fused), settings.native_kernels(path.startswith("native")):
        yield


def path_filter(path: str, model, grid, B: int, dtype: torch.dtype) -> OnlineIntentionFilter:
    """A filter of B streams on one of :func:`paths` (inside its :func:`on_path`)."""
    f = OnlineIntentionFilter(model, grid, batch_size=B, forgetting=0.2, dtype=dtype)
    if path == "native psi2":
        f.compiled_step = None
    return f


def measured_peak(f: OnlineIntentionFilter, z: torch.Tensor, device: torch.device) -> int:
    """Peak bytes of the update ``f.update(z)``, the compiled kernel's work space included (its
    buffers are freed first, so the update allocates them again)."""
    native.clear_scratch()
    return peak_bytes(lambda: f.update(z), device)


def _peak(opts: Options, model, grid, streams, B: int, path: str) -> int:
    """Peak bytes of the fifth update of a filter of B streams (as :func:`path_rows` takes it)."""
    z = streams[torch.arange(B, device=streams.device) % len(streams)]
    f = path_filter(path, model, grid, B, opts.dtype)
    for t in range(4):
        f.update(z[:, t])
    return measured_peak(f, z[:, 4], opts.device)


def path_rows(
    opts: Options, rates: Rates, model, grid, streams, B: int, timed: list[str],
    marginal: bool = False, updates: int = 3,
) -> list[dict]:  # fmt: skip
    """The online update of B streams on each psi2 path of ``timed`` (:func:`paths`): ms per
    stream, its floor (the step's operation count at this device's rates) and the peak memory of
    one update per stream; with ``marginal``, also what each further stream adds to that peak
    (the peaks of 2B and B streams apart, over B): the peak of B streams is the fixed working
    set of one chunk of streams plus B times this.

    The paths' filters take their timed updates in turn (path after path, ``updates`` rounds,
    the best of each path's): a slow spell of a shared machine then slows one update of each
    path rather than all of one path's."""
    z = streams[torch.arange(B, device=streams.device) % len(streams)]
    filters, best = {}, dict.fromkeys(timed, float("inf"))
    for path in timed:
        with on_path(path):
            filters[path] = path_filter(path, model, grid, B, opts.dtype)
            filters[path].update(z[:, 0])  # the first observation only initialises the streams
    for t in range(1, 1 + updates):
        for path in timed:
            with on_path(path):
                start = opts.clock()
                filters[path].update(z[:, t])
                best[path] = min(best[path], opts.clock() - start)
    rows = []
    for path, f in filters.items():
        with on_path(path):
            peak = measured_peak(f, z[:, 1 + updates], opts.device)
            floor = rates.floor_ms(f.operations())
            per_stream = 1e3 * best[path] / B
            row = {
                "algorithm": "online batched", "path": path, "B": B,
                "p50 [ms/obs/stream]": per_stream, "floor [ms/stream]": floor,
                "x floor": per_stream / floor, "peak MB/stream": peak / B / 1e6,
            }  # fmt: skip
            if marginal:
                double = _peak(opts, model, grid, streams, 2 * B, path)
                row["marginal KB/stream"] = (double - peak) / B / 1e3
        rows.append(row)
    return rows


def streams_at(opts: Options, model, grid, streams, path: str, budget_ms: float = 1e3 / 30):
    """The largest B whose update fits in ``budget_ms`` (33 ms: 30 Hz) on this path (best of 2
    updates; :func:`~benchmarks._common.largest_fitting`)."""

    def fits(B: int) -> bool:
        z = streams[torch.arange(B, device=streams.device) % len(streams)]
        f = path_filter(path, model, grid, B, opts.dtype)
        return _update_ms(opts, f, z, updates=2) <= budget_ms

    with on_path(path):
        return largest_fitting(fits)


def sparse_error(model, grid, streams, inducing: int) -> float:
    """Mean |posterior mean (sparse) - posterior mean (exact)| [cm] after every step."""
    out = []
    for m in (None, inducing):
        f = OnlineIntentionFilter(model, grid, batch_size=len(streams), inducing=m)
        out.append(torch.stack([f.update(streams[:, t]).mean[:, 0] for t in range(6)], 1))
    return 100.0 * float((out[0] - out[1]).abs().mean())


def batch_window(opts: Options, model, grid, streams, repeats: int) -> float:
    times = []
    for r in range(repeats):
        z = streams[r % len(streams), :4]
        start = opts.clock()
        infer_intention(model, z, grid)
        times.append(opts.clock() - start)
    return 1e3 * float(np.median(times))


def run(opts: Options) -> ResultTable:
    torch.set_num_threads(1)
    quick = opts.quick
    steps, movements = (2, 30) if quick else (30, N_SEQ)  # quick: N = 150, not the thesis's 500
    model64, grid, streams = build_model(steps, opts.device, movements=movements)
    model32 = build_model(steps, opts.device, FLOAT32_NOISE, movements)[0]
    model = model32 if opts.dtype == torch.float32 else model64
    n = int(model.src_index.numel())
    rates = measure_rates(opts.device, opts.dtype)
    table = ResultTable(
        f"IDDM intention inference, N={n}, Dz={DZ}, Dx={DX}, K={K}, 1 CPU thread, "
        f"device {opts.device}",
        [
            "algorithm",
            "path",
            "dtype",
            "B",
            "p50 [ms/obs/stream]",
            "p99 [ms]",
            "floor [ms/stream]",
            "x floor",
            "peak MB/stream",
            "marginal KB/stream",
            "streams at 30 Hz",
            "loop [ms/stream]",
            "x loop",
            "x exact loop",
            "x plain",
            "|d mean| vs exact [cm]",
        ],  # fmt: skip
        meta={
            **opts.meta(),
            "command": "python -m benchmarks online_intention",
            "alpha_4": {"float64": 1e-2, "float32": FLOAT32_NOISE},
            "rates": rates.as_dict(),
        },  # fmt: skip
    )
    repeats = 3 if quick else 40
    # float32 only for the default evidence: the Q bound's conditional covariance
    # S - C^T P^-1 C cancels to the process noise and is not reliable in float32
    rows = [("predictive", opts.dtype), ("predictive", torch.float32), ("bound", torch.float64)]
    for evidence, dtype in dict.fromkeys(rows):  # without a repeated float32 row
        timed = model32 if dtype == torch.float32 else model64
        p50, p99 = single_stream(opts, timed, grid, streams, dtype, evidence, repeats)
        name = "online" if evidence == "predictive" else "online (Q bound, thesis)"
        table.add(**{
            "algorithm": name, "dtype": str(dtype).removeprefix("torch."), "B": 1,
            "p50 [ms/obs/stream]": p50, "p99 [ms]": p99,
        })  # fmt: skip
        print(table.rows[-1], flush=True)
    if quick:
        sizes, loop_max = [1, 16, 64], 256
    elif opts.gpu_sizes:
        sizes, loop_max = [1, 4, 16, 64, 256, 1024, 4096], 16
    else:
        sizes, loop_max = [1, 4, 16, 64, 256, 1024], 256
    name = str(opts.dtype).removeprefix("torch.")
    exact_loop = {}
    # the psi2 paths (the default first), in turn in this process: time, floor and peak memory
    # per stream; the loop of single-stream filters on the default path
    timed = paths(opts)
    for B in sizes:
        # 2 streams per chunk: minutes per update beyond B = 1,024
        on = [p for p in timed if p != "materialised" or B <= 1024]
        for path, row in zip(
            on, path_rows(opts, rates, model, grid, streams, B, on, B == sizes[-1]), strict=True
        ):
            if path == timed[0] and B <= loop_max:
                exact_loop[B] = loop = loop_ms(opts, model, grid, streams, B)
                row.update({"loop [ms/stream]": loop, "x loop": loop / row["p50 [ms/obs/stream]"]})
            table.add(dtype=name, **row)
            print(table.rows[-1], flush=True)
    for path in timed:
        table.add(**{
            "algorithm": "streams at 30 Hz", "path": path, "dtype": name,
            "streams at 30 Hz": streams_at(opts, model, grid, streams, path),
        })  # fmt: skip
        print(table.rows[-1], flush=True)
    # the sparse pseudo-input transition (Sec. 3.3.3): latency, throughput and accuracy cost
    for m in (50, 25) if quick else (250, 125):
        B = min(sizes[-2], loop_max)  # with a measured loop of exact filters
        try:
            p50, p99 = single_stream(
                opts, model, grid, streams, opts.dtype, "predictive", repeats, m
            )
            per_stream = batched(opts, model, grid, streams, B, m)
            loop = loop_ms(opts, model, grid, streams, B, m)
        except ValueError as err:  # the filter refuses a dtype too coarse for this model
            print(f"online sparse M={m} skipped: {err}", flush=True)
            continue
        table.add(**{
            "algorithm": f"online sparse M={m}", "dtype": name, "B": 1,
            "p50 [ms/obs/stream]": p50, "p99 [ms]": p99,
            "|d mean| vs exact [cm]": sparse_error(model, grid, streams, m),
        })  # fmt: skip
        table.add(**{
            "algorithm": f"online sparse M={m} batched", "dtype": name,
            "B": B, "p50 [ms/obs/stream]": per_stream,
            "loop [ms/stream]": loop, "x loop": loop / per_stream,
            "x exact loop": exact_loop[B] / per_stream,
        })  # fmt: skip
        print(table.rows[-2:], flush=True)
    table.add(**{
        "algorithm": "batch, window 4", "dtype": "float64", "B": 1,
        "p50 [ms/obs/stream]": batch_window(opts, model, grid, streams, 2 if quick else 5),
    })  # fmt: skip
    phase_options(opts, table, model, grid, streams, steps, movements, repeats)
    return table


def phase_options(
    opts: Options, table: ResultTable, model, grid, streams, steps, movements, repeats
) -> None:
    """The phase-aware, per-dim-noise IDDM against the plain one, timed in turn in this process
    (one stream: p50 of the same updates; B = 256: best of three batched updates)."""
    noise = FLOAT32_NOISE if opts.dtype == torch.float32 else 1e-2
    phase = build_model(
        steps, opts.device, noise, movements, phase_width=PHASE_IDDM["phase_width"],
        scale_transitions=True,
    )[0]  # fmt: skip
    name = str(opts.dtype).removeprefix("torch.")
    plain1 = single_stream(opts, model, grid, streams, opts.dtype, "predictive", repeats)[0]
    one = single_stream(opts, phase, grid, streams, opts.dtype, "predictive", repeats)
    B = 256
    plainB = batched(opts, model, grid, streams, B)
    manyB = batched(opts, phase, grid, streams, B)
    table.add(**{
        "algorithm": "online phase + scales", "dtype": name, "B": 1,
        "p50 [ms/obs/stream]": one[0], "p99 [ms]": one[1], "x plain": one[0] / plain1,
    })  # fmt: skip
    table.add(**{
        "algorithm": "online phase + scales batched", "dtype": name, "B": B,
        "p50 [ms/obs/stream]": manyB, "x plain": manyB / plainB,
    })  # fmt: skip
    print(table.rows[-2:], flush=True)


def main(argv: list[str]) -> int:
    opts = parse_options(argv, "python -m benchmarks online_intention")
    table = run(opts)
    print(table.to_markdown(".3g"))
    table.to_json(opts.results_file("online_intention"))
    return 0


if __name__ == "__main__":
    import sys

    raise SystemExit(main(sys.argv[1:]))
