"""The Walkers experiment (real CMU walks): folds and a small real run."""

from __future__ import annotations

import math
from pathlib import Path

import pytest

from hgpdm_torch.experiments.walkers import METHODS, main, walker_folds, walkers

#: the experiment at smoke sizes fits its models a few steps on purpose (each FitResult says it
#: stopped at the step limit): their ConvergenceWarnings are expected here, and only here
SHORT_FITS = pytest.mark.filterwarnings("ignore::hgpdm_torch.fitting.ConvergenceWarning")

CMU = Path("../shared/data/cmu")


def test_folds_are_grouped_balanced_and_cover_every_trial():
    subject = [0, 0] + [1] * 15
    splits = walker_folds(subject, folds=5, train_per_subject=3)
    assert len(splits) == 5
    tested = set()
    for train, test in splits:
        assert not set(train) & set(test)
        assert sorted(subject[i] for i in train) == [0, 1, 1, 1]
        assert sorted(subject[i] for i in test) == [0, 1, 1, 1]
        tested |= set(test)
    assert tested == set(range(17))
    with pytest.raises(ValueError, match="at least 2"):
        walker_folds([0, 1, 1])
    with pytest.raises(ValueError, match="folds"):
        walker_folds(subject, folds=0)
    with pytest.raises(ValueError, match="train_per_subject"):
        walker_folds(subject, train_per_subject=0)


@pytest.mark.skipif(not CMU.is_dir(), reason="../shared/data/cmu absent: real-data test skipped")
@SHORT_FITS
def test_small_real_run_has_every_method_and_an_exact_baseline():
    from hgpdm_torch.datasets import load_walkers
    from hgpdm_torch.experiments.style_recognition import forecast_windows

    data = load_walkers(CMU)
    table = walkers(
        data, lengths=(4,), fit_steps=4, folds=1, train_per_subject=1, stride=8, sharing=0.5
    )
    assert [r["method"] for r in table.rows] == list(METHODS)
    assert table.meta["sharing"] == 0.5
    for row in table.rows:
        assert math.isfinite(row["RMSE"]) and row["RMSE"] > 0
    fits = table.meta["fits"][0]
    assert {"H-GPDM", "GPDM"} <= set(fits) and fits["H-GPDM"]["steps"] == 4
    # Repeat-last-frame RMSE recomputed independently from the same fold.
    from hgpdm_torch.datasets import Standardizer

    train, test = walker_folds(data.subject, 1, 1)[0]
    std = Standardizer().fit([data.sequences[i] for i in train])
    z, nxt, _ = forecast_windows(
        [std.transform(data.sequences[i]) for i in test], data.subject[test], 4, 8
    )
    want = float((z[:, -1] - nxt).pow(2).mean().sqrt())
    got = table.rows[list(METHODS).index("repeat last frame")]["RMSE"]
    assert got == pytest.approx(want, rel=1e-12)
    cal = table.meta["calibration"]["4"][0]
    assert 0 <= cal["ece"] <= 1 and 1 <= cal["set_size"] <= 2


def test_cli_rejects_bad_values_before_any_work(tmp_path, capsys):
    with pytest.raises(SystemExit):
        main(["--folds", "0"])
    assert "positive integer" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main(["--data", str(tmp_path / "missing")])
    assert "not a folder" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main(["--sharing", "1.0"])
    assert "--sharing" in capsys.readouterr().err
