"""Fixtures shared by the robot tests: a few real opponent trials, sampled once per session."""

from __future__ import annotations

import pytest

from hgpdm_torch.robots.table_tennis.opponent import OpponentConfig
from hgpdm_torch.robots.table_tennis.trials import Trials, make_trials

AIMS = {"right": 0.75, "centre": 0.0, "left": -0.75}
"""Intended targets of the shared trials, in order (the robot's right is +x)."""


@pytest.fixture(scope="session")
def opponent_trials() -> Trials:
    """Three strokes of the simulated opponent aimed at the robot's right, middle and left.

    Their balls cross the hitting plane 0.76-1.03 m high, as most returns do (seed 3, say, sends
    one 0.42 m high, below the table top, out of the backhand's reach in time).
    """
    return make_trials(
        3, seed=7, targets=list(AIMS.values()), config=OpponentConfig(late_change_prob=0.0)
    )
