"""Execute an assembly program in PyBullet with physics, and check what it did.

The cell is rebuilt in a headless (DIRECT) client with gravity (-9.81 m/s^2 along world -z): the Panda, the static
bodies (table, jig pads, pedestals) and every loose part as a dynamic compound of its convex pieces
(:func:`planning.convex.convex_pieces`, each inset by half of :attr:`SimSettings.joint_clearance_m`: parts planned
face to face meet with that clearance, as real ones do), its mass and inertia from its volume at
:attr:`SimPart.density_kg_m3` (default :attr:`SimSettings.density_kg_m3`). The parts first settle for
:attr:`SimSettings.settle_s` where they lie; one that moves more than :attr:`SimSettings.settle_tolerance_m` is
reported (the start was not at rest). At rest in the kit, a part falls asleep until something touches it or the
arm comes to pick it (:attr:`SimSettings.kit_sleep_threshold`).

The arm follows the program's samples at ``rate_hz`` (one physics step per sample) under position control with the
Franka's joint torque limits. A gripper step that narrows the opening closes the fingers (position control,
:attr:`SimSettings.finger_force_n` per finger); the part it names is welded to the hand as soon as each finger
presses on it with :attr:`SimSettings.grip_force_n` (a real grip holds from contact on), or else when the step
ends if both fingers touch it; otherwise the grasp fails and is reported. The weld holds the part at the grasp the
program plans (the TCP where the program closes, and the part where it starts) when the part lies within
:attr:`SimSettings.grasp_seat_m` of it, turned by at most ``grasp_seat_deg`` about the closing axis and
``grasp_square_deg`` in all: the closing fingers centre a real part and their flat pads square it, while PyBullet's
finger contacts settle it a fraction of a millimetre and one to three degrees off (they creep under the squeeze);
farther off, it holds the part where it lies, and the error carries through to the check. While welded,
the part does not collide with the robot (see :meth:`_Run._weld`). A gripper step that widens the opening releases
the weld; the released part is then fastened (standing for connectors) to those of its ``fasten_to`` parts that lie
within :attr:`SimSettings.fasten_distance_m` of their planned gap to it, and to the jig if ``fasten_to`` holds
``"fixture"`` and it touches a static body. A part fastened to the jig, directly or through fastened parts, becomes a
static body where it was released; one fastened only to loose parts is fixed to them by constraints (see
:meth:`_Run._release`). After the program the world settles again and every part's final pose is compared with its
target, modulo the part's own symmetries (:mod:`cell.symmetry`); what it measured is a
:class:`cell.sim_result.SimulationResult`.

Unplanned contacts are recorded as events (start, end, program step, the two bodies, deepest penetration):

- a robot link touching anything, except the part it holds (which it does not collide with), and the part of the
  pick or place under way during the approach before a grasp, the gripper steps themselves and the retreat after a
  release;
- the held part touching anything but the robot, except what it rested on after settling during the grasp and
  the lift after it, and its ``fasten_to`` neighbours (with the static bodies under its target for "fixture") during
  the last motion before its release and the release itself.

Two parts whose bodies overlap at their targets (models of real furniture often draw a part a few millimetres into
its neighbour) do not collide with each other from the insertion of the later one on, and the result lists them
(:meth:`_Run._overlaps_at_targets`): physics could only push them apart, off target.

Joint position and velocity limit violations of the simulated arm are recorded as events too. Times are on the
program's clock (0 when it starts). Frames: world (+z up, metres); poses ``world_from_*`` use
:class:`planning.pose.Pose` (quaternions w first).

What a program must allow for:

- PyBullet's Panda collision hulls carry a margin of about 1.1 mm that ``changeDynamics`` does not remove: the
  fingers stop (and touch) about 1.1 mm short of a part's face, and robot links touch things about 1 mm early. A
  close command up to the part's width + 1.5 mm still grasps; the task planner's width - 4 mm squeezes firmly.
- Where a part slides along a neighbour into its target, the arm must put it there to well within
  :attr:`SimSettings.joint_clearance_m` (0.5 mm): a part that meets a placed (static) neighbour's edge instead of
  sliding past it jams, and the jam drags it out of the weld.
- The fingers move at :attr:`SimSettings.finger_speed_m_s` (0.05 m/s each): a closing step must last at least
  (opening - width) / 2 / 0.05 s plus a few hundredths (the default 0.5 s covers openings up to 4.5 cm wider).
- Links and hand get the identified masses and inertias of :data:`LINK_DYNAMICS`, and the link pairs of
  :data:`planning.robot_collision.ALLOWED_SELF_PAIRS` do not collide (their hulls overlap at every configuration).
"""

from __future__ import annotations

import contextlib
import tempfile
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import trimesh
from scipy.spatial.transform import Rotation

from cell.bodies import add_convex_body
from cell.bullet import BulletClient
from cell.frames import CellPictures, CellSnapshot, FrameRecorder
from cell.program import GripperStep, MotionStep, Program
from cell.robot import Panda
from cell.scene import CameraConfig
from cell.sim_result import ContactEvent, GraspFailure, LimitEvent, PartResult, SimulationResult
from cell.symmetry import part_symmetry, position_error_m, rotation_error_deg
from planning.convex import mesh_key
from planning.payload import (
    DEFAULT_DENSITY_KG_M3,
    PANDA_LINK_DYNAMICS,
    PANDA_TORQUE_LIMITS_NM,
    MassProperties,
    mass_properties,
)
from planning.pose import Pose
from planning.robot_collision import ALLOWED_SELF_PAIRS, ARM_JOINTS
from planning.robot_limits import robot_limits

FIXTURE = "fixture"  # the name in ``fasten_to`` that stands for the jig (the static bodies under the target)
MIN_RATE_HZ = 240.0
DEFAULT_RATE_HZ = 480.0
PYBULLET_CONTACT_ERP = 0.08
"""PyBullet's default contact ERP (Bullet's ``erp2``), chosen for its default 240 Hz and 50 solver iterations: each
step pushes a penetration out by this fraction of its depth."""
KIT_HOLD_CHECK_S = 0.25  # how often untouched kit parts at rest are put back where they came to rest
ARM_TORQUE_LIMITS_NM = PANDA_TORQUE_LIMITS_NM  # Franka's published joint torque limits
LINK_DYNAMICS = PANDA_LINK_DYNAMICS  # identified link masses and inertias (planning/payload.py)
ROBOT = "robot"
EVENT_GAP_S = 0.1  # contacts of the same pair (limit breaches of the same joint) closer in time form one event
DEFAULT_CAMERA = CameraConfig(eye=(1.3, -0.9, 0.9), target=(0.45, 0.1, 0.2), fov_deg=50.0, width_px=320,
                              height_px=240)


# --- inputs ---------------------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class SimPart:
    """A loose part. ``mesh``: part frame, metres. ``fasten_to``: parts (or :data:`FIXTURE`) it is fastened to once
    released at its target. ``density_kg_m3``: its material (None: :attr:`SimSettings.density_kg_m3`)."""

    name: str
    mesh: trimesh.Trimesh
    world_from_start: Pose  # where it lies when the program starts (kitting)
    world_from_target: Pose  # where the program puts it
    fasten_to: tuple[str, ...] = ()
    density_kg_m3: float | None = None

    def __post_init__(self) -> None:
        if self.density_kg_m3 is not None and not self.density_kg_m3 > 0:
            raise ValueError(f"SimPart {self.name!r}: density_kg_m3 must be positive or None, got {self.density_kg_m3}")


@dataclass(frozen=True)
class StaticBody:
    """A fixed body (table top, jig pad, pedestal): ``mesh`` in its own frame, metres."""

    name: str
    mesh: trimesh.Trimesh
    world_from_body: Pose


@dataclass(frozen=True)
class SimSettings:
    """How to simulate and what counts as success (metres, degrees, seconds, newtons as the names say)."""

    rate_hz: float = DEFAULT_RATE_HZ  # physics steps per second, one program sample per step (>= 240)
    # how fast a penetration is pushed out: this fraction of its depth per second (Bullet's contact ERP is this over
    # the rate); PyBullet's default ERP of 0.08 is 19.2 per second at 240 Hz, kept at any rate. Left at 0.08, 480 Hz
    # pushes out twice as fast, and a held part pushed out of a chock while it was lifted (chair_bertil_0148) kicked
    # the arm past joint 7's velocity limit
    contact_recovery_per_s: float = PYBULLET_CONTACT_ERP * MIN_RATE_HZ
    position_tolerance_m: float = 0.005  # a part's centre within this of its target ...
    rotation_tolerance_deg: float = 3.0  # ... and turned by less than this (modulo its symmetries) is placed
    settle_s: float = 0.5  # the world settles this long before the program and again after it
    settle_tolerance_m: float = 0.003  # a part moving more while settling at the start is reported
    density_kg_m3: float = DEFAULT_DENSITY_KG_M3  # wood; the planner slows heavy carries with the same
    friction: float = 0.6  # parts and static bodies (the fingers keep the URDF's 1.0)
    joint_clearance_m: float = 0.0005  # two parts planned face to face meet with this gap (each is inset by half)
    # two parts whose bodies overlap deeper at their targets do not collide (see :meth:`_Run._overlaps_at_targets`)
    overlap_tolerance_m: float = 0.00001
    finger_force_n: float = 20.0  # per finger (the URDF's effort limit)
    finger_speed_m_s: float = 0.05  # per finger
    grasp_contact_m: float = 0.0002  # a finger this close to the part (metres, as PyBullet measures) touches it
    # the grip holds as soon as each finger presses on the part with this much (N, the contacts' normal forces)
    # while closing: squeezed on by PyBullet's finger hulls, a 16 g table leg standing on its pedestal turned 12
    # degrees about the closing axis in the 0.4 s the fingers kept closing after both touched it
    grip_force_n: float = 2.0
    grasp_seat_m: float = 0.003  # a grasped part this close to its planned grasp (and ...
    grasp_seat_deg: float = 3.0  # ... turned by less than this about the closing axis, which the pads leave free,
    grasp_square_deg: float = 8.0  # ... and less than this in all) is seated there by the closing fingers
    fasten_distance_m: float = 0.002  # a released part this much farther from a neighbour than planned is not fastened
    contact_distance_m: float = 0.0  # contact points at this distance or closer (negative: penetration) count
    contact_breaking_m: float = 0.02  # PyBullet's contact breaking threshold (Bullet's default) ...
    insertion_contact_breaking_m: float = 0.0025  # ... and while a held part is inserted (see :meth:`_Run._insert`)
    # a part in the kit falls asleep (Bullet's deactivation) once its squared speeds (m/s, rad/s) sum below this for
    # 2 s, until something touches it; from the approach to its pick on it never sleeps (see :meth:`_Run._wake`);
    # None: parts never sleep. PyBullet's solver lets a part resting on its pedestal untouched creep by millimetres
    # a minute (a standing drawer front 4.7 mm in 50 s, then grasped that far off its planned grasp, met a
    # neighbour; a chair's back post fell off); asleep, it stays where it settled. A part tipping over passes this
    # speed well within the 2 s and keeps falling. Bullet also wakes a sleeping body when another passes within its
    # contact margin without touching it, and one woken so may not sleep again (a cabinet's drawer back standing on
    # its 6 mm edge beside a creeping neighbour, woken by a board carried past, turned 10 degrees in 29 s and the
    # fingers came down on it): every KIT_HOLD_CHECK_S, a kit part that touches nothing but static bodies is put
    # back where it was first found slower than this; once the program runs, whatever its speed, as long as nothing
    # else has touched it and it has not moved since the program started (see :meth:`_Run._hold_kit_still`)
    kit_sleep_threshold: float | None = 1e-5
    joint_limit_margin_rad: float = 1e-3  # a joint this far beyond its position limit breaks it
    velocity_tolerance: float = 0.03  # relative: a joint faster than (1 + this) x its velocity limit breaks it
    record_every_s: float | None = None  # simulated seconds between animation frames; None: no frames
    camera: CameraConfig = DEFAULT_CAMERA  # for the frames
    urdf: str = "franka_panda/panda.urdf"  # inside pybullet_data
    robot_model: str = "panda"  # the real arm whose published limits the program must keep (planning/robot_limits.py)

    def __post_init__(self) -> None:
        if not self.rate_hz >= MIN_RATE_HZ:
            raise ValueError(f"SimSettings.rate_hz must be at least {MIN_RATE_HZ:.0f} Hz, got {self.rate_hz}")
        if not 0.0 < self.contact_recovery_per_s <= self.rate_hz:
            raise ValueError("SimSettings.contact_recovery_per_s must be positive and at most rate_hz (an ERP of at "
                             f"most 1), got {self.contact_recovery_per_s} at {self.rate_hz} Hz")
        for name in ("position_tolerance_m", "rotation_tolerance_deg", "density_kg_m3", "finger_force_n",
                     "finger_speed_m_s", "grasp_contact_m", "fasten_distance_m", "contact_breaking_m",
                     "insertion_contact_breaking_m"):
            if not getattr(self, name) > 0:
                raise ValueError(f"SimSettings.{name} must be positive, got {getattr(self, name)}")
        if self.kit_sleep_threshold is not None and not self.kit_sleep_threshold > 0:
            raise ValueError("SimSettings.kit_sleep_threshold must be positive or None, "
                             f"got {self.kit_sleep_threshold}")
        for name in ("settle_s", "grasp_seat_m", "grasp_seat_deg", "grasp_square_deg", "joint_clearance_m"):
            if getattr(self, name) < 0:
                raise ValueError(f"SimSettings.{name} must not be negative, got {getattr(self, name)}")
        if self.record_every_s is not None and not self.record_every_s > 0:
            raise ValueError(f"SimSettings.record_every_s must be positive or None, got {self.record_every_s}")

    @property
    def contact_erp(self) -> float:
        """Bullet's contact ERP at :attr:`rate_hz` (see :attr:`contact_recovery_per_s`)."""
        return self.contact_recovery_per_s / self.rate_hz


def configure_physics(pb, cid: int, settings: SimSettings) -> None:
    """Gravity (-9.81 m/s^2 along world -z), the time step, the contact breaking threshold and the contact ERP of
    :class:`SimSettings`, in client ``cid``: every client that should behave as the simulation does (the rest
    check of :mod:`cell.resting` too) is set up here."""
    pb.setGravity(0.0, 0.0, -9.81, physicsClientId=cid)
    pb.setTimeStep(1.0 / settings.rate_hz, physicsClientId=cid)
    pb.setPhysicsEngineParameter(contactBreakingThreshold=settings.contact_breaking_m,
                                 contactERP=settings.contact_erp, physicsClientId=cid)


# --- building the cell ------------------------------------------------------------------------------------------------
def grasp_offset(tcp_from_part: Pose, planned_tcp_from_part: Pose, settings: SimSettings) -> tuple[float, float, bool]:
    """How far a part lies from its planned grasp when the fingers have closed on it: (metres at the TCP, degrees
    in all, whether the closing fingers seat it there). Seated: within :attr:`SimSettings.grasp_seat_m`, turned by
    at most ``grasp_seat_deg`` about the closing axis (TCP +y, which flat pads leave free) and at most
    ``grasp_square_deg`` in all (the pads square a turn about the other two axes)."""
    offset_m, offset_rad = tcp_from_part.inverse().distance(planned_tcp_from_part.inverse())
    turn_tcp = Rotation.from_matrix(tcp_from_part.rotation @ planned_tcp_from_part.rotation.T).as_rotvec()
    offset_deg = float(np.degrees(offset_rad))
    seated = (offset_m <= settings.grasp_seat_m and abs(float(np.degrees(turn_tcp[1]))) <= settings.grasp_seat_deg
              and offset_deg <= settings.grasp_square_deg)
    return float(offset_m), offset_deg, bool(seated)


class _Cell:
    """The cell loaded into one client: the robot, static bodies and parts, with names for every body id."""

    def __init__(self, client: BulletClient, parts: Sequence[SimPart], static_bodies: Sequence[StaticBody],
                 world_from_robot_base: Pose, settings: SimSettings) -> None:
        self.pb, self.cid = client.pb, client.client_id
        self.settings = settings
        self.panda = Panda(client, world_from_robot_base, settings.urdf, robot_limits(settings.robot_model))
        self.robot = self.panda.body
        self.link_names = {-1: self.pb.getBodyInfo(self.robot, physicsClientId=self.cid)[0].decode()}
        for j in range(self.pb.getNumJoints(self.robot, physicsClientId=self.cid)):
            self.link_names[j] = self.pb.getJointInfo(self.robot, j, physicsClientId=self.cid)[12].decode()
        self._configure_robot()
        self.names: dict[int, str] = {self.robot: ROBOT}
        self.static: dict[str, int] = {}
        self.parts: dict[str, int] = {}
        self.part_from_com: dict[str, Pose] = {}
        with tempfile.TemporaryDirectory(prefix="image-assembly-sim-") as folder:
            for body in static_bodies:
                self.static[body.name] = self._add_body(Path(folder), body.mesh, body.world_from_body, None)
            for part in parts:
                density = settings.density_kg_m3 if part.density_kg_m3 is None else part.density_kg_m3
                props = mass_properties(part.mesh, density)
                self.part_from_com[part.name] = props.part_from_com
                self.parts[part.name] = self._add_body(Path(folder), part.mesh, part.world_from_start, props,
                                                       inset_m=0.5 * settings.joint_clearance_m)
                if settings.kit_sleep_threshold is not None:  # at rest in the kit: see SimSettings
                    self.pb.changeDynamics(self.parts[part.name], -1,
                                           activationState=self.pb.ACTIVATION_STATE_ENABLE_SLEEPING,
                                           sleepThreshold=settings.kit_sleep_threshold, physicsClientId=self.cid)
        self.names.update({v: k for k, v in self.static.items()})
        self.names.update({v: k for k, v in self.parts.items()})

    def _configure_robot(self) -> None:
        pb, cid = self.pb, self.cid
        index_of = {name: j for j, name in self.link_names.items()}
        for name, (mass, inertia) in LINK_DYNAMICS.items():
            if name in index_of:
                pb.changeDynamics(self.robot, index_of[name], mass=mass, localInertiaDiagonal=inertia,
                                  physicsClientId=cid)
        # neighbours and pairs whose hulls overlap in every configuration; sorted, as every set whose order reaches
        # PyBullet here: Bullet's results depend on the order of its calls, and a set's order on PYTHONHASHSEED
        for a, b in sorted(tuple(sorted(pair)) for pair in ALLOWED_SELF_PAIRS):
            if a in index_of and b in index_of:
                pb.setCollisionFilterPair(self.robot, self.robot, index_of[a], index_of[b], 0, physicsClientId=cid)

    def _add_body(self, folder: Path, mesh: trimesh.Trimesh, world_from_body: Pose, props: MassProperties | None,
                  inset_m: float = 0.0) -> int:
        """A body of ``mesh``'s convex pieces (no visual shape: pictures come from :mod:`cell.frames`)."""
        return add_convex_body(self.pb, self.cid, folder, mesh, world_from_body, props, self.settings.friction,
                               inset_m)

    # --- state ------------------------------------------------------------------------------------------------------
    def world_from_part(self, name: str) -> Pose:
        """The part's mesh frame in the world (PyBullet reports the centre-of-mass frame)."""
        position, orientation = self.pb.getBasePositionAndOrientation(self.parts[name], physicsClientId=self.cid)
        return Pose.from_pybullet(position, orientation) @ self.part_from_com[name].inverse()

    def set_part(self, name: str, world_from_part: Pose) -> None:
        position, orientation = (world_from_part @ self.part_from_com[name]).to_pybullet()
        self.pb.resetBasePositionAndOrientation(self.parts[name], position, orientation, physicsClientId=self.cid)

    def body_name(self, body: int, link: int) -> str:
        return f"{ROBOT}/{self.link_names[link]}" if body == self.robot else self.names.get(body, f"body {body}")

    def distance(self, part_a: str, part_b: str, cutoff_m: float = 0.05) -> float:
        """Closest distance between two parts as they are (metres, 0 if they overlap, infinite beyond ``cutoff_m``)."""
        points = self.pb.getClosestPoints(self.parts[part_a], self.parts[part_b], cutoff_m, physicsClientId=self.cid)
        return max(0.0, min((p[8] for p in points), default=np.inf))

    def set_robot_collisions(self, name: str, enabled: bool) -> None:
        """Let the robot's links collide with part ``name`` or not."""
        for link in self.link_names:
            self.pb.setCollisionFilterPair(self.robot, self.parts[name], link, -1, int(enabled),
                                           physicsClientId=self.cid)

    def touching(self, body: int, others: Mapping[str, int], distance_m: float) -> list[str]:
        """Names of ``others`` within ``distance_m`` of ``body`` (closest points, after the last collision pass)."""
        return [name for name, other in others.items() if other != body and self.pb.getClosestPoints(
            body, other, distance_m, physicsClientId=self.cid)]


# --- the program's steps ----------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class _StepRole:
    """What each program step may touch: ``robot_may_touch`` (the part of the pick or place under way, besides
    the held part); the held part's phases: ``pick_of`` (grasp and lift) and ``place_of`` (last motion and
    release) name the part concerned."""

    label: str
    closes: bool = False
    opens: bool = False
    robot_may_touch: frozenset[str] = frozenset()
    pick_of: str | None = None
    place_of: str | None = None


def _step_roles(program: Program) -> list[_StepRole]:
    steps = program.steps
    width = program.initial_width_m
    closes, opens = [False] * len(steps), [False] * len(steps)
    for index, step in enumerate(steps):
        if isinstance(step, GripperStep):
            closes[index], opens[index] = step.width_m < width - 1e-6, step.width_m > width + 1e-6
            width = step.width_m
    roles = []
    for index, step in enumerate(steps):
        may_touch, pick_of, place_of = set(), None, None
        before = steps[index - 1] if index > 0 else None
        after = steps[index + 1] if index + 1 < len(steps) else None
        if isinstance(step, GripperStep) and step.part:
            may_touch.add(step.part)
            pick_of = step.part if closes[index] else None
            place_of = step.part if opens[index] else None
        elif isinstance(step, MotionStep):
            if isinstance(after, GripperStep) and after.part and closes[index + 1]:
                may_touch.add(after.part)  # the approach
            if isinstance(before, GripperStep) and before.part and opens[index - 1]:
                may_touch.add(before.part)  # the retreat
            if isinstance(before, GripperStep) and before.part and closes[index - 1] and step.part == before.part:
                pick_of = step.part  # the lift
            if step.part and isinstance(after, GripperStep) and after.part == step.part and opens[index + 1]:
                place_of = step.part  # the insertion
        roles.append(_StepRole(step.label, closes[index], opens[index], frozenset(may_touch), pick_of, place_of))
    return roles


def _check_inputs(program: Program, parts: Sequence[SimPart], static_bodies: Sequence[StaticBody]) -> None:
    names = [p.name for p in parts]
    static_names = [s.name for s in static_bodies]
    for kind, listed in (("part", names), ("static body", static_names)):
        duplicates = sorted({n for n in listed if listed.count(n) > 1})
        if duplicates:
            raise ValueError(f"{kind} names must be unique: {duplicates} appear more than once")
    clash = sorted(set(names) & (set(static_names) | {FIXTURE, ROBOT}))
    if clash:
        raise ValueError(f"part names {clash} are also static bodies or reserved names ({FIXTURE!r}, {ROBOT!r})")
    for part in parts:
        unknown = [n for n in part.fasten_to if n != FIXTURE and n not in names]
        if unknown:
            raise ValueError(f"part {part.name!r}: fasten_to names {unknown}, which are neither parts nor "
                             f"{FIXTURE!r}")
    for step in program.steps:
        if step.part is not None and step.part not in names:
            raise ValueError(f"program step {step.label!r} names part {step.part!r}, which is not among the parts "
                             f"{names}")


# --- recording ------------------------------------------------------------------------------------------------------
class _EventLog:
    """Merges repeated observations of the same key into events (a gap over :data:`EVENT_GAP_S` starts a new one);
    each event keeps the fields of its most severe observation."""

    def __init__(self) -> None:
        self.open: dict[tuple, dict] = {}
        self.closed: list[dict] = []

    def see(self, key: tuple, time_s: float, step: str, severity: float, **fields) -> None:
        event = self.open.get(key)
        if event is not None and time_s - event["end_s"] > EVENT_GAP_S:
            self.closed.append(self.open.pop(key))
            event = None
        if event is None:
            self.open[key] = {"start_s": time_s, "end_s": time_s, "step": step, "severity": severity, **fields}
        else:
            event["end_s"] = time_s
            if severity > event["severity"]:
                event.update(severity=severity, **fields)

    def events(self) -> list[dict]:
        return sorted(self.closed + list(self.open.values()), key=lambda e: e["start_s"])


class _Run:
    """One simulation: the cell, the program's clock and everything recorded."""

    def __init__(self, cell: _Cell, initial_width_m: float, parts: Sequence[SimPart], settings: SimSettings,
                 planned_grasps: Mapping[int, Pose] | None = None, recorder: FrameRecorder | None = None) -> None:
        self.cell, self.pb, self.cid = cell, cell.pb, cell.cid
        self.recorder = recorder  # takes a snapshot every ``settings.record_every_s``
        self.settings = settings
        self.parts = {p.name: p for p in parts}
        self.dt = 1.0 / settings.rate_hz
        self.time_s = -settings.settle_s  # the program's clock: 0 when it starts
        self.opening_m = initial_width_m
        self.held: str | None = None
        self.weld: int | None = None
        self.grasped: set[str] = set()
        self.closing: GripperStep | None = None  # the close under way while its part is not yet held
        self.awake: set[str] = set()  # parts that may no longer sleep (see SimSettings.kit_sleep_threshold)
        self.planned_grasps = dict(planned_grasps or {})  # id(closing step) -> tcp_from_part the plan grasps at
        self.grasp_offsets: dict[str, tuple[float, float, bool]] = {}  # part -> (metres, degrees, seated)
        self.gripped_at: dict[str, float] = {}  # part -> when its weld was made (program clock, seconds)
        self.released_from_hand: str | None = None  # released; the robot ignores it until the hand has opened
        self.fastened: dict[str, list[str]] = {name: [] for name in self.parts}
        self.grounded: set[str] = set()  # fastened to the jig, directly or through fastened parts
        self.released_at: dict[str, Pose] = {}  # world_from_part when last released
        self.grasp_failures: list[GraspFailure] = []
        self.contacts, self.limits = _EventLog(), _EventLog()
        self.next_frame_s = 0.0 if settings.record_every_s and recorder is not None else np.inf
        self.start_supports: dict[str, frozenset[str]] = {}
        self.planned_gaps: dict[tuple[str, str], float] = {}  # (part, fasten_to neighbour) -> gap at their targets
        self.target_supports = self._target_supports()
        self.overlap_partners: dict[str, set[str]] = {}  # part -> the parts it overlaps at their targets
        self.overlaps = self._overlaps_at_targets()
        self.fitted: set[str] = set()  # held parts whose overlap partners no longer collide with them
        self.inserting = False  # the held part's insertion is under way (see :meth:`_insert`)
        self.steps_to_kit_check = 0
        self.kit_rest: dict[str, tuple] = {}  # kit part -> (position, orientation) where it is held still
        self.kit_disturbed: set[str] = set()  # kit parts something other than a static body has touched
        self.static_bodies = frozenset(cell.static.values())
        self.kit_still: set[str] = set()  # kit parts found at rest, untouched, since the program started
        self.program_running = False  # the parts have settled (see start)
        self.arm_q = np.zeros(7)
        self.arm_qd = np.zeros(7)

    # --- set-up -----------------------------------------------------------------------------------------------------
    def _target_supports(self) -> dict[str, frozenset[str]]:
        """Static bodies each part touches at its target (what "fixture" stands for), found by placing it there;
        fills :attr:`planned_gaps` too."""
        supports = {}
        for name, part in self.parts.items():
            self.cell.set_part(name, part.world_from_target)
            self.pb.performCollisionDetection(physicsClientId=self.cid)
            supports[name] = frozenset(self.cell.touching(self.cell.parts[name], self.cell.static,
                                                          self.settings.fasten_distance_m))
            for other in part.fasten_to:
                if other != FIXTURE and other != name:
                    self.cell.set_part(other, self.parts[other].world_from_target)
                    self.planned_gaps[name, other] = self.cell.distance(name, other)
                    self.cell.set_part(other, self.parts[other].world_from_start)
            self.cell.set_part(name, part.world_from_start)
        return supports

    def _overlaps_at_targets(self) -> list[tuple[str, str, float]]:
        """Pairs of parts whose bodies overlap by more than ``overlap_tolerance_m`` with every part at its target,
        (a, b, depth in metres), deepest first. Their collision is switched off from the insertion of the later of
        the two (the held part's last motion before its release) to the end (:meth:`_let_fit`).

        Such targets cannot be reached with physics: models of real furniture often let a part sink a few
        millimetres into its neighbour (dowels and cam fittings drawn without their holes, or panels drawn into each
        other), and a part's convex pieces may bulge into a neighbour where the mesh itself does not. Pushed apart,
        the part would end off target by the depth and knock its neighbours on the way in; a real part has the hole,
        so the pair is treated as one that fits (and is fastened at release like any touching pair).

        However shallow: ``overlap_tolerance_m`` is 10 micrometres. At 0.1 mm, table_klubbo_0743's L-shaped leg,
        whose convex pieces lie 0.09 mm into the table top's at their targets (beyond the joint clearance's insets),
        slid flush under the top for the last 28 mm of its insertion with the pair colliding: the contact rose to
        139 N, turned the leg in the hand and jammed it 25 mm short. A real part that tight still goes in."""
        cell, pb, cid = self.cell, self.pb, self.cid
        for name, part in self.parts.items():
            cell.set_part(name, part.world_from_target)
        pb.performCollisionDetection(physicsClientId=cid)
        names = list(self.parts)
        overlaps = []
        for i, a in enumerate(names):
            for b in names[i + 1:]:
                points = pb.getClosestPoints(cell.parts[a], cell.parts[b], 0.0, physicsClientId=cid)
                depth = -min((p[8] for p in points), default=0.0)
                if depth > self.settings.overlap_tolerance_m:
                    overlaps.append((a, b, float(depth)))
                    self.overlap_partners.setdefault(a, set()).add(b)
                    self.overlap_partners.setdefault(b, set()).add(a)
        for name, part in self.parts.items():
            cell.set_part(name, part.world_from_start)
        return sorted(overlaps, key=lambda o: -o[2])

    def _insert(self) -> None:
        """The held part's insertion begins (its last motion before the release): it stops colliding with the
        parts it overlaps at their targets (:meth:`_let_fit`), and the contacts PyBullet creates from now on until
        the release break once their points drift :attr:`SimSettings.insertion_contact_breaking_m` apart (Bullet's
        default is 2 cm). A top sliding down between two sides with a quarter of a millimetre to spare first meets
        each side's top edge from above; with the default, PyBullet keeps that contact and refreshes it along its
        first, nearly vertical, normal while the top moves down past the edge, so the gap beside it reads as a
        penetration and the solver jams the top centimetres high (traced on procedural cabinets, whose tops then
        ended 4-14 mm off). 2.5 mm at 480 Hz: at 5 mm, a table's apron slid in under its top with 0.28 mm to spare
        met the top's edge, and PyBullet kept that contact along a normal 14 degrees off the apron's motion until the
        apron jammed 18 mm short (table_torsby_1549; at 240 Hz the contact broke in time; 2.5 and 3.5 mm passed, 4
        mm did not). Not much smaller: at 1-2 mm (240 Hz) the weld drove a held part pushed onto a neighbour most of
        the way into it (10 of 12 mm where 5 mm stopped it 2.7 mm in). Not for the whole carry: parts resting in the
        kit then tipped off their pedestals now and then (a rail standing on its edge on a procedural chair's
        pedestal, untouched)."""
        self.inserting = True
        if self.held not in self.fitted:
            self._let_fit(self.held)
        self.pb.setPhysicsEngineParameter(contactBreakingThreshold=self.settings.insertion_contact_breaking_m,
                                          physicsClientId=self.cid)

    def _let_fit(self, name: str) -> None:
        """From now on, ``name`` does not collide with the parts it overlaps at their targets."""
        for other in sorted(self.overlap_partners.get(name, ())):
            self.pb.setCollisionFilterPair(self.cell.parts[name], self.cell.parts[other], -1, -1, 0,
                                           physicsClientId=self.cid)
        self.fitted.add(name)

    def start(self, q0: np.ndarray) -> dict[str, float]:
        """Robot at ``q0`` with the program's initial opening, parts at their start; settle; returns how far each
        part's centre moved (metres)."""
        panda = self.cell.panda
        panda.set_arm(q0)
        panda.set_opening(self.opening_m)
        self._command_fingers(self.opening_m)
        centres = {n: p.world_from_start.apply(p.mesh.centroid) for n, p in self.parts.items()}
        self.settle(q0, "settling before the program")
        self.program_running = True
        self.pb.performCollisionDetection(physicsClientId=self.cid)
        others = {**self.cell.static, **self.cell.parts}
        self.start_supports = {name: frozenset(self.cell.touching(self.cell.parts[name], others,
                                                                  self.settings.fasten_distance_m))
                               for name in self.parts}
        return {n: float(np.linalg.norm(self.cell.world_from_part(n).apply(self.parts[n].mesh.centroid) - c))
                for n, c in centres.items()}

    def settle(self, q: np.ndarray, label: str) -> None:
        for _ in range(int(round(self.settings.settle_s * self.settings.rate_hz))):
            self.physics_step(q, np.zeros(7), _StepRole(label))

    # --- stepping ---------------------------------------------------------------------------------------------------
    def _command_fingers(self, opening_m: float) -> None:
        half = float(np.clip(opening_m, 0.0, 0.08)) / 2.0
        for joint in self.cell.panda.fingers:
            self.pb.setJointMotorControl2(self.cell.robot, joint, self.pb.POSITION_CONTROL, targetPosition=half,
                                          force=self.settings.finger_force_n,
                                          maxVelocity=self.settings.finger_speed_m_s, physicsClientId=self.cid)

    def physics_step(self, q_target: np.ndarray, qd_target: np.ndarray, role: _StepRole) -> None:
        pb, cid, robot = self.pb, self.cid, self.cell.robot
        if self.held is not None and role.place_of == self.held and not self.inserting:
            self._insert()
        for name in sorted(role.robot_may_touch - self.awake):  # the part to be picked (or just released)
            self._wake(name)
        pb.setJointMotorControlArray(robot, self.cell.panda.arm, pb.POSITION_CONTROL,
                                     targetPositions=q_target.tolist(), targetVelocities=qd_target.tolist(),
                                     forces=ARM_TORQUE_LIMITS_NM, physicsClientId=cid)
        pb.stepSimulation(physicsClientId=cid)
        self.time_s += self.dt
        states = pb.getJointStates(robot, self.cell.panda.arm, physicsClientId=cid)
        self.arm_q = np.array([s[0] for s in states])
        self.arm_qd = np.array([s[1] for s in states])
        self._check_limits(role)
        self._check_contacts(role)
        if self.closing is not None and self.held is None and self._gripped(self.closing.part):
            self._weld(self.closing.part, self.planned_grasps.get(id(self.closing)))
        if self.kit_still:
            self._note_kit_touches()
        self.steps_to_kit_check -= 1
        if self.steps_to_kit_check <= 0 and self.settings.kit_sleep_threshold is not None:
            self.steps_to_kit_check = max(1, int(round(KIT_HOLD_CHECK_S * self.settings.rate_hz)))
            self._hold_kit_still()
        if self.time_s >= self.next_frame_s - 1e-9:
            self.recorder.add(self.snapshot())
            self.next_frame_s += self.settings.record_every_s

    def snapshot(self) -> CellSnapshot:
        """Where the parts and the robot's joints are now (for a picture)."""
        cell = self.cell
        fingers = self.pb.getJointStates(cell.robot, cell.panda.fingers, physicsClientId=self.cid)
        return CellSnapshot({name: cell.world_from_part(name) for name in cell.parts},
                            tuple(float(v) for v in self.arm_q), (float(fingers[0][0]), float(fingers[1][0])))

    def _hold_kit_still(self) -> None:
        """Hold still the kit parts (never woken for a pick) that touch nothing but static bodies, as if asleep:
        each is put back where it was first found moving slower than :attr:`SimSettings.kit_sleep_threshold` (see
        there: Bullet does not always let such a part sleep again once something passing has woken it), and let go
        when it moves faster. Once the program runs, a part found so at rest at one of these checks, which nothing
        has touched and which has not moved since the program started (:meth:`_note_kit_touches`), is held
        whatever its speed: nothing can set it moving (the kitting checked with physics that it rests there), while
        Bullet's contacts on a thin edge can (cabinet_7's drawer back, an 8 mm board standing on its edge between
        chocks, gained speed untouched between two checks, was let go, and tipped onto a chock). A part that tips
        while the parts settle falls, and is reported; one that something touches is let go, and held again only
        where it comes to rest."""
        pb, cid, cell = self.pb, self.cid, self.cell
        for name, body in cell.parts.items():
            if name in self.awake or name == self.held:
                self.kit_rest.pop(name, None)
                self.kit_still.discard(name)
                continue
            linear, angular = pb.getBaseVelocity(body, physicsClientId=cid)
            speed = float(np.dot(linear, linear) + np.dot(angular, angular))
            touched = self._touched_by_moving_body(body)
            if touched:
                self.kit_disturbed.add(name)
                self.kit_still.discard(name)
            moving = speed >= self.settings.kit_sleep_threshold
            if moving and self.program_running and name not in self.kit_still:
                self.kit_disturbed.add(name)  # not at rest when the program started, or knocked since
            if touched or (moving and name not in self.kit_still):
                self.kit_rest.pop(name, None)
                continue
            if self.program_running and name not in self.kit_disturbed:
                self.kit_still.add(name)
            rest = self.kit_rest.get(name)
            if rest is None:
                self.kit_rest[name] = pb.getBasePositionAndOrientation(body, physicsClientId=cid)
            elif speed > 0.0:
                pb.resetBasePositionAndOrientation(body, *rest, physicsClientId=cid)
                pb.resetBaseVelocity(body, [0.0, 0.0, 0.0], [0.0, 0.0, 0.0], physicsClientId=cid)

    def _note_kit_touches(self) -> None:
        """Mark as touched (no longer held whatever its speed) every kit part that something other than a static
        body touches now: checked every step while the program runs, since a brief knock between two checks of
        :meth:`_hold_kit_still` would otherwise be undone there (about 2 microseconds a part a step)."""
        for name in list(self.kit_still):
            if self._touched_by_moving_body(self.cell.parts[name]):
                self.kit_disturbed.add(name)
                self.kit_still.discard(name)
                self.kit_rest.pop(name, None)

    def _touched_by_moving_body(self, body: int) -> bool:
        """Whether anything but a static body (table, jig pads, pedestals) touches ``body`` now."""
        return any(point[2] not in self.static_bodies
                   for point in self.pb.getContactPoints(bodyA=body, physicsClientId=self.cid))

    def _wake(self, name: str) -> None:
        """``name`` wakes and never sleeps again: from the approach to its pick on, so that the approach, the grasp
        and everything after meet the part as they would without sleeping (sleep only keeps untouched parts still)."""
        self.awake.add(name)
        if name in self.cell.parts:
            self.pb.changeDynamics(self.cell.parts[name], -1,
                                   activationState=self.pb.ACTIVATION_STATE_DISABLE_SLEEPING
                                   | self.pb.ACTIVATION_STATE_WAKE_UP, physicsClientId=self.cid)

    def _check_limits(self, role: _StepRole) -> None:
        s, arm = self.settings, self.cell.panda.limits  # the real arm's published limits
        q, qd = self.arm_q, self.arm_qd
        for j in np.flatnonzero((q < arm.lower_rad - s.joint_limit_margin_rad)
                                | (q > arm.upper_rad + s.joint_limit_margin_rad)):
            bound = arm.lower_rad[j] if q[j] < arm.lower_rad[j] else arm.upper_rad[j]
            self.limits.see((j, "position"), self.time_s, role.label, abs(q[j] - bound), joint=ARM_JOINTS[j],
                            quantity="position", limit=float(bound), peak=float(q[j]))
        for j in np.flatnonzero(np.abs(qd) > arm.velocity_rad_s * (1.0 + s.velocity_tolerance)):
            self.limits.see((j, "velocity"), self.time_s, role.label, abs(qd[j]), joint=ARM_JOINTS[j],
                            quantity="velocity", limit=float(np.copysign(arm.velocity_rad_s[j], qd[j])),
                            peak=float(qd[j]))

    def _held_may_touch(self, role: _StepRole) -> frozenset[str]:
        allowed = set()
        if role.pick_of == self.held:
            allowed |= self.start_supports.get(self.held, frozenset())
        if role.place_of == self.held:
            fasten = self.parts[self.held].fasten_to
            allowed |= {n for n in fasten if n != FIXTURE}
            if FIXTURE in fasten:
                allowed |= self.target_supports[self.held]
        return frozenset(allowed)

    def _check_contacts(self, role: _StepRole) -> None:
        pb, cid, cell, limit = self.pb, self.cid, self.cell, self.settings.contact_distance_m
        for point in pb.getContactPoints(bodyA=cell.robot, physicsClientId=cid):
            other, distance = point[2], point[8]
            if distance > limit:
                continue
            other_name = cell.names.get(other)
            if other != cell.robot and (other_name == self.held or other_name in role.robot_may_touch):
                continue
            names = sorted((cell.body_name(cell.robot, point[3]), cell.body_name(other, point[4])))
            self.contacts.see(tuple(names), self.time_s, role.label, -distance, body_a=names[0], body_b=names[1])
        if self.held is None:
            return
        held_body, allowed = cell.parts[self.held], self._held_may_touch(role)
        for point in pb.getContactPoints(bodyA=held_body, physicsClientId=cid):
            other, distance = point[2], point[8]
            if distance > limit or other == cell.robot or cell.names.get(other) in allowed:
                continue
            name = cell.body_name(other, point[4])
            self.contacts.see((self.held, name), self.time_s, role.label, -distance, body_a=self.held, body_b=name)

    # --- gripper events ---------------------------------------------------------------------------------------------
    def enter_gripper_step(self, step: GripperStep, role: _StepRole) -> None:
        if role.opens and self.held is not None:
            self._release()
        if role.closes or role.opens:
            self._command_fingers(step.width_m)
        self.opening_m = step.width_m
        self.closing = step if role.closes and step.part is not None and self.held is None else None

    def leave_gripper_step(self, step: GripperStep, role: _StepRole) -> None:
        self.closing = None
        if role.opens and self.released_from_hand is not None:  # the fingers are clear of it now
            self.cell.set_robot_collisions(self.released_from_hand, True)
            self.released_from_hand = None
        if not role.closes or step.part is None or self.held is not None:
            return
        body = self.cell.parts[step.part]
        touching = tuple(self.cell.link_names[f] for f in self.cell.panda.fingers
                         if self.pb.getClosestPoints(self.cell.robot, body, self.settings.grasp_contact_m,
                                                     linkIndexA=f, physicsClientId=self.cid))
        if len(touching) < len(self.cell.panda.fingers):
            self.grasp_failures.append(GraspFailure(step.part, step.label, self.time_s, touching))
            return
        self._weld(step.part, self.planned_grasps.get(id(step)))

    def _gripped(self, name: str) -> bool:
        """Whether every finger presses on part ``name`` with at least :attr:`SimSettings.grip_force_n`."""
        pb, cell = self.pb, self.cell
        for finger in cell.panda.fingers:
            points = pb.getContactPoints(bodyA=cell.robot, bodyB=cell.parts[name], linkIndexA=finger,
                                         physicsClientId=self.cid)
            if sum(point[9] for point in points) < self.settings.grip_force_n:
                return False
        return True

    def _weld(self, name: str, planned_tcp_from_part: Pose | None) -> None:
        """Hold part ``name`` in the hand: at the planned grasp if it lies close to it (the closing fingers centre
        it and their flat pads square it: a turn about the approach axis or the pads' long axis brings its faces
        flat against the pads, a turn about the closing axis they leave; the simulated contacts settle a fraction
        of a millimetre and one to three degrees off, mostly about the approach axis, as PyBullet's finger hulls
        creep under the squeeze), else where it is. The weld stands for the grip from then on: the robot
        stops colliding with the part and the fingers stay where they closed. Contacts between the fingers or the
        hand and a welded part fight the weld, which then creeps by degrees over a carry; and PyBullet's Panda
        hulls carry a margin of about 1.1 mm, so the part would catch on the arm where the planner leaves it a
        fraction of a millimetre (contacts between the robot and the part it holds are not reported either)."""
        pb, cid, cell, settings = self.pb, self.cid, self.cell, self.settings
        tcp = pb.getLinkState(cell.robot, cell.panda.tcp_link, computeForwardKinematics=True, physicsClientId=cid)
        world_from_tcp = Pose.from_pybullet(tcp[4], tcp[5])
        tcp_from_part = world_from_tcp.inverse() @ cell.world_from_part(name)
        seated = False
        if planned_tcp_from_part is not None:
            offset_m, offset_deg, seated = grasp_offset(tcp_from_part, planned_tcp_from_part, settings)
            self.grasp_offsets[name] = (offset_m, offset_deg, seated)
            if seated:  # a fixed constraint keeps the offset it starts with: put the part where the fingers seat it
                tcp_from_part = planned_tcp_from_part
                cell.set_part(name, world_from_tcp @ tcp_from_part)
        hand = pb.getLinkState(cell.robot, cell.panda.hand_link, computeForwardKinematics=True, physicsClientId=cid)
        hand_com_from_part_com = (Pose.from_pybullet(hand[0], hand[1]).inverse() @ world_from_tcp @ tcp_from_part
                                  @ cell.part_from_com[name])
        position, orientation = hand_com_from_part_com.to_pybullet()
        self.weld = pb.createConstraint(cell.robot, cell.panda.hand_link, cell.parts[name], -1, pb.JOINT_FIXED,
                                        [0, 0, 0], position, [0, 0, 0], orientation, [0, 0, 0, 1],
                                        physicsClientId=cid)
        pb.changeConstraint(self.weld, maxForce=_HOLD_FORCE_N, physicsClientId=cid)
        cell.set_robot_collisions(name, False)
        for joint, state in zip(cell.panda.fingers, pb.getJointStates(cell.robot, cell.panda.fingers,
                                                                      physicsClientId=cid)):
            pb.setJointMotorControl2(cell.robot, joint, pb.POSITION_CONTROL, targetPosition=state[0],
                                     force=settings.finger_force_n, maxVelocity=settings.finger_speed_m_s,
                                     physicsClientId=cid)
        self.held = name
        self.grasped.add(name)
        self.gripped_at[name] = self.time_s
        self._wake(name)

    def _release(self) -> None:
        """Remove the weld and fasten the released part to its ``fasten_to`` neighbours that lie within
        ``fasten_distance_m`` of their planned gap to it, and to the world if ``fasten_to`` holds "fixture" and it
        touches a static body.

        A part fastened to the jig, directly or through parts fastened to it, becomes a static body where it is: a
        chain of fixed constraints between light bodies (PyBullet's iterative solver) creeps under load by
        millimetres and gives way when a part slides along it, a real fastened assembly on its jig does neither. A
        part fastened only to loose parts is fixed to them by constraints. Fastened bodies no longer collide with
        each other (their contacts could only fight the constraints)."""
        pb, cid, cell = self.pb, self.cid, self.cell
        pb.removeConstraint(self.weld, physicsClientId=cid)
        pb.setPhysicsEngineParameter(contactBreakingThreshold=self.settings.contact_breaking_m, physicsClientId=cid)
        self.inserting = False
        name, self.held, self.weld = self.held, None, None
        self.released_from_hand = name
        body = cell.parts[name]
        fasten = self.parts[name].fasten_to
        pb.performCollisionDetection(physicsClientId=cid)
        self.released_at[name] = cell.world_from_part(name)
        world_from_com = Pose.from_pybullet(*pb.getBasePositionAndOrientation(body, physicsClientId=cid))
        gaps = {n: self.planned_gaps.get((name, n), np.inf) for n in fasten if n != FIXTURE}
        neighbours = [n for n, gap in gaps.items()
                      if np.isfinite(gap) and cell.distance(name, n) <= gap + self.settings.fasten_distance_m]
        supports = (cell.touching(body, cell.static, self.settings.fasten_distance_m) if FIXTURE in fasten else [])
        grounded = bool(supports) or any(n in self.grounded for n in neighbours)
        for other_name in neighbours:
            other = cell.parts[other_name]
            pb.setCollisionFilterPair(body, other, -1, -1, 0, physicsClientId=cid)
            self.fastened[name].append(other_name)
            if grounded and other_name in self.grounded:
                continue  # both fixed to the world
            world_from_other = Pose.from_pybullet(*pb.getBasePositionAndOrientation(other, physicsClientId=cid))
            position, orientation = (world_from_other.inverse() @ world_from_com).to_pybullet()
            constraint = pb.createConstraint(other, -1, body, -1, pb.JOINT_FIXED, [0, 0, 0], position, [0, 0, 0],
                                             orientation, [0, 0, 0, 1], physicsClientId=cid)
            pb.changeConstraint(constraint, maxForce=_HOLD_FORCE_N, physicsClientId=cid)
        for support in supports:
            pb.setCollisionFilterPair(body, cell.static[support], -1, -1, 0, physicsClientId=cid)
        if supports:
            self.fastened[name].append(FIXTURE)
        if grounded:
            pb.changeDynamics(body, -1, mass=0.0, physicsClientId=cid)  # static from now on
            pb.resetBaseVelocity(body, [0.0, 0.0, 0.0], [0.0, 0.0, 0.0], physicsClientId=cid)
            self.grounded.add(name)


_HOLD_FORCE_N = 5000.0  # welds and fastenings: far above any load in the cell


# --- the simulation ---------------------------------------------------------------------------------------------------
def simulate_program(program: Program, parts: Sequence[SimPart], static_bodies: Sequence[StaticBody],
                     world_from_robot_base: Pose, settings: SimSettings = SimSettings(),
                     progress: Callable[[float], None] | None = None) -> SimulationResult:
    """Run ``program`` with physics in a fresh headless PyBullet client and measure the result (see the module's
    docstring). ``progress(fraction)`` is called about a hundred times as the program runs, last with 1.0."""
    _check_inputs(program, parts, static_bodies)
    started = time.perf_counter()
    samples = program.sample(settings.rate_hz)
    q, qd = samples["q"], samples["qd"]
    starts = program.step_starts_s()
    step_of = np.clip(np.searchsorted(starts, samples["t"], side="right") - 1, 0, len(program.steps) - 1)
    roles = _step_roles(program)
    # the pictures are rendered beside the physics (a second process where there is a spare core)
    recorder = (FrameRecorder(parts, static_bodies, world_from_robot_base, settings.camera, settings.urdf)
                if settings.record_every_s else None)
    with recorder if recorder is not None else contextlib.nullcontext(), BulletClient() as client:
        pb, cid = client.pb, client.client_id
        configure_physics(pb, cid, settings)
        cell = _Cell(client, parts, static_bodies, world_from_robot_base, settings)
        grasps = _planned_grasps(cell, program, roles, {p.name: p for p in parts},
                                 lambda index: q[min(np.searchsorted(samples["t"], starts[index]), len(q) - 1)])
        run = _Run(cell, program.initial_width_m, parts, settings, grasps, recorder)
        settle_motion = run.start(q[0])
        count = len(q)
        report_every = max(1, count // 100)
        current = None
        for k in range(count - 1):
            index = int(step_of[k])
            if index != current:
                if current is not None and isinstance(program.steps[current], GripperStep):
                    run.leave_gripper_step(program.steps[current], roles[current])
                current = index
                if isinstance(program.steps[current], GripperStep):
                    run.enter_gripper_step(program.steps[current], roles[current])
            run.physics_step(q[k + 1], qd[k + 1], roles[current])
            if progress is not None and k % report_every == 0:
                progress(k / count)
        if current is not None and isinstance(program.steps[current], GripperStep):
            run.leave_gripper_step(program.steps[current], roles[current])
        run.settle(q[-1], "settling after the program")
        if recorder is not None:
            recorder.add(run.snapshot())
        results = _part_results(run, settle_motion)
        final_q, opening = tuple(float(v) for v in run.arm_q), _opening(cell)
        simulated_s = run.time_s + settings.settle_s
        frames = recorder.frames() if recorder is not None else []
    if progress is not None:
        progress(1.0)
    contacts = [ContactEvent(e["start_s"], e["end_s"], e["step"], e["body_a"], e["body_b"], max(e["severity"], 0.0))
                for e in run.contacts.events()]
    limits = [LimitEvent(e["start_s"], e["end_s"], e["step"], e["joint"], e["quantity"], e["peak"], e["limit"])
              for e in run.limits.events()]
    return SimulationResult(results, contacts, limits, run.grasp_failures, frames, settings.rate_hz, simulated_s,
                            time.perf_counter() - started, final_q, opening,
                            [n for n, m in settle_motion.items() if m > settings.settle_tolerance_m], run.overlaps)


def _planned_grasps(cell: _Cell, program: Program, roles: Sequence[_StepRole], parts: Mapping[str, SimPart],
                    q_at_step: Callable[[int], np.ndarray]) -> dict[int, Pose]:
    """``tcp_from_part`` the program grasps each part at, by closing step (``id``): the TCP where the program holds
    the arm while it closes (``q_at_step(index)``, forward kinematics) and the part where it starts. Sets the
    arm: call before :meth:`_Run.start`."""
    grasps = {}
    for index, (step, role) in enumerate(zip(program.steps, roles)):
        if isinstance(step, GripperStep) and role.closes and step.part is not None:
            world_from_tcp = cell.panda.forward_tcp(np.asarray(q_at_step(index), dtype=np.float64))
            grasps[id(step)] = world_from_tcp.inverse() @ parts[step.part].world_from_start
    return grasps


def _opening(cell: _Cell) -> float:
    states = cell.pb.getJointStates(cell.robot, cell.panda.fingers, physicsClientId=cell.cid)
    return float(sum(s[0] for s in states))


def _part_results(run: _Run, settle_motion: dict[str, float]) -> list[PartResult]:
    settings, out, symmetries = run.settings, [], {}
    for name, part in run.parts.items():
        final = run.cell.world_from_part(name)
        key = mesh_key(part.mesh)  # identical parts (legs) share their symmetries
        symmetry = symmetries[key] = symmetries.get(key) or part_symmetry(part.mesh)
        position = position_error_m(symmetry, part.world_from_target, final)
        rotation = rotation_error_deg(symmetry, part.world_from_target, final)
        released = run.released_at.get(name)
        moved = None if released is None else float(np.linalg.norm(final.apply(symmetry.centre_m)
                                                                   - released.apply(symmetry.centre_m)))
        offset_m, offset_deg, seated = run.grasp_offsets.get(name, (None, None, False))
        out.append(PartResult(name, final, position, rotation,
                              position <= settings.position_tolerance_m and rotation <= settings.rotation_tolerance_deg,
                              name in run.grasped, tuple(run.fastened[name]), settle_motion[name], moved, offset_m,
                              offset_deg, seated, run.gripped_at.get(name)))
    return out


# --- pictures ---------------------------------------------------------------------------------------------------------
def render_state(parts: Sequence[SimPart], static_bodies: Sequence[StaticBody], world_from_robot_base: Pose,
                 world_from_part: Mapping[str, Pose], arm_q: Sequence[float], opening_m: float = 0.08,
                 camera: CameraConfig = DEFAULT_CAMERA, urdf: str = "franka_panda/panda.urdf") -> np.ndarray:
    """(H, W, 3) uint8 RGB still of the cell with the parts at ``world_from_part`` (parts not named stay at their
    start), the arm at ``arm_q`` (rad) and the fingers ``opening_m`` apart; no physics."""
    half = float(np.clip(opening_m, 0.0, 0.08)) / 2.0
    with CellPictures(parts, static_bodies, world_from_robot_base, urdf) as pictures:
        return pictures.render(CellSnapshot(dict(world_from_part), tuple(float(v) for v in arm_q), (half, half)),
                               camera)


def render_final(result: SimulationResult, parts: Sequence[SimPart], static_bodies: Sequence[StaticBody],
                 world_from_robot_base: Pose, camera: CameraConfig = DEFAULT_CAMERA) -> np.ndarray:
    """The final state of a simulation as one still (see :func:`render_state`)."""
    return render_state(parts, static_bodies, world_from_robot_base,
                        {p.name: p.world_from_final for p in result.parts}, result.final_arm_q,
                        result.final_opening_m, camera)


def write_gif(frames: Sequence[np.ndarray], path: str | Path, fps: float = 10.0) -> Path:
    """Write RGB ``frames`` ((H, W, 3) uint8) as an animated GIF playing at ``fps`` and looping; returns the path."""
    from PIL import Image

    if not frames:
        raise ValueError("no frames to write: simulate with SimSettings(record_every_s=...)")
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    images = [Image.fromarray(np.asarray(f, dtype=np.uint8)) for f in frames]
    images[0].save(path, save_all=True, append_images=images[1:], duration=int(round(1000.0 / fps)), loop=0,
                   optimize=True)
    return path


__all__ = ["ContactEvent", "DEFAULT_CAMERA", "FIXTURE", "GraspFailure", "LimitEvent", "PartResult", "SimPart",
           "SimSettings", "SimulationResult", "StaticBody", "mass_properties", "render_final", "render_state",
           "simulate_program", "write_gif"]
