"""Table-tennis ball physics: flight, table bounce, net, racket contact, aiming (thesis Sec. 4.3).

The thesis evaluates its robot player in the SL simulator of the Barrett WAM table-tennis setup
(Mülling et al., 2011; Kober/Mülling lineage), whose ball model this module reproduces in batched
torch (float64, any leading batch dims ``...``):

* flight: ``dv/dt = -g e_z - k_d |v| v + k_m (w x v)`` (gravity, quadratic drag, Magnus force), the
  spin ``w`` constant in flight; integrated with RK4;
* table bounce: normal velocity times ``-0.88``, tangential velocity factors 0.72 (x) and 0.68 (y)
  (SL constants), extended to spin by applying the factors to the contact point's slip velocity
  and giving the spin the matching angular impulse (for a spin-free ball this is exactly the SL
  law);
* net: a vertical plane at ``y = 0`` that the ball must clear by its radius; a ball that touches
  it loses most of its speed;
* racket: reflection of the ball's velocity about the racket normal in the racket's frame with
  restitution 0.78 (the SL racket law); the rubber's grip sets the spin so that the ball leaves
  the face rolling (SL has no spin; a frictionless, spin-keeping contact is an option).

Table and net contacts are events located inside a step to machine precision (a safeguarded
Newton search on the RK4 flow), so results do not depend on the step size for ``dt <= 10 ms``.

A single float64 ball on the CPU (an unbatched state) is integrated by :class:`ScalarBall`, the same
arithmetic on Python floats (tensor operations on three numbers cost more than the numbers); batches
are tensors. One call simulates at most :data:`MAX_DURATION` seconds in at most :data:`MAX_STEPS`
steps.

The model is split by concept into the ``ball_*`` modules below; this module re-exports their
public names, so that ``from hgpdm_torch.robots.table_tennis.ball import simulate`` and
``ball.simulate`` work as before:

* :mod:`~hgpdm_torch.robots.table_tennis.ball_state`: constants, state and the ranges a call takes;
* :mod:`~hgpdm_torch.robots.table_tennis.ball_dynamics`: free flight and its RK4 integration;
* :mod:`~hgpdm_torch.robots.table_tennis.ball_contact`: the table, net and racket contact laws;
* :mod:`~hgpdm_torch.robots.table_tennis.ball_events`: stepping through located table and net
  contacts;
* :mod:`~hgpdm_torch.robots.table_tennis.ball_recording`: sampled flights, landing and legality;
* :mod:`~hgpdm_torch.robots.table_tennis.ball_crossing`: the crossing of a vertical plane;
* :mod:`~hgpdm_torch.robots.table_tennis.ball_aiming`: initial velocities that reach a target;
* :mod:`~hgpdm_torch.robots.table_tennis.ball_scalar`: one ball in plain floats (the fast path).

Imports flow one way: ``ball_state`` <- ``ball_scalar``, ``ball_dynamics``, ``ball_contact`` <-
``ball_events`` <- ``ball_recording``, ``ball_crossing`` <- ``ball_aiming`` <- ``ball``.
"""

from __future__ import annotations

from hgpdm_torch.robots.table_tennis import ball_state
from hgpdm_torch.robots.table_tennis.ball_aiming import BounceAim, aim, aim_through_bounce
from hgpdm_torch.robots.table_tennis.ball_contact import racket_contact, racket_velocity_for_return
from hgpdm_torch.robots.table_tennis.ball_crossing import predict_plane_crossing
from hgpdm_torch.robots.table_tennis.ball_dynamics import flight
from hgpdm_torch.robots.table_tennis.ball_events import StepEvents, propagate, step, step_events
from hgpdm_torch.robots.table_tennis.ball_recording import (
    BallTrajectory,
    Landing,
    is_legal_return,
    landing,
    simulate,
)
from hgpdm_torch.robots.table_tennis.ball_scalar import Floats as Floats
from hgpdm_torch.robots.table_tennis.ball_scalar import ScalarBall
from hgpdm_torch.robots.table_tennis.ball_state import *  # noqa: F403 (its __all__, below)

__all__ = [
    *ball_state.__all__,  # constants, state and ranges: listed once, there
    "BallTrajectory",
    "BounceAim",
    "Landing",
    "ScalarBall",
    "StepEvents",
    "aim",
    "aim_through_bounce",
    "flight",
    "is_legal_return",
    "landing",
    "predict_plane_crossing",
    "propagate",
    "racket_contact",
    "racket_velocity_for_return",
    "simulate",
    "step",
    "step_events",
]
