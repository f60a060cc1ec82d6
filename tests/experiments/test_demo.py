"""``hgpdm demo``: the anticipatory player end to end on a few strokes simulated in SAPIEN."""

from __future__ import annotations

import json

import pytest

pytest.importorskip("sapien")

from hgpdm_torch import cli  # noqa: E402
from hgpdm_torch.experiments.demo import run_demo  # noqa: E402


def test_demo_plays_rallies_in_sapien(tmp_path, capsys):
    out = tmp_path / "out"
    args = ["demo", "--trials", "12", "--watched", "20", "--workers", "1", "--out", str(out)]
    assert cli.main([*args, "--cache-dir", str(tmp_path / "cache")]) == 0
    table = json.loads((out / "demo.json").read_text())
    players = [r["player"] for r in table["rows"]]
    assert players[-2:] == ["LSPI", "MCP"] and len(players) == 8
    n_test = int(table["title"].split(", ")[1].split()[0])
    for row in table["rows"]:
        assert 0 <= row["returns"] <= n_test
        assert row["rate"] == pytest.approx(row["returns"] / n_test)
    # the live SAPIEN rallies reproduce the reward table of the deterministic scene
    assert table["meta"]["live = table"] == f"{n_test}/{n_test}"
    for name in ("return_rates.png", "rally.png"):
        assert (out / name).stat().st_size > 10_000
    assert "MCP" in capsys.readouterr().out


def test_demo_rejects_bad_arguments():
    with pytest.raises(ValueError, match="test_fraction"):
        run_demo(test_fraction=1.0)
    with pytest.raises(ValueError, match="watched"):
        run_demo(watched=-1)
    with pytest.raises(ValueError, match="num_trials"):
        run_demo(num_trials=0)
    with pytest.raises(ValueError, match="workers"):
        run_demo(workers=-2)
