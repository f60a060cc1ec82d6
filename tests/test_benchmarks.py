"""Every benchmark runs in its --quick smoke mode and writes its JSON table."""

from __future__ import annotations

import importlib
import json
import pkgutil
from pathlib import Path

import pytest

import benchmarks

NAMES = sorted(
    m.name for m in pkgutil.iter_modules(benchmarks.__path__) if not m.name.startswith("_")
)


def test_benchmarks_are_found():
    assert {"hgpdm_fit", "moment_matching", "online_intention", "mcp"} <= set(NAMES)


#: quick runs over ~20 s on 2 cores, behind ``slow``: the behaviour they time has fast tests of
#: its own (stroke execution in tests/robots, the regressors in tests/test_baselines.py)
SLOW = {"table_tennis", "target_information"}


@pytest.mark.parametrize(
    "name", [pytest.param(n, marks=pytest.mark.slow) if n in SLOW else n for n in NAMES]
)
def test_quick_mode_runs_and_writes_results(name, capsys):
    module = importlib.import_module(f"benchmarks.{name}")
    assert module.main(["--quick"]) == 0
    out = Path(benchmarks.__file__).parent / "results" / f"{name}_quick.json"
    table = json.loads(out.read_text())
    assert table["rows"] and table["columns"]
    assert "|" in capsys.readouterr().out  # the printed Markdown table


@pytest.mark.parametrize("name", ["online_intention", "hgpdm_fit", "moment_matching", "mcp"])
def test_device_and_dtype_options(name, capsys):
    """``--device cpu --dtype float32`` runs and writes its own file, not the float64 one."""
    module = importlib.import_module(f"benchmarks.{name}")
    assert module.main(["--quick", "--device", "cpu", "--dtype", "float32"]) == 0
    out = Path(benchmarks.__file__).parent / "results" / f"{name}_cpu_float32_quick.json"
    table = json.loads(out.read_text())
    assert table["rows"] and table["meta"]["dtype"] == "float32"
    assert "|" in capsys.readouterr().out


def test_device_options_only_go_to_benchmarks_that_take_them(capsys):
    """``--device`` with a CPU-only benchmark is refused instead of silently running it on the
    CPU and overwriting its result file."""
    from benchmarks.__main__ import DEVICE_AWARE, main

    assert "target_sweep" not in DEVICE_AWARE and "online_intention" in DEVICE_AWARE
    assert main(["target_sweep", "--device", "cpu"]) == 2
    assert "take no --device" in capsys.readouterr().err
