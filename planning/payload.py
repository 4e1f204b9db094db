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

Units: kilograms, metres, seconds, radians; frames as the names say.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import trimesh

from planning.convex import convex_pieces
from planning.pose import Pose
from planning.timing import JointLimits

DEFAULT_DENSITY_KG_M3 = 600.0
"""Density of the parts (wood) for their masses, in the simulator and for payload limits."""
WRIST_TORQUE_NM = 12.0
"""Torque limit of the wrist joints panda_joint5..7 (Franka's published figure)."""
TCP_TO_WRIST_M = 0.21
"""Added to the TCP-to-centre-of-mass distance for the lever about the wrist: TCP to flange 0.105 m, flange to
the wrist centre (joint 6's height) 0.107 m."""
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
    """Mass, centre of mass and principal inertia of a part of uniform density (its mesh if closed, else the
    union of its convex pieces); mesh in metres, in the part frame."""
    solid = mesh if mesh.is_volume else trimesh.util.concatenate(convex_pieces(mesh))
    solid = solid.copy()
    solid.density = density_kg_m3
    moments, axes = np.linalg.eigh(np.asarray(solid.moment_inertia, dtype=np.float64))
    if np.linalg.det(axes) < 0:
        axes[:, 0] *= -1.0
    return MassProperties(float(solid.mass), Pose.from_rotation(axes, solid.center_mass),
                          tuple(float(max(m, 1e-9)) for m in moments))


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


__all__ = ["DEFAULT_DENSITY_KG_M3", "MassProperties", "carry_limits", "carry_scale", "mass_properties"]
