"""Global settings of the toolkit, as context managers (the pattern of ``gpytorch.settings``).

:class:`debug` switches on the *debugging* checks of the library's hot loops: validation that
costs a host synchronisation (a GPU round trip) per step and only re-checks what the library
itself computed. The checks that protect users are not gated and always run:

- every public function validates its inputs (shape, dtype, finiteness, and for a Gaussian a
  symmetric positive semi-definite covariance) when called by the user;
- NaN/inf guards that decide what happens next (an observation rejected, a stream restarted, a
  Cholesky factor retried with jitter or a clear error raised) stay on, since nothing may
  return NaN silently and one bad stream must never spoil another.

Gated (run only under ``debug``): the symmetry and positive-semi-definiteness check (an
``eigvalsh`` and a host synchronisation) of the Gaussians that the filtering loops
(``filter_sequence``, :class:`~hgpdm_torch.inference.intention.OnlineIntentionFilter`, batch
intention inference, Monte-Carlo planning) pass from one step to the next. A covariance that
rounding has made indefinite there still cannot pass silently: the online filter checks every
stream's state with one batched Cholesky (:func:`~hgpdm_torch.linalg.positive_definite`) inside
the synchronisation each update makes anyway and restarts a stream whose state fails it, and
``filter_sequence`` (which batch intention inference runs) checks all its covariances once at
the end and raises a ``ValueError`` naming the first bad step; ``debug`` re-checks every input
of the step functions, to find where it first happened.

Example::

    from hgpdm_torch import settings

    with settings.debug(True):
        filter_sequence(transition, measurement, z, mu0, Sigma0)

:class:`moment_path` chooses how the Gaussian-input second moments ``psi2`` (``N x N`` per input
Gaussian) are reduced: ``"fused"`` (default) contracts them tile by tile without storing them per
input (:mod:`hgpdm_torch.tiling`), ``"materialised"`` is the earlier path that forms them for a
chunk of inputs and then reduces them; it stays for comparison in benchmarks and tests.
:class:`tile_bytes` overrides the tile size that :mod:`hgpdm_torch.tiling` picks per device.
:class:`native_kernels` lets the fused path run its compiled CPU kernel (:mod:`hgpdm_torch.native`)
where one is available (default on; the environment variable ``HGPDM_TORCH_NATIVE=0`` turns it off
for a process). :class:`quadrature_points` sets the Gauss-Hermite rule of the kernels without
closed-form expectations (:mod:`hgpdm_torch.quadrature`).

:func:`default_dtype` sets torch's default dtype for a block. :func:`snapshot` captures all of
these (and the default dtype) where a job is made: an executor's worker
(:mod:`hgpdm_torch.parallel`) is a fresh process that inherits none of them, so a job takes the
snapshot with it and runs in ``with snap.applied():``.
"""

from __future__ import annotations

import contextlib
import contextvars
import os
from collections.abc import Iterator
from dataclasses import dataclass
from types import TracebackType

import torch

__all__ = [
    "Snapshot",
    "debug",
    "default_dtype",
    "internal_step",
    "moment_path",
    "native_kernels",
    "quadrature_points",
    "snapshot",
    "tile_bytes",
    "validate_internal",
]

_debug = contextvars.ContextVar("hgpdm_torch_debug", default=False)
_internal = contextvars.ContextVar("hgpdm_torch_internal", default=False)
_path = contextvars.ContextVar("hgpdm_torch_moment_path", default="fused")
_tile = contextvars.ContextVar("hgpdm_torch_tile_bytes", default=None)
_quadrature = contextvars.ContextVar("hgpdm_torch_quadrature_points", default=None)
_native = contextvars.ContextVar(
    "hgpdm_torch_native_kernels", default=os.environ.get("HGPDM_TORCH_NATIVE", "1") != "0"
)


class _Setting:
    """A context manager setting one context variable for its block (per thread/async context)."""

    _var: contextvars.ContextVar

    def __init__(self, value: object) -> None:
        self.value = value
        self._token: contextvars.Token | None = None

    def __enter__(self) -> _Setting:
        self._token = self._var.set(self.value)
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        if self._token is not None:
            self._var.reset(self._token)
            self._token = None


class debug(_Setting):
    """Context manager (and flag) for the debugging checks of the hot loops (module docstring).

    ``with debug(True): ...`` switches them on for the block (``debug(False)`` off); the setting
    is per thread/async context. Default: off.

    Args:
        state: whether the checks run inside the block.
    """

    _var = _debug

    def __init__(self, state: bool = True) -> None:
        super().__init__(bool(state))

    @property
    def state(self) -> bool:
        """Whether the checks run inside the block."""
        return self.value

    @staticmethod
    def on() -> bool:
        """Whether the debugging checks run now."""
        return _debug.get()

    @staticmethod
    def off() -> bool:
        """Whether the debugging checks are skipped now."""
        return not _debug.get()


@contextlib.contextmanager
def internal_step() -> Iterator[None]:
    """Mark the enclosed calls as a hot loop's own: the Gaussians it passes to the library's
    public functions were computed by the library, so their structure check runs only under
    :class:`debug` (:func:`validate_internal`). Used inside the library, not by users."""
    token = _internal.set(True)
    try:
        yield
    finally:
        _internal.reset(token)


@contextlib.contextmanager
def default_dtype(dtype: torch.dtype) -> Iterator[None]:
    """Context in which ``torch.get_default_dtype()`` is ``dtype``; the previous one is
    restored (process-wide, as torch's setting is)."""
    previous = torch.get_default_dtype()
    torch.set_default_dtype(dtype)
    try:
        yield
    finally:
        torch.set_default_dtype(previous)


def validate_internal() -> bool:
    """Whether a structure check of a Gaussian should run now: always for a user's call,
    inside :func:`internal_step` only under :class:`debug`."""
    return _debug.get() or not _internal.get()


class moment_path(_Setting):
    """Context manager choosing how ``psi2`` is reduced (module docstring).

    Args:
        path: ``"fused"`` (the default outside any block) or ``"materialised"``.

    ``moment_path.get()`` is the current choice.
    """

    _var = _path
    choices = ("fused", "materialised")

    def __init__(self, path: str) -> None:
        if path not in self.choices:
            raise ValueError(f"path must be one of {self.choices}, got {path!r}")
        super().__init__(path)

    @staticmethod
    def get() -> str:
        """The path in effect: ``"fused"`` or ``"materialised"``."""
        return _path.get()


class _Count(_Setting):
    """A setting holding a positive int (``None`` outside any block: the default)."""

    #: the argument and what it must be, for the error message
    argument, unit = "value", "a positive int"

    def __init__(self, value: int) -> None:
        if isinstance(value, bool) or not isinstance(value, int) or value < 1:
            raise ValueError(f"{self.argument} must be {self.unit}, got {value!r}")
        super().__init__(value)

    @classmethod
    def get(cls) -> int | None:
        """The value in effect, or ``None`` for the default."""
        return cls._var.get()


class tile_bytes(_Count):
    """Context manager fixing the size of one ``psi2`` tile in bytes, instead of the device's
    default (:func:`hgpdm_torch.tiling.tile_budget`); e.g. small tiles to test the tiled loops.

    Args:
        size: positive int, bytes of the ``[tile, N, N]`` block evaluated at once (at least one
            input Gaussian per tile whatever the size).
    """

    _var = _tile
    argument, unit = "size", "a positive int (bytes)"

    def __init__(self, size: int) -> None:
        super().__init__(size)


class native_kernels(_Setting):
    """Context manager (and flag) letting the fused path use its compiled CPU kernel
    (:mod:`hgpdm_torch.native`: one pass over each ``psi2`` tile in registers, float64, CPUs with
    AVX-512) where it is available; ``native_kernels(False)`` keeps every contraction in torch,
    e.g. to compare the two in one process. Default: on, unless the environment variable
    ``HGPDM_TORCH_NATIVE`` is ``0``.

    Args:
        state: whether the compiled kernel may run inside the block.
    """

    _var = _native

    def __init__(self, state: bool = True) -> None:
        super().__init__(bool(state))

    @staticmethod
    def get() -> bool:
        """Whether the compiled kernel may run now."""
        return _native.get()


class quadrature_points(_Count):
    """Context manager setting the points per Gaussian dimension of the Gauss-Hermite rule that
    integrates kernels without closed-form expectations (:mod:`hgpdm_torch.quadrature`;
    ``n^D`` nodes), instead of :func:`~hgpdm_torch.quadrature.default_points`.

    Args:
        points: an int >= 1 (1 evaluates the kernel at the mean only).
    """

    _var = _quadrature
    argument = "points"

    def __init__(self, points: int) -> None:
        super().__init__(points)


@dataclass(frozen=True)
class Snapshot:
    """The settings in effect where :func:`snapshot` was called: torch's default dtype,
    :class:`moment_path`, :class:`tile_bytes`, :class:`debug`, :class:`native_kernels` and
    :class:`quadrature_points` (picklable)."""

    dtype: torch.dtype
    path: str
    tile: int | None
    debug: bool
    native: bool = True
    quadrature: int | None = None

    @contextlib.contextmanager
    def applied(self) -> Iterator[None]:
        """Context in which these settings are in effect (the previous ones are restored)."""
        with contextlib.ExitStack() as stack:
            stack.enter_context(default_dtype(self.dtype))
            stack.enter_context(moment_path(self.path))
            stack.enter_context(debug(self.debug))
            stack.enter_context(native_kernels(self.native))
            for value, setting, var in (
                (self.tile, tile_bytes, _tile),
                (self.quadrature, quadrature_points, _quadrature),
            ):
                stack.enter_context(setting(value) if value is not None else _Unset(var))
            yield


class _Unset(_Setting):
    """Context in which a setting is back at its default (``None``)."""

    def __init__(self, var: contextvars.ContextVar) -> None:
        self._var = var
        super().__init__(None)


def snapshot() -> Snapshot:
    """The settings in effect now, for a job that runs elsewhere (module docstring)."""
    return Snapshot(
        torch.get_default_dtype(),
        _path.get(),
        _tile.get(),
        _debug.get(),
        _native.get(),
        _quadrature.get(),
    )
