"""A part's own symmetries, and pose errors that do not count them.

A symmetry of a part is a rotation about its centre that maps its surface onto itself: a box turned half a turn
about any of its axes looks exactly the same, so a simulated part that ends up that way is where it should be.
Candidates are the 24 proper rotations that permute and flip the axes of two frames through the surface centroid
(the principal axes of the surface's second moments, and the part's own axes): those that keep the second
moments are checked by mapping surface samples and measuring their distance to the surface. An axis about which
turns by odd angles are symmetries too is an axis of continuous symmetry (a solid of revolution).

Frames and units: everything here is in the part's mesh frame, metres; rotations are (3, 3) matrices acting on
part-frame coordinates about :attr:`PartSymmetry.centre_m`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import trimesh

from planning.pose import AXIS_ROTATIONS, Pose, matrix_to_quat

SYMMETRY_TOLERANCE_M = 0.001  # farthest a mapped surface sample may lie from the surface
SURFACE_SAMPLES = 600
_FIRST_CHUNK = 48  # samples checked before the rest: most candidates that are no symmetry fail here
MOMENT_TOLERANCE = 0.02  # relative change of the second moments a candidate may cause before it is checked
CONTINUOUS_TEST_DEG = (37.0, 101.0)  # turns that no discrete symmetry of a furniture part has


@dataclass(frozen=True)
class PartSymmetry:
    """The symmetries of one part (part frame, metres).

    centre_m: (3,) the surface centroid, fixed by every symmetry.
    rotations: discrete symmetries, (3, 3) rotation matrices about ``centre_m``; the identity first.
    axes: unit axes through ``centre_m`` of continuous symmetry; two or more mean any rotation is a symmetry.
    """

    centre_m: np.ndarray
    rotations: tuple[np.ndarray, ...]
    axes: tuple[np.ndarray, ...] = ()


def surface_moments(mesh: trimesh.Trimesh) -> tuple[np.ndarray, np.ndarray]:
    """(centre (3,), second-moment tensor (3, 3) about it) of the surface as a uniform sheet, exact per triangle;
    also right for open meshes. Metres and m^2 (per unit area)."""
    triangles = np.asarray(mesh.triangles, dtype=np.float64)
    areas = np.asarray(mesh.area_faces, dtype=np.float64)
    total = float(areas.sum())
    if total <= 0:
        raise ValueError("a mesh without area has no surface moments")
    centre = (areas[:, None] * triangles.mean(axis=1)).sum(axis=0) / total
    local = triangles - centre
    corner_sum = local.sum(axis=1)  # (F, 3)
    # mean of x x^T over a triangle with corners a, b, c: ((a+b+c)(a+b+c)^T + a a^T + b b^T + c c^T) / 12
    second = (np.einsum("fi,fj->fij", corner_sum, corner_sum) + np.einsum("fki,fkj->fij", local, local)) / 12.0
    return centre, (areas[:, None, None] * second).sum(axis=0) / total


def _rotation(axis: np.ndarray, angle_rad: float) -> np.ndarray:
    axis = axis / np.linalg.norm(axis)
    k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + np.sin(angle_rad) * k + (1 - np.cos(angle_rad)) * k @ k


def _maps_onto_itself(mesh: trimesh.Trimesh, samples: np.ndarray, centre: np.ndarray, rotation: np.ndarray,
                      tolerance_m: float) -> bool:
    mapped = (samples - centre) @ rotation.T + centre
    for chunk in (mapped[:_FIRST_CHUNK], mapped[_FIRST_CHUNK:]):
        if len(chunk) and float(np.max(trimesh.proximity.closest_point(mesh, chunk)[1])) > tolerance_m:
            return False
    return True


def part_symmetry(mesh: trimesh.Trimesh, tolerance_m: float = SYMMETRY_TOLERANCE_M, samples: int = SURFACE_SAMPLES,
                  seed: int = 0) -> PartSymmetry:
    """The symmetries of ``mesh`` (part frame, metres): rotations about its surface centroid that move no surface
    sample (``samples`` points, seeded) farther than ``tolerance_m`` from the surface."""
    centre, moments = surface_moments(mesh)
    points = np.asarray(trimesh.sample.sample_surface(mesh, samples, seed=seed)[0], dtype=np.float64)
    eigenvalues, principal = np.linalg.eigh(moments)
    if np.linalg.det(principal) < 0:
        principal[:, 0] *= -1.0
    scale = max(float(np.abs(eigenvalues).max()), 1e-12)
    axes = []
    for k in range(3):  # an axis of revolution has the two other moments equal
        others = [eigenvalues[j] for j in range(3) if j != k]
        if abs(others[0] - others[1]) > MOMENT_TOLERANCE * scale:
            continue
        axis = principal[:, k]
        if all(_maps_onto_itself(mesh, points, centre, _rotation(axis, np.radians(a)), tolerance_m)
               for a in CONTINUOUS_TEST_DEG):
            axes.append(axis)
    if len(axes) >= 2:  # a sphere: every rotation
        return PartSymmetry(centre, (np.eye(3),), tuple(axes))
    found: list[np.ndarray] = [np.eye(3)]
    for frame in (principal, np.eye(3)):
        for permutation in AXIS_ROTATIONS:
            rotation = frame @ permutation @ frame.T
            if any(np.allclose(rotation, known, atol=1e-6) for known in found):
                continue
            if np.abs(rotation @ moments @ rotation.T - moments).max() > MOMENT_TOLERANCE * scale:
                continue
            if _maps_onto_itself(mesh, points, centre, rotation, tolerance_m):
                found.append(rotation)
    return PartSymmetry(centre, tuple(found), tuple(axes))


def rotation_error_deg(symmetry: PartSymmetry, world_from_target: Pose, world_from_actual: Pose) -> float:
    """Smallest rotation (degrees, 0..180) between the target and the actual pose of a part over its symmetries:
    a part turned by one of them is not rotated at all."""
    if len(symmetry.axes) >= 2:
        return 0.0
    relative = world_from_target.rotation.T @ world_from_actual.rotation  # part frame
    best = np.pi
    for rotation in symmetry.rotations:
        w, *v = matrix_to_quat(relative @ rotation)
        if symmetry.axes:  # best turn about the axis: |scalar part| rises to sqrt(w^2 + (v . axis)^2)
            along = float(np.dot(v, symmetry.axes[0]))
            w = np.sqrt(w * w + along * along)
        best = min(best, 2.0 * float(np.arccos(min(1.0, abs(w)))))
    return float(np.degrees(best))


def position_error_m(symmetry: PartSymmetry, world_from_target: Pose, world_from_actual: Pose) -> float:
    """Distance (metres) between the part's centre at the target and where it actually is; the centre is fixed by
    every symmetry, so this does not depend on which of them the part ended up in."""
    centre = symmetry.centre_m
    return float(np.linalg.norm(world_from_actual.apply(centre) - world_from_target.apply(centre)))
