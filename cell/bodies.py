"""PyBullet bodies of meshes as the simulation builds them: compounds of convex pieces, optionally inset.

One place for how a part becomes a rigid body (:mod:`cell.simulate` runs the program with these bodies,
:mod:`cell.resting` checks that the kitting layout's parts rest where they lie with the same bodies): the mesh's
convex pieces (:func:`planning.convex.convex_pieces`), each inset by a distance (metres), written as one OBJ
object per piece (PyBullet loads such a file as a compound of convex hulls), no collision margin, the given
friction, and the mass and inertia of :class:`planning.payload.MassProperties` (none: a static body).
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np
import trimesh
from scipy.spatial import HalfspaceIntersection

from planning.convex import convex_hull, convex_pieces, mesh_key
from planning.payload import MassProperties
from planning.pose import Pose


def inset(piece: trimesh.Trimesh, distance_m: float) -> trimesh.Trimesh:
    """The convex ``piece`` with every face moved inwards by ``distance_m`` (metres; the intersection of its faces'
    half-spaces); a piece too thin for that is returned as it is."""
    hull = convex_hull(piece.vertices)
    if distance_m <= 0.0:
        return hull
    normals = np.asarray(hull.face_normals, dtype=np.float64)
    offsets = distance_m - np.einsum("ij,ij->i", normals, hull.triangles[:, 0])  # inside: normals @ x + offsets <= 0
    centre = np.asarray(hull.centroid, dtype=np.float64)
    if np.max(normals @ centre + offsets) > -1e-6:
        return hull
    corners = HalfspaceIntersection(np.hstack([normals, offsets[:, None]]), centre).intersections
    return trimesh.convex.convex_hull(corners)


def write_pieces_obj(pieces: Sequence[trimesh.Trimesh], path: Path) -> None:
    """One OBJ object per convex piece: PyBullet loads such a file as a compound of convex hulls."""
    lines, offset = [], 1
    for index, piece in enumerate(pieces):
        lines.append(f"o piece{index}")
        lines += [f"v {x:.9f} {y:.9f} {z:.9f}" for x, y, z in piece.vertices]
        lines += [f"f {a + offset} {b + offset} {c + offset}" for a, b, c in piece.faces]
        offset += len(piece.vertices)
    path.write_text("\n".join(lines) + "\n")


def add_convex_body(pb, client_id: int, folder: Path, mesh: trimesh.Trimesh, world_from_body: Pose,
                    props: MassProperties | None, friction: float, inset_m: float = 0.0,
                    key: str | None = None) -> int:
    """A body of ``mesh``'s convex pieces inset by ``inset_m`` at ``world_from_body`` (mesh frame), dynamic with
    ``props`` or static (None); no visual shape. The pieces' OBJ file is written into ``folder`` once per mesh and
    inset (reused by later calls with the same folder); ``key``: the mesh's :func:`planning.convex.mesh_key` when
    the caller has it (hashing a large mesh takes time). Returns the body id."""
    path = folder / f"{key or mesh_key(mesh)}-{inset_m:.6f}.obj"
    if not path.exists():
        write_pieces_obj([inset(piece, inset_m) for piece in convex_pieces(mesh)], path)
    collision = pb.createCollisionShape(pb.GEOM_MESH, fileName=str(path), physicsClientId=client_id)
    if collision < 0:
        raise RuntimeError(f"PyBullet refused the collision pieces of a mesh of {len(mesh.faces)} faces")
    position, orientation = world_from_body.to_pybullet()
    inertial = {}
    if props is not None:
        com_position, com_orientation = props.part_from_com.to_pybullet()
        inertial = {"baseInertialFramePosition": com_position, "baseInertialFrameOrientation": com_orientation}
    body = pb.createMultiBody(props.mass_kg if props else 0.0, collision, -1, position, orientation,
                              physicsClientId=client_id, **inertial)
    dynamics = {"localInertiaDiagonal": props.inertia_kg_m2} if props else {}
    # no collision margin: PyBullet's default pads convex hulls by about 1 mm each, so stacked parts would float
    pb.changeDynamics(body, -1, collisionMargin=0.0, lateralFriction=friction, physicsClientId=client_id,
                      **dynamics)
    return body
