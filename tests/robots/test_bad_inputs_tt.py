"""Issue #18's bad inputs through the public entry points: ``evaluate`` refuses start times
outside the stroke's physical window and ``simulate`` refuses absurd durations, each with an
error naming the argument and its valid range, before any long simulation."""

from __future__ import annotations

import math

import pytest

pytest.importorskip("sapien")

from hgpdm_torch.robots.table_tennis import ball as B  # noqa: E402
from hgpdm_torch.robots.table_tennis import geometry as geo  # noqa: E402
from hgpdm_torch.robots.table_tennis.strokes import EARLIEST_START  # noqa: E402
from hgpdm_torch.robots.table_tennis.trials import evaluate  # noqa: E402


def test_evaluate_refuses_start_times_outside_the_stroke_window(opponent_trials) -> None:
    # evaluate(trial, "forehand", -100.0) used to simulate 100 s of waiting
    trial = opponent_trials[1]
    # when the ball reaches the hitting plane, as the stroke computes it (to the message's 1 ms)
    t_cross = float(B.predict_plane_crossing(trial.ball_after_hit, geo.HITTING_PLANE_Y, dt=0.01)[0])
    window = rf"start_time must lie in \[EARLIEST_START = {EARLIEST_START:g}, {t_cross:.3f}\) s"
    for bad in (-100.0, EARLIEST_START - 0.01, t_cross + 0.002, t_cross + 0.05, 1e9, -math.inf):
        with pytest.raises(ValueError, match=window):
            evaluate(trial, "forehand", bad)
    for bad in (math.nan, "soon", True):
        with pytest.raises(ValueError, match="start_time"):
            evaluate(trial, "forehand", bad)  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="movement"):
        evaluate(trial, "smash", -0.24)


def test_simulate_refuses_absurd_durations_and_steps() -> None:
    # simulate(state, 1e5, 0.05) used to run 2 million steps without a cap
    state = B.make_state([0.0, -1.5, 1.0], [0.0, 5.0, 1.0])
    batch = B.make_state([[0.0, -1.5, 1.0]] * 2, [[0.0, 5.0, 1.0]] * 2)
    for s in (state, batch):
        for bad in (1e5, B.MAX_DURATION * 1.01, 0.0, -1.0, math.inf, math.nan):
            with pytest.raises(ValueError, match=r"duration must be a number of seconds in \(0, "):
                B.simulate(s, bad, 0.05)
        with pytest.raises(ValueError, match=r"steps exceeds MAX_STEPS = 100000"):
            B.simulate(s, B.MAX_DURATION, 1e-5)
        for bad_dt in (0.0, -0.01, 0.5, math.nan):
            with pytest.raises(ValueError, match=r"dt must be a number in \(0, "):
                B.simulate(s, 1.0, bad_dt)
    # the largest allowed call still runs (and stops where it should)
    assert B.simulate(state, B.MAX_DURATION, 0.05).times[-1] == pytest.approx(B.MAX_DURATION)
