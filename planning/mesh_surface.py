"""Surface operations the mesh intake (:mod:`planning.mesh_intake`) needs and trimesh does not do (or does too
slowly): consistent winding over a whole soup, holes closed whatever their size, a one-surface board made a board.

All work on triangle meshes in any frame and unit (the part's own); faces (F, 3) int index vertices (V, 3).
"""

from __future__ import annotations

import numpy as np
import trimesh
from trimesh.grouping import group_rows

AREA_EPS = 1e-14
"""A face with less area than this (in the mesh's unit squared: about 0.1 um across in metres) has no area."""


def is_closed_oriented(faces: np.ndarray) -> bool:
    """Whether every directed edge of ``faces`` (F, 3) is met by its reverse as often as it occurs: a closed,
    consistently wound surface (manifold or not), whose volume integral is exact."""
    directed = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    forward = trimesh.grouping.hashable_rows(directed)
    backward = trimesh.grouping.hashable_rows(directed[:, ::-1])
    return bool(np.array_equal(np.sort(forward), np.sort(backward)))


def thinnest_axis(vertices: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
    """(3,) centre, (3, 3) principal axes (rows, the least last) and the spread along the least (vertices' unit)."""
    centre = vertices.mean(axis=0)
    axes = np.linalg.svd(vertices - centre, full_matrices=False)[2]
    if len(axes) < 3:
        axes = np.linalg.qr(np.vstack([axes, np.eye(3)]).T)[0].T[:3]
    return centre, axes, float(np.ptp((vertices - centre) @ axes[2]))


def extruded_sheet(piece: trimesh.Trimesh, thickness: float, outward: np.ndarray | None) -> trimesh.Trimesh:
    """A one-surface board ``piece`` as a board ``thickness`` thick: its faces projected onto their plane and
    extruded (``trimesh.creation.extrude_triangulation``) towards ``outward``, or behind the drawn face."""
    vertices = np.asarray(piece.vertices)
    centre, axes, _ = thinnest_axis(vertices)
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
    faces = faces[np.abs(signed) > 2 * AREA_EPS]
    with np.errstate(all="ignore"):
        board = trimesh.creation.extrude_triangulation(flat, faces, thickness, transform=frame)
        if not board.is_volume:  # projected faces that overlap (a fold): the prism of its outline instead
            board = trimesh.convex.convex_hull(np.concatenate([vertices, vertices + z * thickness]))
    return board


SHEET_TOUCH_M = 0.0005
"""A neighbour within this (metres) of a one-surface board's drawn face touches it there."""
SHEET_RAY_COUNT = 256


def _faces_within(mesh: trimesh.Trimesh, bounds: np.ndarray, margin: float) -> trimesh.Trimesh:
    """The faces of ``mesh`` whose bounds come within ``margin`` of ``bounds`` (2, 3), as a mesh of their own: a
    ray query then indexes only them (indexing a whole assembly's faces takes about a second)."""
    triangles = np.asarray(mesh.triangles)
    near = (np.all(triangles.max(axis=1) >= bounds[0] - margin, axis=1)
            & np.all(triangles.min(axis=1) <= bounds[1] + margin, axis=1))
    return trimesh.Trimesh(triangles[near].reshape(-1, 3), np.arange(3 * int(near.sum())).reshape(-1, 3),
                           process=False)


def sheet_gaps(piece: trimesh.Trimesh, normal: np.ndarray, neighbours: trimesh.Trimesh, reach: float,
               seed: int = 0) -> tuple[float, float]:
    """How far a one-surface board ``piece`` may grow on each side before it meets a neighbour: the nearest hit
    of rays cast from points on it (``SHEET_RAY_COUNT``, sampled with ``seed``) along ``+normal`` and
    ``-normal`` into the faces of ``neighbours`` (the other parts, in the piece's frame and unit, their faces
    turned outwards) that face the board (within 60 degrees: where a ray enters a neighbour; a face it grazes or
    leaves by is no obstacle), inf on a side where none is nearer than ``reach``; 0 where a neighbour touches the
    board's face."""
    back = SHEET_TOUCH_M * 2  # rays start just behind the face, so that a neighbour lying on it is hit
    neighbours = _faces_within(neighbours, piece.bounds, reach + back)
    if not len(neighbours.faces):
        return float("inf"), float("inf")
    points, _ = trimesh.sample.sample_surface(piece, SHEET_RAY_COUNT, seed=seed)
    gaps = []
    for direction in (normal, -normal):
        origins = points - direction * back
        directions = np.broadcast_to(direction, origins.shape)
        locations, rays, faces = neighbours.ray.intersects_location(origins, directions, multiple_hits=True)
        locations = np.asarray(locations, dtype=np.float64).reshape(-1, 3)
        facing = neighbours.face_normals[np.asarray(faces, dtype=np.int64)] @ direction < -0.5
        along = (locations[facing] - origins[np.asarray(rays, dtype=np.int64)[facing]]) @ direction - back
        near = along[along <= reach]
        gaps.append(max(float(near.min()), 0.0) if len(near) else float("inf"))
    return gaps[0], gaps[1]


def sheet_growth(gaps: tuple[float, float], thickness: float) -> tuple[float, float] | None:
    """Which side (+1 along the normal, -1 against it) and how thick a one-surface board grows, from its
    :func:`sheet_gaps`: away from a neighbour that touches one face, up to a neighbour within reach on the other
    side (the board fills the gap between them: a bottom drawn on the floor, under the sides standing on it), else
    ``thickness``; where neither face is touched, up to the nearer neighbour within reach (a shelf drawn as its
    top face, above the pins it rests on). None where neither rule decides (nothing within reach, or both faces
    touched): the caller's default."""
    touched = [gap <= SHEET_TOUCH_M for gap in gaps]
    if touched[0] != touched[1]:
        free = 1 if touched[0] else 0
        return (1.0 if free == 0 else -1.0), (gaps[free] if gaps[free] < float("inf") else thickness)
    if not any(touched) and min(gaps) < float("inf"):
        near = int(np.argmin(gaps))
        return (1.0 if near == 0 else -1.0), gaps[near]
    return None


def boundary_loops(faces: np.ndarray) -> list[list[int]]:
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
        loops.extend(simple for simple in _simple_loops(loop) if len(simple) >= 3)
    return loops


def _simple_loops(loop: list[int]) -> list[list[int]]:
    """``loop`` cut where it passes a vertex again (two holes meeting at a corner) into loops that do not, each
    in the same direction: [0, 1, 3, 7, 4, 3] is [3, 7, 4] and [0, 1, 3]."""
    out, stack, position = [], [], {}
    for vertex in loop:
        if vertex in position:
            at = position[vertex]
            out.append(stack[at:])
            for dropped in stack[at + 1:]:
                del position[dropped]
            del stack[at + 1:]
        else:
            position[vertex] = len(stack)
            stack.append(vertex)
    out.append(stack)
    return out


_MAX_LOOP_FOR_VERTEX_FANS = 64  # longer holes get the fan around their mean point only


def _fan_volume(points: np.ndarray, fan: np.ndarray) -> float:
    """Signed volume (about the origin) that the triangles ``fan`` (T, 3) of ``points`` add to a closed surface."""
    a, b, c = points[fan[:, 0]], points[fan[:, 1]], points[fan[:, 2]]
    cross = np.stack([b[:, 1] * c[:, 2] - b[:, 2] * c[:, 1], b[:, 2] * c[:, 0] - b[:, 0] * c[:, 2],
                      b[:, 0] * c[:, 1] - b[:, 1] * c[:, 0]], axis=1)
    return float(np.sum(a * cross)) / 6.0


def _hole_fans(points: np.ndarray, ring: np.ndarray, centre_index: int) -> list[np.ndarray]:
    """The fans of triangles (T, 3) that close the hole ``ring`` (loop of vertex indices into ``points``, along
    the faces' edges; ``points[centre_index]`` its mean point), each wound against the loop: around the mean point
    first, then around each of the loop's vertices (loops of at most :data:`_MAX_LOOP_FOR_VERTEX_FANS`)."""
    if len(ring) == 3:
        return [ring[::-1][None]]
    following = np.roll(ring, -1)
    fans = [np.column_stack([following, ring, np.full(len(ring), centre_index)])]
    if len(ring) <= _MAX_LOOP_FOR_VERTEX_FANS:
        for k in range(len(ring)):
            turned = np.roll(ring, -k)  # fan around turned[0]: triangles (turned[i + 1], turned[i], turned[0])
            fans.append(np.column_stack([turned[2:], turned[1:-1], np.full(len(ring) - 2, turned[0])]))
    return fans


def holes_closed(piece: trimesh.Trimesh) -> tuple[trimesh.Trimesh, int]:
    """``piece`` with each hole (:func:`boundary_loops`) closed by a fan of triangles wound against the loop, so
    that the surface is closed and oriented; and how many holes there were. Of the fans around the hole's mean
    point and around each of its vertices (:func:`_hole_fans`), the one that encloses the most in the piece's
    sense (the sign of its volume closed by the fans around the mean points), laying no triangle onto a face it
    has. A flat hole's fans all enclose the same (their signed areas sum to the hole's: the volume integral is
    exact whatever the hole's shape); across a bent hole (faces missing on both sides of a board's edge) the fan
    that bulges out restores the edge, where the fan around the mean point would cut it off. Hand-written:
    ``trimesh.repair.fill_holes`` (5.2) takes the loops from a cycle basis of the boundary graph and leaves parts
    of larger holes open."""
    faces = np.asarray(piece.faces)
    loops = boundary_loops(faces)
    if not loops:
        return piece, 0
    rings = [np.array(loop) for loop in loops]
    centres = np.array([np.asarray(piece.vertices)[ring].mean(axis=0) for ring in rings])
    points = np.concatenate([np.asarray(piece.vertices), centres])
    candidates = [_hole_fans(points, ring, len(piece.vertices) + k) for k, ring in enumerate(rings)]
    volumes = [[_fan_volume(points, fan) for fan in fans] for fans in candidates]
    sense = 1.0 if _fan_volume(points, faces) + sum(v[0] for v in volumes) >= 0 else -1.0
    existing = {tuple(face) for face in np.sort(faces, axis=1).tolist()}
    added = []
    for fans, fan_volumes in zip(candidates, volumes):
        usable = [k for k, fan in enumerate(fans)
                  if k == 0 or not any(tuple(t) in existing for t in np.sort(fan, axis=1).tolist())]
        # ties (flat holes): the first, the fan around the mean point
        added.append(fans[max(usable, key=lambda k: (round(sense * fan_volumes[k], 15), -k))])
    faces = _without_opposite_pairs(np.concatenate([faces, *added]))
    closed = trimesh.Trimesh(points, faces, process=False)
    closed.remove_unreferenced_vertices()  # the mean points of holes closed around a vertex of theirs
    return closed, len(loops)


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


def consistently_wound(mesh: trimesh.Trimesh) -> tuple[trimesh.Trimesh, int]:
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
        return mesh, 0
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
        mesh = trimesh.Trimesh(np.asarray(mesh.vertices), _flipped(faces, flip), process=False)
    return mesh, int(np.count_nonzero(flip))


def _flipped(faces: np.ndarray, mask: np.ndarray) -> np.ndarray:
    out = np.array(faces)
    out[mask] = out[mask][:, ::-1]
    return out
