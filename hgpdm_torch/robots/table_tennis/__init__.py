"""The robot table-tennis setup: ball physics, opponent, SAPIEN scene, strokes and trials.

Modules that need SAPIEN (``scene``, ``strokes``, ``trials``) or matplotlib (``draw``) are imported
on first use of their names, so the ball model and the opponent work without the ``sim`` extra.
"""

from __future__ import annotations

import importlib
from typing import Any

_LAZY = {
    "BallParams": "ball",
    "BallState": "ball",
    "BallTrajectory": "ball",
    "MAX_SPEED": "ball",
    "MAX_SPIN": "ball",
    "aim": "ball",
    "is_legal_return": "ball",
    "predict_plane_crossing": "ball",
    "racket_contact": "ball",
    "simulate": "ball",
    "step": "ball",
    "OpponentConfig": "opponent",
    "Strokes": "opponent",
    "sample_strokes": "opponent",
    "SceneConfig": "scene",
    "TableTennisScene": "scene",
    "MOVEMENTS": "strokes",
    "StrokeConfig": "strokes",
    "StrokeOutcome": "strokes",
    "StrokePlanner": "strokes",
    "execute_stroke": "strokes",
    "DEFAULT_START_TIMES": "trials",
    "Trial": "trials",
    "Trials": "trials",
    "evaluate": "trials",
    "hitting_regions": "trials",
    "make_trials": "trials",
    "reward_table": "trials",
    "draw_arm": "draw",
    "draw_stroke": "draw",
    "draw_table": "draw",
    "plot_hitting_regions": "draw",
}

__all__ = sorted(_LAZY)


def __getattr__(name: str) -> Any:
    if name not in _LAZY:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    return getattr(importlib.import_module(f".{_LAZY[name]}", __name__), name)
