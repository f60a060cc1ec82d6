"""Four Walkers gap recovery: the two baselines against exact answers, a small real run, and the
trials the command finds (said before any work; a test folder without test trials stops it)."""

from __future__ import annotations

import math
from pathlib import Path

import pytest
import torch

from hgpdm_torch.datasets.cmu import load_protocol
from hgpdm_torch.datasets.walkers import Standardizer
from hgpdm_torch.experiments.gap_recovery import (
    FRAMES,
    GAP,
    METHODS,
    gap_recovery,
    linear_interpolation,
    main,
    template_copy,
)
from hgpdm_torch.results import ResultTable

from .test_walkers import touch

CMU = Path("../shared/data/cmu")


def test_linear_interpolation_is_exact_on_straight_lines_and_holds_the_ends():
    t = torch.arange(10, dtype=torch.float64)
    z = torch.stack([2 * t - 1, -0.5 * t + 3], -1)[None].repeat(2, 1, 1)
    holed = z.clone()
    holed[0, 3:7] = float("nan")
    holed[1, 7:] = float("nan")  # a gap at the end keeps the last observed row
    out = linear_interpolation(holed)
    torch.testing.assert_close(out[0], z[0], rtol=0, atol=1e-12)
    torch.testing.assert_close(out[1, 7:], z[1, 6].expand(3, 2), rtol=0, atol=0)
    with pytest.raises(ValueError, match="no observed row"):
        linear_interpolation(torch.full((1, 4, 2), float("nan")))


def test_template_copy_finds_the_training_stretch_a_window_was_cut_from():
    g = torch.Generator().manual_seed(0)
    train = [torch.randn(30, 3, generator=g, dtype=torch.float64) for _ in range(3)]
    z = train[1][7:19][None].clone()
    holed = z.clone()
    holed[0, 4:9] = float("nan")
    torch.testing.assert_close(template_copy(holed, train), z, rtol=0, atol=0)
    with pytest.raises(ValueError, match="40 frames"):
        template_copy(torch.zeros(1, 40, 3), train)


@pytest.mark.skipif(not CMU.is_dir(), reason="../shared/data/cmu absent: real-data test")
@pytest.mark.filterwarnings("ignore::hgpdm_torch.fitting.ConvergenceWarning")
def test_small_real_run_scores_the_test_trial_that_is_there():
    table = gap_recovery(folder=CMU, fit_steps=3, gaps=(4, 15))
    assert table.meta["training trials"] == ["35_02", "16_05"]
    assert table.meta["missing test trials"] == ["12_02", "12_03", "16_21"]
    row = table.rows[0]
    assert row["trial"] == "35_03" and table.rows[-1]["trial"] == "average"
    for m in METHODS:
        assert math.isfinite(row[m]) and row[m] > 0
    assert 0 <= row["accuracy"] <= 1
    # the interpolation baseline recomputed by hand on the first placement and the last
    train = load_protocol("four-walkers", folder=CMU)
    std = Standardizer().fit(train.sequences)
    z = std.transform(load_protocol("four-walkers", "test", CMU).sequences[0][:FRAMES])
    errs = []
    for g in (4, 15):
        a, b = z[g - 1], z[g + GAP]
        w = torch.arange(1, GAP + 1, dtype=z.dtype)[:, None] / (GAP + 1)
        errs.append((a + w * (b - a) - z[g : g + GAP]).pow(2))
    want = float(torch.cat(errs).mean().sqrt())
    assert row["linear interpolation"] == pytest.approx(want, rel=1e-10)


def test_cli_rejects_bad_values(tmp_path, capsys):
    with pytest.raises(SystemExit):
        main(["--test-data", str(tmp_path / "missing")])
    assert "not a folder" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main(["--fit-steps", "0"])
    assert "positive integer" in capsys.readouterr().err


def test_an_empty_test_folder_stops_the_run_instead_of_using_the_training_folder(tmp_path, capsys):
    data = touch(tmp_path / "data", "35.asf", "35_02.amc", "35_03.amc")
    empty = touch(tmp_path / "empty")
    with pytest.raises(SystemExit):
        main(["--data", str(data), "--test-data", str(empty)])
    err = capsys.readouterr().err
    assert f"--test-data {empty}: no four-walkers test trial (expected one of 35_03.amc, " in err
    with pytest.raises(FileNotFoundError, match="test_folder .*no four-walkers test trial"):
        gap_recovery(folder=data, test_folder=empty, fit_steps=1)
    with pytest.raises(SystemExit):
        main(["--data", str(empty)])
    assert f"--data {empty}: no four-walkers training trial (expected" in capsys.readouterr().err


def test_the_run_says_where_each_trial_came_from(tmp_path, capsys, monkeypatch):
    data = touch(tmp_path / "data", "35.asf", "16.asf", "35_02.amc", "35_03.amc")
    test = touch(tmp_path / "test", "16_21.amc")  # its skeleton from --data
    said = []

    def run(**kwargs):
        said.append(capsys.readouterr().err.splitlines())
        return ResultTable("t", ["trial"], meta={})

    monkeypatch.setattr("hgpdm_torch.experiments.gap_recovery.gap_recovery", run)
    assert main(["--data", str(data)]) == 0  # the documented default: test trials from --data
    assert said[0] == [
        f"hgpdm gap-recovery: training trials from --data {data}: subject 35: 35_02; subject 10: "
        "none (10_04 missing); subject 12: none (12_01 missing); subject 16: none (16_05 missing)",
        f"hgpdm gap-recovery: test trials from --data {data} (no --test-data given): subject 35: "
        "35_03; subject 12: none (12_02, 12_03 missing); subject 16: none (16_21 missing)",
    ]
    assert main(["--data", str(data), "--test-data", str(test)]) == 0
    assert said[1][1] == (
        f"hgpdm gap-recovery: test trials from --test-data {test}: subject 35: none (35_03 "
        "missing); subject 12: none (12_02, 12_03 missing); subject 16: 16_21"
    )
