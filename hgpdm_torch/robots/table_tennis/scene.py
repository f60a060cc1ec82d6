"""Headless SAPIEN (PhysX CPU) scene of the robot table-tennis setup (thesis Sec. 4.3.1, Fig. 4.4).

Floor, ITTF table and net are static bodies; the hanging Barrett WAM of :mod:`..wam` is a fixed-base
articulation whose joints follow reference trajectories through PD drives (force-limited at the
URDF effort limits) with gravity and Coriolis compensation; the racket disc is a collision shape of
its last link; the ball is a dynamic sphere.

The ball follows the model of :mod:`.ball` (the SL simulator lineage):

* PhysX integrates gravity; drag ``-k_d |v| v`` and Magnus ``k_m (w x v)`` are applied as forces
  every step;
* PhysX resolves table, net and racket contacts with the model's restitutions (materials combine
  by averaging, so every contact partner of the ball is given the model's value for that pair);
  contacts are frictionless in PhysX, and at a table bounce the model's tangential law (slip
  factors 0.72/0.68 with the matching spin change) is applied as an impulse, because isotropic
  Coulomb friction cannot produce direction-dependent factors;
* PhysX's semi-implicit Euler stores velocities half a step behind positions; the ball's velocity
  is staggered accordingly (leapfrog), which makes free flight second-order accurate.

Known PhysX traps handled here: steps of at most 1 ms (a 20 m/s ball moves 2 cm per step, half its
diameter, so it cannot tunnel through the racket), a bounce threshold far below PhysX's 2 m/s,
explicit ball inertia (the automatic one is clamped), and drive force limits (URDF efforts are
ignored by SAPIEN).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import sapien
import sapien.physx as physx
import torch

from ..wam import DOF, RACKET_LINK, WAM, urdf_path
from . import geometry as geo
from .ball import DEFAULT_PARAMS, BallParams, BallState

__all__ = ["SceneConfig", "TableTennisScene"]

_TABLE_THICKNESS = 0.03
_NET_THICKNESS = 0.004


@dataclass(frozen=True)
class SceneConfig:
    """Settings of the physics scene.

    Attributes:
        timestep: PhysX step [s]; at most 1 ms (see the module notes on tunnelling).
        ball: ball model constants (shared with :mod:`.ball`).
        stiffness: PD drive stiffness per joint [N m / rad].
        damping: PD drive damping per joint [N m s / rad].
        solver_iterations: PhysX position iterations of the articulation and the ball.
    """

    timestep: float = 0.001
    ball: BallParams = DEFAULT_PARAMS
    stiffness: tuple[float, ...] = (3000.0, 3000.0, 2000.0, 1500.0, 300.0, 300.0, 100.0)
    damping: tuple[float, ...] = (120.0, 120.0, 80.0, 60.0, 8.0, 8.0, 2.0)
    solver_iterations: int = 16

    def __post_init__(self) -> None:
        if not (isinstance(self.timestep, int | float) and 0 < self.timestep <= 0.001):
            raise ValueError(f"timestep must be in (0, 0.001] s, got {self.timestep!r}")
        if not isinstance(self.ball, BallParams):
            raise TypeError(f"ball must be a BallParams, got {type(self.ball).__name__}")
        for name in ("stiffness", "damping"):
            gains = getattr(self, name)
            if len(gains) != DOF or not all(math.isfinite(g) and g >= 0 for g in gains):
                raise ValueError(f"{name} must be {DOF} finite non-negative gains, got {gains!r}")
        if not (isinstance(self.solver_iterations, int) and self.solver_iterations >= 1):
            raise ValueError(
                f"solver_iterations must be a positive int, got {self.solver_iterations!r}"
            )


def _quat_wxyz(rotation: torch.Tensor) -> list[float]:
    """Unit quaternion (w, x, y, z) of a rotation matrix ``[3, 3]``."""
    r = rotation.double().numpy()
    w = math.sqrt(max(0.0, 1.0 + r[0, 0] + r[1, 1] + r[2, 2])) / 2
    x = math.copysign(math.sqrt(max(0.0, 1.0 + r[0, 0] - r[1, 1] - r[2, 2])) / 2, r[2, 1] - r[1, 2])
    y = math.copysign(math.sqrt(max(0.0, 1.0 - r[0, 0] + r[1, 1] - r[2, 2])) / 2, r[0, 2] - r[2, 0])
    z = math.copysign(math.sqrt(max(0.0, 1.0 - r[0, 0] - r[1, 1] + r[2, 2])) / 2, r[1, 0] - r[0, 1])
    return [w, x, y, z]


class TableTennisScene:
    """The physics scene: table, net, floor, the PD-driven WAM with its racket, and the ball.

    Args:
        config: scene settings.
        wam: the arm's kinematics (its base pose places the articulation); default ``WAM()``.
    """

    def __init__(self, config: SceneConfig | None = None, wam: WAM | None = None) -> None:
        self.config = config = SceneConfig() if config is None else config
        self.wam = WAM() if wam is None else wam
        params = config.ball
        physx.set_scene_config(
            gravity=np.array([0.0, 0.0, -params.gravity], dtype=np.float32),
            bounce_threshold=0.05,
            enable_pcm=True,
            enable_tgs=True,
            enable_ccd=False,
            enable_enhanced_determinism=True,
        )
        self.scene = sapien.Scene([physx.PhysxCpuSystem()])
        self.scene.set_timestep(config.timestep)
        self.dt = float(config.timestep)
        e_ball = params.table_restitution
        # Averaged restitution: partner value 2 e_pair - e_ball gives e_pair for the ball pair.
        self._table_mat = physx.PhysxMaterial(0.0, 0.0, params.table_restitution)
        self._racket_mat = physx.PhysxMaterial(0.0, 0.0, 2 * params.racket_restitution - e_ball)
        self._net_mat = physx.PhysxMaterial(0.0, 0.0, max(0.0, 2 * params.net_restitution - e_ball))
        self._build_static()
        self._build_robot()
        self._build_ball()

    # -- construction --------------------------------------------------------------------------
    def _static(self, name: str, half_size: tuple[float, float, float], center: tuple, mat) -> None:
        b = self.scene.create_actor_builder()
        b.add_box_collision(half_size=half_size, material=mat)
        b.set_initial_pose(sapien.Pose(list(center)))
        b.set_name(name)
        b.build_static()

    def _build_static(self) -> None:
        floor = self.scene.create_actor_builder()
        # A plane's normal is its +x axis; turn it to +z.
        floor.add_plane_collision(sapien.Pose(q=[0.7071068, 0.0, -0.7071068, 0.0]))
        floor.set_name("floor")
        floor.build_static()
        top = geo.TABLE_HEIGHT - _TABLE_THICKNESS / 2
        self._static(
            "table",
            (geo.TABLE_HALF_WIDTH, geo.TABLE_HALF_LENGTH, _TABLE_THICKNESS / 2),
            (0.0, 0.0, top),
            self._table_mat,
        )
        self._static(
            "net",
            (geo.NET_HALF_WIDTH, _NET_THICKNESS / 2, geo.NET_HEIGHT / 2),
            (0.0, geo.NET_Y, geo.TABLE_HEIGHT + geo.NET_HEIGHT / 2),
            self._net_mat,
        )

    def _build_robot(self) -> None:
        loader = self.scene.create_urdf_loader()
        loader.fix_root_link = True
        rac = self._racket_mat
        loader.set_material(rac.static_friction, rac.dynamic_friction, rac.restitution)
        robot = loader.load(urdf_path())
        pose = sapien.Pose(
            self.wam.base_position.tolist(), _quat_wxyz(self.wam.base_rotation.cpu())
        )
        robot.set_root_pose(pose)
        robot.set_solver_position_iterations(self.config.solver_iterations)
        self.robot = robot
        self.joints = robot.get_active_joints()
        names = [j.get_name() for j in self.joints]
        if names != [f"wam_joint{i}" for i in range(1, DOF + 1)]:
            raise RuntimeError(f"unexpected WAM joints {names}")
        effort = self.wam.effort_limit.tolist()
        for j, k, d, f in zip(
            self.joints, self.config.stiffness, self.config.damping, effort, strict=True
        ):
            j.set_drive_properties(k, d, force_limit=f, mode="force")
            j.set_friction(0.0)
        links = {link.get_name(): link for link in robot.get_links()}
        self.racket = links[RACKET_LINK]
        # The arm's own links never collide with one another (they overlap at the joints).
        for link in robot.get_links():
            for shape in link.get_collision_shapes():
                shape.set_collision_groups([1, 1, 2, 0])

    def _build_ball(self) -> None:
        p = self.config.ball
        b = self.scene.create_actor_builder()
        b.add_sphere_collision(
            radius=p.radius, material=physx.PhysxMaterial(0.0, 0.0, p.table_restitution)
        )
        inertia = p.inertia_factor * p.mass * p.radius**2
        b.set_mass_and_inertia(p.mass, sapien.Pose(), [inertia] * 3)
        b.set_name("ball")
        b.set_initial_pose(sapien.Pose([0.0, 0.0, 3.0]))
        entity = b.build()
        self.ball = entity.find_component_by_type(physx.PhysxRigidDynamicComponent)
        self.ball.set_linear_damping(0.0)
        self.ball.set_angular_damping(0.0)
        self.ball.set_solver_position_iterations(self.config.solver_iterations)
        self.ball.set_sleep_threshold(0.0)
        self.ball.set_max_depenetration_velocity(1.0)

    # -- ball ----------------------------------------------------------------------------------
    def _flight_acc(self, vel: np.ndarray, spin: np.ndarray) -> np.ndarray:
        p = self.config.ball
        # spin x vel written out: np.cross costs more than the PhysX step for one 3-vector
        w, v = spin, vel
        magnus = np.array(
            [w[1] * v[2] - w[2] * v[1], w[2] * v[0] - w[0] * v[2], w[0] * v[1] - w[1] * v[0]]
        )
        return -p.drag * math.sqrt(v[0] * v[0] + v[1] * v[1] + v[2] * v[2]) * v + p.magnus * magnus

    def set_ball(self, state: BallState) -> None:
        """Place the ball (unbatched :class:`BallState`, fields ``[3]``)."""
        if not isinstance(state, BallState):
            raise TypeError(f"state must be a BallState, got {type(state).__name__}")
        pos, vel, spin = (np.asarray(t.detach().cpu(), dtype=np.float64) for t in state)
        if pos.shape != (3,) or vel.shape != (3,) or spin.shape != (3,):
            raise ValueError("state must hold a single ball (fields of shape [3])")
        # Stagger: PhysX's velocity lags the position by half a step.
        acc = self._flight_acc(vel, spin) - np.array([0.0, 0.0, self.config.ball.gravity])
        self.ball.set_entity_pose(sapien.Pose(pos.tolist()))
        self.ball.set_linear_velocity((vel - 0.5 * self.dt * acc).tolist())
        self.ball.set_angular_velocity(spin.tolist())
        self.ball.wake_up()

    def ball_arrays(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The ball's position, velocity and spin as float64 arrays ``[3]`` (cheap, per step)."""
        pos = np.asarray(self.ball.get_entity_pose().p, dtype=np.float64)
        vel = np.asarray(self.ball.get_linear_velocity(), dtype=np.float64)
        spin = np.asarray(self.ball.get_angular_velocity(), dtype=np.float64)
        acc = self._flight_acc(vel, spin)
        acc[2] -= self.config.ball.gravity
        return pos, vel + 0.5 * self.dt * acc, spin

    def ball_state(self) -> BallState:
        """The ball's current :class:`BallState` (fields ``[3]``, float64)."""
        return BallState(*(torch.as_tensor(a) for a in self.ball_arrays()))

    # -- robot ---------------------------------------------------------------------------------
    def set_robot(self, q: object, qd: object | None = None) -> None:
        """Set joint angles ``[7]`` (and velocities ``[7]``, default zero) and hold them."""
        qa = np.asarray(torch.as_tensor(q, dtype=torch.float64), dtype=np.float64)
        qv = np.zeros(DOF) if qd is None else np.asarray(torch.as_tensor(qd), dtype=np.float64)
        if qa.shape != (DOF,) or qv.shape != (DOF,):
            raise ValueError(f"q and qd must have shape [{DOF}]")
        self.robot.set_qpos(qa.astype(np.float32))
        self.robot.set_qvel(qv.astype(np.float32))
        self.set_targets(qa, qv)

    def set_targets(self, q: np.ndarray, qd: np.ndarray) -> None:
        """PD drive targets: joint angles ``[7]`` and joint velocities ``[7]``."""
        for j, a, v in zip(self.joints, q, qd, strict=True):
            j.set_drive_target(float(a))
            j.set_drive_velocity_target(float(v))

    def robot_state(self) -> tuple[np.ndarray, np.ndarray]:
        """Joint angles and velocities, ``[7]`` each."""
        return (
            np.asarray(self.robot.get_qpos(), dtype=np.float64),
            np.asarray(self.robot.get_qvel(), dtype=np.float64),
        )

    def racket_pose(self) -> tuple[np.ndarray, np.ndarray]:
        """Racket centre ``[3]`` and blade normal ``[3]`` from the simulated link."""
        m = self.racket.get_entity_pose().to_transformation_matrix()
        return np.asarray(m[:3, 3], dtype=np.float64), np.asarray(m[:3, 2], dtype=np.float64)

    # -- stepping ------------------------------------------------------------------------------
    def step(self) -> None:
        """Advance the scene by one timestep: gravity compensation, ball forces, PhysX, bounce."""
        p = self.config.ball
        self.robot.set_qf(self.robot.compute_passive_force(True, True))
        vel = np.asarray(self.ball.get_linear_velocity(), dtype=np.float64)
        spin = np.asarray(self.ball.get_angular_velocity(), dtype=np.float64)
        force = p.mass * self._flight_acc(vel, spin)
        self.ball.add_force_torque(force.astype(np.float32), np.zeros(3, dtype=np.float32))
        vz_before = vel[2]
        self.scene.step()
        self._table_tangential(vz_before)

    def _table_tangential(self, vz_before: float) -> None:
        """Apply the model's tangential bounce law when the ball just bounced on the table."""
        p = self.config.ball
        vel = np.asarray(self.ball.get_linear_velocity(), dtype=np.float64)
        if not (vz_before < 0 < vel[2]):
            return
        pos = np.asarray(self.ball.get_entity_pose().p, dtype=np.float64)
        on_table = abs(pos[0]) <= geo.TABLE_HALF_WIDTH and abs(pos[1]) <= geo.TABLE_HALF_LENGTH
        if not on_table or pos[2] > geo.TABLE_HEIGHT + p.radius + 0.01:
            return
        spin = np.asarray(self.ball.get_angular_velocity(), dtype=np.float64)
        slip_x = vel[0] - p.radius * spin[1]
        slip_y = vel[1] + p.radius * spin[0]
        dvx = (p.table_friction_x - 1.0) * slip_x
        dvy = (p.table_friction_y - 1.0) * slip_y
        kr = p.inertia_factor * p.radius
        self.ball.set_linear_velocity([vel[0] + dvx, vel[1] + dvy, vel[2]])
        self.ball.set_angular_velocity([spin[0] + dvy / kr, spin[1] - dvx / kr, spin[2]])

    def simulate_ball(self, state: BallState, duration: float) -> tuple[torch.Tensor, torch.Tensor]:
        """Fly the ball alone from ``state`` for ``duration`` seconds.

        Returns:
            ``times [S]`` and ball positions ``[S, 3]`` sampled every step, ``S = n + 1``.
        """
        if not (isinstance(duration, int | float) and duration > 0):
            raise ValueError(f"duration must be a positive number of seconds, got {duration!r}")
        self.set_ball(state)
        n = round(duration / self.dt)
        pos = [self.ball_state().pos]
        for _ in range(n):
            self.step()
            pos.append(self.ball_state().pos)
        return torch.arange(n + 1, dtype=torch.float64) * self.dt, torch.stack(pos)
