"""Collision checking of the Panda (and the part it holds) against a static world, with FCL.

Each link is the convex hull of its URDF collision mesh (slightly conservative, as in most motion planners);
the world is a set of named convex geometries with poses (table, jig pads, kitting parts, placed parts). A
configuration is valid when no held part touches the world, no finger comes within :data:`FINGER_CLEARANCE_M` of it,
no other link within :data:`LINK_CLEARANCE_M`, and no two non-adjacent links within :data:`SELF_CLEARANCE_M` of each
other.
Pure geometry: forward kinematics comes from the URDF chain of :mod:`planning.kinematics`, not from a simulator.

Speed (every planner calls this thousands of times): the chain is compiled once into seven revolute joints and
constant transforms, so forward kinematics is one batched Rodrigues formula and seven 4x4 products, for one
configuration or a batch (:meth:`RobotCollisionChecker.first_invalid`); every moving body (link hull, held-part
piece) and every world piece carries an oriented box. Broad phase in numpy for all bodies and configurations at
once: the bodies' boxes swept over the batch against the world's axis-aligned boxes, then per configuration the
axis-aligned boxes, then the oriented boxes' face axes (separating-axis test); FCL's exact convex test only on the
pairs left, with transforms set only on the bodies involved. The last configuration's poses are cached, so
``is_valid(q)`` followed by ``first_collision(q)`` does forward kinematics once.

Straight joint-space segments (:meth:`RobotCollisionChecker.segment_valid`) are checked at configurations spaced
so that no point of the robot or the held part moves more than ``max_step_m`` between two of them (a bound from
each joint's distance to the farthest point it moves), coarse to fine.
"""

from __future__ import annotations

import threading
from dataclasses import dataclass

import fcl
import numpy as np

from planning.collision import ConvexPart
from planning.gripper import convex_to_fcl, panda_urdf_path
from planning.kinematics import Chain, load_chain

ARM_JOINTS = tuple(f"panda_joint{i}" for i in range(1, 8))
FINGER_JOINTS = ("panda_finger_joint1", "panda_finger_joint2")
FINGER_LINKS = ("panda_leftfinger", "panda_rightfinger")
HAND_LINKS = ("panda_hand", *FINGER_LINKS)  # what the grasp planner checks (hand_ignore)
TCP_LINK = "panda_grasptarget"
BASE_LINK = "panda_link0"
# link pairs never checked against each other: neighbours in the chain and pairs that touch in every
# configuration (found by sampling 2,000 configurations, see tests/test_robot_collision.py)
_CHAIN = ["panda_link0", "panda_link1", "panda_link2", "panda_link3", "panda_link4", "panda_link5", "panda_link6",
          "panda_link7", "panda_hand"]


def _allowed_pairs() -> set[frozenset]:
    allowed = {frozenset((_CHAIN[i], _CHAIN[j])) for i in range(len(_CHAIN)) for j in range(i + 1, min(i + 3,
                                                                                                      len(_CHAIN)))}
    for finger in ("panda_leftfinger", "panda_rightfinger"):
        for link in ("panda_hand", "panda_link7", "panda_link6"):
            allowed.add(frozenset((finger, link)))
    allowed.add(frozenset(("panda_leftfinger", "panda_rightfinger")))
    allowed.add(frozenset(("panda_link5", "panda_hand")))  # the wrist's hulls overlap over the whole range
    return allowed


ALLOWED_SELF_PAIRS = _allowed_pairs()
_REQUEST = fcl.CollisionRequest()  # read-only; a fresh CollisionResult per call (results accumulate contacts)
_DISTANCE = fcl.DistanceRequest()
SELF_CLEARANCE_M = 0.003  # two links checked against each other must stay this far apart (PyBullet's hulls carry
# a margin of about 1.1 mm each, so links 0.01 mm apart in this model touch in the simulator)
LINK_CLEARANCE_M = 0.0015  # the arm's links and the hand stay this far from the world, for the same reason
FINGER_CLEARANCE_M = 0.0012  # the fingers this far from everything but what they grasp (which a query ignores):
# PyBullet's finger hulls stop about 1.1 mm short of a face, so a finger passing a placed rail 0.03 mm off in
# this model touched it in the simulator
SEGMENT_STEP_M = 0.002  # default: no point of the robot moves more than this between checks along a segment
_BATCH = 256  # configurations per vectorised forward-kinematics / broad-phase batch
# what each unit of collision checking costs on the reference machine (the standard 2-core Intel Xeon of
# benchmarks/RESULTS.md), in CPU seconds: a least-squares fit of the CPU time of 80 OMPL searches in five cell runs
# (the bundled chair and cabinet, and table_torsby_1549, bookcase_hensvik_0565 and cabinet_bjorken_0203 of
# ../shared/furniture) on their counts, within 0.82-1.19 of it for every search over 1 s. The query terms carry
# what each query costs besides (the validity wrappers, the torque check, OMPL's own work between checks)
WORK_S_PER_CONFIGURATION = 9.5e-6  # forward kinematics and broad phase, per configuration
WORK_S_PER_PAIR = 2.5e-5  # FCL's exact test, per candidate pair
WORK_S_PER_SINGLE_QUERY = 4.1e-4  # per is_valid or first_collision (one configuration)
WORK_S_PER_BATCH_QUERY = 3.3e-3  # per first_invalid or segment_valid (a batch)


class _CheckingWork(threading.local):
    configurations = 0
    pairs = 0
    single_queries = 0
    batch_queries = 0


_WORK = _CheckingWork()


def checking_work_s() -> float:
    """The collision checking this thread has done so far (all checkers together), in CPU seconds of the reference
    machine (:data:`WORK_S_PER_CONFIGURATION` and the like): a count, not a clock, so the same checks count the same
    on any machine, busy or idle. A search limited by it (``plan_joint_path(..., work=checking_work_s)``) ends at
    the same point everywhere."""
    work = _WORK
    return (work.configurations * WORK_S_PER_CONFIGURATION + work.pairs * WORK_S_PER_PAIR
            + work.single_queries * WORK_S_PER_SINGLE_QUERY + work.batch_queries * WORK_S_PER_BATCH_QUERY)


@dataclass(frozen=True)
class Collision:
    """The first colliding pair found: names of the two bodies (a link or ``"held <part>"``, then an obstacle
    name or a second link)."""

    a: str
    b: str

    def __str__(self) -> str:
        """In words: ``the held part 'seat' meets 'leg_1'``, ``panda_link5 meets 'table'``."""
        def words(name: str) -> str:
            if name.startswith("held "):
                return f"the held part {name[len('held '):]!r}"
            return name if name.startswith("panda_") else repr(name)

        return f"{words(self.a)} meets {words(self.b)}"


@dataclass(frozen=True)
class _CompiledChain:
    """The arm as anchors: anchor 0 is the robot base, anchor k (1..7) the child link of arm joint k.

    ``anchor[k] = anchor[parent[k-1]] @ parent_from_joint[k-1] @ rotation(axis[k-1], q[k-1])``; every other link
    hangs at a constant ``anchor_from_link`` from one anchor (fixed joints, fingers at the current opening).
    With Rodrigues' formula the rotation part of ``parent_from_joint @ rotation`` is
    ``P + sin(q) P K + (1 - cos(q)) P K^2`` (P the rotation of parent_from_joint, K the axis' cross matrix).
    """

    parent: tuple[int, ...]  # (7,) anchor index of each arm joint's parent link
    parent_from_joint: np.ndarray  # (7, 4, 4) from the parent's anchor to the joint frame (before motion)
    rotation_k: np.ndarray  # (7, 3, 3) P @ K
    rotation_k2: np.ndarray  # (7, 3, 3) P @ K @ K
    links: dict[str, tuple[int, np.ndarray]]  # link -> (anchor index, anchor_from_link (4, 4))


def _skew(axis: np.ndarray) -> np.ndarray:
    x, y, z = axis / np.linalg.norm(axis)
    return np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])


def _compile_chain(chain: Chain, opening_m: float) -> _CompiledChain:
    """Collapse ``chain`` around the seven arm joints, with the fingers at ``opening_m`` (metres, both together)
    and every other non-arm joint at 0."""
    links: dict[str, tuple[int, np.ndarray]] = {chain.root: (0, np.eye(4))}
    parent, parent_from_joint, axes = [], [], []
    for joint in chain.joints:
        anchor, anchor_from_parent = links[joint.parent]
        if joint.name in ARM_JOINTS:
            if joint.kind not in ("revolute", "continuous"):
                raise ValueError(f"arm joint {joint.name!r} is {joint.kind}; the checker expects revolute joints")
            if ARM_JOINTS.index(joint.name) != len(parent):
                raise ValueError(f"arm joint {joint.name!r} comes out of order in the URDF chain")
            parent.append(anchor)
            parent_from_joint.append(anchor_from_parent @ joint.parent_from_joint)
            axes.append(_skew(joint.axis))
            links[joint.child] = (len(parent), np.eye(4))
            continue
        motion = np.eye(4)
        if joint.kind == "prismatic" and joint.name in FINGER_JOINTS:
            motion[:3, 3] = joint.axis * (opening_m / 2.0)
        links[joint.child] = (anchor, anchor_from_parent @ joint.parent_from_joint @ motion)
    if len(parent) != len(ARM_JOINTS):
        raise ValueError(f"the URDF chain has {len(parent)} of the arm joints {ARM_JOINTS}")
    fixed = np.array(parent_from_joint)
    cross = np.array(axes)
    rotation_k = fixed[:, :3, :3] @ cross
    return _CompiledChain(tuple(parent), fixed, rotation_k, rotation_k @ cross, links)


def _anchors(compiled: _CompiledChain, world_from_base: np.ndarray, qs: np.ndarray) -> np.ndarray:
    """(N, 8, 4, 4) world poses of the base (0) and the child links of the seven arm joints (1..7) for the
    configurations ``qs`` (N, 7) radians."""
    sin, cos = np.sin(qs)[:, :, None, None], np.cos(qs)[:, :, None, None]
    steps = np.repeat(compiled.parent_from_joint[None], len(qs), axis=0)
    steps[:, :, :3, :3] += sin * compiled.rotation_k + (1.0 - cos) * compiled.rotation_k2
    anchors = np.empty((len(qs), 8, 4, 4))
    anchors[:, 0] = world_from_base
    for k, p in enumerate(compiled.parent):
        np.matmul(anchors[:, p], steps[:, k], out=anchors[:, k + 1])
    return anchors


def _sweep_radii(compiled: _CompiledChain, body_anchor: np.ndarray, body_corners: np.ndarray) -> np.ndarray:
    """(7,) metres: for each arm joint, an upper bound on the distance from its axis of any point of the bodies it
    moves (anchor origins chained by their offsets, plus each body's farthest box corner from its anchor).

    A straight joint-space motion by dq moves no point of the robot farther than ``sum(|dq| * radii)``: each
    joint's rotation moves a point at distance r from its axis by at most r times the angle."""
    offsets = np.linalg.norm(compiled.parent_from_joint[:, :3, 3], axis=1)  # joint k's origin in its parent anchor
    reach = np.linalg.norm(body_corners, axis=2).max(axis=1)  # (M,) farthest corner from the body's anchor origin
    radii = np.zeros(len(compiled.parent))
    for k in range(len(compiled.parent)):
        for anchor, r in zip(body_anchor, reach):
            distance, node = r, int(anchor)
            while node > k + 1:  # walk up to joint k's child anchor, adding the origin offsets on the way
                distance += offsets[node - 1]
                node = compiled.parent[node - 1]
            if node == k + 1:
                radii[k] = max(radii[k], distance)
    return radii


def _obb_overlap(centre_a: np.ndarray, axes_a: np.ndarray, half_a: np.ndarray, centre_b: np.ndarray,
                 axes_b: np.ndarray, half_b: np.ndarray) -> np.ndarray:
    """(P,) whether pairs of oriented boxes may overlap: not separated along any of the 6 face normals
    (centres (P, 3), axes (P, 3, 3) as columns, half extents (P, 3), metres). Conservative: the 9 edge-edge axes
    are not tested, so a few separated pairs pass to the exact test."""
    if len(centre_a) == 0:
        return np.zeros(0, dtype=bool)
    rotation = np.einsum("pki,pkj->pij", axes_a, axes_b)  # b's axes in a's frame
    spread = np.abs(rotation) + 1e-9
    offset = centre_b - centre_a
    in_a = np.einsum("pki,pk->pi", axes_a, offset)
    in_b = np.einsum("pkj,pk->pj", axes_b, offset)
    apart_a = np.abs(in_a) > half_a + np.einsum("pij,pj->pi", spread, half_b)
    apart_b = np.abs(in_b) > half_b + np.einsum("pij,pi->pj", spread, half_a)
    return ~(apart_a.any(axis=1) | apart_b.any(axis=1))


def _bisection_order(count: int) -> np.ndarray:
    """Indices 0..count-1, coarse to fine (the middle first, then the quarters, ...), so that a collision in an
    interval is usually found after few checks."""
    order, seen, step = [], np.zeros(count, dtype=bool), 1 << max(0, int(count).bit_length())
    while step >= 1:
        for index in range(step - 1, count, step):
            if not seen[index]:
                seen[index] = True
                order.append(index)
        step //= 2
    return np.array(order, dtype=np.int64)


def _fcl_transform(matrix: np.ndarray) -> fcl.Transform:
    return fcl.Transform(np.ascontiguousarray(matrix[:3, :3]), np.ascontiguousarray(matrix[:3, 3]))


def _oriented_hull(vertices: np.ndarray, faces: np.ndarray) -> tuple[fcl.CollisionObject, np.ndarray, np.ndarray]:
    """The hull as an FCL object in the frame of its minimum-volume oriented box: (object, link_from_box (4, 4),
    half extents (3,) metres)."""
    import trimesh

    hull = trimesh.Trimesh(vertices, faces, process=False)
    box = hull.bounding_box_oriented
    link_from_box = np.array(box.primitive.transform, dtype=np.float64)
    in_box = (vertices - link_from_box[:3, 3]) @ link_from_box[:3, :3]
    half = 0.5 * (in_box.max(axis=0) - in_box.min(axis=0))
    centre = 0.5 * (in_box.max(axis=0) + in_box.min(axis=0))  # re-centre exactly on the hull's extremes
    link_from_box[:3, 3] += link_from_box[:3, :3] @ centre
    in_box -= centre
    return fcl.CollisionObject(convex_to_fcl(in_box, faces)), link_from_box, half


class RobotCollisionChecker:
    """Validity of arm configurations in a world that the caller may replace.

    world_from_base: (4, 4) the robot base in the world frame (metres).
    obstacles: name -> (ConvexPart, world_from_part (4, 4)) of everything the robot must not touch; replace them
    with :meth:`set_obstacles`, skip some for one query with ``ignore``.
    held_only: check only the held part against the world (not the arm's links nor the links against each other),
    for a check added to another that already covers the robot (the held part grown by a clearance).
    Broad phase in numpy (FCL's managers hand back fresh Python wrappers in their callbacks, so the bodies could not
    be named); narrow phase: ``fcl.collide`` on convex pairs. Not thread-safe (FCL objects and the pose cache are
    shared).
    """

    def __init__(self, world_from_base: np.ndarray, obstacles: dict[str, tuple[ConvexPart, np.ndarray]],
                 urdf_path: str | None = None, self_clearance_m: float = SELF_CLEARANCE_M,
                 link_clearance_m: float = LINK_CLEARANCE_M, finger_clearance_m: float = FINGER_CLEARANCE_M,
                 held_only: bool = False) -> None:
        self.chain = load_chain(urdf_path or panda_urdf_path())
        self.self_clearance_m = float(self_clearance_m)
        self.link_clearance_m = float(link_clearance_m)
        self.finger_clearance_m = float(finger_clearance_m)
        self.world_from_base = np.asarray(world_from_base, dtype=np.float64)
        self.opening_m = 0.08
        self._compiled = _compile_chain(self.chain, self.opening_m)
        # robot bodies: one per collision mesh, each an FCL hull in its oriented-box frame
        self._link_names: list[str] = []
        self._link_objects: list[fcl.CollisionObject] = []
        self._mesh_from_box: list[np.ndarray] = []
        link_half = []
        for link, meshes in self.chain.collision.items():
            for mesh, link_from_mesh in meshes:
                hull = mesh.convex_hull
                obj, mesh_from_box, half = _oriented_hull(np.asarray(hull.vertices), np.asarray(hull.faces))
                self._link_names.append(link)
                self._link_objects.append(obj)
                self._mesh_from_box.append(link_from_mesh @ mesh_from_box)
                link_half.append(half)
        self._link_half = np.array(link_half)
        self.held_only = bool(held_only)
        # the base stands on its table
        self._links_vs_world = np.array([name != BASE_LINK and not held_only for name in self._link_names], dtype=bool)
        n = 0 if held_only else len(self._link_names)
        self._self_pairs = np.array([(i, j) for i in range(n) for j in range(i + 1, n)
                                     if frozenset((self._link_names[i], self._link_names[j])) not in ALLOWED_SELF_PAIRS
                                     and self._link_names[i] != self._link_names[j]], dtype=np.int64).reshape(-1, 2)
        self.held_name = ""
        self._held_part: ConvexPart | None = None
        self._tcp_from_part = np.eye(4)
        self._ignore_masks: dict[frozenset, np.ndarray] = {}
        self._rebuild_bodies()
        self.set_obstacles(obstacles)

    # --- world and held part ---------------------------------------------------------------------------------
    def set_obstacles(self, obstacles: dict[str, tuple[ConvexPart, np.ndarray]]) -> None:
        """Replace the world: name -> (ConvexPart, world_from_part (4, 4), metres). The robot model is kept."""
        names, objects, boxes, centres, axes, halves = [], [], [], [], [], []
        for name, (part, world_from_part) in obstacles.items():
            matrix = np.asarray(world_from_part, dtype=np.float64)
            if matrix.shape != (4, 4) or not np.all(np.isfinite(matrix)):
                raise ValueError(f"obstacle {name!r}: world_from_part must be a finite (4, 4) matrix, got shape "
                                 f"{matrix.shape}")
            transform = _fcl_transform(matrix)
            for geometry, vertices in zip(part.geometries, part.piece_vertices):
                objects.append(fcl.CollisionObject(geometry, transform))
                names.append(name)
                world = vertices @ matrix[:3, :3].T + matrix[:3, 3]
                boxes.append([world.min(axis=0), world.max(axis=0)])
                low, high = vertices.min(axis=0), vertices.max(axis=0)  # the piece's box in the part frame
                centres.append(matrix[:3, :3] @ (0.5 * (low + high)) + matrix[:3, 3])
                axes.append(matrix[:3, :3])
                halves.append(0.5 * (high - low))
        self.world_names: list[str] = names
        self.world_objects: list[fcl.CollisionObject] = objects
        self.world_boxes = np.array(boxes, dtype=np.float64).reshape(-1, 2, 3)
        self._world_upper = np.concatenate([self.world_boxes[:, 1], -self.world_boxes[:, 0]], axis=1)  # (W, 6)
        self._world_obb = (np.array(centres).reshape(-1, 3), np.array(axes).reshape(-1, 3, 3),
                           np.array(halves).reshape(-1, 3))  # oriented boxes: centre, axes (columns), half extents
        self._pair_masks: dict[frozenset, np.ndarray] = {}
        self._ignore_masks = {frozenset(): np.ones(len(names), dtype=bool)}

    @property
    def obstacle_names(self) -> frozenset[str]:
        return frozenset(self.world_names)

    def hold(self, part: ConvexPart | None, tcp_from_part: np.ndarray | None = None, opening_m: float = 0.08) -> None:
        """Attach ``part`` to the TCP at ``tcp_from_part`` (4, 4) (or release with None) and set the finger
        opening (metres between the fingers, 0-0.08)."""
        if part is not None and tcp_from_part is None:
            raise ValueError(f"holding {part.name!r} needs tcp_from_part, the part's pose in the TCP frame")
        if opening_m != self.opening_m:
            self.opening_m = float(opening_m)
            self._compiled = _compile_chain(self.chain, self.opening_m)
        self._held_part = part
        self.held_name = "" if part is None else f"held {part.name}"
        self._tcp_from_part = np.eye(4) if part is None else np.asarray(tcp_from_part, dtype=np.float64)
        self._rebuild_bodies()

    def _rebuild_bodies(self) -> None:
        """Stack the moving bodies (link hulls, then held pieces): anchor index, anchor_from_body, the body's box
        (centre, half extents) in its own frame, FCL object and name."""
        links = self._compiled.links
        anchor, anchor_from_body = [], []
        for name, mesh_from_box in zip(self._link_names, self._mesh_from_box):
            index, anchor_from_link = links[name]
            anchor.append(index)
            anchor_from_body.append(anchor_from_link @ mesh_from_box)
        centre = [np.zeros(3)] * len(self._link_names)
        half = list(self._link_half)
        objects, names = list(self._link_objects), list(self._link_names)
        if self._held_part is not None:
            index, anchor_from_tcp = links[TCP_LINK]
            anchor_from_part = anchor_from_tcp @ self._tcp_from_part
            for geometry, vertices in zip(self._held_part.geometries, self._held_part.piece_vertices):
                low, high = vertices.min(axis=0), vertices.max(axis=0)
                anchor.append(index)
                anchor_from_body.append(anchor_from_part)
                centre.append(0.5 * (low + high))
                half.append(0.5 * (high - low))
                objects.append(fcl.CollisionObject(geometry))
                names.append(self.held_name)
        self._body_anchor = np.array(anchor, dtype=np.int64)
        self._anchor_from_body = np.array(anchor_from_body)
        self._body_centre = np.array(centre)
        self._body_half = np.array(half)
        self._body_objects = objects
        self._body_names = names
        self._vs_world = np.concatenate([self._links_vs_world, np.ones(len(names) - len(self._link_names), bool)])
        self._body_pad = np.array([0.0 if i >= len(self._link_names) else
                                   self.finger_clearance_m if n in FINGER_LINKS else self.link_clearance_m
                                   for i, n in enumerate(names)])
        self._tcp_anchor, self._anchor_from_tcp = links[TCP_LINK]
        self._pair_masks = {}
        signs = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)], dtype=np.float64)
        corners = self._body_centre[:, None, :] + signs[None] * self._body_half[:, None, :]  # body frames
        corners = np.einsum("bij,bkj->bki", self._anchor_from_body[:, :3, :3], corners) + self._anchor_from_body[
            :, None, :3, 3]
        self.sweep_radii_m = _sweep_radii(self._compiled, self._body_anchor, corners)
        self._cached_q: bytes | None = None

    # --- poses ------------------------------------------------------------------------------------------------
    def _boxes(self, qs: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """For configurations ``qs`` (N, 7): anchors (N, 8, 4, 4), world_from_body (N, M, 4, 4), the bodies'
        oriented-box centres (N, M, 3) and their world-axis-aligned boxes, low and high (N, M, 3), metres."""
        _WORK.configurations += len(qs)
        anchors = _anchors(self._compiled, self.world_from_base, qs)
        world_from_body = anchors[:, self._body_anchor] @ self._anchor_from_body
        rotation = world_from_body[..., :3, :3]
        centre = np.einsum("nbij,bj->nbi", rotation, self._body_centre) + world_from_body[..., :3, 3]
        half = np.einsum("nbij,bj->nbi", np.abs(rotation), self._body_half)
        return anchors, world_from_body, centre, centre - half, centre + half

    def _poses(self, q: np.ndarray) -> None:
        """Cache the poses of configuration ``q`` (7,): the last one is often asked again (is_valid, then
        first_collision or world_from_tcp)."""
        key = q.tobytes()
        if key == self._cached_q:
            return
        anchors, world_from_body, centre, low, high = self._boxes(q[None])
        self._anchors_now = anchors[0]
        self._boxes_now = (world_from_body, centre, low, high)
        self._cached_q = key

    def link_frames(self, qs: np.ndarray) -> np.ndarray:
        """(N, 8, 4, 4) world poses of the base (0) and of the seven arm joints' child links (1..7, each joint's
        axis through its origin, along :meth:`joint_axes`) at configurations ``qs`` (N, 7) radians."""
        return _anchors(self._compiled, self.world_from_base, np.atleast_2d(np.asarray(qs, dtype=np.float64)))

    def joint_axes(self) -> np.ndarray:
        """(7, 3) each arm joint's axis in its child link's frame (see :meth:`link_frames`)."""
        return np.array([self.chain.joint(name).axis for name in ARM_JOINTS], dtype=np.float64)

    def anchor_of(self, link: str) -> tuple[int, np.ndarray]:
        """(index into :meth:`link_frames`, anchor_from_link (4, 4)) of any link of the chain (fingers at the
        current opening)."""
        index, anchor_from_link = self._compiled.links[link]
        return int(index), np.asarray(anchor_from_link, dtype=np.float64)

    def world_from_tcp(self, q: np.ndarray) -> np.ndarray:
        """(4, 4) the TCP (``panda_grasptarget``) in the world frame at arm configuration ``q`` (radians)."""
        self._poses(np.ascontiguousarray(q, dtype=np.float64))
        return self._anchors_now[self._tcp_anchor] @ self._anchor_from_tcp

    # --- queries ------------------------------------------------------------------------------------------------
    def _world_mask(self, ignore: frozenset[str]) -> np.ndarray:
        mask = self._ignore_masks.get(ignore)
        if mask is None:
            mask = np.array([name not in ignore for name in self.world_names], dtype=bool)
            self._ignore_masks[ignore] = mask
        return mask

    def _pair_mask(self, ignore: frozenset[str], held_ignore: frozenset[str] = frozenset(),
                   hand_ignore: frozenset[str] = frozenset()) -> np.ndarray:
        """(M, W) which body may meet which world piece: not the base link, not an obstacle in ``ignore``, for
        the held part's pieces not one in ``held_ignore`` either, and for the hand, the fingers and the held part
        not one in ``hand_ignore``."""
        key = (ignore, held_ignore, hand_ignore)
        mask = self._pair_masks.get(key)
        if mask is None:
            mask = self._vs_world[:, None] & self._world_mask(ignore)[None, :]
            if held_ignore:
                mask[len(self._link_names):] &= self._world_mask(ignore | held_ignore)[None, :]
            if hand_ignore:
                hand = np.array([i >= len(self._link_names) or name in HAND_LINKS
                                 for i, name in enumerate(self._body_names)])
                mask[hand] &= self._world_mask(ignore | hand_ignore)[None, :]
            self._pair_masks[key] = mask
        return mask

    def _candidates(self, world_from_body: np.ndarray, centre: np.ndarray, low: np.ndarray, high: np.ndarray,
                    ignore: frozenset[str], held_ignore: frozenset[str] = frozenset(),
                    hand_ignore: frozenset[str] = frozenset()) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Pairs that may touch, for N configurations: (configuration, rank, body, other) arrays, sorted by
        configuration then rank (0: link against a world piece, 1: two links, 2: held piece against a world
        piece). Broad phase: the bodies' boxes swept over the batch against the world boxes, then per configuration
        axis-aligned boxes, then the 6 face axes of the two oriented boxes (separating-axis test)."""
        rotation = world_from_body[..., :3, :3]
        lower = np.concatenate([low, -high], axis=2)  # (N, M, 6); boxes meet when lower_a <= upper_b
        upper = np.concatenate([high, -low], axis=2)
        padded = lower - self._body_pad[None, :, None]  # against the world: the links' clearance
        pair_mask = self._pair_mask(ignore, held_ignore, hand_ignore)
        if len(low) > 1:  # world pairs near the whole batch first, then per configuration
            swept = padded.min(axis=0)  # (M, 6)
            body, piece = np.nonzero((swept[:, None, :] <= self._world_upper).all(axis=2) & pair_mask)
            n, k = np.nonzero((padded[:, body] <= self._world_upper[piece]).all(axis=2))
            body, piece = body[k], piece[k]
        else:
            body, piece = np.nonzero((padded[0, :, None, :] <= self._world_upper).all(axis=2) & pair_mask)
            n = np.zeros(len(body), dtype=np.int64)
        first, second = self._self_pairs[:, 0], self._self_pairs[:, 1]
        n_self, k = np.nonzero((lower[:, first] - self.self_clearance_m <= upper[:, second]).all(axis=2))
        a, b = first[k], second[k]
        # one separating-axis test for both kinds of pairs
        w_centre, w_axes, w_half = self._world_obb
        keep = _obb_overlap(np.concatenate([centre[n, body], centre[n_self, a]]),
                            np.concatenate([rotation[n, body], rotation[n_self, a]]),
                            np.concatenate([self._body_half[body] + self._body_pad[body, None],
                                            self._body_half[a] + self.self_clearance_m]),
                            np.concatenate([w_centre[piece], centre[n_self, b]]),
                            np.concatenate([w_axes[piece], rotation[n_self, b]]),
                            np.concatenate([w_half[piece], self._body_half[b]]))
        configuration = np.concatenate([n, n_self])[keep]
        rank = np.concatenate([np.where(body < len(self._link_names), 0, 2), np.ones(len(a), dtype=np.int64)])[keep]
        order = np.lexsort((rank, configuration))
        return (configuration[order], rank[order], np.concatenate([body, a])[keep][order],
                np.concatenate([piece, b])[keep][order])

    def _narrow(self, world_from_body: np.ndarray, pairs) -> tuple[int, int, bool] | None:
        """FCL on one configuration's candidate pairs ((rank, body, other) triples, in order): (body, other,
        other_is_link) of the first collision, or None."""
        placed = np.zeros(len(self._body_objects), dtype=bool)
        objects = self._body_objects
        work = _WORK
        for rank, body, other in pairs:
            work.pairs += 1
            if not placed[body]:
                objects[body].setTransform(_fcl_transform(world_from_body[body]))
                placed[body] = True
            if rank == 1:
                if not placed[other]:
                    objects[other].setTransform(_fcl_transform(world_from_body[other]))
                    placed[other] = True
                if self.self_clearance_m > 0.0:
                    # GJK distance (-1 when they overlap); convex hulls, so this is as cheap as the boolean test
                    if fcl.distance(objects[body], objects[other], _DISTANCE, fcl.DistanceResult()) < \
                            self.self_clearance_m:
                        return int(body), int(other), True
                    continue
                target = objects[other]
            else:
                target = self.world_objects[other]
                pad = self._body_pad[body]
                if pad > 0.0:
                    if fcl.distance(objects[body], target, _DISTANCE, fcl.DistanceResult()) < pad:
                        return int(body), int(other), False
                    continue
            if fcl.collide(objects[body], target, _REQUEST, fcl.CollisionResult()):
                return int(body), int(other), rank == 1
        return None

    def _first_hit(self, q: np.ndarray, ignore: frozenset[str], held_ignore: frozenset[str] = frozenset(),
                   hand_ignore: frozenset[str] = frozenset()) -> tuple[int, int, bool] | None:
        q = np.ascontiguousarray(q, dtype=np.float64)
        if q.shape != (7,):
            raise ValueError(f"q must hold the 7 arm joint values (radians), got shape {q.shape}")
        _WORK.single_queries += 1
        self._poses(q)
        world_from_body, centre, low, high = self._boxes_now
        _, rank, body, other = self._candidates(world_from_body, centre, low, high, ignore, held_ignore,
                                                hand_ignore)
        if len(rank) == 0:
            return None
        return self._narrow(world_from_body[0], zip(rank.tolist(), body.tolist(), other.tolist()))

    def first_invalid(self, qs: np.ndarray, ignore: frozenset[str] = frozenset(),
                      order: np.ndarray | None = None, held_ignore: frozenset[str] = frozenset(),
                      hand_ignore: frozenset[str] = frozenset()) -> int | None:
        """Index of the first configuration of ``qs`` (N, 7) radians that collides, taken in ``order`` (default:
        0..N-1), or None when all are valid. Forward kinematics and the broad phase run for all at once.
        ``ignore``: obstacles skipped by every body; ``held_ignore``: obstacles skipped by the held part only (the
        neighbours it is planned to touch at its target, which the arm and fingers must still clear);
        ``hand_ignore``: obstacles skipped by the hand, the fingers and the held part, not by the arm's links (the
        part to be picked and its support, which the grasp planner checked the hand against)."""
        _WORK.batch_queries += 1
        qs = np.ascontiguousarray(qs, dtype=np.float64).reshape(-1, 7)
        ignore = frozenset(ignore)
        held_ignore = frozenset(held_ignore)
        hand_ignore = frozenset(hand_ignore)
        order = np.arange(len(qs)) if order is None else np.asarray(order)
        for chunk in range(0, len(qs), _BATCH):
            indices = order[chunk:chunk + _BATCH]
            _, world_from_body, centre, low, high = self._boxes(qs[indices])
            configuration, rank, body, other = self._candidates(world_from_body, centre, low, high, ignore,
                                                                held_ignore, hand_ignore)
            if len(configuration) == 0:
                continue
            starts = np.flatnonzero(np.r_[True, configuration[1:] != configuration[:-1]])
            ends = np.r_[starts[1:], len(configuration)]
            rank, body, other = rank.tolist(), body.tolist(), other.tolist()
            for start, end in zip(starts, ends):  # configurations in the given order; those without pairs are free
                n = configuration[start]
                if self._narrow(world_from_body[n], zip(rank[start:end], body[start:end], other[start:end])):
                    return int(indices[n])
        return None

    def segment_samples(self, q_from: np.ndarray, q_to: np.ndarray, max_step_m: float = SEGMENT_STEP_M) -> int:
        """How many steps the straight joint-space segment needs so that no point of the robot or the held part
        moves more than ``max_step_m`` (metres) between two checked configurations (bound from
        :attr:`sweep_radii_m`)."""
        sweep = float(np.abs(np.asarray(q_to, dtype=np.float64) - q_from) @ self.sweep_radii_m)
        return max(1, int(np.ceil(sweep / max_step_m)))

    def segment_valid(self, q_from: np.ndarray, q_to: np.ndarray, ignore: frozenset[str] = frozenset(),
                      max_step_m: float = SEGMENT_STEP_M, held_ignore: frozenset[str] = frozenset(),
                      hand_ignore: frozenset[str] = frozenset()) -> bool:
        """Whether the straight joint-space segment from ``q_from`` to ``q_to`` (7,) radians is free: ``q_to`` and
        the configurations in between, spaced so that no point of the robot or the held part moves more than
        ``max_step_m`` between checks, checked coarse to fine. ``q_from`` is taken as valid (checked by the
        caller, as OMPL's motion validators assume). ``ignore``, ``held_ignore``, ``hand_ignore``: as in
        :meth:`first_invalid`."""
        q_from = np.asarray(q_from, dtype=np.float64)
        q_to = np.asarray(q_to, dtype=np.float64)
        steps = self.segment_samples(q_from, q_to, max_step_m)
        fractions = np.arange(1, steps + 1) / steps
        qs = q_from + fractions[:, None] * (q_to - q_from)
        order = np.concatenate([[steps - 1], _bisection_order(steps - 1)])  # the end first, then inside
        return self.first_invalid(qs, ignore, order, held_ignore, hand_ignore) is None

    def first_collision(self, q: np.ndarray, ignore: frozenset[str] = frozenset(),
                        held_ignore: frozenset[str] = frozenset(),
                        hand_ignore: frozenset[str] = frozenset()) -> Collision | None:
        """The first collision at arm configuration ``q`` (7,) radians, or None when it is valid. Obstacles
        named in ``ignore`` are skipped for this query, those in ``held_ignore`` by the held part only, those in
        ``hand_ignore`` by the hand, fingers and held part (names not in the world are allowed and change
        nothing)."""
        hit = self._first_hit(q, frozenset(ignore), frozenset(held_ignore), frozenset(hand_ignore))
        if hit is None:
            return None
        body, other, other_is_link = hit
        return Collision(self._body_names[body],
                         self._body_names[other] if other_is_link else self.world_names[other])

    def is_valid(self, q: np.ndarray, ignore: frozenset[str] = frozenset(),
                 held_ignore: frozenset[str] = frozenset(), hand_ignore: frozenset[str] = frozenset()) -> bool:
        """Whether ``q`` (7,) radians is free of collisions, skipping the obstacles named in ``ignore`` (for the
        held part only, those in ``held_ignore``; for the hand, fingers and held part, those in ``hand_ignore``)."""
        return self._first_hit(q, frozenset(ignore), frozenset(held_ignore), frozenset(hand_ignore)) is None
