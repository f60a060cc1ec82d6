r"""The compiled CPU kernel of the fused ``psi2`` contraction, and its exponential.

The shared transition's Gaussian-input second moment ``psi2 = exp(left @ right)`` (``N x N`` per
stream) is reduced against ``K^-1`` (group sums ``T``) and the training weights (pairs of weight
dimensions per pair of groups, ``S``) in one pass, eight columns at a time in AVX-512 registers
(``native_psi2.c``): in torch the same work is a product, an exponential and four reductions, each
reading and writing the 2 MB block (N = 500), and small matrix products whose inner dimension is a
group's 5 points. The exponential is the kernel's own (within 2 ulp, :func:`exp_`, about twice
the rate of NumPy's AVX-512 one). The same source runs the online filter's whole predictive step
(:func:`predictive_step`), Monte-Carlo planning's particles and their values
(:func:`particle_shared`, :func:`particles`, :func:`particle_values`, :func:`rbf_values`) and
torch's categorical and normal draws from torch's own uniforms (:func:`categorical_normal`).

The C source ships with the package and is compiled on first use with the machine's C compiler
(``$CC``, else ``cc``, ``gcc`` or ``clang``) and ``-O3 -march=native`` into a cache folder
(``$HGPDM_TORCH_CACHE``, else ``$XDG_CACHE_HOME/hgpdm_torch`` or ``~/.cache/hgpdm_torch``), named
by a hash of the source, the compiler and the CPU's features, so that a cache shared between
unlike machines never loads code built for another CPU. It is used where:

- the CPU has AVX-512F and DQ (where it was measured; elsewhere the torch path runs, which is
  the faster one known there), on x86-64 Linux or macOS;
- the computation is float64 on the CPU and needs no gradient (autograd, float32 and GPUs take the
  torch path);
- :class:`hgpdm_torch.settings.native_kernels` is on (default; ``HGPDM_TORCH_NATIVE=0`` turns it
  off).

Where the compiler is missing or fails, one warning says so and the torch path runs.
"""

from __future__ import annotations

import ctypes
import functools
import hashlib
import os
import platform
import shutil
import subprocess
import sys
import tempfile
import threading
import warnings
from pathlib import Path
from typing import NamedTuple

import torch

from . import settings

__all__ = [
    "SOURCE",
    "available",
    "cache_dir",
    "categorical_normal",
    "clear_scratch",
    "exp_",
    "ParticleArgs",
    "particle_block",
    "particle_shared",
    "particle_values",
    "particles",
    "predictive_step",
    "psi2_groups",
    "rbf_forms",
    "rbf_values",
    "scratch",
    "supported",
    "usable",
]

#: The kernel's C source, shipped with the package.
SOURCE = Path(__file__).with_name("native_psi2.c")
#: Largest weight dimension (Dx) the kernel takes; beyond it the torch path runs.
MAX_D = 8
_FLAGS = ("-O3", "-march=native", "-fPIC", "-shared", "-fno-math-errno")
_LANES = 8  # native_psi2.c's LANES: particles per block
_LIBS = ("-lm",)


@functools.cache
def _cpu_features() -> frozenset[str]:
    """The CPU features NumPy detected at import (its dispatch table), or none if unknown."""
    try:
        from numpy._core._multiarray_umath import __cpu_features__
    except ImportError:  # NumPy < 2
        try:
            from numpy.core._multiarray_umath import __cpu_features__
        except ImportError:
            return frozenset()
    return frozenset(k for k, v in __cpu_features__.items() if v)


@functools.cache
def supported() -> bool:
    """Whether this CPU can run the kernel: x86-64 with AVX-512F and DQ (NumPy's CPU feature
    detection), on Linux or macOS."""
    if platform.machine().lower() not in ("x86_64", "amd64") or sys.platform == "win32":
        return False
    return {"AVX512F", "AVX512DQ"} <= _cpu_features()


def cache_dir() -> Path:
    """Folder of the compiled kernels (module docstring)."""
    if "HGPDM_TORCH_CACHE" in os.environ:
        return Path(os.environ["HGPDM_TORCH_CACHE"])
    base = os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache"
    return Path(base) / "hgpdm_torch"


def _compiler() -> str | None:
    for name in (os.environ.get("CC"), "cc", "gcc", "clang"):
        if name and shutil.which(name):
            return shutil.which(name)
    return None


def _warn(why: str) -> None:
    warnings.warn(
        f"hgpdm_torch.native: {why}; the fused psi2 contraction runs in torch instead (on this "
        "CPU about twice as slow per batched online update). Install a C compiler (gcc or "
        "clang) or set CC, or set HGPDM_TORCH_NATIVE=0 to silence this.",
        RuntimeWarning,
        stacklevel=3,
    )


@functools.cache
def _library() -> ctypes.CDLL | None:
    """The compiled kernel, built into :func:`cache_dir` if it is not there; ``None`` (with one
    warning) where no compiler is found or the build fails."""
    cc = _compiler()
    if cc is None:
        _warn("no C compiler found (tried $CC, cc, gcc, clang)")
        return None
    try:
        version = subprocess.run(
            [cc, "--version"], capture_output=True, text=True, timeout=60, check=True
        ).stdout
    except (OSError, subprocess.SubprocessError) as exc:
        _warn(f"the C compiler {cc} does not run ({exc})")
        return None
    cpu = ",".join(sorted(_cpu_features()))
    key = hashlib.sha256(
        b"\0".join(
            s.encode() for s in (SOURCE.read_text(), cc, version, " ".join(_FLAGS + _LIBS), cpu)
        )
    ).hexdigest()[:16]
    target = cache_dir() / f"native_psi2_{key}.so"
    if not target.exists():
        try:
            target.parent.mkdir(parents=True, exist_ok=True)
            # built under a temporary name and renamed: processes building at once never load a
            # half-written library
            fd, tmp = tempfile.mkstemp(suffix=".so", dir=target.parent)
            os.close(fd)
        except OSError as exc:
            _warn(f"cannot write the cache folder {target.parent} ({exc}); set HGPDM_TORCH_CACHE")
            return None
        try:
            run = subprocess.run(
                [cc, *_FLAGS, "-o", tmp, str(SOURCE), *_LIBS],
                capture_output=True,
                text=True,
                timeout=300,
            )
            if run.returncode != 0:
                _warn(f"compiling {SOURCE.name} with {cc} failed: {run.stderr.strip()[-500:]}")
                return None
            os.replace(tmp, target)
        except (OSError, subprocess.SubprocessError) as exc:
            _warn(f"compiling {SOURCE.name} with {cc} failed ({exc})")
            return None
        finally:
            if os.path.exists(tmp):
                os.unlink(tmp)
    lib = ctypes.CDLL(str(target))
    ptr, i64 = ctypes.c_void_p, ctypes.c_int64
    lib.hgpdm_exp_f64.argtypes = [i64, ptr]
    lib.hgpdm_exp_f64.restype = None
    lib.hgpdm_psi2_groups_f64.argtypes = [i64] * 6 + [ptr] * 14
    lib.hgpdm_psi2_groups_f64.restype = ctypes.c_int
    f64 = ctypes.c_double
    lib.hgpdm_predictive_step_f64.argtypes = [i64] * 9 + [ptr] * 12 + [f64] * 2 + [ptr] * 7
    lib.hgpdm_predictive_step_f64.restype = ctypes.c_int
    lib.hgpdm_rbf_forms_f64.argtypes = [i64, i64, ptr, ptr, f64, ptr, ptr, ptr]
    lib.hgpdm_rbf_forms_f64.restype = ctypes.c_int
    lib.hgpdm_mcp_shared_f64.argtypes = [i64] * 8 + [ptr] * 14
    lib.hgpdm_mcp_shared_f64.restype = ctypes.c_int
    lib.hgpdm_mcp_particles_f64.argtypes = [i64] * 5 + [ptr] * 5 + [f64] * 2 + [ptr] * 7
    lib.hgpdm_mcp_particles_f64.restype = ctypes.c_int
    lib.hgpdm_rbf_values_f64.argtypes = [i64] * 6 + [ptr] * 6 + [f64] + [ptr] * 3
    lib.hgpdm_rbf_values_f64.restype = ctypes.c_int
    lib.hgpdm_mcp_values_f64.argtypes = (
        [i64] * 5
        + [ptr] * 5
        + [f64] * 2
        + [ptr] * 2
        + [i64] * 3
        + [ptr] * 3
        + [f64]
        + [ptr]
        + [i64]
        + [ptr] * 2
    )
    lib.hgpdm_mcp_values_f64.restype = ctypes.c_int
    lib.hgpdm_draws_f64.argtypes = [i64, i64, ptr, i64, ptr, ptr, ptr, ptr]
    lib.hgpdm_draws_f64.restype = ctypes.c_int
    return lib


def _loaded() -> ctypes.CDLL:
    """The compiled library; ``RuntimeError`` where it is not available."""
    lib = _library()
    if lib is None:
        raise RuntimeError("hgpdm_torch.native is not available here: check native.available()")
    return lib


def available() -> bool:
    """Whether the kernel runs here: a supported CPU, :class:`~hgpdm_torch.settings.native_kernels`
    on, and a compiled library (built on the first call; a warning if it cannot be)."""
    return settings.native_kernels.get() and supported() and _library() is not None


def usable(*tensors: torch.Tensor) -> bool:
    """Whether the kernel may take these tensors: :func:`available`, and all float64 on the CPU,
    none of them recording a gradient (one that requires it while autograd is on: autograd,
    float32 and GPUs take the torch path)."""
    grad = torch.is_grad_enabled()
    return (
        all(
            t.is_cpu and t.dtype == torch.float64 and not (grad and t.requires_grad)
            for t in tensors
        )
        and available()
    )


_scratch = threading.local()


def scratch(numel: int, slot: int = 0) -> torch.Tensor:
    """A float64 CPU buffer of ``numel`` entries, reused by this thread's later calls with the same
    ``slot`` (its contents are not kept between calls that overlap).

    The kernel's outputs are megabytes per call; a fresh allocation of that size is new memory
    from the operating system each time, whose first touch costs a page fault per 4 KB (at N =
    500 this had made the kernel 1.6 times slower inside the filter than alone).
    """
    bufs = getattr(_scratch, "bufs", None)
    if bufs is None:
        bufs = _scratch.bufs = {}
    buf = bufs.get(slot)
    if buf is None or buf.numel() < numel:
        buf = bufs[slot] = torch.empty(numel, dtype=torch.float64, device="cpu")
    return buf if buf.numel() == numel else buf[:numel]  # a call of the same size: no view


def clear_scratch() -> None:
    """Free this thread's :func:`scratch` buffers; the next call allocates its own again (so
    that a measurement of one call's memory counts its work space)."""
    _scratch.__dict__.pop("bufs", None)


def _check(name: str, t: torch.Tensor, shape: tuple[int, ...]) -> int:
    if t.dtype != torch.float64 or not t.is_cpu or not t.is_contiguous():
        raise TypeError(f"{name} must be a contiguous float64 CPU tensor, got {t.dtype} {t.device}")
    if t.shape != shape:
        raise ValueError(f"{name} must have shape {shape}, got {tuple(t.shape)}")
    return t.data_ptr()


def exp_(t: torch.Tensor) -> torch.Tensor:
    """``t.exp_()`` by the kernel's exponential (within 2 ulp; ``inf`` beyond 709.78, 0 below
    -745.13, NaN kept); ``t`` a contiguous float64 CPU tensor. Returns ``t``."""
    ptr = _check("t", t, tuple(t.shape))
    lib = _loaded()
    lib.hgpdm_exp_f64(t.numel(), ptr)
    return t


def categorical_normal(
    prob: torch.Tensor, num: int, dz: int, generator: torch.Generator | None = None
) -> tuple[torch.Tensor, torch.Tensor]:
    """``torch.multinomial(prob, num, replacement=True, generator=generator)`` and then
    ``torch.randn(num, dz, generator=generator, dtype=torch.float64)`` (``native_psi2.c``) from
    one draw of torch's uniforms, in torch's forms: the same grid values (its cumulative
    distribution and bisection, in float64) and normals (its Box-Muller form, with the log, sine
    and cosine vectorised: within a few ulp of torch's; torch calls libm for each, 17 ns a draw
    on the development machine, these take 5 ns), the generator left where torch's two calls
    leave it. One draw or fewer than 16 normals (which torch draws another way): torch's own
    two calls.

    Args:
        prob: ``[K]`` float64 CPU, non-negative with a positive sum (normalised here; else
            ``ValueError``, the uniforms drawn).
        num: draws.
        dz: normals per draw.
        generator: a CPU generator, or ``None`` for torch's default.

    Returns:
        ``g [num]`` int64 in ``0 .. K - 1`` and ``eps [num, dz]``.
    """
    n = num * dz
    if n < 16 or num < 2:  # torch draws one value, or fewer than 16 normals, another way
        g = torch.multinomial(prob, num, replacement=True, generator=generator)
        return g, torch.randn(num, dz, generator=generator, dtype=torch.float64, device="cpu")
    K = prob.shape[0]
    ptr = _check("prob", prob, (K,))
    f64 = {"dtype": torch.float64, "device": "cpu"}  # whatever torch's default device
    u = torch.rand(num + n + (16 if n % 16 else 0), generator=generator, **f64)
    g, eps = torch.empty(num, dtype=torch.int64, device="cpu"), torch.empty(num, dz, **f64)
    code = _loaded().hgpdm_draws_f64(
        num, K, ptr, n, u.data_ptr(), g.data_ptr(), eps.data_ptr(), scratch(K, 6).data_ptr()
    )
    if code:  # 1 (2, fewer than 16 normals, is torch's above)
        raise ValueError("prob must be non-negative and finite with a positive sum")
    return g, eps


def rbf_forms(
    Sigma: torch.Tensor, weight: torch.Tensor, coef: float
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The quadratic forms of one RBF term's ``psi2`` (with itself) and ``psi1`` for each input
    covariance, as :func:`~hgpdm_torch.expectations.rbf_psi2_quadratic` and
    :func:`~hgpdm_torch.expectations.rbf_psi1_quadratic` compute them in torch (``native_psi2.c``;
    at one input Gaussian some 80 small torch operations, a fifth of a single stream's update).

    Args:
        Sigma: ``[S, D, D]`` input covariances.
        weight: ``[D]`` the term's weights ``w`` (``k = coef exp(-sum_a w_a d_a^2 / 2)``).
        coef: the term's coefficient.

    Returns:
        ``forms [S, 4, D, D]`` (``H``, ``M_a``, ``M_b``, ``P``) and ``const [S, 2]`` (psi2's
        ``c`` and psi1's ``c_1 + log coef``): :func:`psi2_groups`'s operands; and ``status
        [S]`` (int64: 1 where a covariance has a NaN or inf entry or ``I + S Sigma S`` did not
        factorise: that stream's forms are undefined; torch's raise there, or add jitter).
    """
    s, d = Sigma.shape[0], weight.shape[0]
    sigma_ptr = _check("Sigma", Sigma, (s, d, d))
    w_ptr = _check("weight", weight, (d,))
    forms = Sigma.new_empty(s, 4, d, d)
    const = Sigma.new_empty(s, 2)
    status = torch.empty(s, dtype=torch.int64, device=Sigma.device)  # the kernel sets each
    lib = _loaded()
    if s:
        code = lib.hgpdm_rbf_forms_f64(
            s, d, sigma_ptr, w_ptr, float(coef), forms.data_ptr(), const.data_ptr(),
            status.data_ptr(),
        )  # fmt: skip
        _ran(code, d)
    return forms, const, status


def psi2_groups(
    points: torch.Tensor,
    cols: torch.Tensor,
    mu: torch.Tensor,
    forms: torch.Tensor,
    const: torch.Tensor,
    log_phase: torch.Tensor | None,
    beta: torch.Tensor,
    betac: torch.Tensor,
    kinv: torch.Tensor,
    phi_t: torch.Tensor,
    groups: int,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Group sums of ``psi2`` against ``K^-1``, its weighted second moments for every grid value,
    and ``psi1``, per stream (``native_psi2.c``), with ``log psi2_ij = d_i^T H d_j + d_i^T M_a
    d_i + d_j^T M_b d_j + c + lp_i + lp_j``, ``log psi1_i = d_i^T P d_i + c_1 + lp_i`` and ``d = x
    - mu`` (:func:`~hgpdm_torch.expectations.rbf_psi2_quadratic` and
    :func:`~hgpdm_torch.expectations.rbf_psi1_quadratic`, plus the log phase factors ``lp``).

    Args:
        points: ``[N, D]`` the points, in group order ``(u, l)``, ``N = U L``.
        cols: ``[Np]`` int64, the point of each column; columns in the order ``(m, v)`` with v
            padded to ``Up`` (a multiple of 8), ``Np = L Up``: column ``m Up + v`` is point
            ``(v, m)`` (a padding column names any point: its weights are 0).
        mu: ``[S, D]`` each stream's input mean.
        forms: ``[S, 4, D, D]`` each stream's ``H``, ``M_a``, ``M_b`` and ``P``.
        const: ``[S, 2]`` each stream's ``c`` and ``c_1``.
        log_phase: ``[S, N]`` each point's log phase factor per stream, or ``None``.
        beta: ``[N, D]`` each point's weights (``D <= MAX_D``).
        betac: ``[D, Np]`` the weights of each column's point (0 at padding columns).
        kinv: ``[N, Np]`` ``K^-1`` (rows as ``points``, columns as ``cols``; 0 at padding).
        phi_t: ``[Up, Kp]`` ``phi[k, v]`` of grid value k and group v (0 at padding v and at
            ``k >= K``; Kp a multiple of 8).
        groups: U.

    Returns:
        Views of this thread's :func:`scratch` buffers, overwritten by its next call:
        ``T [S, U, Up]`` with ``T[s, u, v] = sum_{l, m} psi2 K^-1`` over the block of groups
        ``(u, v)`` (0 for padding v), and ``out [S, D (D + 1) / 2 + 1, Kp]`` with ``out[s, (a,
        b), k] = sum_ij phi[k, u_i] beta_ia psi2_ij beta_jb phi[k, u_j]`` for the pairs ``a <=
        b`` in row-major order, then the trace row ``out[s, -1, k] = sum_uv phi[k, u] T[s, u,
        v] phi[k, v]`` (``tr(K^-1 psi2)`` of value k, contracted in the kernel as each row of T
        is complete: in torch, a small-inner-dimension product over ``S U`` rows had cost a
        tenth of the filter's update). Then ``psi1 [S, N]``.
    """
    dims, ptrs = _contraction(
        (points, cols, mu, forms, const, log_phase, beta, betac, kinv, phi_t, groups)
    )
    s, U, _, up, d, kp = dims
    n, pairs = points.shape[0], d * (d + 1) // 2
    # outputs and work space in this thread's scratch buffers: valid until its next call
    T = scratch(s * U * up, 0).view(s, U, up)
    out = scratch(s * (pairs + 1) * kp, 1).view(s, pairs + 1, kp)
    p1 = scratch(s * n, 3).view(s, n)
    work = scratch(_work(dims, n), 2)
    if s:
        code = _loaded().hgpdm_psi2_groups_f64(
            *dims, *ptrs, T.data_ptr(), out.data_ptr(), p1.data_ptr(), work.data_ptr()
        )
        _ran(code, d)
    return T, out, p1


def predictive_step(
    contraction: tuple,
    trans: torch.Tensor,
    meas: torch.Tensor,
    rank: int,
    keep: float,
    temperature: float,
    z: torch.Tensor,
    log_belief: torch.Tensor,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """The online filter's predictive step for S streams in one call (``native_psi2.c``): per
    stream, :func:`psi2_groups`'s contraction at its state, the transition moments of the K grid
    values from it, the linear measurement's GP-ADF update of each (``rank`` R its latent span),
    the belief step ``keep B + E / temperature`` and the moment-matched mixture.

    Args:
        contraction: :func:`psi2_groups`'s arguments, ``mu [S, D]`` the states' means and the
            forms those of their covariances.
        trans: ``[K U + K + 2 D + 1]`` the transition's ``phi [K, U]``, process noise ``[K]``,
            output scales squared ``[D]``, offset ``[D]`` and kernel coefficient.
        meas: ``[Dz R + R D + D D + 2 Dz + 2]`` the measurement's ``U [Dz, R]``, ``R [R, D]``,
            ``Q [D, D]``, offset ``[Dz]``, scale ``[Dz]``, noise and log-scale term.
        keep: ``1 - forgetting``; temperature: ``T > 0``.
        z: ``[S, Dz]`` observations (an all-NaN row: missing); log_belief: ``[S, K]``.

    Returns:
        ``mean [S, D]``, ``cov [S, D, D]``, ``log_belief [S, K]`` and ``status [S]`` (int64: 1
        where an innovation covariance did not factorise, and that stream's outputs are
        undefined: the caller's torch path takes it).
    """
    dims, ptrs = _contraction(contraction)
    s, U, _, _, d, _ = dims
    K, dz = log_belief.shape[-1], z.shape[-1]
    z_ptr, lb_ptr = _check("z", z, (s, dz)), _check("log_belief", log_belief, (s, K))
    tail = U * d + K * (d * d + d + 2) + d + dz + 2 * rank + 2 * rank * d + 3 * rank * rank
    step_ptrs, work = _step_operands(dims, trans, meas, rank, K, dz, tail)
    ptrs += step_ptrs
    mean, lb = z.new_empty(s, d), z.new_empty(s, K)
    cov, status = z.new_empty(s, d, d), torch.zeros(s, dtype=torch.int64, device=z.device)
    if s:
        code = _loaded().hgpdm_predictive_step_f64(
            *dims, K, dz, rank, *ptrs, float(keep), float(temperature), z_ptr, lb_ptr,
            mean.data_ptr(), cov.data_ptr(), lb.data_ptr(), status.data_ptr(), work.data_ptr(),
        )  # fmt: skip
        _ran(code, d)
    return mean, cov, lb, status


def particle_block(d: int, dz: int, rank: int) -> int:
    """Entries of one grid value's block of :func:`particle_shared`'s state."""
    return d + 2 * d * d + rank * d + rank * rank + rank + 2 + dz + dz * dz


def particle_shared(
    contraction: tuple, trans: torch.Tensor, meas: torch.Tensor, rank: int, K: int, dz: int
) -> tuple[torch.Tensor, bool]:
    """What all Monte-Carlo particles of one belief share (``native_psi2.c``): the K transition
    moments at the belief (:func:`psi2_groups`'s contraction at one input), the linear
    measurement's factors at each (as :func:`predictive_step` forms them) and the Cholesky
    factor of each next observation's covariance (as
    :meth:`~hgpdm_torch.inference.intention.measurement.LinearMeasurement.moments` forms it).

    Args:
        contraction: :func:`psi2_groups`'s arguments for the one belief (``mu [1, D]``).
        trans: as for :func:`predictive_step`.
        meas: as for :func:`predictive_step`.
        rank: as for :func:`predictive_step`.
        K: grid values.
        dz: observed dims.

    Returns:
        ``shared [K, particle_block(D, Dz, rank)]`` (per value ``m``, ``P``, ``P - A^T A``,
        ``A``, ``G = F^-1``, ``c``, ``1 / v``, the log-determinant, ``mz``, ``Lz``) and whether
        it is defined (``False`` where a covariance did not factorise: the caller's torch path
        takes over).
    """
    dims, ptrs = _contraction(contraction)
    s, U, L, up, d, kp = dims
    if s != 1:
        raise ValueError(f"particle_shared takes one belief, got {s}")
    tail = U * d + K * (d * d + d) + rank * d + 2 * rank * rank + 2 * d * dz + dz * dz
    step_ptrs, work = _step_operands(dims, trans, meas, rank, K, dz, tail)
    ptrs += step_ptrs
    shared = trans.new_empty(K, particle_block(d, dz, rank))
    code = _loaded().hgpdm_mcp_shared_f64(
        U, L, up, d, kp, K, dz, rank, *ptrs, shared.data_ptr(), work.data_ptr()
    )
    if code == 2:  # a covariance did not factorise
        return shared, False
    _ran(code, d)
    return shared, True


class ParticleArgs(NamedTuple):
    """The update of one belief (its :func:`particle_shared` state) on I observations
    (:func:`particles`, :func:`particle_values`): particle i observes ``z = mz_g + Lz_g
    noise_i`` for ``g = draws[i]``, or ``z = noise_i`` where ``draws`` is ``None``; a ``z`` that
    the filter's :class:`~hgpdm_torch.observations.ObservationCheck` would not use (``center``,
    ``limit``) is a prediction-only step, as in the filter.

    Attributes:
        shared: ``[K, particle_block(D, Dz, R)]``.
        meas: as for :func:`predictive_step`.
        dims: ``(D, Dz, R)``.
        center: ``[Dz]``, the check's centre.
        limit: ``[Dz]``, its limit (``inf``: finiteness alone).
        log_belief: ``[K]`` normalised.
        keep: as for :func:`predictive_step`.
        temperature: as for :func:`predictive_step`.
        draws: ``[I]`` int64 grid values in ``0 .. K - 1``, or ``None``.
        noise: ``[I, Dz]`` standard normal draws, or the observations.
    """

    shared: torch.Tensor
    meas: torch.Tensor
    dims: tuple[int, int, int]
    center: torch.Tensor
    limit: torch.Tensor
    log_belief: torch.Tensor
    keep: float
    temperature: float
    draws: torch.Tensor | None
    noise: torch.Tensor


def particles(args: ParticleArgs) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """The online filter's update of one belief on I observations (``native_psi2.c``;
    :class:`ParticleArgs`).

    Returns:
        ``mean [I, D]``, ``cov [I, D, D]``, ``log_belief [I, K]`` and the observations ``z [I,
        Dz]``.
    """
    d, dz, rank = args.dims
    num, K = args.noise.shape[0], args.log_belief.shape[0]
    new = args.noise.new_empty
    mean, cov, lb, z = new(num, d), new(num, d, d), new(num, K), new(num, dz)
    code = _loaded().hgpdm_mcp_particles_f64(
        *_particle_ptrs(args), mean.data_ptr(), cov.data_ptr(), lb.data_ptr(), z.data_ptr(),
        scratch(_particle_work(d, K, dz, rank), 4).data_ptr(),
    )  # fmt: skip
    _ran(code, d)
    return mean, cov, lb, z


def particle_values(
    args: ParticleArgs,
    basis: tuple[torch.Tensor, torch.Tensor, torch.Tensor, float, bool],
    weights: torch.Tensor,
    first: int,
) -> torch.Tensor:
    """Each particle's best value over the actions ``first .. A - 1`` of :func:`rbf_values` of
    the beliefs :func:`particles` would return (``native_psi2.c``, one call: the particles'
    means, covariances and probabilities stay in the kernel's work space), the vectors'
    probabilities the mixture's normalised weights (``exp`` of the log-belief within a few
    ulp); NaN where one of the values is NaN.

    Args:
        args: the particles (:class:`ParticleArgs`).
        basis: as for :func:`rbf_values`.
        weights: as for :func:`rbf_values`.
        first: the first action of the maximum, in ``0 .. A - 1``.

    Returns:
        ``[I]``.
    """
    d, dz, rank = args.dims
    K = args.log_belief.shape[0]
    c, f, a, bias, basis_args = _basis_args(basis, weights, d, K)
    if not 0 <= first < a:
        raise ValueError(f"first must be an action in 0 .. {a - 1}, got {first}")
    out = args.noise.new_empty(args.noise.shape[0])
    work = scratch(_particle_work(d, K, dz, rank) + _values_work(c, f), 4)
    code = _loaded().hgpdm_mcp_values_f64(
        *_particle_ptrs(args), c, a, bias, *basis_args, first, out.data_ptr(), work.data_ptr()
    )
    _ran(code, d)
    return out


def _particle_ptrs(args: ParticleArgs) -> list:
    """The particle kernels' arguments up to their outputs, checked."""
    d, dz, rank = args.dims
    K, num, draws = args.log_belief.shape[0], args.noise.shape[0], args.draws
    if not 1 <= d <= MAX_D or not 1 <= rank <= min(d, dz):
        raise ValueError(
            f"dims must have 1 <= D <= {MAX_D} and rank in [1, min(D, Dz)], got {args.dims}"
        )
    ptrs = [
        _check("shared", args.shared, (K, particle_block(d, dz, rank))),
        _check("meas", args.meas, (_meas_size(d, dz, rank),)),
        _check("center", args.center, (dz,)),
        _check("limit", args.limit, (dz,)),
        _check("log_belief", args.log_belief, (K,)),
    ]
    g_ptr = None
    if draws is not None:
        if draws.dtype != torch.int64 or not draws.is_cpu or not draws.is_contiguous():
            raise TypeError(f"draws must be a contiguous int64 CPU tensor [{num}]")
        if draws.shape != (num,):
            raise ValueError(f"draws must have shape ({num},), got {tuple(draws.shape)}")
        low, high = torch.aminmax(draws) if num else (0, 0)
        if not 0 <= int(low) <= int(high) < K:
            raise ValueError(f"draws must be grid values in 0 .. {K - 1}")
        g_ptr = draws.data_ptr()
    noise_ptr = _check("noise", args.noise, (num, dz))
    return [num, d, K, dz, rank, *ptrs, float(args.keep), float(args.temperature), g_ptr, noise_ptr]


def _particle_work(d: int, K: int, dz: int, rank: int) -> int:
    """``native_psi2.c``'s PARTICLE_WORK: a block of particles' quantities, lane-last."""
    return dz + _LANES * (2 * dz + rank + 1 + 4 * K + K * d + d + d * d)


def _values_work(c: int, f: int) -> int:
    """``native_psi2.c``'s VALUES_WORK: the centres' norms and a block's vectors and features."""
    return c + _LANES * (f + c + 1)


def rbf_values(
    mean: torch.Tensor,
    cov: torch.Tensor,
    log_prob: torch.Tensor,
    basis: tuple[torch.Tensor, torch.Tensor, torch.Tensor, float, bool],
    weights: torch.Tensor,
) -> torch.Tensor:
    """Linear values of radial basis features of I beliefs' vectors (``native_psi2.c``), as
    :func:`~hgpdm_torch.decision.stopping.belief_vector`,
    :class:`~hgpdm_torch.decision.basis.RadialBasis` and
    :meth:`~hgpdm_torch.decision.lspi.LinearQ.values` compute them one after another: the
    vector ``[mean, upper triangle of cov, exp(log_prob)]`` (``F`` entries), standardised, its
    features ``exp(-eta |z - c|^2)`` for the C centres (then 1 where ``bias``) and their
    products with the weights.

    Args:
        mean: ``[I, D]``.
        cov: ``[I, D, D]``.
        log_prob: ``[I, K]``.
        basis: the fitted basis's ``(mean [F], std [F], centres [C, F], eta, bias)``.
        weights: ``[A, C + bias]``.

    Returns:
        ``[I, A]``.
    """
    num, d = mean.shape
    K = log_prob.shape[-1]
    c, f, a, bias, basis_args = _basis_args(basis, weights, d, K)
    ptrs = [
        _check("mean", mean, (num, d)),
        _check("cov", cov, (num, d, d)),
        _check("log_prob", log_prob, (num, K)),
    ]
    out = mean.new_empty(num, a)
    work = scratch(_values_work(c, f), 5)
    if num:
        _loaded().hgpdm_rbf_values_f64(
            num, d, K, c, a, bias, *ptrs, *basis_args, out.data_ptr(), work.data_ptr()
        )
    return out


def _basis_args(
    basis: tuple[torch.Tensor, torch.Tensor, torch.Tensor, float, bool],
    weights: torch.Tensor,
    d: int,
    K: int,
) -> tuple[int, int, int, int, list]:
    """The basis's and the weights' sizes ``(C, F, A, bias)`` and the values kernels' arguments
    ``mu, sd, centres, eta, Wq``, checked (:func:`rbf_values`)."""
    mu, sd, centres, eta, bias = basis
    c, f = centres.shape
    a = weights.shape[0]
    if f != d + d * (d + 1) // 2 + K:
        raise ValueError(f"centres must have F = {d + d * (d + 1) // 2 + K} columns, got {f}")
    ptrs = [
        _check("basis mean", mu, (f,)),
        _check("basis std", sd, (f,)),
        _check("centres", centres, (c, f)),
        float(eta),
        _check("weights", weights, (a, c + int(bias))),
    ]
    return c, f, a, int(bias), ptrs


def _meas_size(d: int, dz: int, rank: int) -> int:
    """Entries of a linear measurement's terms (:func:`predictive_step`'s ``meas``)."""
    return dz * rank + rank * d + d * d + 2 * dz + 2


def _step_operands(
    dims: tuple[int, ...], trans: torch.Tensor, meas: torch.Tensor, rank: int, K: int, dz: int,
    tail: int,
) -> tuple[list[int], torch.Tensor]:  # fmt: skip
    """The transition's and the measurement's terms, checked, and the work space of a step after
    the contraction (``tail`` entries beyond the contraction's outputs)."""
    _, U, L, up, d, kp = dims
    if not 1 <= rank <= min(d, dz) or K > kp:
        raise ValueError(f"rank must be in [1, min(D, Dz)] and K <= Kp, got {rank}, {K} > {kp}")
    ptrs = [
        _check("trans", trans, (K * U + K + 2 * d + 1,)),
        _check("meas", meas, (_meas_size(d, dz, rank),)),
    ]
    n = U * L
    return ptrs, scratch(_work(dims, n) + U * up + (d * (d + 1) // 2 + 1) * kp + n + tail, 2)


def _ran(code: int, d: int) -> None:
    """Raise unless the kernel ran (code 0; 1: D outside 1..MAX_D, nothing written)."""
    if code != 0:
        raise RuntimeError(f"the compiled kernel did not run (D = {d}, at most {MAX_D})")


def _work(dims: tuple[int, ...], n: int) -> int:
    """Entries of the contraction's work space per call (``native_psi2.c``'s PSI2_WORK)."""
    _, _, L, up, d, _ = dims
    np_ = L * up
    return (d + 1) * np_ + d * (d + 1) // 2 * up + (d + 1) * (n + np_) + 4 * up


_RANGES: dict[tuple[int, int], tuple[torch.Tensor, int, int]] = {}


def _index_range(index: torch.Tensor) -> tuple[int, int]:
    """The smallest and largest entry of ``index``, once per tensor and in-place version (a
    model's column layout, checked at every call, changes only with the model)."""
    key = (id(index), index._version)
    hit = _RANGES.get(key)
    if hit is None or hit[0] is not index:  # the stored tensor keeps its id from being reused
        low, high = torch.aminmax(index)
        if len(_RANGES) >= 16:
            _RANGES.clear()
        hit = _RANGES[key] = (index, int(low), int(high))
    return hit[1], hit[2]


def _contraction(args: tuple) -> tuple[tuple[int, ...], list[int | None]]:
    """The contraction's sizes ``(S, U, L, Up, D, Kp)`` and its operands' addresses, checked
    (:func:`psi2_groups`'s arguments ``args``); raises where the library is not available."""
    points, cols, mu, forms, const, log_phase, beta, betac, kinv, phi_t, groups = args
    n, d = points.shape
    s, np_, kp = mu.shape[0], cols.shape[0], phi_t.shape[1]
    U = groups
    L = n // U if U else 0
    if not U or n % U or np_ % L or (np_ // L) % 8 or kp % 8 or not 1 <= d <= MAX_D:
        raise ValueError(
            f"psi2_groups needs N = U L points, Np = L Up columns and Kp values with Up and Kp "
            f"multiples of 8 and 1 <= D <= {MAX_D}; got N = {n}, U = {U}, Np = {np_}, Kp = {kp}, "
            f"D = {d}"
        )
    if cols.dtype != torch.int64 or not cols.is_cpu or not cols.is_contiguous() or cols.dim() != 1:
        raise TypeError(
            f"cols must be a contiguous 1-D int64 CPU tensor, got {cols.dtype} {tuple(cols.shape)}"
        )
    low, high = _index_range(cols)  # an index out of range would read outside points
    if low < 0 or high >= n:
        raise ValueError(f"cols must index the {n} points, got values in [{low}, {high}]")
    up = np_ // L
    ptrs = [
        _check("points", points, (n, d)),
        cols.data_ptr(),
        _check("mu", mu, (s, d)),
        _check("forms", forms, (s, 4, d, d)),
        _check("const", const, (s, 2)),
        None if log_phase is None else _check("log_phase", log_phase, (s, n)),
        _check("beta", beta, (n, d)),
        _check("betac", betac, (d, np_)),
        _check("kinv", kinv, (n, np_)),
        _check("phi_t", phi_t, (up, kp)),
    ]
    _loaded()
    return (s, U, L, up, d, kp), ptrs
