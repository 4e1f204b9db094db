"""Mesh intake: the part meshes users give, turned into the solids every later stage weighs, grasps and collides.

Real part meshes are rarely closed volumes: exports draw faces twice (once per side), leave shells open, mix or
invert the winding, draw a thin board as one surface, or come as triangle soup in many loose pieces. Every later
stage needs a solid (mass, centre of mass and inertia from its volume; convex pieces that cover it; surfaces that
face outwards for grasps), so :func:`intake_mesh` makes one, in the part's own frame and unit, and says what it did:

1. A mesh that already is a solid comes back as it is, the same object: closed (every edge of every face met by
   the reverse edge of another, so its volume integral is exact; trimesh's watertight meshes and the closed,
   non-manifold ones of many CAD exports), no face repeated, every connected piece of positive volume.
2. Otherwise, on a copy: duplicate vertices merged (also those split by texture seams), faces without area
   dropped, repeated faces dropped; a face drawn on both sides (also with the opposite winding) keeps one side.
3. Each connected piece on its own:

   - a *single-surface board* (an open piece thinner than ``sheet_max_thickness_m``, 1 mm) becomes a board: its
     outline extruded to ``sheet_thickness_m`` (3 mm, a hardboard back panel) on the side of ``outward`` (away
     from the assembly's centre) where that is known, else behind the drawn face (against the direction most of
     its face normals point: a surface is drawn as seen from outside);
   - any other piece gets a consistent winding (``trimesh.repair.fix_winding``), its holes closed with fans of
     triangles (``trimesh.repair.fill_holes``) and its normals turned outwards (``fix_inversion``);
   - a piece still open after that is reconstructed watertight: the union of the convex hulls of its V-HACD
     pieces, or, where the decomposition fails, its convex hull (recorded as such: a hull closes openings).

4. The pieces stay one rigid part: the solid is their union (one mesh; mass, inertia and collision of all of it).

A part left without volume raises :class:`MeshIntakeError` naming it and why. Repeated faces are dropped by hand
(trimesh's ``unique_faces`` keeps one of a pair but cannot say how many were double-sided, which the record
reports); the sheet test and extrusion are hand-written because trimesh has no notion of a one-surface board.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import trimesh
from trimesh.grouping import group_rows

DEFAULT_SHEET_THICKNESS_M = 0.003
"""Thickness given to a board drawn as one surface: 3 mm, IKEA's hardboard back panels and drawer bottoms."""
SHEET_MAX_THICKNESS_M = 0.001
"""An open piece thinner than this (metres, along its least principal axis) is a board drawn as one surface."""
_AREA_EPS_M2 = 1e-14  # a face with less area than this (about 0.1 um across) has no area


class MeshIntakeError(ValueError):
    """A part mesh that no repair turns into a solid; the message names the part and says why."""


@dataclass(frozen=True)
class MeshIntake:
    """The solid of one part (``mesh``: its own frame and unit) and what the intake did to get it.

    ``fixes``: what was repaired, in words, in order (empty when the mesh came in as a solid and is ``mesh``
    itself). ``volume_before``: trimesh's signed volume of the mesh as given (0 or meaningless for an open or
    double-sided mesh); ``volume_after``: the solid's, in the mesh's unit cubed. ``pieces``: its connected pieces.
    """

    mesh: trimesh.Trimesh
    fixes: tuple[str, ...] = ()
    volume_before: float = 0.0
    volume_after: float = 0.0
    pieces: int = 1
    faces_before: int = 0

    @property
    def changed(self) -> bool:
        return bool(self.fixes)

    def to_json(self, unit_to_m3: float = 1.0) -> dict:
        """The record for ``report.json`` (``mesh_intake``), volumes in m^3 (``unit_to_m3``: the mesh's unit cubed
        in m^3)."""
        return {"changed": self.changed, "fixes": list(self.fixes),
                "volume_before_m3": float(self.volume_before) * unit_to_m3,
                "volume_after_m3": float(self.volume_after) * unit_to_m3,
                "pieces": int(self.pieces), "faces_before": int(self.faces_before),
                "faces_after": int(len(self.mesh.faces))}


def _signed_volume(mesh: trimesh.Trimesh) -> float:
    with np.errstate(all="ignore"):
        volume = float(trimesh.triangles.mass_properties(mesh.triangles, skip_inertia=True).volume)
    return volume if np.isfinite(volume) else 0.0


def _face_groups(mesh: trimesh.Trimesh) -> list[np.ndarray]:
    """Face indices of each connected piece (faces joined by shared edges), every face in exactly one."""
    return trimesh.graph.connected_components(mesh.face_adjacency, nodes=np.arange(len(mesh.faces)), min_len=1)


def _is_closed_oriented(faces: np.ndarray) -> bool:
    """Whether every directed edge of ``faces`` (F, 3) is met by its reverse as often as it occurs: a closed,
    consistently wound surface (manifold or not), whose volume integral is exact."""
    directed = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    forward = trimesh.grouping.hashable_rows(directed)
    backward = trimesh.grouping.hashable_rows(directed[:, ::-1])
    return bool(np.array_equal(np.sort(forward), np.sort(backward)))


def is_solid(mesh: trimesh.Trimesh) -> bool:
    """Whether ``mesh`` is already a solid the later stages take as it is (see the module: step 1)."""
    faces = np.asarray(mesh.faces)
    if len(faces) < 4 or not np.all(np.isfinite(mesh.vertices)):
        return False
    if not _is_closed_oriented(faces):
        return False
    if len(group_rows(np.sort(faces, axis=1), require_count=1)) != len(faces):
        return False  # a face repeated (a double-sided mesh is closed and oriented, with no volume)
    if _signed_volume(mesh) <= 0:
        return False
    groups = _face_groups(mesh)
    if len(groups) == 1:
        return True
    # every piece closed on its own encloses a volume (none inside-out); pieces joined to others through edges
    # of three or more faces are closed only together, and counted in the whole
    with np.errstate(all="ignore"):
        return all(trimesh.triangles.mass_properties(np.asarray(mesh.triangles)[g], skip_inertia=True).volume > 0
                   for g in groups if len(g) >= 4 and _is_closed_oriented(faces[g]))


def _encloses(piece: trimesh.Trimesh) -> bool:
    """Whether one connected piece, repaired, is a solid: closed and oriented, no face repeated, a positive
    volume. (Unlike :func:`is_solid`, the faces it joins through edges of three or more faces are not asked to
    enclose a volume each: the repair orients the piece as a whole.)"""
    faces = np.asarray(piece.faces)
    return (len(faces) >= 4 and _is_closed_oriented(faces) and _signed_volume(piece) > 0
            and len(group_rows(np.sort(faces, axis=1), require_count=1)) == len(faces))


def _cleaned(mesh: trimesh.Trimesh, log: _Log) -> trimesh.Trimesh:
    """Step 2 on a copy: vertices merged, faces without area and repeated faces dropped."""
    out = trimesh.Trimesh(np.array(mesh.vertices, dtype=np.float64), np.array(mesh.faces, dtype=np.int64),
                          process=False)
    count = len(out.vertices)
    out.merge_vertices(merge_tex=True, merge_norm=True)
    out.remove_unreferenced_vertices()
    log.add("merged", count - len(out.vertices))
    area = out.area_faces
    keep = np.isfinite(area) & (area > _AREA_EPS_M2) & (np.ptp(np.sort(out.faces, axis=1), axis=1) > 0)
    if not keep.all():
        log.add("no area", int(np.count_nonzero(~keep)))
        out.update_faces(keep)
    faces = np.asarray(out.faces)
    # faces on the same three vertices, whichever the winding: the first of each is kept
    _, first_index, group = np.unique(np.sort(faces, axis=1), axis=0, return_index=True, return_inverse=True)
    first = first_index[group.reshape(-1)]
    drop = first != np.arange(len(faces))
    # the winding's parity (inversions of the vertex order): the same as the first's: a repeat; the opposite: the
    # face drawn for its other side
    parity = ((faces[:, 0] > faces[:, 1]).astype(int) + (faces[:, 0] > faces[:, 2]) + (faces[:, 1] > faces[:, 2])) % 2
    same = parity == parity[first]
    double_sided = int(np.count_nonzero(drop & ~same))
    repeated = int(np.count_nonzero(drop & same))
    log.add("double-sided", double_sided)
    log.add("repeated", repeated)
    if drop.any():
        out.update_faces(~drop)
    out.remove_unreferenced_vertices()
    return out


def _thinnest_axis(vertices: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
    """(3,) centre, (3, 3) principal axes (rows, the least last) and the spread along the least (vertices' unit)."""
    centre = vertices.mean(axis=0)
    axes = np.linalg.svd(vertices - centre, full_matrices=False)[2]
    if len(axes) < 3:
        axes = np.linalg.qr(np.vstack([axes, np.eye(3)]).T)[0].T[:3]
    return centre, axes, float(np.ptp((vertices - centre) @ axes[2]))


def _extruded_sheet(piece: trimesh.Trimesh, thickness: float, outward: np.ndarray | None) -> trimesh.Trimesh:
    """A one-surface board ``piece`` as a board ``thickness`` thick: its faces projected onto their plane and
    extruded (``trimesh.creation.extrude_triangulation``) towards ``outward``, or behind the drawn face."""
    vertices = np.asarray(piece.vertices)
    centre, axes, _ = _thinnest_axis(vertices)
    normal = axes[2]
    if outward is not None and abs(float(np.dot(outward, normal))) > 1e-9:
        side = 1.0 if float(np.dot(outward, normal)) > 0 else -1.0
    else:  # behind the drawn face: against the area-weighted mean of its face normals
        drawn = float(np.sum((piece.face_normals @ normal) * piece.area_faces))
        side = -1.0 if drawn >= 0 else 1.0
    # the plane frame: x, y in the sheet, z towards the side the board grows to (right-handed)
    z = side * normal
    x = axes[0]
    y = np.cross(z, x)
    frame = np.eye(4)
    frame[:3, 0], frame[:3, 1], frame[:3, 2], frame[:3, 3] = x, y, z, centre
    flat = (vertices - centre) @ np.stack([x, y]).T  # (V, 2) in the sheet's plane
    faces = np.array(piece.faces)
    a, b, c = flat[faces[:, 0]], flat[faces[:, 1]], flat[faces[:, 2]]
    signed = (b[:, 0] - a[:, 0]) * (c[:, 1] - a[:, 1]) - (b[:, 1] - a[:, 1]) * (c[:, 0] - a[:, 0])
    faces[signed < 0] = faces[signed < 0][:, ::-1]  # counter-clockwise in the plane, as the extrusion wants
    faces = faces[np.abs(signed) > 2 * _AREA_EPS_M2]
    with np.errstate(all="ignore"):
        board = trimesh.creation.extrude_triangulation(flat, faces, thickness, transform=frame)
        if not board.is_volume:  # projected faces that overlap (a fold): the prism of its outline instead
            board = trimesh.convex.convex_hull(np.concatenate([vertices, vertices + z * thickness]))
    return board


def _boundary_loops(faces: np.ndarray) -> list[list[int]]:
    """The holes of a consistently wound surface ``faces`` (F, 3): loops of vertex indices, each following the
    direction of the faces' edges along it (every directed edge met by its reverse fewer times than it occurs)."""
    directed = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]]).astype(np.int64)
    size = int(directed.max()) + 1
    keys, counts = np.unique(directed[:, 0] * size + directed[:, 1], return_counts=True)
    reverse_keys = (keys % size) * size + keys // size
    found = np.searchsorted(keys, reverse_keys).clip(0, len(keys) - 1)
    reverse_counts = np.where(keys[found] == reverse_keys, counts[found], 0)
    excess = counts - reverse_counts
    leaving: dict[int, list[int]] = {}
    for key, n in zip(keys[excess > 0].tolist(), excess[excess > 0].tolist()):
        leaving.setdefault(key // size, []).extend([key % size] * n)
    loops = []
    while leaving:
        start = next(iter(leaving))
        loop, vertex = [start], start
        while True:
            ends = leaving.get(vertex)
            if not ends:  # an unbalanced boundary (non-manifold): close the chain as it is
                break
            following = ends.pop()
            if not ends:
                del leaving[vertex]
            if following == start:
                break
            loop.append(following)
            vertex = following
        if len(loop) >= 3:
            loops.append(loop)
    return loops


_MAX_LOOP_FOR_VERTEX_FANS = 64  # longer holes get the fan around their mean point only


def _fan_volume(points: np.ndarray, fan: np.ndarray) -> float:
    """Signed volume (about the origin) that the triangles ``fan`` (T, 3) of ``points`` add to a closed surface."""
    a, b, c = points[fan[:, 0]], points[fan[:, 1]], points[fan[:, 2]]
    cross = np.stack([b[:, 1] * c[:, 2] - b[:, 2] * c[:, 1], b[:, 2] * c[:, 0] - b[:, 0] * c[:, 2],
                      b[:, 0] * c[:, 1] - b[:, 1] * c[:, 0]], axis=1)
    return float(np.sum(a * cross)) / 6.0


def _hole_fan(points: np.ndarray, ring: np.ndarray, centre_index: int) -> np.ndarray:
    """The triangles (T, 3) closing the hole ``ring`` (loop of vertex indices into ``points``, along the faces'
    edges; ``points[centre_index]`` its mean point): of the fans around the mean point and around each of the
    loop's vertices, the one that encloses the most. A flat hole's fans all enclose the same; across a bent hole
    (faces missing on both sides of a board's edge) the fan that bulges out restores the edge, where the fan around
    the mean point would cut it off."""
    if len(ring) == 3:
        return ring[::-1][None]
    following = np.roll(ring, -1)
    fans = [np.column_stack([following, ring, np.full(len(ring), centre_index)])]
    if len(ring) <= _MAX_LOOP_FOR_VERTEX_FANS:
        for k in range(len(ring)):
            turned = np.roll(ring, -k)  # fan around turned[0]: triangles (turned[i + 1], turned[i], turned[0])
            fans.append(np.column_stack([turned[2:], turned[1:-1], np.full(len(ring) - 2, turned[0])]))
    volumes = [_fan_volume(points, fan) for fan in fans]
    best = int(np.argmax(np.round(volumes, 15)))  # ties (flat holes): the first, the fan around the mean point
    return fans[best]


def _holes_closed(piece: trimesh.Trimesh, log: _Log) -> trimesh.Trimesh:
    """``piece`` with each hole (:func:`_boundary_loops`) closed by a fan of triangles (:func:`_hole_fan`), wound
    against the loop, so that the surface is closed and oriented; a flat hole's fan makes the volume integral
    exact whatever the hole's shape (the fan's signed areas sum to the hole's). Hand-written:
    ``trimesh.repair.fill_holes`` (5.2) takes the loops from a cycle basis of the boundary graph and leaves parts
    of larger holes open."""
    faces = np.asarray(piece.faces)
    loops = _boundary_loops(faces)
    if not loops:
        return piece
    rings = [np.array(loop) for loop in loops]
    centres = np.array([np.asarray(piece.vertices)[ring].mean(axis=0) for ring in rings])
    points = np.concatenate([np.asarray(piece.vertices), centres])
    added = [_hole_fan(points, ring, len(piece.vertices) + k) for k, ring in enumerate(rings)]
    log.add("holes", len(loops))
    faces = _without_opposite_pairs(np.concatenate([faces, *added]))
    closed = trimesh.Trimesh(points, faces, process=False)
    closed.remove_unreferenced_vertices()  # the mean points of holes closed around a vertex of theirs
    return closed


def _without_opposite_pairs(faces: np.ndarray) -> np.ndarray:
    """``faces`` less every pair of a face and its reverse (a fan laid back onto a face beside the hole): the pair
    encloses nothing, and dropping both keeps a closed surface closed."""
    _, first_index, group, counts = np.unique(np.sort(faces, axis=1), axis=0, return_index=True,
                                              return_inverse=True, return_counts=True)
    group = group.reshape(-1)
    parity = ((faces[:, 0] > faces[:, 1]).astype(int) + (faces[:, 0] > faces[:, 2]) + (faces[:, 1] > faces[:, 2])) % 2
    shared = counts[group] == 2
    opposite = shared & (parity != parity[first_index[group]])  # the second of an opposite pair
    drop = opposite.copy()
    drop[first_index[group[opposite]]] = True
    return faces[~drop]


def _reconstructed(piece: trimesh.Trimesh) -> tuple[trimesh.Trimesh, str]:
    """A watertight stand-in for a piece that stays open: the union of the convex hulls of its V-HACD pieces
    where they hold at least a tenth of its hull's volume, else its convex hull. Returns it and which."""
    from planning.convex import _decompose, convex_hull

    with np.errstate(all="ignore"):
        hull = convex_hull(piece.vertices)
        hulls = [h for h in _decompose(piece) if h.is_volume]
        if hulls and sum(h.volume for h in hulls) >= 0.1 * hull.volume:
            return trimesh.util.concatenate(hulls), "open pieces rebuilt from convex pieces"
    return hull, "open pieces replaced by their convex hulls (openings closed)"


class _Log:
    """What the intake did, counted per kind, in the order first done."""

    def __init__(self) -> None:
        self.counts: dict[str, float] = {}

    def add(self, kind: str, count: float = 1) -> None:
        if count:
            self.counts[kind] = self.counts.get(kind, 0) + count

    def words(self) -> tuple[str, ...]:
        phrases = {"merged": "merged {n} duplicate vertices", "no area": "dropped {n} faces without area",
                   "double-sided": "reduced {n} double-sided faces to one side",
                   "repeated": "dropped {n} repeated faces", "loose": "{n} loose pieces kept as one rigid part",
                   "rewound": "rewound {n} faces", "holes": "closed {n} holes",
                   "inverted": "turned {n} inside-out pieces outwards",
                   "sheet": "extruded {n} one-surface boards to {t:g} mm"}
        out = []
        for kind, n in self.counts.items():
            template = phrases.get(kind, "{kind} ({n})")
            out.append(template.format(n=int(n), t=self.counts.get("thickness_mm", 0), kind=kind))
        return tuple(w for w, k in zip(out, self.counts) if k != "thickness_mm")


def _consistently_wound(mesh: trimesh.Trimesh, log: _Log) -> trimesh.Trimesh:
    """``mesh`` with each connected piece wound one way: faces flipped so that every edge two faces share runs one
    way in one and the other way in the other, as far as the faces allow (a Moebius-like piece keeps a seam).
    Hand-written, vectorised: ``trimesh.repair.fix_winding`` does the same with a Python loop per face (seconds
    for a soup of 20,000 faces)."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import breadth_first_order, connected_components

    faces = np.asarray(mesh.faces)
    directed = np.stack([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]], axis=1).reshape(-1, 2)
    pairs = group_rows(np.sort(directed, axis=1), require_count=2)  # edges two faces share (manifold)
    if len(pairs) == 0:
        return mesh
    pairs = np.asarray(pairs)
    a, b = pairs[:, 0] // 3, pairs[:, 1] // 3
    same_way = np.all(directed[pairs[:, 0]] == directed[pairs[:, 1]], axis=1)  # the two faces disagree
    count = len(faces)
    graph = coo_matrix((np.ones(len(a)), (a, b)), shape=(count, count)).tocsr()
    # whether the faces of each shared edge disagree, looked up by the pair (either order)
    keys = np.concatenate([a * count + b, b * count + a])
    order_keys = np.argsort(keys)
    keys, disagreeing = keys[order_keys], np.concatenate([same_way, same_way])[order_keys]
    flip = np.zeros(count, dtype=bool)
    _, labels = connected_components(graph, directed=False)
    for root in np.unique(labels, return_index=True)[1]:
        order, predecessors = breadth_first_order(graph, root, directed=False, return_predecessors=True)
        children = order[1:]
        parents = predecessors[children]
        # a face and its parent may share two edges (a fold): either tells
        disagrees = disagreeing[np.searchsorted(keys, children * count + parents)].tolist()
        for face, parent, disagree in zip(children.tolist(), parents.tolist(), disagrees):
            flip[face] = flip[parent] ^ disagree
    if flip.any():
        log.add("rewound", int(np.count_nonzero(flip)))
        mesh = trimesh.Trimesh(np.asarray(mesh.vertices), _flipped(faces, flip), process=False)
    return mesh


def _flipped(faces: np.ndarray, mask: np.ndarray) -> np.ndarray:
    out = np.array(faces)
    out[mask] = out[mask][:, ::-1]
    return out


def _solid_piece(piece: trimesh.Trimesh, settings: tuple[float, float], outward: np.ndarray | None,
                 log: _Log) -> trimesh.Trimesh | None:
    """Step 3 for one connected, consistently wound piece: a solid, or None when the piece has no volume."""
    thickness, sheet_max = settings
    if is_solid(piece):
        return piece
    closed = _is_closed_oriented(np.asarray(piece.faces))
    _, _, spread = _thinnest_axis(np.asarray(piece.vertices))
    if not closed and spread < sheet_max:
        log.add("sheet")
        log.counts["thickness_mm"] = thickness * 1000.0
        return _extruded_sheet(piece, thickness, outward)
    if not closed:
        piece = _holes_closed(piece, log)
    if _is_closed_oriented(np.asarray(piece.faces)) and _signed_volume(piece) < 0:
        piece = trimesh.Trimesh(np.asarray(piece.vertices), np.asarray(piece.faces)[:, ::-1], process=False)
        log.add("inverted")
    if _encloses(piece):
        return piece
    if _hull_volume(piece) <= 0:
        return None
    solid, kind = _reconstructed(piece)
    log.add(kind)
    return solid


def _hull_volume(mesh: trimesh.Trimesh) -> float:
    from planning.convex import convex_hull

    try:
        return float(convex_hull(mesh.vertices).volume)
    except Exception:  # qhull refuses flat or too few points: no volume
        return 0.0


def intake_mesh(mesh: trimesh.Trimesh, name: str, sheet_thickness: float = DEFAULT_SHEET_THICKNESS_M,
                outward: np.ndarray | None = None, sheet_max_thickness: float = SHEET_MAX_THICKNESS_M,
                ) -> MeshIntake:
    """The solid of a part (see the module) and what was done; ``name`` says which part in messages (such as
    ``part 'leg_1'``). ``mesh``: the part's mesh in its own frame;
    ``sheet_thickness`` and ``sheet_max_thickness`` in the mesh's unit; ``outward``: (3,) a direction in the part
    frame pointing away from the assembly's centre (for the side a one-surface board grows to), or None.
    Raises :class:`MeshIntakeError` when no solid can be made."""
    volume_before = _signed_volume(mesh) if len(mesh.faces) else 0.0
    if is_solid(mesh):
        return MeshIntake(mesh, (), volume_before, volume_before, len(_face_groups(mesh)), len(mesh.faces))
    if not sheet_thickness > 0:
        raise ValueError(f"sheet thickness {sheet_thickness!r} must be above 0")
    log = _Log()
    cleaned = _cleaned(mesh, log)
    if len(cleaned.faces) == 0:
        raise MeshIntakeError(f"{name}: every face of its mesh is without area (a line or a point), so it "
                              "has no volume to weigh or collide with; give the part as a solid")
    cleaned = _consistently_wound(cleaned, log)
    groups = _face_groups(cleaned)
    if len(groups) > 1:
        log.add("loose", len(groups))
    unit_outward = None
    if outward is not None and np.linalg.norm(outward) > 0:
        unit_outward = np.asarray(outward, dtype=np.float64) / np.linalg.norm(outward)
    solids = []
    for group in groups:
        piece = cleaned.submesh([group], append=True, repair=False)
        solid = _solid_piece(piece, (sheet_thickness, sheet_max_thickness), unit_outward, log)
        if solid is not None:
            solids.append(solid)
    if not solids:
        raise MeshIntakeError(f"{name}: its mesh encloses no volume and no repair gives it one (all of it "
                              "lies on a line); give the part as a solid")
    solid = solids[0] if len(solids) == 1 else trimesh.util.concatenate(solids)
    solid = trimesh.Trimesh(np.asarray(solid.vertices), np.asarray(solid.faces), process=False)
    volume_after = _signed_volume(solid)
    if not volume_after > 0:
        raise MeshIntakeError(f"{name}: no repair of its mesh encloses a volume ({'; '.join(log.words())}); "
                              "give the part as a closed solid")
    return MeshIntake(solid, log.words() or ("rebuilt",), volume_before, volume_after, len(solids), len(mesh.faces))


def summary_line(records: dict[str, dict]) -> str | None:
    """One line for the run's output: which parts the intake changed and how, or None when it changed none."""
    changed = {name: record for name, record in records.items() if record.get("changed")}
    if not changed:
        return None
    words = "; ".join(f"{name}: {', '.join(record['fixes'])}" for name, record in changed.items())
    return f"mesh intake repaired {len(changed)} of {len(records)} part meshes ({words})"


__all__ = ["DEFAULT_SHEET_THICKNESS_M", "MeshIntake", "MeshIntakeError", "SHEET_MAX_THICKNESS_M", "intake_mesh",
           "is_solid", "summary_line"]
