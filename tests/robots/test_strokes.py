"""Hitting movements: trajectory pieces against oracles, and strokes simulated in SAPIEN."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from hgpdm_torch.robots.table_tennis import ball as B
from hgpdm_torch.robots.table_tennis import geometry as geo
from hgpdm_torch.robots.table_tennis.scene import TableTennisScene
from hgpdm_torch.robots.table_tennis.strokes import (
    EARLIEST_START,
    MOVEMENTS,
    LimitedTracker,
    Quintic,
    StrokeConfig,
    StrokePlanner,
    execute_stroke,
    min_quintic_duration,
)
from hgpdm_torch.robots.table_tennis.trials import make_trials


def test_quintic_boundaries_and_derivatives() -> None:
    rng = np.random.default_rng(0)
    q0, v0, a0, q1, v1, a1 = (rng.normal(size=7) for _ in range(6))
    qu = Quintic(0.2, 0.5, q0, v0, a0, q1, v1, a1)
    for t, ref in ((0.2, (q0, v0, a0)), (0.7, (q1, v1, a1))):
        for got, want in zip(qu(t), ref, strict=True):
            np.testing.assert_allclose(got, want, atol=1e-12)
    h = 1e-6
    p_minus, v_minus, _ = qu(0.4 - h)
    p_plus, v_plus, _ = qu(0.4 + h)
    _, v, a = qu(0.4)
    np.testing.assert_allclose((p_plus - p_minus) / (2 * h), v, atol=1e-6)
    np.testing.assert_allclose((v_plus - v_minus) / (2 * h), a, atol=1e-5)


def test_min_quintic_duration_meets_limits() -> None:
    q0, q1 = np.zeros(7), np.linspace(-1.0, 1.5, 7)
    vmax, amax = np.full(7, 3.0), np.full(7, 20.0)
    T = min_quintic_duration(q0, q1, vmax, amax)
    z = np.zeros(7)
    qu = Quintic(0.0, T, q0, z, z, q1, z, z)
    ts = np.linspace(0, T, 2001)
    vel = np.stack([qu(t)[1] for t in ts])
    acc = np.stack([qu(t)[2] for t in ts])
    assert np.abs(vel).max() <= 3.0 + 1e-9 and np.abs(acc).max() <= 20.0 + 1e-6
    # It is also the shortest: one of the two limits is met with equality.
    assert max(np.abs(vel).max() / 3.0, np.abs(acc).max() / 20.0) > 0.999


def test_tracker_follows_feasible_plan_and_saturates_infeasible() -> None:
    z = np.zeros(7)
    q1 = np.full(7, 0.3)
    slow = Quintic(0.0, 1.0, z, z, z, q1, z, z)
    tr = LimitedTracker(z, np.full(7, 10.0), np.full(7, 50.0))
    for k in range(1000):
        tr.update(slow((k + 1) * 1e-3), 1e-3)
    np.testing.assert_allclose(tr.q, q1, atol=1e-3)
    fast = Quintic(0.0, 0.1, z, z, z, q1, z, z)  # needs ~170 rad/s^2
    tr = LimitedTracker(z, np.full(7, 10.0), np.full(7, 20.0))
    for k in range(100):
        tr.update(fast((k + 1) * 1e-3), 1e-3)
    # With 20 rad/s^2 the reference covers at most a t^2 / 4 = 0.05 rad of a rest-to-rest move.
    assert float(np.abs(tr.q).max()) < 0.3 / 2


def test_blocks_of_the_reference_equal_its_steps() -> None:
    # a fast plan saturates the tracker; update_many gives what update gives, step by step
    rng = np.random.default_rng(1)
    z = np.zeros(7)
    for scale in (0.2, 2.0):
        qu = Quintic(0.0, 0.3, z, z, z, scale * rng.normal(size=7), z, z)
        one = LimitedTracker(z, np.full(7, 3.0), np.full(7, 30.0))
        many = LimitedTracker(z, np.full(7, 3.0), np.full(7, 30.0))
        for block in range(80):
            ts = 1e-3 * (5 * block + np.arange(5))
            for target in zip(*qu.at(ts), strict=True):
                one.update(target, 1e-3)
            many.update_many(*qu.at(ts), 1e-3)
            # the same elementwise steps, vectorised over a block: up to 400 steps rounding a
            # few eps of a state of size <= ~3 each, ~1e-12 at worst (measured: 1e-14)
            np.testing.assert_allclose(many.q, one.q, atol=1e-12, rtol=0)
            np.testing.assert_allclose(many.v, one.v, atol=1e-12, rtol=0)
        for t, pos, vel, acc in zip(ts, *qu.at(ts), strict=True):
            for got, want in zip((pos, vel, acc), qu(float(t)), strict=True):
                np.testing.assert_allclose(got, want, atol=1e-9, rtol=1e-12)


@pytest.fixture(scope="module")
def sim() -> tuple[TableTennisScene, StrokePlanner]:
    planner = StrokePlanner()
    return TableTennisScene(wam=planner.wam), planner


@pytest.fixture(scope="module")
def opponent_balls(opponent_trials) -> dict[str, B.BallState]:
    """Balls returned by the simulated opponent towards the right, the middle and the left."""
    sides = ("right", "centre", "left")  # the order of the targets in conftest.py
    return {k: opponent_trials[i].ball_after_hit for i, k in enumerate(sides)}


def test_preparation_poses_put_racket_behind_plane(sim) -> None:
    _, planner = sim
    cfg = planner.config
    for name, q in planner.prep.items():
        pos = planner.wam.fk(torch.as_tensor(q)).position
        assert abs(float(pos[0]) - cfg.prep_x[name]) < 1e-3
        assert float(pos[1]) < geo.HITTING_PLANE_Y


@pytest.mark.parametrize(
    "movement, side", [("forehand", "right"), ("middle", "centre"), ("backhand", "left")]
)
def test_movement_returns_opponent_ball_in_its_region(sim, opponent_balls, movement, side) -> None:
    scene, planner = sim
    out = execute_stroke(scene, planner, opponent_balls[side], movement, -0.24)
    assert out.hit and out.success, out.landing
    assert 0 < out.landing[1] <= geo.TABLE_HALF_LENGTH
    assert abs(out.landing[0]) <= geo.TABLE_HALF_WIDTH
    assert out.joint_path.shape == (out.racket_path.shape[0], 7)


@pytest.mark.parametrize("movement, side", [("forehand", "left"), ("backhand", "right")])
def test_movement_misses_far_outside_its_region(sim, opponent_balls, movement, side) -> None:
    scene, planner = sim
    assert not execute_stroke(scene, planner, opponent_balls[side], movement, -0.24).success


def test_late_start_fails(sim, opponent_balls) -> None:
    scene, planner = sim
    ball = opponent_balls["right"]
    t_cross, _, _ = B.predict_plane_crossing(ball, geo.HITTING_PLANE_Y)
    out = execute_stroke(scene, planner, ball, "forehand", float(t_cross) - 0.15)
    assert not out.success


def test_side_movement_needs_early_initiation(sim, opponent_balls) -> None:
    # The forehand's preparation takes ~0.9 s: initiated at the opponent's hit, it is still on
    # its way when the swing must begin and the ball it returns from -0.24 s is lost.
    scene, planner = sim
    assert not execute_stroke(scene, planner, opponent_balls["right"], "forehand", 0.0).success


def _agreement(scene, planner, balls, start_times) -> tuple[int, int]:
    """Cells whose reward is the same as with 1 ms steps throughout, and all cells."""
    same = cells = 0
    for ball in balls:
        for m in MOVEMENTS:
            for t0 in start_times:
                old = execute_stroke(scene, planner, ball, m, t0, reference=True)
                new = execute_stroke(scene, planner, ball, m, t0)
                same += old.success == new.success
                cells += 1
    return same, cells


def test_rewards_are_those_of_one_ms_steps(sim, opponent_balls) -> None:
    # The reference (1 ms PhysX steps throughout, the ball in PhysX from the opponent's hit) and
    # the fast executor on 3 balls x 3 movements x 2 start times: the same rewards.
    scene, planner = sim
    same, cells = _agreement(scene, planner, opponent_balls.values(), (-0.24, 0.0))
    assert same == cells, f"{cells - same} of {cells} rewards differ"


@pytest.mark.slow
def test_rewards_are_those_of_one_ms_steps_on_many_strokes() -> None:
    # 20 opponent trials x 3 movements x 5 start times: >= 99% of the 300 rewards agree (all
    # of them did, and 600 of 600 on make_trials(40, seed=0)). What can differ: PhysX's ball
    # strays by ~1 mm from the ball model before the robot-side bounce (the model flies it
    # there), and the arm's PD drives track with 10 ms steps until 100 ms before the hit.
    planner = StrokePlanner()
    scene = TableTennisScene(wam=planner.wam)
    trials = make_trials(20, seed=0)
    balls = [trials[i].ball_after_hit for i in range(len(trials))]
    same, cells = _agreement(scene, planner, balls, (-0.32, -0.24, -0.16, -0.08, 0.0))
    assert same >= 0.99 * cells, f"{cells - same} of {cells} rewards differ"


def test_reference_takes_1_ms_steps_with_the_ball_in_physx(sim, opponent_balls, monkeypatch):
    # the oracle of the agreement tests must differ from the fast executor where it cuts corners
    scene, planner = sim
    steps, parked = [], []
    step = scene.step

    def counting(n: int = 1) -> None:
        steps.append(n)
        parked.append(scene.ball_parked)  # during this step
        step(n)

    monkeypatch.setattr(scene, "step", counting)
    for reference in (True, False):
        steps.clear()
        parked.clear()
        out = execute_stroke(scene, planner, opponent_balls["centre"], "middle", -0.24,
                             reference=reference)  # fmt: skip
        assert out.hit
        # start of each step relative to the opponent's hit (the movement starts at -0.24 s)
        start = -0.24 + scene.dt * (np.cumsum(steps) - np.asarray(steps))
        in_play = start > 1e-6
        if reference:
            assert set(steps) == {1} and not any(np.asarray(parked)[in_play])
        else:
            assert max(steps) == scene.config.coarse_steps and any(np.asarray(parked)[in_play])
    with pytest.raises(TypeError, match="reference"):
        execute_stroke(scene, planner, opponent_balls["centre"], "middle", -0.24, reference=1)


def test_cached_plans_do_not_change_a_stroke(sim, opponent_balls) -> None:
    scene, planner = sim
    ball = opponent_balls["right"]
    warm = execute_stroke(scene, planner, ball, "forehand", -0.16)  # plans cached by now
    planner._cache.clear()
    cold = execute_stroke(scene, planner, ball, "forehand", -0.16)
    np.testing.assert_array_equal(warm.landing, cold.landing)
    np.testing.assert_array_equal(warm.racket_path, cold.racket_path)
    assert warm.success and warm.t_hit == cold.t_hit


def test_start_times_outside_the_stroke_window_are_refused(sim, opponent_balls) -> None:
    # evaluate(trial, "forehand", -100.0) used to simulate 100 s of waiting
    scene, planner = sim
    ball = opponent_balls["centre"]
    t_cross = float(B.predict_plane_crossing(ball, geo.HITTING_PLANE_Y, dt=0.01)[0])
    window = rf"start_time must lie in \[EARLIEST_START = {EARLIEST_START:g}, {t_cross:.3f}\) s"
    for reference in (False, True):
        for bad in (-100.0, EARLIEST_START - 1e-3, t_cross, 1e9, math.inf):
            with pytest.raises(ValueError, match=window):
                execute_stroke(scene, planner, ball, "middle", bad, reference=reference)
    with pytest.raises(ValueError, match="start_time"):
        execute_stroke(scene, planner, ball, "middle", "soon")  # type: ignore[arg-type]
    # the earliest start is allowed: the arm holds, prepares and swings for two seconds
    assert len(execute_stroke(scene, planner, ball, "middle", EARLIEST_START).racket_path) > 180


def test_bad_configuration(sim, opponent_balls) -> None:
    scene, planner = sim
    ball = opponent_balls["centre"]
    with pytest.raises(ValueError, match="movement"):
        execute_stroke(scene, planner, ball, "smash", -0.2)
    t_cross, _, _ = B.predict_plane_crossing(ball, geo.HITTING_PLANE_Y)
    with pytest.raises(ValueError, match="start_time"):
        execute_stroke(scene, planner, ball, "middle", float(t_cross) + 0.01)
    with pytest.raises(ValueError, match="start_time"):
        execute_stroke(scene, planner, ball, "middle", math.nan)
    with pytest.raises(ValueError, match="acceleration_limit"):
        StrokeConfig(acceleration_limit=(1.0,) * 3)
    with pytest.raises(ValueError, match="keys"):
        StrokeConfig(prep_x={"forehand": 0.4})
