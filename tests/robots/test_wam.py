"""WAM kinematics against an independent DH product, finite differences and IK round trips."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from hgpdm_torch.robots.wam import DOF, WAM

# Published standard DH parameters of the 7-DOF Barrett WAM.
D = [0.0, 0.0, 0.55, 0.0, 0.3, 0.0, 0.06]
A = [0.0, 0.0, 0.045, -0.045, 0.0, 0.0, 0.0]
ALPHA = [-math.pi / 2, math.pi / 2, -math.pi / 2, math.pi / 2, -math.pi / 2, math.pi / 2, 0.0]


def dh(theta: float, d: float, a: float, alpha: float) -> np.ndarray:
    ct, st, ca, sa = np.cos(theta), np.sin(theta), np.cos(alpha), np.sin(alpha)
    return np.array(
        [
            [ct, -st * ca, st * sa, a * ct],
            [st, ct * ca, -ct * sa, a * st],
            [0.0, sa, ca, d],
            [0.0, 0.0, 0.0, 1.0],
        ]
    )


def racket_dh(q: np.ndarray, base_pos: tuple[float, float, float]) -> np.ndarray:
    """World pose of the racket: hanging base (rotation pi about x), DH chain, racket offset."""
    base = np.eye(4)
    base[:3, :3] = np.diag([1.0, -1.0, -1.0])
    base[:3, 3] = base_pos
    t = base
    for i in range(DOF):
        t = t @ dh(q[i], D[i], A[i], ALPHA[i])
    racket = np.eye(4)
    racket[2, 3] = 0.24  # blade centre 0.3 m beyond the wrist centre
    racket[:3, :3] = np.array([[0.0, 0.0, 1.0], [0.0, 1.0, 0.0], [-1.0, 0.0, 0.0]])  # Ry(pi/2)
    return t @ racket


@pytest.fixture(scope="module")
def wam() -> WAM:
    return WAM()


def random_q(wam: WAM, n: int, generator: torch.Generator, margin: float = 0.2) -> torch.Tensor:
    u = torch.rand(n, DOF, generator=generator)
    lo, hi = wam.lower + margin, wam.upper - margin
    return lo + u * (hi - lo)


def test_fk_matches_dh_product(wam: WAM, generator: torch.Generator) -> None:
    q = random_q(wam, 20, generator, margin=0.0)
    pose = wam.fk(q)
    # pytorch-kinematics parses URDF origins in float32: agreement to ~1e-8 m is the best possible.
    for i in range(q.shape[0]):
        ref = racket_dh(q[i].numpy(), wam.base_position.tolist())
        np.testing.assert_allclose(pose.position[i].numpy(), ref[:3, 3], atol=1e-7)
        np.testing.assert_allclose(pose.rotation[i].numpy(), ref[:3, :3], atol=1e-7)
        np.testing.assert_allclose(pose.normal[i].numpy(), ref[:3, 2], atol=1e-7)


def test_frame_positions_end_at_racket(wam: WAM, generator: torch.Generator) -> None:
    q = random_q(wam, 3, generator)
    pts = wam.frame_positions(q)
    assert pts.shape == (3, 10, 3)
    torch.testing.assert_close(pts[:, -1], wam.fk(q).position)
    torch.testing.assert_close(pts[:, 0], wam.base_position.expand(3, 3))
    # Elbow (frame after the upper arm) is 0.55 m (plus the 0.045 m offset) from the shoulder.
    np.testing.assert_allclose(
        (pts[:, 4] - pts[:, 0]).norm(dim=-1).numpy(), math.hypot(0.55, 0.045), atol=1e-7
    )


def test_jacobian_matches_finite_differences(wam: WAM, generator: torch.Generator) -> None:
    q = random_q(wam, 4, generator)
    jac = wam.jacobian(q)
    eps = 1e-6
    for j in range(DOF):
        dq = torch.zeros(DOF)
        dq[j] = eps
        plus, minus = wam.fk(q + dq), wam.fk(q - dq)
        lin = (plus.position - minus.position) / (2 * eps)
        # Angular velocity from the skew part of dR R^T.
        dr = (plus.rotation - minus.rotation) / (2 * eps) @ wam.fk(q).rotation.transpose(-1, -2)
        ang = torch.stack([dr[:, 2, 1], dr[:, 0, 2], dr[:, 1, 0]], dim=-1)
        torch.testing.assert_close(jac[:, :3, j], lin, atol=1e-8, rtol=0)
        torch.testing.assert_close(jac[:, 3:, j], ang, atol=1e-8, rtol=0)


def test_ik_reaches_reachable_targets(wam: WAM, generator: torch.Generator) -> None:
    q_true = random_q(wam, 16, generator, margin=0.4)
    target = wam.fk(q_true)
    seed = q_true + 0.3 * torch.randn(q_true.shape, generator=generator)
    seed = torch.minimum(torch.maximum(seed, wam.lower), wam.upper)
    res = wam.ik(target.position, target.normal, seed)
    reached = wam.fk(res.q)
    err = (reached.position - target.position).norm(dim=-1)
    assert bool(res.success.float().mean() >= 0.9), res.position_error
    assert float(err[res.success].max()) < 1e-3
    cos = (reached.normal * target.normal).sum(-1)[res.success]
    assert float(cos.min()) > math.cos(2e-3)
    assert bool(((res.q >= wam.lower) & (res.q <= wam.upper)).all())
    torch.testing.assert_close(res.position_error, err)


def test_ik_reports_unreachable_target(wam: WAM) -> None:
    far = wam.base_position + torch.tensor([0.0, 0.0, -3.0])
    res = wam.ik(far, torch.tensor([0.0, 1.0, 0.0]), torch.zeros(DOF), max_iter=50)
    assert not bool(res.success)
    assert float(res.position_error) > 1.5


def test_joint_velocity_produces_racket_velocity(wam: WAM, generator: torch.Generator) -> None:
    q = random_q(wam, 5, generator, margin=0.4)
    v = torch.randn(5, 3, generator=generator)
    qd = wam.joint_velocity(q, v, damping=1e-6)
    torch.testing.assert_close(wam.racket_velocity(q, qd), v, atol=1e-6, rtol=0)
    # Minimum norm: no component in the null space of the linear Jacobian.
    jv = wam.jacobian(q)[:, :3]
    null = torch.eye(DOF) - torch.linalg.pinv(jv) @ jv
    assert float((null @ qd.unsqueeze(-1)).abs().max()) < 1e-6


def test_one_configuration_in_numpy_matches_pytorch_kinematics(
    wam: WAM, generator: torch.Generator
) -> None:
    # One IK problem (the stroke planner's) runs on the numpy chain, a batch of one on
    # pytorch-kinematics: the same iteration on the same arm, to rounding. At an unreachable
    # target the iteration never settles and amplifies rounding (after ~20 iterations the two
    # differ), so there only the first iterations are compared.
    q_true = random_q(wam, 6, generator, margin=0.4).double()
    target = wam.fk(q_true)
    seed = torch.minimum(torch.maximum(q_true + 0.3, wam.lower), wam.upper)
    far = wam.base_position + torch.tensor([0.0, 0.0, -3.0], dtype=torch.float64)
    cases = [(target.position[i], target.normal[i], seed[i], 150) for i in range(6)]
    cases.append((far, target.normal[0], seed[0], 5))
    v = torch.tensor([1.0, -2.0, 0.5], dtype=torch.float64)
    eps, eye3, eye6 = torch.finfo(torch.float64).eps, torch.eye(3), torch.eye(6)
    for pos, normal, q0, iters in cases:
        one = wam.ik(pos, normal, q0, max_iter=iters)
        batch = wam.ik(pos[None], normal, q0, max_iter=iters)
        # Rounding differs (numpy/OpenBLAS LU against torch/MKL Cholesky, other FK code). Each
        # step solves with J J^T + 0.02^2 I (J: the 5 task rows; condition number kappa ~1e4
        # here) and a Gauss-Newton iteration corrects the errors of earlier steps, so q agrees
        # to ~kappa eps |q|; 10 times that (measured: up to 0.05 kappa eps |q|).
        jac = wam.jacobian(one.q)
        n = wam.fk(one.q).normal
        j = torch.cat([jac[:3], (eye3 - n[:, None] * n[None]) @ jac[3:]])
        tol_q = 10 * float(torch.linalg.cond(j @ j.T + 0.02**2 * eye6)) * eps
        torch.testing.assert_close(
            one.q, batch.q[0], rtol=tol_q, atol=tol_q * float(one.q.abs().max())
        )
        # the errors move by |J| times q's difference, plus their own rounding: the position
        # error cancels |p| ~ 1 m to ~1e-4 m (a few eps |p|), and the normal error is acos of a
        # cosine within a few eps of 1, whose slope 1 / sin(angle) amplifies that (2.9e-10 at
        # 7.6e-7 rad: one ulp of the cosine)
        moved = float(torch.linalg.matrix_norm(jac, ord=2)) * tol_q * float(one.q.abs().max())
        torch.testing.assert_close(
            one.position_error, batch.position_error[0], rtol=0,
            atol=moved + 8 * eps * float(pos.norm()),
        )  # fmt: skip
        torch.testing.assert_close(
            one.normal_error, batch.normal_error[0], rtol=0,
            atol=moved + 8 * eps / math.sin(float(one.normal_error)),
        )  # fmt: skip
        assert bool(one.success) == bool(batch.success[0]) == (iters == 150)
        # damped least squares with J_v J_v^T + 1e-3^2 I (condition number up to ~2e3 here):
        # one or a batch of one configurations agree to ~kappa eps |qd|; 10 times that
        # (measured: up to 0.25 kappa eps |qd|)
        jv = jac[:3]
        tol_qd = 10 * float(torch.linalg.cond(jv @ jv.T + 1e-3**2 * eye3)) * eps
        qd = wam.joint_velocity(one.q, v)
        torch.testing.assert_close(
            qd, wam.joint_velocity(one.q[None], v)[0], rtol=tol_qd,
            atol=tol_qd * float(qd.abs().max()),
        )  # fmt: skip
    assert float(wam.ik(far, target.normal[0], seed[0], max_iter=150).position_error) > 1.5


def test_bad_input(wam: WAM) -> None:
    with pytest.raises(ValueError, match="q"):
        wam.fk(torch.zeros(6))
    with pytest.raises(ValueError, match="normal"):
        wam.ik(torch.zeros(3), torch.zeros(3), torch.zeros(DOF))
    with pytest.raises(ValueError, match="q"):
        wam.fk(torch.full((DOF,), float("nan")))
    with pytest.raises(TypeError, match="q"):
        wam.fk("abc")


def test_mismatched_batches_are_named(wam: WAM) -> None:
    """Issue 54: batch shapes that do not broadcast are a ValueError naming the arguments and
    their shapes, not a torch broadcast error."""
    q0 = torch.zeros(DOF)
    with pytest.raises(ValueError, match=r"position \[2, 3\], normal \[3, 3\].*do not broadcast"):
        wam.ik(torch.zeros(2, 3), torch.ones(3, 3), q0)
    with pytest.raises(ValueError, match=r"q0 \[4, 7\]"):
        wam.ik(torch.zeros(2, 3), torch.ones(2, 3), torch.zeros(4, DOF))
    with pytest.raises(ValueError, match=r"q_rest \[3, 7\]"):
        wam.ik(torch.zeros(2, 3), torch.ones(2, 3), q0, q_rest=torch.zeros(3, DOF))
    with pytest.raises(ValueError, match=r"q \[2, 7\], qd \[3, 7\]"):
        wam.racket_velocity(torch.zeros(2, DOF), torch.zeros(3, DOF))
    with pytest.raises(ValueError, match=r"q \[2, 7\], racket_velocity \[3, 3\]"):
        wam.joint_velocity(torch.zeros(2, DOF), torch.zeros(3, 3))


def test_ik_broadcasts_initial_guesses_over_one_target(
    wam: WAM, generator: torch.Generator
) -> None:
    # several initial guesses [n, 7] for one target [3]: the batch of q0 joins the broadcast,
    # and each row is the IK from that guess alone
    q_true = random_q(wam, 1, generator, margin=0.4)[0].double()
    target = wam.fk(q_true)
    seeds = torch.stack([q_true + 0.2, q_true - 0.2]).clamp(wam.lower, wam.upper)
    res = wam.ik(target.position, target.normal, seeds, max_iter=30)
    assert res.q.shape == (2, DOF) and res.position_error.shape == (2,)
    for i in range(2):
        one = wam.ik(target.position[None], target.normal[None], seeds[i], max_iter=30)
        torch.testing.assert_close(res.q[i], one.q[0])
