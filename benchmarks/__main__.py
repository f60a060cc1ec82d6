"""Run every benchmark module in this folder: ``python -m benchmarks [--quick] [NAME ...]``.

Each benchmark is a module ``benchmarks/<name>.py`` with ``main(argv: list[str]) -> int`` that
prints a table and writes ``benchmarks/results/<name>.json``; ``--quick`` is a smoke mode.
"""

from __future__ import annotations

import importlib
import pkgutil
import sys
from pathlib import Path


def main(argv: list[str]) -> int:
    quick = [a for a in argv if a == "--quick"]
    names = [a for a in argv if not a.startswith("-")]
    folder = Path(__file__).parent
    found = sorted(
        m.name for m in pkgutil.iter_modules([str(folder)]) if not m.name.startswith("_")
    )
    unknown = set(names) - set(found)
    if unknown:
        print(f"unknown benchmarks {sorted(unknown)}; available: {found}", file=sys.stderr)
        return 2
    status = 0
    for name in names or found:
        print(f"== benchmarks.{name}")
        status |= int(importlib.import_module(f"benchmarks.{name}").main(quick) or 0)
    return status


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))
