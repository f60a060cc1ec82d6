"""``hgpdm style-discovery --data weird-walking``: the trials it found, said before any work,
and all absent ones named at once (empty files: nothing may be read)."""

from __future__ import annotations

import re

import pytest

from hgpdm_torch.datasets.cmu import PROTOCOLS
from hgpdm_torch.experiments.style_discovery import main, run_style_discovery


def test_weird_walking_names_every_absent_trial_and_says_what_it_found(
    tmp_path, capsys, monkeypatch
):
    trials = [t for t, _ in PROTOCOLS["weird-walking"].train]
    for name in ("132.asf", *(f"{t}.amc" for t in trials if t not in ("132_02", "132_46"))):
        (tmp_path / name).write_text("")
    with pytest.raises(SystemExit):
        main(["--data", "weird-walking", "--cmu", str(tmp_path), "--out", str(tmp_path / "o")])
    want = f"--cmu {tmp_path}: the weird-walking training trials must all be there; absent: "
    assert want + "132_02.amc, 132_46.amc" in capsys.readouterr().err
    with pytest.raises(FileNotFoundError, match=re.escape("absent: 132_02.amc, 132_46.amc")):
        run_style_discovery(data="weird-walking", folder=tmp_path)
    for name in ("132_02.amc", "132_46.amc"):
        (tmp_path / name).write_text("")

    class Stop(Exception):
        """The run itself is not under test."""

    def run(**kwargs):
        raise Stop

    monkeypatch.setattr("hgpdm_torch.experiments.style_discovery.run_style_discovery", run)
    with pytest.raises(Stop):
        main(["--data", "weird-walking", "--cmu", str(tmp_path), "--out", str(tmp_path / "o")])
    assert capsys.readouterr().err == (
        f"hgpdm style-discovery: training trials from --cmu {tmp_path}: style arms out: 132_01, "
        "132_02, 132_03, 132_04, 132_05; style fast: 132_17, 132_18, 132_19; style hopping on "
        "the left foot: 132_23, 132_24, 132_25; style slow: 132_45, 132_46, 132_47\n"
    )
