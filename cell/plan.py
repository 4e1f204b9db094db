"""The cell's plan for one assembly: jig, kitting layout, pick-and-place tasks and the timed program.

Inputs: a scene (:mod:`cell.scene`), an assembly at its target poses (assembly frame: metres, +z up, floor at
z = 0) and its assembly sequence (:mod:`planning.sequence`). The assembly frame sits on the jig at the scene's
``world_from_assembly``; the jig's pads (:mod:`planning.fixture`) stand on the table under the parts that touch
the floor.
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Mapping
from dataclasses import dataclass, field

import numpy as np
import trimesh

from cell.bullet import BulletClient
from cell.resting import PhysicsRestCheck
from cell.robot import CARTESIAN_STEP_M, IKError, IKSettings, Panda, StraightLineError, pose_rng
from cell.scene import Scene
from cell.simulate import SimSettings
from cell.task import (
    INSERTION_M,
    INSERTION_STEP_M,
    JOINT_LIMIT_MARGIN_RAD,
    LIFT_M,
    LONGEST_WAY_IN_M,
    PICK_STAGES,
    RETREAT_KIT_CLEARANCE_M,
    CellWorld,
    PartTask,
    TaskPlan,
    TaskPlanningError,
    plan_tasks,
)
from planning.assembly import Assembly, AssemblyPart
from planning.collision import ConvexPart, box_distance, world_bounds
from planning.disassembly import SequenceResult
from planning.fixture import fixture_pads
from planning.grasp import APPROACH_M, Grasp, feasible_grasps, grasp_pose_key
from planning.gripper import clearance_gripper
from planning.kitting import (
    NO_GRASP_AT_TARGET,
    NO_PLACE,
    TOO_LARGE,
    KittingError,
    KittingSlot,
    Reach,
    plan_kitting,
)
from planning.kitting_area import KittingArea
from planning.motion import MotionSettings
from planning.panda_ik import SHOULDER_HEIGHT_M
from planning.payload import (
    DEFAULT_DENSITY_KG_M3,
    HOLDING_TORQUE_FRACTION,
    PANDA_PAYLOAD_KG,
    PANDA_TORQUE_LIMITS_NM,
    JointTorques,
    MassProperties,
    mass_properties,
)
from planning.pick_clearance import HAND_CLEARANCE_M
from planning.pose import Pose
from planning.robot_collision import LINK_CLEARANCE_M, RobotCollisionChecker
from planning.sequence import GraspChecker, plan_assembly_sequence

PANDA_REACH_M = 0.855  # from the shoulder (joint 2) to the flange, fully stretched
# inverse-kinematics attempts for a chain of poses, each from where the last left the arm or, where another elbow is
# sought, from a random start (each query's own draws: cell.robot.pose_rng)
CHAIN_ATTEMPTS = 3
RELEASE_SEEDS = 4  # arm configurations at earlier releases that seed a release out of reach from elsewhere
HAND_LENGTH_M = 0.21  # flange to the TCP between the fingertips
NEAR_TARGET_M = 0.25  # placed parts farther than this from a part's target cannot touch the hand placing it
KIT_SEGMENT_STEP_M = 0.01  # kitting checks the straight lines at its configurations this finely (the task planner
# checks every motion at planning.robot_collision.SEGMENT_STEP_M)
SELF = "the part itself"  # its name among the obstacles of its own reach checks


class PlanningFailed(RuntimeError):
    """No plan: the message says which stage and part; ``stage`` is sequence, kitting or motion."""

    def __init__(self, stage: str, message: str, part: str | None = None) -> None:
        super().__init__(message)
        self.stage, self.part = stage, part
        self.seconds: dict[str, float] = {}  # time spent before failing, per stage
        self.beyond_reach = False  # the part failed at its target only for want of inverse kinematics
        self.kind: str | None = None  # a kitting failure's :class:`planning.kitting.KittingError` kind


@dataclass
class StaticObstacle:
    name: str
    mesh: trimesh.Trimesh  # own frame, metres
    world_from_obstacle: Pose


@dataclass
class CellPlan:
    world_from_assembly: Pose
    static: list[StaticObstacle]
    slots: list[KittingSlot]
    tasks: list[PartTask]
    task_plan: TaskPlan
    joint_limits: tuple[np.ndarray, np.ndarray]  # lower, upper (rad): the real arm's published ranges
    seconds: dict[str, float] = field(default_factory=dict)
    jig_turn_deg: float = 0.0  # how far the jig was turned from the scene's pose to make the plan work
    jig_slide_m: float = 0.0  # how far the jig was slid toward the robot from the scene's pose (m)
    sequence: SequenceResult | None = None  # the order planned with: the given one, or one planned for the arm

    @property
    def program(self):
        return self.task_plan.program


def out_of_reach(scene: Scene, assembly: Assembly) -> list[tuple[str, float]]:
    """Parts with a point the robot cannot reach at the jig: (name, distance from the shoulder in m) for each
    part whose nearest vertex lies farther from the shoulder than the arm plus the hand."""
    base = scene.robot.world_from_base
    shoulder = base.apply(np.array([[0.0, 0.0, SHOULDER_HEIGHT_M]]))[0]
    world_from_assembly = scene.fixture.world_from_assembly
    far = []
    for part in assembly.parts:
        world = (world_from_assembly @ part.assembly_from_part).apply(part.mesh.vertices)
        nearest = float(np.linalg.norm(world - shoulder, axis=1).min())
        if nearest > PANDA_REACH_M + HAND_LENGTH_M - 0.05:
            far.append((part.name, nearest))
    return far


def part_masses_kg(assembly: Assembly, density_kg_m3: float = DEFAULT_DENSITY_KG_M3,
                   part_density_kg_m3: Mapping[str, float] | None = None) -> dict[str, float]:
    """Each part's mass (kg) at its density (kg/m3): ``part_density_kg_m3[name]`` where given, else
    ``density_kg_m3`` (default :data:`DEFAULT_DENSITY_KG_M3`, wood)."""
    return {part.name: part_payload(part, density_kg_m3, part_density_kg_m3).mass_kg for part in assembly.parts}


def part_payload(part: AssemblyPart, density_kg_m3: float = DEFAULT_DENSITY_KG_M3,
                 part_density_kg_m3: Mapping[str, float] | None = None) -> MassProperties:
    """``part``'s mass properties at its density (kg/m3): ``part_density_kg_m3[part.name]`` where given, else
    ``density_kg_m3``."""
    return mass_properties(part.mesh, (part_density_kg_m3 or {}).get(part.name, density_kg_m3))


def too_heavy(masses_kg: dict[str, float], payload_kg: float = PANDA_PAYLOAD_KG) -> list[tuple[str, float]]:
    """Of the parts' masses (:func:`part_masses_kg`), those over the Panda's rated payload: (name, mass in kg),
    heaviest first."""
    return sorted(((name, kg) for name, kg in masses_kg.items() if kg > payload_kg), key=lambda item: -item[1])


def grasps_clear_at_target(grasps: list[Grasp], world_from_target: Pose, obstacles, insertion_world: np.ndarray,
                           floor_z: float) -> list[Grasp]:
    """Of ``grasps``, those whose hand (grown by :data:`HAND_CLEARANCE_M`) clears the ``obstacles`` ((mesh,
    world_from_mesh) pairs: the parts placed before, the jig's pads) and the table top at ``floor_z`` with the part
    at its target and along the whole straight insertion of :data:`INSERTION_M` along ``insertion_world`` that the
    arm makes (with only its last 3 cm checked, as the sequence planner does, a finger of bookcase_expedit_0373 met a
    shelf higher up), and whose hand closed on the part clears them there too by the motion planner's clearance
    (:data:`LINK_CLEARANCE_M`; chair_10's back panel lay where a closed finger on its back post was), ranked for
    the target, best first."""
    return feasible_grasps(grasps, world_from_target, obstacles, insertion_world, floor_z=floor_z,
                           insertion_sweep_m=INSERTION_M, gripper=clearance_gripper(HAND_CLEARANCE_M),
                           closed_gripper=clearance_gripper(LINK_CLEARANCE_M))


def _table(scene: Scene) -> StaticObstacle:
    size = scene.table.size
    centre = [scene.table.centre_xy[0], scene.table.centre_xy[1], scene.table.top_z - 0.5 * size[2]]
    return StaticObstacle("table", trimesh.creation.box(size), Pose(centre, [1, 0, 0, 0]))


def _pads(scene: Scene, assembly: Assembly) -> list[StaticObstacle]:
    pads = fixture_pads(assembly.part_names, assembly.meshes_in_assembly_frame())
    world_from_assembly = scene.fixture.world_from_assembly
    return [StaticObstacle(f"pad {pad.part}", pad.mesh(), world_from_assembly @ pad.assembly_from_pad)
            for pad in pads]


def _kitting_area(scene: Scene, assembly: Assembly) -> KittingArea:
    world_from_assembly = scene.fixture.world_from_assembly
    points = np.concatenate([world_from_assembly.apply(m.vertices) for m in assembly.meshes_in_assembly_frame()])
    margin = scene.kitting.jig_margin
    keep_out = ((tuple(points[:, :2].min(axis=0) - margin), tuple(points[:, :2].max(axis=0) + margin)),)
    table = scene.table
    half = np.array(table.size[:2]) / 2
    return KittingArea(
        centre_xy=tuple(scene.robot.world_from_base.position[:2]),
        inner_radius_m=scene.kitting.inner_radius, outer_radius_m=scene.kitting.outer_radius,
        table_min_xy=tuple(np.array(table.centre_xy) - half), table_max_xy=tuple(np.array(table.centre_xy) + half),
        table_z_m=table.top_z, pedestal_height_m=scene.kitting.pedestal_height, keep_out=keep_out,
        gap_m=scene.kitting.gap)


class _KitReach(Reach):
    """Arm configurations (IK) for each part's grasp at the pick (grasp, pre-grasp, lifted) and at the target
    (release, pre-place, end of the retreat), clear of the table, of the jig's ``pads``, of the parts on the jig at
    that time and of the parts and pedestals laid out in the kitting area so far, with inverse kinematics all along
    the straight TCP lines the task planner moves on between them. Kitting keeps later parts clear of all of
    them."""

    def __init__(self, panda: Panda, scene: Scene, seed: int, home_q: np.ndarray,
                 targets: dict[str, Pose], meshes: dict[str, trimesh.Trimesh], order: list[str],
                 insertion: dict[str, np.ndarray], payloads: dict[str, MassProperties] | None = None,
                 pads: list[StaticObstacle] = ()) -> None:
        # every query draws its random starts from the seed and its own first pose (cell.robot.pose_rng), never
        # from a generator shared with the queries before it
        self.panda, self.seed, self.home_q = panda, seed, home_q
        self.payloads = dict(payloads or {})  # a held part's weight must be held at its configurations too
        self.targets, self.meshes, self.order, self.insertion = targets, meshes, order, insertion
        self.checker = RobotCollisionChecker(scene.robot.world_from_base.matrix(), {})
        # the task planner's retreat keeps RETREAT_KIT_CLEARANCE_M from the parts in the kit: so does kitting's
        self.kit_checker = RobotCollisionChecker(scene.robot.world_from_base.matrix(), {},
                                                 link_clearance_m=RETREAT_KIT_CLEARANCE_M,
                                                 finger_clearance_m=RETREAT_KIT_CLEARANCE_M)
        self._part_meshes = {id(mesh) for mesh in meshes.values()}
        table = _table(scene)
        self._convex: dict[int, tuple[trimesh.Trimesh, ConvexPart]] = {}  # id(mesh) -> (mesh, its convex pieces)
        self.table = {"table": (self._convex_part(table.mesh), table.world_from_obstacle.matrix())}
        # the jig's pads: an arm link that met one was refused only by the task planner, and the jig's whole
        # placement with it (table_16's leg_rear_left at its pick, link 6)
        self.pads = {o.name: (self._convex_part(o.mesh), o.world_from_obstacle.matrix()) for o in pads}
        self.settings = IKSettings(restarts=4)
        self.shoulder = scene.robot.world_from_base.apply(np.array([[0.0, 0.0, SHOULDER_HEIGHT_M]]))[0]
        self.at_target_cache: dict[tuple, tuple | None] = {}  # (part, grasp, opening, kit) -> configurations
        self.too_heavy = 0  # arm configurations refused only because they could not hold the part's weight
        self.chain_unreached = False  # the last _chain found no inverse kinematics (rather than only collisions)
        self.release_seeds: list[np.ndarray] = []  # the latest arm configurations found at a release
        self.heavy_parts: dict[str, int] = {}  # part -> how many of its grasps failed at the target for its weight
        self.reached_at_target: dict[str, bool] = {}  # part -> whether any of its grasps had IK at its target

    def _world(self, kit: list[tuple[trimesh.Trimesh, Pose]], jig_parts: list[str], pads: bool = True) -> dict:
        out = dict(self.table) | (self.pads if pads else {})
        for k, (mesh, pose) in enumerate(kit):
            out[f"kit {k}"] = (self._convex_part(mesh), pose.matrix())
        for name in jig_parts:
            out[name] = (self._convex_part(self.meshes[name]), self.targets[name].matrix())
        return out

    def _convex_part(self, mesh: trimesh.Trimesh) -> ConvexPart:
        """``mesh``'s convex pieces, computed once per mesh object (the checks ask for the same ones thousands of
        times; the obstacle's name is its key in the world, not the ConvexPart's)."""
        entry = self._convex.get(id(mesh))
        if entry is None or entry[0] is not mesh:
            entry = (mesh, ConvexPart.from_mesh("obstacle", mesh))
            self._convex[id(mesh)] = entry
        return entry[1]

    def _chain(self, poses: list[Pose], seed: np.ndarray | None,
               checks: list[tuple[frozenset[str], frozenset[str]]] | None,
               load: JointTorques | None = None, held: tuple[bool, ...] = (), elsewhere: bool = False,
               first_ik: IKSettings | None = None, lines: tuple[tuple[int, float, int], ...] = (), accept=None):
        """IK for ``poses`` in turn (each seeded from the previous), each valid ignoring its (ignore, hand_ignore)
        sets (see :meth:`RobotCollisionChecker.first_invalid`; no collision check when ``checks`` is None), and,
        where ``held``, holding the ``load``; or None. Each of ``lines`` (index, step in m, index of the checks) is
        the straight TCP line from the first pose to that one, which the task planner moves on: inverse kinematics
        must follow it from the first configuration without a jump between branches
        (:meth:`cell.robot.Panda.tcp_line`), every step of it valid as those checks say. The first attempt starts
        from ``seed``; the others from where the last one left the arm, or, ``elsewhere``, from random
        configurations (the arm is redundant: another elbow may clear what the first one meets). The first pose's
        inverse kinematics uses ``first_ik`` (default: the planner's settings, few restarts), the others start from
        the pose before. ``accept(configurations)``, where given, must hold too."""
        self.chain_unreached = True  # no attempt found inverse kinematics for every pose
        if not all(self._within_reach(pose) for pose in poses):
            return None
        rng = pose_rng(poses[0], self.seed)
        for attempt in range(CHAIN_ATTEMPTS):
            configurations = []
            previous = (seed if attempt == 0 else rng.uniform(self.panda.lower_limits, self.panda.upper_limits)
                        if elsewhere else None)
            try:
                for k, pose in enumerate(poses):
                    settings = (first_ik or self.settings) if k == 0 else IKSettings(restarts=1)
                    previous = self.panda.inverse_tcp(pose, rng, seed_q=previous, settings=settings)
                    configurations.append(previous)
            except IKError:
                continue
            # the task planner keeps its configurations this far inside the limits and would refuse these:
            # bookcase_hensvik_0565's part_04 was kitted with a release on a joint limit and failed in motion
            if not all(self.panda.within_limits(q, JOINT_LIMIT_MARGIN_RAD) for q in configurations):
                continue
            self.chain_unreached = False
            free = checks is None or (
                all(self.checker.is_valid(q, ignore=ignore, hand_ignore=hand_ignore)
                    for q, (ignore, hand_ignore) in zip(configurations, checks))
                and all(self._line_clear(configurations[0], poses[0], poses[end], step_m, *checks[k])
                        for end, step_m, k in lines)
                and (accept is None or accept(configurations)))
            if load is not None and not all(load.within(q[None])[0] for q, h in zip(configurations, held) if h):
                self.too_heavy += int(free)  # it would have worked, but for the part's weight
                continue
            if free:
                return configurations
        return None

    def _line_clear(self, q_start: np.ndarray, world_from_tcp_start: Pose, world_from_tcp_end: Pose, step_m: float,
                    ignore: frozenset[str], hand_ignore: frozenset[str]) -> bool:
        """Whether inverse kinematics follows the straight TCP line from ``q_start`` to ``world_from_tcp_end`` with
        no jump between branches, every step between its configurations clear of the checker's obstacles but
        those ignored. Checked as joint-space lines between the ends, chair_16's leg_front was kitted with a pick
        whose approach needed such a jump, and desk_mikael_1064's part_02 with a retreat whose links met; the task
        planner refused the jig's placement for them."""
        offset = np.asarray(world_from_tcp_end.position) - np.asarray(world_from_tcp_start.position)
        try:
            path = self.panda.tcp_line(q_start, world_from_tcp_start, offset, self.seed, step_m)
        except StraightLineError:
            return False
        return all(self.checker.segment_valid(a, b, ignore=ignore, hand_ignore=hand_ignore,
                                              max_step_m=KIT_SEGMENT_STEP_M) for a, b in zip(path[:-1], path[1:]))

    def _within_reach(self, world_from_tcp: Pose) -> bool:
        """A quick necessary condition before inverse kinematics: the flange (the hand's length back from the
        TCP along the approach) lies within the arm's reach of the shoulder."""
        flange = world_from_tcp.position - world_from_tcp.rotation[:, 2] * HAND_LENGTH_M
        return float(np.linalg.norm(flange - self.shoulder)) <= PANDA_REACH_M

    def _at_target_poses(self, part: str, grasp: Grasp) -> list[Pose]:
        """The TCP poses (world frame) of ``part``'s release, pre-place and retreat's end with ``grasp``."""
        tcp = self.targets[part] @ grasp.part_from_tcp
        pre = Pose(tcp.position - self.insertion[part] * INSERTION_M, tcp.quat_wxyz)
        retreat = Pose(tcp.position - tcp.rotation[:, 2] * APPROACH_M, tcp.quat_wxyz)
        return [tcp, pre, retreat]

    def _at_target_world(self, part: str, grasp: Grasp, kit: list[tuple[trimesh.Trimesh, Pose]] = ()) -> list[Pose]:
        """Load the jig as it is when ``part`` arrives (the parts before it, the part itself as :data:`SELF`; and
        the ``kit`` bodies) and open the hand for ``grasp``; returns the TCP poses of the release, the pre-place
        and the retreat's end."""
        world = self._world(list(kit), self.order[:self.order.index(part)])
        world[SELF] = (self._convex_part(self.meshes[part]), self.targets[part].matrix())
        self.checker.set_obstacles(world)
        self.checker.hold(None, opening_m=grasp.opening_m)
        return self._at_target_poses(part, grasp)

    def could_reach_target(self, part: str, grasp: Grasp) -> bool:
        """Whether the arm could reach ``part``'s release, pre-place and retreat's end with ``grasp`` at all: each
        pose's flange within the arm's reach and a configuration within the joint limits in the Panda's closed form
        (:meth:`cell.robot.Panda.closed_form_reaches`), collisions, the part's weight and the planner's margin
        from the limits aside. A necessary condition of :meth:`at_target` finding configurations (up to the
        sampling of joint 7, 0.016 rad apart), answered in milliseconds and with no side effect: no
        inverse-kinematics query runs, so no cache, release seed or arm state changes, and the queries after it
        answer as they would without it."""
        poses = self._at_target_poses(part, grasp)
        return (all(self._within_reach(pose) for pose in poses)
                and all(self.panda.closed_form_reaches(pose) for pose in poses))

    # release: the arm and the opened fingers clear the neighbours the part touches (the part's own contacts are
    # planned; the hand around it was checked by the grasp planner, the arm's links must clear it); pre-place: the
    # part is in the hand, not at its target; end of the retreat: clear of everything, the released part included
    _AT_TARGET_IGNORES = ((frozenset(), frozenset({SELF})), (frozenset({SELF}), frozenset()),
                          (frozenset(), frozenset()))
    # the straight TCP lines between them, which the task planner solves from the release (the insertion
    # backwards, from the pre-place: the part in the hand; the retreat: the opened fingers around the part) and from
    # the grasp (the approach backwards, from the pre-grasp: the hand around the part; the lift: the part in the
    # hand), as (index of the line's other end, inverse kinematics step, index of the checks). The configurations
    # checked alone let an arm meet a kitted part halfway along (cabinet_1's bottom: link 7 met
    # drawer_1_side_right on the approach to its pick)
    _TARGET_LINES = ((1, INSERTION_STEP_M, 1), (2, CARTESIAN_STEP_M, 0))
    _PICK_LINES = ((1, CARTESIAN_STEP_M, 0), (2, CARTESIAN_STEP_M, 2))
    # the same lines as joint-space segments (from, to), at the pick and at the target: still_clear checks either
    # kind of configurations against the kit laid out later
    _STRAIGHT_LINES = ((1, 0), (0, 2))

    def at_target(self, part: str, grasp: Grasp, kit: list[tuple[trimesh.Trimesh, Pose]] = ()) -> tuple | None:
        """The arm configurations at ``part``'s release, pre-place and retreat's end with ``grasp``, clear of the
        parts on the jig then and of the ``kit`` bodies (computed once per part, grasp and kit)."""
        key = (part, grasp_pose_key(grasp), round(grasp.opening_m, 9),
               tuple((id(mesh), pose.position.tobytes(), pose.quat_wxyz.tobytes()) for mesh, pose in kit))
        if key not in self.at_target_cache:
            refused = self.too_heavy
            poses = self._at_target_world(part, grasp, kit)
            # the part is in the hand at the release and the pre-place, not at the retreat's end
            checks, load = list(self._AT_TARGET_IGNORES), self._load(part, grasp)
            retreat_clear = (None if not kit else
                             lambda configurations: self._retreat_clear(configurations, grasp.opening_m, kit))
            found = self._chain(poses, self.home_q, checks, load, (True, True, False), elsewhere=bool(kit),
                                lines=self._TARGET_LINES, accept=retreat_clear)
            reached = not self.chain_unreached
            if found is None and not kit:  # harder: other elbows, and more starts for the release (the first
                # attempts start at home and near each other)
                start = pose_rng(poses[0], self.seed + 1).uniform(self.panda.lower_limits, self.panda.upper_limits)
                found = self._chain(poses, start, checks, load, (True, True, False), elsewhere=True,
                                    first_ik=IKSettings(), lines=self._TARGET_LINES)
                reached = reached or not self.chain_unreached
                # at the edge of the reach (cabinet_13's side panel), random starts rarely converge: from the
                # releases found for other grasps and parts, nearby
                for seed in (self.release_seeds[::-1] if found is None and self.chain_unreached else []):
                    found = self._chain(poses, seed, checks, load, (True, True, False), first_ik=IKSettings(),
                                        lines=self._TARGET_LINES)
                    reached = reached or not self.chain_unreached
                    if found is not None or not self.chain_unreached:
                        break
            if not kit:
                self.reached_at_target[part] = self.reached_at_target.get(part, False) or reached
            if found is not None:
                self.release_seeds = (self.release_seeds + [found[0]])[-RELEASE_SEEDS:]
            self.at_target_cache[key] = None if found is None else tuple(found)
            if found is None and self.too_heavy > refused and not kit:
                self.heavy_parts[part] = self.heavy_parts.get(part, 0) + 1
        return self.at_target_cache[key]

    def beyond_reach(self, part: str) -> bool:
        """Whether every grasp of ``part`` tried at its target failed for want of inverse kinematics (the release,
        pre-place and retreat poses together), none for a collision or the part's weight."""
        return self.reached_at_target.get(part) is False

    def weight_words(self, part: str) -> str:
        """Why ``part``'s grasps failed at its target for its weight, in words ("" when none did)."""
        count = self.heavy_parts.get(part, 0)
        if not count or part not in self.payloads:
            return ""
        return (f"; at {count} of its grasps the arm could not hold its {self.payloads[part].mass_kg:.1f} kg there "
                f"(gravity alone needs more than {HOLDING_TORQUE_FRACTION:.0%} of a joint's torque limit, "
                f"{PANDA_TORQUE_LIMITS_NM[-1]:.0f} N m at the wrist)")

    def arm_meets(self, part: str, grasp: Grasp) -> set[str] | None:
        """The parts on the jig that the arm (hand open, the part released) meets at ``grasp``'s release, pre-place
        and retreat configurations when ``part`` arrives; None when these have no inverse kinematics, or meet the
        table or the arm itself."""
        found = self._chain(self._at_target_world(part, grasp), self.home_q, None)
        if found is None:
            return None
        met: set[str] = set()
        for q, ignore in zip(found, self._AT_TARGET_IGNORES):
            while (hit := self.checker.first_collision(q, ignore=ignore[0] | met, hand_ignore=ignore[1])) is not None:
                if hit.b not in self.meshes or hit.b == part:
                    return None
                met.add(hit.b)
        return met

    def at_pick(self, part, grasp, world_from_part, obstacles, support=()):
        target = self.at_target(part, grasp)
        # at the target too, the arm must clear what lies in the kitting area then (pedestals, later parts, and
        # what the part lay on): where the first configurations found there do not (an arm reaching low into a
        # cabinet sweeps its wrist over the kit), others that do
        # (solved again once per layout so far, the other slots' bodies; again with the part's own support only
        # where those configurations meet it: keyed on the support, that search ran at every place tried)
        kit = list(obstacles) + list(support)
        if target is not None and not self.still_clear(((), target, grasp.opening_m), kit):
            target = self.at_target(part, grasp, list(obstacles))
            if target is not None and support and not self.still_clear(((), target, grasp.opening_m), kit):
                target = self.at_target(part, grasp, kit)
        if target is None:
            return None
        tcp = world_from_part @ grasp.part_from_tcp
        pre = Pose(tcp.position - tcp.rotation[:, 2] * APPROACH_M, tcp.quat_wxyz)
        lifted = Pose(tcp.position + np.array([0.0, 0.0, LIFT_M]), tcp.quat_wxyz)
        world = self._world(list(obstacles), self.order[:self.order.index(part)])
        world[SELF] = (self._convex_part(self.meshes[part]), world_from_part.matrix())
        self.checker.set_obstacles(world)
        self.checker.hold(None, opening_m=grasp.opening_at_pick_m)
        # grasp: the hand around the part was checked by the grasp planner (the arm's links must clear it);
        # pre-grasp: clear of the part; lifted: the part is in the hand
        none, hand_only = (frozenset(), frozenset()), (frozenset(), frozenset({SELF}))
        found = self._chain([tcp, pre, lifted], self.home_q, [hand_only, none, (frozenset({SELF}), frozenset())],
                            self._load(part, grasp), (True, False, True), lines=self._PICK_LINES)
        return None if found is None else (tuple(found), target, max(grasp.opening_m, grasp.opening_at_pick_m))

    def _load(self, part: str, grasp: Grasp) -> JointTorques | None:
        """The arm's static torques holding ``part`` at ``grasp`` (None when its mass is not known)."""
        payload = self.payloads.get(part)
        return None if payload is None else JointTorques(self.checker, payload, grasp.part_from_tcp.inverse())

    def still_clear(self, reach, obstacles) -> bool:
        """Whether the arm configurations of ``reach`` (at the pick and at the target), and the straight lines
        between them, touch neither the table nor ``obstacles`` (kitting parts and pedestals), the retreat at the
        target keeping :data:`RETREAT_KIT_CLEARANCE_M` from the parts (see :meth:`_retreat_clear`). The jig's pads,
        which the configurations were found clear of, are left out: the straight lines here are joint-space lines
        between their ends, not the TCP lines the arm moves on, and a release low beside a pad whose insertion and
        retreat were clear along their TCP lines met the pad between the ends (cabinet_akurum_0011's part_02)."""
        self.checker.set_obstacles(self._world(list(obstacles), [], pads=False))
        self.checker.hold(None, opening_m=reach[2])
        return (all(self.checker.is_valid(q) for q in reach[0] + reach[1])
                and all(self.checker.segment_valid(configurations[a], configurations[b], max_step_m=KIT_SEGMENT_STEP_M)
                        for configurations in reach[:2] if len(configurations) == 3
                        for a, b in self._STRAIGHT_LINES)
                and (len(reach[1]) != 3 or self._retreat_clear(reach[1], reach[2], obstacles)))

    _RETREAT = (0, 2)  # at the target: from the release to the end of the retreat

    def _retreat_clear(self, at_target, opening_m: float, kit) -> bool:
        """Whether the retreat at the target (release to retreat's end, the hand opened to ``opening_m``) keeps
        :data:`RETREAT_KIT_CLEARANCE_M` from the parts among the ``kit`` bodies (their pedestals are checked
        exactly, as by the task planner). Checked exactly only, cabinet_11's bottom was kitted with a retreat that
        passed within it of drawer_1_side_left lying in the kit: the task planner refused the retreat and, with
        no other grasp of the bottom left, the jig's placement."""
        parts = [body for body in kit if id(body[0]) in self._part_meshes]
        if not parts:
            return True
        self.kit_checker.set_obstacles({f"kit {k}": (self._convex_part(mesh), pose.matrix())
                                        for k, (mesh, pose) in enumerate(parts)})
        self.kit_checker.hold(None, opening_m=opening_m)
        start, end = (np.asarray(at_target[index]) for index in self._RETREAT)
        return self.kit_checker.is_valid(start) and self.kit_checker.segment_valid(start, end,
                                                                                   max_step_m=KIT_SEGMENT_STEP_M)


JIG_TURNS_DEG = (0.0, 90.0, 270.0, 180.0)
# where a part's grasps are all beyond the arm's reach at its target, the jig at that turn slides this far toward
# the robot and is tried again (cabinet_3's far side panel: its grasps' flanges 0.81-0.86 m from the shoulder, at
# the edge of the 0.855 m reach, had no inverse kinematics; 6 cm nearer, 9 of them had)
JIG_SLIDE_M = 0.06
MOTION_RETRIES = 4  # motion planning restarts with a failing part's next grasp at most this often
# the jig is turned about +z until the parts can be kitted and placed, within this many CPU seconds per build (the
# procedural cabinet_5, 19 parts, took 216 s at the jig's first placement on 2 cores shared with three other jobs;
# 180 s cut it short there)
DEFAULT_TIME_BUDGET_S = 300.0
REORDERS = 3  # a part the arm cannot place among the parts before it moves ahead of them, at most this often


def grasp_options_after_failure(options: list[tuple[Grasp, tuple]], stage: str) -> list[tuple[Grasp, tuple]]:
    """The grasp options left for a part whose motions failed at ``stage`` with the first of ``options``
    (kitting's (grasp, arm configurations at the pick and at the target) pairs, best first): the others, less
    those that differ from it only in how wide the hand opens at the pick where ``stage`` is not one of
    :data:`cell.task.PICK_STAGES`. From the grasp on they would plan the same motions again: kitting keeps such
    variants of one grasp for a board that may lean between its chocks, and bookcase_hensvik_0565's ``part_06``
    failed its carry to the target with each of three, 25 s apiece, before the jig was turned."""
    failed, others = options[0], list(options[1:])
    if stage in PICK_STAGES:
        return others
    return [option for option in others if not _same_but_pick_opening(option, failed)]


def _same_but_pick_opening(a: tuple[Grasp, tuple], b: tuple[Grasp, tuple]) -> bool:
    """Whether two grasp options (grasp, arm configurations) hold the part alike, reach it with the same arm
    configurations at the pick and at the target, and open alike at the target (their pick openings aside)."""
    (grasp_a, reach_a), (grasp_b, reach_b) = a, b
    return (grasp_pose_key(grasp_a) == grasp_pose_key(grasp_b)
            and abs(grasp_a.width_m - grasp_b.width_m) < 1e-9 and abs(grasp_a.opening_m - grasp_b.opening_m) < 1e-9
            and np.allclose(reach_a[0][0], reach_b[0][0], rtol=0.0, atol=1e-9)
            and np.allclose(reach_a[1][0], reach_b[1][0], rtol=0.0, atol=1e-9))


def jig_placed(scene: Scene, turn_deg: float, slide_m: float = 0.0) -> Scene:
    """``scene`` with its jig (the assembly frame) turned by ``turn_deg`` about the world's +z axis and slid
    ``slide_m`` (m) horizontally toward the robot's base."""
    half = np.radians(turn_deg) / 2
    pose = scene.fixture.world_from_assembly
    position = np.array(pose.position, dtype=np.float64)
    if slide_m:
        away = position[:2] - scene.robot.world_from_base.position[:2]
        position[:2] -= slide_m * away / np.linalg.norm(away)
    turned = Pose(position, [np.cos(half), 0.0, 0.0, np.sin(half)]) @ Pose([0, 0, 0], pose.quat_wxyz)
    return dataclasses.replace(scene, fixture=dataclasses.replace(scene.fixture, world_from_assembly=turned))


def plan_cell(scene: Scene, assembly: Assembly, sequence: SequenceResult, seed: int = 0,
              motion: MotionSettings | None = None, progress=None, on_stage=None,
              time_budget_s: float = DEFAULT_TIME_BUDGET_S, on_note=None,
              density_kg_m3: float = DEFAULT_DENSITY_KG_M3,
              part_density_kg_m3: Mapping[str, float] | None = None) -> CellPlan:
    """Kitting layout, pick-and-place tasks and the timed program for ``assembly`` in ``scene``; raises
    :class:`PlanningFailed` naming the stage and the part. ``on_stage(name, jig_turn_deg, jig_slide_m)`` is
    called as the kitting and the motion stages begin (for each placement of the jig tried); ``progress(fraction)``
    after each part's motions are planned; ``on_note(text)`` says, in a line or two, why the planner tries again
    (another grasp of a part, another placement of the jig). ``CellPlan.seconds`` holds the time of kitting,
    motion (OMPL, IK, checks) and timing (Ruckig, with its collision re-check).

    Where kitting or motion fail with the jig as the scene places it, the jig is turned by 90, 270 and 180
    degrees (an assembly's grasps may only be reachable from one side); where a part's grasps are all beyond the
    arm's reach at its target, the jig at that turn is first slid :data:`JIG_SLIDE_M` toward the robot. A part
    that failed kitting at one placement is laid out first at the next (``plan_kitting``'s ``lay_out_first``).
    ``CellPlan.world_from_assembly`` says where it ended up, and a failure's message names every placement tried,
    one line each, the scene's own first. Planning gives up after ``time_budget_s`` seconds of its own work (the
    CPU time of the calling thread, on which every check and search runs: a busy machine takes longer by the clock
    but plans the same), and the failure then names the first placement it left untried. Parts weigh their volume
    at their density (kg/m3: ``part_density_kg_m3[name]`` where given, else ``density_kg_m3``) in the arm's torque
    checks. The kit's rest checks take every part at ``density_kg_m3``: a part alone on its pedestal rests or tips
    the same at any density (its weight and its friction scale together); only boards stacked in the kit press on
    each other by their own weights."""
    if not sequence.success:
        raise PlanningFailed("sequence", f"no assembly sequence: {sequence.reason}")
    deadline = time.thread_time() + time_budget_s
    payloads = {p.name: part_payload(p, density_kg_m3, part_density_kg_m3) for p in assembly.parts}
    # shared by the turns: a part rests on a pedestal the same anywhere
    with PhysicsRestCheck(SimSettings(density_kg_m3=density_kg_m3)) as rests:
        return _plan_turns(scene, assembly, sequence, seed, motion, progress, on_stage, deadline, rests, payloads,
                           on_note, time_budget_s)


def _placement_words(turn_deg: float, slide_m: float) -> str:
    return f"turned {turn_deg:.0f} deg" + (f", slid {100 * slide_m:.0f} cm toward the robot" if slide_m else "")


def _plan_turns(scene: Scene, assembly: Assembly, sequence: SequenceResult, seed: int,
                motion: MotionSettings | None, progress, on_stage, deadline: float,
                rests: PhysicsRestCheck, payloads: dict[str, MassProperties], on_note=None,
                time_budget_s: float = DEFAULT_TIME_BUDGET_S) -> CellPlan:
    failures = []
    out_of_time = None  # the first placement left untried for the time budget
    spent: dict[str, float] = {}
    too_large = False  # no placement of the jig makes the kitting ring larger
    why_again = None  # the last failure, said once another placement is tried (the final error lists them all)
    # the parts that failed kitting at a placement tried: laid out first at the next (a part whose grasps fail
    # at every place fails there at once, not after the whole kit is laid out; one that needs a place gets it)
    lay_out_first: tuple[str, ...] = ()
    for turn, slide in ((turn, slide) for turn in JIG_TURNS_DEG for slide in (0.0, JIG_SLIDE_M)):
        if slide and not (failures[-1][0] == turn and failures[-1][2].beyond_reach):
            continue  # slid only where the arm did not reach a part's target at this turn
        if too_large:
            break
        if failures and time.thread_time() > deadline:
            out_of_time = (turn, slide)
            break
        if why_again is not None and on_note is not None:
            on_note(why_again)
        try:
            stage = None if on_stage is None else (
                lambda name, _turn=turn, _slide=slide: on_stage(name, _turn, _slide))
            plan = _plan_with_jig(jig_placed(scene, turn, slide), assembly, sequence, seed, motion, progress,
                                  stage, deadline, payloads, rests, on_note, lay_out_first)
        except PlanningFailed as exc:
            failures.append((turn, slide, exc))
            if exc.stage == "kitting" and exc.part and exc.part not in lay_out_first:
                lay_out_first += (exc.part,)  # (out of time or a ring too small, no placement follows anyway)
            why_again = f"{exc.stage} failed with the jig {_placement_words(turn, slide)}: {exc}"
            for name, value in getattr(exc, "seconds", {}).items():
                spent[name] = spent.get(name, 0.0) + value
            too_large = exc.kind == TOO_LARGE
            continue
        for name, value in spent.items():
            plan.seconds[name] = plan.seconds.get(name, 0.0) + value
        plan.jig_turn_deg, plan.jig_slide_m = turn, slide
        return plan
    _, _, first = failures[0]
    # one line per placement of the jig tried, the first (the scene's own) first
    lines = [str(first)] + [f"also tried the jig {_placement_words(turn, slide)}: {exc.stage}: {exc}"
                            for turn, slide, exc in failures[1:]]
    if out_of_time is not None:
        lines.append(f"the planning time budget of {time_budget_s:g} s ran out before the jig "
                     f"{_placement_words(*out_of_time)} was tried (python -m cell.run --time-budget SECONDS "
                     f"allows more)")
    error = PlanningFailed(first.stage, "\n".join(lines), first.part)
    error.seconds = spent
    raise error


class _Kit:
    """The kitting layout for one assembly order: every part's slot in the kitting area with a grasp that works at
    its pick and at its target (arm checked), the order's steps, insertion directions (world frame) and the
    obstacles each part is planned to touch at its target (neighbours placed before it, its jig pad). Raises
    :class:`_KitFailed`."""

    def __init__(self, scene: Scene, assembly: Assembly, sequence: SequenceResult, panda: Panda,
                 static: list[StaticObstacle], targets: dict[str, Pose], hand_check, seed: int,
                 deadline: float, rests: PhysicsRestCheck | None = None,
                 payloads: dict[str, MassProperties] | None = None, lay_out_first: tuple[str, ...] = ()) -> None:
        world_from_assembly = scene.fixture.world_from_assembly
        order = sequence.order
        self.steps = {s.part: s for s in sequence.steps}
        # the sequence's directions are in the assembly frame; the jig may be turned
        self.insertion = {n: world_from_assembly.rotation @ np.asarray(self.steps[n].insertion_direction,
                                                                       dtype=np.float64) for n in order}
        pads_under = {o.name.removeprefix("pad "): o.name for o in static if o.name.startswith("pad ")}
        self._pad_obstacles = [(o.mesh, o.world_from_obstacle) for o in static if o.name.startswith("pad ")]
        self._assembly, self._targets, self._floor_z = assembly, targets, scene.table.top_z
        self.touches = {}
        for name in order:
            touching = [n for n in self.steps[name].fastened_to if n in targets]
            self.touches[name] = tuple(touching + ([pads_under[name]] if name in pads_under else []))
        home_q = np.array(scene.robot.home_q)
        kit_reach = _KitReach(panda, scene, seed, home_q, targets,
                              {p.name: p.mesh for p in assembly.parts}, order, self.insertion, payloads,
                              [o for o in static if o.name.startswith("pad ")])
        ranked: dict[str, list[Grasp]] = {}
        bounds = {p.name: world_bounds(p.mesh, targets[p.name]) for p in assembly.parts}
        self.near: dict[str, list[str]] = {}
        for name in order:  # grasps clear of the hand's surroundings at the target, ranked for the target
            self.near[name] = [n for n in order[:order.index(name)]
                               if box_distance(bounds[n], bounds[name]) < NEAR_TARGET_M]
            ranked[name] = self._hand_grasps(name, hand_check.candidates[name], self.near[name])
        self.reach, self.hand_check = kit_reach, hand_check
        for name in order:  # grasps, but none whose hand clears the parts before it: placed earlier it may
            if hand_check.candidates[name] and not ranked[name]:
                raise _KitFailed(self, KittingError(
                    f"part {name!r}: no grasp works at its target (none of its {len(hand_check.candidates[name])} "
                    f"grasps keeps the hand clear of the parts placed before it and of the jig's pads along its "
                    f"{INSERTION_M * 100:.0f} cm insertion)", NO_GRASP_AT_TARGET, name))
        for name in order:  # a part with no grasp the arm could reach at its target at all fails this placement of
            # the jig before the layout, not after the larger parts have been laid out (tvunit_0406 turned 0 deg:
            # 34 s): the layout would fail on it at the end, and the jig is slid or turned for it all the same
            if ranked[name] and not any(kit_reach.could_reach_target(name, grasp) for grasp in ranked[name]):
                kit_reach.reached_at_target[name] = False
                raise _KitFailed(self, KittingError(f"part {name!r}: no grasp works at its target",
                                                    NO_GRASP_AT_TARGET, name))

        def ok_at_target(name: str, grasp: Grasp) -> bool:
            return kit_reach.at_target(name, grasp) is not None

        try:
            self.slots = plan_kitting(order, [assembly.part(n).mesh for n in order], ranked, ok_at_target,
                                      _kitting_area(scene, assembly), prefer_near_xy=world_from_assembly.position[:2],
                                      reach=kit_reach, deadline=deadline,
                                      target_rotations={n: targets[n].rotation for n in order}, rests=rests,
                                      settles=None if rests is None else rests.settle, lay_out_first=lay_out_first)
        except KittingError as exc:
            words = kit_reach.weight_words(exc.part) if exc.part else ""
            if words and exc.kind in (NO_GRASP_AT_TARGET, NO_PLACE):
                exc = KittingError(str(exc) + words, exc.kind, exc.part)
            raise _KitFailed(self, exc) from exc

    def _hand_grasps(self, name: str, grasps: list[Grasp], present: list[str]) -> list[Grasp]:
        """Of ``grasps``, those whose hand clears the parts ``present`` and the jig's pads at the part's target
        (and along its insertion), ranked for the target (:func:`grasps_clear_at_target`)."""
        obstacles = [(self._assembly.part(n).mesh, self._targets[n]) for n in present] + self._pad_obstacles
        return grasps_clear_at_target(grasps, self._targets[name], obstacles, self.insertion[name], self._floor_z)

    def blockers(self, part: str) -> frozenset[str] | None:
        """The fewest parts placed before ``part`` that keep the hand or the arm from one of its grasps at its
        target (grasps that clear the pads on an empty jig, whose release, pre-place and retreat have inverse
        kinematics), or None when there is no such grasp (placing the part earlier would not help). Parts it rests
        on are never among them: it cannot come before its supports."""
        best: frozenset[str] | None = None
        supports = set(self.steps[part].rests_on)
        for grasp in self._hand_grasps(part, self.hand_check.candidates[part], []):
            met = self.reach.arm_meets(part, grasp)
            if met is None:
                continue
            met |= {n for n in self.near[part] if not self._hand_grasps(part, [grasp], [n])}
            if met and not met & supports and (best is None or len(met) < len(best)):
                best = frozenset(met)
        return best


class _KitFailed(Exception):
    """A :class:`_Kit` whose layout failed (``kit``: for :meth:`_Kit.blockers`), with the error."""

    def __init__(self, kit: _Kit, error: KittingError) -> None:
        super().__init__(str(error))
        self.kit, self.error = kit, error


def _kitting_failed(exc: KittingError, started: float, context: str = "",
                    beyond_reach: bool = False) -> PlanningFailed:
    error = PlanningFailed("kitting", f"{exc} ({context})" if context else str(exc), exc.part)
    error.kind = exc.kind
    error.seconds = {"kitting": time.perf_counter() - started}
    error.beyond_reach = beyond_reach
    return error


class _PlacedBefore:
    """The sequence planner's grasp check (``(part, parts present, insertion direction) -> grasp or None``) with
    precedences: part P has no grasp while any part in ``after[P]`` is present, so P is placed before them (the
    arm, not the hand, meets them at P's target); otherwise the hand's check decides."""

    def __init__(self, hand_check, after: dict[str, frozenset[str]]) -> None:
        self.hand_check, self.after = hand_check, after

    def __call__(self, name: str, present: frozenset, insertion_direction: np.ndarray) -> Grasp | None:
        if self.after.get(name, frozenset()) & present:
            return None
        return self.hand_check(name, present, insertion_direction)


def _plan_with_jig(scene: Scene, assembly: Assembly, sequence: SequenceResult, seed: int,
                   motion: MotionSettings | None, progress, on_stage, deadline: float,
                   payloads: dict[str, MassProperties], rests: PhysicsRestCheck | None = None,
                   on_note=None, lay_out_first: tuple[str, ...] = ()) -> CellPlan:
    on_stage = on_stage or (lambda name: None)
    seconds: dict[str, float] = {}
    world_from_assembly = scene.fixture.world_from_assembly
    home_q = np.array(scene.robot.home_q)
    static = [_table(scene)] + _pads(scene, assembly)
    targets = {p.name: world_from_assembly @ p.assembly_from_part for p in assembly.parts}

    with BulletClient() as client:
        panda = Panda(client, scene.robot.world_from_base, scene.robot.urdf, scene.robot.limits)

        # --- kitting: a grasp that works at the pick and at the target ----------------------------------------
        on_stage("kitting")
        started = time.perf_counter()
        hand_check = GraspChecker(assembly, seed)
        # the sequence checked the hand only: a part that the arm cannot place among the parts before it is
        # placed before those, and the order planned again (at most REORDERS times)
        after: dict[str, frozenset[str]] = {}
        for reorder in range(REORDERS + 1):
            try:
                kit = _Kit(scene, assembly, sequence, panda, static, targets, hand_check, seed, deadline, rests,
                           payloads, lay_out_first)
                break
            except _KitFailed as failed:
                exc = failed.error
                beyond = exc.kind == NO_GRASP_AT_TARGET and bool(exc.part) and failed.kit.reach.beyond_reach(exc.part)
                if beyond:
                    exc = KittingError(f"{exc}: each grasp tried there is beyond the arm's reach", exc.kind,
                                       exc.part)
                context = f"with the order planned again {reorder} time(s) for the arm" if reorder else ""
                if exc.kind != NO_GRASP_AT_TARGET or reorder == REORDERS or time.thread_time() > deadline:
                    raise _kitting_failed(exc, started, context, beyond) from exc
                blockers = failed.kit.blockers(exc.part)
                if not blockers:
                    raise _kitting_failed(exc, started, context, beyond) from exc
                after[exc.part] = after.get(exc.part, frozenset()) | blockers
                again = plan_assembly_sequence(assembly, seed, grasp_check=_PlacedBefore(hand_check, after),
                                               max_overlap_exit_m=LONGEST_WAY_IN_M)
                if not again.success:
                    raise _kitting_failed(exc, started, f"the arm meets {', '.join(sorted(blockers))} there, and "
                                          f"no order places it before them: {again.reason}", beyond) from exc
                sequence = again
        slots, insertion, touches = kit.slots, kit.insertion, kit.touches
        seconds["kitting"] = time.perf_counter() - started

        # --- pick and place -------------------------------------------------------------------------------------
        on_stage("motion")
        started = time.perf_counter()
        static += [StaticObstacle(f"pedestal {s.part}", s.pedestal.mesh(), s.pedestal.world_from_pedestal)
                   for s in slots if s.pedestal is not None]
        convex_static = {o.name: (ConvexPart.from_mesh(o.name, o.mesh), o.world_from_obstacle) for o in static}
        convex_parts = {p.name: ConvexPart.from_mesh(p.name, p.mesh) for p in assembly.parts}
        # a part whose motions fail with its grasp is tried with its kitting alternatives (each valid at its
        # pick and target) that would not plan the same motions again (grasp_options_after_failure), at most
        # MOTION_RETRIES times in all; the parts before it are kept as planned
        options = {s.part: [(s.grasp, s.reach)] + list(s.alternatives) for s in slots}
        timing_seconds = 0.0
        resume = None
        for attempt in range(MOTION_RETRIES + 1):
            tasks = []
            for slot in slots:
                grasp, reach = options[slot.part][0]
                tasks.append(PartTask(slot.part, slot.world_from_part, targets[slot.part], grasp,
                                      insertion[slot.part], touches[slot.part],
                                      slot.rests_on or f"pedestal {slot.part}", reach[0][0], reach[1][0],
                                      payloads[slot.part]))
            world = CellWorld(panda, scene.robot.world_from_base, convex_static, convex_parts,
                              np.random.default_rng([seed, 2, attempt]), motion or MotionSettings(), payloads)
            try:
                task_plan = plan_tasks(world, tasks, home_q, progress=progress, deadline=deadline, resume=resume)
                timing_seconds += world.timing_seconds
                break
            except TaskPlanningError as exc:
                timing_seconds += world.timing_seconds
                failed = options.get(exc.part, [])
                left = grasp_options_after_failure(failed, exc.stage) if failed else []
                out_of_time = exc.kind == "timeout" and exc.stage == "planning"  # the budget, not one search
                if attempt == MOTION_RETRIES or not left or out_of_time or time.thread_time() > deadline:
                    error = PlanningFailed("motion", str(exc), exc.part)
                    error.seconds = {**seconds, "motion": time.perf_counter() - started - timing_seconds,
                                     "timing": timing_seconds}
                    raise error from exc
                resume = exc.checkpoint
                if on_note is not None:
                    same = _same_but_pick_opening(left[0], failed[0])
                    how = (f"its grasp opened {left[0][0].opening_at_pick_m * 1000:.0f} mm at the pick (was "
                           f"{failed[0][0].opening_at_pick_m * 1000:.0f} mm)" if same else "another grasp of it")
                    on_note(f"{exc}\nplanning the motions again from {exc.part}, with {how}")
                options[exc.part] = left
        slots = [dataclasses.replace(s, grasp=options[s.part][0][0], reach=options[s.part][0][1],
                                     alternatives=tuple(options[s.part][1:])) for s in slots]
        seconds["timing"] = timing_seconds
        seconds["motion"] = time.perf_counter() - started - timing_seconds
        limits = (panda.limits.lower_rad.copy(), panda.limits.upper_rad.copy())
    return CellPlan(world_from_assembly, static, slots, tasks, task_plan, limits, seconds, sequence=sequence)


__all__ = ["CellPlan", "PlanningFailed", "StaticObstacle", "grasp_options_after_failure", "grasps_clear_at_target",
           "out_of_reach", "part_masses_kg", "part_payload", "plan_cell", "too_heavy"]
