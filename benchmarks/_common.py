"""Helpers shared by the benchmark modules: timing and the environment recorded with results."""

from __future__ import annotations

import argparse
import platform
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import torch

from hgpdm_torch.tiling import OpCount, exp_

RESULTS = Path(__file__).parent / "results"

#: process noise alpha_4 of the models timed in float32: the online filter refuses float32 for
#: smaller noises (alpha-bar's 1e-4, and 1e-2), whose evidence float32 cannot resolve to 0.1 nats
#: (docs, user guide); the cost per step does not depend on alpha_4
FLOAT32_NOISE = 0.1


def best_of(fn: Callable[[], object], repeats: int, device: torch.device | None = None) -> float:
    """Smallest wall-clock time of ``repeats`` calls of ``fn`` (seconds), waiting for the queued
    work of ``device`` (an accelerator) before each reading of the clock."""

    def sync() -> None:
        if device is not None and device.type == "cuda":
            torch.cuda.synchronize(device)

    times = []
    for _ in range(repeats):
        sync()
        start = time.perf_counter()
        fn()
        sync()
        times.append(time.perf_counter() - start)
    return min(times)


def environment() -> dict[str, object]:
    """torch version, processor and thread count, stored in every result's ``meta``."""
    return {
        "torch": torch.__version__,
        "machine": platform.processor() or platform.machine(),
        "threads": torch.get_num_threads(),
    }


def device_name(device: torch.device) -> dict[str, str]:
    """``{"device name": ...}`` for an accelerator (e.g. ``NVIDIA H200``); empty for the CPU,
    whose processor :func:`environment` records."""
    if device.type == "cuda":
        return {"device name": torch.cuda.get_device_name(device)}
    return {}


@dataclass(frozen=True)
class Options:
    """Command-line options shared by the benchmarks (:func:`parse_options`)."""

    quick: bool
    device: torch.device
    dtype: torch.dtype
    gpu_sizes: bool

    def results_file(self, name: str) -> Path:
        """``results/[gpu_]<name>[_<device>_<dtype>][_quick].json``: the default CPU float64
        run keeps its historical file name; a run at the accelerator sizes (``--gpu-sizes``)
        is ``gpu_<name>_<device>_<dtype>``; other runs do not overwrite either (and smoke runs
        stay ``*_quick.json``, which git ignores)."""
        tag = ""
        if self.gpu_sizes or self.device.type != "cpu" or self.dtype != torch.float64:
            tag += f"_{self.device.type}_{str(self.dtype).removeprefix('torch.')}"
        tag += "_quick" if self.quick else ""
        return RESULTS / f"{'gpu_' if self.gpu_sizes else ''}{name}{tag}.json"

    def meta(self) -> dict[str, object]:
        """What the result's ``meta`` records about the run (with :func:`environment`)."""
        return {
            **environment(),
            "quick": self.quick,
            "device": str(self.device),
            "dtype": str(self.dtype).removeprefix("torch."),
            "gpu sizes": self.gpu_sizes,
            **device_name(self.device),
        }

    def synchronize(self) -> None:
        """Wait for the device's queued work (a no-op on the CPU), before reading a clock."""
        if self.device.type == "cuda":
            torch.cuda.synchronize(self.device)

    def clock(self) -> float:
        """Seconds: CPU time of the process on the CPU (closer to an idle core's time on a
        shared machine), wall time after a synchronisation on an accelerator."""
        if self.device.type == "cpu":
            return time.process_time()
        self.synchronize()
        return time.perf_counter()


def parse_options(argv: list[str], prog: str) -> Options:
    """Parse ``[--quick] [--device DEVICE] [--dtype {float64,float32}] [--gpu-sizes]``.

    ``--gpu-sizes`` selects the problem sizes meant for an accelerator (each benchmark's
    docstring lists them); without it the CPU sizes are run, on any device.
    """
    parser = argparse.ArgumentParser(prog=prog)
    parser.add_argument("--quick", action="store_true", help="smoke mode: tiny sizes")
    parser.add_argument("--device", default="cpu", help="torch device, e.g. cpu or cuda")
    parser.add_argument("--dtype", default="float64", choices=sorted(DTYPES))
    parser.add_argument(
        "--gpu-sizes", action="store_true", help="the accelerator problem sizes (see docstring)"
    )
    args = parser.parse_args(argv)
    device = torch.device(args.device)
    if device.type == "cuda" and not torch.cuda.is_available():
        parser.error("--device cuda needs CUDA, which torch cannot find here")
    return Options(args.quick, device, DTYPES[args.dtype], args.gpu_sizes)


DTYPES = {"float64": torch.float64, "float32": torch.float32}


@dataclass(frozen=True)
class Rates:
    """What this device does per second, measured in this process (:func:`measure_rates`):
    multiply-adds in a large GEMM and exponentials in a large in-place ``exp``."""

    madd: float
    exp: float

    def floor_ms(self, ops: OpCount) -> float:
        """Milliseconds ``ops`` take at these rates: the floor of a computation."""
        return 1e3 * ops.seconds(self.exp, self.madd)

    def as_dict(self) -> dict[str, float]:
        return {"GEMM [Gmadd/s]": self.madd / 1e9, "exp [G/s]": self.exp / 1e9}


def measure_rates(device: torch.device, dtype: torch.dtype, repeats: int = 5) -> Rates:
    """The floor's rates on ``device`` in ``dtype``, best of ``repeats``: a square GEMM (1,024
    on a CPU, 8,192 on an accelerator) and the library's in-place exponential
    (:func:`hgpdm_torch.tiling.exp_`, NumPy's where it is the faster) over 2^20 entries in
    [-20, 0] (2^26 on an accelerator), each repeat on a fresh copy."""
    n, m = (1024, 2**20) if device.type == "cpu" else (8192, 2**26)
    a = torch.randn(n, n, dtype=dtype, device=device)
    b = torch.randn(n, n, dtype=dtype, device=device)
    gemm = best_of(lambda: a @ b, repeats, device)
    x = torch.empty(m, dtype=dtype, device=device).uniform_(-20.0, 0.0)
    copies = iter([x.clone() for _ in range(repeats)])
    expo = best_of(lambda: exp_(next(copies)), repeats, device)
    return Rates(madd=n**3 / gemm, exp=m / expo)


def peak_bytes(fn: Callable[[], object], device: torch.device) -> int:
    """Peak bytes allocated while ``fn()`` runs, above what was allocated before it.

    On an accelerator the allocator's peak statistic; on a CPU the running sum of the
    allocation and release events that ``torch.profiler`` records (in the order they happened).
    """
    if device.type == "cuda":
        torch.cuda.synchronize(device)
        before = torch.cuda.memory_allocated(device)
        torch.cuda.reset_peak_memory_stats(device)
        fn()
        torch.cuda.synchronize(device)
        return torch.cuda.max_memory_allocated(device) - before
    with torch.profiler.profile(
        activities=[torch.profiler.ProfilerActivity.CPU], profile_memory=True
    ) as prof:
        fn()
    events = [e for e in prof.profiler.kineto_results.events() if e.name() == "[memory]"]
    events.sort(key=lambda e: e.start_ns())
    current = peak = 0
    for e in events:
        current += e.nbytes()
        peak = max(peak, current)
    return peak


def largest_fitting(fits: Callable[[int], bool], cap: int = 2**14) -> int:
    """The largest ``B <= cap`` with ``fits(B)``, for a ``fits`` that holds up to some B and not
    beyond (e.g. "an update of B streams takes at most 33 ms"): B doubles from 1 until it
    fails, then bisection between the last two; 0 when ``fits(1)`` fails."""
    if not fits(1):
        return 0
    low, high = 1, 2
    while high <= cap and fits(high):
        low, high = high, 2 * high
    if high > cap:
        return low
    while high - low > 1:
        mid = (low + high) // 2
        low, high = (mid, high) if fits(mid) else (low, mid)
    return low
