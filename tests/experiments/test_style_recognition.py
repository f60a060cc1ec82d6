"""Style-recognition experiment (Tables 2.1-2.4, Fig. 2.3) at smoke size."""

from __future__ import annotations

import json
import math

import pytest
import torch

from hgpdm_torch.experiments import style_recognition as sr

#: the experiment at smoke sizes fits its models a few steps on purpose (each FitResult says it
#: stopped at the step limit): their ConvergenceWarnings are expected here, and only here
SHORT_FITS = pytest.mark.filterwarnings("ignore::hgpdm_torch.fitting.ConvergenceWarning")


@SHORT_FITS
def test_synthetic_table_layout_and_recognition(tmp_path):
    table = sr.style_recognition(("synthetic",), lengths=(5,), fit_steps=40)
    assert table.columns == sr.COLUMNS and len(table.rows) == 1
    row = table.rows[0]
    assert row["data"] == "synthetic" and row["T"] == 5 and row["windows"] >= 10
    assert row["VB H-GPDM accuracy"] >= 0.9  # chance is 1/3
    rmses = [row[c] for c in sr.COLUMNS if c.endswith("RMSE")]
    assert all(math.isfinite(v) and v > 0 for v in rmses)
    # the style-aware model forecasts better than one model for all styles
    assert row["oracle VB RMSE"] < row["GPDM VB RMSE"]
    table.to_json(tmp_path / "t.json")
    assert json.loads((tmp_path / "t.json").read_text())["rows"][0]["T"] == 5


@SHORT_FITS
def test_basic_motions_loader_and_row():
    pytest.importorskip("aeon")
    data = sr.load_data("basic_motions", smoke=True)
    assert len(data.train) == 8 and data.train[0].shape == (34, 6)
    assert sorted(data.train_labels.tolist()) == [0, 0, 1, 1, 2, 2, 3, 3]
    flat = torch.cat(data.train)
    torch.testing.assert_close(flat.mean(0), torch.zeros(6), atol=1e-9, rtol=0)
    table = sr.style_recognition(("basic_motions",), lengths=(5,), fit_steps=20, stride=2)
    row = table.rows[0]
    assert row["data"] == "basic_motions" and row["windows"] >= 60
    # 4 activities, chance 0.25 (measured: 0.52 of 60 windows at smoke size, 0.58 at full size)
    assert row["VB H-GPDM accuracy"] >= 0.4
    assert all(math.isfinite(row[c]) for c in sr.COLUMNS if c.endswith("RMSE"))
    assert row["oracle VB RMSE"] < row["repeat last frame RMSE"]


@SHORT_FITS
def test_gap_figure_and_main(tmp_path, monkeypatch):
    import matplotlib

    backend = matplotlib.get_backend()
    matplotlib.use("svg")  # a user's choice the library must not override
    try:
        rmse = sr.gap_recovery_figure(tmp_path / "gap.png", fit_steps=40)
        assert matplotlib.get_backend() == "svg"
    finally:
        matplotlib.use(backend)
    assert (tmp_path / "gap.png").stat().st_size > 1000
    assert rmse["H-GPDM"] < rmse["GPDM"]
    with pytest.raises(ValueError, match="datasets"):
        sr.style_recognition(("mocap",))
    calls = {}
    monkeypatch.setattr(sr, "style_recognition", lambda *a, **k: calls.setdefault("t", _table()))
    assert (
        sr.main(["--data", "synthetic", "--lengths", "5", "--out", str(tmp_path / "o.json")]) == 0
    )
    assert (tmp_path / "o.json").exists() and "t" in calls


def _table():
    from hgpdm_torch.results import ResultTable

    return ResultTable("t", ["data"], [{"data": "synthetic"}])
