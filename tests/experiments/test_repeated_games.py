"""Sec. 5.4 experiments at small sizes: the properties the thesis figures show."""

from __future__ import annotations

import numpy as np
import pytest

from hgpdm_torch.experiments.repeated_games import (
    main,
    stationary_rps,
    switching_rps,
    table_tennis_serves,
    two_stage_rps_experiment,
)


def test_stationary_rps_bound_holds_and_converges() -> None:
    table = stationary_rps([1, 30, 1000, 10**6, 10**8], repeats=8, delta=0.1, seed=1)
    assert table.column("n_samples") == [1, 30, 1000, 10**6, 10**8]
    # the estimate lower-bounds the true reward (at least 1 - delta of runs; here always)
    assert min(table.column("bound_held")) >= 0.9
    est, true = table.column("estimated_mean"), table.column("true_mean")
    assert all(np.diff(est) >= -1e-9)  # the bound tightens with data
    assert true[-1] == pytest.approx(0.4, abs=1e-3) and est[-1] == pytest.approx(0.4, abs=2e-3)
    # with one observation delta-safe plays minimax (0), fictitious play can lose
    assert table.rows[0]["true_min"] == pytest.approx(0.0, abs=1e-9)
    assert table.rows[0]["fp_true_min"] < 0


def test_switching_rps_detection_beats_no_detection() -> None:
    table = switching_rps(n_games=700, switch_at=250, n_min=64, repeats=3, window=50, seed=2)
    meta = table.meta
    assert meta["detected_within_3_blocks"] == 1.0
    assert meta["false_alarm_rate_per_test"] <= 0.1 and meta["false_alarm_tests"] > 0
    with_cd = np.array(meta["curves"]["with_detection"])
    without = np.array(meta["curves"]["without_detection"])
    np.testing.assert_allclose(with_cd[:128], without[:128])  # identical until the first test
    assert with_cd[250:].mean() > without[250:].mean() + 0.1
    assert len(table.rows) == 14


def test_two_stage_rps_converges_to_global_optimum() -> None:
    table = two_stage_rps_experiment([10, 10**6], repeats=3, seed=3)
    assert min(table.column("bound_held")) == 1.0
    last = table.rows[-1]
    assert last["optimal"] == pytest.approx(0.8)  # 0.2 at Stage 1 + 2 x 0.3 on average at Stage 2
    assert last["true_mean"] == pytest.approx(0.8, abs=1e-3)
    assert 0.7 < last["estimated_mean"] <= last["true_mean"]


def test_table_tennis_serves_aer() -> None:
    uniform = table_tennis_serves("uniform", n_serves=120, repeats=8, seed=4)
    final = uniform.rows[-1]
    # the middle pose is optimal against uniform serves; delta-safe beats minimax, nears it
    assert final["pure_middle"] > max(final["pure_forehand"], final["pure_backhand"])
    assert final["delta_safe_detection"] > final["minimax"]
    # the paired difference over sessions averages to the difference of the final AERs (the
    # mean of the sessions' means), and its SEM is that of 8 sessions' differences
    meta = uniform.meta
    assert meta["delta_safe_detection - minimax"] == pytest.approx(
        final["delta_safe_detection"] - final["minimax"], abs=1e-12
    )
    assert 0.0 < meta["delta_safe_detection - minimax SEM"] < 0.1
    switching = table_tennis_serves("switching", n_serves=150, repeats=8, seed=5)
    end = switching.rows[-1]
    assert end["delta_safe_detection"] > end["delta_safe"]
    with pytest.raises(ValueError, match="volunteer"):
        table_tennis_serves("nobody")


def test_cli_quick(capsys: pytest.CaptureFixture[str], tmp_path) -> None:
    assert main(["two-stage", "--quick", "--json", str(tmp_path / "t.json")]) == 0
    assert "Fig. 5.3" in capsys.readouterr().out
    assert (tmp_path / "t.json").exists()
