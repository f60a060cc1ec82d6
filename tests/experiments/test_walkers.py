"""The Walkers experiment (real CMU walks): folds, calibration measures, a small real run."""

from __future__ import annotations

import math
from pathlib import Path

import pytest
import torch

from hgpdm_torch.experiments.walkers import METHODS, calibration, main, walker_folds, walkers

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


def test_calibration_against_hand_computed_values():
    truth = torch.tensor([0, 1, 1, 0])
    onehot = torch.nn.functional.one_hot(truth, 2).double()
    assert calibration(onehot, truth) == {"coverage": 1.0, "set_size": 1.0, "ece": 0.0}
    # Confident and wrong on one window of four: the 90% set misses it once.
    post = onehot.clone()
    post[3] = torch.tensor([0.0, 1.0])
    cal = calibration(post, truth)
    assert cal["coverage"] == 0.75 and cal["ece"] == pytest.approx(0.25)
    # 0.8 on the top class, right 3 times in 4: the 90% set needs both classes; ECE |0.75-0.8|.
    post = torch.tensor([[0.8, 0.2], [0.2, 0.8], [0.2, 0.8], [0.2, 0.8]])
    cal = calibration(post, truth)
    assert cal["coverage"] == 1.0 and cal["set_size"] == 2.0
    assert cal["ece"] == pytest.approx(0.05)


@pytest.mark.skipif(not CMU.is_dir(), reason="../shared/data/cmu absent: real-data test skipped")
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
