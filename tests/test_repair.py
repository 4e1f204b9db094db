"""Pose repair: interpenetration removed, near-contacts closed, faces aligned, moves bounded."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from planning.assembly import read_assembly
from planning.collision import ConvexPart
from planning.contact import contact_graph
from planning.pose import Pose
from planning.repair import RepairSettings, repair_poses, snap_rotation_to_axes
from scenes import sample_folder


def perturbed(truth, seed, position_sigma_m=0.004, angle_sigma_deg=2.0):
    rng = np.random.default_rng(seed)
    out = []
    for pose in truth:
        rotation = Rotation.from_rotvec(rng.normal(size=3) * np.radians(angle_sigma_deg)).as_matrix()
        out.append(Pose.from_rotation(rotation @ pose.rotation, pose.position + rng.normal(size=3) * position_sigma_m))
    return out


def edges(graph):
    return {frozenset(e) for e in graph.edges}


@pytest.mark.parametrize("category", ["chair", "table", "cabinet"])
def test_repair_restores_contacts_and_removes_penetration(category):
    assembly = read_assembly(sample_folder(category))
    parts = [ConvexPart.from_mesh(p.name, p.mesh) for p in assembly.parts]
    truth = [p.assembly_from_part for p in assembly.parts]
    noisy = perturbed(truth, seed=1)
    settings = RepairSettings()
    repaired, report = repair_poses(parts, noisy, settings)
    assert report.deepest_penetration_before_m > 0.002
    assert report.deepest_penetration_after_m <= 0.001
    assert all(depth <= 0.001 for _, _, depth in report.overlapping_pairs_after)
    assert max(report.translation_m.values()) <= settings.max_translation_m + 1e-9
    assert max(report.rotation_deg.values()) <= settings.max_rotation_deg + 1e-6
    assert report.crossed_parts == ()  # nothing crossed: no part got the wider bound
    # the generator builds along the axes: aligned faces come back exactly
    for pose, true_pose in zip(repaired, truth):
        assert np.degrees(pose.distance(true_pose)[1]) < 1e-6
    # the contacts of the true assembly are there again
    assert edges(contact_graph(parts, truth)) <= edges(contact_graph(parts, repaired))


def test_crossed_parts_get_the_wider_bound_and_are_parted():
    """A cabinet side placed 14 cm inward runs through the shelves deeper than the 50 mm bound undoes; step 5
    gives the crossed parts the wider bound and parts them, and moves no other part further than before."""
    assembly = read_assembly(sample_folder("cabinet"))
    parts = [ConvexPart.from_mesh(p.name, p.mesh) for p in assembly.parts]
    poses = [p.assembly_from_part for p in assembly.parts]
    side = assembly.part_names.index("side_left")
    poses[side] = Pose(poses[side].position + [0.14, 0.0, 0.0], poses[side].quat_wxyz)
    settings = RepairSettings()
    assert settings.crossing_translation_m > settings.max_translation_m

    bounded_only, report = repair_poses(parts, poses, RepairSettings(crossing_translation_m=settings.max_translation_m))
    assert report.overlapping_pairs_after[0][2] > settings.crossing_depth_m  # still crossed: no cell builds this
    assert report.crossed_parts == ()

    repaired, report = repair_poses(parts, poses, settings)
    assert "side_left" in report.crossed_parts
    assert all(depth <= settings.crossing_depth_m for _, _, depth in report.overlapping_pairs_after)
    assert report.translation_m["side_left"] > settings.max_translation_m + 0.01  # it needed the wider bound
    for name, moved_m in report.translation_m.items():
        bound = settings.crossing_translation_m if name in report.crossed_parts else settings.max_translation_m
        assert moved_m <= bound + 1e-9, name
    # the side went back out towards its place
    assert repaired[side].position[0] < bounded_only[side].position[0] - 0.01


def test_a_tilted_crossed_part_is_turned_back_onto_the_axes():
    """A cabinet's bottom tilted 40 degrees and raised 8 cm cuts through the lowest shelf: moving it alone, even by the
    wider bound, leaves them crossed (40 mm), and turning the crossed parts onto the assembly axes parts them, the
    bottom back in its true orientation."""
    assembly = read_assembly(sample_folder("cabinet"))
    parts = [ConvexPart.from_mesh(p.name, p.mesh) for p in assembly.parts]
    poses = [p.assembly_from_part for p in assembly.parts]
    k = assembly.part_names.index("bottom")
    centre = poses[k].apply(assembly.part("bottom").mesh.bounding_box.centroid[None])[0]
    tilt = Rotation.from_euler("y", 40, degrees=True).as_matrix()
    poses[k] = Pose([0.0, 0.0, 0.08], [1, 0, 0, 0]) @ Pose.from_rotation(tilt, centre) @ Pose(-centre, [1, 0, 0, 0]) \
        @ poses[k]
    settings = RepairSettings()
    assert settings.crossing_align_tolerance_deg >= 62.8  # every crossed part is turned onto the axes

    _, untouched = repair_poses(parts, poses, RepairSettings(crossing_align_tolerance_deg=settings.align_tolerance_deg))
    assert untouched.overlapping_pairs_after[0][2] > settings.crossing_depth_m
    repaired, report = repair_poses(parts, poses, settings)
    assert "bottom" in report.crossed_parts
    assert all(depth <= settings.crossing_depth_m for _, _, depth in report.overlapping_pairs_after)
    assert report.rotation_deg["bottom"] == pytest.approx(40.0, abs=1e-6)
    np.testing.assert_allclose(repaired[k].rotation, assembly.part("bottom").assembly_from_part.rotation, atol=1e-9)
    assert report.translation_m["bottom"] <= settings.crossing_translation_m + 1e-9


def test_moves_are_bounded():
    assembly = read_assembly(sample_folder("table"))
    parts = [ConvexPart.from_mesh(p.name, p.mesh) for p in assembly.parts]
    poses = [p.assembly_from_part for p in assembly.parts]
    top = assembly.part_names.index("top")
    poses[top] = Pose(poses[top].position - [0, 0, 0.05], poses[top].quat_wxyz)  # sunk 5 cm into the legs
    settings = RepairSettings(max_translation_m=0.02)
    repaired, report = repair_poses(parts, poses, settings)
    assert repaired[top].position[2] > poses[top].position[2] + 0.01  # pushed up out of the legs
    assert all(v <= 0.02 + 1e-9 for v in report.translation_m.values())
    assert max(report.translation_m.values()) == pytest.approx(0.02, abs=1e-6)  # the bound was needed


def test_crossed_panels_stay_crossed_and_are_reported():
    """Two panels through each other (a cross, 300 mm deep) need more than even the crossed parts' wider bound to
    part: the repair moves each by at most that bound and reports the pair, deepest first."""
    import trimesh

    panel = trimesh.creation.box([0.6, 0.015, 0.4])
    parts = [ConvexPart.from_mesh("front", panel), ConvexPart.from_mesh("side", panel),
             ConvexPart.from_mesh("shelf", trimesh.creation.box([0.1, 0.1, 0.01]))]
    quarter_turn_z = Rotation.from_euler("z", 90, degrees=True).as_matrix()
    poses = [Pose([0.0, 0.0, 0.2], [1.0, 0.0, 0.0, 0.0]), Pose.from_rotation(quarter_turn_z, [0.0, 0.0, 0.2]),
             Pose([0.8, 0.0, 0.005], [1.0, 0.0, 0.0, 0.0])]
    settings = RepairSettings(connect_distance_m=0.0)
    _, report = repair_poses(parts, poses, settings)
    assert report.crossed_parts == ("front", "side")
    assert max(report.translation_m.values()) == pytest.approx(settings.crossing_translation_m, abs=1e-6)
    assert report.translation_m["shelf"] == 0.0
    (a, b, depth), = report.overlapping_pairs_after  # the shelf apart on the floor overlaps nothing
    assert {a, b} == {"front", "side"}
    assert depth > 0.3 - 2 * settings.crossing_translation_m - 1e-3 and depth == report.deepest_penetration_after_m


def test_snap_rotation():
    small = Rotation.from_rotvec([0.02, -0.03, 0.05]).as_matrix()
    np.testing.assert_array_equal(snap_rotation_to_axes(small, 8.0), np.eye(3))
    turned = Rotation.from_rotvec([0, 0, np.pi / 2 + 0.05]).as_matrix()
    np.testing.assert_allclose(snap_rotation_to_axes(turned, 8.0), [[0, -1, 0], [1, 0, 0], [0, 0, 1]], atol=1e-12)
    tilted = Rotation.from_rotvec([0, 0.3, 0]).as_matrix()  # 17 degrees: left alone
    np.testing.assert_array_equal(snap_rotation_to_axes(tilted, 8.0), tilted)
    def angle_deg(a, b):
        return np.degrees(np.arccos(np.clip((np.trace(a.T @ b) - 1) / 2, -1, 1)))

    axis_rotations = Rotation.from_euler("zyx", [(a, b, c) for a in (0, 90, 180, 270) for b in (0, 90, 180, 270)
                                                 for c in (0, 90, 180, 270)], degrees=True).as_matrix().round()
    for rotation in Rotation.random(200, random_state=0).as_matrix():  # with no tolerance, the nearest of the 24
        snapped = snap_rotation_to_axes(rotation, 180.0)
        assert set(np.unique(snapped)) <= {-1.0, 0.0, 1.0} and np.linalg.det(snapped) == pytest.approx(1.0)
        assert angle_deg(rotation, snapped) <= 62.8 + 1e-6
        assert angle_deg(rotation, snapped) <= min(angle_deg(rotation, r) for r in axis_rotations) + 1e-6
        assert snap_rotation_to_axes(snapped @ Rotation.from_rotvec([0.0, 0.0, 0.1]).as_matrix(), 8.0) \
            == pytest.approx(snapped)


@pytest.mark.parametrize("gap_m, joins", [(0.02, True), (RepairSettings().connect_distance_m + 0.02, False)])
def test_an_isolated_part_joins_its_nearest_part(gap_m, joins):
    """A part touching nothing, farther than the pairwise snap but within connect_distance_m of another part, is
    moved alone onto it; beyond that distance, or with the step off, it stays where it was predicted."""
    import trimesh

    board = ConvexPart.from_mesh("board", trimesh.creation.box((0.30, 0.20, 0.02)))
    post = ConvexPart.from_mesh("post", trimesh.creation.box((0.03, 0.03, 0.20)))
    identity = np.array([1.0, 0.0, 0.0, 0.0])
    # in the air: the post under the board, a gap between them
    poses = [Pose(np.array([0.0, 0.0, 0.50]), identity), Pose(np.array([0.0, 0.0, 0.39 - gap_m]), identity)]
    for settings in (RepairSettings(snap_distance_m=0.01), RepairSettings(snap_distance_m=0.01, connect_distance_m=0)):
        parts = [board, post]
        repaired, report = repair_poses(parts, poses, settings)
        graph = contact_graph(parts, repaired)
        connected = graph.has_edge("board", "post")
        assert connected == (joins and settings.connect_distance_m > 0)
        if connected:
            # the post alone moved up by the gap, within the bound; the board stayed
            assert report.translation_m["board"] < 1e-9
            assert report.translation_m["post"] == pytest.approx(gap_m, abs=1e-4)
        else:
            assert max(report.translation_m.values()) < 1e-9


def test_joining_repeats_when_the_contact_rounds_part_a_joined_part_again():
    """The sample chair, its truth poses moved by 3 cm (sigma): after one join pass and the contact rounds that
    follow it the chair is in two pieces again (a part's neighbours moved with their other contacts); the default
    passes join it anew, within the bound."""
    from planning.contact import pieces

    assembly = read_assembly(sample_folder("chair"))
    parts = [ConvexPart.from_mesh(p.name, p.mesh) for p in assembly.parts]
    noisy = perturbed([p.assembly_from_part for p in assembly.parts], seed=0, position_sigma_m=0.03,
                      angle_sigma_deg=3.0)

    def piece_count(poses):
        return len(pieces(contact_graph(parts, poses)))

    once, _ = repair_poses(parts, noisy, RepairSettings(connect_passes=1))
    settings = RepairSettings()
    assert settings.connect_passes > 1
    repeated, report = repair_poses(parts, noisy, settings)
    assert piece_count(noisy) > 1 and piece_count(once) == 2 and piece_count(repeated) == 1
    assert max(report.translation_m.values()) <= settings.max_translation_m + 1e-9


def test_a_floating_piece_of_several_parts_is_lowered_onto_the_standing_one():
    """A board with a block fastened on it hangs 3 cm above a post standing on the floor (a predicted table top
    and its legs, short of the aprons): the two touching parts move down together onto the post, which stays on
    the floor. Joining parts one at a time would lift the post off the floor instead and leave the board and
    block hanging."""
    import trimesh

    from planning.contact import FLOOR, pieces, ungrounded

    board = ConvexPart.from_mesh("board", trimesh.creation.box((0.30, 0.20, 0.02)))
    block = ConvexPart.from_mesh("block", trimesh.creation.box((0.05, 0.05, 0.05)))
    post = ConvexPart.from_mesh("post", trimesh.creation.box((0.03, 0.03, 0.40)))
    identity = np.array([1.0, 0.0, 0.0, 0.0])
    gap_m = 0.03
    poses = [Pose(np.array([0.0, 0.0, 0.41 + gap_m]), identity),  # board: 0.40 + gap to 0.42 + gap
             Pose(np.array([0.10, 0.0, 0.445 + gap_m]), identity),  # block: on the board
             Pose(np.array([0.0, 0.0, 0.20]), identity)]  # post: on the floor, top at 0.40
    parts = [board, block, post]
    assert len(pieces(contact_graph(parts, poses))) == 2
    repaired, report = repair_poses(parts, poses, RepairSettings(snap_distance_m=0.01))
    graph = contact_graph(parts, repaired)
    assert pieces(graph) == [{"board", "block", "post"}]
    assert ungrounded(graph, {"board", "block", "post"}) == set() and graph.has_edge(FLOOR, "post")
    assert report.translation_m["post"] < 1e-9
    assert report.translation_m["board"] == pytest.approx(gap_m, abs=1e-4)
    assert report.translation_m["block"] == pytest.approx(gap_m, abs=1e-4)


@pytest.mark.parametrize("height_m, lowered", [(0.03, True), (RepairSettings().rest_distance_m + 0.02, False)])
def test_a_whole_assembly_hanging_above_the_floor_is_lowered_onto_it(height_m, lowered):
    """A board on a post, in contact, the whole hanging ``height_m`` above the floor (a repaired prediction in one
    piece whose lowest part the rounds lifted): step 6 lowers both together onto the floor, so the post stands on
    it and the board still rests on the post; beyond ``rest_distance_m``, or with the step off, nothing moves."""
    import trimesh

    from planning.contact import FLOOR

    board = ConvexPart.from_mesh("board", trimesh.creation.box((0.30, 0.20, 0.02)))
    post = ConvexPart.from_mesh("post", trimesh.creation.box((0.03, 0.03, 0.40)))
    identity = np.array([1.0, 0.0, 0.0, 0.0])
    poses = [Pose(np.array([0.0, 0.0, 0.41 + height_m]), identity),  # board: on the post
             Pose(np.array([0.0, 0.0, 0.20 + height_m]), identity)]  # post: its foot height_m above the floor
    parts = [board, post]
    for settings in (RepairSettings(), RepairSettings(rest_distance_m=0.0)):
        repaired, report = repair_poses(parts, poses, settings)
        graph = contact_graph(parts, repaired)
        assert graph.has_edge("board", "post")
        moves = lowered and settings.rest_distance_m > 0
        assert graph.has_edge(FLOOR, "post") == moves
        assert report.lowered_m == pytest.approx(height_m if moves else 0.0, abs=1e-9)
        for before, after in zip(poses, repaired):
            assert after.position == pytest.approx(before.position - [0.0, 0.0, report.lowered_m], abs=1e-9)
            assert after.quat_wxyz == pytest.approx(before.quat_wxyz)
