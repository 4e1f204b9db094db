"""The held part as a payload: its mass properties and how much slower the arm must move while carrying it.

The Panda's wrist joints (5-7) deliver at most 12 Nm. Timed at the unloaded arm's acceleration limits, a heavy
board held by its edge (a 2.7 kg table top, its centre 14 cm from the fingers) needs more torque than that; the
wrist falls behind its trajectory and then whips through it (in the simulator: joint 6 at twice its velocity
limit). Real controllers lower the dynamic limits with the payload; so do we, with a deliberately simple model:

- the payload's inertia about the wrist, ``I = I_max + m r^2``: ``I_max`` its largest principal moment about its
  centre of mass, ``r`` the distance of that centre from the TCP plus :data:`TCP_TO_WRIST_M`;
- its largest gravity torque there, ``m g r``;
- the wrist acceleration the rest of the torque allows, ``(WRIST_TORQUE_NM - m g r) / I``.

Checked in the simulator on that table top (2.7 kg, 14 cm from the TCP): timed at 0.63 of the limits the wrist
still overshot joint 6's velocity limit by 34%; at 0.4 it tracked; the model gives 0.36.

When that is below the wrist's acceleration limit, every joint's motion is slowed as one by time scaling: with
``s`` the ratio, accelerations scale by ``s``, velocities by ``sqrt(s)`` and jerks by ``s^1.5`` (the same path,
played back slower), never below :data:`MIN_SCALE`. Light parts (the usual case) keep the full limits.

That model is a first guess. Every timed motion is then checked with the arm's and the payload's rigid-body
inverse dynamics (:meth:`JointTorques.moving_torques_nm`, Newton-Euler with the identified link masses and
inertias of :data:`PANDA_LINK_DYNAMICS`, equal to PyBullet's own to 1e-6 N m), and timed slower where any joint
would need more than :data:`MOVING_TORQUE_FRACTION` of its torque limit (:meth:`JointTorques.motion_scale`;
``cell/task.py``).

Units: kilograms, metres, seconds, radians; frames as the names say.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import trimesh

from planning.convex import convex_hull, convex_pieces
from planning.pose import Pose
from planning.timing import JointLimits

DEFAULT_DENSITY_KG_M3 = 600.0
"""Density of the parts (wood) for their masses, in the simulator and for payload limits."""
PANDA_PAYLOAD_KG = 3.0
"""The Panda's rated payload (Franka's datasheet): the cell refuses a heavier part instead of trying to carry it."""
WRIST_TORQUE_NM = 12.0
"""Torque limit of the wrist joints panda_joint5..7 (Franka's published figure)."""
TCP_TO_WRIST_M = 0.21
"""Added to the TCP-to-centre-of-mass distance for the lever about the wrist: TCP to flange 0.105 m, flange to
the wrist centre (joint 6's height) 0.107 m."""
PANDA_TORQUE_LIMITS_NM = (87.0, 87.0, 87.0, 87.0, 12.0, 12.0, 12.0)
"""Franka's published joint torque limits, panda_joint1..7."""
PANDA_LINK_DYNAMICS = {
    "panda_link1": (4.970684, (0.70337, 0.70661, 0.009117)),
    "panda_link2": (0.646926, (0.007962, 0.02811, 0.025995)),
    "panda_link3": (3.228604, (0.037242, 0.036155, 0.01083)),
    "panda_link4": (3.587895, (0.025853, 0.019552, 0.028323)),
    "panda_link5": (1.225946, (0.035549, 0.029474, 0.008627)),
    "panda_link6": (1.666555, (0.001964, 0.004354, 0.005433)),
    "panda_link7": (0.735522, (0.012516, 0.010027, 0.004815)),
    "panda_hand": (0.73, (0.001, 0.0025, 0.0017)),
    "panda_leftfinger": (0.015, (2.375e-6, 2.375e-6, 7.5e-7)),
    "panda_rightfinger": (0.015, (2.375e-6, 2.375e-6, 7.5e-7)),
}
"""Link masses (kg) and principal inertias (kg m^2) identified by Gaz et al. (RA-L 2019); the inertias in
pybullet_data's URDF (0.1 kg m^2 for every link) are placeholders that the wrist's 12 Nm cannot accelerate as the
real arm does. The simulator gives the links these; the holding-torque model uses the masses."""
HOLDING_TORQUE_FRACTION = 0.8
"""A configuration that holds the payload may need at most this fraction of each joint's torque limit against
gravity alone: the rest accelerates the arm and its load (slowly, see :func:`carry_limits`) and corrects tracking
errors. (The simulated wrist sagged 10-28 degrees off its path, and the part hit the assembly, carrying a 3.3 kg
table top by its edge where gravity alone needed up to 134% of joint 5's 12 N m. At 90%, carrying a 3.8 kg top
whose hold needed 86-90% of joint 5's limit, joints 5 and 6 saturated on the way, the wrist fell 0.8 rad behind
and whipped through at 2.8 rad/s, beyond joint 6's velocity limit.)"""
MOVING_TORQUE_FRACTION = 0.9
"""A timed motion may need at most this fraction of each joint's torque limit (inverse dynamics, the arm and its
load): the rest corrects tracking errors. (Timed at the limits :func:`carry_limits` leaves a light part, a
bookcase's 0.8 kg board of 36 x 48 cm, the simulated joint 6 hit its 12 N m swinging it: the wrist fell behind
and then whipped through at 3.7 rad/s, beyond its 2.61.)"""
MIN_SCALE = 0.1
"""Accelerations are never scaled below this fraction (velocities: its square root)."""
GRAVITY_M_S2 = 9.81
WRIST_JOINTS = (4, 5, 6)  # panda_joint5..7, zero-based


@dataclass(frozen=True)
class MassProperties:
    """A rigid part of uniform density: mass (kg), ``part_from_com`` (centre of mass, axes along the principal
    axes of inertia; part frame) and the principal moments (kg m^2) about the centre of mass."""

    mass_kg: float
    part_from_com: Pose
    inertia_kg_m2: tuple[float, float, float]


def mass_properties(mesh: trimesh.Trimesh, density_kg_m3: float = DEFAULT_DENSITY_KG_M3) -> MassProperties:
    """Mass, centre of mass and principal inertia of a part of uniform density (its mesh if closed and manifold,
    else the union of its convex pieces, or, where those enclose nothing, the mesh's convex hull: never NaN; the
    part's solid comes from :mod:`planning.mesh_intake`); mesh in metres, in the part frame."""
    solid = mesh if mesh.is_volume else trimesh.util.concatenate(convex_pieces(mesh))
    solid = solid.copy()
    solid.density = density_kg_m3
    if not (solid.mass > 0 and np.all(np.isfinite(solid.center_mass))):  # flat pieces: no volume to weigh
        solid = convex_hull(mesh.vertices)
        solid.density = density_kg_m3
    moments, axes = np.linalg.eigh(np.asarray(solid.moment_inertia, dtype=np.float64))
    if np.linalg.det(axes) < 0:
        axes[:, 0] *= -1.0
    return MassProperties(float(solid.mass), Pose.from_rotation(axes, solid.center_mass),
                          tuple(float(max(m, 1e-9)) for m in moments))


FLANGE_FROM_TCP = Pose.from_rotation(np.array([[np.sqrt(0.5), np.sqrt(0.5), 0.0], [-np.sqrt(0.5), np.sqrt(0.5), 0.0],
                                                [0.0, 0.0, 1.0]]), [0.0, 0.0, 0.105])
"""The TCP (between the fingertips) in the flange frame (the arm's last link, ``panda_link8``): the hand is turned
-45 degrees about the flange's z axis, the TCP 0.105 m out along it."""


@dataclass(frozen=True)
class FlangeLoad:
    """A held load as Franka's SetLoad service takes it: ``mass_kg``, ``flange_from_com_m`` (3,) its centre of mass
    in the flange frame (metres) and ``inertia_kg_m2`` (3, 3) its inertia about that centre, flange axes."""

    mass_kg: float
    flange_from_com_m: tuple[float, float, float]
    inertia_kg_m2: tuple[tuple[float, float, float], tuple[float, float, float], tuple[float, float, float]]


NO_LOAD = FlangeLoad(0.0, (0.0, 0.0, 0.0), ((0.0, 0.0, 0.0), (0.0, 0.0, 0.0), (0.0, 0.0, 0.0)))
"""Nothing held (beyond the hand, which the robot's end-effector settings carry)."""


def flange_load(payload: MassProperties, part_from_tcp: Pose) -> FlangeLoad:
    """``payload`` (the part's mass properties, part frame) held at the grasp ``part_from_tcp``, in the flange
    frame (:data:`FLANGE_FROM_TCP`)."""
    flange_from_part = FLANGE_FROM_TCP @ part_from_tcp.inverse()
    flange_from_com = flange_from_part @ payload.part_from_com
    axes = flange_from_com.rotation  # the principal axes in the flange frame
    inertia = axes @ np.diag(payload.inertia_kg_m2) @ axes.T
    inertia = 0.5 * (inertia + inertia.T)
    return FlangeLoad(float(payload.mass_kg), tuple(float(v) for v in flange_from_com.position),
                      tuple(tuple(float(v) for v in row) for row in inertia))


def volume_m3(mesh: trimesh.Trimesh) -> float:
    """The part's volume (m^3) as :func:`mass_properties` weighs it; mesh in metres."""
    return mass_properties(mesh, 1.0).mass_kg


def carry_scale(payload: MassProperties, part_from_tcp: Pose, wrist_acceleration_rad_s2: float) -> float:
    """The fraction (``MIN_SCALE`` .. 1) of the wrist's acceleration limit ``wrist_acceleration_rad_s2`` that the
    payload allows, held at the grasp ``part_from_tcp`` (see the module's model)."""
    lever_m = float(np.linalg.norm(payload.part_from_com.position - part_from_tcp.position)) + TCP_TO_WRIST_M
    inertia = max(payload.inertia_kg_m2) + payload.mass_kg * lever_m ** 2
    spare_nm = WRIST_TORQUE_NM - payload.mass_kg * GRAVITY_M_S2 * lever_m
    if spare_nm <= 0.0:
        return MIN_SCALE
    return float(np.clip(spare_nm / inertia / wrist_acceleration_rad_s2, MIN_SCALE, 1.0))


def carry_limits(limits: JointLimits, payload: MassProperties, part_from_tcp: Pose) -> JointLimits:
    """``limits`` slowed for carrying ``payload`` at the grasp ``part_from_tcp`` (time scaling, see the module);
    the same object when the payload needs no slowing."""
    scale = carry_scale(payload, part_from_tcp, float(np.max(limits.acceleration[list(WRIST_JOINTS)])))
    if scale >= 1.0:
        return limits
    return limits.slowed(float(np.sqrt(scale)))


class JointTorques:
    """Joint torques (N m) of the arm and a payload: static ones that hold them against gravity (world -z), per
    configuration, and those of a motion (:meth:`moving_torques_nm`).

    The arm's links and hand are point masses (:data:`PANDA_LINK_DYNAMICS`) at their centres of mass
    (``chain.centre_of_mass``, the URDF's inertial origins); the payload is one at its centre of mass, rigidly held
    at the grasp ``tcp_from_part``. Joint k carries the torque of every mass beyond it about its axis:
    ``tau_k = axis_k . ((c - o_k) x m g)``. ``kinematics`` is a
    :class:`planning.robot_collision.RobotCollisionChecker` (its forward kinematics, ``link_frames``,
    ``joint_axes``, ``anchor_of`` and ``chain``), ``tcp_link`` the TCP's link.
    """

    def __init__(self, kinematics, payload: MassProperties | None = None, tcp_from_part: Pose | None = None,
                 tcp_link: str = "panda_grasptarget", torque_limits_nm=PANDA_TORQUE_LIMITS_NM,
                 link_masses: dict | None = None, fraction: float = HOLDING_TORQUE_FRACTION) -> None:
        self.kinematics = kinematics
        anchors, points, masses, rotations, inertias = [], [], [], [], []
        for link, (mass, inertia) in (link_masses or PANDA_LINK_DYNAMICS).items():
            index, anchor_from_link = kinematics.anchor_of(link)
            centre = kinematics.chain.centre_of_mass.get(link, np.zeros(3))
            anchors.append(index)
            points.append(anchor_from_link[:3, :3] @ centre + anchor_from_link[:3, 3])
            masses.append(mass)
            rotations.append(anchor_from_link[:3, :3])  # pybullet_data's inertial frames are not rotated
            inertias.append(inertia)
        if payload is not None:
            if tcp_from_part is None:
                raise ValueError("a payload needs tcp_from_part, the part's pose in the TCP frame")
            index, anchor_from_tcp = kinematics.anchor_of(tcp_link)
            anchor_from_com = Pose.from_matrix(anchor_from_tcp) @ tcp_from_part @ payload.part_from_com
            anchors.append(index)
            points.append(anchor_from_com.position)
            masses.append(payload.mass_kg)
            rotations.append(anchor_from_com.matrix()[:3, :3])
            inertias.append(payload.inertia_kg_m2)
        self.payload_kg = 0.0 if payload is None else float(payload.mass_kg)
        self._anchors = np.array(anchors, dtype=np.int64)
        self._points = np.array(points, dtype=np.float64)
        self._masses = np.array(masses, dtype=np.float64)
        self._weights = GRAVITY_M_S2 * self._masses
        self._rotations = np.array(rotations, dtype=np.float64)  # (B, 3, 3) anchor_from_body (principal axes)
        self._inertias = np.array(inertias, dtype=np.float64)  # (B, 3) principal moments, kg m^2
        self._axes = kinematics.joint_axes()
        # joint k (child anchor k + 1) moves the masses hanging from anchors k + 1 and beyond (a serial arm)
        self._moved = self._anchors[None, :] >= np.arange(1, 8)[:, None]  # (7, B)
        self.limits_nm = np.asarray(torque_limits_nm, dtype=np.float64)
        self.fraction = float(fraction)

    def torques_nm(self, qs: np.ndarray) -> np.ndarray:
        """(N, 7) joint torques holding the arm and payload still at configurations ``qs`` (N, 7) radians."""
        frames = self.kinematics.link_frames(qs)  # (N, 8, 4, 4)
        body = frames[:, self._anchors]  # (N, B, 4, 4)
        centres = np.einsum("nbij,bj->nbi", body[..., :3, :3], self._points) + body[..., :3, 3]  # (N, B, 3)
        joints = frames[:, 1:]  # (N, 7, 4, 4)
        axes = np.einsum("nkij,kj->nki", joints[..., :3, :3], self._axes)  # (N, 7, 3) world
        lever = centres[:, None, :, :] - joints[:, :, None, :3, 3]  # (N, 7, B, 3)
        # (c - o) x (0, 0, -w) = (-w ly, w lx, 0)
        moment = np.stack([-lever[..., 1], lever[..., 0], np.zeros_like(lever[..., 0])], axis=-1) \
            * self._weights[None, None, :, None]
        return -np.einsum("nki,nkbi,kb->nk", axes, moment, self._moved.astype(np.float64))  # holds: -gravity's

    def moving_torques_nm(self, qs: np.ndarray, qds: np.ndarray, qdds: np.ndarray) -> np.ndarray:
        """(N, 7) joint torques (N m) that move the arm and payload along ``qs``, ``qds``, ``qdds`` (N, 7): rad,
        rad/s, rad/s^2; rigid-body inverse dynamics (Newton-Euler), without joint friction. At rest it equals
        :meth:`torques_nm`.

        The base is fixed. Link k's angular velocity and acceleration, and the acceleration of its joint's origin,
        follow outwards from the base; each body's centre of mass accelerates with its link; joint k delivers the
        moment about its axis that accelerates every body beyond it against gravity (world -z):
        ``tau_k = z_k . sum_b [(c_b - o_k) x m_b (a_b - g) + I_b alpha_b + omega_b x I_b omega_b]``.
        """
        qs, qds, qdds = (np.atleast_2d(np.asarray(v, dtype=np.float64)) for v in (qs, qds, qdds))
        return self._newton_euler(self.kinematics.link_frames(qs), qds, qdds)

    def _newton_euler(self, frames: np.ndarray, qds: np.ndarray, qdds: np.ndarray) -> np.ndarray:
        """:meth:`moving_torques_nm` from the link frames ``frames`` (N, 8, 4, 4: the base, then each joint's child
        link) of the configurations."""
        count = len(frames)
        axes = np.einsum("nkij,kj->nki", frames[:, 1:, :3, :3], self._axes)  # (N, 7, 3) world
        origins = frames[:, :, :3, 3]  # (N, 8, 3)
        omega = np.zeros((count, 8, 3))
        alpha = np.zeros((count, 8, 3))
        accel = np.zeros((count, 8, 3))  # of each anchor's origin
        for k in range(7):  # a serial arm: anchor k + 1 hangs from anchor k through joint k
            reach = origins[:, k + 1] - origins[:, k]
            accel[:, k + 1] = (accel[:, k] + np.cross(alpha[:, k], reach)
                               + np.cross(omega[:, k], np.cross(omega[:, k], reach)))
            spin = axes[:, k] * qds[:, k, None]
            omega[:, k + 1] = omega[:, k] + spin
            alpha[:, k + 1] = alpha[:, k] + axes[:, k] * qdds[:, k, None] + np.cross(omega[:, k], spin)
        body = frames[:, self._anchors]  # (N, B, 4, 4)
        centres = np.einsum("nbij,bj->nbi", body[..., :3, :3], self._points) + body[..., :3, 3]  # (N, B, 3)
        w, dw = omega[:, self._anchors], alpha[:, self._anchors]  # (N, B, 3)
        arm = centres - origins[:, self._anchors]
        a_centre = accel[:, self._anchors] + np.cross(dw, arm) + np.cross(w, np.cross(w, arm))
        force = self._masses[None, :, None] * (a_centre + np.array([0.0, 0.0, GRAVITY_M_S2]))  # (N, B, 3)
        world_from_principal = np.einsum("nbij,bjk->nbik", body[..., :3, :3], self._rotations)  # (N, B, 3, 3)
        inertia = np.einsum("nbij,bj,nbkj->nbik", world_from_principal, self._inertias, world_from_principal)
        moment_at_centre = (np.einsum("nbij,nbj->nbi", inertia, dw)
                            + np.cross(w, np.einsum("nbij,nbj->nbi", inertia, w)))
        lever = centres[:, None, :, :] - origins[:, 1:, None, :]  # (N, 7, B, 3) from each joint's origin
        moment = np.cross(lever, force[:, None]) + moment_at_centre[:, None]  # (N, 7, B, 3)
        return np.einsum("nki,nkbi,kb->nk", axes, moment, self._moved.astype(np.float64))

    def motion_scale(self, qs: np.ndarray, qds: np.ndarray, qdds: np.ndarray,
                     fraction: float = MOVING_TORQUE_FRACTION) -> float:
        """The time scaling (1: none; at least :data:`MIN_SCALE`) that keeps the motion sampled at ``qs``, ``qds``,
        ``qdds`` (N, 7) within ``fraction`` of every joint's torque limit, under the scaling of
        :func:`carry_limits` (accelerations by ``s``, velocities by ``sqrt(s)``): the torque beyond holding the
        load still scales by ``s``, the holding torque not at all."""
        qs, qds, qdds = (np.atleast_2d(np.asarray(v, dtype=np.float64)) for v in (qs, qds, qdds))
        frames = self.kinematics.link_frames(qs)
        moving = self._newton_euler(frames, qds, qdds)
        holding = self._newton_euler(frames, np.zeros_like(qds), np.zeros_like(qdds))  # equals torques_nm
        cap = fraction * self.limits_nm
        over = np.abs(moving) > cap
        if not over.any():
            return 1.0
        spare = np.maximum(cap - np.abs(holding), 0.0)[over]
        dynamic = np.abs(moving - holding)[over]
        return float(np.clip(np.min(spare / np.maximum(dynamic, 1e-12)), MIN_SCALE, 1.0))

    def within(self, qs: np.ndarray) -> np.ndarray:
        """(N,) whether each configuration holds the load within :attr:`fraction` of every joint's limit."""
        return np.all(np.abs(self.torques_nm(qs)) <= self.fraction * self.limits_nm, axis=1)

    def words(self, q: np.ndarray) -> str:
        """The joint most over its share at ``q``, in words (for error messages)."""
        torques = np.abs(self.torques_nm(np.atleast_2d(q))[0])
        k = int(np.argmax(torques / self.limits_nm))
        return (f"holding {self.payload_kg:.2f} kg needs {torques[k]:.1f} N m at panda_joint{k + 1} against gravity, "
                f"more than {self.fraction:.0%} of its {self.limits_nm[k]:.0f} N m")


__all__ = ["DEFAULT_DENSITY_KG_M3", "FLANGE_FROM_TCP", "FlangeLoad", "JointTorques", "MOVING_TORQUE_FRACTION",
           "MassProperties", "NO_LOAD", "PANDA_LINK_DYNAMICS", "PANDA_TORQUE_LIMITS_NM", "carry_limits", "carry_scale",
           "flange_load", "mass_properties", "volume_m3"]
