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
"""

from __future__ import annotations

import contextlib
import contextvars
from collections.abc import Iterator
from types import TracebackType

__all__ = ["debug", "internal_step", "validate_internal"]

_debug = contextvars.ContextVar("hgpdm_torch_debug", default=False)
_internal = contextvars.ContextVar("hgpdm_torch_internal", default=False)


class debug:
    """Context manager (and flag) for the debugging checks of the hot loops (module docstring).

    ``with debug(True): ...`` switches them on for the block (``debug(False)`` off); the setting
    is per thread/async context. Default: off.

    Args:
        state: whether the checks run inside the block.
    """

    def __init__(self, state: bool = True) -> None:
        self.state = bool(state)
        self._token: contextvars.Token[bool] | None = None

    @staticmethod
    def on() -> bool:
        """Whether the debugging checks run now."""
        return _debug.get()

    @staticmethod
    def off() -> bool:
        """Whether the debugging checks are skipped now."""
        return not _debug.get()

    def __enter__(self) -> debug:
        self._token = _debug.set(self.state)
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        if self._token is not None:
            _debug.reset(self._token)
            self._token = None


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


def validate_internal() -> bool:
    """Whether a structure check of a Gaussian should run now: always for a user's call,
    inside :func:`internal_step` only under :class:`debug`."""
    return _debug.get() or not _internal.get()
