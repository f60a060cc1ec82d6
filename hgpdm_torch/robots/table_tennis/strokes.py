"""The robot's three hitting movements: forehand, middle and backhand (thesis Sec. 3.5.1, 4.3.1).

A movement follows the stages of a table-tennis stroke (thesis Fig. 3.5): the arm waits in the
*awaiting* pose; when the movement is initiated it swings to the movement's *preparation* pose
(a rest-to-rest quintic, as fast as the joint velocity and acceleration limits allow); once the
incoming ball is predictable from its flight (``predict_delay`` after the opponent's hit), and no
earlier than ``hit_duration`` before the ball reaches the virtual hitting plane and no earlier
than the arm has reached the preparation pose (the stage order of Fig. 3.5; optional), the
*hitting* stage plans a quintic from the arm's current state to the joint state that puts the
racket on the ball at the plane with the racket velocity and normal that return the ball to the
opponent's court (inverting the racket law of :mod:`.ball`); a *finishing* quintic brings the arm
to rest.

The reference that drives the simulated arm is the plan passed through a joint-space tracker whose
acceleration and velocity saturate at the limits, and the PD drives are force-limited at the
joint torque limits. A plan that needs more than the limits allow is therefore not followed, the
racket misses the ball, and the hitting region of each movement emerges from its preparation pose,
the limits and the time left - nothing states where a movement can hit. With the defaults and a
start 240 ms before the opponent's hit, the forehand returns balls crossing the plane at about
x in [0.15, 0.85] m, the middle movement [-0.25, 0.35] m and the backhand [-0.85, -0.2] m; beyond
+-0.85 m the elbow would need more than its acceleration limit, and beyond +-1.0 m the arm is too
short (see ``benchmarks/table_tennis.py`` and notebook 05 for the measured curves). Because the
preparation to a side pose takes 0.65-0.9 s, the side movements lose balls when started after
about 160 ms before the opponent's hit, and any movement fails when started too late.

The preparation poses are found by IK from several seeds; the one reachable fastest from the
middle pose wins, and the awaiting pose is the solution whose slowest move to a preparation pose
is quickest. The joint acceleration limits are our choice (the WAM's data sheet gives torque
limits, which the drives enforce); the joint velocity limits are the URDF's.

The movements are split by concept into the ``stroke_*`` modules below; this module re-exports
their public names, so that ``from hgpdm_torch.robots.table_tennis.strokes import execute_stroke``
and ``strokes.MOVEMENTS`` work as before:

* :mod:`~hgpdm_torch.robots.table_tennis.stroke_config`: the movement names and their settings;
* :mod:`~hgpdm_torch.robots.table_tennis.stroke_quintic`: the quintic segments of every stage;
* :mod:`~hgpdm_torch.robots.table_tennis.stroke_planner`: poses by IK and the plans of a ball;
* :mod:`~hgpdm_torch.robots.table_tennis.stroke_tracker`: the joint reference within the limits;
* :mod:`~hgpdm_torch.robots.table_tennis.stroke_execution`: one stroke simulated in SAPIEN, and
  its outcome (with how the simulation is made fast, and the slow reference,
  ``execute_stroke(..., reference=True)``, that the speed benchmark and the reward-agreement
  tests compare with).

Imports flow one way: ``stroke_config``, ``stroke_quintic`` <- ``stroke_planner``; those and
``stroke_tracker`` <- ``stroke_execution`` <- ``strokes``.
"""

from __future__ import annotations

from .stroke_config import MOVEMENTS, StrokeConfig
from .stroke_execution import EARLIEST_START, StrokeOutcome, execute_stroke
from .stroke_planner import HitPlan, StrokePlanner
from .stroke_quintic import Quintic, min_quintic_duration
from .stroke_tracker import LimitedTracker

__all__ = [
    "EARLIEST_START",
    "MOVEMENTS",
    "HitPlan",
    "LimitedTracker",
    "Quintic",
    "StrokeConfig",
    "StrokeOutcome",
    "StrokePlanner",
    "execute_stroke",
    "min_quintic_duration",
]
