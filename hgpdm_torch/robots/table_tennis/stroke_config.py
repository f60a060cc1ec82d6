"""Settings of the robot's hitting movements: the movement names and :class:`StrokeConfig`.

The three movements (thesis Sec. 3.5.1, 4.3.1) differ only by their preparation pose and racket
face; :class:`StrokeConfig` holds these with the joint limits and the timing of the stages that
:mod:`~hgpdm_torch.robots.table_tennis.strokes` describes.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from ..wam import DOF

__all__ = ["MOVEMENTS", "StrokeConfig"]

MOVEMENTS = ("forehand", "middle", "backhand")


@dataclass(frozen=True)
class StrokeConfig:
    """Settings of the hitting movements.

    Attributes:
        awaiting_position: racket centre of the awaiting pose (world, m).
        prep_x: racket ``x`` of each movement's preparation pose (forehand on the robot's right).
        prep_height: racket centre height of the preparation poses (m).
        prep_backswing: how far behind the hitting plane the racket waits in preparation (m).
        face: which racket face each movement hits with (+1: normal towards the opponent).
        acceleration_limit: joint acceleration limits (rad/s^2); velocity and torque limits come
            from the URDF.
        predict_delay: time after the opponent's hit from which the ball's flight is known (s).
        hit_duration: longest hitting stage (s): the swing starts this long before the ball
            reaches the hitting plane (from wherever the preparation has brought the arm), or
            later when the ball is predictable only later.
        hit_from_preparation: whether the hitting stage waits until the preparation pose is
            reached (the strict stage order of thesis Fig. 3.5) instead of starting from the
            arm's state on the way there.
        finish_duration: time to bring the arm to rest after the hit (s).
        return_target: ``(x, y)`` on the opponent's court where returns are aimed (m).
        return_flight_times: candidate flight times of the return (s); the first legal one in
            the simulated model wins.
    """

    awaiting_position: tuple[float, float, float] = (0.0, -2.3, 0.7)
    prep_x: dict[str, float] = field(
        default_factory=lambda: {"forehand": 0.6, "middle": 0.0, "backhand": -0.6}
    )
    prep_height: float = 0.75
    prep_backswing: float = 0.2
    face: dict[str, float] = field(
        default_factory=lambda: {"forehand": 1.0, "middle": 1.0, "backhand": -1.0}
    )
    acceleration_limit: tuple[float, ...] = (25.0, 25.0, 30.0, 30.0, 50.0, 50.0, 50.0)
    predict_delay: float = 0.16
    hit_duration: float = 0.35
    hit_from_preparation: bool = True
    finish_duration: float = 0.3
    return_target: tuple[float, float] = (0.0, 0.8)
    return_flight_times: tuple[float, ...] = (0.55, 0.65, 0.75, 0.85)

    def __post_init__(self) -> None:
        for d in (self.prep_x, self.face):
            if set(d) != set(MOVEMENTS):
                raise ValueError(f"prep_x and face must have the keys {MOVEMENTS}, got {set(d)}")
        if len(self.acceleration_limit) != DOF or min(self.acceleration_limit) <= 0:
            raise ValueError(f"acceleration_limit must be {DOF} positive values")
        for name in ("predict_delay", "hit_duration", "finish_duration"):
            if not getattr(self, name) > 0:
                raise ValueError(f"{name} must be positive, got {getattr(self, name)!r}")
