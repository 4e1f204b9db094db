"""Joint-space motion planning against MPlib 0.2.1 on identical pick-and-place queries.

    python -m benchmarks.motion --queries 60 --seed 0 --time-limit 5 [--json out/motion.json]

Queries. Procedural level-3 objects (``perception.synth``, ``default_rng([seed, i])``, chair / table / cabinet in
turn) stand on the jig at the scene's ``world_from_assembly`` (``scenes/cell.toml``), with their fixture pads.
For each object a part P is drawn among those with an earlier-assembled part (designed stages); the parts of
earlier stages are placed at their targets, the others lie in their most probable stable pose on 4 cm pedestals
in the kitting ring around the robot (first free place along the ring, away from the jig). Two queries per object:

- ``carry``: P held at an antipodal grasp (``planning.grasp``, steepest approach from above first), from the
  grasp 10 cm above its kitting pose (the lift after the pick) to the grasp 10 cm above its target (pre-place);
- ``return``: P placed, hand empty, from that pre-place configuration to the pre-grasp 10 cm above the next part
  Q in the kitting ring.

Each end is solved once by inverse kinematics (``cell.robot.Panda``, seeded) and kept only when both planners'
collision models call it free in its query's world (the return's start, the carry's goal, also with the part placed
and the hand empty); both planners get the same joint-space start and goal.

Same geometry. Our checker uses the convex hull of every collision mesh of pybullet_data's ``panda.urdf``; MPlib
gets a copy of that URDF whose collision meshes are replaced by the same hulls (loaded with ``use_convex=True``),
written at run time under ``--cache`` (default ``~/.cache/image-assembly/mplib``; the SRDF MPlib generates on
first use, about 80 s, is kept there). Obstacles (table, pads, placed and kitting parts, pedestals) go to MPlib as
FCL ``Convex`` objects of the same pieces; the held part as attached ``Convex`` pieces on ``panda_hand``. Both
skip the base link against the world and the held part against the robot's own links (MPlib: ACM entries and
touch links). Self-collision pairs: each planner's own list (ours: chain neighbours and always-touching pairs;
MPlib: its generated SRDF).

Planners. Ours: ``planning.motion.plan_joint_path`` with its defaults (RRTConnect, simplification),
``RobotCollisionChecker.is_valid`` for states and ``RobotCollisionChecker.segment_valid`` for edges (checks spaced
so that no point of the robot or the held part moves more than 2 mm between them). MPlib: ``Planner.planner.plan``
(its OMPL RRTConnect with ``simplifyMax``) with ``range=0.1`` as ``Planner.plan_qpos`` passes it, TOPP-RA excluded
from the time. Same time limit. Planning time: wall clock and CPU time (``time.process_time``; both planners are
single-threaded) of the call, failures included.

Verification. Each returned path is re-checked densely (at most 0.001 rad per joint between samples) for contact
in *both* collision models: ours (FCL's convex test) and MPlib's distance query (<= 0; its collision query also
reports pairs about 2 mm apart, where its own distance query and ours agree they are apart, so it does not judge).
Ours judges with its clearances off: our planner keeps the arm's links 1.5 mm, the fingers 1.2 mm and the links 3 mm
from each other (``planning.robot_collision``: the simulator's hulls are larger), which is our planner's choice, not
contact; judged with them (from commit e01c41e on), an MPlib path passing a part 1.2 mm off counted as in contact.
"Collision-free" counts the paths with no sample in contact; "overlapping" the paths where MPlib's distance query
reports interpenetration (not only touching within numerical precision).
"""

from __future__ import annotations

import argparse
import contextlib
import hashlib
import io
import json
import os
import platform
import shutil
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import trimesh

from cell.bullet import BulletClient
from cell.robot import IKError, IKSettings, Panda
from cell.scene import Scene, load_scene
from perception.synth import generate
from planning.collision import ConvexPart
from planning.fixture import fixture_pads
from planning.grasp import antipodal_grasps
from planning.gripper import HAND_FROM_TCP
from planning.motion import MotionPlanningError, MotionSettings, plan_joint_path
from planning.pose import Pose
from planning.robot_collision import RobotCollisionChecker
from planning.stability import stable_rest_poses

CATEGORIES = ("chair", "table", "cabinet")
LIFT_M = 0.10  # pre-grasp / pre-place: the grasp's TCP this far above the pick / the target (world +z)
GRASPS_TRIED = 12
VERIFY_STEP_RAD = 0.001
MPLIB_RANGE = 0.1  # what mplib.Planner.plan_qpos passes to its RRTConnect by default
JIG_KEEP_OUT_M = 0.12  # kitting footprints stay this far from the assembly's footprint
KIT_PARTS = 6  # loose parts lying in the kitting ring: the moving part and the next ones in the order
MOVING_TRIES = 3  # parts of one object tried as the moving part before the object is skipped


# --- the MPlib-ready Panda -------------------------------------------------------------------------------------------
def mplib_panda_urdf(cache: Path) -> Path:
    """A copy of pybullet_data's ``franka_panda`` whose collision meshes are their convex hulls (``.obj`` and the
    ``.obj.convex.stl`` that MPlib's ``use_convex=True`` reads), under ``cache/<hash of the source URDF>/``."""
    import pybullet_data

    source = Path(pybullet_data.getDataPath()) / "franka_panda"
    key = hashlib.sha256((source / "panda.urdf").read_bytes()).hexdigest()[:16]
    folder = cache / key / "franka_panda"
    urdf = folder / "panda.urdf"
    if (folder / ".complete").is_file():
        return urdf
    shutil.rmtree(folder, ignore_errors=True)
    shutil.copytree(source, folder)
    for mesh_file in sorted((folder / "meshes").rglob("*.obj")):  # MPlib refuses the originals' 2-vertex faces
        mesh = trimesh.load(mesh_file, force="mesh", process=True)
        if mesh_file.parent.name == "collision":
            mesh = mesh.convex_hull
            mesh.export(f"{mesh_file}.convex.stl")
        mesh.export(mesh_file)
    (folder / ".complete").write_text("ok\n")
    return urdf


# --- queries ---------------------------------------------------------------------------------------------------------
@dataclass
class Query:
    """One planning problem: world obstacles (name -> (ConvexPart, world_from_part 4x4)), the held part (with
    ``tcp_from_part`` 4x4) or None, the finger opening (m) and the arm's start and goal (7,) radians."""

    name: str
    obstacles: dict[str, tuple[ConvexPart, np.ndarray]]
    held: tuple[ConvexPart, np.ndarray] | None
    opening_m: float
    start_q: np.ndarray
    goal_q: np.ndarray


def _box_part(name: str, size: tuple[float, float, float]) -> ConvexPart:
    return ConvexPart.from_mesh(name, trimesh.creation.box(size))


def _translation(xyz) -> np.ndarray:
    matrix = np.eye(4)
    matrix[:3, 3] = xyz
    return matrix


def _yaw(angle: float) -> np.ndarray:
    matrix = np.eye(4)
    matrix[:2, :2] = [[np.cos(angle), -np.sin(angle)], [np.sin(angle), np.cos(angle)]]
    return matrix


@dataclass
class _Layout:
    world_from_part_target: dict[str, np.ndarray]
    world_from_part_kit: dict[str, np.ndarray] = field(default_factory=dict)
    pedestals: dict[str, tuple[ConvexPart, np.ndarray]] = field(default_factory=dict)


def _kit_layout(scene: Scene, names: list[str], meshes: dict[str, trimesh.Trimesh],
                assembly_box: np.ndarray) -> _Layout | None:
    """Rest poses on pedestals along the kitting ring (world frame, metres), first free place from the jig's side
    outwards; None when the parts do not fit."""
    layout = _Layout({})
    top = scene.table.top_z + scene.kitting.pedestal_height
    taken: list[tuple[np.ndarray, float]] = []
    keep_lo, keep_hi = assembly_box[0] - JIG_KEEP_OUT_M, assembly_box[1] + JIG_KEEP_OUT_M
    radii = np.linspace(scene.kitting.inner_radius, scene.kitting.outer_radius, 5)
    angles = np.deg2rad(np.concatenate([np.arange(30, 181, 6), -np.arange(30, 181, 6)]))
    for name in names:
        rest_from_part = stable_rest_poses(meshes[name], max_poses=1)[0][0]
        rested = meshes[name].vertices @ rest_from_part[:3, :3].T + rest_from_part[:3, 3]
        half_xy = 0.5 * (rested.max(axis=0) - rested.min(axis=0))[:2]
        radius_xy = float(np.linalg.norm(half_xy))
        for angle in sorted(angles, key=abs):
            spot = [(r * np.cos(angle), r * np.sin(angle)) for r in radii]
            free = [xy for xy in spot
                    if all(np.linalg.norm(np.subtract(xy, c)) > radius_xy + r_c + scene.kitting.gap for c, r_c in taken)
                    and not (np.all(np.add(xy, radius_xy) > keep_lo[:2]) and np.all(np.subtract(xy, radius_xy)
                                                                                      < keep_hi[:2]))]
            if free:
                xy = np.array(free[0])
                break
        else:
            return None
        taken.append((xy, radius_xy))
        world_from_rest = _translation([xy[0], xy[1], top]) @ _yaw(float(np.arctan2(xy[1], xy[0])) + np.pi / 2)
        layout.world_from_part_kit[name] = world_from_rest @ rest_from_part
        inset = np.minimum(0.03, 0.3 * 2 * half_xy)
        size = (max(2 * half_xy[0] - 2 * inset[0], 0.01), max(2 * half_xy[1] - 2 * inset[1], 0.01),
                scene.kitting.pedestal_height)
        layout.pedestals[f"pedestal {name}"] = (_box_part(f"pedestal {name}", size),
                                                world_from_rest @ _translation([0, 0, -size[2] / 2]))
    return layout


class QueryBuilder:
    """Builds the seeded queries; IK from ``cell.robot.Panda`` (PyBullet, DIRECT), ends kept when free in every
    collision model of ``models`` (objects with ``set_world`` and ``is_valid``)."""

    def __init__(self, scene: Scene, models: list, seed: int) -> None:
        self.scene, self.models = scene, models
        self.rng = np.random.default_rng(seed)
        self.client = BulletClient()
        self.panda = Panda(self.client, scene.robot.world_from_base)
        self.home = np.array(scene.robot.home_q)
        self.skipped: list[str] = []
        table = scene.table
        self.table = (_box_part("table", table.size),
                      _translation([table.centre_xy[0], table.centre_xy[1], table.top_z - table.size[2] / 2]))

    def close(self) -> None:
        self.client.close()

    def _free(self, q: np.ndarray, obstacles, held, opening_m: float) -> bool:
        for model in self.models:
            model.set_world(obstacles, held, opening_m)
        return all(model.is_valid(q) for model in self.models)

    def _ik(self, world_from_tcp: np.ndarray, obstacles, held, opening_m: float) -> np.ndarray | None:
        target = Pose.from_matrix(world_from_tcp)
        for attempt in range(4):
            try:
                q = self.panda.inverse_tcp(target, self.rng, seed_q=self.home if attempt == 0 else None,
                                           settings=IKSettings(restarts=6))
            except IKError:
                continue
            if self._free(q, obstacles, held, opening_m):
                return q
        return None

    def object_queries(self, index: int, seed: int) -> list[Query]:
        category = CATEGORIES[index % len(CATEGORIES)]
        assembly = generate(category, "3", np.random.default_rng([seed, index]), f"{category}_{index:02d}")
        stages = assembly.metadata["stages"]
        parts = {p.name: p for p in assembly.parts}
        order = sorted(parts, key=lambda n: (stages[n], n))
        world_from_assembly = self.scene.fixture.world_from_assembly.matrix()
        target = {n: world_from_assembly @ parts[n].assembly_from_part.matrix() for n in order}
        posed = [parts[n].mesh.copy().apply_transform(parts[n].assembly_from_part.matrix()) for n in order]
        corners = np.array([m.bounds for m in posed])
        assembly_box = np.array([corners[:, 0].min(axis=0), corners[:, 1].max(axis=0)]) + world_from_assembly[:3, 3]
        static = {"table": self.table}
        for pad in fixture_pads(order, posed):
            static[f"pad {pad.part}"] = (ConvexPart.from_mesh(f"pad {pad.part}", pad.mesh()),
                                         world_from_assembly @ pad.assembly_from_pad.matrix())
        convex = {n: ConvexPart.from_mesh(n, parts[n].mesh) for n in order}
        first_stage = [n for n in order if stages[n] == stages[order[0]]]
        candidates = list(range(len(first_stage), len(order) - 1))
        self.rng.shuffle(candidates)
        for k in candidates[:MOVING_TRIES]:
            queries = self._queries_for(assembly.name, order, k, parts, convex, target, static, assembly_box)
            if queries:
                return queries
        if not candidates:
            self.skipped.append(f"{assembly.name}: fewer than three stages")
        return []

    def _queries_for(self, name, order, k, parts, convex, target, static, assembly_box) -> list[Query]:
        moving, following = order[k], order[k + 1]
        kit_now = order[k:k + KIT_PARTS]
        layout = _kit_layout(self.scene, kit_now, {n: parts[n].mesh for n in kit_now}, assembly_box)
        if layout is None:
            self.skipped.append(f"{name}: the loose parts do not fit the kitting ring")
            return []

        def world(placed: list[str], kit: list[str]) -> dict:
            out = dict(static)
            out.update({n: (convex[n], target[n]) for n in placed})
            out.update({n: (convex[n], layout.world_from_part_kit[n]) for n in kit})
            out.update(layout.pedestals)
            return out

        carry_world = world(order[:k], [n for n in kit_now if n != moving])
        return_world = world(order[:k + 1], [n for n in kit_now if n != moving])
        carry = self._carry(name, moving, parts[moving].mesh, convex[moving], layout, target, carry_world)
        if carry is None:
            return []
        back = self._pre_grasp(following, parts[following].mesh, layout, return_world)
        if back is None:
            self.skipped.append(f"{name}: no free pre-grasp for {following}")
            return []
        if not self._free(carry.goal_q, return_world, None, carry.opening_m):
            # the pre-place was checked with the part in the hand; placed, it may meet the empty hand there
            self.skipped.append(f"{name}: the empty hand at {moving}'s pre-place touches it placed")
            return []
        return [carry, Query(f"{name} return {moving} -> {following}", return_world, None, carry.opening_m,
                             carry.goal_q, back[0])]

    @staticmethod
    def _above(world_from_part: np.ndarray, part_from_tcp: np.ndarray) -> np.ndarray:
        """The TCP of a grasp raised by :data:`LIFT_M` in the world (orientation kept)."""
        world_from_tcp = world_from_part @ part_from_tcp
        world_from_tcp[2, 3] += LIFT_M
        return world_from_tcp

    def _grasps(self, mesh: trimesh.Trimesh, world_from_part: list[np.ndarray]):
        """Grasp candidates, those approaching most steeply from above (at every given pose) first."""
        grasps = antipodal_grasps(mesh, self.rng, max_candidates=24)
        steepness = [max(float((pose @ g.part_from_tcp.matrix())[2, 2]) for pose in world_from_part) for g in grasps]
        return [grasps[i] for i in np.argsort(steepness, kind="stable")][:GRASPS_TRIED]

    def _carry(self, name, moving, mesh, convex, layout, target, obstacles) -> Query | None:
        for grasp in self._grasps(mesh, [layout.world_from_part_kit[moving], target[moving]]):
            part_from_tcp = grasp.part_from_tcp.matrix()
            tcp_from_part = np.linalg.inv(part_from_tcp)
            # the lift: the part itself moved back along the approach, still in the hand
            held = (convex, tcp_from_part)
            start = self._ik(self._above(layout.world_from_part_kit[moving], part_from_tcp), obstacles, held,
                             grasp.opening_m)
            if start is None:
                continue
            goal = self._ik(self._above(target[moving], part_from_tcp), obstacles, held, grasp.opening_m)
            if goal is None:
                continue
            return Query(f"{name} carry {moving}", obstacles, held, grasp.opening_m, start, goal)
        self.skipped.append(f"{name}: no grasp of {moving} with free, reachable lift and pre-place")
        return None

    def _pre_grasp(self, part, mesh, layout, obstacles) -> tuple[np.ndarray, float] | None:
        for grasp in self._grasps(mesh, [layout.world_from_part_kit[part]]):
            q = self._ik(self._above(layout.world_from_part_kit[part], grasp.part_from_tcp.matrix()), obstacles, None,
                         grasp.opening_m)
            if q is not None:
                return q, grasp.opening_m
        return None


def build_queries(scene: Scene, models: list, seed: int, count: int) -> tuple[list[Query], list[str]]:
    """At least ``count`` queries (two per usable object, objects 0, 1, ... in turn) and why objects were
    skipped; prints a summary."""
    builder = QueryBuilder(scene, models, seed)
    queries: list[Query] = []
    index = 0
    try:
        while len(queries) < count and index < 5 * count:
            queries += builder.object_queries(index, seed)
            index += 1
    finally:
        builder.close()
    print(f"{len(queries)} queries from {index} objects; {len(builder.skipped)} tries skipped", flush=True)
    for reason in builder.skipped:
        print(f"  skipped {reason}", flush=True)
    return queries, builder.skipped


# --- the two planners ------------------------------------------------------------------------------------------------
class OurPlanner:
    label = "ours (OMPL RRTConnect, Python FCL checker)"
    name = "ours"

    def __init__(self, scene: Scene, lower: np.ndarray, upper: np.ndarray, time_limit_s: float, seed: int) -> None:
        self.checker = RobotCollisionChecker(scene.robot.world_from_base.matrix(), {})
        # the same model without the clearances the planner keeps: contact, for the re-check of both planners' paths
        self.exact = RobotCollisionChecker(scene.robot.world_from_base.matrix(), {}, self_clearance_m=0.0,
                                           link_clearance_m=0.0, finger_clearance_m=0.0)
        self.lower, self.upper = lower, upper
        # one call, ended by the clock too, as MPlib's
        self.settings = MotionSettings(time_limit_s=time_limit_s, wall_limit_s=time_limit_s, seed=seed, searches=1)

    def set_world(self, obstacles, held, opening_m: float) -> None:
        for checker in (self.checker, self.exact):
            checker.set_obstacles(obstacles)
            checker.hold(held[0] if held else None, held[1] if held else None, opening_m=opening_m)

    def is_valid(self, q: np.ndarray) -> bool:
        return self.checker.is_valid(q)

    def collision_words(self, q: np.ndarray) -> str:
        """What touches what at ``q`` in our model without its clearances, or "free"."""
        hit = self.exact.first_collision(q)
        return "free" if hit is None else f"{hit.a} / {hit.b}"

    def touches(self, q: np.ndarray) -> bool:
        """Exact contact (FCL's convex-convex test) in our model, without the clearances its planner keeps."""
        return not self.exact.is_valid(q)

    def plan(self, query: Query) -> np.ndarray | None:
        try:
            return plan_joint_path(self.checker.is_valid, query.start_q, query.goal_q, self.lower, self.upper,
                                   self.settings, segment_valid=self.checker.segment_valid)
        except MotionPlanningError:
            return None


class MPlibPlanner:
    label = "MPlib 0.2.1 (OMPL RRTConnect, C++ FCL)"
    name = "MPlib"

    def __init__(self, urdf: Path, scene: Scene, time_limit_s: float, seed: int) -> None:
        import mplib
        from mplib.collision_detection import fcl as mfcl

        self.mplib, self.fcl = mplib, mfcl
        mplib.set_global_seed(max(1, seed))  # OMPL refuses 0
        srdf = next(iter(sorted(urdf.parent.glob("*.srdf"))), None)  # generated by the first run (about 80 s)
        with contextlib.redirect_stdout(io.StringIO()):  # its SRDF generation prints every link pair
            self.planner = mplib.Planner(urdf=str(urdf), move_group="panda_hand", use_convex=True,
                                         srdf=str(srdf) if srdf else None)
        self.planner.set_base_pose(mplib.Pose(scene.robot.world_from_base.matrix()))
        self.world = self.planner.planning_world
        self.acm = self.world.get_allowed_collision_matrix()
        self.robot_name = self.planner.robot.get_name()
        self.links = list(self.planner.user_link_names)
        self.time_limit_s = time_limit_s
        self.opening_m = 0.08
        self._geometry: dict[int, tuple[ConvexPart, list]] = {}  # id(part) -> (part, its Convex geometries)
        self._names: list[str] = []

    def _convexes(self, part: ConvexPart) -> list:
        if id(part) not in self._geometry:
            pieces = []
            for vertices in part.piece_vertices:
                hull = trimesh.convex.convex_hull(vertices)
                pieces.append(self.fcl.Convex(np.asarray(hull.vertices, dtype=np.float64),
                                              np.asarray(hull.faces, dtype=np.int32)))
            self._geometry[id(part)] = (part, pieces)  # keep the part alive: ids must not be reused
        return self._geometry[id(part)][1]

    def set_world(self, obstacles, held, opening_m: float) -> None:
        for name in self._names:
            self.world.remove_object(name)
        self._names = []
        for name, (part, world_from_part) in obstacles.items():
            pose = self.mplib.Pose(np.asarray(world_from_part, dtype=np.float64))
            for k, geometry in enumerate(self._convexes(part)):
                object_name = f"{name}#{k}"
                self.world.add_object(object_name, self.fcl.CollisionObject(geometry, pose))
                self._names.append(object_name)
        self.acm.set_entry("panda_link0", list(self._names), True)  # the base stands on the table
        if held is not None:
            part, tcp_from_part = held
            hand_from_part = self.mplib.Pose(HAND_FROM_TCP.matrix() @ tcp_from_part)
            link = self.planner.link_name_2_idx["panda_hand"]
            for k, geometry in enumerate(self._convexes(part)):
                object_name = f"held#{k}"
                self.world.attach_object(object_name, geometry, self.robot_name, link, hand_from_part, self.links)
                self._names.append(object_name)
        self.opening_m = opening_m

    def _full(self, q: np.ndarray) -> np.ndarray:
        return np.concatenate([q, [self.opening_m / 2, self.opening_m / 2]])

    def is_valid(self, q: np.ndarray) -> bool:
        self.planner.robot.set_qpos(self._full(np.asarray(q, dtype=np.float64)), True)
        return len(self.world.check_collision()) == 0

    def collision_words(self, q: np.ndarray) -> str:
        self.planner.robot.set_qpos(self._full(np.asarray(q, dtype=np.float64)), True)
        closest = self.world.distance()
        gap = "overlapping" if closest.min_distance < 0 else f"{1000 * closest.min_distance:.2f} mm apart"
        return f"{closest.link_name1 or closest.object_name1} / {closest.link_name2 or closest.object_name2} {gap}"

    def distance(self, q: np.ndarray) -> float:
        """Smallest distance (m) in MPlib's model by its distance query, negative (-1) when bodies overlap. Its
        collision query (``is_valid``, what its planner uses) also reports pairs up to about 2 mm apart, where its
        own distance query and ours agree they are apart (seen on this benchmark's paths), so it does not judge
        paths."""
        self.planner.robot.set_qpos(self._full(np.asarray(q, dtype=np.float64)), True)
        return float(self.world.distance().min_distance)

    def plan(self, query: Query) -> np.ndarray | None:
        self.planner.robot.set_qpos(self._full(query.start_q), True)
        status, path = self.planner.planner.plan(query.start_q, [query.goal_q], time=self.time_limit_s,
                                                 range=MPLIB_RANGE, simplify=True)
        return np.asarray(path) if status == "Exact solution" and len(path) else None


def dense(path: np.ndarray, step_rad: float = VERIFY_STEP_RAD) -> np.ndarray:
    """(N, 7) configurations along the straight segments of ``path``, at most ``step_rad`` apart per joint."""
    out = [path[:1]]
    for a, b in zip(path[:-1], path[1:]):
        steps = max(1, int(np.ceil(np.max(np.abs(b - a)) / step_rad)))
        out.append(a + (b - a) * (np.arange(1, steps + 1) / steps)[:, None])
    return np.concatenate(out)


def verify(path: np.ndarray, query: Query, ours: OurPlanner, theirs: MPlibPlanner) -> dict:
    """Dense re-check of ``path``: how many samples (every :data:`VERIFY_STEP_RAD` per joint) are in contact in
    either model (our FCL convex test; MPlib's distance query <= 0), how many of those MPlib's distance query calls
    overlapping (rather than touching within its precision), and the first one in words."""
    if not (np.allclose(path[0], query.start_q, atol=1e-6) and np.allclose(path[-1], query.goal_q, atol=1e-6)):
        return {"samples": 0, "contact": 1, "overlap": 0, "first": "does not join the start and the goal"}
    samples = dense(path)
    ours.set_world(query.obstacles, query.held, query.opening_m)
    theirs.set_world(query.obstacles, query.held, query.opening_m)
    contact = overlap = 0
    first = ""
    for index, q in enumerate(samples):
        ours_touch = ours.touches(q)
        distance = theirs.distance(q)
        if ours_touch or distance <= 0.0:
            contact += 1
            overlap += distance < 0.0
            if not first:
                first = (f"sample {index}/{len(samples)}: ours {ours.collision_words(q)}; MPlib "
                         f"{theirs.collision_words(q)}")
    return {"samples": len(samples), "contact": contact, "overlap": int(overlap), "first": first}


# --- main ------------------------------------------------------------------------------------------------------------
def _summary(label: str, records: list[dict], key: str) -> str:
    times = np.array([r[key]["seconds"] for r in records])
    solved = np.mean([r[key]["solved"] for r in records])
    verified = np.mean([r[key]["verified"] for r in records])
    lengths = [r[key]["length_rad"] for r in records if r[key]["solved"]]
    overlapping = sum(r[key]["overlap"] > 0 for r in records)
    cpu = np.array([r[key]["cpu_seconds"] for r in records])
    return (f"| {label} | {len(records)} | {100 * solved:.0f}% | {100 * verified:.0f}% | {overlapping} | "
            f"{1000 * np.median(times):.0f} | {1000 * np.percentile(times, 95):.0f} | {1000 * times.max():.0f} | "
            f"{1000 * np.median(cpu):.0f} | {1000 * np.percentile(cpu, 95):.0f} | {np.median(lengths):.2f} |")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--queries", type=int, default=60, help="at least this many queries (two per object)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--time-limit", type=float, default=5.0, help="planning time limit per query (s)")
    parser.add_argument("--cache", type=Path, default=Path.home() / ".cache" / "image-assembly" / "mplib",
                        help="where the MPlib-ready Panda copy (and its generated SRDF) is written")
    parser.add_argument("--json", type=Path, help="write per-query results here")
    args = parser.parse_args(argv)
    scene = load_scene()
    urdf = mplib_panda_urdf(args.cache)
    theirs = MPlibPlanner(urdf, scene, args.time_limit, args.seed)
    lower = np.array([limit[0] for limit in theirs.planner.joint_limits[:7]])
    upper = np.array([limit[1] for limit in theirs.planner.joint_limits[:7]])
    ours = OurPlanner(scene, lower, upper, args.time_limit, args.seed)
    print(f"machine: {platform.machine()}, {os.cpu_count()} cores, Python {platform.python_version()}; "
          f"time limit {args.time_limit:.1f} s; seed {args.seed}", flush=True)
    queries, skipped = build_queries(scene, [ours, theirs], args.seed, args.queries)
    records = []
    for query in queries:
        record = {"query": query.name, "held": query.held is not None,
                  "start_q": query.start_q.tolist(), "goal_q": query.goal_q.tolist()}
        paths = {}
        for key, planner in (("ours", ours), ("mplib", theirs)):
            planner.set_world(query.obstacles, query.held, query.opening_m)
            start, cpu = time.perf_counter(), time.process_time()
            path = planner.plan(query)
            seconds, cpu_seconds = time.perf_counter() - start, time.process_time() - cpu
            paths[key] = path
            length = 0.0 if path is None else float(np.linalg.norm(np.diff(path, axis=0), axis=1).sum())
            record[key] = {"seconds": seconds, "cpu_seconds": cpu_seconds, "solved": path is not None,
                           "waypoints": 0 if path is None else len(path), "length_rad": length}
        for key, path in paths.items():
            check = {"samples": 0, "contact": 0, "overlap": 0, "first": "no path"}
            if path is not None:
                check = verify(path, query, ours, theirs)
            record[key].update(check)
            record[key]["verified"] = path is not None and check["contact"] == 0
        records.append(record)
        print(f"{query.name:55s} ours {record['ours']['seconds'] * 1000:7.0f} ms "
              f"{'ok' if record['ours']['verified'] else 'FAIL' if record['ours']['solved'] else 'none'}   "
              f"mplib {record['mplib']['seconds'] * 1000:7.0f} ms "
              f"{'ok' if record['mplib']['verified'] else 'FAIL' if record['mplib']['solved'] else 'none'}",
              flush=True)
        for key in ("ours", "mplib"):
            if record[key]["solved"] and not record[key]["verified"]:
                print(f"    {key}: {record[key]['contact']} of {record[key]['samples']} samples in contact "
                      f"({record[key]['overlap']} overlapping); first {record[key]['first']}", flush=True)
    print("\n| planner | queries | solved | collision-free (dense re-check) | paths overlapping | median ms | p95 ms | "
          "max ms | median CPU ms | p95 CPU ms | median length rad |")
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    print(_summary(ours.label, records, "ours"))
    print(_summary(theirs.label, records, "mplib"))
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps({"seed": args.seed, "time_limit_s": args.time_limit, "records": records,
                                         "skipped": skipped}, indent=1))
    sys.stdout.flush()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
