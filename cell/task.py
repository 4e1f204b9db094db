"""Pick-and-place planning: from an assembly sequence and a kitting layout to a timed robot program.

For every part, in assembly order, the robot

1. moves (OMPL, hand empty) to the pre-grasp above the part lying in the kitting area,
2. approaches in a straight line along the grasp's approach axis (:data:`APPROACH_M`; where no path to the
   pre-grasp is found, from :data:`FARTHER_APPROACH_M` farther back, see :func:`_farther_approach`),
3. closes the gripper on the part,
4. lifts it straight up (:data:`LIFT_M`),
5. moves (OMPL, holding the part) to the pre-place pose, :data:`INSERTION_M` back along the insertion direction
   (where that pose lies between neighbours: to the start of a lead-in along the insertion or across it, see
   :func:`_lead_in`; else the carry's last stretch among the neighbours joins the insertion, see
   :func:`_slot_entry`),
6. inserts it in a straight line along the insertion direction into its target, slowly
   (:data:`INSERTION_SPEED_M_S`; where it slides along a neighbour: held off it, then sideways into contact; see
   :func:`_insertion`),
7. opens the gripper, retreats in a straight line back along the approach axis, and opens to the next grasp
   (where a finger opening wider would meet a placed part there: at the start of the next approach instead).

Finally it returns home. Straight segments are solved by inverse kinematics every :data:`CARTESIAN_STEP_M`
(seeded from the previous point, so the joints move continuously) and checked with the collision model;
the contact end of each straight segment is solved first (with restarts) so that the free end follows it.

Collision worlds (all in the cell's world frame, metres): the table, the jig pads, every pedestal, the parts
still lying in the kitting area, and the parts already placed. What the plan deliberately touches is ignored
for the segment that touches it, and only there: the part being grasped during the approach, the pedestal it
rests on during the lift, its neighbours and pads during the insertion, the released part during the retreat
(the grasp and sequence planners already checked those motions).

Failures raise :class:`TaskPlanningError`, naming the part, the stage and the kind (``no_ik``,
``start_in_collision``, ``goal_in_collision``, ``timeout``, ``straight_line_blocked``).
"""

from __future__ import annotations

import time
from collections.abc import Sequence, Set
from dataclasses import dataclass, field, replace

import numpy as np

from cell.program import GripperStep, MotionStep, Program
from cell.robot import (
    ACCELERATION_LIMITS,
    CARTESIAN_STEP_M,
    JERK_LIMITS,
    VELOCITY_LIMITS,
    IKError,
    IKSettings,
    Panda,
    StraightLineError,
    pose_rng,
)
from planning.collision import ConvexPart, shrunk, signed_distance
from planning.grasp import APPROACH_M, Grasp
from planning.gripper import MAX_OPENING_M
from planning.motion import (
    MotionPlanningError,
    MotionSettings,
    first_invalid_on_line,
    plan_joint_path,
)
from planning.payload import GRAVITY_M_S2, NO_LOAD, JointTorques, MassProperties, carry_limits, flange_load
from planning.pose import Pose
from planning.robot_collision import Collision, RobotCollisionChecker, checking_work_s
from planning.timing import MAX_DEVIATION_RAD, JointLimits, time_path
from planning.validity import AllValid, ClearExceptNearEnds, Validity, dense_path_valid, with_dense_check

LIFT_M = 0.10  # straight lift after grasping, world +z
INSERTION_M = 0.08  # straight insertion along the insertion direction into the target
LEAD_IN_STEPS_M = (0.04, 0.08, 0.16, 0.24)  # farther back it may start, where its pre-place lies between neighbours
# the longest straight way in, lead-in and insertion: a part that stays inside a neighbour it overlaps at its target
# for longer along its insertion cannot be placed, and the sequence stage gives it another direction
LONGEST_WAY_IN_M = INSERTION_M + LEAD_IN_STEPS_M[-1]
# and along the insertion, whose joint path between IK points sags off the straight line by the square of their
# spacing: at 2 cm the TCP strayed 0.3 mm, more than a part fitted between two neighbours has to spare (a quarter
# of a millimetre each side in the simulator), and a drawer's back was pushed into a side at 430 N
INSERTION_STEP_M = 0.005
HELD_MARGIN_M = 0.002  # the held part is checked pulled in by this much, so it may slide along faces it touches
SQUEEZE_M = 0.004  # the closing command asks for this much less than the part's width (force closure)
# a real gripper's grasp holds the part with GRASP_SAFETY times the force friction needs to carry its weight
# (friction coefficient GRASP_FRICTION on both fingers), within the Franka Hand's GRASP_FORCE_RANGE_N
GRASP_SAFETY = 3.0
GRASP_FRICTION = 0.5
GRASP_FORCE_RANGE_N = (20.0, 70.0)
DENSE_CHECK_RAD = 0.004  # joint step of the re-check of planned paths
IK_ATTEMPTS = 6  # IK solutions tried (each with restarts) for a collision-free contact configuration
JOINT_LIMIT_MARGIN_RAD = 0.01  # configurations keep this from the joint limits (timed motions must not touch them)
CARRY_CLEARANCE_M = 0.002  # the carried part is grown by this much on its way to the target ...
TRANSIT_CLEARANCE_M = 0.003  # ... and free-space moves keep this from every obstacle
# a carry that may pass the part's neighbours closer than that keeps the part, as it is (not pulled in by the
# HELD_MARGIN_M it may have near the carry's ends), this far from them away from its ends: table_6's shelf, checked
# pulled in, could pass up to 2 mm into a leg in mid-carry, and met it in the simulator
PASSING_CLEARANCE_M = 0.001
# where no path reaches the pre-grasp (a pocket among the kit's parts and pedestals), the approach starts this much
# farther back along its axis
FARTHER_APPROACH_M = 0.08
# free-space moves and carries keep their clearance except this close (joint-space distance) to an end that lies
# closer than that to something (planning.validity.ClearExceptNearEnds): a retreat ending near a placed part
NEAR_END_RAD = 0.15
# the stages of a part's motions with the hand open for its pick (as wide as the pick's opening, which kitting may
# widen where a board standing between chocks may lean); every later stage is planned the same whatever that opening
PICK_STAGES = frozenset({"move to the pick", "grasp at the pick", "approach to the pick", "approach"})
# the retreat's links and fingers keep this from the parts lying in the kit (the exact check keeps LINK_CLEARANCE_M,
# 1.5 mm, within which PyBullet's link hulls, padded about 1.1 mm, touch a part that settled a little on its pedestal)
RETREAT_KIT_CLEARANCE_M = 0.0025
SLIDE_CLEARANCE_M = 0.004  # a part inserted along a neighbour's face comes down this far off it
SLIDE_SAMPLES = 5  # poses along the insertion where the neighbours it slides along are looked for
SIDE_NORMAL_MAX_COS = 0.3  # a contact normal this close to perpendicular to the insertion is a neighbour's side
HELD_OFF_TOLERANCE_M = 1e-4  # a part held off its neighbour by the slide clearance may sink this far into another
INSERTION_SPEED_M_S = 0.05  # the TCP's top speed (m/s) while a part goes into its target: see _insertion_limits
# the insertion's blends keep this close to its path (joint-space distance; about 0.1 mm at the TCP, whose lever
# is under 0.9 m): a part goes between neighbours with a quarter of a millimetre to spare on each side, and blends
# at the timing's default (MAX_DEVIATION_RAD) carried a cabinet top 0.5 mm sideways off its line between IK points
# 2 cm apart; it caught on a side's edge and tilted 7 degrees. With INSERTION_STEP_M the TCP keeps within 0.04 mm
INSERTION_DEVIATION_RAD = 1e-4
TORQUE_CHECK_HZ = 250.0  # a timed motion's torques are checked at this rate (the simulator steps at 240 Hz)
TORQUE_RETIMINGS = 4  # at most this many slower timings of one motion for its torques
TORQUE_SCALE_MARGIN = 0.9  # each slower timing scales accelerations by this much more than the torques ask
LIMIT_FRACTION = 0.9  # motions are planned at this fraction of the published limits: headroom for tracking
PANDA_LIMITS = JointLimits(LIMIT_FRACTION * VELOCITY_LIMITS, LIMIT_FRACTION * ACCELERATION_LIMITS,
                           LIMIT_FRACTION * JERK_LIMITS)


def timing_limits(panda: Panda) -> JointLimits:
    """The limits motions of ``panda`` are timed within: :data:`LIMIT_FRACTION` of its real arm's published velocity,
    acceleration and jerk limits (``panda.limits``, :mod:`planning.robot_limits`)."""
    arm = panda.limits
    return JointLimits(LIMIT_FRACTION * arm.velocity_rad_s, LIMIT_FRACTION * arm.acceleration_rad_s2,
                       LIMIT_FRACTION * arm.jerk_rad_s3)


def grasp_force_n(mass_kg: float | None) -> float:
    """The force (N) a real gripper grasps a part of ``mass_kg`` with (the largest of the range where unknown)."""
    low, high = GRASP_FORCE_RANGE_N
    if mass_kg is None:
        return high
    return float(np.clip(GRASP_SAFETY * mass_kg * GRAVITY_M_S2 / (2.0 * GRASP_FRICTION), low, high))


class TaskPlanningError(RuntimeError):
    """A pick or place could not be planned. ``kind``: no_ik, start_in_collision, goal_in_collision, timeout,
    straight_line_blocked; ``part`` and ``stage`` name where."""

    def __init__(self, kind: str, part: str, stage: str, message: str) -> None:
        super().__init__(f"part {part!r}, {stage}: {message}")
        self.kind, self.part, self.stage = kind, part, stage
        # set by plan_tasks: the program planned before the part it was planning when this was raised
        self.checkpoint: TaskCheckpoint | None = None


@dataclass(frozen=True)
class PartTask:
    """What the robot does with one part (world frame, metres)."""

    part: str
    world_from_pick: Pose  # where the part lies in the kitting area
    world_from_target: Pose  # where it goes on the jig
    grasp: Grasp  # part frame
    insertion_direction: np.ndarray  # unit, world: the part's motion during insertion
    touches_at_target: tuple[str, ...]  # obstacles it may touch when it arrives (neighbours, its pads)
    pedestal: str  # the obstacle it rests on at the pick (its pedestal, or the board it lies on)
    pick_q_hint: np.ndarray | None = None  # an arm configuration known to reach the grasp (from kitting)
    place_q_hint: np.ndarray | None = None  # ... and the release at the target
    payload: MassProperties | None = None  # the part's mass properties (part frame); None: carried at full speed


# how a part's carry to its target was checked (PlannedTask.carry_check), from the safest to the last resort
CARRY_CHECKS = ("clearance", "clearance except near its ends", "among neighbours", "no clearance")


@dataclass
class PlannedTask:
    """The arm configurations (rad) at one part's grasp and at its release, and how the carry between them was
    checked (one of :data:`CARRY_CHECKS`): ``clearance``, the part grown by :data:`CARRY_CLEARANCE_M` and
    :data:`TRANSIT_CLEARANCE_M` from everything; where an end of the carry lies closer than that to something, the
    part as it is (or pulled in by :data:`HELD_MARGIN_M`) and :data:`TRANSIT_CLEARANCE_M` from everything except
    within :data:`NEAR_END_RAD` of the ends (``clearance except near its ends``), else from everything but the
    parts it touches at its target, which the part as it is passes :data:`PASSING_CLEARANCE_M` off away from the
    ends (``among neighbours``); ``no clearance``, the part as it is (or pulled in), from everything, which the part
    as it is passes :data:`PASSING_CLEARANCE_M` off away from the ends (where those searches failed)."""

    part: str
    grasp_q: np.ndarray
    place_q: np.ndarray
    carry_check: str = CARRY_CHECKS[0]


@dataclass
class TaskPlan:
    program: Program
    parts: list[PlannedTask] = field(default_factory=list)


@dataclass(frozen=True)
class TaskCheckpoint:
    """The program as planned up to ``part``'s task, not including it: where :func:`plan_tasks` picks up for a
    task list that starts with the same tasks (``parts_before``), e.g. with another grasp of ``part``.
    ``world_from_parts``: every loose part (world frame: those placed at their targets, the rest at their picks);
    ``q`` (rad): the arm after the last retreat."""

    part: str
    parts_before: tuple[str, ...]
    steps: tuple
    planned: tuple[PlannedTask, ...]
    world_from_parts: dict[str, Pose]
    q: np.ndarray


class CellWorld:
    """Named convex obstacles of the cell (world frame) and the robot's collision and IK models.

    ``static``: name -> (ConvexPart, world_from_obstacle) that never move (table, pads, pedestals);
    ``parts``: name -> ConvexPart of the loose parts, whose poses change as they are placed.
    """

    def __init__(self, panda: Panda, world_from_base: Pose, static: dict[str, tuple[ConvexPart, Pose]],
                 parts: dict[str, ConvexPart], rng: np.random.Generator,
                 motion: MotionSettings | None = None, payloads: dict[str, MassProperties] | None = None) -> None:
        self.panda = panda
        self.payloads = dict(payloads or {})  # part -> its mass properties: held, its weight must be held too
        self._load: JointTorques | None = None
        self._arm_torques: JointTorques | None = None
        self.static = static
        self.parts = parts
        # IK restarts are drawn per target pose from this seed (cell.robot.pose_rng), not from a shared stream
        self.ik_seed = int(rng.integers(2**31))
        self.motion = motion or MotionSettings()
        self.part_poses: dict[str, Pose] = {}
        self.checker = RobotCollisionChecker(world_from_base.matrix(), {})
        # free-space moves keep TRANSIT_CLEARANCE_M from every obstacle (the simulator's and a real robot's
        # geometry is a little larger than the planning model); moves into contact use the exact one
        self.transit_checker = RobotCollisionChecker(world_from_base.matrix(), {})
        # the held part as it is, grown by PASSING_CLEARANCE_M, whatever its margin (see _among_neighbours_validity),
        # on top of a check of the robot: seldom needed, so its world is brought up to date only when it is
        self.passing_checker = RobotCollisionChecker(world_from_base.matrix(), {}, held_only=True)
        self._obstacles: dict[str, tuple[ConvexPart, np.ndarray]] = {}
        self._passing_obstacles: dict[str, tuple[ConvexPart, np.ndarray]] | None = None
        self._held: tuple[str | None, Grasp | None, float] = (None, None, 0.0)  # part, grasp, opening
        # the retreat keeps RETREAT_KIT_CLEARANCE_M from the parts in the kit (see kit_validity)
        self.kit_checker = RobotCollisionChecker(world_from_base.matrix(), {},
                                                 link_clearance_m=RETREAT_KIT_CLEARANCE_M,
                                                 finger_clearance_m=RETREAT_KIT_CLEARANCE_M)
        self.ik_settings = IKSettings()
        self._grown_cache: dict[tuple, ConvexPart] = {}
        self.timing_seconds = 0.0  # spent in Ruckig timing and its collision re-checks

    # --- world state ------------------------------------------------------------------------------------------
    def set_part_poses(self, poses: dict[str, Pose]) -> None:
        """Where every loose part is now (parts not named are absent, e.g. the one in the hand)."""
        self.part_poses = dict(poses)
        obstacles = {name: (part, pose.matrix()) for name, (part, pose) in self.static.items()}
        obstacles.update({name: (self.parts[name], pose.matrix()) for name, pose in self.part_poses.items()})
        self.checker.set_obstacles(obstacles)
        self._obstacles = obstacles
        self.transit_checker.set_obstacles({name: (self._grown(name, part), pose)
                                            for name, (part, pose) in obstacles.items()})

    def _grown(self, name: str, part: ConvexPart, by_m: float = TRANSIT_CLEARANCE_M) -> ConvexPart:
        key = (name, id(part), by_m)
        if key not in self._grown_cache:
            self._grown_cache[key] = shrunk(part, -by_m)
        return self._grown_cache[key]

    def passing_validity(self):
        """``q -> bool``: the part in the hand (as :meth:`hold` put it there) as it is, grown by
        :data:`PASSING_CLEARANCE_M`, clear of everything where it lies now. Neither the robot nor the held weight is
        checked: combine it with a check that does (:func:`_among_neighbours_validity`). The world and the hold are
        taken as they are when this is called."""
        if self._passing_obstacles is not self._obstacles:
            self.passing_checker.set_obstacles(self._obstacles)
            self._passing_obstacles = self._obstacles
        part, grasp, opening_m = self._held
        if part is None:
            self.passing_checker.hold(None, opening_m=opening_m)
        else:
            self.passing_checker.hold(self._grown(part, self.parts[part], PASSING_CLEARANCE_M),
                                      grasp.part_from_tcp.inverse().matrix(), opening_m=opening_m)
        return Validity(self.passing_checker, frozenset())

    def validity(self, ignore: frozenset[str] = frozenset(), transit: bool = False,
                 held_ignore: frozenset[str] = frozenset(), hand_ignore: frozenset[str] = frozenset()):
        """``q -> bool`` against the current world, skipping the obstacles named in ``ignore``, for the held part
        only those in ``held_ignore`` (the robot must still clear them), and for the hand, fingers and held part
        those in ``hand_ignore`` (the arm's links must still clear them); ``transit``: with every obstacle grown
        by :data:`TRANSIT_CLEARANCE_M`. While a part is held, a configuration must also hold its weight."""
        return Validity(self.transit_checker if transit else self.checker, ignore, held_ignore, self._load,
                        hand_ignore)

    def kit_validity(self, in_kit: frozenset[str]):
        """``q -> bool``: the empty hand, opened as it is now, and the arm keep :data:`RETREAT_KIT_CLEARANCE_M` from
        the parts ``in_kit`` where they lie now (nothing else is checked; valid until the next call)."""
        self.kit_checker.set_obstacles({name: (self.parts[name], self.part_poses[name].matrix())
                                        for name in sorted(in_kit) if name in self.part_poses})
        self.kit_checker.hold(None, opening_m=self.checker.opening_m)
        return Validity(self.kit_checker, frozenset())

    def hold(self, part: str | None, grasp: Grasp | None, opening_m: float,
             margin_m: float = HELD_MARGIN_M) -> None:
        """Put ``part`` in the hand at ``grasp`` (its geometry pulled in by ``margin_m``; negative: grown), or
        empty the hand; the fingers open to ``opening_m``."""
        for checker in (self.checker, self.transit_checker):
            if part is None:
                checker.hold(None, opening_m=opening_m)
            else:
                held = shrunk(self.parts[part], margin_m)
                checker.hold(held, grasp.part_from_tcp.inverse().matrix(), opening_m=opening_m)
        self._held = (part, grasp, opening_m)
        self._load = None
        if part is not None and part in self.payloads:
            self._load = JointTorques(self.checker, self.payloads[part], grasp.part_from_tcp.inverse())

    def torques(self) -> JointTorques:
        """The joint-torque model of the arm as it is now: with the held part's load, or the empty hand's."""
        if self._load is not None:
            return self._load
        if self._arm_torques is None:
            self._arm_torques = JointTorques(self.checker)
        return self._arm_torques

    # --- kinematics -------------------------------------------------------------------------------------------
    def solve_ik(self, world_from_tcp: Pose, seed_q: np.ndarray, valid, part: str, stage: str,
                 hint_q: np.ndarray | None = None) -> np.ndarray:
        """A collision-free IK solution at least :data:`JOINT_LIMIT_MARGIN_RAD` inside the joint limits: ``hint_q``
        if it is one, else the one nearest ``seed_q`` first (a release from kitting's hint 6 mrad inside joint 7's
        limit went past it in the simulator as the arm lowered a cabinet's 3 kg top). Where none is found, the
        message says why ``hint_q`` (kitting's configuration) was not taken."""
        hint_refused = ""  # why the hint was not taken, for the message where no solution is found either
        if hint_q is not None:
            if not self.panda.within_limits(hint_q, JOINT_LIMIT_MARGIN_RAD):
                hint_refused = "kitting's configuration for it lies on a joint limit"
            elif not valid(hint_q):
                hint_refused = f"kitting's configuration for it collides ({self._collision_words(hint_q, valid)})"
            else:
                reached, angle = self.panda.forward_tcp(hint_q).distance(world_from_tcp)
                if reached <= self.ik_settings.position_tolerance_m and angle <= self.ik_settings.angle_tolerance_rad:
                    return np.asarray(hint_q, dtype=np.float64)
                hint_refused = f"kitting's configuration for it misses the pose by {reached * 1000:.1f} mm"
        last_error = "no solution"
        collided = None
        rng = pose_rng(world_from_tcp, self.ik_seed)
        for attempt in range(IK_ATTEMPTS):
            try:
                q = self.panda.inverse_tcp(world_from_tcp, rng, seed_q=seed_q if attempt == 0 else None,
                                           settings=self.ik_settings)
            except IKError as exc:
                last_error = str(exc)
                continue
            if not self.panda.within_limits(q, JOINT_LIMIT_MARGIN_RAD):
                last_error = "the solution lies on a joint limit"
                continue
            if valid(q):
                return q
            collided = collided or self._collision_words(q, valid)
        refused = f"; {hint_refused}" if hint_refused else ""
        if collided:
            raise TaskPlanningError("goal_in_collision", part, stage,
                                    f"every inverse-kinematics solution for the TCP at {world_from_tcp} collides "
                                    f"or cannot hold the part (first: {collided}){refused}")
        raise TaskPlanningError("no_ik", part, stage, last_error + refused)

    def straight_line(self, q_contact: np.ndarray, world_from_tcp_contact: Pose, offset_world: np.ndarray,
                      valid, part: str, stage: str, step_m: float = CARTESIAN_STEP_M) -> np.ndarray:
        """Joint waypoints (K, 7) from the contact configuration out to the TCP moved by ``offset_world`` (m),
        keeping the orientation (:meth:`cell.robot.Panda.tcp_line`), each segment between them ``valid``. A
        collision before the point where the line fails inverse kinematics is the one reported."""
        distance = float(np.linalg.norm(offset_world))
        steps = max(1, int(np.ceil(distance / step_m)))
        try:
            path, failure = self.panda.tcp_line(q_contact, world_from_tcp_contact, offset_world, self.ik_seed,
                                                step_m), None
        except StraightLineError as exc:
            path, failure = exc.path, exc
        for k in range(1, len(path)):
            blocked = first_invalid_on_line(valid, path[k - 1], path[k])
            if blocked is not None:
                raise TaskPlanningError("straight_line_blocked", part, stage,
                                        f"the straight {distance * 100:.0f} cm segment collides "
                                        f"{distance * 100 * (k - 1) / steps:.0f} cm "
                                        f"along ({self._collision_words(blocked, valid)})")
        if failure is not None:
            raise TaskPlanningError("no_ik", part, stage, str(failure)) from failure
        return path

    def clearance_shift(self, part: str, task: PartTask) -> np.ndarray:
        """Where the part slides along a placed neighbour's side on its way into the target, a sideways offset (m,
        world) of :data:`SLIDE_CLEARANCE_M` away from that neighbour: the part comes down held off it and moves
        into contact only at the end of its insertion (:func:`_insertion`), as a guarded move would. A neighbour
        counts when the part passes within :data:`SLIDE_CLEARANCE_M` of it anywhere along the insertion (checked
        at :data:`SLIDE_SAMPLES` poses from the pre-place pose to the target) with a contact normal within
        :data:`SIDE_NORMAL_MAX_COS` of perpendicular to the insertion (what the part lands on does not count; the
        jig's pad it is slid sideways over does, and the parts it is fitted into at its target do not).
        Sliding down a neighbour's face 0.25 mm off it, the simulated part caught on its edge and twisted in the
        hand by 18-65 degrees (chairs' side stretchers against the middle stretcher they butt onto). Neighbours on
        opposite sides (a slot) cancel: the part then comes straight down the middle. No offset where the part held
        off would run into a neighbour (:meth:`_held_off_blocked`): four splayed legs in the sockets of a table top
        pushed it off sideways, and the top came down 4 mm off and sat on their ends 13 mm high
        (table_jokkmokk_0694)."""
        direction = task.insertion_direction
        samples = [Pose(task.world_from_target.position - direction * INSERTION_M * fraction,
                        task.world_from_target.quat_wxyz) for fraction in np.linspace(1.0, 0.0, SLIDE_SAMPLES)]
        fitted = self._fitted(part, task.world_from_target)
        # the placed parts, and the jig's pads the part lands on: slid sideways over its pad (chair_ivar_0668's
        # side pushed onto the seat's tenons), a part comes in held above it and is set down at the end
        neighbours = {n: (convex, pose) for n, (convex, pose) in self.static.items()
                      if n.startswith("pad ") and n in task.touches_at_target}
        neighbours.update((n, (self.parts[n], pose)) for n, pose in self.part_poses.items()
                          if n != part and n not in fitted)
        away, seen = np.zeros(3), set()
        for pose in samples:
            for other, (other_convex, other_pose) in neighbours.items():
                if other in seen:
                    continue
                result = signed_distance(other_convex, other_pose, self.parts[part], pose,
                                         cutoff_m=SLIDE_CLEARANCE_M)
                if not (result.measured and result.distance_m < SLIDE_CLEARANCE_M and result.normal_ab is not None):
                    continue
                normal = np.asarray(result.normal_ab, dtype=np.float64)
                if abs(float(normal @ direction)) > SIDE_NORMAL_MAX_COS:
                    continue
                seen.add(other)
                sideways = normal - float(normal @ direction) * direction
                away += sideways / np.linalg.norm(sideways)
        norm = float(np.linalg.norm(away))
        if norm <= 1e-6:
            return np.zeros(3)
        shift = away / norm * SLIDE_CLEARANCE_M
        return np.zeros(3) if self._held_off_blocked(part, samples, shift, fitted) else shift

    def _fitted(self, part: str, world_from_target: Pose) -> set[str]:
        """The placed parts that ``part`` overlaps at its target by more than :data:`HELD_OFF_TOLERANCE_M` (a
        tenon drawn into its neighbour): the simulation lets them fit, without contact between them, from its
        insertion on, so they neither guide nor block it."""
        fitted = set()
        for other, other_pose in self.part_poses.items():
            if other == part:
                continue
            result = signed_distance(self.parts[other], other_pose, self.parts[part], world_from_target, cutoff_m=0.0)
            if result.measured and result.distance_m < -HELD_OFF_TOLERANCE_M:
                fitted.add(other)
        return fitted

    def _held_off_blocked(self, part: str, samples: Sequence[Pose], shift_m: np.ndarray,
                          fitted: Set[str] = frozenset()) -> bool:
        """Whether ``part`` at any of the insertion poses ``samples``, moved by ``shift_m`` (world, m), sinks more
        than :data:`HELD_OFF_TOLERANCE_M` into a placed part (one it lands on included: shifted across a slanted
        face it would sink into it) other than those it is ``fitted`` into at its target."""
        for pose in samples:
            shifted = Pose(pose.position + shift_m, pose.quat_wxyz)
            for other, other_pose in self.part_poses.items():
                if other == part or other in fitted:
                    continue
                result = signed_distance(self.parts[other], other_pose, self.parts[part], shifted, cutoff_m=0.0)
                if result.measured and result.distance_m < -HELD_OFF_TOLERANCE_M:
                    return True
        return False

    def _collision_words(self, q: np.ndarray, valid=None) -> str:
        """The first collision at ``q`` as ``valid`` (a :class:`Validity`) sees it: its checker, skipping what it
        ignores; the exact world when ``valid`` is something else."""
        if isinstance(valid, AllValid):  # the first of its checks that refuses q
            refusing = next((check for check in valid.checks if not check(q)), None)
            return "no collision there" if refusing is None else self._collision_words(q, refusing)
        load = valid.load if isinstance(valid, Validity) else None
        if load is not None and not load.within(np.asarray(q, dtype=np.float64)[None])[0]:
            return load.words(q)
        hit = self._first_collision(q, valid)
        return "no collision there" if hit is None else str(hit)

    def _first_collision(self, q: np.ndarray, valid=None) -> Collision | None:
        """The first colliding pair at ``q`` as ``valid`` (a :class:`Validity`) sees it (the exact world when
        ``valid`` is something else), the arm's load aside."""
        checker, ignore, held_ignore, hand_ignore = (
            (valid.checker, valid.ignore, valid.held_ignore, valid.hand_ignore) if isinstance(valid, Validity)
            else (self.checker, frozenset(), frozenset(), frozenset()))
        return checker.first_collision(np.asarray(q, dtype=np.float64), ignore=ignore, held_ignore=held_ignore,
                                       hand_ignore=hand_ignore)

    def transit(self, start_q: np.ndarray, goal_q: np.ndarray, valid, part: str, stage: str) -> np.ndarray:
        """An OMPL path, re-checked every :data:`DENSE_CHECK_RAD` (OMPL checks its edges at its resolution, or
        ``valid.segment`` at its spacing, and either can step over a thin overlap); a path that fails is planned
        again with a finer resolution, and with the re-check among the checks of every edge (else the straight
        line from start to goal, which the edge check passed, would be planned again: table_klubbo_0743's return
        home passed a finger 2 mm into a part's clearance between two of ``segment``'s samples, three times)."""
        settings = self.motion
        segment = getattr(valid, "segment", None)
        # the search keeps off the joint limits (its own ends may lie closer, where inverse kinematics put them)
        lower = np.minimum(self.panda.lower_limits + JOINT_LIMIT_MARGIN_RAD, np.minimum(start_q, goal_q))
        upper = np.maximum(self.panda.upper_limits - JOINT_LIMIT_MARGIN_RAD, np.maximum(start_q, goal_q))
        for _ in range(3):
            try:
                path = plan_joint_path(valid, start_q, goal_q, lower, upper, settings, segment_valid=segment,
                                       work=checking_work_s)
            except MotionPlanningError as exc:
                raise TaskPlanningError(exc.kind, part, stage, str(exc)) from exc
            if dense_path_valid(valid, path, DENSE_CHECK_RAD):
                return path
            settings = replace(settings, check_resolution=settings.check_resolution / 4)
            if segment is not None:
                segment = with_dense_check(valid, DENSE_CHECK_RAD)
        raise TaskPlanningError("timeout", part, stage, "every planned path grazes an obstacle between OMPL's checks")


def _approach_to_pick(world: CellWorld, task: PartTask, q: np.ndarray):
    """(grasp configuration, straight approach path ending there, the validity they were checked with) for
    ``task``'s pick. The arm keeps :data:`TRANSIT_CLEARANCE_M` from the neighbouring kitting parts where it can (a
    link passing a neighbour board 0.1 mm off in this model touches it in the simulator), else it comes as close
    as the exact check allows. The hand is not checked against the part and its pedestal (the grasp planner
    checked it against them); the arm's links are (a wrist passing low over a table top knocked it off its
    pedestal)."""
    name, beside = task.part, frozenset({task.part, task.pedestal})
    tcp_pick = task.world_from_pick @ task.grasp.part_from_tcp
    back = -tcp_pick.rotation[:, 2] * APPROACH_M
    failure = None  # the exact check's, when both fail
    for transit in (True, False):
        valid = world.validity(transit=transit, hand_ignore=beside)
        try:
            grasp_q = world.solve_ik(tcp_pick, q, valid, name, "grasp at the pick", hint_q=task.pick_q_hint)
            approach = world.straight_line(grasp_q, tcp_pick, back, valid, name, "approach to the pick")[::-1]
            return grasp_q, approach, valid
        except TaskPlanningError as exc:
            failure = exc
    raise failure


def _farther_approach(world: CellWorld, task: PartTask, approach_path: np.ndarray, valid) -> np.ndarray | None:
    """``approach_path`` (joint waypoints (K, 7) from the pre-grasp to the grasp) extended :data:`FARTHER_APPROACH_M`
    farther back along the grasp's approach axis, the extension checked as the approach was (``valid``, the hand
    opened for the pick); None where that line is blocked or leaves the reachable space. A pre-grasp low among the
    kit's parts and pedestals can lie in a pocket of joint space that a search seldom enters: 5% of the
    configurations within 0.2 rad of bookcase_expedit_0373's part_01's pre-grasp were free (its hand between the
    table, a pedestal and two parts), 21% of those 8 cm farther back, and its move to the pick failed two 5 s
    searches."""
    tcp_pick = task.world_from_pick @ task.grasp.part_from_tcp
    back = -tcp_pick.rotation[:, 2]
    tcp_pre = Pose(tcp_pick.position + back * APPROACH_M, tcp_pick.quat_wxyz)
    world.hold(None, None, task.grasp.opening_at_pick_m)
    try:
        line = world.straight_line(approach_path[0], tcp_pre, back * FARTHER_APPROACH_M, valid, task.part,
                                   "approach to the pick")
    except TaskPlanningError:
        return None
    return np.concatenate([line[::-1], approach_path[1:]])


def _among_neighbours_validity(world: CellWorld, task: PartTask, exact, ends: tuple[np.ndarray, ...],
                               off_neighbours: bool = False):
    """Validity for a carry whose ends lie closer to the part's neighbours than the carry clearance: ``exact``
    (the part held as it is, or pulled in by :data:`HELD_MARGIN_M`) everywhere, and the transit clearance from
    everything but the parts ``task``'s part touches at its target (``off_neighbours``: from those too), except
    within :data:`NEAR_END_RAD` of the ``ends`` (see :class:`ClearExceptNearEnds`; the hold must stay as it is
    while it is used). Away from the ends the part, as it is, keeps :data:`PASSING_CLEARANCE_M` from its neighbours
    too."""
    clear = world.validity(transit=True, ignore=frozenset() if off_neighbours else frozenset(task.touches_at_target))
    if off_neighbours:
        return ClearExceptNearEnds(AllValid(clear, exact), exact, ends, NEAR_END_RAD)
    return ClearExceptNearEnds(AllValid(clear, exact, world.passing_validity()), exact, ends, NEAR_END_RAD)


def _no_clearance_validity(world: CellWorld, exact, ends: tuple[np.ndarray, ...]):
    """Validity for a carry's last resort: ``exact`` (the part held as it is, or pulled in by
    :data:`HELD_MARGIN_M`) everywhere, and away from the ``ends`` (beyond :data:`NEAR_END_RAD`) the part as it is
    keeps :data:`PASSING_CLEARANCE_M` from everything, as :func:`_among_neighbours_validity` has it pass its
    neighbours. Checked pulled in all the way, the procedural table_6's shelf, carried this way past a leg it touches
    at its target once its searches were seeded per query, could have passed up to 2 mm into it in mid-carry."""
    return ClearExceptNearEnds(AllValid(exact, world.passing_validity()), exact, ends, NEAR_END_RAD)


def _retreat_validity(world: CellWorld, placed: str, in_kit: frozenset[str]):
    """Validity for the retreat of the open hand from ``placed``, just released: the exact check (the fingers may
    pass close to it and to its neighbours on the jig), and :data:`RETREAT_KIT_CLEARANCE_M` from the parts still
    in the kit (``in_kit``): cabinet_17's shelf_1 retreated 1.5-2 mm from side_left lying in the kit, and link 6
    grazed it in the simulator. (The transit clearance, 3 mm on top of the exact check's, was too much: a chair's
    stretcher retreating 3-3.5 mm from a part in the kit had no other grasp.)"""
    return AllValid(world.validity(hand_ignore=frozenset({placed})), world.kit_validity(in_kit))


def _free_space_validity(world: CellWorld, start_q: np.ndarray, goal_q: np.ndarray):
    """Validity for a move of the empty hand from ``start_q`` to ``goal_q``: with the transit clearance, relaxed
    near an end that lies closer than that to something (see :class:`ClearExceptNearEnds`)."""
    clear = world.validity(transit=True)
    if clear(start_q) and clear(goal_q):
        return clear
    return ClearExceptNearEnds(clear, world.validity(), (start_q, goal_q), NEAR_END_RAD)


def _timed(world: CellWorld, path: np.ndarray, valid, part: str, stage: str,
           limits: JointLimits | None = None, stops: Sequence[int] = (),
           max_deviation_rad: float = MAX_DEVIATION_RAD):
    """Time a joint path with Ruckig within ``limits`` (default: :func:`timing_limits` of the arm) and the joints'
    position limits, at rest at the waypoints
    indexed by ``stops``, its blends within ``max_deviation_rad`` of the path (adds the seconds spent to
    ``world.timing_seconds``)."""
    started = time.perf_counter()
    limits = timing_limits(world.panda) if limits is None else limits
    kept = _kept(path)
    path = np.asarray(path)[kept]
    stops = [kept.index(k) for k in stops if k in kept and 0 < kept.index(k) < len(kept) - 1]
    if len(path) < 2:
        path = np.stack([path[0], path[0] + 1e-9])
    def timed_within(limits: JointLimits):
        return time_path(path, limits, is_valid=valid, first_invalid=getattr(valid, "first_invalid", None),
                         position_limits=(world.panda.lower_limits, world.panda.upper_limits), stops=stops,
                         max_deviation_rad=max_deviation_rad)

    try:
        timed = timed_within(limits)
        torques = world.torques()
        for _ in range(TORQUE_RETIMINGS):  # slower where the arm and its load need more torque than they have
            times = np.append(np.arange(0.0, timed.duration, 1.0 / TORQUE_CHECK_HZ), timed.duration)
            scale = torques.motion_scale(*timed.at_times(times))
            if scale >= 1.0:
                break
            limits = limits.slowed(float(np.sqrt(TORQUE_SCALE_MARGIN * scale)))
            timed = timed_within(limits)
        return timed
    except ValueError as exc:
        raise TaskPlanningError("straight_line_blocked", part, stage, str(exc)) from exc
    finally:
        world.timing_seconds += time.perf_counter() - started


def _kept(path: np.ndarray) -> list[int]:
    """Indices of the waypoints of ``path`` that differ from the one before (repeats dropped)."""
    return [0] + [k for k in range(1, len(path)) if np.max(np.abs(path[k] - path[k - 1])) > 1e-7]


def plan_tasks(world: CellWorld, tasks: list[PartTask], home_q: np.ndarray,
               progress=None, deadline: float = float("inf"), resume: TaskCheckpoint | None = None) -> TaskPlan:
    """The whole program: every part of ``tasks`` picked and placed in order, then home.

    ``progress(fraction)`` is called after each part; past ``deadline`` (``time.thread_time()``) it gives up.
    A :class:`TaskPlanningError` carries the checkpoint before the part it failed on (``checkpoint``); given as
    ``resume`` with a task list that starts with the same tasks, planning picks up there (the parts before it are
    not planned again).
    """
    checkpoints: list[TaskCheckpoint] = []
    try:
        return _plan_tasks(world, tasks, home_q, progress, deadline, resume, checkpoints)
    except TaskPlanningError as exc:
        if checkpoints and checkpoints[-1].part == exc.part:
            exc.checkpoint = checkpoints[-1]
        raise


def _plan_tasks(world: CellWorld, tasks: list[PartTask], home_q: np.ndarray, progress, deadline: float,
                resume: TaskCheckpoint | None, checkpoints: list[TaskCheckpoint]) -> TaskPlan:
    program = Program(initial_width_m=tasks[0].grasp.opening_at_pick_m if tasks else MAX_OPENING_M,
                      robot=world.panda.limits.model)
    if resume is None:
        first = 0
        plan = TaskPlan(program)
        poses = {t.part: t.world_from_pick for t in tasks}
        q = np.asarray(home_q, dtype=np.float64)
    else:
        first = len(resume.parts_before)
        if tuple(t.part for t in tasks[:first]) != resume.parts_before or tasks[first].part != resume.part:
            raise ValueError(f"the checkpoint before {resume.part!r} is not one of these tasks")
        program.steps = list(resume.steps)
        plan = TaskPlan(program, list(resume.planned))
        poses = dict(resume.world_from_parts)
        q = np.array(resume.q, dtype=np.float64)
        if progress is not None:
            progress(first / len(tasks))
    world.set_part_poses(poses)

    def add_motion(part: str, label: str, path: np.ndarray, valid, held: str | None,
                   limits: JointLimits | None = None) -> None:
        program.steps.append(MotionStep(f"{part}: {label}", _timed(world, path, valid, part, label, limits), held))

    opening = program.initial_width_m
    arm_limits = timing_limits(world.panda)
    for index in range(first, len(tasks)):
        task = tasks[index]
        name, grasp = task.part, task.grasp
        checkpoints.append(TaskCheckpoint(name, tuple(t.part for t in tasks[:index]), tuple(program.steps),
                                          tuple(plan.parts), dict(poses), q.copy()))
        if index:  # the fingers open for this pick where they can, after the last retreat
            opening = _opening_after_retreat(world, program, q, tasks[index - 1].grasp.opening_m,
                                             grasp.opening_at_pick_m, "open for the next part")
        # a heavy part is carried slower (the wrist's torque, planning/payload.py)
        carrying = arm_limits if task.payload is None else carry_limits(arm_limits, task.payload,
                                                                          grasp.part_from_tcp)
        if time.thread_time() > deadline:
            raise TaskPlanningError("timeout", name, "planning", "the planning time budget ran out")
        # --- pick ------------------------------------------------------------------------------------------
        # the approach is checked with the hand open for the pick; where it could not open that wide after the
        # last retreat (a finger would meet a placed part there), it moves there as it is and opens at the start
        # of the approach, which kitting checked clear with the pick's opening
        world.hold(None, None, grasp.opening_at_pick_m)
        tcp_pick = task.world_from_pick @ grasp.part_from_tcp
        grasp_q, approach_path, valid = _approach_to_pick(world, task, q)
        world.hold(None, None, opening)
        free = _free_space_validity(world, q, approach_path[0])
        try:
            to_pick = world.transit(q, approach_path[0], free, name, "move to the pick")
        except TaskPlanningError as exc:
            farther = _farther_approach(world, task, approach_path, valid) if exc.kind == "timeout" else None
            if farther is None:
                raise
            approach_path = farther
            world.hold(None, None, opening)
            free = _free_space_validity(world, q, approach_path[0])
            to_pick = world.transit(q, approach_path[0], free, name, "move to the pick")
        add_motion(name, "move to the pick", to_pick, free, None)
        if opening < grasp.opening_at_pick_m - 1e-6:
            program.steps.append(GripperStep(f"open for {name}", grasp.opening_at_pick_m, None))
            opening = grasp.opening_at_pick_m
        add_motion(name, "approach", approach_path, valid, None)
        program.steps.append(GripperStep(
            f"{name}: close", max(0.0, grasp.width_m - SQUEEZE_M), name, kind="grasp", grasp_width_m=grasp.width_m,
            force_n=grasp_force_n(None if task.payload is None else task.payload.mass_kg),
            load=None if task.payload is None else flange_load(task.payload, grasp.part_from_tcp)))
        # --- carry -----------------------------------------------------------------------------------------
        del poses[name]
        world.set_part_poses(poses)
        world.hold(name, grasp, grasp.width_m)
        valid = world.validity(hand_ignore=frozenset({task.pedestal}))
        lift = world.straight_line(grasp_q, tcp_pick, np.array([0.0, 0.0, LIFT_M]), valid, name, "lift")
        add_motion(name, "lift", lift, valid, name, carrying)
        tcp_place = task.world_from_target @ grasp.part_from_tcp
        # the part arrives touching its neighbours and pads; the arm and fingers must still clear them
        valid_insert = world.validity(held_ignore=frozenset(task.touches_at_target))
        place_q = world.solve_ik(tcp_place, lift[-1], valid_insert, name, "release at the target",
                                 hint_q=task.place_q_hint)
        insertion, corner = _insertion(world, place_q, tcp_place, task.insertion_direction,
                                       world.clearance_shift(name, task), valid_insert, name)
        # carry with the part grown by a margin (clear of everything by more than the simulator's contact slop);
        # where the pre-place pose already lies between neighbours, the insertion starts farther back, where the
        # part is clear (a drawer's back between its sides), or else the carry checks the part as it is (or pulled
        # in) and keeps the transit clearance from everything but the neighbours it touches at its target, except
        # near its ends: planned with no clearance at all, a drawer front carried past the kit pushed the
        # cabinet's top lying there 4-5 mm off its pedestal (the simulator's contacts act before bodies touch)
        carry_margin_m = -CARRY_CLEARANCE_M
        world.hold(name, grasp, grasp.width_m, margin_m=carry_margin_m)
        valid = world.validity(transit=True)
        if not valid(insertion[0]) and valid(lift[-1]):
            found = _lead_in(world, name, grasp, insertion[0], task.insertion_direction, valid, valid_insert)
            if found is not None:
                lead_in, sideways = found
                insertion = np.concatenate([lead_in, insertion[1:]])
                corner = (((len(lead_in) - 1,) if sideways else ())  # it turns into the insertion there
                          + tuple(k + len(lead_in) - 1 for k in corner))
        if not valid(insertion[0]) or not valid(lift[-1]):
            carry_margin_m = 0.0  # as it is, if its ends allow
            world.hold(name, grasp, grasp.width_m, margin_m=carry_margin_m)
            valid = world.validity()
            if not valid(insertion[0]) or not valid(lift[-1]):
                carry_margin_m = HELD_MARGIN_M
                world.hold(name, grasp, grasp.width_m, margin_m=carry_margin_m)
                valid = world.validity()
            if not valid(insertion[0]):
                raise TaskPlanningError("goal_in_collision", name, "move to the target", "the pre-place "
                                        f"configuration collides ({world._collision_words(insertion[0], valid)})"
                                        + _still_inside_words(world, name, task, insertion[0], valid))
            # the clearance from everything away from the carry's ends, then from all but the part's neighbours
            # (table_6's shelf, carried past a leg it touches at its target with none, met it 0.013 mm deep in
            # simulation), then none
            exact = valid
            checks = [(CARRY_CHECKS[1], _among_neighbours_validity(world, task, exact, (lift[-1], insertion[0]),
                                                                   off_neighbours=True)),
                      (CARRY_CHECKS[2], _among_neighbours_validity(world, task, exact, (lift[-1], insertion[0]))),
                      (CARRY_CHECKS[3], _no_clearance_validity(world, exact, (lift[-1], insertion[0])))]
            for k, (check_name, check) in enumerate(checks):
                try:
                    carry = world.transit(lift[-1], insertion[0], check, name, "move to the target")
                except TaskPlanningError:
                    if k == len(checks) - 1:
                        raise
                    continue
                carry_check, valid = check_name, check
                break
        else:
            carry_check = CARRY_CHECKS[0]
            carry = world.transit(lift[-1], insertion[0], valid, name, "move to the target")
        carry, entry = _slot_entry(world, name, grasp, carry)
        if len(entry) > 1:  # the carry's end lies among neighbours: entered like the insertion, which it joins
            insertion = np.concatenate([entry, insertion[1:]])
            corner = (len(entry) - 1,) + tuple(k + len(entry) - 1 for k in corner)
        world.hold(name, grasp, grasp.width_m, margin_m=carry_margin_m)
        add_motion(name, "move to the target", carry, valid, name, carrying)
        world.hold(name, grasp, grasp.width_m)
        program.steps.append(MotionStep(f"{name}: insert",
                                        _timed_insertion(world, insertion, valid_insert, name, carrying, corner), name))
        # --- release ---------------------------------------------------------------------------------------
        program.steps.append(GripperStep(f"{name}: open", grasp.opening_m, name,
                                         load=None if task.payload is None else NO_LOAD))
        poses[name] = task.world_from_target
        world.set_part_poses(poses)
        world.hold(None, None, grasp.opening_m)
        valid = _retreat_validity(world, name, frozenset(t.part for t in tasks[index + 1:]))
        retreat = world.straight_line(place_q, tcp_place, -tcp_place.rotation[:, 2] * APPROACH_M, valid, name,
                                      "retreat")
        add_motion(name, "retreat", retreat, valid, None)
        q = retreat[-1]
        plan.parts.append(PlannedTask(name, grasp_q, place_q, carry_check))
        if progress is not None:
            progress((index + 1) / len(tasks))
    if tasks:
        opening = _opening_after_retreat(world, program, q, tasks[-1].grasp.opening_m, MAX_OPENING_M, "open")
    world.hold(None, None, opening)
    park = _park_configuration(np.asarray(home_q, dtype=np.float64), world.validity(transit=True))
    free = _free_space_validity(world, q, park)
    home = world.transit(q, park, free, "-", "return home")
    program.steps.append(MotionStep("return home", _timed(world, home, free, "-", "return home")))
    if tasks and opening < MAX_OPENING_M - 1e-6:
        world.hold(None, None, MAX_OPENING_M)
        if world.validity()(park):
            program.steps.append(GripperStep("open", MAX_OPENING_M, None))
    return plan


def _opening_after_retreat(world: CellWorld, program: Program, q: np.ndarray, released_m: float, wanted_m: float,
                           label: str) -> float:
    """The fingers' opening (m) after a retreat that ended at ``q`` with them at ``released_m``: ``wanted_m``
    (a gripper step appended to ``program``) where the hand opened to it clears every placed part there, else
    ``released_m`` (a finger would meet a placed part: it opens at the next approach, or at home)."""
    if abs(wanted_m - released_m) <= 1e-6:
        return wanted_m
    world.hold(None, None, max(wanted_m, released_m))
    if not world.validity()(q):
        return released_m
    program.steps.append(GripperStep(label, wanted_m, None))
    return wanted_m


def _insertion(world: CellWorld, place_q: np.ndarray, world_from_tcp_place: Pose, direction: np.ndarray,
               shift_m: np.ndarray, valid, part: str) -> tuple[np.ndarray, tuple[int, ...]]:
    """The insertion: joint waypoints from the pre-place configuration to ``place_q`` (release), and the indices of
    the waypoints where the motion must stop. Without a sideways ``shift_m`` (world, m; see
    :meth:`CellWorld.clearance_shift`) a straight line :data:`INSERTION_M` along ``direction``. With one, the part
    comes down held off the neighbour it slides along by the shift, stops, and moves sideways into contact: on a
    diagonal line it would meet the neighbour's face while still moving in, where friction wedges it (a cabinet's
    side panel jammed 18 mm short of the floor that way, against the ends of the panels it closes). Where that
    path collides or leaves the reachable space, the diagonal line."""
    if np.linalg.norm(shift_m) > 0.0:
        try:
            seat = world.straight_line(place_q, world_from_tcp_place, shift_m, valid, part, "insertion",
                                       INSERTION_STEP_M)
            held_off = Pose(world_from_tcp_place.position + shift_m, world_from_tcp_place.quat_wxyz)
            down = world.straight_line(seat[-1], held_off, -direction * INSERTION_M, valid, part, "insertion",
                                       INSERTION_STEP_M)
            return np.concatenate([down[::-1], seat[::-1][1:]]), (len(down) - 1,)
        except TaskPlanningError:
            pass
    back = -direction * INSERTION_M + shift_m
    return world.straight_line(place_q, world_from_tcp_place, back, valid, part, "insertion",
                               INSERTION_STEP_M)[::-1], ()


def _still_inside_words(world: CellWorld, part: str, task: PartTask, pre_q: np.ndarray, valid) -> str:
    """Why a pre-place pose collides, where the held ``part`` meets a neighbour it touches at its target (as
    ``valid`` sees it): it overlaps that neighbour along its whole way in, so the targets put the two into each
    other ("" otherwise)."""
    hit = world._first_collision(pre_q, valid)
    if hit is None or hit.a != f"held {part}" or hit.b not in task.touches_at_target:
        return ""
    direction = ", ".join(f"{v:+.2f}" for v in task.insertion_direction)
    return (f": {part!r} still overlaps {hit.b!r}, a neighbour at its target, {100 * INSERTION_M:.0f} cm back along "
            f"its insertion direction ({direction}, world), and no straight lead-in up to "
            f"{100 * LEAD_IN_STEPS_M[-1]:.0f} cm farther back clears it: the target poses put the two parts into "
            "each other along its way in")


def _lead_in(world: CellWorld, part: str, grasp: Grasp, pre_q: np.ndarray, direction: np.ndarray, clear,
             valid_insert) -> tuple[np.ndarray, bool] | None:
    """(joint waypoints (K, 7) of a straight line that ends at the pre-place configuration ``pre_q`` and starts
    :data:`LEAD_IN_STEPS_M` back from it, at the first distance where the part, grown by the carry margin, is
    ``clear``; whether the line comes in sideways). The line runs along the insertion ``direction`` (world, unit)
    where that works, else along a world axis across it (a chair's back panel between two tall posts enters
    between them from the front, where straight down it stays between them for 30 cm); None when none does (or
    every line leaves the reachable space). A line along the insertion is checked like the insertion
    (``valid_insert``, the part held as for it), one across it against everything, the neighbours the part touches
    at its target included (checked like the insertion, a panel of bookcase_flaerke_0403 came in sideways through
    a neighbour it ends against and jammed); the hold is left grown."""
    world_from_tcp_pre = world.panda.forward_tcp(pre_q)
    across = [sign * axis for axis in np.eye(3) if abs(float(axis @ direction)) < 0.1 for sign in (1.0, -1.0)]
    everything = world.validity()  # (with the hold below) the part may not pass through what it touches at the end
    found = None
    for k, towards in enumerate([np.asarray(direction, dtype=np.float64), *across]):
        for extra_m in LEAD_IN_STEPS_M:
            world.hold(part, grasp, grasp.width_m)
            try:
                line = world.straight_line(pre_q, world_from_tcp_pre, -towards * extra_m,
                                           valid_insert if k == 0 else everything, part, "lead-in")
            except TaskPlanningError:
                break
            world.hold(part, grasp, grasp.width_m, margin_m=-CARRY_CLEARANCE_M)
            if clear(line[-1]):
                found = (line[::-1], k > 0)
                break
        if found is not None:
            break
    world.hold(part, grasp, grasp.width_m, margin_m=-CARRY_CLEARANCE_M)
    return found


def _slot_entry(world: CellWorld, part: str, grasp: Grasp, carry: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The carry path (K, 7) split where the held part, grown by :data:`CARRY_CLEARANCE_M`, was last clear of
    everything (the transit clearance; checked every :data:`DENSE_CHECK_RAD` along its straight joint segments):
    (the carry up to that configuration, the rest from it), the rest a single configuration when the carry ends
    clear, or when no configuration of it is. The rest is the part's way into a slot between neighbours with
    fractions of a millimetre to spare (a cabinet's side between the door and the back it closes, a drawer's back
    between its sides, where no straight lead-in starts clear within reach): planned with the part as it is, it
    goes on slowly, like the insertion it joins, and may touch what the part touches at its target. At the carry's
    speed the simulated part grazed those neighbours by hundredths of a millimetre. The hold is left grown."""
    world.hold(part, grasp, grasp.width_m, margin_m=-CARRY_CLEARANCE_M)
    clear = world.validity(transit=True)
    carry = np.asarray(carry, dtype=np.float64)
    if clear(carry[-1]):
        return carry, carry[-1:]
    for j in range(len(carry) - 2, -1, -1):  # segment carry[j] -> carry[j + 1], from its end back
        a, b = carry[j], carry[j + 1]
        steps = max(1, int(np.ceil(float(np.max(np.abs(b - a))) / DENSE_CHECK_RAD)))
        for k in range(steps - 1, -1, -1):
            q = a + (b - a) * (k / steps)
            if clear(q):
                return np.concatenate([carry[:j + 1], q[None]]), np.concatenate([q[None], carry[j + 1:]])
    return carry, carry[-1:]


def _timed_insertion(world: CellWorld, path: np.ndarray, valid, part: str, limits: JointLimits,
                     stops: Sequence[int]):
    """The insertion ``path`` timed: within ``limits`` slowed by :func:`_insertion_limits`, its blends within
    :data:`INSERTION_DEVIATION_RAD` of the path, at rest at the waypoints indexed by ``stops``."""
    return _timed(world, path, valid, part, "insert", _insertion_limits(world, path, limits), stops,
                  INSERTION_DEVIATION_RAD)


def _insertion_limits(world: CellWorld, path: np.ndarray, limits: JointLimits) -> JointLimits:
    """``limits`` slowed so that the TCP moves at most about :data:`INSERTION_SPEED_M_S` along the insertion ``path``
    (joint waypoints). The bound per piece: its TCP distance over the shortest time its joint motion takes within
    the limits. A part carried into a fit with fractions of a millimetre to spare goes in slowly, as on a real cell;
    at the full limits (0.3-0.4 m/s) the simulator's contacts met a slat passing a rail's edge 0.6 mm off it as if
    it hit it (speculative contacts along the edge-to-edge normal) and twisted it in the hand by 14 degrees."""
    path = np.asarray(path, dtype=np.float64)
    tcp = np.array([world.panda.forward_tcp(q).position for q in path])
    fastest = 0.0
    for k in range(len(path) - 1):
        seconds = float(np.max(np.abs(path[k + 1] - path[k]) / limits.velocity))
        if seconds > 0.0:
            fastest = max(fastest, float(np.linalg.norm(tcp[k + 1] - tcp[k])) / seconds)
    if fastest <= INSERTION_SPEED_M_S:
        return limits
    return replace(limits, velocity=limits.velocity * (INSERTION_SPEED_M_S / fastest))  # it cruises at that speed


def _park_configuration(home_q: np.ndarray, valid) -> np.ndarray:
    """Where the arm ends: home, or, when the finished assembly stands where the arm would be, home swung aside
    about the base (joint 1) by the smallest angle that clears it."""
    for swing in (0.0, 0.5, -0.5, 1.0, -1.0, 1.57, -1.57, 2.2, -2.2):
        q = home_q.copy()
        q[0] += swing
        if valid(q):
            return q
    return home_q
