"""MkDocs hook: every module of ``hgpdm_torch`` must be documented on an API reference page.

Each page under ``api/`` renders modules with mkdocstrings (``::: hgpdm_torch.xxx``). After the
build this hook compares the modules named there with the ``.py`` files of the package (found on
disk; nothing is imported) and logs a warning for each module no page names, so that
``mkdocs build --strict`` fails until the new module gets its ``::: ...`` line. Private modules
(``_name.py``) are exempt.
"""

from __future__ import annotations

import logging
import re
from pathlib import Path
from typing import Any

log = logging.getLogger("mkdocs.hooks.completeness")

_IDENTIFIER = re.compile(r"^:::\s+([\w.]+)", re.MULTILINE)
_documented: set[str] = set()


def _package_modules(root: Path) -> set[str]:
    modules = set()
    for path in (root / "hgpdm_torch").rglob("*.py"):
        parts = path.relative_to(root).with_suffix("").parts
        if parts[-1] == "__init__":
            parts = parts[:-1]
        if not any(part.startswith("_") for part in parts):
            modules.add(".".join(parts))
    return modules


def on_pre_build(config: Any, **kwargs: Any) -> None:
    _documented.clear()


def on_page_markdown(markdown: str, page: Any, **kwargs: Any) -> str:
    if page.file.src_uri.startswith("api/"):
        _documented.update(_IDENTIFIER.findall(markdown))
    return markdown


def on_post_build(config: Any, **kwargs: Any) -> None:
    root = Path(config.config_file_path).parent
    for module in sorted(_package_modules(root) - _documented):
        log.warning(f"module {module} is on no API reference page (docs/api/*.md: '::: {module}')")
