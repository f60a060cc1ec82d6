"""Free-flight dynamics of the ball and its RK4 integration (no contacts).

``dv/dt = -g e_z - k_d |v| v + k_m (w x v)`` (gravity, quadratic drag, Magnus force) with the
spin ``w`` constant in flight. :func:`flight` is the acceleration; the private ``rk4_step`` is one
classical RK4 step of it with a per-ball step (its stages written out: the hot path of every
simulation), ``fly_batch_for`` a contact-free flight of given length.
"""

from __future__ import annotations

import math
from functools import lru_cache

import torch

from hgpdm_torch.robots.table_tennis.ball_state import DEFAULT_PARAMS, BallParams, BallState

__all__ = [
    "flight",
]


def flight(state: BallState, params: BallParams = DEFAULT_PARAMS) -> torch.Tensor:
    """Acceleration ``[..., 3]`` in free flight: ``-g e_z - k_d |v| v + k_m (w x v)``."""
    v, w = state.vel, state.spin
    acc = (-params.drag) * torch.linalg.vector_norm(v, dim=-1, keepdim=True) * v
    if params.magnus:
        acc = acc + params.magnus * torch.linalg.cross(w, v, dim=-1)
    acc[..., 2] -= params.gravity
    return acc


@lru_cache(maxsize=16)
def _gravity(g: float, dtype: torch.dtype, device: torch.device) -> torch.Tensor:
    return torch.tensor([0.0, 0.0, -g], dtype=dtype, device=device)


def rk4_step(state: BallState, h: torch.Tensor, params: BallParams) -> BallState:
    """One classical RK4 step of the flight ODE with a per-ball step ``h`` [...] (may be 0).

    :func:`flight` in few tensor operations (fused multiply-adds, the Magnus factor applied to
    the spin once), because batches of tens of balls cost per operation, not per ball.
    """
    h = h.unsqueeze(-1)
    p, v, w = state
    kd = -params.drag
    mw = params.magnus * w if params.magnus else None
    g = _gravity(params.gravity, v.dtype, v.device)

    def acc(u: torch.Tensor) -> torch.Tensor:
        a = torch.linalg.vector_norm(u, dim=-1, keepdim=True).mul(kd).mul(u)
        if mw is not None:
            a.add_(torch.linalg.cross(mw, u, dim=-1))
        return a.add_(g)

    hh = 0.5 * h
    a1 = acc(v)
    v2 = torch.addcmul(v, hh, a1)
    a2 = acc(v2)
    v3 = torch.addcmul(v, hh, a2)
    a3 = acc(v3)
    v4 = torch.addcmul(v, h, a3)
    a4 = acc(v4)
    h6 = h / 6.0
    new_p = torch.addcmul(p, h6, torch.add(v, v2, alpha=2).add_(v3, alpha=2).add_(v4))
    new_v = torch.addcmul(v, h6, torch.add(a1, a2, alpha=2).add_(a3, alpha=2).add_(a4))
    return BallState(new_p, new_v, w)


def fly_batch_for(
    pos: torch.Tensor, vel: torch.Tensor, spin: torch.Tensor, t: torch.Tensor, params: BallParams
) -> torch.Tensor:
    """Free-flight position after ``t`` [...] seconds (RK4, steps <= 5 ms, no contacts)."""
    n = max(8, math.ceil(float(t.max()) / 0.005))
    h = t / n
    s = BallState(pos, vel, spin)
    for _ in range(n):
        s = rk4_step(s, h, params)
    return s.pos
