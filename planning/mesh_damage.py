"""Broken copies of clean part meshes, as real-world exports come: inputs for tests and benchmarks of
:mod:`planning.mesh_intake`.

Each damage takes a closed, outward mesh and a seed (``numpy.random.default_rng(seed)``) and returns a new mesh in
the same frame and unit (``process=False``: exactly the faces written here):

- ``double_sided``: every face also drawn with the opposite winding (the most common export);
- ``inside_out``: every face's winding reversed;
- ``half_flipped``: a random half of the faces reversed;
- ``holes``: 3% of the faces removed at random;
- ``one_surface``: only the faces of one large flat side of a board (a board drawn as one surface; for parts whose
  least extent is at most a fifth of their middle one and whose side is flat; others come back unchanged, see
  :func:`is_board`);
- ``soup``: triangle soup: every face with its own three vertices, in random order, half of them reversed, 3%
  removed;
- ``split``: two loose open pieces, a 1 mm slice through the centre missing between them, the second
  inside-out.

:data:`AS_EXPORTED` (``as_exported``) combines them per part at the rates counted on 602 parts of 78 real furniture
models as exported (surface models of retail furniture): see :func:`as_exported`.
"""

from __future__ import annotations

import numpy as np
import trimesh

DAMAGES = ("double_sided", "inside_out", "half_flipped", "holes", "one_surface", "soup", "split")
HOLE_FRACTION = 0.03
AS_EXPORTED = "as_exported"
# per part, the share of the 602 counted parts with each flaw (they overlap: 371 double-sided, 236 open shells,
# 50 with inconsistent winding, 15 inside-out, 10 boards drawn as one surface; 2 closed volumes)
EXPORT_RATES = {"double_sided": 371 / 602, "holes": 236 / 602, "half_flipped": 50 / 602, "inside_out": 15 / 602,
                "one_surface": 10 / 602}


def _mesh(vertices: np.ndarray, faces: np.ndarray) -> trimesh.Trimesh:
    return trimesh.Trimesh(np.asarray(vertices, dtype=np.float64), np.asarray(faces, dtype=np.int64), process=False)


def _flip(faces: np.ndarray, mask: np.ndarray) -> np.ndarray:
    out = np.array(faces)
    out[mask] = out[mask][:, ::-1]
    return out


def _flat_side(mesh: trimesh.Trimesh, seed: int) -> np.ndarray | None:
    """The faces of one large flat side of a board as a face mask: those whose normals lie within 30 degrees of its
    least principal axis, on one side, their vertices within 1 mm of a plane; of two such sides the larger, or
    one picked at random (``seed``) where both are as large. None when ``mesh`` is no flat board (least extent
    more than a fifth of the middle one, or no flat side)."""
    centred = np.asarray(mesh.vertices) - np.asarray(mesh.vertices).mean(axis=0)
    axes = np.linalg.svd(centred, full_matrices=False)[2]
    spread = np.ptp(centred @ axes.T, axis=0)
    if spread[2] > 0.2 * spread[1]:
        return None
    facing = mesh.face_normals @ axes[2]
    sides = [facing > np.cos(np.radians(30)), facing < -np.cos(np.radians(30))]
    flat = [side for side in sides
            if side.any() and np.ptp(centred[np.unique(np.asarray(mesh.faces)[side])] @ axes[2]) <= 0.001]
    if not flat:
        return None
    areas = [float(mesh.area_faces[side].sum()) for side in flat]
    if len(flat) == 2 and abs(areas[0] - areas[1]) <= 1e-9 * max(areas):
        return flat[int(np.random.default_rng(seed).integers(2))]
    return flat[int(np.argmax(areas))]


def is_board(mesh: trimesh.Trimesh) -> bool:
    """Whether ``mesh`` is a flat board that ``one_surface`` draws as one surface."""
    return _flat_side(mesh, 0) is not None


def double_sided(mesh: trimesh.Trimesh, seed: int) -> trimesh.Trimesh:
    faces = np.asarray(mesh.faces)
    return _mesh(mesh.vertices, np.concatenate([faces, faces[:, ::-1]]))


def inside_out(mesh: trimesh.Trimesh, seed: int) -> trimesh.Trimesh:
    return _mesh(mesh.vertices, np.asarray(mesh.faces)[:, ::-1])


def half_flipped(mesh: trimesh.Trimesh, seed: int) -> trimesh.Trimesh:
    rng = np.random.default_rng(seed)
    return _mesh(mesh.vertices, _flip(mesh.faces, rng.random(len(mesh.faces)) < 0.5))


def holes(mesh: trimesh.Trimesh, seed: int) -> trimesh.Trimesh:
    rng = np.random.default_rng(seed)
    keep = rng.random(len(mesh.faces)) >= HOLE_FRACTION
    return _mesh(mesh.vertices, np.asarray(mesh.faces)[keep])


def one_surface(mesh: trimesh.Trimesh, seed: int) -> trimesh.Trimesh:
    """The faces of one large flat side of a board, or ``mesh`` unchanged when it is no flat board."""
    side = _flat_side(mesh, seed)
    if side is None:
        return mesh
    surface = _mesh(mesh.vertices, np.asarray(mesh.faces)[side])
    surface.remove_unreferenced_vertices()
    return surface


def soup(mesh: trimesh.Trimesh, seed: int) -> trimesh.Trimesh:
    rng = np.random.default_rng(seed)
    faces = np.asarray(mesh.faces)
    faces = faces[rng.permutation(len(faces))]
    faces = faces[rng.random(len(faces)) >= HOLE_FRACTION]
    faces = _flip(faces, rng.random(len(faces)) < 0.5)
    vertices = np.asarray(mesh.vertices)[faces.reshape(-1)]
    return _mesh(vertices, np.arange(len(vertices)).reshape(-1, 3))


def split(mesh: trimesh.Trimesh, seed: int) -> trimesh.Trimesh:
    """Two open pieces with a 1 mm gap between them: the slice 1 mm thick through the centre of the bounds across
    the longest extent removed, the second piece inside-out. Nothing moves, so the pieces still touch what the part
    touched."""
    axis = int(np.argmax(mesh.extents))
    normal = np.eye(3)[axis]
    centre = mesh.bounds.mean(axis=0)
    pieces = []
    for sign in (1.0, -1.0):
        vertices, faces = trimesh.intersections.slice_faces_plane(mesh.vertices, mesh.faces, sign * normal,
                                                                  centre + sign * 0.0005 * normal)[:2]
        piece = _mesh(vertices, faces)
        piece.merge_vertices(digits_vertex=7)  # the cut's new vertices, made per triangle, joined again (0.1 um)
        pieces.append((np.asarray(piece.vertices), np.asarray(piece.faces)))
    (v1, f1), (v2, f2) = pieces
    return _mesh(np.concatenate([v1, v2]), np.concatenate([f1, f2[:, ::-1] + len(v1)]))


def export_flaws(mesh: trimesh.Trimesh, seed: int) -> tuple[str, ...]:
    """The flaws :func:`as_exported` gives ``mesh`` with ``seed``, in the order it applies them (``unmerged``: each
    face its own three vertices)."""
    return tuple(flaw for flaw, _ in _export_draws(mesh, seed))


def _export_draws(mesh: trimesh.Trimesh, seed: int) -> list[tuple[str, int]]:
    rng = np.random.default_rng(seed)
    drawn = {flaw: rng.random() < rate for flaw, rate in EXPORT_RATES.items()}
    drawn["unmerged"] = rng.random() < 0.5
    seeds = dict(zip(EXPORT_RATES, rng.integers(2**31, size=len(EXPORT_RATES)).tolist()))
    if drawn["one_surface"] and is_board(mesh):
        return [("one_surface", seeds["one_surface"])]
    return [(flaw, seeds.get(flaw, 0)) for flaw in ("inside_out", "half_flipped", "double_sided", "holes", "unmerged")
            if drawn[flaw]]


def unmerged(mesh: trimesh.Trimesh, seed: int = 0) -> trimesh.Trimesh:
    """Every face with its own three vertices, faces and winding as they were."""
    faces = np.asarray(mesh.faces)
    vertices = np.asarray(mesh.vertices)[faces.reshape(-1)]
    return _mesh(vertices, np.arange(len(vertices)).reshape(-1, 3))


def as_exported(mesh: trimesh.Trimesh, seed: int) -> trimesh.Trimesh:
    """``mesh`` with flaws drawn independently at :data:`EXPORT_RATES` (seeded), as one export of a real model has
    them: a board drawn as one surface (boards only; no other flaw then), else its winding reversed everywhere
    and on half its faces, every face drawn on both sides, 3% of the faces removed, in that order; and, for half the
    parts, vertices unmerged (a rate assumed, not counted: exports split vertices at normal and texture seams). A
    part drawn without a flaw comes back unchanged (:func:`export_flaws` names them)."""
    out = mesh
    for flaw, flaw_seed in _export_draws(mesh, seed):
        out = globals()[flaw](out, flaw_seed)
    return out


def damaged(mesh: trimesh.Trimesh, damage: str, seed: int = 0) -> trimesh.Trimesh:
    """``mesh`` broken by ``damage`` (one of :data:`DAMAGES`, or :data:`AS_EXPORTED`), seeded."""
    if damage not in (*DAMAGES, AS_EXPORTED):
        raise ValueError(f"unknown damage {damage!r}; one of {', '.join((*DAMAGES, AS_EXPORTED))}")
    return globals()[damage](mesh, seed)


__all__ = ["AS_EXPORTED", "DAMAGES", "EXPORT_RATES", "damaged", "export_flaws", "is_board"]
