"""The Franka Panda hand's geometry: frames, dimensions and a light FCL collision model of hand + fingers.

Everything here is read from PyBullet's ``pybullet_data/franka_panda/panda.urdf`` (joint origins) and its collision
meshes ``franka_panda/meshes/collision/hand.obj`` and ``finger.obj``; the module-level constants below are those
values written out (``tests/test_grasp.py`` checks them against the files).

Frames (metres, quaternions w first, see :mod:`planning.pose`)
-----------------------------------------------------------------
``hand``
    The URDF link ``panda_hand``: origin at the flange face, +z pointing out of the flange towards the fingertips,
    +y the direction in which ``panda_leftfinger`` opens (``panda_finger_joint1`` axis ``(0, 1, 0)``).
``tcp`` (tool centre point, the grasp frame)
    Origin between the two finger pads, on the hand's z axis, at the URDF link ``panda_grasptarget``
    (``panda_grasptarget_hand`` joint: ``xyz = 0 0 0.105``, no rotation), with the same axes as ``hand``:

    - +z is the **approach direction**, from the hand towards the fingertips;
    - +y is the **finger closing axis** (the left finger sits at ``y = +opening/2``, the right one at ``-opening/2``);
    - +x = y cross z, the pads' width direction.

    ``HAND_FROM_TCP = Pose([0, 0, 0.105], identity)``: a TCP pose converts to the hand-link pose for inverse
    kinematics with ``world_from_hand = world_from_tcp @ HAND_FROM_TCP.inverse()`` (or ask PyBullet's IK for link
    11, ``panda_grasptarget``, directly with the TCP pose). The flat part of each finger's inner face (the pad)
    spans ``z = -10.4 mm .. +7.2 mm`` around the TCP (fingertip at +7.2 mm), so the TCP lies on the pads, 1.6 mm
    towards the fingertips from their centre.

Collision model
---------------
Three convex pieces, each the convex hull of a URDF collision mesh, as ``fcl.Convex`` objects: ``hand`` (102
vertices) and the two fingers (18 vertices each), the fingers placed at ``y = +/- opening/2`` for the requested
opening (the right finger turned by pi about z, as in the URDF). Convex hulls rather than fitted boxes because
pybullet_data's collision meshes are already convex (hull volume equals mesh volume to 0.1 %), so the hulls are
the URDF's own collision geometry, exactly, while boxes would either overlap the tapered fingertips or leave
gaps of several millimetres; and convex pieces matter for FCL: a convex shape tested against a triangle mesh is
treated as a solid, so a part lying wholly inside the palm is still reported (see ``../shared/STACK_NOTES.md``
for the mesh-mesh quirk). The one case FCL cannot see (a piece wholly *inside* a closed part mesh) is handled by
:meth:`GripperCollisionModel.collides`.
"""

from __future__ import annotations

import dataclasses
import functools
import os
import xml.etree.ElementTree as ET
from dataclasses import dataclass

import fcl
import numpy as np
import trimesh

from planning.pose import Pose

__all__ = [
    "MAX_OPENING_M",
    "FINGER_TRAVEL_M",
    "FINGER_JOINT_Z_IN_HAND_M",
    "TCP_Z_IN_HAND_M",
    "FINGERTIP_Z_IN_HAND_M",
    "PALM_Z_IN_HAND_M",
    "FINGER_PAD_LENGTH_M",
    "FINGER_PAD_WIDTH_M",
    "FINGER_PAD_DEPTH_M",
    "PAD_Z_RANGE_IN_TCP_M",
    "USABLE_FINGER_DEPTH_M",
    "TCP_TO_PALM_M",
    "HAND_FROM_TCP",
    "PIECE_NAMES",
    "hand_from_tcp",
    "HandGeometry",
    "GripperCollisionModel",
    "panda_urdf_path",
    "load_hand_geometry",
    "default_gripper",
    "convex_to_fcl",
    "mesh_to_fcl",
]

# --- constants (metres), from panda.urdf and its collision meshes --------------------------------------------------
FINGER_TRAVEL_M = 0.04
"""Stroke of each prismatic finger joint (``panda_finger_joint1/2``, limit 0 .. 0.04)."""
MAX_OPENING_M = 2 * FINGER_TRAVEL_M
"""Largest distance between the two pads: 0.08 m."""
FINGER_JOINT_Z_IN_HAND_M = 0.0584
"""z of the finger joints' origin in the hand frame."""
TCP_Z_IN_HAND_M = 0.105
"""z of ``panda_grasptarget`` (the TCP) in the hand frame."""
FINGERTIP_Z_IN_HAND_M = 0.1122
"""z of the fingertips in the hand frame (finger joint origin + 53.8 mm of finger)."""
PALM_Z_IN_HAND_M = 0.0660
"""z of the palm (the hand mesh's face between the fingers) in the hand frame."""
FINGER_PAD_LENGTH_M = 0.0176
"""Length of the flat inner face of a fingertip along the approach axis (finger z 36.2 .. 53.8 mm)."""
FINGER_PAD_WIDTH_M = 0.0175
"""Width of the pad along the TCP x axis."""
FINGER_PAD_DEPTH_M = 0.0143
"""Thickness of the fingertip behind its pad, along the closing axis: the room a finger needs beside a part."""
PAD_Z_RANGE_IN_TCP_M = (-0.0104, 0.0072)
"""(from, to) of the pad along the approach axis in the TCP frame."""
USABLE_FINGER_DEPTH_M = FINGERTIP_Z_IN_HAND_M - PALM_Z_IN_HAND_M
"""How far a part edge can go between the fingers, from the fingertips to the palm: 0.0462 m."""
TCP_TO_PALM_M = TCP_Z_IN_HAND_M - PALM_Z_IN_HAND_M
"""How far behind the TCP (towards the hand) a part edge may lie before it meets the palm: 0.039 m."""

HAND_FROM_TCP = Pose(np.array([0.0, 0.0, TCP_Z_IN_HAND_M]), np.array([1.0, 0.0, 0.0, 0.0]))
"""The TCP in the ``panda_hand`` link frame (``panda_grasptarget``)."""

PIECE_NAMES = ("hand", "left_finger", "right_finger")


def hand_from_tcp() -> Pose:
    """The TCP in the ``panda_hand`` link frame: ``HAND_FROM_TCP``, (0, 0, 0.105) m, no rotation."""
    return HAND_FROM_TCP


def panda_urdf_path() -> str:
    """Path of pybullet_data's ``franka_panda/panda.urdf`` on this machine."""
    import pybullet_data

    path = os.path.join(pybullet_data.getDataPath(), "franka_panda", "panda.urdf")
    if not os.path.isfile(path):
        raise FileNotFoundError(f"{path} does not exist; reinstall pybullet (it ships pybullet_data)")
    return path


# ---------------------------------------------------------------------------------------------------------
# reading the URDF
# ---------------------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class HandGeometry:
    """The hand as the URDF describes it (metres).

    hand_vertices, finger_vertices: (N, 3) float64 convex-hull vertices in the ``panda_hand`` / ``panda_leftfinger``
    link frames; hand_faces, finger_faces: (M, 3) int64 hull triangles. The right finger uses the same hull turned
    by ``right_finger_yaw_rad`` about z (URDF collision origin).
    """

    hand_vertices: np.ndarray
    hand_faces: np.ndarray
    finger_vertices: np.ndarray
    finger_faces: np.ndarray
    finger_joint_z_m: float
    finger_travel_m: float
    right_finger_yaw_rad: float
    tcp_z_m: float

    @property
    def fingertip_z_m(self) -> float:
        return self.finger_joint_z_m + float(self.finger_vertices[:, 2].max())

    @property
    def palm_z_m(self) -> float:
        return float(self.hand_vertices[:, 2].max())

    def pad_vertices(self) -> np.ndarray:
        """(K, 3) hull vertices on the finger's inner face (y within 0.5 mm of 0), finger link frame."""
        return self.finger_vertices[np.abs(self.finger_vertices[:, 1]) < 5e-4]


def _origin(joint: ET.Element) -> tuple[np.ndarray, np.ndarray]:
    origin = joint.find("origin")
    xyz = np.fromstring(origin.get("xyz", "0 0 0"), sep=" ") if origin is not None else np.zeros(3)
    rpy = np.fromstring(origin.get("rpy", "0 0 0"), sep=" ") if origin is not None else np.zeros(3)
    return xyz, rpy


def _hull(path: str) -> trimesh.Trimesh:
    mesh = trimesh.load(path, force="mesh", process=True)
    if not isinstance(mesh, trimesh.Trimesh) or len(mesh.faces) == 0:
        raise ValueError(f"{path}: no triangles in the Panda collision mesh")
    return mesh.convex_hull


@functools.lru_cache(maxsize=4)
def load_hand_geometry(urdf_path: str | None = None) -> HandGeometry:
    """Read the hand and finger collision geometry and joint origins from ``panda.urdf`` (cached)."""
    urdf_path = urdf_path or panda_urdf_path()
    root = ET.parse(urdf_path).getroot()
    joints = {j.get("name"): j for j in root.findall("joint")}
    links = {link.get("name"): link for link in root.findall("link")}
    for name in ("panda_finger_joint1", "panda_finger_joint2", "panda_grasptarget_hand"):
        if name not in joints:
            raise ValueError(f"{urdf_path}: joint {name!r} not found; is this the Franka Panda URDF?")
    finger_xyz, _ = _origin(joints["panda_finger_joint1"])
    tcp_xyz, tcp_rpy = _origin(joints["panda_grasptarget_hand"])
    if np.any(np.abs(tcp_xyz[:2]) > 1e-9) or np.any(np.abs(tcp_rpy) > 1e-9):
        raise ValueError(f"{urdf_path}: panda_grasptarget is expected on the hand's z axis, unrotated")
    travel = float(joints["panda_finger_joint1"].find("limit").get("upper"))

    def collision_mesh(link_name: str) -> tuple[str, np.ndarray]:
        collision = links[link_name].find("collision")
        filename = collision.find("geometry/mesh").get("filename").replace("package://", "")
        _, rpy = _origin(collision)
        return os.path.join(os.path.dirname(urdf_path), filename), rpy

    hand_file, _ = collision_mesh("panda_hand")
    finger_file, _ = collision_mesh("panda_leftfinger")
    _, right_rpy = collision_mesh("panda_rightfinger")
    hand, finger = _hull(hand_file), _hull(finger_file)
    return HandGeometry(
        hand_vertices=np.asarray(hand.vertices, dtype=np.float64),
        hand_faces=np.asarray(hand.faces, dtype=np.int64),
        finger_vertices=np.asarray(finger.vertices, dtype=np.float64),
        finger_faces=np.asarray(finger.faces, dtype=np.int64),
        finger_joint_z_m=float(finger_xyz[2]),
        finger_travel_m=travel,
        right_finger_yaw_rad=float(right_rpy[2]),
        tcp_z_m=float(tcp_xyz[2]),
    )


# ---------------------------------------------------------------------------------------------------------
# FCL helpers
# ---------------------------------------------------------------------------------------------------------


def convex_to_fcl(vertices: np.ndarray, faces: np.ndarray) -> fcl.Convex:
    """An ``fcl.Convex`` from a convex triangle mesh (vertices (N, 3) metres, faces (M, 3))."""
    faces = np.asarray(faces, dtype=np.int64)
    flat = np.hstack([np.full((len(faces), 1), 3, dtype=np.int64), faces]).ravel()
    return fcl.Convex(np.asarray(vertices, dtype=np.float64), len(faces), flat)


def mesh_to_fcl(mesh: trimesh.Trimesh) -> fcl.BVHModel:
    """An ``fcl.BVHModel`` (OBBRSS) of a triangle mesh in its own frame."""
    model = fcl.BVHModel()
    model.beginModel(len(mesh.vertices), len(mesh.faces))
    model.addSubModel(np.asarray(mesh.vertices, dtype=np.float64), np.asarray(mesh.faces, dtype=np.int64))
    model.endModel()
    return model


def _rot_z(angle: float) -> np.ndarray:
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


# ---------------------------------------------------------------------------------------------------------
# the collision model
# ---------------------------------------------------------------------------------------------------------


class GripperCollisionModel:
    """Hand + two fingers as three FCL convex pieces, posed by a TCP pose and an opening width.

    The FCL geometries are built once and shared; :meth:`collision_objects` makes fresh ``fcl.CollisionObject``
    wrappers, so one model can serve several threads.
    """

    def __init__(self, geometry: HandGeometry | None = None):
        self.geometry = geometry or load_hand_geometry()
        g = self.geometry
        self.max_opening_m = 2.0 * g.finger_travel_m
        self._fcl_geometries = (
            convex_to_fcl(g.hand_vertices, g.hand_faces),
            convex_to_fcl(g.finger_vertices, g.finger_faces),
            convex_to_fcl(g.finger_vertices, g.finger_faces),
        )
        self._piece_vertices = (g.hand_vertices, g.finger_vertices, g.finger_vertices)
        self._right_rotation = _rot_z(g.right_finger_yaw_rad)
        self._swept: dict[float, GripperCollisionModel] = {}  # distance -> swept_back(distance), built once

    # --- poses of the pieces ------------------------------------------------------------------------------
    def tcp_from_pieces(self, opening_m: float) -> np.ndarray:
        """(3, 4, 4) poses of (hand, left finger, right finger) link frames in the TCP frame at this opening."""
        opening_m = float(np.clip(opening_m, 0.0, self.max_opening_m))
        out = np.tile(np.eye(4), (3, 1, 1))
        z0 = -self.geometry.tcp_z_m
        out[0, 2, 3] = z0
        out[1, :3, 3] = (0.0, opening_m / 2.0, z0 + self.geometry.finger_joint_z_m)
        out[2, :3, :3] = self._right_rotation
        out[2, :3, 3] = (0.0, -opening_m / 2.0, z0 + self.geometry.finger_joint_z_m)
        return out

    def piece_vertices(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Hull vertices of (hand, left finger, right finger), each (N, 3) in its own link frame."""
        return self._piece_vertices

    def vertices(self, frame_from_tcp: Pose | np.ndarray, opening_m: float) -> np.ndarray:
        """(N, 3) hull vertices of all three pieces in the frame of ``frame_from_tcp`` (a Pose or (4, 4))."""
        m = frame_from_tcp.matrix() if isinstance(frame_from_tcp, Pose) else np.asarray(frame_from_tcp)
        pieces = m @ self.tcp_from_pieces(opening_m)
        return np.concatenate([v @ p[:3, :3].T + p[:3, 3] for v, p in zip(self._piece_vertices, pieces)])

    def collision_objects(self) -> list[fcl.CollisionObject]:
        """Fresh FCL objects for (hand, left finger, right finger), identity transforms; pose them with
        :meth:`set_pose`."""
        return [fcl.CollisionObject(g, fcl.Transform()) for g in self._fcl_geometries]

    def set_pose(self, objects: list[fcl.CollisionObject], frame_from_tcp: np.ndarray, opening_m: float) -> None:
        """Move objects from :meth:`collision_objects` to the TCP pose ``frame_from_tcp`` ((4, 4)) and opening."""
        pieces = np.asarray(frame_from_tcp) @ self.tcp_from_pieces(opening_m)
        for obj, p in zip(objects, pieces):
            obj.setTransform(fcl.Transform(p[:3, :3], p[:3, 3]))

    def swept_back(self, distance_m: float) -> GripperCollisionModel:
        """This hand with every piece swept ``distance_m`` back along -z (from the fingertips towards the hand):
        what the hand and fingers pass through on a straight approach of that length ending at the pose it is
        checked at, or on the retreat starting there, at a fixed opening. Each swept piece is the convex hull of
        the piece and its copy shifted back (a convex piece swept along a line stays convex), so one check of a
        pose covers the whole straight line, with no gap between samples. Built once per distance and kept (the
        same model serves every part, and caches keyed on the model, such as the grasp probes', keep working)."""
        if not np.isfinite(distance_m) or distance_m < 0.0:
            raise ValueError(f"distance_m must be a finite length >= 0, got {distance_m}")
        distance_m = float(distance_m)
        if distance_m not in self._swept:
            g = self.geometry
            hand = _swept_hull(g.hand_vertices, distance_m)
            finger = _swept_hull(g.finger_vertices, distance_m)
            self._swept[distance_m] = GripperCollisionModel(dataclasses.replace(
                g, hand_vertices=hand.vertices, hand_faces=hand.faces, finger_vertices=finger.vertices,
                finger_faces=finger.faces))
        return self._swept[distance_m]

    def collides(
        self,
        frame_from_tcp: Pose | np.ndarray,
        opening_m: float,
        other: fcl.CollisionObject,
        other_mesh: trimesh.Trimesh | None = None,
        frame_from_other: Pose | np.ndarray | None = None,
    ) -> bool:
        """Whether the hand at this TCP pose and opening overlaps ``other`` (an FCL object posed in the same frame).

        Pass ``other_mesh`` (the triangle mesh behind ``other``, in its own frame) and ``frame_from_other`` to also
        catch a piece lying wholly inside a closed mesh, which FCL's mesh-versus-convex test does not report.
        """
        m = frame_from_tcp.matrix() if isinstance(frame_from_tcp, Pose) else np.asarray(frame_from_tcp)
        objects = self.collision_objects()
        self.set_pose(objects, m, opening_m)
        request = fcl.CollisionRequest()
        for obj in objects:
            if fcl.collide(obj, other, request, fcl.CollisionResult()):
                return True
        if other_mesh is None:
            return False
        if frame_from_other is None:
            frame_from_other = np.eye(4)
        f = frame_from_other.matrix() if isinstance(frame_from_other, Pose) else np.asarray(frame_from_other)
        other_from_frame = np.linalg.inv(f)
        pieces = m @ self.tcp_from_pieces(opening_m)
        probes = np.array([(p @ np.append(v.mean(axis=0), 1.0))[:3] for v, p in zip(self._piece_vertices, pieces)])
        probes = probes @ other_from_frame[:3, :3].T + other_from_frame[:3, 3]
        return bool(np.any(other_mesh.contains(probes)))


@functools.lru_cache(maxsize=1)
def default_gripper() -> GripperCollisionModel:
    """The collision model of pybullet_data's Panda hand (built once)."""
    return GripperCollisionModel()


def _swept_hull(vertices: np.ndarray, distance_m: float) -> trimesh.Trimesh:
    shifted = vertices - np.array([0.0, 0.0, distance_m])
    hull = trimesh.convex.convex_hull(np.concatenate([vertices, shifted]))
    return trimesh.Trimesh(np.asarray(hull.vertices, dtype=np.float64), np.asarray(hull.faces, dtype=np.int64),
                           process=False)


def _grown(vertices: np.ndarray, margin_m: float) -> np.ndarray:
    low, high = vertices.min(axis=0), vertices.max(axis=0)
    centre, extent = 0.5 * (low + high), high - low
    return (vertices - centre) * ((extent + 2.0 * margin_m) / np.maximum(extent, 1e-12)) + centre


@functools.lru_cache(maxsize=4)
def clearance_gripper(margin_m: float) -> GripperCollisionModel:
    """The hand and fingers grown by about ``margin_m`` on every side (scaled about each piece's centre): a grasp
    clear of obstacles with this model keeps that clearance, which a simulator's or a real hand's slightly
    larger geometry needs."""
    g = load_hand_geometry()
    grown = dataclasses.replace(g, hand_vertices=_grown(g.hand_vertices, margin_m),
                                finger_vertices=_grown(g.finger_vertices, margin_m))
    return GripperCollisionModel(grown)
