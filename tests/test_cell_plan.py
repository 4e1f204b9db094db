"""The robot's side of kitting in the cell planner (cell/plan.py): arm configurations at the pick and at the
target, with the real Panda model, inverse kinematics and collision checker."""

import dataclasses

import numpy as np
import pytest
import trimesh

from cell.bullet import BulletClient
from cell.plan import (
    HAND_CLEARANCE_M,
    StaticObstacle,
    _Kit,
    _KitFailed,
    _KitReach,
    _pads,
    _table,
    grasp_options_after_failure,
    grasps_clear_at_target,
    jig_placed,
    part_payload,
)
from cell.robot import Panda, StraightLineError
from cell.scene import load_scene
from perception.synth import generate
from planning.grasp import APPROACH_M, Grasp, antipodal_grasps, feasible_grasps, grasp_pose_key
from planning.gripper import clearance_gripper
from planning.kitting import NO_GRASP_AT_TARGET
from planning.pose import Pose
from planning.sequence import GraspChecker, plan_assembly_sequence

BOARD = trimesh.creation.box((0.2, 0.02, 0.1))  # standing on its long edge, metres
DOWN_TCP = [0.0, 1.0, 0.0, 0.0]  # the TCP's approach axis along world -z


def test_the_arm_at_a_target_takes_other_configurations_where_the_first_meet_the_kit():
    """The first arm configurations found at a board's target put the forearm where a kitted part lies: the pick
    then asks for configurations at the target that clear the kit, and gets them (the arm is redundant: another
    elbow), instead of ruling the grasp out at every place."""
    scene = load_scene()
    top_z = scene.table.top_z
    target = Pose([0.55, 0.0, top_z + 0.15], [1.0, 0.0, 0.0, 0.0])
    pick = Pose([0.25, -0.45, top_z + 0.05], [1.0, 0.0, 0.0, 0.0])
    grasp = Grasp(Pose([0.0, 0.0, 0.038], DOWN_TCP), width_m=0.02, opening_m=0.04, score=1.0, centroid_score=1.0,
                  contact_score=1.0)
    with BulletClient() as client:
        panda = Panda(client, scene.robot.world_from_base)
        # the other elbow comes from random starts, each query's own (cell.robot.pose_rng): about half the seeds
        # find one in their three attempts, this one among them
        reach = _KitReach(panda, scene, 1, np.array(scene.robot.home_q), {"board": target},
                          {"board": BOARD}, ["board"], {"board": np.array([0.0, 0.0, -1.0])})
        first = reach.at_target("board", grasp)
        assert first is not None
        frames = reach.checker.link_frames(np.array(first[0])[None])[0]
        forearm = 0.5 * (frames[4, :3, 3] + frames[5, :3, 3])  # between the elbow (joint 4) and the wrist (joint 5)
        kit = [(trimesh.creation.box((0.05, 0.05, 0.05)), Pose(forearm, [1.0, 0.0, 0.0, 0.0]))]
        assert not reach.still_clear(((), first, grasp.opening_m), kit)
        found = reach.at_pick("board", grasp, pick, kit)
        assert found is not None
        picked, placed, opening = found
        assert reach.still_clear(((), placed, opening), kit) and reach.still_clear((picked, (), opening), kit)
        assert np.linalg.norm(np.array(placed[0]) - np.array(first[0])) > 0.1  # another arm configuration
        for q, expected in zip(placed[:1], [target @ grasp.part_from_tcp]):
            assert np.allclose(reach.checker.world_from_tcp(np.array(q))[:3, 3], expected.position, atol=1e-3)


def test_the_arm_configurations_at_a_target_do_not_depend_on_the_queries_before():
    """Where a target is reached only from random starts (the kit meets the configurations found from home), the
    configurations found are the same whether or not other queries ran first: each query draws its starts from
    the seed and its own pose (cell.robot.pose_rng), so an unrelated change upstream cannot flip a marginal part."""
    scene = load_scene()
    top_z = scene.table.top_z
    target = Pose([0.55, 0.0, top_z + 0.15], [1.0, 0.0, 0.0, 0.0])
    other = Pose([0.45, 0.25, top_z + 0.12], [1.0, 0.0, 0.0, 0.0])
    grasp = Grasp(Pose([0.0, 0.0, 0.038], DOWN_TCP), width_m=0.02, opening_m=0.04, score=1.0, centroid_score=1.0,
                  contact_score=1.0)
    insertion = np.array([0.0, 0.0, -1.0])

    def configurations(warm_up: int) -> tuple:
        with BulletClient() as client:
            panda = Panda(client, scene.robot.world_from_base)
            reach = _KitReach(panda, scene, 7, np.array(scene.robot.home_q), {"board": target, "other": other},
                              {"board": BOARD, "other": BOARD}, ["board", "other"],
                              {"board": insertion, "other": insertion})
            for k in range(warm_up):  # unrelated queries, as other parts' layouts make them
                assert reach.at_target("other", grasp, [(BOARD, Pose([0.3, -0.4 - 0.05 * k, top_z + 0.1],
                                                                     [1.0, 0.0, 0.0, 0.0]))]) is not None
            first = reach.at_target("board", grasp)
            frames = reach.checker.link_frames(np.array(first[0])[None])[0]
            forearm = 0.5 * (frames[4, :3, 3] + frames[5, :3, 3])
            kit = [(trimesh.creation.box((0.05, 0.05, 0.05)), Pose(forearm, [1.0, 0.0, 0.0, 0.0]))]
            return reach.at_target("board", grasp, kit)

    alone, after_others = configurations(0), configurations(3)
    assert alone is not None
    assert np.allclose(np.array(alone), np.array(after_others), atol=1e-9)


def test_the_arm_at_a_target_keeps_clear_of_the_jigs_pads():
    """A jig pad where the first arm configurations at a board's target put the forearm: kitting takes other
    configurations, clear of the pad, as the task planner would ask (before, only the hand was checked against
    the pads, and table_16's leg_rear_left was kitted with a pick whose link 6 met one)."""
    scene = load_scene()
    target = Pose([0.55, 0.0, scene.table.top_z + 0.15], [1.0, 0.0, 0.0, 0.0])
    grasp = Grasp(Pose([0.0, 0.0, 0.038], DOWN_TCP), width_m=0.02, opening_m=0.04, score=1.0, centroid_score=1.0,
                  contact_score=1.0)
    down = np.array([0.0, 0.0, -1.0])
    with BulletClient() as client:
        panda = Panda(client, scene.robot.world_from_base)
        home_q = np.array(scene.robot.home_q)
        # the other elbow comes from random starts (cell.robot.pose_rng): five of the seeds 0-7 find one
        bare = _KitReach(panda, scene, 0, home_q, {"board": target}, {"board": BOARD}, ["board"], {"board": down})
        first = bare.at_target("board", grasp)
        assert first is not None
        frames = bare.checker.link_frames(np.array(first[0])[None])[0]
        forearm = 0.5 * (frames[4, :3, 3] + frames[5, :3, 3])
        pad = StaticObstacle("pad board", trimesh.creation.box((0.05, 0.05, 0.05)), Pose(forearm, [1.0, 0.0, 0.0, 0.0]))
        padded = _KitReach(panda, scene, 0, home_q, {"board": target}, {"board": BOARD}, ["board"], {"board": down},
                           pads=[pad])

        def clear_of_the_pad(configurations) -> bool:
            padded.checker.set_obstacles(padded.pads)
            padded.checker.hold(None, opening_m=grasp.opening_m)
            return all(padded.checker.is_valid(np.asarray(q)) for q in configurations)

        assert not clear_of_the_pad(first)
        found = padded.at_target("board", grasp)
        assert found is not None and clear_of_the_pad(found)


def test_a_pick_whose_straight_approach_needs_a_jump_between_ik_branches_is_not_kitted():
    """chair_16's leg_front (procedural, seed [2000, 16]) as kitting laid it out with the jig turned 0 degrees: the
    first arm configuration found at its grasp, near joint 6's limit, cannot follow the straight approach back
    from the grasp without a jump between inverse-kinematics branches, and the task planner refused the jig's
    placement for it, at two turns. Kitting now follows the approach and the lift itself and takes another
    configuration that follows them."""
    scene = load_scene()
    pick = Pose([0.2930, 0.4552, 0.1280], [0.4632, 0.1495, -0.2846, -0.8259])
    grasp = Grasp(Pose([0.0672, 0.0004, 0.0006], [0.2425, -0.0908, -0.9153, 0.3084]), width_m=0.0183,
                  opening_m=0.0283, score=1.0, centroid_score=1.0, contact_score=1.0)
    leg = trimesh.creation.box((0.16, 0.018, 0.018))
    target = Pose([0.55, 0.0, scene.table.top_z + 0.15], [1.0, 0.0, 0.0, 0.0])
    tcp = pick @ grasp.part_from_tcp
    with BulletClient() as client:
        panda = Panda(client, scene.robot.world_from_base)
        reach = _KitReach(panda, scene, 0, np.array(scene.robot.home_q), {"leg": target}, {"leg": leg}, ["leg"],
                          {"leg": np.array([0.0, 0.0, -1.0])})
        # the configuration kitting kept before, at the grasp (the task planner's hint)
        before = np.array([0.5334, 0.1998, 0.5699, -2.7405, 0.4741, 3.4516, 0.3609])
        assert np.allclose(panda.forward_tcp(before).position, tcp.position, atol=5e-4)
        with pytest.raises(StraightLineError, match="jump between IK branches"):
            panda.tcp_line(before, tcp, -tcp.rotation[:, 2] * APPROACH_M, 0)
        found = reach.at_pick("leg", grasp, pick, [])
        assert found is not None
        at_grasp = np.array(found[0][0])
        assert np.allclose(panda.forward_tcp(at_grasp).position, tcp.position, atol=1e-4)
        approach = panda.tcp_line(at_grasp, tcp, -tcp.rotation[:, 2] * APPROACH_M, 0)
        assert np.max(np.abs(np.diff(approach, axis=0))) <= 0.35


def test_a_target_beyond_the_arm_is_told_apart_from_one_the_arm_meets():
    """A board whose grasps lie beyond the arm's reach is flagged as such (the cell then slides the jig toward the
    robot); one within reach but blocked by a box where the arm must be is not."""
    scene = load_scene()
    top_z = scene.table.top_z
    far = Pose([0.95, 0.0, top_z + 0.15], [1.0, 0.0, 0.0, 0.0])  # the flange ~0.97 m from the shoulder
    near = Pose([0.55, 0.0, top_z + 0.15], [1.0, 0.0, 0.0, 0.0])
    grasp = Grasp(Pose([0.0, 0.0, 0.038], DOWN_TCP), width_m=0.02, opening_m=0.04, score=1.0, centroid_score=1.0,
                  contact_score=1.0)
    down = np.array([0.0, 0.0, -1.0])
    wall = trimesh.creation.box((0.6, 0.6, 0.02))  # lying over the board's target, where the hand must be
    with BulletClient() as client:
        panda = Panda(client, scene.robot.world_from_base)
        reach = _KitReach(panda, scene, 0, np.array(scene.robot.home_q),
                          {"far": far, "near": near, "wall": Pose([0.55, 0.0, top_z + 0.3], [1.0, 0.0, 0.0, 0.0])},
                          {"far": BOARD, "near": BOARD, "wall": wall}, ["wall", "far", "near"],
                          {"far": down, "near": down, "wall": down})
        # the closed form's answer comes first and changes nothing: no query ran, nothing is cached
        assert not reach.could_reach_target("far", grasp) and reach.could_reach_target("near", grasp)
        assert not reach.at_target_cache and not reach.release_seeds and not reach.reached_at_target
        assert reach.at_target("far", grasp) is None and reach.beyond_reach("far")
        assert reach.at_target("near", grasp) is None and not reach.beyond_reach("near")
        assert not reach.beyond_reach("wall")  # never asked


def test_a_part_beyond_the_arm_at_every_grasp_fails_the_kit_before_its_layout():
    """The jig slid 70 cm away from the robot: no grasp of the chair's parts can be reached at its target, and the
    kit fails on the first part of the order at once, told as beyond the arm's reach, before the layout has asked
    the arm for any configuration (it used to lay out the larger parts first: tvunit_0406 spent 34 s so). At the
    jig's own placement each part has a grasp the closed form reaches, and the layout runs."""
    scene = load_scene()
    chair = generate("chair", "mixed", np.random.default_rng([3, 3]), "small_chair")
    sequence = plan_assembly_sequence(chair, seed=0)
    assert sequence.success
    payloads = {p.name: part_payload(p) for p in chair.parts}
    hand_check = GraspChecker(chair, 0)

    def kit(placed):
        targets = {p.name: placed.fixture.world_from_assembly @ p.assembly_from_part for p in chair.parts}
        with BulletClient() as client:
            panda = Panda(client, placed.robot.world_from_base)
            return _Kit(placed, chair, sequence, panda, [_table(placed)] + _pads(placed, chair), targets,
                        hand_check, 0, float("inf"), payloads=payloads)

    with pytest.raises(_KitFailed) as failed:
        kit(jig_placed(scene, 0.0, -0.7))
    first = sequence.order[0]
    assert failed.value.error.kind == NO_GRASP_AT_TARGET and failed.value.error.part == first
    assert failed.value.kit.reach.beyond_reach(first)
    assert not failed.value.kit.reach.at_target_cache  # no configuration was asked for: the layout never began
    assert {slot.part for slot in kit(scene).slots} == {p.name for p in chair.parts}


def test_the_jig_slides_toward_the_robot_and_turns_about_its_own_origin():
    scene = load_scene()
    placed = jig_placed(scene, 90.0, 0.06).fixture.world_from_assembly
    start = scene.fixture.world_from_assembly.position
    base = scene.robot.world_from_base.position
    assert np.isclose(placed.position[2], start[2])
    moved = np.asarray(placed.position[:2]) - start[:2]
    assert np.isclose(np.linalg.norm(moved), 0.06)
    toward_base = (base[:2] - start[:2]) / np.linalg.norm(base[:2] - start[:2])
    assert np.isclose(moved @ toward_base, 0.06)
    assert np.allclose(placed.rotation @ [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], atol=1e-9)  # a quarter turn about +z


def test_kitting_checks_the_straight_lines_between_its_arm_configurations():
    """Two TCP poses 30 cm apart, a box halfway between them: the arm configurations at both ends are clear, the
    straight TCP line between them is not, and a chain asked to check that line finds none (kitting checks the
    approach, lift, insertion and retreat so: cabinet_1's arm met a kitted part halfway along an approach)."""
    scene = load_scene()
    top_z = scene.table.top_z
    start, end = (Pose([0.5, y, top_z + 0.25], DOWN_TCP) for y in (-0.15, 0.15))
    box = (trimesh.creation.box((0.04, 0.04, 0.04)), Pose([0.5, 0.0, top_z + 0.25], [1.0, 0.0, 0.0, 0.0]))
    clear = (frozenset(), frozenset())
    with BulletClient() as client:
        panda = Panda(client, scene.robot.world_from_base)
        reach = _KitReach(panda, scene, 0, np.array(scene.robot.home_q), {"board": start}, {"board": BOARD},
                          ["board"], {"board": np.array([0.0, 0.0, -1.0])})
        reach.checker.set_obstacles(reach._world([box], []))
        reach.checker.hold(None, opening_m=0.04)
        ends = reach._chain([start, end], reach.home_q, [clear, clear])
        assert ends is not None
        assert not reach.checker.segment_valid(ends[0], ends[1])
        assert reach._chain([start, end], reach.home_q, [clear, clear], lines=((1, 0.02, 0),)) is None


def test_a_grasp_at_the_target_clears_the_whole_insertion():
    """A post pushed 8 cm down into its target under a shelf: the hand, top-down on the post, clears the shelf at
    the target and over the last 3 cm, and meets it 4 cm up. The cell inserts along INSERTION_M (8 cm), so it
    rules the grasp out (a finger of bookcase_expedit_0373 met a shelf so); the 3 cm check kept it."""
    target = Pose([0.5, 0.0, 0.3], [1.0, 0.0, 0.0, 0.0])
    grasp = Grasp(Pose([0.0, 0.0, 0.08], DOWN_TCP), width_m=0.02, opening_m=0.03, score=1.0, centroid_score=1.0,
                  contact_score=1.0)
    hand_top_z = clearance_gripper(HAND_CLEARANCE_M).vertices(target @ grasp.part_from_tcp, 0.03)[:, 2].max()
    shelf = [(trimesh.creation.box((0.3, 0.3, 0.005)), Pose([0.5, 0.0, hand_top_z + 0.04 + 0.0025], [1, 0, 0, 0]))]
    down = np.array([0.0, 0.0, -1.0])
    assert grasps_clear_at_target([grasp], target, [], down, 0.0) != []
    assert feasible_grasps([grasp], target, shelf, down, floor_z=0.0,
                           gripper=clearance_gripper(HAND_CLEARANCE_M)) != []  # the last 3 cm are clear
    assert grasps_clear_at_target([grasp], target, shelf, down, 0.0) == []


def test_a_grasp_at_the_target_keeps_its_closed_fingers_clear_of_a_neighbour_flush_with_the_gripped_face():
    """A post between two thin plates, each flush with a face the fingers close on (a chair's back panel against
    its back post): the opened fingers are clear of them, but the fingers closed on the post, as they are while
    the arm inserts it, lie inside them. The grasp is ruled out at the target; the open hand alone kept it (the
    motion planner then found no arm configuration at chair_10's release)."""
    target = Pose([0.5, 0.0, 0.3], [1.0, 0.0, 0.0, 0.0])
    post = 0.02  # square section, metres; the fingers close across it along world y
    grasp = Grasp(Pose([0.0, 0.0, 0.08], DOWN_TCP), width_m=post, opening_m=0.04, score=1.0, centroid_score=1.0,
                  contact_score=1.0)
    plates = [(trimesh.creation.box((0.06, 0.003, 0.04)), Pose([0.5, side * (post / 2 + 0.002), 0.38 - 0.01],
                                                                [1.0, 0.0, 0.0, 0.0])) for side in (-1.0, 1.0)]
    down = np.array([0.0, 0.0, -1.0])
    assert feasible_grasps([grasp], target, plates, down, floor_z=0.0, insertion_sweep_m=0.08,
                           gripper=clearance_gripper(HAND_CLEARANCE_M)) != []  # open, grown by the clearance
    assert grasps_clear_at_target([grasp], target, plates, down, 0.0) == []
    lower = [(mesh, Pose(pose.position - np.array([0.0, 0.0, 0.04]), pose.quat_wxyz)) for mesh, pose in plates]
    assert grasps_clear_at_target([grasp], target, lower, down, 0.0) != []  # below the fingertips


def test_a_retreat_at_the_target_keeps_its_clearance_from_parts_in_the_kit():
    """Kitting accepts a grasp's arm configurations at the target only where the retreat keeps the task planner's
    RETREAT_KIT_CLEARANCE_M from the parts lying in the kit (cabinet_11's bottom was kitted with a retreat that the
    task planner then refused). A part in the kit a fraction of a millimetre off the hand's path up from the
    release (clear, checked exactly) spoils the configurations; a pedestal there does not (checked exactly, as by
    the task planner); the same part 3 mm farther off does not either."""
    from cell.task import RETREAT_KIT_CLEARANCE_M

    scene = load_scene()
    top_z = scene.table.top_z
    target = Pose([0.55, 0.0, top_z + 0.15], [1.0, 0.0, 0.0, 0.0])
    grasp = Grasp(Pose([0.0, 0.0, 0.038], DOWN_TCP), width_m=0.02, opening_m=0.04, score=1.0, centroid_score=1.0,
                  contact_score=1.0)
    kit_part = trimesh.creation.box((0.04, 0.04, 0.04))  # beside the hand at the release, world frame
    with BulletClient() as client:
        panda = Panda(client, scene.robot.world_from_base)
        reach = _KitReach(panda, scene, 1, np.array(scene.robot.home_q), {"board": target, "post": target},
                          {"board": BOARD, "post": kit_part}, ["board", "post"],
                          {"board": np.array([0.0, 0.0, -1.0]), "post": np.array([0.0, 0.0, -1.0])})
        at_target = reach.at_target("board", grasp)
        assert at_target is not None
        tcp = reach.checker.world_from_tcp(np.array(at_target[0]))[:3, 3]

        def post_at(offset_m: float, mesh=kit_part):
            return [(mesh, Pose(tcp + [offset_m, 0.0, 0.03], [1.0, 0.0, 0.0, 0.0]))]

        def exactly_clear(offset_m: float) -> bool:  # the pedestal's check: a copy of the mesh is no part
            return reach.still_clear(((), at_target, grasp.opening_m), post_at(offset_m, kit_part.copy()))

        near, far = 0.0, 0.3  # the box beside the hand along +x: touching at `near`, clear at `far`
        assert not exactly_clear(near) and exactly_clear(far)
        while far - near > 1e-4:
            middle = 0.5 * (near + far)
            near, far = (near, middle) if exactly_clear(middle) else (middle, far)
        assert exactly_clear(far)  # a pedestal there: clear
        assert not reach.still_clear(((), at_target, grasp.opening_m), post_at(far))  # a part there: too near
        assert reach.still_clear(((), at_target, grasp.opening_m), post_at(far + RETREAT_KIT_CLEARANCE_M + 5e-4))
        # asked for configurations clear of the part there, kitting finds none: the hand at the release, which is
        # too near, lies where it lies whatever the elbow
        assert reach.at_target("board", grasp, post_at(far)) is None
        assert reach.at_target("board", grasp, post_at(far + RETREAT_KIT_CLEARANCE_M + 5e-4)) is not None


def test_after_a_failure_past_the_pick_the_variants_of_the_grasp_that_differ_only_at_the_pick_are_not_tried():
    """Kitting keeps variants of one grasp that open wider at the pick (a board that may lean between its chocks);
    from the grasp on they plan the same motions, so a carry that failed with one is not planned again with the
    next (bookcase_hensvik_0565's part_06 failed its carry three times so), but a pick that failed is."""
    board = trimesh.creation.box((0.30, 0.20, 0.012))
    grasps = antipodal_grasps(board, np.random.default_rng(0), 20)
    first = grasps[0]
    other = next(g for g in grasps if grasp_pose_key(g) != grasp_pose_key(first))
    at_pick, at_target = np.linspace(-1.0, 1.0, 7), np.linspace(0.5, -0.5, 7)
    reach = ((at_pick, at_pick + 0.1, at_pick + 0.2), (at_target, at_target + 0.1, at_target + 0.2), 0.04)
    wider = dataclasses.replace(first, pick_opening_m=first.opening_m + 0.027)
    wide = dataclasses.replace(first, pick_opening_m=first.opening_m + 0.014)
    options = [(wider, reach), (wide, reach), (first, reach), (other, reach)]

    left = grasp_options_after_failure(options, "move to the target")
    assert [grasp for grasp, _ in left] == [other]
    # at the pick, the opening matters: the narrower variants are tried next
    left = grasp_options_after_failure(options, "move to the pick")
    assert [grasp for grasp, _ in left] == [wide, first, other]
    # a variant reaching the target with another arm configuration plans another carry
    elsewhere = (reach[0], (at_target + 0.3,) + reach[1][1:], reach[2])
    left = grasp_options_after_failure([(wider, reach), (wide, elsewhere), (other, reach)], "insertion")
    assert [grasp for grasp, _ in left] == [wide, other]
