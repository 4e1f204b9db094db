"""Collision checking of the Panda (and the part it holds) against a static world, with FCL.

Each link is the convex hull of its URDF collision mesh (slightly conservative, as in most motion planners);
the world is a set of named convex geometries with poses (table, jig pads, kitting parts, placed parts). A
configuration is valid when no link and no held part touches the world and no two non-adjacent links touch.
Pure geometry: forward kinematics comes from :mod:`planning.kinematics`, not from a simulator.
"""

from __future__ import annotations

from dataclasses import dataclass

import fcl
import numpy as np

from planning.collision import ConvexPart
from planning.gripper import convex_to_fcl, panda_urdf_path
from planning.kinematics import load_chain

ARM_JOINTS = tuple(f"panda_joint{i}" for i in range(1, 8))
FINGER_JOINTS = ("panda_finger_joint1", "panda_finger_joint2")
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


def _transform(matrix: np.ndarray) -> fcl.Transform:
    return fcl.Transform(matrix[:3, :3], matrix[:3, 3])


@dataclass(frozen=True)
class Collision:
    """The first colliding pair found: names of the two bodies."""

    a: str
    b: str


class RobotCollisionChecker:
    """Validity of arm configurations in a fixed world.

    world_from_base: (4, 4) the robot base in the world frame.
    obstacles: name -> (ConvexPart, world_from_part 4x4) of everything the robot must not touch.
    Broad phase: axis-aligned boxes in numpy (FCL's managers hand back fresh Python wrappers in their callbacks,
    so the bodies could not be named); narrow phase: ``fcl.collide`` on convex pairs.
    """

    def __init__(self, world_from_base: np.ndarray, obstacles: dict[str, tuple[ConvexPart, np.ndarray]],
                 urdf_path: str | None = None) -> None:
        self.chain = load_chain(urdf_path or panda_urdf_path())
        self.world_from_base = np.asarray(world_from_base, dtype=np.float64)
        # robot: (link name, fcl object, link_from_mesh, hull vertices in the mesh frame)
        self.links = []
        for link, meshes in self.chain.collision.items():
            for mesh, link_from_mesh in meshes:
                hull = mesh.convex_hull
                geometry = convex_to_fcl(hull.vertices, hull.faces)
                self.links.append((link, fcl.CollisionObject(geometry), link_from_mesh, np.asarray(hull.vertices)))
        self.world_names: list[str] = []
        self.world_objects: list[fcl.CollisionObject] = []
        boxes = []
        for name, (part, world_from_part) in obstacles.items():
            matrix = np.asarray(world_from_part, dtype=np.float64)
            for geometry, vertices in zip(part.geometries, part.piece_vertices):
                self.world_objects.append(fcl.CollisionObject(geometry, _transform(matrix)))
                self.world_names.append(name)
                world = vertices @ matrix[:3, :3].T + matrix[:3, 3]
                boxes.append([world.min(axis=0), world.max(axis=0)])
        self.world_boxes = np.array(boxes).reshape(-1, 2, 3)
        self.held: list[tuple[fcl.CollisionObject, np.ndarray, np.ndarray]] = []
        self.held_name = ""
        self.opening_m = 0.08
        n = len(self.links)
        self._self_pairs = np.array([(i, j) for i in range(n) for j in range(i + 1, n)
                                     if frozenset((self.links[i][0], self.links[j][0])) not in ALLOWED_SELF_PAIRS
                                     and self.links[i][0] != self.links[j][0]], dtype=np.int64).reshape(-1, 2)

    def hold(self, part: ConvexPart | None, tcp_from_part: np.ndarray | None = None, opening_m: float = 0.08) -> None:
        """Attach ``part`` to the TCP at ``tcp_from_part`` (or release with None) and set the finger opening."""
        self.opening_m = opening_m
        self.held = []
        self.held_name = ""
        if part is None:
            return
        self.held_name = f"held {part.name}"
        for geometry, vertices in zip(part.geometries, part.piece_vertices):
            self.held.append((fcl.CollisionObject(geometry), np.asarray(tcp_from_part, dtype=np.float64), vertices))

    def _link_poses(self, q: np.ndarray) -> dict[str, np.ndarray]:
        positions = dict(zip(ARM_JOINTS, q))
        for finger in FINGER_JOINTS:
            positions[finger] = self.opening_m / 2.0
        base_from_link = self.chain.link_poses(positions)
        return {link: self.world_from_base @ m for link, m in base_from_link.items()}

    def world_from_tcp(self, q: np.ndarray) -> np.ndarray:
        return self._link_poses(q)[TCP_LINK]

    def _against_world(self, obj: fcl.CollisionObject, box: np.ndarray, name: str) -> Collision | None:
        if len(self.world_boxes) == 0:
            return None
        lo, hi = box
        near = np.flatnonzero(np.all(self.world_boxes[:, 0] <= hi, axis=1)
                              & np.all(self.world_boxes[:, 1] >= lo, axis=1))
        for k in near:
            if fcl.collide(obj, self.world_objects[k], fcl.CollisionRequest(), fcl.CollisionResult()):
                return Collision(name, self.world_names[k])
        return None

    def first_collision(self, q: np.ndarray) -> Collision | None:
        """The first collision at arm configuration ``q`` (radians), or None when it is valid."""
        world_from_link = self._link_poses(q)
        boxes = []
        for link, obj, link_from_mesh, vertices in self.links:
            matrix = world_from_link[link] @ link_from_mesh
            obj.setTransform(_transform(matrix))
            world = vertices @ matrix[:3, :3].T + matrix[:3, 3]
            box = np.array([world.min(axis=0), world.max(axis=0)])
            boxes.append(box)
            if link == BASE_LINK:
                continue  # mounted on the table: static, and touching its support by design
            hit = self._against_world(obj, box, link)
            if hit:
                return hit
        boxes = np.array(boxes)
        first, second = self._self_pairs[:, 0], self._self_pairs[:, 1]
        overlapping = np.all(boxes[first, 0] <= boxes[second, 1], axis=1) & np.all(
            boxes[second, 0] <= boxes[first, 1], axis=1)
        for i, j in self._self_pairs[overlapping]:
            if fcl.collide(self.links[i][1], self.links[j][1], fcl.CollisionRequest(), fcl.CollisionResult()):
                return Collision(self.links[i][0], self.links[j][0])
        if self.held:
            world_from_tcp = world_from_link[TCP_LINK]
            for obj, tcp_from_part, vertices in self.held:
                matrix = world_from_tcp @ tcp_from_part
                obj.setTransform(_transform(matrix))
                world = vertices @ matrix[:3, :3].T + matrix[:3, 3]
                hit = self._against_world(obj, np.array([world.min(axis=0), world.max(axis=0)]), self.held_name)
                if hit:
                    return hit
        return None

    def is_valid(self, q: np.ndarray) -> bool:
        return self.first_collision(q) is None
