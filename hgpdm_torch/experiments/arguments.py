"""Argument types for the experiments' command lines: bad values end in an argparse usage message
(exit code 2) naming the option, before any data is generated or any model fitted.

Each function is an ``argparse`` ``type=``: it takes the option's text and returns the parsed
value or raises :class:`argparse.ArgumentTypeError`. :func:`add_executor_arguments` and
:func:`connect` give a command the toolkit's ``--workers`` / ``--ray-address`` convention. Only
the standard library (and the standard-library-only :mod:`hgpdm_torch.parallel`) is imported
here.
"""

from __future__ import annotations

import argparse
import os
import shutil
import tempfile
from collections.abc import Callable, Iterable
from pathlib import Path

from ..parallel import Executor, get_executor, ray_address_type

__all__ = [
    "MAX_SEED",
    "SMOKE",
    "add_executor_arguments",
    "check_output_files",
    "connect",
    "int_at_least",
    "non_negative_int",
    "output_file",
    "output_folder",
    "positive_int",
    "random_seed",
    "smoke_run",
]

#: Largest accepted seed: scikit-learn's ``random_state`` (used by K-means) takes ``[0, 2**32)``.
MAX_SEED = 2**32 - 1


def smoke_run() -> bool:
    """Whether ``HGPDM_SMOKE=1`` asks for a smoke-sized run (CI, quick checks), read now."""
    return os.environ.get("HGPDM_SMOKE", "0") == "1"


#: :func:`smoke_run` when the experiments are imported: the sizes of their smoke defaults
SMOKE = smoke_run()


def _int(text: str, expected: str) -> int:
    try:
        return int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected {expected}, got {text!r}") from None


def int_at_least(low: int) -> Callable[[str], int]:
    """A type accepting integers ``>= low``."""
    expected = {0: "a non-negative integer", 1: "a positive integer"}.get(
        low, f"an integer >= {low}"
    )

    def parse(text: str) -> int:
        value = _int(text, expected)
        if value < low:
            raise argparse.ArgumentTypeError(f"expected {expected}, got {text}")
        return value

    return parse


positive_int = int_at_least(1)
non_negative_int = int_at_least(0)


def random_seed(text: str) -> int:
    """A random seed: an integer in ``[0, MAX_SEED]``."""
    expected = f"a seed in [0, {MAX_SEED}]"
    value = _int(text, expected)
    if not 0 <= value <= MAX_SEED:
        raise argparse.ArgumentTypeError(f"expected {expected}, got {text}")
    return value


def _writable(text: str, kind: str) -> Path:
    """``text`` as a path whose existing ancestors are folders and that this process can write
    (so that a long run does not end by failing to save its results)."""
    if not text.strip():
        raise argparse.ArgumentTypeError(f"expected a {kind} path, got an empty string")
    path = Path(text)
    for parent in path.parents:
        if parent.exists() and not parent.is_dir():
            raise argparse.ArgumentTypeError(f"{text}: {parent} is a file, not a folder")
    _probe_write(path, text)
    return path


def _probe_write(path: Path, text: str) -> None:
    """Raise ``ArgumentTypeError`` unless ``path`` can be written, trying it for real (as root,
    permission bits say nothing of a read-only or virtual file system), and leaving nothing
    behind: an existing folder gets a temporary file, an existing file is opened for appending,
    and otherwise the nearest existing ancestor gets a temporary folder."""
    try:
        if path.is_dir():
            tempfile.TemporaryFile(dir=path).close()
        elif path.exists():
            path.open("a").close()
        else:
            ancestor = next(p for p in path.absolute().parents if p.exists())
            shutil.rmtree(tempfile.mkdtemp(dir=ancestor))
    except OSError as err:
        raise argparse.ArgumentTypeError(f"{text} cannot be written: {err}") from None


def output_folder(text: str) -> Path:
    """A folder to write into: it may not exist yet, but must not be a file."""
    path = _writable(text, "folder")
    if path.exists() and not path.is_dir():
        raise argparse.ArgumentTypeError(f"{text} is a file, expected a folder")
    return path


def output_file(text: str) -> Path:
    """A file to write: it may not exist yet, but must not be a folder."""
    path = _writable(text, "file")
    if path.is_dir() or text.endswith(("/", "\\")):
        raise argparse.ArgumentTypeError(f"{text} is a folder, expected a file path")
    return path


def check_output_files(
    parser: argparse.ArgumentParser, option: str, folder: Path, names: Iterable[str]
) -> None:
    """End in a usage error unless each file ``names`` that a command will save into ``folder``
    (the value of ``option``, e.g. ``--out``) can be written there: checked when the arguments
    are parsed, so that a folder standing where a results file goes does not lose a long run's
    results at its end.

    Raises:
        SystemExit: (``parser.error``, exit code 2) naming the path, e.g. ``argument --out:
            DIR/demo.json is a folder, expected a file path``.
    """
    for name in names:
        try:
            output_file(str(Path(folder) / name))
        except argparse.ArgumentTypeError as err:
            parser.error(
                f"argument {option}: {err} (the command saves {name} there; move it away or "
                f"choose another {option})"
            )


def add_executor_arguments(parser: argparse.ArgumentParser, what: str) -> None:
    """``--workers W`` and ``--ray-address ADDRESS`` for running ``what`` (e.g. "the folds")
    on local processes or a Ray cluster (:func:`connect`)."""
    parser.add_argument(
        "--workers",
        type=positive_int,
        default=None,
        help=f"run {what} W at a time in local processes (default 1: in this process); with "
        "--ray-address local the Ray instance's CPUs, with a cluster the most tasks in flight",
    )
    parser.add_argument(
        "--ray-address",
        type=ray_address_type,
        default=None,
        help=f"run {what} on Ray: 'local' (a Ray instance here), 'auto' ($RAY_ADDRESS or the "
        "cluster `ray start` runs here) or HOST:PORT of a head node",
    )


def connect(
    parser: argparse.ArgumentParser,
    workers: int | None,
    ray_address: str | None,
    *,
    local: bool = False,
) -> Executor | None:
    """The executor of a command's ``--workers`` / ``--ray-address``: Ray where an address is
    given (Ray missing, or a cluster that does not answer, ends in a usage error naming the
    option); with ``local``, ``workers > 1`` local processes; else ``None`` (this process)."""
    if ray_address is None:
        return get_executor(workers) if local and workers is not None and workers > 1 else None
    try:
        return get_executor(workers, ray_address)
    except (ImportError, ConnectionError) as err:
        parser.error(f"argument --ray-address: {err}")
