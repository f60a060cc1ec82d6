"""Trials from the opponent, evaluation in SAPIEN, and the cached, parallel reward table."""

from __future__ import annotations

import json
from collections.abc import Callable, Iterable, Iterator

import numpy as np
import pytest
import torch

from hgpdm_torch.parallel import SerialExecutor
from hgpdm_torch.robots.table_tennis import ball as B
from hgpdm_torch.robots.table_tennis import geometry as geo
from hgpdm_torch.robots.table_tennis import trials as T
from hgpdm_torch.robots.table_tennis.trials import (
    Trials,
    evaluate,
    hitting_regions,
    make_trials,
    reward_table,
)


class Recording(SerialExecutor):
    """Runs the jobs here and keeps them, to see which cells were simulated."""

    def __init__(self) -> None:
        self.jobs: list[tuple] = []

    def map(self, fn: Callable, items: Iterable) -> Iterator:
        items = list(items)
        self.jobs += items
        return super().map(fn, items)

    def cells(self) -> list[tuple]:
        return [job[3] for job in self.jobs]


def subset(trials: Trials, idx: list[int]) -> Trials:
    return Trials(
        trials.obs[idx],
        trials.obs_times,
        trials.targets[idx],
        trials.hit_times[idx],
        B.BallState(*(f[idx] for f in trials.ball_after_hit)),
    )


def test_make_trials_wraps_opponent(opponent_trials) -> None:
    trials = opponent_trials
    assert len(trials) == 3 and trials.obs.shape[:2] == (3, trials.obs_times.shape[0])
    # The recorded targets are where the balls really cross the hitting plane, near the aims.
    _, at, valid = B.predict_plane_crossing(trials.ball_after_hit, geo.HITTING_PLANE_Y)
    assert bool(valid.all())
    torch.testing.assert_close(at.pos[:, 0], trials.targets, atol=1e-3, rtol=0)
    assert float((trials.targets - torch.tensor([0.75, 0.0, -0.75])).abs().max()) < 0.15
    again = make_trials(1, seed=5)
    assert torch.equal(make_trials(1, seed=5).targets, again.targets)
    t = trials[1]
    assert t.target == float(trials.targets[1]) and t.ball_after_hit.pos.shape == (3,)


def test_evaluate_reward_table_and_regions_agree_and_cache_every_cell(
    opponent_trials, tmp_path, monkeypatch
) -> None:
    trials = opponent_trials  # aimed at the robot's right, middle and left
    out = evaluate(trials[0], "forehand", -0.24)
    assert out.success
    table = reward_table(trials, ("forehand",), (-0.24,), cache_dir=tmp_path, progress=False)
    assert table.shape == (3, 1, 1) and table.dtype == torch.int8
    assert table[0, 0, 0] == 1 and table[2, 0, 0] == -1
    # the region curve bins exactly these rewards (read back from the cache: no new strokes)
    edges = np.array([-1.2, -0.4, 0.4, 1.2])
    none = Recording()
    centers, rates, counts = hitting_regions(
        trials, -0.24, edges, ("forehand",), executor=none, cache_dir=tmp_path, progress=False
    )
    assert none.jobs == []
    np.testing.assert_allclose(centers, [-0.8, 0.0, 0.8])
    assert counts.tolist() == [1, 1, 1]
    # bins run left to right, the trials right to left
    won = (table[:, 0, 0].numpy() > 0).astype(float)
    np.testing.assert_array_equal(rates["forehand"], won[::-1])
    # one cache file per trial, named by its ball
    files = {f.stem: f for f in (tmp_path / "table_tennis" / "rewards").glob("*/*.json")}
    assert sorted(files) == sorted(trials.fingerprints())
    # Another table simulates only its cells missing from the cache, once per distinct ball
    # (trial 2 appears twice): the forehand column comes from the cache.
    rec = Recording()
    both = reward_table(
        subset(trials, [2, 2, 0]), ("forehand", "middle"), (-0.24,), executor=rec,
        cache_dir=tmp_path, progress=False,
    )  # fmt: skip
    assert rec.cells() == [(("middle", -0.24),)] * 2
    assert torch.equal(both[:, :1], table[[2, 2, 0]]) and torch.equal(both[0], both[1])
    # A later call reads the cache (a flipped entry, written with its checksum, shows it is the
    # file that is returned).
    first = files[trials.fingerprints()[0]]
    stamp = T._Stamp(T._simulation_fingerprint(), first.parent.name)
    T._write_cells(first, {"forehand@-0.24": -1}, stamp)
    cached = reward_table(trials, ("forehand",), (-0.24,), cache_dir=tmp_path, progress=False)
    assert cached.flatten().tolist() == [-1, *table.flatten().tolist()[1:]]
    # A flip by hand fails the checksum: that trial is simulated again, with one warning.
    second = files[trials.fingerprints()[1]]
    data = json.loads(second.read_text())
    data["cells"]["forehand@-0.24"] *= -1
    second.write_text(json.dumps(data))
    with pytest.warns(UserWarning, match="rejected 1 of 3 files"):
        honest = reward_table(trials, ("forehand",), (-0.24,), cache_dir=tmp_path, progress=False)
    assert torch.equal(honest, cached)
    # A changed simulation (its source hash) does not read the old cells.
    monkeypatch.setattr(T, "_simulation_fingerprint", lambda: "changed")
    fresh = reward_table(trials, ("forehand",), (-0.24,), cache_dir=tmp_path, progress=False)
    assert torch.equal(fresh, table)


def test_reward_table_in_parallel_matches_serial(opponent_trials, tmp_path) -> None:
    trials = opponent_trials
    serial = reward_table(trials, ("middle",), (-0.24,), cache_dir=tmp_path / "a", progress=False)
    par = reward_table(
        trials, ("middle",), (-0.24,), workers=2, cache_dir=tmp_path / "b", progress=False
    )
    assert torch.equal(serial, par)


def test_bad_arguments(opponent_trials, tmp_path) -> None:
    trials = opponent_trials
    with pytest.raises(ValueError, match="action"):
        reward_table(trials, ("lob",), (-0.2,), cache_dir=tmp_path, progress=False)
    with pytest.raises(ValueError, match="start_times"):
        reward_table(trials, ("middle",), (5.0,), cache_dir=tmp_path, progress=False)
    with pytest.raises(ValueError, match="workers"):
        reward_table(trials, workers=0, cache_dir=tmp_path, progress=False)
    with pytest.raises(ValueError, match="not both"):
        reward_table(trials, workers=2, executor=SerialExecutor(), cache_dir=tmp_path)
    with pytest.raises(TypeError, match="executor"):
        reward_table(trials, executor=2, cache_dir=tmp_path)  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="bins"):
        hitting_regions(trials, -0.24, [0.5, 0.0], cache_dir=tmp_path, progress=False)
    with pytest.raises(ValueError, match="movement"):
        evaluate(trials[0], "lob", -0.2)
    with pytest.raises(TypeError, match="seed"):
        make_trials(2, seed="x")  # type: ignore[arg-type]
