"""Trials from the opponent, evaluation in SAPIEN, and the cached, parallel reward table."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from hgpdm_torch.robots.table_tennis import ball as B
from hgpdm_torch.robots.table_tennis import geometry as geo
from hgpdm_torch.robots.table_tennis.trials import Trials, evaluate, make_trials, reward_table

START = torch.tensor([0.0, 1.65, 1.0])


def aimed_trials(xs: list[float]) -> Trials:
    """Trials whose balls cross the hitting plane at the given lateral positions."""
    n = len(xs)
    res = B.aim_through_bounce(START.expand(n, 3), torch.tensor(xs), -0.9, 0.47)
    assert bool(res.converged.all())
    _, at, _ = B.predict_plane_crossing(B.make_state(START.expand(n, 3), res.vel), -2.17)
    return Trials(
        obs=torch.zeros(n, 6, 15),
        obs_times=torch.linspace(-0.4, 0.0, 6),
        targets=at.pos[:, 0],
        hit_times=torch.ones(n),
        ball_after_hit=B.make_state(START.expand(n, 3), res.vel),
    )


def test_make_trials_wraps_opponent() -> None:
    trials = make_trials(3, seed=0)
    assert len(trials) == 3 and trials.obs.shape[:2] == (3, trials.obs_times.shape[0])
    # The recorded targets are where the balls really cross the hitting plane.
    _, at, valid = B.predict_plane_crossing(trials.ball_after_hit, geo.HITTING_PLANE_Y)
    assert bool(valid.all())
    torch.testing.assert_close(at.pos[:, 0], trials.targets, atol=1e-3, rtol=0)
    again = make_trials(3, seed=0)
    torch.testing.assert_close(again.targets, trials.targets)
    t = trials[1]
    assert t.target == float(trials.targets[1]) and t.ball_after_hit.pos.shape == (3,)


def test_evaluate_and_reward_table_agree_and_cache(tmp_path) -> None:
    trials = aimed_trials([0.3, -0.9])
    out = evaluate(trials[0], "forehand", -0.24)
    assert out.success
    table = reward_table(trials, ("forehand",), (-0.24,), cache_dir=tmp_path, progress=False)
    assert table.shape == (2, 1, 1) and table.dtype == torch.int8
    assert table[:, 0, 0].tolist() == [1, -1]
    files = list((tmp_path / "table_tennis").glob("rewards_*.npy"))
    assert len(files) == 1
    # A second call reads the cache (a corrupted entry shows it is the file that is returned).
    np.save(files[0], np.full((2, 1, 1), 7, dtype=np.int8))
    cached = reward_table(trials, ("forehand",), (-0.24,), cache_dir=tmp_path, progress=False)
    assert cached.tolist() == [[[7]], [[7]]]


def test_reward_table_in_parallel_matches_serial(tmp_path) -> None:
    trials = aimed_trials([0.0, 0.6])
    serial = reward_table(trials, ("middle",), (-0.24,), cache_dir=tmp_path / "a", progress=False)
    par = reward_table(
        trials, ("middle",), (-0.24,), workers=2, cache_dir=tmp_path / "b", progress=False
    )
    assert torch.equal(serial, par)


def test_bad_arguments(tmp_path) -> None:
    trials = aimed_trials([0.0])
    with pytest.raises(ValueError, match="action"):
        reward_table(trials, ("lob",), (-0.2,), cache_dir=tmp_path, progress=False)
    with pytest.raises(ValueError, match="start_times"):
        reward_table(trials, ("middle",), (5.0,), cache_dir=tmp_path, progress=False)
    with pytest.raises(ValueError, match="workers"):
        reward_table(trials, workers=0, cache_dir=tmp_path, progress=False)
    with pytest.raises(ValueError, match="movement"):
        evaluate(trials[0], "lob", -0.2)
    with pytest.raises(TypeError, match="seed"):
        make_trials(2, seed="x")  # type: ignore[arg-type]
