"""``hgpdm_torch.decision`` imports its parts on first use: the opponent modeling of Ch. 5 does
not load the GP inference behind the planners, and every public name is the object it names
whatever was imported first (checked by what is imported, in fresh interpreters)."""

from __future__ import annotations

import json
import subprocess
import sys

import hgpdm_torch.decision as decision


def _run(code: str) -> dict:
    run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert run.returncode == 0, run.stderr
    return json.loads(run.stdout.strip().splitlines()[-1])


def test_opponent_modeling_does_not_load_gp_inference():
    loaded = _run(
        "import sys, json\n"
        "from hgpdm_torch.decision.opponent import DeltaSafeResponder\n"
        "heavy = ('gpytorch', 'pyro', 'hgpdm_torch.inference', 'hgpdm_torch.models')\n"
        "print(json.dumps({m: m in sys.modules for m in heavy}))\n"
    )
    assert not any(loaded.values()), loaded


def test_names_are_their_objects_whatever_was_imported_first():
    # the planners import the lspi module first; the package's lspi must stay the function
    kinds = _run(
        "import json\n"
        "import hgpdm_torch.decision.mcp\n"
        "import hgpdm_torch.decision.lspi, hgpdm_torch.decision.nac\n"
        "import hgpdm_torch.decision as d\n"
        "print(json.dumps({n: type(getattr(d, n)).__name__ for n in d.__all__}))\n"
    )
    assert kinds["lspi"] == kinds["nac"] == "function"
    assert "module" not in kinds.values(), kinds
    assert set(kinds) == set(decision.__all__) and set(dir(decision)) >= set(decision.__all__)
