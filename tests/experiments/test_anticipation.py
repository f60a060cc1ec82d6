"""The Sec. 4.3 protocol on synthetic strokes (no simulator): bookkeeping against direct counts,
exclusion, and learning that beats the single-movement baselines; the CLI at smoke size."""

from __future__ import annotations

import pytest
import torch

from hgpdm_torch.datasets import targeted_movements
from hgpdm_torch.decision.beliefs import decision_indices
from hgpdm_torch.experiments.anticipation import (
    AnticipationConfig,
    plot_results,
    run_protocol,
    valid_trials,
)

START = (-0.32, -0.24, -0.16, -0.08, 0.0)
OBS_TIMES = torch.tensor([-0.4, -0.32, -0.24, -0.16, -0.08, 0.0])


def _synthetic(n: int, seed: int = 0):
    """Strokes whose late frames reveal the target; the movement of the target's region returns
    the ball if started at least 80 ms before the hit, any other never; |g| > 1.1 is unreachable."""
    data = targeted_movements(n, len(OBS_TIMES), 6, target_range=(-1.2, 1.2), noise=0.02, seed=seed)
    obs = torch.stack(data.sequences)
    g = data.labels
    region = torch.bucketize(g, torch.tensor([-0.4, 0.4]))
    right = torch.arange(3)[None, :, None] == region[:, None, None]
    in_time = torch.tensor(START)[None, None, :] <= -0.08
    rewards = torch.where(right & in_time & (g.abs() <= 1.1)[:, None, None], 1.0, -1.0)
    return obs, g, rewards


@pytest.fixture(scope="module")
def result():
    obs, g, rewards = _synthetic(45)
    # a return just beyond the grid (+-1.2), out of reach as before: the oracle clips it
    far = int(torch.nonzero(g.abs() > 1.1)[0])
    g[far] = 1.3 * g[far].sign()
    config = AnticipationConfig.smoke(
        folds=3, repetitions=2, episodes=(2,), iddm_trials=14, fit_steps=10, grid_size=9,
        centres=15, particles=100, nac_iterations=15,
    )  # fmt: skip
    fig6, fig7 = run_protocol(obs, OBS_TIMES, g, rewards, START, config)
    return obs, g, rewards, fig6, fig7


def test_tables_and_bookkeeping(result):
    _, g, rewards, fig6, fig7 = result
    valid = valid_trials(rewards)
    n = int(valid.sum())
    assert n == int((g.abs() <= 1.1).sum()) and fig6.meta["valid trials"] == n
    rows = {r["method"]: r for r in fig6.rows}
    assert list(rows) == [
        "single forehand @240ms", "single middle @240ms", "single backhand @240ms",
        "oracle timing @240ms", "oracle timing @160ms", "oracle timing @80ms",
        "best blind (training folds)", "best fixed time (training folds)", "NAC", "LSPI", "MCP",
        "LSPI (linear-iddm belief)", "LSPI (gp-iddm belief)", "LSPI (promp belief)",
        "MCP (oracle belief)",
    ]  # fmt: skip
    # the belief of each fold, chosen among the candidates by CV on its training strokes
    assert len(fig6.meta["belief used"]) == 3
    assert set(fig6.meta["belief used"]) <= {"linear-iddm", "gp-iddm"}
    for used, cv in zip(fig6.meta["belief used"], fig6.meta["belief CV return rates"],
                        strict=True):  # fmt: skip
        assert cv[used] == max(cv.values())
    # every valid trial is tested once per repetition: the single-movement counts are direct sums
    for a, name in enumerate(("forehand", "middle", "backhand")):
        row = rows[f"single {name} @240ms"]
        assert row["returns"] == int((rewards[valid, a, 1] > 0).sum())
        assert row["SEM"] == 0.0 and row["rate"] == pytest.approx(row["returns"] / n)
    for r in fig6.rows:
        assert 0 <= r["returns"] <= n
    assert rows["LSPI"]["SEM"] == 0.0  # deterministic given the folds
    # a blind strategy chosen on the training folds: the same in every repetition
    assert rows["best blind (training folds)"]["SEM"] == 0.0
    assert fig7.column("episodes") == [2]


def test_learning_beats_single_movements(result):
    *_, fig6, _ = result
    rows = {r["method"]: r["returns"] for r in fig6.rows}
    best_single = max(v for k, v in rows.items() if k.startswith("single"))
    assert rows["oracle timing @80ms"] > best_single
    assert rows["LSPI"] > best_single and rows["MCP"] > best_single
    assert rows["MCP (oracle belief)"] >= rows["best blind (training folds)"]


def test_plots(result, tmp_path):
    *_, fig6, fig7 = result
    paths = plot_results(fig6, fig7, tmp_path)
    assert all(p.exists() and p.stat().st_size > 1000 for p in paths)


def test_decision_indices_and_bad_input():
    assert decision_indices(OBS_TIMES, START) == [1, 2, 3, 4, 5]
    with pytest.raises(ValueError, match="no observation"):
        decision_indices(OBS_TIMES, (-0.5,))
    obs, g, rewards = _synthetic(12)
    config = AnticipationConfig.smoke(folds=3)
    with pytest.raises(ValueError, match="rewards must have shape"):
        run_protocol(obs, OBS_TIMES, g, rewards[:, :2], START, config)
    with pytest.raises(ValueError, match="start_times must include"):
        run_protocol(obs, OBS_TIMES, g, rewards[..., :3], START[:3], config)
    with pytest.raises(ValueError, match="valid trials"):
        run_protocol(obs, OBS_TIMES, g, rewards, START, AnticipationConfig.smoke(folds=10))
    with pytest.raises(ValueError, match="folds"):
        AnticipationConfig(folds=1)
    with pytest.raises(ValueError, match="episodes"):
        AnticipationConfig(episodes=(0,))
    with pytest.raises(ValueError, match="unknown belief 'oracle'"):
        AnticipationConfig(belief="oracle")
    with pytest.raises(ValueError, match="unknown features"):
        AnticipationConfig(features="pixels")
    with pytest.raises(ValueError, match="wait_value"):
        AnticipationConfig(wait_value="forever")
