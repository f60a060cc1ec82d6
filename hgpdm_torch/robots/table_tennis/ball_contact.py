"""Contact laws of the ball: table bounce, net touch and racket hit.

* table bounce: normal velocity times ``-0.88``, tangential velocity factors 0.72 (x) and 0.68 (y)
  (SL constants) applied to the contact point's slip velocity, with the matching angular impulse;
* net: a ball that touches the net loses most of its speed;
* racket: reflection of the ball's velocity about the racket normal in the racket's frame with
  restitution 0.78 (the SL racket law), and :func:`racket_velocity_for_return`, its inverse.

The table and net laws map the state at a contact (located by
:mod:`~hgpdm_torch.robots.table_tennis.ball_events`) to the state after it.
"""

from __future__ import annotations

import torch

from hgpdm_torch.robots.table_tennis import geometry as geo
from hgpdm_torch.robots.table_tennis.ball_state import (
    DEFAULT_PARAMS,
    BallParams,
    BallState,
    check_params,
)
from hgpdm_torch.validation import as_tensor, check_shape

__all__ = [
    "racket_contact",
    "racket_velocity_for_return",
]


def table_bounce(s: BallState, params: BallParams) -> BallState:
    """Post-bounce state of balls touching the table (SL law on the contact point's slip)."""
    r = params.radius
    v, w = s.vel, s.spin
    # slip velocity of the contact point r_c = (0, 0, -r): v + w x r_c
    slip_x = v[..., 0] - r * w[..., 1]
    slip_y = v[..., 1] + r * w[..., 0]
    dvx = (params.table_friction_x - 1.0) * slip_x
    dvy = (params.table_friction_y - 1.0) * slip_y
    new_v = torch.stack(
        [v[..., 0] + dvx, v[..., 1] + dvy, -params.table_restitution * v[..., 2]], -1
    )
    # angular impulse of the friction impulse m dv at r_c: I dw = r_c x (m dv), I = kappa m r^2
    kr = params.inertia_factor * r
    new_w = torch.stack([w[..., 0] + dvy / kr, w[..., 1] - dvx / kr, w[..., 2]], -1)
    pos = s.pos.clone()
    pos[..., 2] = geo.TABLE_HEIGHT + r  # exactly on the surface so the event cannot re-trigger
    return BallState(pos, new_v, new_w)


def net_hit(s: BallState, sign: torch.Tensor, params: BallParams) -> BallState:
    """Post-contact state of balls touching the net face (``sign`` = direction of travel in y)."""
    scale = torch.tensor(
        [params.net_damping, -params.net_restitution, params.net_damping],
        dtype=s.vel.dtype,
        device=s.vel.device,
    )
    pos = s.pos.clone()
    pos[..., 1] = geo.NET_Y - sign * params.radius
    return BallState(pos, s.vel * scale, s.spin * params.net_damping)


def _unit(n: torch.Tensor, name: str) -> torch.Tensor:
    norm = n.norm(dim=-1, keepdim=True)
    if bool((norm < 1e-12).any()):
        raise ValueError(f"{name} must be non-zero vectors")
    return n / norm


def racket_contact(
    ball_vel: object,
    ball_spin: object,
    racket_vel: object,
    racket_normal: object,
    params: BallParams = DEFAULT_PARAMS,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Ball velocity and spin after a racket contact (SL racket law, Mülling et al., 2011).

    In the racket's frame the ball's normal velocity is reversed and scaled by the restitution
    ``e`` and its tangential velocity kept: ``v_out = v + (1 + e) ((v_r - v) . n) n``; the
    velocity law is symmetric in the sign of ``n``. The SL law has no spin; with
    ``params.racket_spin == "rolling"`` (default) the rubber grips the ball so that it leaves the
    face rolling: ``w_out = (w . n) n + n' x (v_out - v_r) / r`` with ``n'`` the normal oriented
    towards the departing ball (an upward brush gives topspin). With ``"kept"`` the contact is
    frictionless and ``w_out = w``. All arguments ``[..., 3]`` (broadcast); the normal need not
    be unit length.

    Returns:
        ``(vel_out, spin_out)``, each ``[..., 3]``.
    """
    params = check_params(params)
    v = as_tensor(ball_vel, "ball_vel", min_ndim=1)
    kw = {"dtype": v.dtype, "device": v.device, "min_ndim": 1}
    w = as_tensor(ball_spin, "ball_spin", **kw)
    vr = as_tensor(racket_vel, "racket_vel", **kw)
    n = as_tensor(racket_normal, "racket_normal", **kw)
    for t, name in ((v, "ball_vel"), (w, "ball_spin"), (vr, "racket_vel"), (n, "racket_normal")):
        check_shape(t, name, (3,))
    n = _unit(n, "racket_normal")
    closing = ((vr - v) * n).sum(-1, keepdim=True)
    vel_out = v + (1.0 + params.racket_restitution) * closing * n
    w = torch.broadcast_to(w, vel_out.shape)
    if params.racket_spin == "kept":
        return vel_out, w.clone()
    rel = vel_out - vr
    n = torch.broadcast_to(n, vel_out.shape)
    n_out = n * torch.sign((rel * n).sum(-1, keepdim=True))  # the face the ball leaves from
    spin_out = (w * n).sum(-1, keepdim=True) * n + torch.linalg.cross(n_out, rel) / params.radius
    return vel_out, spin_out


def racket_velocity_for_return(
    ball_vel_in: object,
    desired_vel_out: object,
    params: BallParams = DEFAULT_PARAMS,
    *,
    tangential: object | None = None,
    spin_out: object | None = None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Racket normal and velocity that turn ``ball_vel_in`` into ``desired_vel_out``.

    Inverts :func:`racket_contact`: the velocity change ``dv = v_out - v_in`` lies along the
    normal, so ``n = dv / |dv|``, and its size fixes the racket's normal speed,
    ``v_r . n = v_in . n + |dv| / (1 + e)``. The racket's tangential velocity does not change the
    ball's velocity. It is ``tangential`` projected onto the racket plane, or, given
    ``spin_out`` (``"rolling"`` spin law), the one that makes the ball leave with that spin's
    in-plane part, ``v_r,t = v_out,t + r n x w_out``; by default zero (the slowest racket).

    Args:
        ball_vel_in: ``[..., 3]`` ball velocity just before contact.
        desired_vel_out: ``[..., 3]`` ball velocity wanted just after contact.
        params: ball constants (uses ``racket_restitution``, ``radius``).
        tangential: optional ``[..., 3]`` racket velocity whose in-plane part is kept.
        spin_out: optional ``[..., 3]`` wanted spin after contact; its component along ``n``
            cannot be changed by the racket and is ignored.

    Returns:
        ``(racket_normal, racket_vel)``, each ``[..., 3]``; the normal is a unit vector pointing
        along ``dv`` (towards where the ball is sent).
    """
    params = check_params(params)
    v_in = as_tensor(ball_vel_in, "ball_vel_in", min_ndim=1)
    kw = {"dtype": v_in.dtype, "device": v_in.device}
    v_out = as_tensor(desired_vel_out, "desired_vel_out", **kw)
    check_shape(v_in, "ball_vel_in", (3,))
    check_shape(v_out, "desired_vel_out", (3,))
    if tangential is not None and spin_out is not None:
        raise ValueError("give at most one of tangential and spin_out")
    if spin_out is not None and params.racket_spin != "rolling":
        raise ValueError('spin_out needs params.racket_spin == "rolling"')
    dv = v_out - v_in
    if bool((dv.norm(dim=-1) < 1e-9).any()):
        raise ValueError(
            "desired_vel_out must differ from ball_vel_in (no contact changes nothing)"
        )
    n = dv / dv.norm(dim=-1, keepdim=True)
    speed = (v_in * n).sum(-1, keepdim=True) + dv.norm(dim=-1, keepdim=True) / (
        1.0 + params.racket_restitution
    )
    racket_vel = speed * n
    if tangential is not None:
        tan = as_tensor(tangential, "tangential", **kw)
        check_shape(tan, "tangential", (3,))
        racket_vel = racket_vel + tan - (tan * n).sum(-1, keepdim=True) * n
    elif spin_out is not None:
        w = as_tensor(spin_out, "spin_out", **kw)
        check_shape(w, "spin_out", (3,))
        v_t = v_out - (v_out * n).sum(-1, keepdim=True) * n
        racket_vel = racket_vel + v_t + params.radius * torch.linalg.cross(n, w.expand_as(n))
    return n, racket_vel
