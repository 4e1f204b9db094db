"""The assembly fixture: raised pads under the parts that stand on the floor of the assembly frame.

A board lying flat on a table cannot be held by a parallel-jaw gripper at its target: the lower finger would have
to go through the table. Robot cells solve this with a jig; ours is a set of box pads whose tops form the plane
z = 0 of the assembly frame, one under each part that touches that plane, each inset from the part's footprint
by :data:`FINGER_CLEARANCE_M` where the footprint is large enough, so that fingers can reach under a board's
edge. The pads stand on the cell's table, :data:`PAD_HEIGHT_M` below z = 0; a part drawn a few millimetres above
the floor (within the contact tolerance that makes the sequence fasten it there) gets a pad rising to meet it.

Some objects cannot be built standing: a table whose top has its legs under both overhangs and a frame flush
under its long edges leaves a parallel-jaw hand no edge to hold it by when it comes last, from above. Cells build
those upside down, the top first on the jig, and turn the finished object over: :func:`upside_down` gives the
assembly as the jig then holds it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import trimesh
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from planning.assembly import Assembly, AssemblyPart
from planning.contact import tolerance_for_size_m
from planning.pose import Pose

PAD_HEIGHT_M = 0.12  # the hand is about 20 cm long across its closing axis: an edge grasp of a flat board
# reaches about 10 cm below it
FINGER_CLEARANCE_M = 0.03  # fingertip (1.8 cm wide pad, 1.4 cm thick) plus margin
MIN_PAD_FRACTION = 0.4  # a pad keeps at least this fraction of each footprint dimension
FLOOR_CONTACT_M = 0.002  # vertices this close to a part's lowest point form its footprint


TURNED_OVER = Pose([0.0, 0.0, 0.0], [0.0, 1.0, 0.0, 0.0])  # half a turn about the assembly frame's x axis


def upside_down(assembly: Assembly) -> tuple[Assembly, Pose]:
    """``assembly`` turned over as a jig holds it built upside down: half a turn about its x axis, then moved so
    that its new lowest point lies on z = 0 and the origin at the centre of its new footprint (the x-y box of the
    vertices within :data:`FLOOR_CONTACT_M` of the floor: a table's top), as the assembly frame is defined
    (:mod:`planning.assembly`). Returns the turned assembly (same meshes, same part names) and
    ``turned_from_assembly``, the pose of the given assembly frame in the turned one."""
    turned = [(TURNED_OVER @ part.assembly_from_part).apply(part.mesh.vertices) for part in assembly.parts]
    lowest = min(float(points[:, 2].min()) for points in turned)
    floor = np.concatenate([points[points[:, 2] <= lowest + FLOOR_CONTACT_M, :2] for points in turned])
    centre = 0.5 * (floor.min(axis=0) + floor.max(axis=0))
    turned_from_assembly = Pose([-centre[0], -centre[1], -lowest], [1.0, 0.0, 0.0, 0.0]) @ TURNED_OVER
    parts = [AssemblyPart(part.name, part.mesh, turned_from_assembly @ part.assembly_from_part, part.mesh_file)
             for part in assembly.parts]
    return Assembly(assembly.name, parts, dict(assembly.metadata)), turned_from_assembly


@dataclass(frozen=True)
class Pad:
    """The fixture under part ``part``: one axis-aligned box per foot of the part (``boxes``: (size, centre) in the
    pad frame, metres), their tops at the part's lowest point (z = 0 of the assembly frame, or within a few
    millimetres of it), their feet on the table. The pad frame is the assembly frame translated to the middle of
    the part's footprint, at the boxes' mid-height."""

    part: str
    boxes: tuple[tuple[tuple[float, float, float], tuple[float, float, float]], ...]
    assembly_from_pad: Pose

    def mesh(self) -> trimesh.Trimesh:
        """The pad's boxes in its own frame."""
        boxes = [trimesh.creation.box(size, transform=trimesh.transformations.translation_matrix(centre))
                 for size, centre in self.boxes]
        return boxes[0] if len(boxes) == 1 else trimesh.util.concatenate(boxes)


def _feet(mesh: trimesh.Trimesh, lowest: float) -> list[tuple[np.ndarray, np.ndarray]]:
    """(low, high) x-y corners of each foot: the connected patches of faces lying within :data:`FLOOR_CONTACT_M` of
    the lowest point, patches whose boxes touch merged (a board's underside is one foot, a frame's two legs are
    two); a part that touches the floor only at vertices or edges has one foot around them."""
    vertices = np.asarray(mesh.vertices)
    near = vertices[:, 2] <= lowest + FLOOR_CONTACT_M
    faces = np.asarray(mesh.faces)
    bottom = faces[near[faces].all(axis=1)]
    boxes = []
    if len(bottom):
        # faces sharing a vertex position belong to one patch (meshes often repeat vertices at seams)
        _, key = np.unique(np.round(vertices[:, :2], 6), axis=0, return_inverse=True)
        corners = key.reshape(-1)[bottom]  # (faces, 3) position keys
        edges = np.concatenate([corners[:, [0, 1]], corners[:, [1, 2]]])
        size = int(key.max()) + 1
        _, patch = connected_components(coo_matrix((np.ones(len(edges)), (edges[:, 0], edges[:, 1])),
                                                   shape=(size, size)), directed=False)
        face_patch = patch[corners[:, 0]]
        for label in np.unique(face_patch):
            xy = vertices[bottom[face_patch == label].reshape(-1), :2]
            boxes.append((xy.min(axis=0), xy.max(axis=0)))
    else:
        xy = vertices[near, :2]
        boxes.append((xy.min(axis=0), xy.max(axis=0)))
    merged = True
    while merged and len(boxes) > 1:  # patches whose boxes touch or overlap form one foot
        merged = False
        for i in range(len(boxes)):
            for j in range(i + 1, len(boxes)):
                (lo_i, hi_i), (lo_j, hi_j) = boxes[i], boxes[j]
                if np.all(lo_i <= hi_j + FLOOR_CONTACT_M) and np.all(lo_j <= hi_i + FLOOR_CONTACT_M):
                    boxes[i] = (np.minimum(lo_i, lo_j), np.maximum(hi_i, hi_j))
                    del boxes[j]
                    merged = True
                    break
            if merged:
                break
    return boxes


def fixture_pads(names: list[str], meshes_in_assembly: list[trimesh.Trimesh]) -> list[Pad]:
    """Pads under every part that stands on z = 0 (meshes already posed in the assembly frame): its lowest point
    within the contact graph's tolerance of the floor (:func:`planning.contact.tolerance_for_size_m`, 2-12 mm, so
    that a part the sequence fastens to the floor has a pad). A pad's top meets its part's lowest point: the legs of
    a real table drawn 4 mm above the floor stand on their pads. Each foot of the part gets its own box, inset by
    :data:`FINGER_CLEARANCE_M` (or to :data:`MIN_PAD_FRACTION` of a small foot): one box spanning a side frame's two
    legs, inset from its ends, would miss both."""
    pads = []
    bounds = [np.asarray(mesh.bounds) for mesh in meshes_in_assembly]
    for index, (name, mesh) in enumerate(zip(names, meshes_in_assembly)):
        vertices = np.asarray(mesh.vertices)
        lowest = float(vertices[:, 2].min())
        if lowest > tolerance_for_size_m(float(np.linalg.norm(np.ptp(vertices, axis=0)))):
            continue
        height = PAD_HEIGHT_M + lowest  # the foot stays on the table, PAD_HEIGHT_M below z = 0
        # a foot above another part (a cabinet's side drawn on its bottom board, a few millimetres up) rests on
        # that part, not on a pad
        below = [b for k, b in enumerate(bounds) if k != index and b[0, 2] < lowest - FLOOR_CONTACT_M]
        feet = [(lo, hi) for lo, hi in _feet(mesh, lowest)
                if not any(np.all(lo < b[1, :2]) and np.all(b[0, :2] < hi) for b in below)]
        if not feet:
            continue
        middle = 0.5 * (np.min([lo for lo, _ in feet], axis=0) + np.max([hi for _, hi in feet], axis=0))
        boxes = []
        for low, high in feet:
            extent = high - low
            inset = np.minimum(FINGER_CLEARANCE_M, 0.5 * (1.0 - MIN_PAD_FRACTION) * extent)
            size_xy = np.maximum(extent - 2.0 * inset, 1e-3)
            centre_xy = 0.5 * (low + high) - middle
            boxes.append(((float(size_xy[0]), float(size_xy[1]), height),
                          (float(centre_xy[0]), float(centre_xy[1]), 0.0)))
        pads.append(Pad(name, tuple(boxes), Pose([middle[0], middle[1], lowest - 0.5 * height],
                                                 [1.0, 0.0, 0.0, 0.0])))
    return pads
