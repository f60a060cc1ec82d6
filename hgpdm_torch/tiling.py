r"""Tiles for the fused ``psi2`` contractions: their size per device, the fast exponential, and
the operation counts that say how far a step is from the hardware's floor.

The Gaussian-input second moment ``psi2 = E[k(x, X)^T k(x, X)]`` is an ``N x N`` matrix per input
Gaussian, ``exp(left @ right)`` with ``left [N, D+2]`` and ``right [D+2, N]``
(:func:`hgpdm_torch.expectations.rbf_psi2_exponent`), and every consumer reduces it right away:
against training weights (``beta^T psi2 beta``), group sums or ``K^-1`` (a trace). The fused path
(:class:`hgpdm_torch.settings.moment_path` ``"fused"``) evaluates it for a tile of input Gaussians
at a time and reduces each tile before the next, so no ``[B, N, N]`` tensor exists:

- a tile holds as many inputs as fit :func:`tile_budget` bytes: on a CPU one input at N = 500
  (the tile and its reductions stay in the L2/L3 cache, where the passes over it cost little),
  on a GPU hundreds (one launch per operation does the work of all of them);
- its exponential runs in place through :func:`exp_`, the faster of two vectorised
  implementations for the device.

:class:`OpCount` counts what a step must compute (exponentials and multiply-adds); with the
device's measured rates (a large GEMM and a large exponential timed in the same process,
``benchmarks/_common.py``) it gives the step's floor, against which the benchmarks report their
times.
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from dataclasses import dataclass
from typing import TypeVar

import numpy as np
import torch
from torch.utils.checkpoint import checkpoint

from . import native, settings

T = TypeVar("T")

__all__ = [
    "CPU_STREAM_CHUNK",
    "KEEP_FOR_BACKWARD_BYTES",
    "NATIVE_STREAM_CHUNK",
    "OpCount",
    "differentiable_tile",
    "exp_",
    "keeps_tiles",
    "per_tile",
    "stream_chunk",
    "tile_budget",
]

#: Bytes of one psi2 tile on a CPU: the tile and its weight contractions stay in the cache (on
#: the 2-core EPYC of the development machines, 1 MB L2 per core and a shared L3: N = 500
#: streams one at a time ran the shared transition at 1.0 ms per stream, two at a time at 1.1).
CPU_TILE_BYTES = 2**21
#: Bytes of one psi2 tile on an accelerator: large enough that each launch does the work of
#: hundreds of input Gaussians (at N = 500 in float64 about 500 tiles' worth of psi2 alone),
#: small enough to leave room for the rest of a step; at most an eighth of the device's memory.
GPU_TILE_BYTES = 2**30


def tile_budget(device: torch.device) -> int:
    """Bytes of one ``psi2`` tile on ``device``: :class:`hgpdm_torch.settings.tile_bytes` when
    set, else :data:`CPU_TILE_BYTES` on a CPU and :data:`GPU_TILE_BYTES` (at most an eighth of
    the device's total memory) on an accelerator. A property of the device, never of the
    moment's free memory, so that the tiles, and with them the rounding, repeat from run to
    run."""
    fixed = settings.tile_bytes.get()
    if fixed is not None:
        return fixed
    if device.type == "cpu":
        return CPU_TILE_BYTES
    if device.type == "cuda":
        total = torch.cuda.get_device_properties(device).total_memory
        return max(1, min(GPU_TILE_BYTES, total // 8))
    return GPU_TILE_BYTES


#: Under autograd, the ``psi2`` of all tiles together up to this many bytes is kept for the
#: backward pass; beyond it every tile is recomputed there (``torch.utils.checkpoint``), so
#: memory stays bounded. Recomputing costs a second exponential per entry: VB's L-BFGS on a
#: window of an H-GPDM with N = 912 ran 20% slower with every tile recomputed.
KEEP_FOR_BACKWARD_BYTES = 2**28


def keeps_tiles(entries: int, dtype: torch.dtype) -> bool:
    """Whether ``entries`` of ``psi2`` (all tiles of a call) are kept for the backward pass
    (:data:`KEEP_FOR_BACKWARD_BYTES`) instead of recomputed."""
    return entries * dtype.itemsize <= KEEP_FOR_BACKWARD_BYTES


def differentiable_tile(fn: Callable[..., T], *args: torch.Tensor, keep: bool) -> T:
    """``fn(*args)`` for one tile under autograd: its intermediates kept for the backward pass
    (``keep``, :func:`keeps_tiles`) or recomputed there (``torch.utils.checkpoint``)."""
    return fn(*args) if keep else checkpoint(fn, *args, use_reentrant=False)


def per_tile(entries: int, dtype: torch.dtype, device: torch.device) -> int:
    """How many input Gaussians, each with ``entries`` psi2 entries, one tile holds (>= 1)."""
    return max(1, tile_budget(device) // max(1, entries * dtype.itemsize))


#: Streams an online filter updates together on a CPU on the fused path. The psi2 work is tiled
#: inside the transition whatever the chunk; the rest of a step (measurement update, belief,
#: mixture: dozens of small operations per chunk) costs per stream, at N = 500, K = 25, one
#: thread: 0.21 ms in chunks of 2, 0.074 of 8, 0.039 of 32, 0.038 of 64, 0.029 of 256. Each
#: stream of a chunk holds O(N Dx) numbers while the chunk runs (about 70 KB at N = 500).
CPU_STREAM_CHUNK = 32
#: Streams updated together on a CPU where the compiled kernel (:mod:`hgpdm_torch.native`) runs
#: the transition: it keeps no psi2 tile nor O(N Dx) factors, so a stream of a chunk holds only
#: the rest of the update's temporaries (about 40 KB at N = 500, K = 25, Dz = 15), and larger
#: chunks spread the update's small operations further. At B = 256, N = 500, one thread: 0.77
#: ms per stream in chunks of 16, 0.57 of 32, 0.56 of 64, 0.52 of 128.
NATIVE_STREAM_CHUNK = 128


def stream_chunk(
    n: int, workspace: int, dtype: torch.dtype, device: torch.device, compiled: bool = False
) -> int:
    """Default number of streams updated together (``OnlineIntentionFilter(chunk_size=None)``).

    Args:
        n: N, the transition GP's training (or pseudo-) inputs.
        workspace: entries of the psi2 tile work space one stream needs (the transition's
            ``workspace()``).
        compiled: whether the transition runs on the compiled CPU kernel (its
            ``compiled()``).

    On the materialised path the earlier default, ``2^19 / N^2`` (its ``[chunk, N, N]``
    temporaries in cache); on the fused path :data:`CPU_STREAM_CHUNK` on a CPU
    (:data:`NATIVE_STREAM_CHUNK` with the compiled kernel), and on an accelerator as many streams
    as one tile holds (:func:`per_tile`), so that one launch per operation updates them all.
    """
    if settings.moment_path.get() == "materialised":
        return max(1, 2**19 // (n * n))
    if device.type == "cpu":
        return NATIVE_STREAM_CHUNK if compiled else CPU_STREAM_CHUNK
    return per_tile(workspace, dtype, device)


@functools.cache
def _numpy_is_faster(dtype: torch.dtype) -> bool:
    """Whether NumPy's exponential runs on AVX-512 for ``dtype`` here.

    Measured on the development machines (AMD EPYC with AVX-512, one thread, 250,000 entries in
    cache): torch's ``exp_`` 0.62 G/s in float64 and 1.2 G/s in float32, NumPy's 1.24 and 2.2
    G/s. NumPy's exponential has its own AVX-512 kernels; on machines without AVX-512 its float64
    loop is not vectorised the same way, so torch's is kept there. The choice depends on the
    machine only, never on timing, so that results repeat from run to run.
    """
    if dtype not in (torch.float32, torch.float64):
        return False
    try:
        from numpy.lib.introspect import opt_func_info
    except ImportError:  # NumPy < 2.0 has no introspection of its dispatch
        return False
    sig = "dd" if dtype == torch.float64 else "ff"
    current = opt_func_info(func_name="^exp$").get("exp", {}).get(sig, {}).get("current", "")
    return "AVX512" in current


def exp_(t: torch.Tensor) -> torch.Tensor:
    """``t.exp_()`` by the fastest vectorised exponential for ``t``'s device and dtype.

    For a contiguous float64 CPU tensor that needs no gradient, the compiled kernel's where it
    runs (:func:`hgpdm_torch.native.exp_`, within 2 ulp: 2.0 G/s against NumPy's 1.1-1.2 on the
    development machines); else for a contiguous CPU tensor NumPy's where it runs on AVX-512
    (:func:`_numpy_is_faster`); torch's everywhere else (GPU, autograd, other dtypes). Overflow
    gives ``inf`` as torch's does, without a NumPy warning. Returns ``t``.
    """
    if t.is_contiguous() and native.usable(t):
        return native.exp_(t)
    if (
        t.device.type == "cpu"
        and not t.requires_grad
        and t.is_contiguous()
        and _numpy_is_faster(t.dtype)
    ):
        a = t.numpy()
        with np.errstate(over="ignore", under="ignore"):
            np.exp(a, out=a)
        return t
    return t.exp_()


@dataclass(frozen=True)
class OpCount:
    """Work of a computation: ``exps`` exponentials and ``madds`` multiply-adds (a multiply, an
    add or one of each), per input Gaussian (stream) unless said otherwise."""

    exps: float = 0.0
    madds: float = 0.0

    def __add__(self, other: OpCount) -> OpCount:
        return OpCount(self.exps + other.exps, self.madds + other.madds)

    def __mul__(self, times: float) -> OpCount:
        return OpCount(self.exps * times, self.madds * times)

    __rmul__ = __mul__

    def seconds(self, exp_rate: float, madd_rate: float) -> float:
        """The floor: the time at the measured rates (exponentials and multiply-adds per second;
        one GEMM multiply-add is two flops)."""
        return self.exps / exp_rate + self.madds / madd_rate
