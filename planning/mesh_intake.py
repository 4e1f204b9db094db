"""Mesh intake: the part meshes users give, turned into the solids every later stage weighs, grasps and collides.

Real part meshes are rarely closed volumes: exports draw faces twice (once per side), leave shells open, mix or
invert the winding, draw a thin board as one surface, or come as triangle soup in many loose pieces. Every later
stage needs a solid (mass, centre of mass and inertia from its volume; convex pieces that cover it; surfaces that
face outwards for grasps), so :func:`intake_mesh` makes one, in the part's own frame and unit, and says what it did:

1. A mesh that already is a solid comes back as it is, the same object: closed (every edge of every face met by
   the reverse edge of another, so its volume integral is exact; trimesh's watertight meshes and the closed,
   non-manifold ones of many CAD exports), no face repeated, every connected piece of positive volume.
2. Otherwise, on a copy: duplicate vertices merged (also those split by texture seams), faces without area
   dropped, repeated faces dropped; a face drawn on both sides (also with the opposite winding) keeps one side;
   the faces of each connected piece wound one way (:func:`planning.mesh_surface.consistently_wound`).
3. Each connected piece on its own:

   - a *single-surface board* (an open piece thinner than ``sheet_max_thickness``, 1 mm) becomes a board: its
     faces extruded. Where the other parts and the floor are placed around it (``neighbours``), it grows away
     from a part that touches one face, to meet a part within ``sheet_reach`` (60 mm) on the other side, else
     ``sheet_thickness`` thick (3 mm, a hardboard back panel); where no part touches it, to meet the nearer part
     within reach: a board drawn as one face of a 16 mm shelf regains its 16 mm
     (:func:`planning.mesh_surface.sheet_growth`). Otherwise ``sheet_thickness``
     on the side of ``outward`` (away from the assembly's centre) where that is known, else behind the drawn face
     (against the direction most of its face normals point: a surface is drawn as seen from outside);
   - any other open piece has its holes closed with fans of triangles
     (:func:`planning.mesh_surface.holes_closed`), and is turned outwards where it encloses a negative volume;
   - a piece still not closed after that is reconstructed watertight: the union of the convex hulls of its
     V-HACD pieces, or, where those hold less than a tenth of its hull, its convex hull (recorded as such: a hull
     closes openings).

4. The pieces stay one rigid part: the solid is their union (one mesh; mass, inertia and collision of all of it;
   pieces that overlap count twice in the mass).

A part left without volume raises :class:`MeshIntakeError` naming it and why. Written here rather than taken
from trimesh: repeated faces are dropped by hand (``unique_faces`` keeps one of a pair but cannot say how many
were double-sided, which the record reports); winding, holes and sheets in :mod:`planning.mesh_surface` (see
there why). A cavity drawn as an inner shell is taken as a loose piece and filled.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from functools import cache

import numpy as np
import trimesh
from trimesh.grouping import group_rows

from planning.mesh_surface import (
    AREA_EPS,
    consistently_wound,
    extruded_sheet,
    holes_closed,
    is_closed_oriented,
    sheet_gaps,
    sheet_growth,
    thinnest_axis,
)

DEFAULT_SHEET_THICKNESS_M = 0.003
"""Thickness given to a board drawn as one surface: 3 mm, IKEA's hardboard back panels and drawer bottoms."""
SHEET_MAX_THICKNESS_M = 0.001
"""An open piece thinner than this (metres, along its least principal axis) is a board drawn as one surface."""
SHEET_REACH_M = 0.06
"""A one-surface board grows to meet a neighbour at most this far from its drawn face (metres): the thickest
boards of furniture (honeycomb table tops) are about 50 mm."""


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


def is_solid(mesh: trimesh.Trimesh) -> bool:
    """Whether ``mesh`` is already a solid the later stages take as it is (see the module: step 1)."""
    faces = np.asarray(mesh.faces)
    if len(faces) < 4 or not np.all(np.isfinite(mesh.vertices)):
        return False
    if not is_closed_oriented(faces):
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
                   for g in groups if len(g) >= 4 and is_closed_oriented(faces[g]))


def _encloses(piece: trimesh.Trimesh) -> bool:
    """Whether one connected piece, repaired, is a solid: closed and oriented, no face repeated, a positive
    volume. (Unlike :func:`is_solid`, the faces it joins through edges of three or more faces are not asked to
    enclose a volume each: the repair orients the piece as a whole.)"""
    faces = np.asarray(piece.faces)
    return (len(faces) >= 4 and is_closed_oriented(faces) and _signed_volume(piece) > 0
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
    keep = np.isfinite(area) & (area > AREA_EPS) & (np.ptp(np.sort(out.faces, axis=1), axis=1) > 0)
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
        self.sheet_mm: list[float] = []  # the thickness each one-surface board was given

    def add(self, kind: str, count: float = 1) -> None:
        if count:
            self.counts[kind] = self.counts.get(kind, 0) + count

    def words(self) -> tuple[str, ...]:
        phrases = {"merged": "merged {n} duplicate vertices", "no area": "dropped {n} faces without area",
                   "double-sided": "reduced {n} double-sided faces to one side",
                   "repeated": "dropped {n} repeated faces", "loose": "{n} loose pieces kept as one rigid part",
                   "rewound": "rewound {n} faces", "holes": "closed {n} holes",
                   "inverted": "turned {n} inside-out pieces outwards",
                   "sheet": "extruded {n} one-surface boards to {t} mm",
                   "sheet met": "grew {n} of them to meet the part beside them"}
        thickness = ", ".join(f"{t:.3g}" for t in sorted(set(np.round(self.sheet_mm, 1))))
        return tuple(phrases.get(kind, "{kind} ({n})").format(n=int(n), t=thickness, kind=kind)
                     for kind, n in self.counts.items())


@dataclass(frozen=True)
class _SheetSettings:
    thickness: float
    max_thickness: float
    reach: float
    outward: np.ndarray | None
    neighbours: Callable[[], trimesh.Trimesh] | None


def _sheet(piece: trimesh.Trimesh, axes: np.ndarray, sheet: _SheetSettings, log: _Log) -> trimesh.Trimesh:
    """A one-surface board ``piece`` (``axes``: its principal axes, rows, the plane's normal last) made a board
    (see the module: step 3). It meets a neighbour at most half its width away: a strip is no board."""
    growth = None
    neighbours = sheet.neighbours() if sheet.neighbours is not None else None
    if neighbours is not None and len(neighbours.faces):
        width = float(np.ptp(np.asarray(piece.vertices) @ axes[1]))
        gaps = sheet_gaps(piece, axes[2], neighbours, min(sheet.reach, 0.5 * width))
        growth = sheet_growth(gaps, sheet.thickness)
    thickness, side = sheet.thickness, sheet.outward
    if growth is not None:
        side, thickness = growth[0] * axes[2], growth[1]
    log.add("sheet")
    if thickness != sheet.thickness:
        log.add("sheet met")
    log.sheet_mm.append(thickness * 1000.0)  # the readers pass metres
    return extruded_sheet(piece, thickness, side)


def _solid_piece(piece: trimesh.Trimesh, sheet: _SheetSettings, log: _Log) -> trimesh.Trimesh | None:
    """Step 3 for one connected, consistently wound piece: a solid, or None when the piece has no volume."""
    if is_solid(piece):
        return piece
    closed = is_closed_oriented(np.asarray(piece.faces))
    _, axes, spread = thinnest_axis(np.asarray(piece.vertices))
    if not closed and spread < sheet.max_thickness:
        return _sheet(piece, axes, sheet, log)
    if not closed:
        piece, holes = holes_closed(piece)
        log.add("holes", holes)
    if is_closed_oriented(np.asarray(piece.faces)) and _signed_volume(piece) < 0:
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
                neighbours: Callable[[], trimesh.Trimesh] | None = None, sheet_reach: float = SHEET_REACH_M,
                ) -> MeshIntake:
    """The solid of a part (see the module) and what was done; ``name`` says which part in messages (such as
    ``part 'leg_1'``). ``mesh``: the part's mesh in its own frame;
    ``sheet_thickness``, ``sheet_max_thickness`` and ``sheet_reach`` in the mesh's unit; ``outward``: (3,) a
    direction in the part frame pointing away from the assembly's centre, or None; ``neighbours``: a function giving
    the other parts' meshes as given, placed in this part's frame (called once, at the first one-surface board), or
    None (both for the side a one-surface board grows to and how thick).
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
    cleaned, rewound = consistently_wound(cleaned)
    log.add("rewound", rewound)
    groups = _face_groups(cleaned)
    if len(groups) > 1:
        log.add("loose", len(groups))
    unit_outward = None
    if outward is not None and np.linalg.norm(outward) > 0:
        unit_outward = np.asarray(outward, dtype=np.float64) / np.linalg.norm(outward)
    sheet = _SheetSettings(sheet_thickness, sheet_max_thickness, sheet_reach, unit_outward,
                           None if neighbours is None else cache(neighbours))  # placed once, for any board
    solids = []
    for group in groups:
        piece = cleaned.submesh([group], append=True, repair=False)
        solid = _solid_piece(piece, sheet, log)
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
