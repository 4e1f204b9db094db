"""Kitting: where and how each loose part lies before the robot picks it.

Every part starts at rest in one of its stable poses (trimesh's ``compute_stable_poses``) on a pedestal in the
kitting area. A pedestal is a box under the part, inset from its footprint like the jig pads
(:mod:`planning.fixture`), so that fingers can reach under a board's edge. For each part the planner picks the
most probable stable pose in which some grasp works both at the pick (clear of the pedestal, the table and
the neighbouring parts) and at the target (clear of the parts placed before it), and lays the parts out in rows.

Limits of this first version: the layout is rows in one rectangle, the robot's reach is not checked, and a
grasp is checked against its own pedestal only (the 10 cm gap between parts stands for the hand's room).

Frames: ``kitting`` poses are in the world frame of the cell (metres, +z up, table top at ``table_z_m``).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import trimesh

from planning.fixture import FINGER_CLEARANCE_M, MIN_PAD_FRACTION
from planning.grasp import Grasp, feasible_grasps
from planning.pose import Pose

LAYOUT_GAP_M = 0.1  # free space between neighbouring parts' footprints, for the hand


@dataclass(frozen=True)
class Pedestal:
    size_m: tuple[float, float, float]
    world_from_pedestal: Pose  # box centre

    def mesh(self) -> trimesh.Trimesh:
        return trimesh.creation.box(self.size_m)


@dataclass(frozen=True)
class KittingSlot:
    """Where one part starts: its pose (world), the pedestal under it, and the grasp to pick and place it."""

    part: str
    world_from_part: Pose
    pedestal: Pedestal
    grasp: Grasp
    stable_pose_probability: float


class KittingError(RuntimeError):
    """No stable pose and grasp serve a part at both pick and place, or the parts do not fit the area."""


def stable_rest_poses(mesh: trimesh.Trimesh, max_poses: int = 6) -> list[tuple[np.ndarray, float]]:
    """(rest_from_part 4x4, probability), most probable first: the part resting on z = 0, centred in x-y."""
    transforms, probabilities = trimesh.poses.compute_stable_poses(mesh, n_samples=1, threshold=0.0)
    out = []
    for transform, probability in sorted(zip(transforms, probabilities), key=lambda tp: -tp[1])[:max_poses]:
        moved = mesh.vertices @ transform[:3, :3].T + transform[:3, 3]
        centre = 0.5 * (moved.min(axis=0) + moved.max(axis=0))
        shift = np.eye(4)
        shift[:3, 3] = [-centre[0], -centre[1], -moved[:, 2].min()]
        out.append((shift @ transform, float(probability)))
    return out


def pedestal_for(footprint_min: np.ndarray, footprint_max: np.ndarray, table_z_m: float,
                 height_m: float) -> Pedestal:
    """A pedestal under a footprint (x-y bounds, world), inset for the fingers, top at ``table_z_m + height_m``."""
    extent = footprint_max - footprint_min
    inset = np.minimum(FINGER_CLEARANCE_M, 0.5 * (1.0 - MIN_PAD_FRACTION) * extent)
    size = np.maximum(extent - 2 * inset, 1e-3)
    centre = 0.5 * (footprint_min + footprint_max)
    return Pedestal((float(size[0]), float(size[1]), height_m),
                    Pose([centre[0], centre[1], table_z_m + 0.5 * height_m], [1.0, 0.0, 0.0, 0.0]))


def plan_kitting(names: list[str], meshes: list[trimesh.Trimesh], candidates: dict[str, list[Grasp]],
                 grasp_ok_at_target: Callable[[str, Grasp], bool], area_origin_xy: np.ndarray,
                 area_size_xy: np.ndarray, table_z_m: float, pedestal_height_m: float) -> list[KittingSlot]:
    """A slot for every part, laid out in rows from ``area_origin_xy`` (the area's corner, world x-y).

    ``grasp_ok_at_target(part, grasp)`` says whether a grasp (part frame) also works where the part is placed.
    """
    slots: list[KittingSlot] = []
    cursor = np.array(area_origin_xy, dtype=np.float64)
    row_depth = 0.0
    area_end = np.asarray(area_origin_xy) + np.asarray(area_size_xy)
    for name, mesh in zip(names, meshes):
        chosen = None
        for rest_from_part, probability in stable_rest_poses(mesh):
            rested = mesh.vertices @ rest_from_part[:3, :3].T + rest_from_part[:3, 3]
            half = 0.5 * (rested.max(axis=0) - rested.min(axis=0))
            if cursor[0] + 2 * half[0] > area_end[0]:  # next row
                cursor = np.array([area_origin_xy[0], cursor[1] + row_depth + LAYOUT_GAP_M])
                row_depth = 0.0
            centre_xy = cursor + half[:2]
            world_from_rest = Pose([centre_xy[0], centre_xy[1], table_z_m + pedestal_height_m], [1, 0, 0, 0])
            world_from_part = world_from_rest @ Pose.from_matrix(rest_from_part)
            pedestal = pedestal_for(centre_xy - half[:2], centre_xy + half[:2], table_z_m, pedestal_height_m)
            at_pick = feasible_grasps(candidates[name], world_from_part,
                                      [(pedestal.mesh(), pedestal.world_from_pedestal)], None, floor_z=table_z_m)
            usable = [g for g in at_pick if grasp_ok_at_target(name, g)]
            if usable:
                chosen = KittingSlot(name, world_from_part, pedestal, usable[0], probability)
                cursor = cursor + [2 * half[0] + LAYOUT_GAP_M, 0.0]
                row_depth = max(row_depth, 2 * half[1])
                break
        if chosen is None:
            raise KittingError(f"part {name!r}: no stable pose in which one grasp works both at the pick and at "
                               "its target")
        if chosen.world_from_part.position[1] + row_depth / 2 > area_end[1] + 1e-9:
            raise KittingError(f"the parts do not fit the kitting area of {area_size_xy[0]:.2f} x "
                               f"{area_size_xy[1]:.2f} m (stopped at part {name!r})")
        slots.append(chosen)
    return slots
