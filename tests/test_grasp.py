"""Panda hand geometry and antipodal grasps: real meshes, real FCL, seeded."""

import glob
import math
import os
import xml.etree.ElementTree as ET
from pathlib import Path

import fcl
import numpy as np
import pytest
import trimesh

from planning import grasp as grasp_module
from planning import gripper as hand
from planning.assembly import read_assembly
from planning.grasp import (
    MAX_GRASP_WIDTH_M,
    NoGraspError,
    ObstacleSet,
    antipodal_grasps,
    explain_no_grasp,
    feasible_grasps,
    rank,
)
from planning.pose import Pose

REPO = Path(__file__).resolve().parents[1]
FURNITURE = REPO.parent / "shared" / "furniture"
IDENTITY_Q = np.array([1.0, 0.0, 0.0, 0.0])


# --- an FCL model of the hand built here from the URDF, independently of planning.gripper's posing code ---------


def _convex(vertices, faces):
    flat = np.concatenate([[3, *f] for f in faces]).astype(np.int64)
    return fcl.Convex(np.asarray(vertices, dtype=np.float64), len(faces), flat)


def _hand_pieces(world_from_tcp: Pose, opening: float) -> list[tuple[np.ndarray, Pose]]:
    """(hull vertices in link frame, world_from_link) for hand, left and right finger, from the URDF numbers."""
    geo = hand.load_hand_geometry()
    world_from_hand = world_from_tcp @ hand.HAND_FROM_TCP.inverse()
    z = geo.finger_joint_z_m
    half_turn = np.array([[-1.0, 0.0, 0.0], [0.0, -1.0, 0.0], [0.0, 0.0, 1.0]])
    return [
        (geo.hand_vertices, world_from_hand),
        (geo.finger_vertices, world_from_hand @ Pose(np.array([0.0, opening / 2, z]), IDENTITY_Q)),
        (geo.finger_vertices, world_from_hand @ Pose.from_rotation(half_turn, [0.0, -opening / 2, z])),
    ]


def hand_hits(world_from_tcp: Pose, opening: float, mesh: trimesh.Trimesh, world_from_mesh: Pose) -> bool:
    """FCL convex pieces against the mesh's BVH, plus any hull vertex inside the (watertight) mesh."""
    geo = hand.load_hand_geometry()
    model = fcl.BVHModel()
    model.beginModel(len(mesh.vertices), len(mesh.faces))
    model.addSubModel(np.asarray(mesh.vertices, dtype=np.float64), np.asarray(mesh.faces, dtype=np.int64))
    model.endModel()
    target = fcl.CollisionObject(model, world_from_mesh.to_fcl())
    faces = (geo.hand_faces, geo.finger_faces, geo.finger_faces)
    mesh_from_world = world_from_mesh.inverse()
    for (vertices, world_from_link), f in zip(_hand_pieces(world_from_tcp, opening), faces):
        obj = fcl.CollisionObject(_convex(vertices, f), world_from_link.to_fcl())
        if fcl.collide(obj, target, fcl.CollisionRequest(), fcl.CollisionResult()):
            return True
        if np.any(mesh.contains(mesh_from_world.apply(world_from_link.apply(vertices)))):
            return True
    return False


def hand_min_z(world_from_tcp: Pose, opening: float) -> float:
    return min(float(pose.apply(v)[:, 2].min()) for v, pose in _hand_pieces(world_from_tcp, opening))


def box_at(extents, centre) -> tuple[trimesh.Trimesh, Pose]:
    return trimesh.creation.box(extents), Pose(np.asarray(centre, dtype=np.float64), IDENTITY_Q)


# --- the hand -------------------------------------------------------------------------------------------------------


def test_constants_match_the_urdf():
    geo = hand.load_hand_geometry()
    root = ET.parse(hand.panda_urdf_path()).getroot()
    joints = {j.get("name"): j for j in root.findall("joint")}
    tcp_xyz = [float(v) for v in joints["panda_grasptarget_hand"].find("origin").get("xyz").split()]
    assert tcp_xyz == [0.0, 0.0, hand.TCP_Z_IN_HAND_M]
    np.testing.assert_allclose(hand.HAND_FROM_TCP.position, tcp_xyz)
    np.testing.assert_allclose(hand.HAND_FROM_TCP.quat_wxyz, IDENTITY_Q)
    assert geo.finger_travel_m == hand.FINGER_TRAVEL_M and hand.MAX_OPENING_M == pytest.approx(0.08)
    assert geo.finger_joint_z_m == pytest.approx(hand.FINGER_JOINT_Z_IN_HAND_M)
    assert geo.fingertip_z_m == pytest.approx(hand.FINGERTIP_Z_IN_HAND_M, abs=5e-4)
    assert geo.palm_z_m == pytest.approx(hand.PALM_Z_IN_HAND_M, abs=5e-4)
    pad = geo.pad_vertices()
    assert np.ptp(pad[:, 2]) == pytest.approx(hand.FINGER_PAD_LENGTH_M, abs=5e-4)
    assert np.ptp(pad[:, 0]) == pytest.approx(hand.FINGER_PAD_WIDTH_M, abs=5e-4)
    tip = geo.finger_vertices[geo.finger_vertices[:, 2] >= pad[:, 2].min() - 1e-6]
    assert tip[:, 1].max() == pytest.approx(hand.FINGER_PAD_DEPTH_M, abs=5e-4)
    pad_z_in_tcp = geo.finger_joint_z_m + np.array([pad[:, 2].min(), pad[:, 2].max()]) - hand.TCP_Z_IN_HAND_M
    np.testing.assert_allclose(pad_z_in_tcp, hand.PAD_Z_RANGE_IN_TCP_M, atol=5e-4)
    assert hand.USABLE_FINGER_DEPTH_M == pytest.approx(0.0462, abs=5e-4)
    assert hand.PAD_Z_RANGE_IN_TCP_M[0] < 0.0 < hand.PAD_Z_RANGE_IN_TCP_M[1]  # the TCP lies on the pads


def test_collision_model_places_the_pads_at_the_opening():
    model = hand.default_gripper()
    for opening in (0.0, 0.03, 0.08):
        pieces = model.tcp_from_pieces(opening)
        left = model.piece_vertices()[1] @ pieces[1, :3, :3].T + pieces[1, :3, 3]
        right = model.piece_vertices()[2] @ pieces[2, :3, :3].T + pieces[2, :3, 3]
        assert left[:, 1].min() == pytest.approx(opening / 2, abs=2e-4)
        assert right[:, 1].max() == pytest.approx(-opening / 2, abs=2e-4)
        assert left[:, 2].max() == pytest.approx(hand.FINGERTIP_Z_IN_HAND_M - hand.TCP_Z_IN_HAND_M, abs=5e-4)
    # the model agrees with the test's own construction of the hand
    rng = np.random.default_rng(0)
    q = rng.normal(size=4)
    pose = Pose(rng.normal(size=3), q)
    ours = np.concatenate([p.apply(v) for v, p in _hand_pieces(pose, 0.05)])
    np.testing.assert_allclose(model.vertices(pose, 0.05), ours, atol=1e-12)


def test_frames_agree_with_pybullet():
    from cell.bullet import BulletClient

    rng = np.random.default_rng(5)
    with BulletClient() as sim:
        pb, cid = sim.pb, sim.client_id
        robot = pb.loadURDF(hand.panda_urdf_path(), useFixedBase=True, physicsClientId=cid)
        names = {pb.getJointInfo(robot, j, physicsClientId=cid)[12].decode(): j for j in range(11 + 1)}
        model = hand.default_gripper()
        for _ in range(3):
            opening = float(rng.uniform(0.0, 0.08))
            for j in range(7):
                pb.resetJointState(robot, j, float(rng.uniform(-1.5, 1.5)), physicsClientId=cid)
            for j in (9, 10):
                pb.resetJointState(robot, j, opening / 2, physicsClientId=cid)

            def link_pose(name):
                state = pb.getLinkState(robot, names[name], computeForwardKinematics=True, physicsClientId=cid)
                return Pose.from_pybullet(state[4], state[5])  # the URDF link frame

            world_from_tcp = link_pose("panda_hand") @ hand.HAND_FROM_TCP
            assert world_from_tcp.is_close(link_pose("panda_grasptarget"), 1e-6, 1e-6)
            pieces = world_from_tcp.matrix() @ model.tcp_from_pieces(opening)
            np.testing.assert_allclose(pieces[1], link_pose("panda_leftfinger").matrix(), atol=1e-6)
            np.testing.assert_allclose(pieces[2, :3, 3], link_pose("panda_rightfinger").position, atol=1e-6)
            for k, name in ((1, "panda_leftfinger"), (2, "panda_rightfinger")):
                ours = model.piece_vertices()[k] @ pieces[k, :3, :3].T + pieces[k, :3, 3]
                lo, hi = (np.array(v) for v in pb.getAABB(robot, names[name], physicsClientId=cid))
                # PyBullet's box is its local box turned with the link, so looser than ours, never tighter
                assert np.all(ours.min(axis=0) >= lo - 1e-4) and np.all(ours.max(axis=0) <= hi + 1e-4)
                assert np.all(ours.max(axis=0) - ours.min(axis=0) >= 0.6 * (hi - lo))


# --- candidates on single parts -------------------------------------------------------------------------------------


def test_bar_is_grasped_across_its_thin_dimension():
    bar = trimesh.creation.box((0.03, 0.03, 0.30))
    grasps = antipodal_grasps(bar, np.random.default_rng(0))
    assert len(grasps) >= 20
    for g in grasps:
        assert g.width_m == pytest.approx(0.03, abs=1e-6)
        axis = g.closing_axis_part
        assert abs(axis[2]) < 1e-6 and max(abs(axis[0]), abs(axis[1])) == pytest.approx(1.0)
        tcp = g.part_from_tcp.position
        np.testing.assert_allclose(tcp, g.contacts_part.mean(axis=0), atol=1e-9)
        np.testing.assert_allclose(g.contacts_part[1] - g.contacts_part[0], g.width_m * axis, atol=1e-9)
        assert np.all(np.abs(g.contacts_part[:, :2]).max(axis=1) == pytest.approx(0.015, abs=1e-6))
        assert g.opening_m == pytest.approx(0.04)
    for g in grasps[:30]:
        assert not hand_hits(g.part_from_tcp, g.opening_m, bar, Pose.identity())
    world_from_bar = Pose(np.array([0.4, 0.1, 0.015]), np.array([0.5, 0.5, 0.5, 0.5]))
    g = grasps[0]
    assert (g.world_from_hand(world_from_bar) @ hand.HAND_FROM_TCP).is_close(g.world_from_tcp(world_from_bar), 1e-12)
    scores = [g.score for g in grasps]
    assert scores == sorted(scores, reverse=True)
    assert grasps[0].contact_score == 1.0 and grasps[0].centroid_score > 0.8


def test_same_seed_same_grasps():
    bar = trimesh.creation.box((0.03, 0.03, 0.30))
    a = antipodal_grasps(bar, np.random.default_rng(7))
    b = antipodal_grasps(bar.copy(), np.random.default_rng(7))  # a different object with the same content
    assert len(a) == len(b)
    for ga, gb in zip(a, b):
        assert ga.part_from_tcp.is_close(gb.part_from_tcp) and ga.score == gb.score


def test_cube_too_thick_for_the_hand():
    cube = trimesh.creation.box((0.1, 0.1, 0.1))
    assert antipodal_grasps(cube, np.random.default_rng(0)) == []
    message = explain_no_grasp(cube, part_name="cube")
    assert "10.0 cm thick" in message and "8 cm" in message
    with pytest.raises(NoGraspError, match="10.0 cm thick"):
        antipodal_grasps(cube, np.random.default_rng(0), strict=True, part_name="cube")
    assert issubclass(NoGraspError, ValueError)


def test_thin_board_is_grasped_at_an_edge():
    half = np.array([0.10, 0.075, 0.009])
    board = trimesh.creation.box(2 * half)
    grasps = antipodal_grasps(board, np.random.default_rng(0))
    assert len(grasps) >= 10
    for g in grasps:
        assert g.width_m == pytest.approx(0.018, abs=1e-6)
        assert abs(g.closing_axis_part[2]) == pytest.approx(1.0)
        # walk back from the TCP towards the hand: the board's edge comes before the palm
        tcp, back = g.part_from_tcp.position, -g.approach_part
        exits = [(np.sign(b) * half[i] - tcp[i]) / b for i, b in enumerate(back[:2]) if abs(b) > 1e-9]
        assert 0.0 < min(exits) <= hand.TCP_TO_PALM_M + 1e-6
    assert grasps[0].contact_score == 1.0
    for g in grasps[:10]:
        assert not hand_hits(g.part_from_tcp, g.opening_m, board, Pose.identity())


def test_round_leg_has_grasps():
    leg = trimesh.creation.cylinder(radius=0.015, height=0.30, sections=32)
    grasps = antipodal_grasps(leg, np.random.default_rng(0))
    assert len(grasps) >= 20
    for g in grasps:
        assert g.width_m == pytest.approx(0.03, abs=5e-4)
        assert abs(g.closing_axis_part[2]) < 0.05
    for g in grasps[:10]:
        assert not hand_hits(g.part_from_tcp, g.opening_m, leg, Pose.identity())


def _approach_hits(grasp, bodies, step_m: float = 0.01) -> bool:
    """Whether the hand, opened to the grasp's opening, meets one of ``bodies`` (watertight meshes, part frame) at
    some pose of its straight approach (sampled every ``step_m`` from APPROACH_M back to the grasp)."""
    back = -grasp.part_from_tcp.rotation[:, 2]
    for d in np.arange(0.0, grasp_module.APPROACH_M + 1e-9, step_m):
        pose = Pose(grasp.part_from_tcp.position + d * back, grasp.part_from_tcp.quat_wxyz)
        if any(hand_hits(pose, grasp.opening_m, body, Pose.identity()) for body in bodies):
            return True
    return False


def test_approach_to_every_grasp_clears_the_part():
    """A ring: a hand straddling its wall could come in through the wall across the hole. Every grasp's straight
    approach is clear of the ring, checked with the independent hand model; without the check some are not."""
    ring = trimesh.creation.annulus(r_min=0.08, r_max=0.10, height=0.02, sections=48)
    grasps = antipodal_grasps(ring, np.random.default_rng(0))
    assert len(grasps) >= 20
    for g in grasps[:25]:
        assert not _approach_hits(g, [ring])
    unswept, _ = grasp_module._compute_candidates(ring, 0, 100, 200, 12, grasp_module.FRICTION_COEFFICIENT,
                                                  grasp_module.GRASP_CLEARANCE_M, hand.default_gripper(), 0.0)
    assert sum(_approach_hits(g, [ring]) for g in unswept[:25]) >= 1


def test_grasps_clear_the_convex_pieces_the_simulator_holds():
    """A large ring decomposes into 12 hulls whose chords bulge 7 mm into the hole, more than the fingers' 5 mm
    clearance: the simulated part is those hulls, so no grasp may put the inner finger inside one (without that
    check about half of the ring's grasps do)."""
    from planning.convex import convex_pieces

    ring = trimesh.creation.annulus(r_min=0.20, r_max=0.22, height=0.02, sections=96)
    pieces = convex_pieces(ring)
    assert len(pieces) > 1
    grasps = antipodal_grasps(ring, np.random.default_rng(0))
    assert len(grasps) >= 20
    for g in grasps[::4]:
        assert not _approach_hits(g, pieces)


def _square_tube(outer: float = 0.052, wall: float = 0.0015, length: float = 0.30) -> trimesh.Trimesh:
    """A hollow square tube (a table's column), one closed shell along z, its sides turned 45 degrees about z."""
    return trimesh.creation.annulus(r_min=(outer - 2 * wall) / np.sqrt(2), r_max=outer / np.sqrt(2), height=length,
                                    sections=4)


def test_hollow_tube_is_grasped_across_its_outside():
    """A ray into a tube's wall first meets the wall's inner face, 1.5 mm in; where it leaves the tube for good,
    on the far side, is the grasp a hand takes: across the outside (52 mm). Before, most grasps held a wall's end
    between a finger outside and one inside the tube."""
    tube = _square_tube()
    grasps = antipodal_grasps(tube, np.random.default_rng(0))
    across = [g for g in grasps if abs(g.width_m - 0.052) < 5e-4]
    assert len(across) >= 50  # without the far side, only rays starting within a wall's thickness of a corner
    for g in across[:10]:
        assert not hand_hits(g.part_from_tcp, g.opening_m, tube, Pose.identity())


def test_pads_close_on_the_contact_pair_first(monkeypatch):
    """A 2 mm plate with a 6 mm rib along it: fingers opened 1 cm wider than the plate clear the rib, but a grasp
    on the plate beside it would close on the rib first. No grasp's fingers, closed to its width plus 1.9 mm,
    touch the part (checked with the independent model); without the closing check some do."""
    plate, _ = box_at((0.06, 0.002, 0.20), (0.0, 0.0, 0.0))
    rib, _ = box_at((0.004, 0.006, 0.20), (0.012, 0.0, 0.0))
    part = trimesh.util.concatenate([plate, rib.apply_translation((0.012, 0.0, 0.0))])

    def closing_hits(grasps):
        return sum(any(hand_hits(g.part_from_tcp, g.width_m + 0.0019, body, Pose.identity())
                       for body in (plate, rib)) for g in grasps)

    grasps = antipodal_grasps(part, np.random.default_rng(0))
    assert len(grasps) >= 20
    assert closing_hits(grasps) == 0
    monkeypatch.setattr(grasp_module, "CLOSING_SLACK_M", None)
    grasp_module._CANDIDATE_CACHE.clear()
    assert closing_hits(antipodal_grasps(part, np.random.default_rng(0))) >= 1
    grasp_module._CANDIDATE_CACHE.clear()


def test_sealed_hollow_box_explains_the_collisions():
    outer, inner = trimesh.creation.box((0.2, 0.2, 0.2)), trimesh.creation.box((0.18, 0.18, 0.18))
    inner.invert()  # a closed shell with 1 cm walls: every antipodal pair is across a wall the fingers cannot reach
    shell = trimesh.util.concatenate([outer, inner])
    assert antipodal_grasps(shell, np.random.default_rng(0)) == []
    message = explain_no_grasp(shell, part_name="shell")
    assert "antipodal contact pairs fit between the fingers" in message and "collide" in message


def test_model_collides_agrees_with_independent_check():
    bar = trimesh.creation.box((0.03, 0.03, 0.30))
    model = hand.default_gripper()
    bvh = fcl.CollisionObject(hand.mesh_to_fcl(bar), fcl.Transform())
    rng = np.random.default_rng(3)
    verdicts = []
    for _ in range(40):
        pose = Pose(rng.uniform(-0.08, 0.08, size=3), rng.normal(size=4))
        opening = float(rng.uniform(0.0, 0.08))
        expected = hand_hits(pose, opening, bar, Pose.identity())
        assert model.collides(pose, opening, bvh, bar, Pose.identity()) == expected
        verdicts.append(expected)
    assert any(verdicts) and not all(verdicts)


def test_width_limit():
    assert MAX_GRASP_WIDTH_M == pytest.approx(0.075)
    ok = trimesh.creation.box((0.07, 0.2, 0.2))
    too_wide = trimesh.creation.box((0.078, 0.2, 0.2))
    assert all(g.width_m == pytest.approx(0.07) for g in antipodal_grasps(ok, np.random.default_rng(0)))
    assert antipodal_grasps(too_wide, np.random.default_rng(0)) == []
    assert "7.8 cm thick" in explain_no_grasp(too_wide)


@pytest.mark.parametrize("shape", ["board", "leg"])
def test_convex_shortcuts_give_the_grasps_of_the_general_path(shape, monkeypatch):
    # closed convex parts skip the ray engine, most narrow-phase calls and the FCL pad probes; nothing may change
    mesh = {"board": trimesh.creation.box((0.3, 0.2, 0.012)),
            "leg": trimesh.creation.cylinder(radius=0.015, height=0.25, sections=24)}[shape]
    grasp_module._CANDIDATE_CACHE.clear()
    fast = antipodal_grasps(mesh, np.random.default_rng(5))
    monkeypatch.setattr(grasp_module, "_convex_planes", lambda mesh: None)
    grasp_module._CANDIDATE_CACHE.clear()
    general = antipodal_grasps(mesh, np.random.default_rng(5))
    grasp_module._CANDIDATE_CACHE.clear()
    assert len(fast) == len(general) > 20
    for a, b in zip(fast, general):
        assert a.part_from_tcp.is_close(b.part_from_tcp, 1e-9)
        assert a.contact_score == b.contact_score and a.score == pytest.approx(b.score, abs=1e-12)


def test_pad_contact_scores_of_convex_parts_match_fcl():
    # TCP frames scattered over a small block (closing axis and approach at random): the pad cells land fully on,
    # partly over and wholly off its faces
    block = trimesh.creation.box((0.02, 0.03, 0.012))
    rng = np.random.default_rng(4)
    rotations = np.array([Pose(np.zeros(3), q / np.linalg.norm(q)).rotation for q in rng.normal(size=(300, 4))])
    poses = np.tile(np.eye(4), (300, 1, 1))
    poses[:, :3, :3], poses[:, :3, 3] = rotations, rng.uniform(-0.015, 0.015, (300, 3))
    widths = rng.uniform(0.005, 0.03, 300)
    planes = grasp_module._convex_planes(block)
    fast = grasp_module._contact_scores_convex(block, planes, poses, widths)
    slow = grasp_module._contact_scores(grasp_module._bvh(block), poses, widths)
    np.testing.assert_array_equal(fast, slow)
    assert len(np.unique(fast)) >= 5  # many different fractions, not only all-on and all-off


def test_inside_tests_of_closed_meshes():
    rng = np.random.default_rng(0)
    tall, short = trimesh.creation.box((0.1, 0.2, 0.3)), trimesh.creation.box((0.1, 0.1, 0.1))
    short.apply_translation((0.1, 0.0, 0.0))
    joined = trimesh.util.concatenate([tall, short])  # two closed shells touching along a face, as merged parts are
    points = rng.uniform(joined.bounds[0] - 0.02, joined.bounds[1] + 0.02, (3000, 3))
    truth = (np.all(np.abs(points) <= [0.05, 0.1, 0.15], axis=1)
             | np.all(np.abs(points - [0.1, 0.0, 0.0]) <= 0.05, axis=1))
    np.testing.assert_array_equal(grasp_module._contains(joined, points), truth)
    world_from_joined = Pose(np.array([0.3, -0.2, 0.1]), np.array([0.5, 0.5, 0.5, 0.5]))
    obstacles = ObstacleSet([(joined, world_from_joined), (tall, world_from_joined)])
    np.testing.assert_array_equal(obstacles.contains(0, world_from_joined.apply(points)), truth)
    in_tall = truth & (points[:, 0] <= 0.05)
    np.testing.assert_array_equal(obstacles.contains(1, world_from_joined.apply(points)), in_tall)


def test_rays_through_a_convex_part_meet_trimesh():
    mesh = trimesh.creation.cylinder(radius=0.02, height=0.1, sections=16)
    rng = np.random.default_rng(2)
    origins = rng.uniform(-0.06, 0.06, (400, 3))
    directions = rng.normal(size=(400, 3))
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    locations, rays, normals = grasp_module._first_hits(mesh, origins, directions)
    expected, expected_rays, triangles = mesh.ray.intersects_location(origins, directions, multiple_hits=False)
    order = np.argsort(expected_rays)
    np.testing.assert_array_equal(rays, expected_rays[order])
    np.testing.assert_allclose(locations, expected[order], atol=1e-9)
    np.testing.assert_allclose(normals, mesh.face_normals[triangles[order]], atol=1e-9)
    assert 50 < len(rays) < 400  # some rays start inside, some enter from outside, some miss


# --- in the world ---------------------------------------------------------------------------------------------------


def test_feasible_grasps_avoid_the_neighbour_and_the_floor():
    part, world_from_part = box_at((0.04, 0.04, 0.06), (0.0, 0.0, 0.03))  # standing on the floor
    neighbour, world_from_neighbour = box_at((0.06, 0.06, 0.06), (0.055, 0.0, 0.03))  # 5 mm gap in +x
    candidates = antipodal_grasps(part, np.random.default_rng(0))
    feasible = feasible_grasps(candidates, world_from_part, [(neighbour, world_from_neighbour)], None, floor_z=0.0)
    assert 0 < len(feasible) < len(candidates)
    kept = {id(g.part_from_tcp) for g in feasible}
    removed = [g for g in candidates if id(g.part_from_tcp) not in kept]
    for g in feasible:
        world_from_tcp = world_from_part @ g.part_from_tcp
        assert not hand_hits(world_from_tcp, g.opening_m, neighbour, world_from_neighbour)
        assert hand_min_z(world_from_tcp, g.opening_m) >= 0.0
    into_neighbour = below_floor = 0
    for g in removed:
        world_from_tcp = world_from_part @ g.part_from_tcp
        hits = hand_hits(world_from_tcp, g.opening_m, neighbour, world_from_neighbour)
        low = hand_min_z(world_from_tcp, g.opening_m) < 0.001
        assert hits or low  # nothing removed without a reason
        into_neighbour += hits
        below_floor += low
    assert into_neighbour > 0 and below_floor > 0
    # closing across x would put a finger into the neighbour
    assert all(abs(g.closing_axis_part[0]) < 0.5 for g in feasible)
    scores = [g.score for g in feasible]
    assert scores == sorted(scores, reverse=True)


def test_leg_inserted_downwards_is_not_held_from_below():
    leg = trimesh.creation.box((0.03, 0.03, 0.30))
    world_from_leg = Pose(np.array([0.0, 0.0, 0.20]), IDENTITY_Q)  # its foot 5 cm above the floor, going down
    down = np.array([0.0, 0.0, -1.0])
    candidates = antipodal_grasps(leg, np.random.default_rng(0))
    assert any(g.approach_part[2] > 0.5 for g in candidates)  # grasps from below exist on the part
    for obstacles in ([], [box_at((0.2, 0.2, 0.02), (0.0, 0.0, 0.36))]):  # free top end, then a plate on top
        feasible = feasible_grasps(candidates, world_from_leg, obstacles, down, floor_z=0.0)
        assert feasible
        approach = world_from_leg.rotation @ feasible[0].approach_part
        assert approach[2] <= 1e-9  # from above or the side
        assert all((world_from_leg.rotation @ g.approach_part) @ down >= -0.3 for g in feasible)
    # with the top end free the best grasp comes down onto it (within 30 degrees of vertical)
    best = feasible_grasps(candidates, world_from_leg, [], down, floor_z=0.0)[0]
    assert (world_from_leg.rotation @ best.approach_part)[2] <= -math.cos(math.radians(30)) + 1e-9
    # reversing the motion reverses the preference
    up_best = rank(candidates, world_from_leg, -down)[0]
    assert (world_from_leg.rotation @ up_best.approach_part)[2] > 0.5


def test_obstacle_set_reuse_matches_list():
    part, world_from_part = box_at((0.03, 0.03, 0.2), (0.0, 0.0, 0.1))
    others = [box_at((0.05, 0.05, 0.05), (0.05 * k, 0.04, 0.025)) for k in range(-2, 3)]
    candidates = antipodal_grasps(part, np.random.default_rng(1))
    a = feasible_grasps(candidates, world_from_part, others, np.array([0.0, 0.0, -1.0]))
    b = feasible_grasps(candidates, world_from_part, ObstacleSet(others), np.array([0.0, 0.0, -1.0]))
    assert [g.score for g in a] == [g.score for g in b] and len(a) > 0


def test_bad_inputs_name_the_culprit():
    bar = trimesh.creation.box((0.03, 0.03, 0.3))
    grasps = antipodal_grasps(bar, np.random.default_rng(0))
    with pytest.raises(ValueError, match="insertion_direction_world"):
        feasible_grasps(grasps, Pose.identity(), [], np.zeros(3))
    with pytest.raises(TypeError, match="obstacle 0"):
        feasible_grasps(grasps, Pose.identity(), [(bar, np.eye(4))], None)


# --- sample objects -------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("scene", ["chair", "table", "cabinet"])
def test_every_sample_part_has_a_grasp(scene):
    assembly = read_assembly(REPO / "scenes" / scene)
    for part in assembly.parts:
        grasps = antipodal_grasps(part.mesh, np.random.default_rng(0))
        assert grasps, f"{scene}/{part.name}: {explain_no_grasp(part.mesh, part_name=part.name)}"


@pytest.mark.skipif(not FURNITURE.is_dir(), reason="shared furniture not present")
def test_real_furniture_summary(capsys):
    missing, total = [], 0
    for folder in sorted(glob.glob(str(FURNITURE / "*" / "assembly.json"))):
        assembly = read_assembly(os.path.dirname(folder))
        for part in assembly.parts:
            total += 1
            if not antipodal_grasps(part.mesh, np.random.default_rng(0), max_candidates=5):
                missing.append(f"{assembly.name}/{part.name}: {explain_no_grasp(part.mesh, part_name=part.name)}")
    with capsys.disabled():
        print(f"\nreal furniture: {len(missing)} of {total} parts have no grasp")
        for line in missing:
            print("  " + line)
    assert total > 0


def _l_bar() -> trimesh.Trimesh:
    """An L of 7.6 mm bar (x-z profile extruded along y): a 46 cm apron along x, 12 mm tall, and at its +x end a
    14 cm leg down, 12 mm wide; its centre of mass lies near the apron."""
    profile = np.array([[-0.23, 0.058], [0.218, 0.058], [0.218, -0.07], [0.23, -0.07], [0.23, 0.07], [-0.23, 0.07]])
    half = 0.0038
    vertices = np.array([[x, y, z] for y in (-half, half) for x, z in profile])
    fan = [(4, 5, 0), (4, 0, 1), (4, 1, 2), (4, 2, 3)]  # from the outer top corner, which sees every vertex
    faces = list(fan) + [(c + 6, b + 6, a + 6) for a, b, c in fan]
    for i in range(6):
        j = (i + 1) % 6
        faces += [(i, j, j + 6), (i, j + 6, i + 6)]
    mesh = trimesh.Trimesh(vertices, faces, process=True)
    mesh.fix_normals()
    return mesh


def test_candidates_spread_over_the_part_beyond_the_edge_nearest_its_centre():
    """The best-scored grasps of an L all lie on the apron, nearest the centre of mass; the list still holds
    grasps on the far end of the leg (where the apron may be covered at a target, the only free place)."""
    bar = _l_bar()
    assert bar.is_watertight and bar.volume > 0
    grasps = antipodal_grasps(bar, np.random.default_rng(0))
    assert len(grasps) == 100
    on_leg_end = [g for g in grasps if g.part_from_tcp.position[2] < -0.03]
    assert on_leg_end, "no candidate on the lower half of the leg"
    scores = [g.score for g in grasps]
    assert scores == sorted(scores, reverse=True)


def test_a_surface_that_no_ray_crosses_gives_no_pairs():
    """A flat open sheet: no ray from its surface meets it again, and the first and last hits (both empty) join
    without a shape error; no antipodal pairs, hence no grasps."""
    sheet = trimesh.Trimesh([[0, 0, 0], [0.1, 0, 0], [0.1, 0.1, 0], [0, 0.1, 0]], [[0, 1, 2], [0, 2, 3]],
                            process=False)
    first, second = grasp_module._antipodal_pairs(sheet, 0, 200, 0.5, grasp_module._Stats())
    assert first.shape == second.shape == (0, 3)
