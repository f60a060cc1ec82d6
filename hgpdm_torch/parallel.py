"""One executor interface for the work that may outgrow one machine: local processes or Ray.

Reward tables and trial generation, and the experiments' repeated cross-validation and
model-selection sweeps, hand independent jobs to an :class:`Executor` from :func:`get_executor`:

- ``workers=1``: :class:`SerialExecutor`, in this process;
- ``workers > 1`` (the default, all cores): :class:`ProcessExecutor`, local processes;
- ``ray_address`` given: :class:`RayExecutor`, the tasks of a Ray cluster. ``"local"`` starts a
  private Ray instance with ``workers`` CPUs on this machine; ``"auto"`` connects to the cluster
  named by the ``RAY_ADDRESS`` environment variable or else to the one ``ray start`` runs here;
  ``"HOST:PORT"`` (a head node's GCS address) or ``"ray://HOST:PORT"`` (Ray Client) connect to
  that cluster. Ray is the optional extra ``pip install hgpdm-torch[cluster]``; it is imported
  only when a Ray executor is made.

``Executor.map(fn, items)`` returns the results in the order of ``items`` whatever the executor,
so a job whose randomness comes from its item (a seed, a generator state) gives the same result
everywhere: same seed, same table, on one core or a hundred. A job must not read the caller's
process-wide state (torch's default dtype, a global seed): local workers and Ray workers start
fresh processes that do not inherit it; put such settings in the item.

Local processes are *spawned*, never forked. A process that has used torch's intra-op thread
pool (OpenMP, MKL) holds locks that a forked child inherits in whatever state the parent's
threads left them, so a forked worker can block forever in its first matrix product (seen as a
hang of ``hgpdm demo`` in its first parallel stage). A spawned worker is a fresh interpreter:
it costs an import of torch (about 2 s, once per worker, as the pool lives until
:meth:`Executor.close`), and, as for any ``multiprocessing`` code, a script that makes a local
executor must guard its top level with ``if __name__ == "__main__":``. Each worker takes
``available_cpus() // workers`` intra-op threads (at least one) unless ``OMP_NUM_THREADS`` is
set, so the workers together do not oversubscribe the cores.

This module is a leaf: it imports only the standard library (and Ray on demand), nothing of
``hgpdm_torch``, so every layer -- ``robots`` included, which otherwise imports nothing of ours
outside itself -- may use it without breaking the dependency direction.
"""

from __future__ import annotations

import argparse
import multiprocessing
import os
import pickle
import socket
import sys
from abc import ABC, abstractmethod
from collections import deque
from collections.abc import Callable, Iterable, Iterator
from concurrent.futures import ProcessPoolExecutor
from typing import Any, TypeVar

__all__ = [
    "Executor",
    "ProcessExecutor",
    "RayExecutor",
    "SerialExecutor",
    "available_cpus",
    "check_ray_address",
    "get_executor",
    "ray_address_type",
]

T = TypeVar("T")
R = TypeVar("R")

INSTALL_HINT = "pip install 'hgpdm-torch[cluster]'"
_SPECIAL = ("auto", "local")


class Executor(ABC):
    """Runs ``fn`` on independent items, returning the results in the items' order.

    ``fn`` and the items must be picklable (a module-level function; Ray also takes closures).
    Executors hold resources (processes, a Ray connection): use them as context managers or call
    :meth:`close`. One executor may serve many :meth:`map` calls; workers keep what they cached
    (e.g. a built simulator) between calls.

    Attributes:
        workers: the most jobs run at once (``None``: as many as the Ray cluster schedules).
    """

    workers: int | None

    @abstractmethod
    def map(self, fn: Callable[[T], R], items: Iterable[T]) -> Iterator[R]:
        """``fn(item)`` for every item, yielded in the order of ``items`` as they are ready.

        Local processes and Ray start the jobs when ``map`` is called (Ray with a ``workers``
        limit: that many, then one more per result read); the serial executor runs each job as
        its result is read. An exception raised by a job is re-raised when its result is read.
        """

    @abstractmethod
    def close(self) -> None:
        """Release the workers (idempotent)."""

    def __enter__(self) -> Executor:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def __repr__(self) -> str:
        return f"{type(self).__name__}(workers={self.workers})"


class SerialExecutor(Executor):
    """Runs every job in this process, one after the other (lazily, as the results are read)."""

    workers = 1

    def map(self, fn: Callable[[T], R], items: Iterable[T]) -> Iterator[R]:
        return map(fn, items)

    def close(self) -> None:
        """Nothing to release."""


class ProcessExecutor(Executor):
    """Local processes (:class:`concurrent.futures.ProcessPoolExecutor` with the ``spawn`` start
    method: safe after torch has started threads, see the module's docstring), started on
    first use.

    The pool lives until :meth:`close`, so a worker's module-level caches survive between
    :meth:`map` calls.

    Raises (from :meth:`map`):
        TypeError: ``fn`` cannot be pickled (a lambda, a local function); an item that cannot
            be pickled raises its pickling error when its result is read.
    """

    def __init__(self, workers: int) -> None:
        self.workers = _check_workers(workers, allow_none=False)
        self._pool: ProcessPoolExecutor | None = None

    def map(self, fn: Callable[[T], R], items: Iterable[T]) -> Iterator[R]:
        try:  # here, not in the pool's feeder thread, whose failure may never reach the caller
            pickle.dumps(fn)
        except (pickle.PicklingError, AttributeError, TypeError) as err:
            raise TypeError(
                f"ProcessExecutor needs a picklable fn (a module-level function or a picklable "
                f"object), got {fn!r}: {err}"
            ) from err
        if self._pool is None:
            threads = max(1, available_cpus() // self.workers)
            self._pool = ProcessPoolExecutor(
                max_workers=self.workers,
                mp_context=multiprocessing.get_context("spawn"),
                initializer=_limit_threads,
                initargs=(threads,),
            )
        return self._pool.map(fn, items)

    def close(self) -> None:
        if self._pool is not None:
            self._pool.shutdown(cancel_futures=True)
            self._pool = None


def _limit_threads(threads: int) -> None:
    """Start of each local worker: ``threads`` intra-op threads, unless ``OMP_NUM_THREADS``
    says otherwise (for a torch imported later by a job, and for one already imported)."""
    if "OMP_NUM_THREADS" in os.environ:
        return
    os.environ["OMP_NUM_THREADS"] = str(threads)
    torch = sys.modules.get("torch")
    if torch is not None:
        torch.set_num_threads(threads)


def _apply(fn: Callable[[T], R], item: T) -> R:
    """A Ray task: ``fn(item)`` on a cluster worker."""
    return fn(item)


class RayExecutor(Executor):
    """The tasks of a Ray cluster (one CPU each); see :func:`get_executor` for ``address``.

    Connecting checks first that the address answers (a TCP connection within ``timeout``
    seconds), because ``ray.init`` waits for an unreachable cluster for minutes. A process
    already connected to Ray (``ray.init`` called before) keeps that connection, and
    :meth:`close` leaves it open; otherwise :meth:`close` disconnects (and stops a ``"local"``
    instance).

    Args:
        address: ``"local"``, ``"auto"``, ``"HOST:PORT"`` or ``"ray://HOST:PORT"``.
        workers: ``"local"``: the CPUs of the instance (default: this machine's); a cluster:
            the most tasks in flight at once (default: no limit, the cluster schedules).
        timeout: seconds to wait for the address to answer.

    Raises:
        ImportError: Ray is not installed.
        ConnectionError: nothing answers at the address, or no cluster is found for ``"auto"``.
    """

    def __init__(self, address: str, workers: int | None = None, *, timeout: float = 10.0):
        address = check_ray_address(address)
        workers = _check_workers(workers, allow_none=True)
        if not (isinstance(timeout, int | float) and timeout > 0):
            raise ValueError(f"timeout must be a positive number of seconds, got {timeout!r}")
        ray = _import_ray(address)
        self.address = address
        self._owner = not ray.is_initialized()  # else reuse this process's connection
        if address == "local":
            self.workers = None  # the instance's CPUs bound the tasks in flight
            if self._owner:
                ray.init(address="local", num_cpus=workers or available_cpus(),
                         include_dashboard=False)  # fmt: skip
        else:
            self.workers = workers
            if self._owner or address != "auto":  # a given address must answer, even so
                _check_reachable(address, _resolve(address), timeout)
            if self._owner:
                try:
                    ray.init(address=address)
                except ConnectionError as err:
                    raise ConnectionError(_refused(address, err)) from err
        self._ray = ray
        self._task = ray.remote(num_cpus=1)(_apply)

    def map(self, fn: Callable[[T], R], items: Iterable[T]) -> Iterator[R]:
        if self._ray is None:
            raise RuntimeError("this RayExecutor is closed")
        ray, task, fn_ref = self._ray, self._task, self._ray.put(fn)
        todo, pending = iter(items), deque()

        def submit() -> bool:
            for item in todo:
                pending.append(task.remote(fn_ref, item))
                return True
            return False

        while (self.workers is None or len(pending) < self.workers) and submit():
            pass

        def results() -> Iterator[R]:
            try:
                while pending:
                    result = ray.get(pending.popleft())
                    submit()
                    yield result
            finally:  # abandoned or failed: do not leave the rest running on the cluster
                for ref in pending:
                    ray.cancel(ref)

        return results()

    def close(self) -> None:
        if self._ray is not None and self._owner:
            self._ray.shutdown()
        self._ray = None

    def __repr__(self) -> str:
        return f"RayExecutor({self.address!r}, workers={self.workers})"


def available_cpus() -> int:
    """CPUs this process may run on (its affinity mask where the OS has one)."""
    if hasattr(os, "sched_getaffinity"):
        return max(1, len(os.sched_getaffinity(0)))
    return os.cpu_count() or 1


def get_executor(
    workers: int | None = None, ray_address: str | None = None, *, timeout: float = 10.0
) -> Executor:
    """The executor for ``workers`` local jobs at once, or for a Ray cluster.

    Args:
        workers: jobs at once: ``1`` runs them in this process, more in local processes
            (default: :func:`available_cpus`). With ``ray_address="local"`` the CPUs of the Ray
            instance; with a cluster address the most tasks in flight (default: no limit).
        ray_address: ``None`` for local execution; ``"local"`` to start a Ray instance here;
            ``"auto"`` for the cluster in ``$RAY_ADDRESS`` or the one ``ray start`` runs on this
            machine; ``"HOST:PORT"`` / ``"ray://HOST:PORT"`` for a given cluster.
        timeout: seconds to wait for a cluster address to answer before giving up.

    Returns:
        An :class:`Executor`; close it (or use it in a ``with`` block) when done.

    Raises:
        ValueError: ``workers`` not a positive int, or a malformed ``ray_address``.
        ImportError: ``ray_address`` given but Ray is not installed
            (``pip install 'hgpdm-torch[cluster]'``).
        ConnectionError: no Ray cluster answers at ``ray_address`` within ``timeout``.
    """
    if ray_address is not None:
        return RayExecutor(ray_address, workers, timeout=timeout)
    workers = _check_workers(workers, allow_none=True) or available_cpus()
    return SerialExecutor() if workers == 1 else ProcessExecutor(workers)


def check_ray_address(address: object) -> str:
    """``address`` stripped, if it is ``"auto"``, ``"local"``, ``"HOST:PORT"`` or
    ``"ray://HOST:PORT"`` (port 1-65535; an IPv6 host in brackets); else ``ValueError``."""
    if not isinstance(address, str):
        raise TypeError(f"ray_address must be a str, got {type(address).__name__}")
    address = address.strip()
    if address not in _SPECIAL:
        _host_port(address)
    return address


def ray_address_type(text: str) -> str:
    """``argparse`` ``type=`` for a ``--ray-address`` option (see :func:`check_ray_address`)."""
    try:
        return check_ray_address(text)
    except ValueError as err:
        raise argparse.ArgumentTypeError(str(err)) from None


def _host_port(address: str) -> tuple[str, int]:
    host, sep, port = address.removeprefix("ray://").rpartition(":")
    if host.startswith("[") and host.endswith("]"):
        host = host[1:-1]  # an IPv6 literal
    elif ":" in host:
        host = ""  # an IPv6 host must be in brackets
    valid = sep and host and port.isdigit() and 0 < int(port) < 65536
    if not valid or any(c.isspace() or c in "/[]" for c in host):
        raise ValueError(
            "ray_address must be 'auto', 'local', 'HOST:PORT' or 'ray://HOST:PORT', "
            f"got {address!r}"
        )
    return host, int(port)


def _check_workers(workers: object, *, allow_none: bool) -> int | None:
    if workers is None and allow_none:
        return None
    if isinstance(workers, bool) or not isinstance(workers, int) or workers < 1:
        raise ValueError(f"workers must be a positive int, got {workers!r}")
    return workers


def _import_ray(address: str) -> Any:
    try:
        import ray
    except ImportError as err:
        raise ImportError(
            f"ray_address={address!r} needs Ray, which is not installed: {INSTALL_HINT}"
        ) from err
    return ray


def _resolve(address: str) -> str | None:
    """The concrete address ``"auto"`` stands for (``None`` if Ray's lookup is unavailable)."""
    if address != "auto":
        return address
    try:
        from ray._private.services import get_ray_address_from_environment
    except ImportError:  # a Ray without this helper: ray.init does the lookup itself
        return os.environ.get("RAY_ADDRESS") or None
    try:
        return get_ray_address_from_environment("auto", None)
    except ConnectionError as err:
        raise ConnectionError(_unreachable(address, err)) from err


def _check_reachable(given: str, resolved: str | None, timeout: float) -> None:
    """Raise ``ConnectionError`` unless a TCP connection to ``resolved`` (what the address
    ``given`` stands for) opens within ``timeout`` seconds."""
    if resolved is None or resolved in _SPECIAL:
        return
    name = given if resolved == given else f"{given} (resolved to {resolved})"
    try:
        host, port = _host_port(resolved)
    except ValueError as err:  # e.g. a malformed $RAY_ADDRESS behind "auto"
        raise ValueError(f"ray_address={name}: {err}") from None
    try:
        socket.create_connection((host, port), timeout=timeout).close()
    except OSError as err:
        raise ConnectionError(_unreachable(name, err)) from err


def _refused(address: str, err: BaseException) -> str:
    """Why ``ray.init`` failed at an address that answers, with the root cause (often auth)."""
    root = err
    while root.__cause__ is not None:
        root = root.__cause__
    last = [line for line in str(root).splitlines() if line.strip()][-1:] or [""]
    cause = "" if root is err else f" ({type(root).__name__}: ...{last[0][:160]})"
    return (
        f"Ray could not connect to the cluster at ray_address={address}: {err}{cause}. A "
        "cluster with token authentication (Ray's default) needs RAY_AUTH_MODE=token here and "
        "its token in $RAY_AUTH_TOKEN or ~/.ray/auth_token"
    )


def _unreachable(address: str, err: BaseException) -> str:
    return (
        f"no Ray cluster answers at ray_address={address} ({err}); start one with "
        "`ray start --head` (then ray_address='auto' or 'HEAD_IP:6379') or use "
        "ray_address='local' for a Ray instance on this machine"
    )
