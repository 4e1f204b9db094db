"""The assembly fixture's pads (planning/fixture.py): under every part the contact graph stands on the floor."""

import numpy as np
import trimesh

from planning.assembly import AssemblyPart
from planning.collision import ConvexPart
from planning.contact import FLOOR, contact_graph
from planning.fixture import FINGER_CLEARANCE_M, PAD_HEIGHT_M, fixture_pads, upside_down
from planning.pose import Pose


def _box(size, centre):
    return trimesh.creation.box(size, transform=trimesh.transformations.translation_matrix(centre))


def _table_drawn_loosely():
    """A small table as real models draw one: leg a on the floor, leg b 4 mm above it (both under the top), a
    stretcher 3 cm above the floor, and a board lying on the floor."""
    return {"leg_a": _box((0.04, 0.04, 0.3), (0.0, 0.0, 0.15)),
            "leg_b": _box((0.04, 0.04, 0.3), (0.3, 0.0, 0.154)),
            "stretcher": _box((0.26, 0.02, 0.02), (0.15, 0.0, 0.04)),
            "board": _box((0.3, 0.2, 0.018), (0.15, 0.4, 0.009))}


def _box_corners(pad):
    """(8 * boxes, 3) corners of a pad's boxes, assembly frame."""
    return np.concatenate([pad.assembly_from_pad.apply(trimesh.bounds.corners(
        np.array([centre, centre]) + np.array([-0.5, 0.5])[:, None] * np.array(size))) for size, centre in pad.boxes])


def test_pads_meet_every_part_the_contact_graph_stands_on_the_floor():
    meshes = _table_drawn_loosely()
    pads = {pad.part: pad for pad in fixture_pads(list(meshes), list(meshes.values()))}
    identity = Pose([0.0, 0.0, 0.0], [1.0, 0.0, 0.0, 0.0])
    graph = contact_graph([ConvexPart.from_mesh(n, m) for n, m in meshes.items()], [identity] * len(meshes))
    on_floor = set(graph.neighbors(FLOOR))
    assert on_floor == {"leg_a", "leg_b", "board"} == set(pads)
    for name, pad in pads.items():
        z = _box_corners(pad)[:, 2]
        lowest = meshes[name].bounds[0][2]
        assert abs(z.max() - lowest) < 1e-9  # the top meets the part ...
        assert abs(z.min() + PAD_HEIGHT_M) < 1e-9  # ... and the foot stands on the table
    assert abs(pads["leg_b"].boxes[0][0][2] - (PAD_HEIGHT_M + 0.004)) < 1e-9
    # a board's pad is inset for the fingers; a leg's keeps a share of its footprint
    assert np.allclose(pads["board"].boxes[0][0][:2], (0.3 - 2 * FINGER_CLEARANCE_M, 0.2 - 2 * FINGER_CLEARANCE_M))
    assert 0.0 < pads["leg_b"].boxes[0][0][0] < 0.04


def test_a_frame_stands_on_a_box_under_each_foot_and_a_side_on_its_bottom_board_gets_none():
    # a side frame: two 2 cm legs 24 cm apart joined by a rail; one box spanning the footprint, inset 3 cm from its
    # ends for the fingers, would stand under neither leg
    legs = [_box((0.02, 0.02, 0.5), (0.0, y, 0.25)) for y in (-0.12, 0.12)]
    frame = trimesh.util.concatenate(legs + [_box((0.02, 0.26, 0.02), (0.0, 0.0, 0.3))])
    bottom = _box((0.4, 0.3, 0.006), (0.5, 0.0, 0.003))  # a 6 mm board on the floor; the side stands on it, drawn
    side = _box((0.018, 0.3, 0.4), (0.5 + 0.19, 0.0, 0.004 + 0.2))  # 2 mm into it: 4 mm up, within the tolerance
    pads = {pad.part: pad for pad in fixture_pads(["frame", "bottom", "side"], [frame, bottom, side])}
    assert set(pads) == {"frame", "bottom"}
    corners = _box_corners(pads["frame"]).reshape(-1, 8, 3)
    assert len(corners) == 2
    for leg, box in zip(sorted(legs, key=lambda m: m.bounds[0][1]), sorted(corners, key=lambda c: c[:, 1].min())):
        assert np.all(box[:, :2].min(axis=0) >= leg.bounds[0][:2] - 1e-9)  # under the leg
        assert np.all(box[:, :2].max(axis=0) <= leg.bounds[1][:2] + 1e-9)


def test_upside_down_turns_the_assembly_over_with_its_top_on_the_floor(tray):
    tray.parts[0] = AssemblyPart("top", tray.parts[0].mesh, Pose([0.02, 0.01, 0.109], [1, 0, 0, 0]))  # off centre
    turned, turned_from_tray = upside_down(tray)
    assert np.allclose(turned_from_tray.rotation, np.diag([1.0, -1.0, -1.0]))
    meshes = dict(zip(turned.part_names, turned.meshes_in_assembly_frame()))
    top = meshes["top"].bounds
    assert abs(top[0, 2]) < 1e-9  # the top lies on the floor
    assert np.allclose(0.5 * (top[0, :2] + top[1, :2]), 0.0)  # the origin at the middle of its footprint
    for name in ("long_left", "long_right", "end_front", "end_back"):  # the walls stand on it, reaching up
        assert abs(meshes[name].bounds[0, 2] - 0.018) < 1e-9 and abs(meshes[name].bounds[1, 2] - 0.118) < 1e-9
    assert np.allclose(meshes["long_left"].bounds[:, 1], [0.092, 0.110])  # -y turned over about x, the top centred
    for before, after in zip(tray.parts, turned.parts):  # same meshes, each part where the turn puts it
        assert after.mesh is before.mesh and after.name == before.name
        assert np.allclose(after.assembly_from_part.matrix(),
                           (turned_from_tray @ before.assembly_from_part).matrix())
