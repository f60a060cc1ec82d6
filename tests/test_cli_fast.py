"""``hgpdm`` without a subcommand stays light (issue 15, item 6): no torch & co.

Checked by what is imported, never by a timing (timings flake on shared CI machines). The
``--help`` case of both the function and ``python -m hgpdm_torch.cli`` is in ``test_cli.py``;
this covers the other paths that must not import a subcommand: no arguments, an unknown command,
and the installed console script; and that every subcommand's own ``--help`` still works once
it is imported.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from hgpdm_torch import cli

HEAVY = ("torch", "gpytorch", "pyro", "sapien", "numpy", "scipy", "sklearn", "matplotlib", "ray")
# The experiments and model packages would pull in torch; their absence is the point.
OWN_HEAVY = ("hgpdm_torch.experiments", "hgpdm_torch.models", "hgpdm_torch.inference")


def _loaded_after(argv: list[str]) -> tuple[subprocess.CompletedProcess[str], list[str]]:
    """Run ``cli.main(argv)`` in a fresh interpreter; return the process and the heavy modules
    it had imported when ``main`` returned or exited."""
    watched = HEAVY + OWN_HEAVY
    code = (
        "import sys\n"
        "from hgpdm_torch.cli import main\n"
        "try:\n"
        f"    rc = main({argv!r})\n"
        "except SystemExit as stop:\n"
        "    rc = stop.code\n"
        "import json\n"
        f"loaded = sorted(m for m in {watched!r} if m in sys.modules)\n"
        "print('LOADED', json.dumps(loaded), file=sys.stderr)\n"
        "raise SystemExit(rc)\n"
    )
    run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    line = [x for x in run.stderr.splitlines() if x.startswith("LOADED ")]
    assert line, run.stderr
    return run, json.loads(line[-1].removeprefix("LOADED "))


def test_no_arguments_prints_help_without_heavy_imports():
    run, loaded = _loaded_after([])
    assert run.returncode == 0, run.stderr
    assert "usage: hgpdm" in run.stdout and all(name in run.stdout for name in cli.COMMANDS)
    assert loaded == []


@pytest.mark.parametrize("argv", [["no-such-command"], ["--version-typo"], ["Demo", "--help"]])
def test_unknown_command_is_a_usage_error_without_heavy_imports(argv):
    run, loaded = _loaded_after(argv)
    assert run.returncode == 2, (run.stdout, run.stderr)
    assert f"unknown command {argv[0]!r}" in run.stderr and "style-discovery" in run.stderr
    assert loaded == []


def test_console_script_help_imports_no_heavy_package():
    script = Path(sys.executable).with_name("hgpdm")
    if not script.exists():
        pytest.skip("the hgpdm console script is not installed next to this interpreter")
    run = subprocess.run(
        [str(script), "--help"],
        capture_output=True,
        text=True,
        timeout=60,
        env={"PYTHONPROFILEIMPORTTIME": "1", "PATH": str(script.parent)},
    )
    assert run.returncode == 0, run.stderr
    assert "usage: hgpdm" in run.stdout
    imported = {line.split("|")[-1].strip() for line in run.stderr.splitlines()}
    assert "hgpdm_torch.cli" in imported, "not an import-time profile"
    assert not imported & set(HEAVY + OWN_HEAVY), sorted(imported & set(HEAVY + OWN_HEAVY))


@pytest.mark.parametrize("command", sorted(cli.COMMANDS))
def test_every_subcommand_still_has_its_own_help(command, capsys):
    """The lazy dispatch reaches each experiment's parser (its import is paid here, once)."""
    with pytest.raises(SystemExit) as stop:
        cli.main([command, "--help"])
    assert stop.value.code == 0
    out = capsys.readouterr().out
    assert out.startswith("usage:") and "--help" in out
