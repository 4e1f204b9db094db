"""Whether a grasp of a part lying in the kitting area clears what is around it at the pick.

The hand is checked with a little clearance (:data:`HAND`) against the part's own support and the table, over the
whole straight approach; with more (:data:`NEIGHBOUR_HAND`) against the other slots' parts and pedestals; and
with more again (:data:`TILTED_HAND`) where the fingers close on a slant. A part standing on a narrow foot that a
slanted hand would tip over is judged by :func:`tips_under`. Frames: world (metres, +z up) unless a name says
otherwise; grasps are in the part frame.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence

import numpy as np
import trimesh

from planning.grasp import APPROACH_M, Grasp, feasible_grasps, grasp_pose_key
from planning.gripper import clearance_gripper
from planning.pose import Pose
from planning.stability import centre_of_mass

HAND_CLEARANCE_M = 0.002  # grasps keep this from pedestals and neighbours (real hands are larger) ...
TILTED_CLEARANCE_M = 0.004  # ... and this where the fingers close on a slant, sliding down a round part towards
# its support (2 mm was measured too little in simulation)
# ... and this from the other slots' parts and pedestals: the arm's approach keeps the task planner's transit
# clearance (3 mm) from them where it can, and the simulator's Panda hulls are about 1.1 mm larger than the model
# (with 2 mm, a hand coming down beside a cabinet's top lying in the kit grazed it)
NEIGHBOUR_CLEARANCE_M = 0.0035
HAND = clearance_gripper(HAND_CLEARANCE_M)
TILTED_HAND = clearance_gripper(TILTED_CLEARANCE_M)
NEIGHBOUR_HAND = clearance_gripper(NEIGHBOUR_CLEARANCE_M)
FROM_ABOVE = np.cos(np.radians(30.0))  # a pick from above: the approach within 30 degrees of straight down
LEVEL_FINGERS = np.sin(np.radians(10.0))  # at the pick, grasps closing within 10 degrees of level come first
# a part standing with its centre of mass higher than this many times its foot's reach from it, across the fingers'
# closing axis, tips over its foot when a hand approaching on a slant closes on it (chair_5's back slat, standing
# 24 cm tall on a 25 mm foot, tipped 4.9 degrees under fingers coming 30 degrees off vertical and was carried so)
TIPPING_HEIGHT_RATIO = 3.0
SLANTED_APPROACH = np.cos(np.radians(10.0))  # an approach more than 10 degrees off straight down is slanted
FOOT_M = 0.002  # a part's foot: its points within this height of its lowest point


def finger_tilt(world_from_part_rotation: np.ndarray, grasp: Grasp) -> float:
    """|sin| of the angle between the fingers' closing axis and the horizontal, the part turned as given."""
    return abs(float((world_from_part_rotation @ grasp.part_from_tcp.rotation[:, 1])[2]))


def slanted(world_from_part: Pose, grasp: Grasp) -> bool:
    """Whether the fingers close neither level nor vertically at this pose of the part."""
    return LEVEL_FINGERS < finger_tilt(world_from_part.rotation, grasp) < np.cos(np.radians(10.0))


def tips_under(mesh: trimesh.Trimesh, world_from_part: Pose):
    """``tips(grasp)``: whether the part, standing at ``world_from_part``, would tip over its foot as the hand of
    ``grasp`` closes on it: the approach is slanted (:data:`SLANTED_APPROACH`), the fingers close level
    (:data:`LEVEL_FINGERS`), and along the horizontal direction across the closing axis (the fingers' flat pads
    leave a turn about that axis free; chocks hold a standing board along it) the foot straddles the centre of
    mass but reaches less than 1 / :data:`TIPPING_HEIGHT_RATIO` of its height from it. A foot (the points within
    :data:`FOOT_M` of the lowest) to one side of the centre of mass is not all the part rests on (chair_agne_0010's
    curved frame lying flat, which the rest check found stable): not judged."""
    rotation = world_from_part.rotation
    points = mesh.vertices @ rotation.T
    low = float(points[:, 2].min())
    foot = points[points[:, 2] <= low + FOOT_M]
    com = rotation @ centre_of_mass(mesh)
    height = float(com[2]) - low

    def tips(grasp: Grasp) -> bool:
        tcp = rotation @ grasp.part_from_tcp.rotation
        if -float(tcp[2, 2]) >= SLANTED_APPROACH:
            return False
        if abs(float(tcp[2, 1])) > LEVEL_FINGERS:
            return False  # the fingers close on a tilt: not a part standing between level fingers
        across = np.cross(tcp[:, 1], [0.0, 0.0, 1.0])
        along = (foot - com) @ (across / np.linalg.norm(across))
        lever = min(float(along.max()), float(-along.min()))
        return 0.0 <= lever and lever * TIPPING_HEIGHT_RATIO < height

    return tips


def picks_from_above(grasps: Sequence[Grasp], rest_from_part: np.ndarray) -> int:
    """How many ``grasps`` approach from above with level fingers when the part lies in this rest pose."""
    rotation = rest_from_part[:3, :3]
    return sum(float((rotation @ grasp.part_from_tcp.rotation[:, 2])[2]) <= -FROM_ABOVE
               and finger_tilt(rotation, grasp) <= LEVEL_FINGERS for grasp in grasps)


def clear_at_pick(grasps: Sequence[Grasp], world_from_part: Pose, obstacles, floor_z: float,
                  gripper, approach_m: float = 0.0) -> list[Grasp]:
    """The ``grasps`` (in their order) whose hand is clear of ``obstacles`` both opened to its opening at the pick
    (``Grasp.opening_at_pick_m``), as it arrives (over the last ``approach_m`` of its straight approach too), and
    closed to ``width_m`` on the part, as it lifts: a closing fingertip that reaches below a board's edge moves
    towards the pedestal under it (5 mm per finger), which the open hand alone does not show."""
    arriving = [dataclasses.replace(g, opening_m=g.opening_at_pick_m) for g in grasps]
    kept = {grasp_key(g) for g in feasible_grasps(arriving, world_from_part, obstacles, None, floor_z=floor_z,
                                                   retreat_m=approach_m, gripper=gripper, closed_gripper=gripper)}
    return [g for g, at_pick in zip(grasps, arriving) if grasp_key(at_pick) in kept]


def neighbour_hand_for(world_from_part: Pose, grasp: Grasp):
    """The hand model a grasp at the pick is checked with against other slots' bodies: :data:`TILTED_HAND` where
    its fingers close on a slant, else :data:`NEIGHBOUR_HAND`."""
    return TILTED_HAND if slanted(world_from_part, grasp) else NEIGHBOUR_HAND


def pickable(grasps: Sequence[Grasp], world_from_part: Pose, support, floor_z: float,
              neighbours=()) -> list[Grasp]:
    """The ``grasps`` clear at the pick (:func:`clear_at_pick`) of the ``support`` (the part's pedestal) and the
    floor with :data:`HAND`, along the whole straight approach (the arm's motion does not check the hand against
    them), and of the ``neighbours`` (other slots' bodies; for a board lying on a board, the one under it too) with
    :data:`NEIGHBOUR_HAND`; those whose fingers close on a slant checked with :data:`TILTED_HAND` against both."""
    feasible = clear_at_pick(grasps, world_from_part, support, floor_z, HAND, approach_m=APPROACH_M)
    if neighbours and feasible:
        feasible = clear_at_pick(feasible, world_from_part, list(neighbours), None, NEIGHBOUR_HAND)
    on_slant = [g for g in feasible if slanted(world_from_part, g)]
    spoiled = {grasp_key(g) for g in on_slant} - {grasp_key(g) for g in clear_at_pick(
        on_slant, world_from_part, list(support) + list(neighbours), floor_z, TILTED_HAND)}
    return [g for g in feasible if grasp_key(g) not in spoiled]


def grasp_key(grasp: Grasp) -> tuple:
    """The same grasp whatever its ranking scores (ranking returns re-scored copies), at the same openings."""
    return grasp_pose_key(grasp) + (round(grasp.opening_m, 9), round(grasp.opening_at_pick_m, 9))
