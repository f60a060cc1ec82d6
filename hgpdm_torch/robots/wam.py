"""Kinematics of the Barrett WAM table-tennis arm (thesis Sec. 3.5.1, 4.3.1).

The arm is described by ``assets/wam7.urdf`` (standard DH parameters of the WAM, a racket disc on
the flange) and evaluated with pytorch-kinematics. The arm hangs upside down from above the
robot's side of the table, as in the thesis's setup; :class:`WAM` applies that mounting so that
every pose it returns is in the world frame (origin on the floor below the table centre, y from the
robot towards the opponent, z up).

Shapes: ``q`` is ``[..., 7]`` joint angles (rad); positions and normals are ``[..., 3]`` (m).

One configuration (the robot's stroke planning solves one IK problem per stroke) goes through the
same chain in numpy (:class:`_Chain1`): pytorch-kinematics spends milliseconds per call on a batch
of one, numpy tens of microseconds; the transforms are taken from the pytorch-kinematics chain, so
the two agree to rounding (``tests/robots/test_wam.py``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from importlib import resources

import numpy as np
import pytorch_kinematics as pk
import torch

from ..linalg import psd_cholesky
from ..validation import as_tensor, check_shape

__all__ = [
    "DEFAULT_BASE_POSITION",
    "DOF",
    "IKResult",
    "JOINT_NAMES",
    "RACKET_LINK",
    "RACKET_RADIUS",
    "RacketPose",
    "WAM",
    "urdf_path",
]

DOF = 7
JOINT_NAMES = tuple(f"wam_joint{i}" for i in range(1, DOF + 1))
RACKET_LINK = "racket"
RACKET_RADIUS = 0.076
# Shoulder (DH frame 0) of the hanging arm: centred laterally, 0.23 m behind the virtual hitting
# plane and 0.29 m above the table surface. The opponent's returns cross the plane at 0.5-1.05 m
# height; from here the racket (1.2 m from the shoulder at full stretch) reaches them across
# x = +-1.0 m, the widest the arm's length allows (+-1.2 m would need the shoulder on the plane).
DEFAULT_BASE_POSITION = (0.0, -2.40, 1.05)
# Hanging: the base z axis (joint 1) points down; base x stays world x.
_HANGING_RPY = (math.pi, 0.0, 0.0)


def urdf_path() -> str:
    """Filesystem path of the packaged WAM URDF."""
    return str(resources.files("hgpdm_torch.robots") / "assets" / "wam7.urdf")


@dataclass(frozen=True)
class RacketPose:
    """Racket centre, blade normal and orientation in the world frame.

    Attributes:
        position: ``[..., 3]`` centre of the racket disc.
        normal: ``[..., 3]`` unit normal of the disc (the racket frame's z axis).
        rotation: ``[..., 3, 3]`` racket frame axes as columns.
    """

    position: torch.Tensor
    normal: torch.Tensor
    rotation: torch.Tensor


@dataclass(frozen=True)
class IKResult:
    """Output of :meth:`WAM.ik`.

    Attributes:
        q: ``[..., 7]`` joint angles found (within the joint limits).
        position_error: ``[...]`` distance of the racket centre from the target (m).
        normal_error: ``[...]`` angle between racket normal and target normal (rad).
        success: ``[...]`` both errors below the tolerances.
    """

    q: torch.Tensor
    position_error: torch.Tensor
    normal_error: torch.Tensor
    success: torch.Tensor


def _rpy_matrix(roll: float, pitch: float, yaw: float) -> torch.Tensor:
    cr, sr, cp, sp, cy, sy = (
        math.cos(roll),
        math.sin(roll),
        math.cos(pitch),
        math.sin(pitch),
        math.cos(yaw),
        math.sin(yaw),
    )
    rz = torch.tensor([[cy, -sy, 0.0], [sy, cy, 0.0], [0.0, 0.0, 1.0]])
    ry = torch.tensor([[cp, 0.0, sp], [0.0, 1.0, 0.0], [-sp, 0.0, cp]])
    rx = torch.tensor([[1.0, 0.0, 0.0], [0.0, cr, -sr], [0.0, sr, cr]])
    return (rz @ ry @ rx).to(torch.float64)


class WAM:
    """The hanging 7-DOF WAM with its racket: forward kinematics, Jacobian and batched IK.

    Args:
        base_position: world position of the shoulder (DH frame 0), metres.
        base_rpy: roll-pitch-yaw of the base frame in the world (default: hanging, z down).
        dtype: floating dtype of all computations.
        device: torch device.
    """

    def __init__(
        self,
        base_position: tuple[float, float, float] = DEFAULT_BASE_POSITION,
        base_rpy: tuple[float, float, float] = _HANGING_RPY,
        *,
        dtype: torch.dtype = torch.float64,
        device: torch.device | str | None = None,
    ) -> None:
        pos = as_tensor(base_position, "base_position", dtype=dtype, device=device, ndim=1)
        check_shape(pos, "base_position", (3,))
        rpy = as_tensor(base_rpy, "base_rpy", ndim=1)
        check_shape(rpy, "base_rpy", (3,))
        with open(urdf_path(), "rb") as f:
            self.chain = pk.build_serial_chain_from_urdf(f.read(), RACKET_LINK).to(
                dtype=dtype, device=device
            )
        if tuple(self.chain.get_joint_parameter_names()) != JOINT_NAMES:
            raise RuntimeError("wam7.urdf joints do not match JOINT_NAMES")
        self.dtype, self.device = dtype, pos.device
        self.base_position = pos
        self.base_rpy = tuple(float(v) for v in rpy)
        self.base_rotation = _rpy_matrix(*self.base_rpy).to(dtype=dtype, device=pos.device)
        lower, upper = self.chain.get_joint_limits()
        self.lower = torch.as_tensor(lower, dtype=dtype, device=pos.device)
        self.upper = torch.as_tensor(upper, dtype=dtype, device=pos.device)
        self.velocity_limit = torch.as_tensor(
            self.chain.get_joint_velocity_limits()[1], dtype=dtype, device=pos.device
        )
        self.effort_limit = torch.as_tensor(
            self.chain.get_joint_effort_limits()[1], dtype=dtype, device=pos.device
        )
        self._one: _Chain1 | None = None

    def _single(self, *tensors: torch.Tensor) -> _Chain1 | None:
        """The numpy chain when every argument is one float64 CPU vector (no autograd)."""
        if self.dtype != torch.float64 or not all(
            t.dim() == 1 and t.device.type == "cpu" and not t.requires_grad for t in tensors
        ):
            return None
        if self._one is None:
            self._one = _Chain1(self)
        return self._one

    # -- helpers -------------------------------------------------------------------------------
    def _q(self, q: object, name: str = "q") -> torch.Tensor:
        t = as_tensor(q, name, dtype=self.dtype, device=self.device, min_ndim=1)
        check_shape(t, name, (DOF,))
        return t

    @staticmethod
    def _batch(**tensors: torch.Tensor) -> torch.Size:
        """The broadcast of the arguments' batch shapes (every dim but the last).

        Raises:
            ValueError: they do not broadcast, naming each argument with its shape.
        """
        try:
            return torch.broadcast_shapes(*(t.shape[:-1] for t in tensors.values()))
        except RuntimeError:
            shapes = ", ".join(f"{name} {list(t.shape)}" for name, t in tensors.items())
            raise ValueError(
                f"the batch shapes (all dims but the last) of {shapes} do not broadcast; "
                "give each a matching batch, or none for one shared value"
            ) from None

    def _to_world(self, m: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Rotation and translation of base-frame homogeneous matrices ``[..., 4, 4]``."""
        rot = self.base_rotation @ m[..., :3, :3]
        pos = m[..., :3, 3] @ self.base_rotation.T + self.base_position
        return rot, pos

    # -- kinematics ----------------------------------------------------------------------------
    def fk(self, q: object) -> RacketPose:
        """Racket pose in the world frame. ``q``: ``[..., 7]``."""
        q = self._q(q)
        batch = q.shape[:-1]
        m = self.chain.forward_kinematics(q.reshape(-1, DOF)).get_matrix()
        rot, pos = self._to_world(m)
        rot = rot.reshape(*batch, 3, 3)
        return RacketPose(pos.reshape(*batch, 3), rot[..., :, 2], rot)

    def frame_positions(self, q: object) -> torch.Tensor:
        """World positions of the base, every link frame, the flange and the racket.

        Used for drawing the arm. ``q``: ``[..., 7]`` -> ``[..., 10, 3]``.
        """
        q = self._q(q)
        batch = q.shape[:-1]
        frames = self.chain.forward_kinematics(q.reshape(-1, DOF), end_only=False)
        names = ["wam_base", *[f"wam_link{i}" for i in range(1, DOF + 1)], "wam_flange"]
        names.append(RACKET_LINK)
        pts = torch.stack([self._to_world(frames[n].get_matrix())[1] for n in names], dim=-2)
        return pts.reshape(*batch, len(names), 3)

    def jacobian(self, q: object) -> torch.Tensor:
        """Geometric Jacobian of the racket centre in the world frame.

        Rows 0-2 map joint velocities to the racket centre's linear velocity, rows 3-5 to the
        racket's angular velocity. ``q``: ``[..., 7]`` -> ``[..., 6, 7]``.
        """
        q = self._q(q)
        batch = q.shape[:-1]
        jac = self.chain.jacobian(q.reshape(-1, DOF))
        r = self.base_rotation
        jac = torch.cat([r @ jac[:, :3], r @ jac[:, 3:]], dim=-2)
        return jac.reshape(*batch, 6, DOF)

    def racket_velocity(self, q: object, qd: object) -> torch.Tensor:
        """Linear velocity of the racket centre ``J_v(q) qd``. ``[..., 7]`` x2 -> ``[..., 3]``
        (batch shapes broadcast; ``ValueError`` if they do not)."""
        q, qd = self._q(q), self._q(qd, "qd")
        self._batch(q=q, qd=qd)
        return (self.jacobian(q)[..., :3, :] @ qd.unsqueeze(-1)).squeeze(-1)

    def ik(
        self,
        position: object,
        normal: object,
        q0: object,
        *,
        q_rest: object | None = None,
        damping: float = 0.02,
        rest_gain: float = 0.1,
        max_iter: int = 200,
        position_tol: float = 1e-4,
        normal_tol: float = 1e-3,
    ) -> IKResult:
        """Batched damped-least-squares IK for a racket centre and a blade normal.

        Solves for ``q`` with ``fk(q).position = position`` and ``fk(q).normal = normal``; the
        rotation about the normal is free (5 task constraints, 7 joints). Each iteration takes
        ``dq = J^T (J J^T + damping^2 I)^-1 e + (I - J^+ J) rest_gain (q_rest - q)`` (J^+ the
        Moore-Penrose inverse), with J the
        stacked linear Jacobian and the angular Jacobian projected orthogonally to the normal, and
        e the position error and the rotation vector ``n x n_target``; joints are clipped to
        their limits. The null-space term keeps the solution close to ``q_rest``.

        Args:
            position: ``[..., 3]`` target racket centre (world).
            normal: ``[..., 3]`` target blade normal (normalised here).
            q0: ``[..., 7]`` or ``[7]`` initial joint angles.
            q_rest: ``[..., 7]`` or ``[7]`` posture preferred in the null space (default q0).

        The batch shapes (``...``) of ``position``, ``normal``, ``q0`` and ``q_rest``
        broadcast, e.g. several initial guesses ``q0 [n, 7]`` for one target.
            damping: damping factor of the least squares (m).
            rest_gain: gain of the null-space pull towards ``q_rest``.
            max_iter: number of iterations at most.
            position_tol: success tolerance on the position error (m).
            normal_tol: success tolerance on the normal error (rad).

        Raises:
            ValueError: a wrong trailing size, batch shapes that do not broadcast, a zero
                normal, ``damping <= 0`` or ``max_iter < 1``.
        """
        p_t = as_tensor(position, "position", dtype=self.dtype, device=self.device, min_ndim=1)
        check_shape(p_t, "position", (3,))
        n_t = as_tensor(normal, "normal", dtype=self.dtype, device=self.device, min_ndim=1)
        check_shape(n_t, "normal", (3,))
        norm = n_t.norm(dim=-1, keepdim=True)
        if bool((norm < 1e-9).any()):
            raise ValueError("normal must have non-zero length")
        n_t = n_t / norm
        if not damping > 0 or not max_iter >= 1:
            raise ValueError("damping must be positive and max_iter at least 1")
        q0_t = self._q(q0, "q0")
        rest_t = q0_t if q_rest is None else self._q(q_rest, "q_rest")
        batch = self._batch(position=p_t, normal=n_t, q0=q0_t, q_rest=rest_t)
        one = self._single(p_t, n_t, q0_t, rest_t)
        if one is not None:
            res = one.ik(
                p_t.numpy(), n_t.numpy(), q0_t.numpy(), rest_t.numpy(), damping, rest_gain,
                max_iter, position_tol, normal_tol,
            )  # fmt: skip
            return IKResult(*(torch.as_tensor(x) for x in res))
        q = q0_t.expand(*batch, DOF).reshape(-1, DOF).clone()
        rest = rest_t.expand(*batch, DOF).reshape(-1, DOF)
        p_t = p_t.expand(*batch, 3).reshape(-1, 3)
        n_t = n_t.expand(*batch, 3).reshape(-1, 3)
        eye3 = torch.eye(3, dtype=self.dtype, device=self.device)
        eye6 = torch.eye(6, dtype=self.dtype, device=self.device)
        eye7 = torch.eye(DOF, dtype=self.dtype, device=self.device)
        for _ in range(max_iter):
            pose = self.fk(q)
            e_p = p_t - pose.position
            e_n = torch.linalg.cross(pose.normal, n_t)
            # Opposite normals give a vanishing cross product; any axis orthogonal to n turns it.
            flip = (pose.normal * n_t).sum(-1, keepdim=True) < 0
            e_n = torch.where(flip, e_n / e_n.norm(dim=-1, keepdim=True).clamp_min(1e-9), e_n)
            err_p = e_p.norm(dim=-1)
            err_n = torch.atan2(e_n.norm(dim=-1), (pose.normal * n_t).sum(-1))
            if bool(((err_p < position_tol) & (err_n < normal_tol)).all()):
                break
            # Bound the step so that the linearisation holds.
            e_p = e_p * (0.1 / err_p.clamp_min(0.1)).unsqueeze(-1)
            jac = self.jacobian(q)
            proj = eye3 - pose.normal.unsqueeze(-1) * pose.normal.unsqueeze(-2)
            j = torch.cat([jac[:, :3], proj @ jac[:, 3:]], dim=-2)
            e = torch.cat([e_p, e_n], dim=-1).unsqueeze(-1)
            chol = psd_cholesky(j @ j.transpose(-1, -2) + damping**2 * eye6, name="J J^T")
            pinv = j.transpose(-1, -2) @ torch.cholesky_solve(eye6.expand_as(chol), chol)
            # Exact projector (SVD pseudo-inverse): the posture pull must not disturb the task.
            null = eye7 - torch.linalg.pinv(j, rtol=1e-6) @ j
            dq = (pinv @ e).squeeze(-1) + (null @ (rest_gain * (rest - q)).unsqueeze(-1)).squeeze(
                -1
            )
            q = torch.minimum(torch.maximum(q + dq, self.lower), self.upper)
        pose = self.fk(q)
        err_p = (p_t - pose.position).norm(dim=-1)
        cos = (pose.normal * n_t).sum(-1).clamp(-1.0, 1.0)
        err_n = torch.acos(cos)
        ok = (err_p < position_tol) & (err_n < normal_tol)
        return IKResult(
            q.reshape(*batch, DOF),
            err_p.reshape(batch),
            err_n.reshape(batch),
            ok.reshape(batch),
        )

    def joint_velocity(
        self, q: object, racket_velocity: object, *, damping: float = 1e-3
    ) -> torch.Tensor:
        """Smallest joint velocity giving the racket centre a linear velocity.

        Damped least squares on the linear Jacobian: ``qd = J_v^T (J_v J_v^T + damping^2 I)^-1 v``
        (the racket may turn meanwhile; a ball contact is too short for that to matter).
        ``q``: ``[..., 7]``, ``racket_velocity``: ``[..., 3]`` -> ``[..., 7]`` (batch shapes
        broadcast; ``ValueError`` if they do not).
        """
        v = as_tensor(racket_velocity, "racket_velocity", dtype=self.dtype, device=self.device)
        check_shape(v, "racket_velocity", (3,))
        q = self._q(q)
        self._batch(q=q, racket_velocity=v)
        one = self._single(q, v)
        if one is not None:
            jv1 = one.jacobian(q.numpy())[:3]
            gram1 = jv1 @ jv1.T + damping**2 * np.eye(3)
            return torch.as_tensor(jv1.T @ np.linalg.solve(gram1, v.numpy()))
        jv = self.jacobian(q)[..., :3, :]
        eye3 = torch.eye(3, dtype=self.dtype, device=self.device)
        gram = jv @ jv.transpose(-1, -2) + damping**2 * eye3
        return (jv.transpose(-1, -2) @ torch.linalg.solve(gram, v.unsqueeze(-1))).squeeze(-1)


class _Chain1:
    """Racket pose, Jacobian and IK of one configuration ``[7]`` in numpy (float64).

    The fixed transform in front of each joint is read off the pytorch-kinematics chain (its
    frames at ``q = 0``), so that both evaluate the same arm to rounding.
    """

    def __init__(self, wam: WAM) -> None:
        names = ["wam_base", *[f"wam_link{i}" for i in range(1, DOF + 1)], "wam_flange"]
        names.append(RACKET_LINK)
        zero = torch.zeros(1, DOF, dtype=torch.float64, device=wam.device)
        frames = wam.chain.forward_kinematics(zero, end_only=False)
        mats = [frames[n].get_matrix()[0].cpu().double().numpy() for n in names]
        # offset i maps frame i-1 to frame i at q_i = 0 (joint i turns about its frame's z)
        offsets = [np.linalg.solve(mats[i - 1], mats[i]) for i in range(1, len(mats))]
        self.offsets = offsets[:DOF]
        self.tail = offsets[DOF] @ offsets[DOF + 1]  # link 7 -> flange -> racket
        self.base = np.eye(4)
        self.base[:3, :3] = wam.base_rotation.cpu().double().numpy()
        self.base[:3, 3] = wam.base_position.cpu().double().numpy()
        self.lower = wam.lower.cpu().double().numpy()
        self.upper = wam.upper.cpu().double().numpy()

    def _frames(self, q: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Joint axes ``[7, 3]``, joint origins ``[7, 3]`` and the racket frame ``[4, 4]``."""
        t = self.base
        axes, origins = np.empty((DOF, 3)), np.empty((DOF, 3))
        for j, (off, qj) in enumerate(zip(self.offsets, q.tolist(), strict=True)):
            t = t @ off
            axes[j], origins[j] = t[:3, 2], t[:3, 3]
            c, s = math.cos(qj), math.sin(qj)
            t = t.copy()
            t[:3, 0], t[:3, 1] = c * t[:3, 0] + s * t[:3, 1], c * t[:3, 1] - s * t[:3, 0]
        return axes, origins, t @ self.tail

    def fk(self, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Racket centre ``[3]`` and frame axes ``[3, 3]`` (columns; the normal is column 2)."""
        end = self._frames(q)[2]
        return end[:3, 3], end[:3, :3]

    def jacobian(self, q: np.ndarray) -> np.ndarray:
        """:meth:`WAM.jacobian` of one configuration: ``[6, 7]``."""
        return self._pose_jacobian(q)[2]

    def _pose_jacobian(self, q: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Racket centre ``[3]``, frame axes ``[3, 3]`` and Jacobian ``[6, 7]`` in one pass."""
        axes, origins, end = self._frames(q)
        arm = end[:3, 3] - origins
        lin = np.stack(
            [
                axes[:, 1] * arm[:, 2] - axes[:, 2] * arm[:, 1],
                axes[:, 2] * arm[:, 0] - axes[:, 0] * arm[:, 2],
                axes[:, 0] * arm[:, 1] - axes[:, 1] * arm[:, 0],
            ]
        )
        return end[:3, 3], end[:3, :3], np.concatenate([lin, axes.T])

    def ik(
        self,
        p_t: np.ndarray,
        n_t: np.ndarray,
        q0: np.ndarray,
        rest: np.ndarray,
        damping: float,
        rest_gain: float,
        max_iter: int,
        position_tol: float,
        normal_tol: float,
    ) -> tuple[np.ndarray, float, float, bool]:
        """:meth:`WAM.ik` for one target (the same iteration, step by step)."""
        q = q0.copy()
        eye6, eye7 = np.eye(6), np.eye(DOF)
        for _ in range(max_iter):
            pos, rot, jac = self._pose_jacobian(q)
            normal = rot[:, 2]
            e_p = p_t - pos
            e_n = _cross(normal, n_t)
            cos = float(normal @ n_t)
            if cos < 0:  # opposite normals: any axis orthogonal to n turns it
                e_n = e_n / max(float(np.linalg.norm(e_n)), 1e-9)
            err_p = float(np.linalg.norm(e_p))
            err_n = math.atan2(float(np.linalg.norm(e_n)), cos)
            if err_p < position_tol and err_n < normal_tol:
                break
            e_p = e_p * (0.1 / max(err_p, 0.1))
            proj = np.eye(3) - np.outer(normal, normal)
            j = np.concatenate([jac[:3], proj @ jac[3:]])
            e = np.concatenate([e_p, e_n])
            dq = j.T @ np.linalg.solve(j @ j.T + damping**2 * eye6, e)
            null = eye7 - np.linalg.pinv(j, rcond=1e-6) @ j
            q = np.minimum(
                np.maximum(q + dq + null @ (rest_gain * (rest - q)), self.lower), self.upper
            )
        pos, rot = self.fk(q)
        err_p = float(np.linalg.norm(p_t - pos))
        err_n = math.acos(min(max(float(rot[:, 2] @ n_t), -1.0), 1.0))
        return q, err_p, err_n, err_p < position_tol and err_n < normal_tol


def _cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Cross product of two 3-vectors (np.cross costs ten times more for one pair)."""
    return np.array(
        [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]]
    )
