"""Lazy re-exports of a package's public names (PEP 562), so that importing a package does not
import every module behind it (torch, gpytorch and pyro load on first use only)."""

from __future__ import annotations

import importlib
import sys
from collections.abc import Callable
from typing import Any


def lazy_exports(
    package: str, exports: dict[str, str]
) -> tuple[Callable[[str], Any], Callable[[], list[str]]]:
    """``__getattr__`` and ``__dir__`` for ``package`` (its ``__name__``).

    Args:
        exports: public name -> module it lives in, relative to ``package`` (``".lspi"``); a
            subpackage or module exported under its own name maps to itself.

    Returns:
        The two module-level functions; the first imports a name's module on first access and
        caches the name in the package.
    """

    def __getattr__(name: str) -> Any:
        if name not in exports:
            raise AttributeError(f"module {package!r} has no attribute {name!r}")
        module = importlib.import_module(exports[name], package)
        value = module if module.__name__ == f"{package}.{name}" else getattr(module, name)
        setattr(sys.modules[package], name, value)
        return value

    def __dir__() -> list[str]:
        return sorted({*vars(sys.modules[package]), *exports})

    return __getattr__, __dir__
