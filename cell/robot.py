"""The Franka Panda in a PyBullet client: joints, limits, forward and inverse kinematics.

Joint values are radians, positions metres, poses ``world_from_*`` in the world frame of the cell. Inverse
kinematics uses PyBullet's damped least squares from several seeded starts and accepts a solution only when
forward kinematics confirms it and every joint is within its limits.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pybullet_data

from planning import panda_ik
from planning.pose import Pose
from planning.robot_collision import ARM_JOINTS, FINGER_JOINTS, TCP_LINK
from planning.robot_limits import PANDA, RobotLimits

HAND_LINK = "panda_hand"
# the Panda's published limits (rad/s, rad/s^2, rad/s^3), joints 1-7 (planning/robot_limits.py)
VELOCITY_LIMITS = PANDA.velocity_rad_s
ACCELERATION_LIMITS = PANDA.acceleration_rad_s2
JERK_LIMITS = PANDA.jerk_rad_s3
CARTESIAN_STEP_M = 0.02  # inverse kinematics every this much along straight TCP lines
MAX_JOINT_STEP_RAD = 0.35  # larger jumps between neighbouring straight-line solutions mean a branch switch


def pose_rng(world_from_tcp: Pose, seed: int = 0) -> np.random.Generator:
    """A generator of random IK starts drawn from ``seed`` and the target pose itself (rounded to 1 um and 1e-6 of
    the w-first quaternion, sign fixed), so that the restarts for one target do not depend on which queries ran
    before it: an unrelated change upstream (another layout tried, another part's grasp) no longer changes whether
    a marginal target is reached."""
    quat = np.asarray(world_from_tcp.quat_wxyz, dtype=np.float64)
    quat = -quat if quat[np.flatnonzero(np.abs(quat) > 1e-9)[0]] < 0 else quat
    key = np.round(np.concatenate([np.asarray(world_from_tcp.position) * 1e6, quat * 1e6])).astype(np.int64)
    return np.random.default_rng([int(seed) & 0xFFFFFFFF, *(int(k) & 0xFFFFFFFF for k in key)])


class IKError(RuntimeError):
    """No inverse-kinematics solution within tolerance and joint limits."""


class StraightLineError(IKError):
    """A straight TCP line that inverse kinematics cannot follow: it leaves the reachable space, or needs a jump
    between IK branches. ``path`` (K, 7): the configurations solved along it before the failure, the first one
    included."""

    def __init__(self, message: str, path: np.ndarray) -> None:
        super().__init__(message)
        self.path = path


@dataclass(frozen=True)
class IKSettings:
    """Inverse kinematics: ``restarts`` starts, each ``refinements`` rounds of PyBullet's damped least squares
    (``iterations`` each) until within ``coarse_tolerance_m`` / ``coarse_tolerance_rad``, then Gauss-Newton
    polishing (:meth:`Panda.polish_tcp`) to ``position_tolerance_m`` and ``angle_tolerance_rad``. The tight
    default matters: a part meets its neighbours with fractions of a millimetre to spare (PyBullet's IK alone
    stops about 0.5 mm and 0.3 degrees off, and an assembled panel then lands on the rails it should drop
    between). Where the first start fails, a closed-form check with joint 7 at ``closed_form_samples`` angles
    (:meth:`Panda.closed_form_reaches`) refuses a pose out of reach before the other starts (0: no check)."""

    restarts: int = 12
    position_tolerance_m: float = 2e-5
    angle_tolerance_rad: float = 2e-4
    iterations: int = 100
    refinements: int = 8
    coarse_tolerance_m: float = 0.002
    coarse_tolerance_rad: float = 0.02
    closed_form_samples: int = 361


class Panda:
    """A Panda loaded into an existing PyBullet client ``client`` (a :class:`cell.bullet.BulletClient`).

    ``limits``: the real arm's published limits (:mod:`planning.robot_limits`; the Panda's by default, or the FR3's,
    whose kinematics are the Panda's). ``lower_limits`` / ``upper_limits`` (rad) are what inverse kinematics and the
    planner keep within: the datasheet ranges less their margin, inside the URDF's (``sim_lower_limits`` /
    ``sim_upper_limits``, the simulation model's own, which are wider than a real arm accepts)."""

    def __init__(self, client, world_from_base: Pose, urdf: str = "franka_panda/panda.urdf",
                 limits: RobotLimits = PANDA) -> None:
        self.pb, self.cid = client.pb, client.client_id
        self.world_from_base = world_from_base
        self.limits = limits
        position, orientation = world_from_base.to_pybullet()
        self.body = self.pb.loadURDF(f"{pybullet_data.getDataPath()}/{urdf}", position, orientation,
                                     useFixedBase=True, flags=self.pb.URDF_USE_SELF_COLLISION,
                                     physicsClientId=self.cid)
        names, self._movable = {}, []  # movable: the joints PyBullet's Jacobian has a column for
        for j in range(self.pb.getNumJoints(self.body, physicsClientId=self.cid)):
            info = self.pb.getJointInfo(self.body, j, physicsClientId=self.cid)
            names[info[1].decode()] = j
            names[info[12].decode()] = j  # link names map to their joint index too
            if info[2] != self.pb.JOINT_FIXED:
                self._movable.append(j)
        self.arm = [names[n] for n in ARM_JOINTS]
        self.fingers = [names[n] for n in FINGER_JOINTS]
        self.tcp_link = names[TCP_LINK]
        self.hand_link = names[HAND_LINK]
        infos = [self.pb.getJointInfo(self.body, j, physicsClientId=self.cid) for j in self.arm]
        self.sim_lower_limits = np.array([i[8] for i in infos])
        self.sim_upper_limits = np.array([i[9] for i in infos])
        self.lower_limits, self.upper_limits = limits.planning_range(self.sim_lower_limits, self.sim_upper_limits)
        self._arm_columns = [self._movable.index(j) for j in self.arm]
        # the TCP link's frame origin in its centre-of-mass frame, where calculateJacobian takes its point
        _, _, com_position, com_orientation, _, _ = self.pb.getLinkState(self.body, self.tcp_link,
                                                                         physicsClientId=self.cid)
        self._tcp_in_com = Pose.from_pybullet(com_position, com_orientation).inverse().position

    # --- state ----------------------------------------------------------------------------------------------
    def set_arm(self, q: np.ndarray) -> None:
        for joint, value in zip(self.arm, q):
            self.pb.resetJointState(self.body, joint, float(value), physicsClientId=self.cid)

    def arm_q(self) -> np.ndarray:
        return np.array([s[0] for s in self.pb.getJointStates(self.body, self.arm, physicsClientId=self.cid)])

    def set_opening(self, opening_m: float) -> None:
        """Open the hand to ``opening_m`` (0-0.08 m between the fingers)."""
        half = float(np.clip(opening_m, 0.0, 0.08)) / 2.0
        for joint in self.fingers:
            self.pb.resetJointState(self.body, joint, half, physicsClientId=self.cid)

    def within_limits(self, q: np.ndarray, margin: float = 0.0) -> bool:
        return bool(np.all(q >= self.lower_limits + margin) and np.all(q <= self.upper_limits - margin))

    def _facing(self, q: np.ndarray, world_point: np.ndarray) -> np.ndarray:
        """``q`` with joint 1 turned so that the arm faces ``world_point`` (within joint 1's limits)."""
        x, y, _ = self.world_from_base.inverse().apply(np.asarray(world_point, dtype=np.float64)[None])[0]
        facing = np.array(q, dtype=np.float64)
        facing[0] = np.clip(np.arctan2(y, x), self.lower_limits[0], self.upper_limits[0])
        return facing

    # --- kinematics -----------------------------------------------------------------------------------------
    def forward_tcp(self, q: np.ndarray) -> Pose:
        """``world_from_tcp`` at arm configuration ``q`` (sets the arm)."""
        self.set_arm(q)
        state = self.pb.getLinkState(self.body, self.tcp_link, computeForwardKinematics=True,
                                     physicsClientId=self.cid)
        return Pose.from_pybullet(state[4], state[5])

    def tcp_jacobian(self, q: np.ndarray) -> np.ndarray:
        """(6, 7): the TCP's linear (m/rad) and angular (rad/rad) velocity in the world frame per arm joint's rate at
        ``q`` (PyBullet's analytic Jacobian; sets the arm)."""
        self.set_arm(q)
        positions = [s[0] for s in self.pb.getJointStates(self.body, self._movable, physicsClientId=self.cid)]
        zeros = [0.0] * len(positions)
        linear, angular = self.pb.calculateJacobian(self.body, self.tcp_link, self._tcp_in_com.tolist(), positions,
                                                    zeros, zeros, physicsClientId=self.cid)
        return np.vstack([np.asarray(linear)[:, self._arm_columns], np.asarray(angular)[:, self._arm_columns]])

    def polish_tcp(self, q: np.ndarray, world_from_tcp: Pose, steps: int = 6, tolerance_m: float = 2e-6,
                   tolerance_rad: float = 2e-5) -> np.ndarray:
        """``q`` (near a solution) moved by Gauss-Newton steps on the TCP's position and rotation error (the
        analytic Jacobian, damped, within the joint limits) until within ``tolerance_m`` and ``tolerance_rad`` or
        ``steps`` are done."""
        q = np.asarray(q, dtype=np.float64).copy()

        def error(at: np.ndarray) -> np.ndarray:
            reached = self.forward_tcp(at)
            turn = world_from_tcp.rotation @ reached.rotation.T  # world frame
            return np.concatenate([world_from_tcp.position - reached.position, _rotation_vector(turn)])

        for _ in range(steps):
            e = error(q)
            if np.linalg.norm(e[:3]) <= tolerance_m and np.linalg.norm(e[3:]) <= tolerance_rad:
                break
            jacobian = self.tcp_jacobian(q)
            damping = 1e-6
            step = jacobian.T @ np.linalg.solve(jacobian @ jacobian.T + damping * np.eye(6), e)
            q = np.clip(q + step, self.lower_limits, self.upper_limits)
        return q

    def inverse_tcp(self, world_from_tcp: Pose, rng: np.random.Generator, seed_q: np.ndarray | None = None,
                    settings: IKSettings = IKSettings()) -> np.ndarray:
        """Arm configuration placing the TCP at ``world_from_tcp``; raises :class:`IKError`.

        The first start is ``seed_q`` (or the current configuration), the second (with ``restarts`` >= 2) the
        same turned by joint 1 to face the target (so that the arm reaches out towards it, elbow up, rather than
        folding over its own base from a random start), the others uniform within the limits. Where the first
        start fails and the Panda's closed form (:mod:`planning.panda_ik`, joint 7 at ``closed_form_samples``
        angles) finds no solution at all, the pose is out of reach and the other starts are not tried: a refusal
        then takes milliseconds, not the tenth of a second that every start's rounds take.
        """
        position, orientation = world_from_tcp.to_pybullet()
        first = np.asarray(seed_q if seed_q is not None else self.arm_q(), dtype=np.float64)
        starts = [first, self._facing(first, world_from_tcp.position)][:settings.restarts]
        starts += [rng.uniform(self.lower_limits, self.upper_limits) for _ in range(settings.restarts - 2)]
        best_error = np.inf
        for index, start in enumerate(starts):
            if index == 1 and settings.closed_form_samples and not self.closed_form_reaches(
                    world_from_tcp, settings.closed_form_samples):
                raise IKError(f"no arm configuration within the joint limits places the TCP at {world_from_tcp} "
                              f"(closed form, joint 7 at {settings.closed_form_samples} angles)")
            q = start
            for _ in range(settings.refinements):  # PyBullet's IK is one damped step: iterate it from its own result
                self.set_arm(q)
                solution = self.pb.calculateInverseKinematics(
                    self.body, self.tcp_link, position, orientation, maxNumIterations=settings.iterations,
                    residualThreshold=1e-7, physicsClientId=self.cid)
                q = np.clip(np.array(solution[:7]), self.lower_limits, self.upper_limits)
                dp, da = self.forward_tcp(q).distance(world_from_tcp)
                if dp <= settings.coarse_tolerance_m and da <= settings.coarse_tolerance_rad:
                    q = self.polish_tcp(q, world_from_tcp)
                    dp, da = self.forward_tcp(q).distance(world_from_tcp)
                    break
            if not self.within_limits(q):
                continue
            best_error = min(best_error, dp)
            if dp <= settings.position_tolerance_m and da <= settings.angle_tolerance_rad:
                return q
        raise IKError(f"no inverse kinematics for the TCP at {world_from_tcp} within limits "
                      f"({settings.restarts} starts; closest {best_error * 1000:.1f} mm)")

    def tcp_line(self, q_start: np.ndarray, world_from_tcp_start: Pose, offset_world: np.ndarray, seed: int,
                 step_m: float = CARTESIAN_STEP_M) -> np.ndarray:
        """Joint waypoints (K, 7) from ``q_start`` (placing the TCP at ``world_from_tcp_start``) out to the TCP moved
        by ``offset_world`` (world frame, m), keeping its orientation: inverse kinematics every ``step_m`` (m), each
        started from the point before, no joint moving more than :data:`MAX_JOINT_STEP_RAD` between neighbours.
        Collisions are not checked. Raises :class:`StraightLineError`. The task planner's straight moves follow
        these waypoints, and kitting asks for them before it keeps a grasp, so both get the same answer."""
        distance = float(np.linalg.norm(offset_world))
        steps = max(1, int(np.ceil(distance / step_m)))
        settings = IKSettings(restarts=1, refinements=24, iterations=200)
        path = [np.asarray(q_start, dtype=np.float64)]
        for k in range(1, steps + 1):
            target = Pose(world_from_tcp_start.position + offset_world * (k / steps), world_from_tcp_start.quat_wxyz)
            try:
                q = self.inverse_tcp(target, pose_rng(target, seed), seed_q=path[-1], settings=settings)
            except IKError as exc:
                raise StraightLineError(f"straight line leaves the reachable space: {exc}", np.array(path)) from exc
            if np.max(np.abs(q - path[-1])) > MAX_JOINT_STEP_RAD:
                raise StraightLineError("straight line needs a jump between IK branches", np.array(path))
            path.append(q)
        return np.array(path)

    def closed_form_reaches(self, world_from_tcp: Pose, samples: int = IKSettings.closed_form_samples) -> bool:
        """Whether the Panda's closed form finds a configuration within the joint limits placing the TCP at
        ``world_from_tcp``, with joint 7 at ``samples`` angles across its range."""
        base_from_tcp = (self.world_from_base.inverse() @ world_from_tcp).matrix()
        q7_values = np.linspace(self.lower_limits[6], self.upper_limits[6], samples)
        return len(panda_ik.ik_solutions(base_from_tcp, q7_values, self.lower_limits, self.upper_limits)) > 0


def _rotation_vector(rotation: np.ndarray) -> np.ndarray:
    """Axis times angle (radians) of a rotation matrix (3, 3), angles below pi."""
    cos = np.clip((np.trace(rotation) - 1.0) / 2.0, -1.0, 1.0)
    angle = float(np.arccos(cos))
    axis = np.array([rotation[2, 1] - rotation[1, 2], rotation[0, 2] - rotation[2, 0], rotation[1, 0] - rotation[0, 1]])
    if angle < 1e-8:
        return axis / 2.0
    return axis * (angle / (2.0 * np.sin(angle)))

