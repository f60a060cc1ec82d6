"""``make gpu-check`` (benchmarks/gpu_check.py) in its CPU mode, and the list of GPU test files
it collects from."""

from __future__ import annotations

import json
import re
import time
from pathlib import Path

import pytest

from benchmarks import gpu_check

ROOT = Path(__file__).resolve().parent.parent


def test_every_gpu_test_lives_in_a_file_the_check_collects():
    """The check collects ``gpu`` tests from GPU_TEST_FILES only (so a GPU machine without
    SAPIEN can run it); a test taking the ``device`` fixture or marked ``gpu`` elsewhere would
    silently never run on a GPU."""
    uses_gpu = re.compile(r"mark\.gpu|def test_\w+\([^)]*\bdevice\b", re.DOTALL)
    found = {
        str(p.relative_to(ROOT))
        for p in (ROOT / "tests").rglob("test_*.py")
        if uses_gpu.search(p.read_text()) and p.name != Path(__file__).name
    }
    assert found and found <= set(gpu_check.GPU_TEST_FILES), found - set(gpu_check.GPU_TEST_FILES)


def test_cpu_mode_runs_tests_and_benchmarks_and_writes_its_summary(capsys):
    """The CPU mode: the CPU half of the GPU tests and one benchmark at tiny sizes (the whole
    mode, every benchmark in both dtypes, is ``make gpu-check`` without CUDA)."""
    status = gpu_check.main(["--cpu", "--budget", "240", "--only", "tests", "hgpdm_fit:float32"])
    out = capsys.readouterr().out
    assert status == 0, out[-3000:]
    assert "no CUDA device (or --cpu)" in out
    summary = json.loads((ROOT / "benchmarks/results/gpu_check_quick.json").read_text())
    steps = {s["key"]: s for s in summary["steps"]}
    assert steps["tests"]["status"] == "ok" and steps["tests"]["counts"]["passed"] >= 2
    assert "skipped" not in steps["tests"]["counts"]  # the CPU halves run, none is skipped
    bench = steps["hgpdm_fit:float32"]
    assert bench["status"] == "ok"
    table = json.loads((ROOT / bench["results"]).read_text())
    assert table["rows"] and table["meta"]["dtype"] == "float32"


def test_a_step_that_overruns_the_budget_is_recorded_not_waited_for():
    step = gpu_check._run_step("sleep", ["sleep", "30"], deadline=time.monotonic() + 1.0)
    assert step["status"] == "timed out" and step["seconds"] < 10


@pytest.mark.parametrize("argv", [["--budget", "0"], ["--only", "nonsense"]])
def test_bad_arguments_are_refused(argv):
    with pytest.raises(SystemExit) as err:
        gpu_check.main(argv)
    assert err.value.code == 2
