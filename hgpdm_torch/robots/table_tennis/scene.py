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

Known PhysX traps handled here: steps of at most 1 ms while the ball is simulated (a 20 m/s ball
moves 2 cm per step, half its diameter, so it cannot tunnel through the racket), a bounce threshold
far below PhysX's 2 m/s, explicit ball inertia (the automatic one is clamped), and drive force
limits (URDF efforts are ignored by SAPIEN).

Speed: a PhysX step of the arm costs ~50 us whatever its length, so the scene can also take longer
steps (``SceneConfig.coarse_timestep``) with the ball *parked* (kinematic, out of the way) while the
ball model of :mod:`.ball` flies it: :meth:`TableTennisScene.arm_clear_of` tells when the ball
cannot touch any part of the arm within a step (bounding spheres of the links and a bound on their
speed), and :func:`.strokes.execute_stroke` hands the ball to PhysX before it can.
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass

import numpy as np
import torch

with warnings.catch_warnings():
    # the scene simulates physics only, never renders: a missing system Vulkan (SAPIEN falls
    # back to its own, unused here) is nothing a user must act on
    warnings.filterwarnings("ignore", "Failed to find system libvulkan", UserWarning)
    import sapien
    import sapien.physx as physx

from ..wam import DOF, RACKET_LINK, WAM, urdf_path
from . import geometry as geo
from .ball import DEFAULT_PARAMS, MAX_DURATION, MAX_STEPS, BallParams, BallState

__all__ = ["SceneConfig", "TableTennisScene"]

_TABLE_THICKNESS = 0.03
_NET_THICKNESS = 0.004
_PARKED = sapien.Pose([5.0, 5.0, 3.0])  # where a parked ball waits, far from everything
_JOINT_ACC = 200.0  # rad/s^2: bound on joint accelerations within a clearance horizon


@dataclass(frozen=True)
class SceneConfig:
    """Settings of the physics scene.

    Attributes:
        timestep: PhysX step [s] while the ball is simulated, and the control period of the
            arm's reference; at most 1 ms (see the module notes on tunnelling).
        coarse_timestep: longest PhysX step [s] while the ball is parked (the ball model flies
            it and it cannot touch the arm): a whole multiple of ``timestep``, at most 10 ms
            (the stroke's record period); equal to ``timestep``, every step is short. The
            stroke loop takes short steps anyway around the planned hit and while PhysX has the
            ball (:func:`.strokes.execute_stroke`). With 10 ms a stroke takes ~250 PhysX steps
            instead of ~1300, and the rewards of 900 of 900 strokes (60 opponent trials x 3
            movements x 5 start times) are those of 1 ms steps throughout, the landing points
            of the returns within 3 cm (median; 5 ms: 2 cm); ``tests/robots/test_strokes.py``
            checks the agreement.
        ball: ball model constants (shared with :mod:`.ball`).
        stiffness: PD drive stiffness per joint [N m / rad].
        damping: PD drive damping per joint [N m s / rad].
        solver_iterations: PhysX position iterations of the articulation and the ball.
    """

    timestep: float = 0.001
    coarse_timestep: float = 0.01
    ball: BallParams = DEFAULT_PARAMS
    stiffness: tuple[float, ...] = (3000.0, 3000.0, 2000.0, 1500.0, 300.0, 300.0, 100.0)
    damping: tuple[float, ...] = (120.0, 120.0, 80.0, 60.0, 8.0, 8.0, 2.0)
    solver_iterations: int = 16

    def __post_init__(self) -> None:
        if not (isinstance(self.timestep, int | float) and 0 < self.timestep <= 0.001):
            raise ValueError(f"timestep must be in (0, 0.001] s, got {self.timestep!r}")
        c = self.coarse_timestep
        ratio = c / self.timestep if isinstance(c, int | float) and 0 < c <= 0.01 else math.nan
        if not (math.isfinite(ratio) and round(ratio) >= 1 and abs(ratio - round(ratio)) < 1e-9):
            raise ValueError(
                "coarse_timestep must be a whole multiple of timestep and at most 0.01 s, got "
                f"{self.coarse_timestep!r} (timestep {self.timestep!r})"
            )
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

    @property
    def coarse_steps(self) -> int:
        """``coarse_timestep / timestep``: how many short steps one coarse step spans."""
        return round(self.coarse_timestep / self.timestep)


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
        self._steps = 1  # timesteps per PhysX step now set in the scene
        self.ball_parked = False
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
        self._build_clearance()

    def _build_clearance(self) -> None:
        """Bounding spheres of the arm's collision shapes and the lever arms that bound their
        speed.

        The links form a chain (SAPIEN lists them root first) and each link's frame sits on the
        axis of the joint in front of it, so a point of a shape of link ``i`` is at most
        ``lever[s, j]`` = (the fixed joint offsets from link ``j`` to link ``i``) + (the shape's
        distance from its link's frame) + (its radius) from the axis of active joint ``j <= i``,
        and moves at most ``sum_j |qd_j| lever[s, j]``.
        """
        links = self.robot.get_links()
        joints = self.robot.get_joints()  # joints[i] leads into links[i] (joints[0]: the root)
        offset = [float(np.linalg.norm(j.get_pose_in_parent().p)) for j in joints]
        names = {j.get_name() for j in self.joints}
        active = [i for i, j in enumerate(joints) if j.get_name() in names]
        spheres, lever, reach = [], [], []
        for i, link in enumerate(links):
            for shape in link.get_collision_shapes():
                if isinstance(shape, physx.PhysxCollisionShapeSphere):
                    size = shape.get_radius()
                elif isinstance(shape, physx.PhysxCollisionShapeBox):
                    size = float(np.linalg.norm(shape.get_half_size()))
                elif isinstance(shape, physx.PhysxCollisionShapeCylinder):
                    size = math.hypot(shape.get_radius(), shape.get_half_length())
                elif isinstance(shape, physx.PhysxCollisionShapeCapsule):
                    size = shape.get_radius() + shape.get_half_length()
                else:
                    raise RuntimeError(f"no bounding sphere for a {type(shape).__name__}")
                local = shape.get_local_pose()
                extent = float(np.linalg.norm(local.p)) + size
                # PhysX reports the velocity of the centre of mass: the shape's farthest point
                arm = float(np.linalg.norm(local.p - link.get_cmass_local_pose().p)) + size
                spheres.append((link, sapien.Pose(local.p), size, arm))
                lever.append(
                    [sum(offset[k + 1 : i + 1]) + extent if k <= i else 0.0 for k in active]
                )
                reach.append(sum(offset[1 : i + 1]) + extent)
        self._spheres = spheres
        lever_arr = np.array(lever)
        self._lever_sum = lever_arr.sum(1).tolist()
        self._lever_max = lever_arr.max(0)
        self._lever_max_sum = float(self._lever_max.sum())
        self._shoulder = [float(x) for x in links[0].get_entity_pose().p]
        self._reach = max(reach)  # every point of the arm lies this close to the root's origin

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
    def _flight_acc(self, v: list[float], w: list[float]) -> tuple[float, float, float]:
        """Drag and Magnus acceleration (no gravity) in floats (numpy costs more than a step)."""
        p = self.config.ball
        c = -p.drag * math.sqrt(v[0] * v[0] + v[1] * v[1] + v[2] * v[2])
        km = p.magnus
        return (
            c * v[0] + km * (w[1] * v[2] - w[2] * v[1]),
            c * v[1] + km * (w[2] * v[0] - w[0] * v[2]),
            c * v[2] + km * (w[0] * v[1] - w[1] * v[0]),
        )

    def set_ball(self, state: BallState) -> None:
        """Place the ball (unbatched :class:`BallState`, fields ``[3]``) and simulate it."""
        if not isinstance(state, BallState):
            raise TypeError(f"state must be a BallState, got {type(state).__name__}")
        pos, vel, spin = (np.asarray(t.detach().cpu(), dtype=np.float64) for t in state)
        if pos.shape != (3,) or vel.shape != (3,) or spin.shape != (3,):
            raise ValueError("state must hold a single ball (fields of shape [3])")
        self.set_ball_floats((*pos.tolist(), *vel.tolist(), *spin.tolist()))

    def set_ball_floats(self, s: tuple[float, ...]) -> None:
        """:meth:`set_ball` from nine floats ``(pos, vel, spin)`` (:class:`.ball.ScalarBall`)."""
        vel, spin = s[3:6], s[6:9]
        if self.ball_parked:
            self.ball.set_kinematic(False)
            self.ball_parked = False
        # Stagger: PhysX's velocity lags the position by half a step.
        ax, ay, az = self._flight_acc(vel, spin)
        h = 0.5 * self.dt
        az -= self.config.ball.gravity
        self.ball.set_entity_pose(sapien.Pose(list(s[0:3])))
        self.ball.set_linear_velocity([vel[0] - h * ax, vel[1] - h * ay, vel[2] - h * az])
        self.ball.set_angular_velocity(list(spin))
        self.ball.wake_up()

    def park_ball(self) -> None:
        """Take the ball out of the simulation: kinematic, far from everything, until
        :meth:`set_ball`. Its state then comes from the ball model, not from PhysX."""
        if not self.ball_parked:
            self.ball.set_kinematic(True)
            self.ball_parked = True
        self.ball.set_kinematic_target(_PARKED)
        self.ball.set_entity_pose(_PARKED)

    def ball_floats(self) -> tuple[float, ...]:
        """The ball's position, velocity and spin as nine floats (cheap, per step)."""
        pos = self.ball.get_entity_pose().p.tolist()
        vel = self.ball.get_linear_velocity().tolist()
        spin = self.ball.get_angular_velocity().tolist()
        ax, ay, az = self._flight_acc(vel, spin)
        h = 0.5 * self.dt
        az -= self.config.ball.gravity
        return (*pos, vel[0] + h * ax, vel[1] + h * ay, vel[2] + h * az, *spin)

    def ball_arrays(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The ball's position, velocity and spin as float64 arrays ``[3]``."""
        s = np.array(self.ball_floats())
        return s[0:3], s[3:6], s[6:9]

    def arm_clear_of(self, pos: tuple[float, ...], speed: float, horizon: float) -> bool:
        """Whether a ball at ``pos`` [3] moving at ``speed`` [m/s] cannot touch any part of the
        arm within ``horizon`` seconds.

        Every collision shape of the arm is bounded by a sphere. Within ``horizon = h`` the ball
        moves at most ``speed h + g h^2 / 2``, a point of a shape at most ``u h + A L h^2 / 2``:
        ``u`` its speed now (from its link's velocity and angular velocity), ``L`` the sum of
        its lever arms about the joints and ``A = 200 rad/s^2`` a joint acceleration 4-8 times
        the reference's limits; 1 cm is kept in hand. The whole arm's sphere about the shoulder,
        with ``u`` bounded by the joint velocities (one read), is tried first, the shapes' only
        when the ball is near.
        """
        h = horizon
        slack = self.config.ball.radius + 0.01 + (speed + 0.5 * self.config.ball.gravity * h) * h
        grow = 0.5 * _JOINT_ACC * h * h
        x, y, z = pos[0], pos[1], pos[2]
        c = self._shoulder
        far = math.sqrt((x - c[0]) ** 2 + (y - c[1]) ** 2 + (z - c[2]) ** 2) - self._reach
        qd = np.abs(self.robot.get_qvel())
        if far - slack > float(self._lever_max.dot(qd)) * h + grow * self._lever_max_sum:
            return True
        for (link, local, radius, arm), lever in zip(self._spheres, self._lever_sum, strict=True):
            pose = link.get_entity_pose()
            centre = (pose * local).p
            gap = math.dist((x, y, z), centre.tolist()) - radius - slack
            if gap <= grow * lever:
                return False
            v = link.get_linear_velocity()
            w = link.get_angular_velocity()
            u = math.hypot(*v.tolist()) + math.hypot(*w.tolist()) * arm
            if gap <= u * h + grow * lever:
                return False
        return True

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
        q, qd = np.asarray(q, dtype=np.float64).tolist(), np.asarray(qd, dtype=np.float64).tolist()
        for j, a, v in zip(self.joints, q, qd, strict=True):
            j.set_drive_target(a)
            j.set_drive_velocity_target(v)

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
    def step(self, steps: int = 1) -> None:
        """Advance the scene by ``steps`` timesteps in one PhysX step: gravity compensation,
        ball forces, PhysX, bounce law. ``steps > 1`` (at most ``config.coarse_steps``) needs
        the ball parked (:meth:`park_ball`)."""
        if steps != self._steps:
            if not (isinstance(steps, int) and 1 <= steps <= self.config.coarse_steps):
                raise ValueError(
                    f"steps must be an int in [1, coarse_steps = {self.config.coarse_steps}], "
                    f"got {steps!r}"
                )
            if steps > 1 and not self.ball_parked:
                raise ValueError("steps > 1 needs the ball parked (park_ball)")
            self.scene.set_timestep(steps * self.dt)
            self._steps = steps
        self.robot.set_qf(self.robot.compute_passive_force(True, True))
        if self.ball_parked:
            self.scene.step()
            return
        p = self.config.ball
        vel = self.ball.get_linear_velocity().tolist()
        ax, ay, az = self._flight_acc(vel, self.ball.get_angular_velocity().tolist())
        m = p.mass
        self.ball.add_force_torque([m * ax, m * ay, m * az], [0.0, 0.0, 0.0])
        self.scene.step()
        self._table_tangential(vel[2])

    def _table_tangential(self, vz_before: float) -> None:
        """Apply the model's tangential bounce law when the ball just bounced on the table."""
        p = self.config.ball
        vel = self.ball.get_linear_velocity().tolist()
        if not (vz_before < 0 < vel[2]):
            return
        pos = self.ball.get_entity_pose().p.tolist()
        on_table = abs(pos[0]) <= geo.TABLE_HALF_WIDTH and abs(pos[1]) <= geo.TABLE_HALF_LENGTH
        if not on_table or pos[2] > geo.TABLE_HEIGHT + p.radius + 0.01:
            return
        spin = self.ball.get_angular_velocity().tolist()
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

        Raises:
            ValueError: ``duration`` outside ``(0, MAX_DURATION]`` or more than ``MAX_STEPS``
                steps (see :mod:`.ball`).
        """
        if not (
            isinstance(duration, int | float)
            and math.isfinite(duration)
            and 0 < duration <= MAX_DURATION
        ):
            raise ValueError(
                f"duration must be a number of seconds in (0, MAX_DURATION = {MAX_DURATION:g}], "
                f"got {duration!r}"
            )
        n = round(duration / self.dt)
        if n > MAX_STEPS:
            raise ValueError(f"duration / timestep = {n} steps exceeds MAX_STEPS = {MAX_STEPS}")
        self.set_ball(state)
        pos = [self.ball_state().pos]
        for _ in range(n):
            self.step()
            pos.append(self.ball_state().pos)
        return torch.arange(n + 1, dtype=torch.float64) * self.dt, torch.stack(pos)
