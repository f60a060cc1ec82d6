"""The README's quick start runs as written (in a temporary folder: it saves a file)."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def quick_start() -> str:
    text = (ROOT / "README.md").read_text()
    section = text.split("## Quick start", 1)[1]
    return re.search(r"```python\n(.*?)```", section, re.S).group(1)


def test_quick_start_is_short_and_shows_a_kernel_and_online_inference():
    code = quick_start()
    lines = [line for line in code.splitlines() if line.strip() and not line.startswith("#")]
    assert len(lines) < 25, len(lines)
    assert "measurement_kernel=" in code and "OnlineIntentionFilter" in code


@pytest.mark.slow  # a 60-step fit (~15 s); tests/models/test_custom_kernels.py covers the same
def test_quick_start_runs(tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    exec(compile(quick_start(), "README quick start", "exec"), {"__name__": "__readme__"})
    assert (tmp_path / "hgpdm.pt").is_file()
    assert "tensor" in capsys.readouterr().out
