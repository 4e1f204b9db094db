"""Forward kinematics of a serial URDF chain in numpy, with each link's collision geometry.

Pure geometry: no simulator. Link poses are ``base_from_link`` 4x4 matrices (metres) in the robot's base frame
(the URDF root link). Revolute and prismatic joints are supported; fixed joints carry their origin.
"""

from __future__ import annotations

import functools
import os
import xml.etree.ElementTree as ET
from dataclasses import dataclass, field

import numpy as np
import trimesh


def _rpy_matrix(rpy: np.ndarray) -> np.ndarray:
    r, p, y = rpy
    cr, sr, cp, sp, cy, sy = np.cos(r), np.sin(r), np.cos(p), np.sin(p), np.cos(y), np.sin(y)
    return np.array([[cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr],
                     [sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr],
                     [-sp, cp * sr, cp * cr]])


def _origin(element: ET.Element | None) -> np.ndarray:
    matrix = np.eye(4)
    if element is not None:
        matrix[:3, 3] = [float(v) for v in element.get("xyz", "0 0 0").split()]
        matrix[:3, :3] = _rpy_matrix(np.array([float(v) for v in element.get("rpy", "0 0 0").split()]))
    return matrix


def _axis_rotation(axis: np.ndarray, angle: float) -> np.ndarray:
    x, y, z = axis
    c, s = np.cos(angle), np.sin(angle)
    t = 1 - c
    return np.array([[t * x * x + c, t * x * y - s * z, t * x * z + s * y],
                     [t * x * y + s * z, t * y * y + c, t * y * z - s * x],
                     [t * x * z - s * y, t * y * z + s * x, t * z * z + c]])


@dataclass(frozen=True)
class Joint:
    name: str
    kind: str  # "revolute", "prismatic" or "fixed"
    parent: str
    child: str
    parent_from_joint: np.ndarray  # (4, 4)
    axis: np.ndarray  # (3,) in the joint frame
    lower: float
    upper: float


@dataclass
class Chain:
    """A kinematic tree read from a URDF; ``joints`` in an order where parents come before children."""

    root: str
    joints: list[Joint]
    collision: dict[str, list[tuple[trimesh.Trimesh, np.ndarray]]] = field(default_factory=dict)  # link_from_mesh
    centre_of_mass: dict[str, np.ndarray] = field(default_factory=dict)  # link frame, metres (the URDF's inertial)

    def joint(self, name: str) -> Joint:
        for j in self.joints:
            if j.name == name:
                return j
        raise KeyError(f"no joint {name!r}")

    def link_poses(self, positions: dict[str, float]) -> dict[str, np.ndarray]:
        """``base_from_link`` (4, 4) for every link, given joint positions (missing joints at 0)."""
        poses = {self.root: np.eye(4)}
        for joint in self.joints:
            motion = np.eye(4)
            value = positions.get(joint.name, 0.0)
            if joint.kind in ("revolute", "continuous"):
                motion[:3, :3] = _axis_rotation(joint.axis, value)
            elif joint.kind == "prismatic":
                motion[:3, 3] = joint.axis * value
            poses[joint.child] = poses[joint.parent] @ joint.parent_from_joint @ motion
        return poses


def _load_mesh(path: str) -> trimesh.Trimesh:
    return trimesh.load(path, force="mesh", process=True)


@functools.lru_cache(maxsize=4)
def load_chain(urdf_path: str) -> Chain:
    """Parse ``urdf_path``: joints and the collision meshes of every link (loaded from the URDF's folder)."""
    tree = ET.parse(urdf_path)
    robot = tree.getroot()
    folder = os.path.dirname(urdf_path)
    joints = []
    children = set()
    for element in robot.findall("joint"):
        limit = element.find("limit")
        axis = element.find("axis")
        joints.append(Joint(
            name=element.get("name"),
            kind=element.get("type"),
            parent=element.find("parent").get("link"),
            child=element.find("child").get("link"),
            parent_from_joint=_origin(element.find("origin")),
            axis=np.array([float(v) for v in (axis.get("xyz") if axis is not None else "1 0 0").split()]),
            lower=float(limit.get("lower", 0)) if limit is not None else 0.0,
            upper=float(limit.get("upper", 0)) if limit is not None else 0.0,
        ))
        children.add(joints[-1].child)
    links = [link.get("name") for link in robot.findall("link")]
    root = next(name for name in links if name not in children)
    ordered, known = [], {root}
    pending = list(joints)
    while pending:  # parents before children
        ready = [j for j in pending if j.parent in known]
        if not ready:
            raise ValueError(f"{urdf_path}: joints do not form a tree")
        for j in ready:
            ordered.append(j)
            known.add(j.child)
            pending.remove(j)
    collision: dict[str, list[tuple[trimesh.Trimesh, np.ndarray]]] = {}
    for link in robot.findall("link"):
        for element in link.findall("collision"):
            mesh_element = element.find("geometry/mesh")
            if mesh_element is None:
                continue
            filename = mesh_element.get("filename")
            if filename.startswith("package://"):  # a ROS package path: pybullet_data keeps it beside the URDF
                filename = filename[len("package://"):]
            mesh = _load_mesh(os.path.join(folder, filename))
            collision.setdefault(link.get("name"), []).append((mesh, _origin(element.find("origin"))))
    centre_of_mass = {}
    for link in robot.findall("link"):
        origin = link.find("inertial/origin")
        if link.find("inertial") is not None:
            centre_of_mass[link.get("name")] = np.array(
                [float(v) for v in (origin.get("xyz", "0 0 0") if origin is not None else "0 0 0").split()])
    return Chain(root, ordered, collision, centre_of_mass)
