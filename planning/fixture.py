"""The assembly fixture: raised pads under the parts that stand on the floor of the assembly frame.

A board lying flat on a table cannot be held by a parallel-jaw gripper at its target: the lower finger would have
to go through the table. Robot cells solve this with a jig; ours is a set of box pads whose tops form the plane
z = 0 of the assembly frame, one under each part that touches that plane, each inset from the part's footprint
by :data:`FINGER_CLEARANCE_M` where the footprint is large enough, so that fingers can reach under a board's
edge. The pads stand on the cell's table, :data:`PAD_HEIGHT_M` below z = 0; a part drawn a few millimetres above
the floor (within the contact tolerance that makes the sequence fasten it there) gets a pad rising to meet it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import trimesh

from planning.contact import tolerance_for_size_m
from planning.pose import Pose

PAD_HEIGHT_M = 0.12  # the hand is about 20 cm long across its closing axis: an edge grasp of a flat board
# reaches about 10 cm below it
FINGER_CLEARANCE_M = 0.03  # fingertip (1.8 cm wide pad, 1.4 cm thick) plus margin
MIN_PAD_FRACTION = 0.4  # a pad keeps at least this fraction of each footprint dimension
FLOOR_CONTACT_M = 0.002  # vertices this close to a part's lowest point form its footprint


@dataclass(frozen=True)
class Pad:
    """One fixture pad: an axis-aligned box (metres) under part ``part``, its top at the part's lowest point (z = 0
    of the assembly frame, or within a few millimetres of it), its foot on the table."""

    part: str
    size_m: tuple[float, float, float]
    assembly_from_pad: Pose  # box centre

    def mesh(self) -> trimesh.Trimesh:
        """The pad's box in its own frame (centred)."""
        return trimesh.creation.box(self.size_m)


def fixture_pads(names: list[str], meshes_in_assembly: list[trimesh.Trimesh]) -> list[Pad]:
    """Pads under every part that stands on z = 0 (meshes already posed in the assembly frame): its lowest point
    within the contact graph's tolerance of the floor (:func:`planning.contact.tolerance_for_size_m`, 2-12 mm, so
    that a part the sequence fastens to the floor has a pad). A pad's top meets its part's lowest point: the legs of
    a real table drawn 4 mm above the floor stand on their pads."""
    pads = []
    for name, mesh in zip(names, meshes_in_assembly):
        vertices = np.asarray(mesh.vertices)
        lowest = float(vertices[:, 2].min())
        if lowest > tolerance_for_size_m(float(np.linalg.norm(np.ptp(vertices, axis=0)))):
            continue
        footprint = vertices[vertices[:, 2] <= lowest + FLOOR_CONTACT_M][:, :2]
        low, high = footprint.min(axis=0), footprint.max(axis=0)
        extent = high - low
        inset = np.minimum(FINGER_CLEARANCE_M, 0.5 * (1.0 - MIN_PAD_FRACTION) * extent)
        size_xy = np.maximum(extent - 2.0 * inset, 1e-3)
        centre_xy = 0.5 * (low + high)
        height = PAD_HEIGHT_M + lowest  # the foot stays on the table, PAD_HEIGHT_M below z = 0
        pads.append(Pad(name, (float(size_xy[0]), float(size_xy[1]), height),
                        Pose([centre_xy[0], centre_xy[1], lowest - 0.5 * height], [1.0, 0.0, 0.0, 0.0])))
    return pads
