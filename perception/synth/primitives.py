"""Closed convex primitive meshes (vertex and face arrays) and the canonical part frame.

Every builder here returns ``(vertices, faces)`` for a solid centred at the origin of its bounding box,
"as built" (a prism's axis along z), with faces wound outward. :func:`canonical_frame` then turns such a
mesh into the part's canonical frame: bounding-box centre at the origin and box axes ordered by decreasing
extent (x longest, z thinnest), with the proper rotation that maps the canonical frame back to the
as-built orientation. Two parts built from the same numbers therefore have identical vertices, whatever
their orientation in the assembly.

Round sections are regular polygons of 24 sides with a vertex at angle 0, so there is a vertex every 15
degrees (at 0, 90, 180 and 270, and at the 120-degree spacing of three pedestal feet): a flat face placed at
distance ``r`` from the axis in one of those directions touches the polygon along that vertex's edge, without
overlapping it.
"""

from __future__ import annotations

import numpy as np

__all__ = [
    "ROUND_SIDES",
    "box",
    "square_frustum",
    "prism",
    "canonical_frame",
    "rotation_z",
]

ROUND_SIDES = 24  # sides of a round leg or column: a vertex every 15 degrees, one at angle 0

# Unit cube topology: vertex i has signs from bits (x: 4, y: 2, z: 1), faces wound outward.
_BOX_SIGNS = np.array([[(i >> 2) & 1, (i >> 1) & 1, i & 1] for i in range(8)], dtype=np.float64) * 2.0 - 1.0
_BOX_FACES = np.array(
    [[1, 3, 0], [4, 1, 0], [0, 3, 2], [2, 4, 0], [1, 7, 3], [5, 1, 4],
     [5, 7, 1], [3, 7, 2], [6, 4, 2], [2, 7, 6], [6, 5, 4], [7, 5, 6]],
    dtype=np.int64,
)  # fmt: skip
_PRISM_FACES: dict[int, np.ndarray] = {}


def box(extents) -> tuple[np.ndarray, np.ndarray]:
    """Rectangular box with the given full extents (x, y, z), centred at the origin."""
    half = 0.5 * np.asarray(extents, dtype=np.float64)
    return _BOX_SIGNS * half, _BOX_FACES.copy()


def square_frustum(bottom_width: float, top_width: float, height: float) -> tuple[np.ndarray, np.ndarray]:
    """Square-section frustum along z (a tapered leg): ``bottom_width`` at z = -h/2, ``top_width`` at +h/2.
    Centred on its bounding box (the axis is the box's vertical centre line)."""
    v = _BOX_SIGNS.copy()
    half_width = np.where(v[:, 2] > 0, 0.5 * top_width, 0.5 * bottom_width)
    v[:, 0] *= half_width
    v[:, 1] *= half_width
    v[:, 2] *= 0.5 * height
    return v, _BOX_FACES.copy()


def _prism_faces(sides: int) -> np.ndarray:
    faces = _PRISM_FACES.get(sides)
    if faces is None:
        k = np.arange(sides)
        a, b = k, (k + 1) % sides
        bottom_centre, top_centre = 2 * sides, 2 * sides + 1
        side1 = np.stack([a, b, sides + b], axis=1)
        side2 = np.stack([a, sides + b, sides + a], axis=1)
        top = np.stack([np.full(sides, top_centre), sides + a, sides + b], axis=1)
        bottom = np.stack([np.full(sides, bottom_centre), b, a], axis=1)
        faces = np.concatenate([side1, side2, top, bottom]).astype(np.int64)
        _PRISM_FACES[sides] = faces
    return faces.copy()


def prism(
    radius_x_bottom: float,
    radius_y_bottom: float,
    radius_x_top: float,
    radius_y_top: float,
    height: float,
    sides: int = ROUND_SIDES,
) -> tuple[np.ndarray, np.ndarray]:
    """Polygonal prism or frustum along z with elliptic section (a cylinder when all radii are equal, a cone
    frustum when top and bottom differ, an oval slab when x and y differ). Vertex k of each ring is at angle
    ``2 pi k / sides``; ``sides`` must be a multiple of 4 so the bounding box is exactly the radii."""
    if sides % 4 != 0 or sides < 8:
        raise ValueError(f"prism sides must be a multiple of 4 and at least 8, got {sides}")
    theta = 2.0 * np.pi * np.arange(sides) / sides
    c, s = np.cos(theta), np.sin(theta)
    # exact axis directions, so the bounding box and tangent contacts are exact
    quarter = sides // 4
    c[quarter :: 2 * quarter] = 0.0
    s[0 :: 2 * quarter] = 0.0
    h = 0.5 * height
    bottom = np.stack([radius_x_bottom * c, radius_y_bottom * s, np.full(sides, -h)], axis=1)
    top = np.stack([radius_x_top * c, radius_y_top * s, np.full(sides, h)], axis=1)
    centres = np.array([[0.0, 0.0, -h], [0.0, 0.0, h]])
    return np.concatenate([bottom, top, centres]), _prism_faces(sides)


def canonical_frame(vertices: np.ndarray, extents) -> tuple[np.ndarray, np.ndarray]:
    """Rotate an as-built mesh (centred at its bounding-box centre, box axes along x, y, z with full
    ``extents``) into the canonical frame: extents in decreasing order along x, y, z.

    Returns ``(canonical_vertices, rotation)`` where ``rotation`` (proper, det +1) maps canonical coordinates
    to as-built ones: ``as_built = rotation @ canonical``.
    """
    order = np.argsort(-np.asarray(extents, dtype=np.float64), kind="stable")
    rotation = np.zeros((3, 3))
    rotation[order, np.arange(3)] = 1.0
    if np.linalg.det(rotation) < 0:
        rotation[:, 2] *= -1.0
    return vertices @ rotation, rotation


def rotation_z(angle_rad: float) -> np.ndarray:
    """Rotation about +z by ``angle_rad``; exact at multiples of 90 degrees."""
    quarter_turns = angle_rad / (0.5 * np.pi)
    if abs(quarter_turns - round(quarter_turns)) < 1e-12:
        c, s = [(1.0, 0.0), (0.0, 1.0), (-1.0, 0.0), (0.0, -1.0)][int(round(quarter_turns)) % 4]
    else:
        c, s = float(np.cos(angle_rad)), float(np.sin(angle_rad))
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
