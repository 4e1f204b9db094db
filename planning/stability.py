"""How a part rests on a flat support: its stable poses, where it touches the support, and whether those points
hold its centre of mass.

Frames: a *rest* frame has the support's top at z = 0 (+z up), the part's lowest point on it and its footprint
centred on the origin in x-y; ``rest_from_part`` (4x4) poses the part's own mesh frame there. Metres throughout.
Used by kitting (:mod:`planning.kitting`) for the parts lying on their pedestals (:mod:`planning.pedestal`); the
simulator's check of the same, with physics, is :mod:`cell.resting`.
"""

from __future__ import annotations

import numpy as np
import trimesh

SUPPORT_MARGIN_M = 0.002  # the centre of mass lies at least this far inside the points a part rests on
CONTACT_HEIGHT_M = 1e-4  # vertices this close to the support touch it (a round part's facets rise faster)
TIP_ANGLE_DEG = 10.0  # a resting part must not tip over when tilted by this much


def stable_rest_poses(mesh: trimesh.Trimesh, max_poses: int = 6) -> list[tuple[np.ndarray, float]]:
    """(rest_from_part 4x4, probability), most probable first: the part resting on z = 0, centred in x-y."""
    with np.errstate(invalid="ignore"):  # a sliver face's solid angle is sqrt(< 0): NaN, taken as improbable below
        transforms, probabilities = trimesh.poses.compute_stable_poses(mesh, n_samples=1, threshold=0.0)
    probabilities = np.nan_to_num(np.asarray(probabilities, dtype=np.float64), nan=0.0)
    out = []
    for transform, probability in sorted(zip(transforms, probabilities), key=lambda tp: -tp[1])[:max_poses]:
        moved = mesh.vertices @ transform[:3, :3].T + transform[:3, 3]
        centre = 0.5 * (moved.min(axis=0) + moved.max(axis=0))
        shift = np.eye(4)
        shift[:3, 3] = [-centre[0], -centre[1], -moved[:, 2].min()]
        out.append((shift @ transform, float(probability)))
    return out


def upright_rest_pose(mesh: trimesh.Trimesh, world_from_part_rotation: np.ndarray) -> np.ndarray:
    """``rest_from_part`` (4x4) of the part turned as ``world_from_part_rotation`` (e.g. as it sits in the
    assembly), lowest point on z = 0, centred in x-y. Whether it rests stably there is checked per support."""
    transform = np.eye(4)
    transform[:3, :3] = world_from_part_rotation
    moved = mesh.vertices @ world_from_part_rotation.T
    centre = 0.5 * (moved.min(axis=0) + moved.max(axis=0))
    transform[:3, 3] = [-centre[0], -centre[1], -moved[:, 2].min()]
    return transform


def centre_of_mass(mesh: trimesh.Trimesh) -> np.ndarray:
    """The part's centre of mass (part frame, metres): of its volume when closed, else its surface centroid."""
    if mesh.is_watertight and mesh.volume > 1e-12:
        return np.asarray(mesh.center_mass, dtype=np.float64)
    return np.asarray(mesh.centroid, dtype=np.float64)


def inside_convex(points: np.ndarray, polygon: np.ndarray) -> np.ndarray:
    """Which 2-D ``points`` lie inside the convex ``polygon`` (corners in order, either direction)."""
    edges = np.roll(polygon, -1, axis=0) - polygon
    cross = edges[None, :, 0] * (points[:, None, 1] - polygon[None, :, 1]) \
        - edges[None, :, 1] * (points[:, None, 0] - polygon[None, :, 0])
    return np.all(cross >= -1e-12, axis=1) | np.all(cross <= 1e-12, axis=1)


def clip_to_convex(polygon: np.ndarray, convex: np.ndarray) -> np.ndarray:
    """``polygon`` (2-D corners) clipped to the ``convex`` polygon (Sutherland-Hodgman)."""
    first, second = convex[1] - convex[0], convex[2] - convex[1]
    orientation = np.sign(first[0] * second[1] - first[1] * second[0]) or 1.0  # 2-D cross product
    out = polygon
    for a, b in zip(convex, np.roll(convex, -1, axis=0)):
        if len(out) == 0:
            break
        edge = b - a
        side = orientation * (edge[0] * (out[:, 1] - a[1]) - edge[1] * (out[:, 0] - a[0]))
        kept = []
        for k in range(len(out)):
            j = (k + 1) % len(out)
            if side[k] >= 0:
                kept.append(out[k])
            if (side[k] >= 0) != (side[j] >= 0):
                t = side[k] / (side[k] - side[j])
                kept.append(out[k] + t * (out[j] - out[k]))
        out = np.array(kept).reshape(-1, 2)
    return out


def touching_points(mesh: trimesh.Trimesh, rest_from_part: np.ndarray,
                    support_rest_xy: np.ndarray) -> np.ndarray:
    """(K, 2) rest-frame x-y points where the resting part touches the support: its lowest vertices over the
    support's outline, and its lowest faces clipped to that outline."""
    rested = mesh.vertices @ rest_from_part[:3, :3].T + rest_from_part[:3, 3]
    low = rested[:, 2] < CONTACT_HEIGHT_M
    support = np.asarray(support_rest_xy, dtype=np.float64)
    pieces = [rested[low, :2][inside_convex(rested[low, :2], support)]]
    for face in mesh.faces[np.all(low[mesh.faces], axis=1)]:
        clipped = clip_to_convex(rested[face, :2], support)
        if len(clipped):
            pieces.append(clipped)
    return np.concatenate(pieces)


def rests_stably(mesh: trimesh.Trimesh, rest_from_part: np.ndarray, support_rest_xy: np.ndarray | list[np.ndarray],
                 margin_m: float = SUPPORT_MARGIN_M) -> bool:
    """Whether the part, lying in its rest pose (rest frame: lowest point at z = 0), stands on a support whose top
    is the convex polygon ``support_rest_xy`` (rest frame x-y, at z = 0): the points where it touches the
    support surround its centre of mass with ``margin_m`` to spare, more for a high centre of mass (it must
    survive a tilt of :data:`TIP_ANGLE_DEG`). (A stable pose of the part's hull is not
    enough on a pedestal inset from the footprint, nor for parts whose underside is not flat.) A support of several
    tops (posts) is a sequence of such polygons: the part's points on any of them hold it."""
    single = isinstance(support_rest_xy, np.ndarray) and support_rest_xy.ndim == 2
    outlines = [support_rest_xy] if single else list(support_rest_xy)
    touching = np.concatenate([touching_points(mesh, rest_from_part, outline) for outline in outlines])
    if len(touching) < 3:
        return False
    from scipy.spatial import ConvexHull, QhullError

    try:
        hull = touching[ConvexHull(touching).vertices]
    except QhullError:  # collinear: a knife edge
        return False
    com_rest = rest_from_part[:3, :3] @ centre_of_mass(mesh) + rest_from_part[:3, 3]
    # a tall part needs a wider base: it must survive a tilt of TIP_ANGLE_DEG (bumps, the arm passing by)
    margin_m = max(margin_m, float(com_rest[2]) * np.tan(np.radians(TIP_ANGLE_DEG)))
    probes = com_rest[:2] + margin_m * np.array([[0, 0], [1, 0], [-1, 0], [0, 1], [0, -1]])
    return bool(np.all(inside_convex(probes, hull)))
