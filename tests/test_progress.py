"""Progress bars: no tqdm warning in a Jupyter kernel without ipywidgets (the tutorials'
outputs), and every module takes its bars from :mod:`hgpdm_torch.progress`."""

from __future__ import annotations

import importlib
import importlib.util
import re
import warnings
from pathlib import Path

import tqdm.std

import hgpdm_torch.progress as progress

PACKAGE = Path(progress.__file__).parent


def test_text_bar_without_ipywidgets(monkeypatch):
    real = importlib.util.find_spec
    monkeypatch.setattr(
        importlib.util, "find_spec", lambda name, *a: None if name == "ipywidgets" else real(name)
    )
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # a TqdmWarning would fail here
        module = importlib.reload(progress)
    try:
        assert module.tqdm is tqdm.std.tqdm and module.trange is tqdm.std.trange
    finally:
        monkeypatch.undo()
        importlib.reload(progress)


def test_every_module_imports_its_bars_from_progress():
    direct = re.compile(r"^\s*(from tqdm\b|import tqdm\b)", re.MULTILINE)
    offenders = [
        str(p.relative_to(PACKAGE))
        for p in PACKAGE.rglob("*.py")
        if p.name != "progress.py" and direct.search(p.read_text())
    ]
    assert offenders == [], f"import tqdm through hgpdm_torch.progress in {offenders}"
