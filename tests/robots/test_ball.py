"""Tests of the table-tennis ball model against closed forms, scipy and conservation laws."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from scipy.integrate import solve_ivp

from hgpdm_torch.robots.table_tennis import ball as B
from hgpdm_torch.robots.table_tennis import geometry as geo

P = B.BallParams()
VACUUM = B.BallParams(drag=0.0, magnus=0.0)
SURFACE = geo.TABLE_HEIGHT + geo.BALL_RADIUS


def _served(n: int, generator: torch.Generator) -> B.BallState:
    """Robot-side hits aimed at random points on the opponent's half, with random spin."""
    u = torch.rand(n, 6, generator=generator)
    pos = torch.stack([0.6 * u[:, 0] - 0.3, -1.7 - 0.3 * u[:, 1], 0.9 + 0.2 * u[:, 2]], -1)
    target = torch.stack([1.0 * u[:, 3] - 0.5, 0.4 + 0.8 * u[:, 4]], -1)
    spin = 60.0 * (torch.rand(n, 3, generator=generator) - 0.5)
    vel = B.aim(pos, target, 0.45 + 0.15 * u[:, 5], spin=spin)
    return B.make_state(pos, vel, spin)


def test_vacuum_flight_is_an_exact_parabola() -> None:
    # start beside the table so that nothing is hit
    p0 = torch.tensor([2.0, -1.0, 3.0])
    v0 = torch.tensor([0.5, 3.0, 4.0])
    traj = B.simulate(B.make_state(p0, v0), 0.8, 0.01, VACUUM)
    t = traj.times[:, None]
    g = torch.tensor([0.0, 0.0, -geo.GRAVITY])
    torch.testing.assert_close(traj.pos, p0 + v0 * t + 0.5 * g * t**2, rtol=0, atol=1e-12)
    torch.testing.assert_close(traj.vel, v0 + g * t, rtol=0, atol=1e-12)
    assert not traj.bounce.any() and not traj.net.any()


def test_vertical_fall_with_quadratic_drag_matches_closed_form() -> None:
    # dv/dt = g - k v^2 from rest: v = v_t tanh(g t / v_t), drop = v_t^2 / g log cosh(g t / v_t)
    params = B.BallParams(magnus=0.0)
    z0 = 10.0
    traj = B.simulate(B.make_state([3.0, 0.0, z0], [0.0, 0.0, 0.0]), 1.2, 0.01, params)
    g, k = params.gravity, params.drag
    vt = math.sqrt(g / k)
    t = traj.times
    speed = vt * torch.tanh(g * t / vt)
    drop = vt**2 / g * torch.log(torch.cosh(g * t / vt))
    torch.testing.assert_close(traj.vel[:, 2], -speed, rtol=0, atol=1e-8)
    torch.testing.assert_close(traj.pos[:, 2], z0 - drop, rtol=0, atol=1e-8)


def test_spinning_flight_matches_scipy() -> None:
    p0 = np.array([2.0, -2.0, 3.0])
    v0 = np.array([-1.0, 6.0, 2.0])
    w = np.array([-120.0, 40.0, 80.0])

    def rhs(_t: float, y: np.ndarray) -> np.ndarray:
        v = y[3:]
        acc = -P.drag * np.linalg.norm(v) * v + P.magnus * np.cross(w, v)
        acc[2] -= P.gravity
        return np.concatenate([v, acc])

    t_eval = np.linspace(0.0, 0.6, 61)
    ref = solve_ivp(rhs, (0, 0.6), np.concatenate([p0, v0]), t_eval=t_eval, rtol=1e-12, atol=1e-12)
    traj = B.simulate(B.make_state(p0, v0, w), 0.6, 0.01)
    np.testing.assert_allclose(traj.pos.numpy(), ref.y[:3].T, atol=1e-8)
    np.testing.assert_allclose(traj.vel.numpy(), ref.y[3:].T, atol=1e-8)


def test_magnus_coefficient_is_the_spin_parameter_lift() -> None:
    # k_m = rho pi r^3 / (2 m) with rho = 1.2 kg/m^3
    assert P.magnus == pytest.approx(1.2 * math.pi * 0.02**3 / (2 * 0.0027))
    # and the SL drag constant corresponds to a drag coefficient near 0.5
    c_d = 2 * P.drag * P.mass / (1.2 * math.pi * P.radius**2)
    assert 0.45 < c_d < 0.55


def test_vertical_bounce_restitution_and_apex() -> None:
    h = 0.3
    traj = B.simulate(B.make_state([0.2, 0.5, SURFACE + h], [0, 0, 0]), 0.8, 0.01, VACUUM)
    land = B.landing(traj)
    assert bool(land.landed)
    t_impact = math.sqrt(2 * h / geo.GRAVITY)
    assert float(land.time) == pytest.approx(t_impact, abs=1e-12)
    torch.testing.assert_close(land.pos, torch.tensor([0.2, 0.5, geo.TABLE_HEIGHT]))
    # after the bounce the ball rises with e * sqrt(2 g h) and peaks at e^2 h
    k = int(torch.nonzero(traj.bounce)[0])
    v_up = P.table_restitution * math.sqrt(2 * geo.GRAVITY * h)
    dt_after = float(traj.times[k]) - t_impact
    assert float(traj.vel[k, 2]) == pytest.approx(v_up - geo.GRAVITY * dt_after, abs=1e-12)
    apex = float(traj.pos[k:, 2].max()) - SURFACE
    assert apex == pytest.approx(P.table_restitution**2 * h, rel=2e-3)  # sampled at 10 ms


def test_oblique_bounce_without_spin_is_the_sl_law() -> None:
    p0 = torch.tensor([-0.3, -1.0, SURFACE + 0.2])
    v0 = torch.tensor([1.0, 4.0, -1.0])
    traj = B.simulate(B.make_state(p0, v0), 0.3, 0.01, VACUUM)
    g = geo.GRAVITY
    t_b = (v0[2] + math.sqrt(v0[2] ** 2 + 2 * g * 0.2)) / g  # z(t) = SURFACE
    land = B.landing(traj)
    assert float(land.time) == pytest.approx(float(t_b), abs=1e-12)
    v_in = v0 + torch.tensor([0.0, 0.0, -g * float(t_b)])
    v_out = v_in * torch.tensor([0.72, 0.68, -0.88])
    k = int(torch.nonzero(traj.bounce)[0])
    expect = v_out + torch.tensor([0.0, 0.0, -g * (float(traj.times[k]) - float(t_b))])
    torch.testing.assert_close(traj.vel[k], expect, rtol=0, atol=1e-12)
    # friction produces topspin: w = r_c x dv / (kappa r^2)
    dv = v_out - v_in
    w = torch.tensor([dv[1], -dv[0], 0.0]) / (P.inertia_factor * P.radius)
    torch.testing.assert_close(traj.spin[k], w, rtol=0, atol=1e-9)


def test_bounce_conserves_angular_momentum_about_the_contact_point() -> None:
    # the friction impulse acts at the contact point, so I w + m (r e_z) x v is unchanged there
    v0 = torch.tensor([[2.0, 5.0, -2.0], [-1.0, -3.0, -1.5]])
    w0 = torch.tensor([[-100.0, 60.0, 30.0], [80.0, -50.0, 0.0]])
    state = B.make_state(torch.tensor([[0.0, 0.4, SURFACE + 1e-3]] * 2), v0, w0)
    new, ev = B.step_events(state, 0.002, VACUUM)
    assert bool(ev.bounce.all())
    # undo the short flights before and after the contact with the vacuum flow
    tau = ev.bounce_time[:, None]
    g = torch.tensor([0.0, 0.0, -geo.GRAVITY])
    v_in = v0 + g * tau
    v_out = new.vel - g * (0.002 - tau)

    def l_contact(v: torch.Tensor, w: torch.Tensor) -> torch.Tensor:
        r_ez = torch.tensor([0.0, 0.0, P.radius]).expand_as(v)
        return P.inertia_factor * P.radius**2 * w + torch.linalg.cross(r_ez, v)

    torch.testing.assert_close(l_contact(v_out, new.spin), l_contact(v_in, w0), atol=1e-12, rtol=0)
    torch.testing.assert_close(v_out[:, 2], -0.88 * v_in[:, 2], atol=1e-12, rtol=0)
    # the slip of the contact point shrinks by 1 - (1 - k)(1 + 1 / kappa), no reversal
    slip_in = v_in[:, :2] + P.radius * torch.stack([-w0[:, 1], w0[:, 0]], -1)
    slip_out = v_out[:, :2] + P.radius * torch.stack([-new.spin[:, 1], new.spin[:, 0]], -1)
    factor = 1 - (1 - torch.tensor([0.72, 0.68])) * (1 + 1 / P.inertia_factor)
    torch.testing.assert_close(slip_out, factor * slip_in, atol=1e-10, rtol=0)


def test_contacts_do_not_depend_on_the_step(generator: torch.Generator) -> None:
    state = _served(6, generator)
    fine = B.landing(B.simulate(state, 0.8, 0.001))
    coarse = B.landing(B.simulate(state, 0.8, 0.01))
    assert bool(fine.landed.all()) and bool(coarse.landed.all())
    torch.testing.assert_close(coarse.pos, fine.pos, atol=1e-6, rtol=0)
    torch.testing.assert_close(coarse.time, fine.time, atol=1e-7, rtol=0)
    # states after the bounce agree too
    f = B.simulate(state, 0.8, 0.001)
    c = B.simulate(state, 0.8, 0.01)
    torch.testing.assert_close(c.pos[..., -1, :], f.pos[..., -1, :], atol=1e-5, rtol=0)


def test_batch_equals_loop(generator: torch.Generator) -> None:
    state = _served(5, generator)
    batch = B.simulate(state, 0.7, 0.005)
    for i in range(5):
        single = B.simulate(B.BallState(state.pos[i], state.vel[i], state.spin[i]), 0.7, 0.005)
        # elementwise tensor code on other shapes, no BLAS: equal but for a vectorised kernel's
        # tail rounding transcendental functions differently (measured: bit for bit)
        torch.testing.assert_close(single.pos, batch.pos[i], atol=1e-13, rtol=0)
        torch.testing.assert_close(single.bounce_pos, batch.bounce_pos[i], atol=1e-13, rtol=0)
        assert torch.equal(single.bounce, batch.bounce[i])
    # leading batch dims of any rank
    grid = B.BallState(*(x.reshape(5, 1, 3).expand(5, 2, 3) for x in state))
    t, at, valid = B.predict_plane_crossing(grid, 1.6)
    t1, at1, valid1 = B.predict_plane_crossing(state, 1.6)
    torch.testing.assert_close(t[:, 1], t1)
    torch.testing.assert_close(at.pos[:, 0], at1.pos)
    assert torch.equal(valid[:, 0], valid1)


def test_propagate_gives_each_ball_its_own_time(generator: torch.Generator) -> None:
    state = _served(3, generator)
    traj = B.simulate(state, 0.9, 0.005)
    steps = torch.tensor([40, 110, 180])
    out = B.propagate(state, traj.times[steps])
    torch.testing.assert_close(out.pos, traj.pos[torch.arange(3), steps], atol=1e-12, rtol=0)
    torch.testing.assert_close(out.spin, traj.spin[torch.arange(3), steps], atol=1e-12, rtol=0)
    # an off-grid time: half a step further equals flying that half step
    half = B.propagate(state, traj.times[steps] + 0.0025)
    torch.testing.assert_close(half.pos, B.propagate(out, 0.0025).pos, atol=1e-12, rtol=0)
    with pytest.raises(ValueError, match="duration"):
        B.propagate(state, -0.1)


def test_aim_hits_its_target_within_a_millimetre(generator: torch.Generator) -> None:
    n = 8
    u = torch.rand(n, 5, generator=generator)
    pos = torch.stack([0.8 * u[:, 0] - 0.4, -1.6 - 0.5 * u[:, 1], 0.85 + 0.3 * u[:, 2]], -1)
    target = torch.stack([1.2 * u[:, 3] - 0.6, 0.3 + 0.9 * u[:, 4]], -1)
    spin = 80.0 * (torch.rand(n, 3, generator=generator) - 0.5)
    flight_time = torch.linspace(0.35, 0.7, n)
    vel = B.aim(pos, target, flight_time, spin=spin)
    traj = B.simulate(B.make_state(pos, vel, spin), 0.9, 0.005)
    land = B.landing(traj)
    assert bool(land.landed.all())
    err = (land.pos[:, :2] - target).norm(dim=-1)
    assert float(err.max()) < 1e-3
    torch.testing.assert_close(land.time, flight_time, atol=1e-6, rtol=0)
    # a free point in space (3-d target) is reached at the given time
    point = torch.tensor([0.5, 1.0, 1.3])
    v = B.aim(torch.tensor([0.0, -1.5, 1.0]), point, 0.5)
    end = B.simulate(B.make_state([0.0, -1.5, 1.0], v), 0.5, 0.005).pos[-1]
    assert float((end - point).norm()) < 1e-6


def test_racket_contact_law_and_its_inverse_round_trip(generator: torch.Generator) -> None:
    n = 50
    v_in = torch.randn(n, 3, generator=generator) * 3 + torch.tensor([0.0, 5.0, -1.0])
    v_out = torch.randn(n, 3, generator=generator) * 2 + torch.tensor([0.0, -6.0, 1.5])
    spin = torch.randn(n, 3, generator=generator) * 50
    tangential = torch.randn(n, 3, generator=generator)
    normal, v_r = B.racket_velocity_for_return(v_in, v_out, tangential=tangential)
    torch.testing.assert_close(normal.norm(dim=-1), torch.ones(n))
    got, spin_out = B.racket_contact(v_in, spin, v_r, normal, B.BallParams(racket_spin="kept"))
    torch.testing.assert_close(got, v_out, atol=1e-12, rtol=0)
    torch.testing.assert_close(spin_out, spin)
    # the law in the racket frame: normal relative velocity reversed times e, tangential kept
    rel_in, rel_out = v_in - v_r, got - v_r
    n_in, n_out = (rel_in * normal).sum(-1), (rel_out * normal).sum(-1)
    torch.testing.assert_close(n_out, -P.racket_restitution * n_in)
    torch.testing.assert_close(
        rel_out - n_out[:, None] * normal, rel_in - n_in[:, None] * normal, atol=1e-12, rtol=0
    )
    # the ball approached the racket face, and the sign of the normal does not matter
    assert bool((n_in < 0).all())
    flipped, _ = B.racket_contact(v_in, spin, v_r, -3.0 * normal)
    torch.testing.assert_close(flipped, got)
    # with the default (rolling) law the spin does not depend on the normal's sign either
    torch.testing.assert_close(
        B.racket_contact(v_in, spin, v_r, -normal)[1], B.racket_contact(v_in, spin, v_r, normal)[1]
    )
    # the tangential velocity was kept in the racket plane
    torch.testing.assert_close(
        v_r - (v_r * normal).sum(-1, keepdim=True) * normal,
        tangential - (tangential * normal).sum(-1, keepdim=True) * normal,
    )


def test_rolling_racket_spin_law_and_its_inverse(generator: torch.Generator) -> None:
    n = 40
    v_in = torch.randn(n, 3, generator=generator) * 2 + torch.tensor([0.0, 5.0, -1.0])
    v_out = torch.randn(n, 3, generator=generator) + torch.tensor([0.0, -6.0, 1.5])
    spin_in = torch.randn(n, 3, generator=generator) * 80
    wanted = torch.randn(n, 3, generator=generator) * 60
    normal, v_r = B.racket_velocity_for_return(v_in, v_out, spin_out=wanted)
    vel, spin = B.racket_contact(v_in, spin_in, v_r, normal)
    torch.testing.assert_close(vel, v_out, atol=1e-12, rtol=0)
    # in-plane spin as wanted; the spin about the normal is the incoming one

    def along(w: torch.Tensor) -> torch.Tensor:
        return (w * normal).sum(-1, keepdim=True) * normal

    torch.testing.assert_close(spin - along(spin), wanted - along(wanted), atol=1e-9, rtol=0)
    torch.testing.assert_close(along(spin), along(spin_in), atol=1e-9, rtol=0)
    # the ball leaves rolling: its contact point (at -r n) has no in-plane velocity on the racket
    cp = vel + torch.linalg.cross(spin, -P.radius * normal) - v_r
    torch.testing.assert_close(cp - along(cp), torch.zeros(n, 3), atol=1e-9, rtol=0)
    # an upward brush on a ball sent towards -y gives topspin (w_x > 0 for motion along -y)
    n0 = torch.tensor([0.0, -1.0, 0.0])
    vel, spin = B.racket_contact([0.0, 4.0, 0.0], [0.0, 0.0, 0.0], [0.0, -2.0, 3.0], n0)
    assert float(vel[1]) < 0 and float(spin[0]) > 0
    with pytest.raises(ValueError, match="at most one"):
        B.racket_velocity_for_return(v_in, v_out, tangential=wanted, spin_out=wanted)


def test_predict_plane_crossing_is_consistent_with_simulate(generator: torch.Generator) -> None:
    state = _served(4, generator)
    t, at, valid = B.predict_plane_crossing(state, 1.5)
    assert bool(valid.all())
    torch.testing.assert_close(at.pos[:, 1], torch.full((4,), 1.5), atol=1e-10, rtol=0)
    for i in range(4):
        single = B.BallState(state.pos[i], state.vel[i], state.spin[i])
        end = B.simulate(single, float(t[i]), 0.002)
        torch.testing.assert_close(end.pos[-1], at.pos[i], atol=1e-6, rtol=0)
        torch.testing.assert_close(end.vel[-1], at.vel[i], atol=1e-5, rtol=0)
    # vacuum: the closed-form crossing time of a straight line in y
    v = B.make_state([0.0, 0.5, 2.0], [0.0, -3.0, 1.0])
    t, at, valid = B.predict_plane_crossing(v, -1.0, VACUUM)
    assert bool(valid) and float(t) == pytest.approx(0.5, abs=1e-12)
    # a ball that falls to the floor first never crosses
    t, _, valid = B.predict_plane_crossing(B.make_state([3.0, 0.0, 1.0], [0, -1.0, 0]), -2.0)
    assert not bool(valid) and float(t) == 2.0


def test_net_contact_and_legality() -> None:
    pos = torch.tensor([0.0, -1.5, 0.95])
    # low and fast at the net; long; short onto the own half; a good return
    shots = {
        "net": B.aim(pos, torch.tensor([0.0, 0.0, SURFACE + 0.05]), 0.25),
        "long": B.aim(pos, torch.tensor([0.0, 2.0]), 0.4),
        "own_half": B.aim(pos, torch.tensor([0.2, -0.4]), 0.3),
        "good": B.aim(pos, torch.tensor([0.2, 0.8]), 0.45),
    }
    vel = torch.stack(list(shots.values()))
    traj = B.simulate(B.make_state(pos.expand(4, 3), vel), 1.0, 0.005)
    legal = B.is_legal_return(traj)
    land = B.landing(traj)
    assert legal.tolist() == [False, False, False, True]
    assert land.net_before.tolist() == [True, False, False, False]
    assert land.landed.tolist()[1:] == [False, True, True]
    # the net stops the ball on the robot's side, pushed back and slowed
    k = int(torch.nonzero(traj.net[0])[0])
    assert float(traj.pos[0, k, 1]) < 0 and float(traj.vel[0, k, 1]) < 0
    assert float(traj.vel[0, k].norm()) < 0.5 * float(vel[0].norm())
    assert bool((traj.pos[0, :, 1] < 0).all())
    # the opponent's returns are judged on the robot's half
    assert not bool(B.is_legal_return(traj, side=geo.ROBOT_SIDE)[3])
    assert bool(B.is_legal_return(traj, side=geo.ROBOT_SIDE)[2])


def test_aim_through_bounce_reaches_the_hitting_plane_target() -> None:
    pos = torch.tensor([[0.3, 1.8, 1.0], [-0.4, 1.7, 0.95], [0.0, 1.9, 1.05]])
    plane_x = torch.tensor([-1.0, 0.9, 0.1])
    bounce_y = torch.tensor([-0.8, -0.9, -1.0])
    v0, bounce_x, _, converged = B.aim_through_bounce(pos, plane_x, bounce_y, 0.5)
    assert bool(converged.all())
    state = B.make_state(pos, v0)
    t, at, valid = B.predict_plane_crossing(state, geo.HITTING_PLANE_Y)
    assert bool(valid.all())
    torch.testing.assert_close(at.pos[:, 0], plane_x, atol=1e-5, rtol=0)
    traj = B.simulate(state, float(t.max()), 0.005)
    land = B.landing(traj)
    torch.testing.assert_close(
        land.pos[:, :2], torch.stack([bounce_x, bounce_y], -1), atol=1e-3, rtol=0
    )
    assert bool(B.is_legal_return(traj, side=geo.ROBOT_SIDE).all())
    # a flat ball from low down meets the net: reported, not raised
    low = B.aim_through_bounce(torch.tensor([0.0, 1.6, 0.85]), 0.0, -0.4, 0.25)
    assert not bool(low.converged)


def test_bad_input_raises() -> None:
    state = B.make_state([0.0, 0.0, 1.0], [0.0, 1.0, 0.0])
    with pytest.raises(ValueError, match="dt"):
        B.step(state, 0.0)
    with pytest.raises(ValueError, match="dt"):
        B.simulate(state, 1.0, 0.5)
    with pytest.raises(ValueError, match="duration"):
        B.simulate(state, -1.0, 0.01)
    with pytest.raises(ValueError, match="pos"):
        B.make_state([0.0, 1.0], [0.0, 1.0, 0.0])
    with pytest.raises(ValueError, match="vel"):
        B.make_state([0.0, 0.0, 1.0], [float("nan"), 1.0, 0.0])
    with pytest.raises(TypeError, match="state"):
        B.step((state.pos, state.vel, state.spin), 0.01)
    with pytest.raises(ValueError, match="table_restitution"):
        B.BallParams(table_restitution=1.5)
    with pytest.raises(ValueError, match="side"):
        B.is_legal_return(B.simulate(state, 0.1, 0.01), side=0)
    with pytest.raises(ValueError, match="racket_normal"):
        B.racket_contact([0, 1.0, 0], [0, 0, 0], [0, 0, 0], [0, 0, 0])
    with pytest.raises(ValueError, match="flight_time"):
        B.aim([0.0, -1.5, 1.0], [0.0, 0.5], 0.0)
    with pytest.raises(ValueError, match="desired_vel_out"):
        B.racket_velocity_for_return([0, 1.0, 0], [0, 1.0, 0])


def test_unreachable_aims_raise_or_are_reported_never_nan() -> None:
    # with a drag 700 times too strong no launch velocity reaches the far court in 0.5 s and
    # Newton diverges to NaN, which the old NaN-blind check let through; aim raises, and
    # aim_through_bounce reports the elements and keeps every velocity finite
    heavy = B.BallParams(drag=100.0)
    with pytest.raises(ValueError, match="did not converge"):
        B.aim([0.0, -1.5, 1.0], [0.0, 1.0], 0.5, heavy)
    res = B.aim_through_bounce(torch.tensor([0.0, 1.65, 1.0]), 0.3, -0.9, 0.47, heavy, max_iter=2)
    assert not bool(res.converged)
    assert bool(torch.isfinite(res.vel).all())


@pytest.mark.parametrize(
    "vel,spin,match",
    [
        ([0.0, 1e8, 0.0], [0.0, 0.0, 0.0], r"vel: \|vel\| must be at most MAX_SPEED = 50 m/s"),
        ([0.0, 40.0, 40.0], [0.0, 0.0, 0.0], "vel.*got 56.57 m/s"),
        ([0.0, 5.0, 0.0], [1e6, 0.0, 0.0], r"spin: \|spin\| must be at most MAX_SPIN = 2000 rad/s"),
    ],
)
def test_unphysical_ball_states_raise_instead_of_nan(vel, spin, match) -> None:
    pos = [0.0, -1.5, 1.0]
    with pytest.raises(ValueError, match=match):
        B.make_state(pos, vel, spin)
    # a BallState built directly is checked by every integrator
    state = B.BallState(*(torch.tensor(x, dtype=torch.float64) for x in (pos, vel, spin)))
    for run in (
        lambda: B.simulate(state, 0.5, 0.01),
        lambda: B.step(state, 0.01),
        lambda: B.propagate(state, 0.1),
        lambda: B.predict_plane_crossing(state, 0.0),
    ):
        with pytest.raises(ValueError, match=match.split(":")[0]):
            run()


def test_ranges_admit_the_fastest_real_balls() -> None:
    # a 50 m/s smash with 2000 rad/s of spin is inside the documented ranges and stays finite
    state = B.make_state([0.0, -1.5, 1.0], [0.0, 50.0, 0.0], [-2000.0, 0.0, 0.0])
    traj = B.simulate(state, 0.3, 0.005)
    assert bool(torch.isfinite(traj.pos).all()) and bool(torch.isfinite(traj.spin).all())
    assert B.MAX_SPEED == 50.0 and B.MAX_SPIN == 2000.0


def test_integration_overflow_raises() -> None:
    # constants far outside the model's range overflow: a clear error instead of NaN data
    state = B.make_state([0.0, -1.5, 1.0], [0.0, 5.0, 1.0])
    absurd = B.BallParams(drag=1e300)
    for run in (
        lambda: B.simulate(state, 0.2, 0.01, absurd),
        lambda: B.step(state, 0.01, absurd),
        lambda: B.propagate(state, 0.05, absurd),
        lambda: B.predict_plane_crossing(state, 0.0, absurd),
    ):
        with pytest.raises(ValueError, match="non-finite values"):
            run()


def _batch_of_one(state: B.BallState) -> B.BallState:
    return B.BallState(*(x.unsqueeze(0) for x in state))


def test_one_ball_in_floats_matches_the_tensor_code(generator: torch.Generator) -> None:
    # An unbatched state takes ScalarBall's float path, a batch of one the tensor path: the same
    # flights, bounces and net contacts to rounding. A third of the balls are lowered into the
    # net, so the sample has both kinds of contact.
    state = _served(9, generator)
    vel = state.vel.clone()
    vel[::3, 2] -= 1.5
    state = B.make_state(state.pos, vel, state.spin)
    nets = bounces = 0
    for i in range(9):
        one = B.BallState(*(x[i] for x in state))
        single, batch = B.simulate(one, 1.0, 0.01), B.simulate(_batch_of_one(one), 1.0, 0.01)
        # Python floats (libm) against tensors (vectorised math): each of the 100 steps rounds
        # a few eps of a state of size <= ~10 (m, m/s) differently, 100 * 4 eps * 10 ~ 1e-12
        # (measured: up to 1.4e-13)
        torch.testing.assert_close(single.times, batch.times, atol=0, rtol=0)
        for name in ("pos", "vel", "spin", "bounce_pos", "bounce_time"):
            torch.testing.assert_close(
                getattr(single, name), getattr(batch, name)[0], atol=1e-12, rtol=0
            )
        assert torch.equal(single.bounce, batch.bounce[0])
        assert torch.equal(single.net, batch.net[0])
        nets += int(single.net.any())
        bounces += int(single.bounce.sum())
        # the other entry points: a step over the first contact, a duration through it and the
        # plane crossing
        k = max(int(torch.argmax((single.bounce | single.net).to(torch.int8))) - 2, 0)
        near = B.BallState(single.pos[k], single.vel[k], single.spin[k])
        s1, e1 = B.step_events(near, 0.05)
        sb, eb = B.step_events(_batch_of_one(near), 0.05)
        assert bool(e1.bounce or e1.net) or k == 0
        for a, b in zip((*s1, *e1), (*sb, *eb), strict=True):
            torch.testing.assert_close(a, b[0], atol=1e-12, rtol=0)
        for a, b in zip(B.propagate(one, 0.73), B.propagate(_batch_of_one(one), 0.73), strict=True):
            torch.testing.assert_close(a, b[0], atol=1e-12, rtol=0)
        t1, at1, ok1 = B.predict_plane_crossing(one, 0.5)
        tb, atb, okb = B.predict_plane_crossing(_batch_of_one(one), 0.5)
        torch.testing.assert_close(t1, tb[0], atol=1e-12, rtol=0)
        for a, b in zip(at1, atb, strict=True):
            torch.testing.assert_close(a, b[0], atol=1e-12, rtol=0)
        assert bool(ok1) == bool(okb[0])
    assert nets >= 2 and bounces >= 6, (nets, bounces)
    # aiming one ball: the same Newton iteration (same steps, same stopping rule)
    v1 = B.aim(state.pos[0], [0.2, 0.7], 0.5, spin=state.spin[0])
    vb = B.aim(state.pos[:1], torch.tensor([[0.2, 0.7]]), 0.5, spin=state.spin[:1])
    torch.testing.assert_close(v1, vb[0], atol=1e-12, rtol=0)


def test_absurd_durations_are_refused_before_any_work() -> None:
    # simulate(state, 1e5, 0.05) used to run 2 million steps; every integrator has a cap
    state = B.make_state([0.0, -1.5, 1.0], [0.0, 5.0, 1.0])
    with pytest.raises(ValueError, match=r"duration must be .* \(0, MAX_DURATION = 10\], got 1"):
        B.simulate(state, 1e5, 0.05)
    with pytest.raises(ValueError, match=r"duration / dt = 500000 steps exceeds MAX_STEPS"):
        B.simulate(state, 5.0, 1e-5)
    with pytest.raises(ValueError, match="duration must be at most MAX_DURATION = 10 s"):
        B.propagate(state, 100.0)
    with pytest.raises(ValueError, match="MAX_STEPS"):
        B.propagate(state, 5.0, dt=1e-5)
    with pytest.raises(ValueError, match=r"max_time must be .* MAX_DURATION"):
        B.predict_plane_crossing(state, 0.0, max_time=1e3)
    with pytest.raises(ValueError, match="flight_time must be positive and at most MAX_DURATION"):
        B.aim([0.0, -1.5, 1.0], [0.0, 0.5], 1e3)
    with pytest.raises(ValueError, match="flight_time"):
        B.aim_through_bounce([0.0, 1.6, 1.0], 0.0, -1.0, 50.0)
    # the caps themselves are allowed
    assert B.simulate(state, B.MAX_DURATION, 0.05).times.shape == (201,)


def test_ball_module_re_exports_each_concept_module() -> None:
    """``ball`` is the public face of the ``ball_*`` modules: it re-exports exactly their public
    names, each the very object of its home module, and no ``ball_*`` module imports ``ball``."""
    import importlib
    from pathlib import Path

    homes = sorted(Path(B.__file__).parent.glob("ball_*.py"))
    assert len(homes) == 8
    names: dict[str, object] = {}
    for path in homes:
        module = importlib.import_module(f"hgpdm_torch.robots.table_tennis.{path.stem}")
        assert module.__doc__ and module.__all__
        assert "table_tennis.ball import" not in path.read_text()
        for name in module.__all__:
            assert name not in names
            names[name] = getattr(module, name)
    assert set(B.__all__) | {"Floats"} == set(names)
    assert all(getattr(B, name) is obj for name, obj in names.items())
