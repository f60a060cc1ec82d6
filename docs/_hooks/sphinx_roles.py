"""Griffe extension for the API reference: Sphinx roles in docstrings become inline code.

The docstrings are Google style but name other objects with Sphinx roles
(:func:`fit_map`, :class:`~hgpdm_torch.models.GPDM`); Markdown would show the role verbatim.
This rewrites each role to inline code (``fit_map``, ``GPDM``: a leading ``~`` keeps the last
dotted component, as in Sphinx) when mkdocstrings loads the package. The source files are not
changed.
"""

from __future__ import annotations

import re
from typing import Any

import griffe

_ROLE = re.compile(r":(?:py:)?(?:func|class|meth|mod|attr|data|obj|exc|const):`(~?)([^`]+)`")


def _to_code(match: re.Match[str]) -> str:
    tilde, target = match.groups()
    return f"`{target.rsplit('.', 1)[-1] if tilde else target}`"


class SphinxRolesToCode(griffe.Extension):
    """Rewrite ``:role:`target``` in every docstring to ```target``` (Markdown inline code)."""

    def on_instance(self, *, obj: griffe.Object, **kwargs: Any) -> None:
        if obj.docstring is not None:
            obj.docstring.value = _ROLE.sub(_to_code, obj.docstring.value)
