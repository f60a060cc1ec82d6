"""Run every benchmark module in this folder: ``python -m benchmarks [OPTIONS] [NAME ...]``.

Each benchmark is a module ``benchmarks/<name>.py`` with ``main(argv: list[str]) -> int`` that
prints a table and writes ``benchmarks/results/<name>.json``. Options, passed on to every
module: ``--quick`` (smoke mode); and for ``online_intention``, ``hgpdm_fit``,
``moment_matching``, ``mcp`` and ``variational`` (:data:`DEVICE_AWARE`): ``--device DEVICE``
(e.g. ``cuda``), ``--dtype {float64,float32}`` and ``--gpu-sizes`` (the accelerator problem
sizes; see :func:`benchmarks._common.parse_options`). With any of these, only those benchmarks
run, and naming another one is an error.
"""

from __future__ import annotations

import importlib
import pkgutil
import sys
from pathlib import Path


def _split(argv: list[str]) -> tuple[list[str], list[str]]:
    """Benchmark names and the options passed on to each (``--device``/``--dtype`` take a
    value)."""
    names, options, rest = [], [], iter(argv)
    for arg in rest:
        if arg in ("--device", "--dtype"):
            options += [arg, next(rest, "")]
        elif arg.startswith("-"):
            options.append(arg)
        else:
            names.append(arg)
    return names, options


#: modules of this folder that are not benchmarks: ``gpu_check`` runs the device-aware ones (and
#: the GPU tests) on an accelerator, ``make gpu-check``
NOT_BENCHMARKS = ("gpu_check",)

#: the benchmarks that take ``--device``/``--dtype``/``--gpu-sizes``; the others run on the CPU
#: in float64 and would ignore them (and overwrite their CPU result files)
DEVICE_AWARE = ("hgpdm_fit", "mcp", "moment_matching", "online_intention", "variational")


def main(argv: list[str]) -> int:
    names, options = _split(argv)
    folder = Path(__file__).parent
    found = sorted(
        m.name
        for m in pkgutil.iter_modules([str(folder)])
        if not m.name.startswith("_") and m.name not in NOT_BENCHMARKS
    )
    unknown = set(names) - set(found)
    if unknown:
        print(f"unknown benchmarks {sorted(unknown)}; available: {found}", file=sys.stderr)
        return 2
    if any(o in ("--device", "--dtype", "--gpu-sizes") for o in options):
        unaware = sorted(set(names) - set(DEVICE_AWARE))
        if unaware:
            print(
                f"{unaware} take no --device/--dtype/--gpu-sizes (they run on the CPU in "
                f"float64); those options apply to {list(DEVICE_AWARE)}",
                file=sys.stderr,
            )
            return 2
        names = names or [n for n in found if n in DEVICE_AWARE]
    status = 0
    for name in names or found:
        print(f"== benchmarks.{name}")
        status |= int(importlib.import_module(f"benchmarks.{name}").main(options) or 0)
    return status


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))
