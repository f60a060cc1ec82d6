"""The `hgpdm` command and the style-discovery experiment."""

from __future__ import annotations

import json

import pytest
import torch

from hgpdm_torch import cli
from hgpdm_torch.experiments.style_discovery import style_purity


def test_style_discovery_runs_and_discovers_styles(tmp_path, capsys):
    assert cli.main(["style-discovery", "--quick", "--out", str(tmp_path)]) == 0
    table = json.loads((tmp_path / "style_discovery.json").read_text())
    discovered = [r for r in table["rows"] if r["styles"].startswith("discovered")][0]
    assert discovered["style purity"] >= 0.9
    assert (tmp_path / "latent_trajectories.png").stat().st_size > 10_000
    assert "style purity" in capsys.readouterr().out


def test_help_and_unknown_command(capsys):
    assert cli.main([]) == 0
    assert "demo" in capsys.readouterr().out
    with pytest.raises(SystemExit):
        cli.main(["no-such-command"])


def test_style_purity():
    truth = torch.tensor([0, 0, 1, 1, 2, 2])
    assert style_purity(truth, torch.tensor([2, 2, 0, 0, 1, 1])) == 1.0
    assert style_purity(truth, torch.tensor([0, 0, 0, 0, 0, 0])) == pytest.approx(2 / 6)
    with pytest.raises(ValueError, match="truth"):
        style_purity(truth, torch.tensor([0, 1]))
