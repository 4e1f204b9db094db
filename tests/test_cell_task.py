"""The cell's task planner: how a part is brought into contact with its neighbours (held off the ones it slides
along, slowly)."""

import dataclasses

import numpy as np
import pytest
import trimesh

from cell.bullet import BulletClient
from cell.robot import Panda
from cell.task import (
    CARRY_CHECKS,
    CARRY_CLEARANCE_M,
    DENSE_CHECK_RAD,
    FARTHER_APPROACH_M,
    HELD_MARGIN_M,
    INSERTION_M,
    INSERTION_SPEED_M_S,
    JOINT_LIMIT_MARGIN_RAD,
    LEAD_IN_STEPS_M,
    NEAR_END_RAD,
    PANDA_LIMITS,
    PASSING_CLEARANCE_M,
    RETREAT_KIT_CLEARANCE_M,
    SLIDE_CLEARANCE_M,
    TRANSIT_CLEARANCE_M,
    CellWorld,
    PartTask,
    TaskPlanningError,
    _among_neighbours_validity,
    _insertion,
    _insertion_limits,
    _lead_in,
    _no_clearance_validity,
    _retreat_validity,
    _slot_entry,
    _timed_insertion,
    plan_tasks,
)
from planning.collision import ConvexPart
from planning.grasp import APPROACH_M, Grasp
from planning.motion import MotionSettings
from planning.pose import Pose
from planning.robot_collision import LINK_CLEARANCE_M
from planning.timing import time_path
from planning.validity import dense_path_valid

BAR = trimesh.creation.box((0.008, 0.19, 0.02))  # a side stretcher (x thin, y long), metres
CROSS = trimesh.creation.box((0.18, 0.008, 0.02))  # the middle stretcher butting onto it (+x side)
SHELF = trimesh.creation.box((0.19, 0.19, 0.01))  # something the bar could land on
DOWN = np.array([0.0, 0.0, -1.0])


@pytest.fixture(scope="module")
def panda():
    with BulletClient() as client:
        yield Panda(client, Pose.identity())


def world_with(panda, placed: dict[str, tuple[trimesh.Trimesh, Pose]]) -> CellWorld:
    parts = {"bar": ConvexPart.from_mesh("bar", BAR)}
    parts.update({name: ConvexPart.from_mesh(name, mesh) for name, (mesh, _) in placed.items()})
    world = CellWorld(panda, Pose.identity(), {}, parts, np.random.default_rng(0))
    world.set_part_poses({name: pose for name, (_, pose) in placed.items()})
    return world


def posts_world(panda, name: str, mesh: trimesh.Trimesh, post: trimesh.Trimesh, placed: dict[str, Pose]):
    """A world of posts (``post`` at each of ``placed``) and the part ``name`` held at the identity grasp (the TCP is
    the part's frame), closing on its ``mesh``'s y extent: (world, grasp)."""
    parts = {name: ConvexPart.from_mesh(name, mesh)}
    parts.update({other: ConvexPart.from_mesh(other, post) for other in placed})
    world = CellWorld(panda, Pose.identity(), {}, parts, np.random.default_rng(0))
    world.set_part_poses(placed)
    width = float(mesh.extents[1])
    grasp = Grasp(Pose.identity(), width_m=width, opening_m=width + 0.012, score=1.0, centroid_score=1.0,
                  contact_score=1.0)
    world.hold(name, grasp, grasp.width_m)
    return world, grasp


def release_and_pre_place(world: CellWorld, name: str, target: Pose, valid):
    """The release configuration at ``target`` (the TCP pose) and the pre-place one INSERTION_M above it."""
    place_q = world.solve_ik(target, np.array([0.0, -0.3, 0.0, -2.2, 0.0, 2.0, 0.8]), valid, name, "test")
    return place_q, world.straight_line(place_q, target, -DOWN * INSERTION_M, valid, name, "test")[-1]


def task_to(target: Pose) -> PartTask:
    grasp = Grasp(Pose.identity(), width_m=0.008, opening_m=0.02, score=1.0, centroid_score=1.0, contact_score=1.0)
    return PartTask("bar", Pose([0.3, 0.3, 0.1], [1, 0, 0, 0]), target, grasp, DOWN, (), "pedestal")


def test_a_part_meeting_a_neighbours_side_only_near_its_target_comes_down_held_off_it(panda):
    # the cross stretcher's end face touches the bar's +x face only over the last 2 cm of the 8 cm insertion: the
    # bar is held 4 mm off it (-x) on the way down, not only when it touches it from the start
    target = Pose([0.5, 0.0, 0.2], [1, 0, 0, 0])
    cross = Pose([0.5 + 0.004 + 0.09, 0.0, 0.2], [1, 0, 0, 0])
    shift = world_with(panda, {"cross": (CROSS, cross)}).clearance_shift("bar", task_to(target))
    assert shift == pytest.approx([-SLIDE_CLEARANCE_M, 0.0, 0.0], abs=1e-9)


def test_a_part_between_two_neighbours_or_landing_on_one_comes_straight_down(panda):
    target = Pose([0.5, 0.0, 0.2], [1, 0, 0, 0])
    both_sides = {"cross": (CROSS, Pose([0.5 + 0.094, 0.0, 0.2], [1, 0, 0, 0])),
                  "other": (CROSS, Pose([0.5 - 0.094, 0.0, 0.2], [1, 0, 0, 0]))}
    assert np.all(world_with(panda, both_sides).clearance_shift("bar", task_to(target)) == 0.0)
    below = {"shelf": (SHELF, Pose([0.5, 0.0, 0.2 - 0.015], [1, 0, 0, 0]))}
    assert np.all(world_with(panda, below).clearance_shift("bar", task_to(target)) == 0.0)
    far = {"cross": (CROSS, Pose([0.5 + 0.094 + 0.01, 0.0, 0.2], [1, 0, 0, 0]))}  # 1 cm away: no slide
    assert np.all(world_with(panda, far).clearance_shift("bar", task_to(target)) == 0.0)
    assert INSERTION_M > 0.02  # the cross stretcher is met only near the end of the insertion above


def test_a_part_is_not_held_off_into_another_neighbour(panda):
    """The cross stretcher would hold the bar 4 mm off towards -x, but a slanted face (45 degrees: not a side it
    slides along) touches the bar's -x bottom edge at its target: held off, the bar would sink 2.8 mm into it, so it
    comes straight down (four splayed legs in a table top's sockets pushed the top off sideways onto their ends)."""
    target = Pose([0.5, 0.0, 0.2], [1, 0, 0, 0])
    cross = Pose([0.5 + 0.004 + 0.09, 0.0, 0.2], [1, 0, 0, 0])
    wedge = trimesh.creation.box((0.02, 0.19, 0.02))
    half = np.sqrt(0.5)
    wedge.apply_transform(np.array([[half, 0, half, 0], [0, 1, 0, 0], [-half, 0, half, 0], [0, 0, 0, 1.0]]))
    corner, normal = np.array([0.5 - 0.004, 0.0, 0.2 - 0.01]), np.array([half, 0.0, half])
    placed = {"cross": (CROSS, cross), "wedge": (wedge, Pose(corner - normal * 0.01, [1, 0, 0, 0]))}
    assert np.all(world_with(panda, placed).clearance_shift("bar", task_to(target)) == 0.0)
    placed["wedge"] = (wedge, Pose(corner - normal * 0.0105, [1, 0, 0, 0]))  # 0.5 mm off: 2.3 mm in, still too deep
    assert np.all(world_with(panda, placed).clearance_shift("bar", task_to(target)) == 0.0)
    del placed["wedge"]
    assert world_with(panda, placed).clearance_shift("bar", task_to(target)) == pytest.approx(
        [-SLIDE_CLEARANCE_M, 0.0, 0.0], abs=1e-9)


def test_a_side_slid_sideways_over_its_pad_onto_tenons_comes_in_held_above_the_pad(panda):
    """A chair's side panel pushed sideways (-x) onto its pad and onto a rail whose end is drawn 9 mm into it (a
    tenon, which the simulation lets fit): it comes in held 4 mm above the pad and is set down at the end. The
    tenon neither guides it nor blocks the offset; without the pad among the neighbours it would slide along it."""
    side = trimesh.creation.box((0.019, 0.276, 0.3))
    rail = trimesh.creation.box((0.2, 0.03, 0.03))
    pad = trimesh.creation.box((0.01, 0.2, 0.12))
    target = Pose([0.5, 0.0, 0.15], [1, 0, 0, 0])
    parts = {"side": ConvexPart.from_mesh("side", side), "rail": ConvexPart.from_mesh("rail", rail)}
    static = {"pad side": (ConvexPart.from_mesh("pad side", pad), Pose([0.5, 0.0, -0.06], [1, 0, 0, 0]))}
    world = CellWorld(panda, Pose.identity(), static, parts, np.random.default_rng(0))
    world.set_part_poses({"rail": Pose([0.5 - 0.0095 - 0.1 + 0.009, 0.0, 0.2], [1, 0, 0, 0])})  # 9 mm into it
    grasp = Grasp(Pose.identity(), width_m=0.019, opening_m=0.03, score=1.0, centroid_score=1.0, contact_score=1.0)
    task = PartTask("side", Pose([0.3, 0.3, 0.1], [1, 0, 0, 0]), target, grasp, np.array([-1.0, 0.0, 0.0]),
                    ("rail", "pad side"), "pedestal")
    assert world.clearance_shift("side", task) == pytest.approx([0.0, 0.0, SLIDE_CLEARANCE_M], abs=1e-9)
    other_pad = PartTask("side", task.world_from_pick, target, grasp, task.insertion_direction, ("rail",), "pedestal")
    assert np.all(world.clearance_shift("side", other_pad) == 0.0)  # only the pads it lands on count


def test_insertions_are_timed_slowly_enough_for_tight_fits(panda):
    world = world_with(panda, {})
    down = Pose([0.5, 0.0, 0.25], [0.0, 1.0, 0.0, 0.0])  # TCP pointing down
    q = world.solve_ik(down, np.array([0.0, -0.3, 0.0, -2.2, 0.0, 2.0, 0.8]), lambda q: True, "bar", "test")
    path = world.straight_line(q, down, np.array([0.0, 0.0, INSERTION_M]), lambda q: True, "bar", "test")[::-1]
    limits = _insertion_limits(world, path, PANDA_LIMITS)
    assert np.all(limits.velocity < PANDA_LIMITS.velocity)

    def top_speed(timed):
        _, qs, _, _ = timed.sample(200.0)
        tcp = np.array([panda.forward_tcp(q).position for q in qs])
        return float(np.max(np.linalg.norm(np.diff(tcp, axis=0), axis=1)) * 200.0)

    assert top_speed(time_path(path, PANDA_LIMITS)) > 4 * INSERTION_SPEED_M_S  # what it would be at full speed
    assert 0.7 * INSERTION_SPEED_M_S < top_speed(time_path(path, limits)) <= 1.05 * INSERTION_SPEED_M_S


def test_an_insertion_keeps_the_part_on_its_straight_line(panda):
    """The insertion as the task planner times it, sampled at 1 kHz, keeps the TCP within 0.1 mm of its straight
    line: a part fitted between two neighbours has a quarter of a millimetre to spare on each side in the simulator.
    The hand comes in level (+x) and goes down, as it placed a cabinet's top between its sides; with IK every 2 cm
    and the timing's default blends the TCP strayed 0.35 mm here (0.55 mm on the cabinet, whose top caught on a
    side)."""
    world = world_with(panda, {})
    # TCP z (approach) along world +x, high enough for the Panda's datasheet joint ranges to reach it level
    level = Pose([0.55, 0.0, 0.47], [np.sqrt(0.5), 0.0, np.sqrt(0.5), 0.0])
    assert level.rotation[:, 2] == pytest.approx([1.0, 0.0, 0.0], abs=1e-9)
    q = world.solve_ik(level, np.array([0.0, -0.3, 0.0, -2.2, 0.0, 2.0, 0.8]), lambda q: True, "bar", "test")
    path, stops = _insertion(world, q, level, DOWN, np.zeros(3), lambda q: True, "bar")
    _, qs, _, _ = _timed_insertion(world, path, lambda q: True, "bar", PANDA_LIMITS, stops).sample(1000.0)
    tcp = np.array([panda.forward_tcp(q).position for q in qs])
    assert tcp[0, 2] - tcp[-1, 2] == pytest.approx(INSERTION_M, abs=1e-4)
    assert np.max(np.linalg.norm(tcp[:, :2] - level.position[:2], axis=1)) < 1e-4


def test_an_insertion_starts_farther_back_where_its_pre_place_lies_between_neighbours(panda):
    """A plank whose ends come down between pairs of posts 0.5 mm off its faces: 8 cm above its target it is
    still between them, so the carry (the plank grown by 2 mm) cannot end there. The insertion starts farther back
    along the insertion, at the first of LEAD_IN_STEPS_M where the grown plank is clear, and is straight."""
    plank = trimesh.creation.box((0.008, 0.4, 0.02))
    post = trimesh.creation.box((0.01, 0.03, 0.3))
    target = Pose([0.5, 0.0, 0.2], [0.0, 1.0, 0.0, 0.0])  # the TCP (= the plank's frame) pointing down
    posts_top_z = 0.2 + 0.13  # 13 cm above the target: 8 cm of insertion is not enough, 8 + 8 cm is
    placed = {f"post {i}": Pose([0.5 + sx * (0.004 + 0.0005 + 0.005), sy * 0.17, posts_top_z - 0.15], [1, 0, 0, 0])
              for i, (sx, sy) in enumerate(((1, 1), (-1, 1), (1, -1), (-1, -1)))}
    world, grasp = posts_world(panda, "plank", plank, post, placed)
    valid_insert = world.validity()
    _, pre = release_and_pre_place(world, "plank", target, valid_insert)
    world.hold("plank", grasp, grasp.width_m, margin_m=-CARRY_CLEARANCE_M)
    clear = world.validity(transit=True)
    assert not clear(pre)  # the grown plank meets the posts at the pre-place pose
    lead_in, sideways = _lead_in(world, "plank", grasp, pre, DOWN, clear, valid_insert)
    assert clear(lead_in[0]) and not sideways
    np.testing.assert_allclose(lead_in[-1], pre)
    tcp = np.array([panda.forward_tcp(q).position for q in lead_in])
    rise_m = tcp[0, 2] - tcp[-1, 2]
    assert rise_m == pytest.approx(LEAD_IN_STEPS_M[1], abs=1e-4)  # 4 cm more was not enough, 8 cm was
    assert np.max(np.abs(tcp[:, :2] - tcp[-1, :2])) < 1e-4  # straight down the insertion


def test_a_part_inside_its_neighbour_all_the_way_in_is_named_with_the_overlap(panda):
    """A block whose target overlaps a 50 cm rail by 1 cm, inserted along the rail: 8 cm back, and at every
    straight lead-in up to 24 cm farther back, it is still inside the rail. The plan fails at the pre-place pose,
    and the message names the rail, the insertion direction and that the poses put the two into each other."""
    block = trimesh.creation.box((0.03, 0.03, 0.06))
    rail = trimesh.creation.box((0.5, 0.03, 0.03))
    down_tcp, up = [0.0, 1.0, 0.0, 0.0], [1.0, 0.0, 0.0, 0.0]
    static = {"rail": (ConvexPart.from_mesh("rail", rail), Pose([0.45, 0.0, 0.2], up))}
    world = CellWorld(panda, Pose.identity(), static, {"block": ConvexPart.from_mesh("block", block)},
                      np.random.default_rng(0))
    grasp = Grasp(Pose([0.0, 0.0, 0.02], down_tcp), width_m=0.03, opening_m=0.04, score=1.0, centroid_score=1.0,
                  contact_score=1.0)  # near the block's top, the fingers above the rail
    along = np.array([1.0, 0.0, 0.0])
    task = PartTask("block", Pose([0.35, 0.3, 0.03], up), Pose([0.6, 0.0, 0.235], up), grasp, along, ("rail",),
                    "pad")
    with pytest.raises(TaskPlanningError) as failure:
        plan_tasks(world, [task], np.array([0.0, -0.3, 0.0, -2.2, 0.0, 2.0, 0.8]))
    assert failure.value.kind == "goal_in_collision"
    assert ("the held part 'block' meets 'rail'): 'block' still overlaps 'rail', a neighbour at its target, 8 cm "
            "back along its insertion direction (+1.00, +0.00, +0.00, world), and no straight lead-in up to 24 cm "
            "farther back clears it: the target poses put the two parts into each other") in str(failure.value)


def test_an_insertion_between_tall_posts_starts_beside_them(panda):
    """A 30 cm panel whose ends go between two posts 60 cm tall, 0.5 mm off its end faces: from straight above it
    would be between them for 32 cm, farther than any lead-in; it comes in from the side, 4 cm across, and stops
    at the pre-place pose before it goes down (as a chair's back panel between its back posts)."""
    panel = trimesh.creation.box((0.3, 0.012, 0.2))  # its own frame = the TCP's: fingers close across y
    post = trimesh.creation.box((0.03, 0.02, 0.6))
    down_along_y = Pose([0, 0, 0], [np.cos(np.pi / 4), 0, 0, np.sin(np.pi / 4)]) @ Pose([0, 0, 0], [0, 1, 0, 0])
    target = Pose([0.5, 0.0, 0.2], down_along_y.quat_wxyz)  # pointing down, the panel's length along world y
    placed = {f"post {i}": Pose([0.5, sy * (0.15 + 0.0005 + 0.01), 0.3], [1, 0, 0, 0])
              for i, sy in enumerate((1, -1))}
    world, grasp = posts_world(panda, "panel", panel, post, placed)
    valid_insert = world.validity()
    _, pre = release_and_pre_place(world, "panel", target, valid_insert)
    world.hold("panel", grasp, grasp.width_m, margin_m=-CARRY_CLEARANCE_M)
    clear = world.validity(transit=True)
    assert not clear(pre)
    lead_in, sideways = _lead_in(world, "panel", grasp, pre, DOWN, clear, valid_insert)
    assert sideways and clear(lead_in[0])
    np.testing.assert_allclose(lead_in[-1], pre)
    tcp = np.array([panda.forward_tcp(q).position for q in lead_in])
    assert abs(tcp[0, 0] - tcp[-1, 0]) == pytest.approx(LEAD_IN_STEPS_M[0], abs=1e-4)  # 4 cm, out from the posts
    assert np.max(np.abs(tcp[:, 1:] - tcp[-1, 1:])) < 1e-4  # level, along x only


def test_a_carry_ending_between_neighbours_is_split_where_the_part_was_last_clear(panda):
    """The plank comes down between its posts from 30 cm above its target. Its posts reach 13 cm above the target,
    so the last part of the carry, to the pre-place pose 8 cm above, runs with the plank between them: the carry
    is split where the plank, grown by the carry clearance, was last clear (its bottom just above the posts' tops
    plus the carry's clearances); the rest goes with the insertion. A carry that ends clear is not split."""
    plank = trimesh.creation.box((0.008, 0.4, 0.02))
    post = trimesh.creation.box((0.01, 0.03, 0.3))
    target = Pose([0.5, 0.0, 0.2], [0.0, 1.0, 0.0, 0.0])
    posts_top_z = 0.2 + 0.13
    placed = {f"post {i}": Pose([0.5 + sx * (0.004 + 0.0005 + 0.005), sy * 0.17, posts_top_z - 0.15], [1, 0, 0, 0])
              for i, (sx, sy) in enumerate(((1, 1), (-1, 1), (1, -1), (-1, -1)))}
    world, grasp = posts_world(panda, "plank", plank, post, placed)
    valid = world.validity()
    place_q, _ = release_and_pre_place(world, "plank", target, valid)
    down = world.straight_line(place_q, target, -DOWN * 0.30, valid, "plank", "test")[::-1]  # 30 cm up to 0 cm
    carry = down[:-4]  # the carry: from 30 cm above the target to the pre-place pose, 8 cm above (2 cm steps)
    assert world.panda.forward_tcp(carry[-1]).position[2] == pytest.approx(0.2 + INSERTION_M, abs=1e-4)
    head, entry = _slot_entry(world, "plank", grasp, carry)
    np.testing.assert_allclose(head[-1], entry[0])
    np.testing.assert_allclose(entry[-1], carry[-1])
    clear = world.validity(transit=True)  # _slot_entry leaves the plank grown
    assert clear(entry[0]) and not clear(entry[1])
    plank_bottom_z = world.panda.forward_tcp(entry[0]).position[2] - 0.01
    clearance_m = CARRY_CLEARANCE_M + TRANSIT_CLEARANCE_M  # the plank grown, the posts grown for a carry
    assert posts_top_z + clearance_m <= plank_bottom_z < posts_top_z + clearance_m + 0.002
    assert len(head) + len(entry) == len(carry) + 2  # the split configuration ends one and starts the other
    high = carry[:6]  # from 30 down to 20 cm above: clear all the way
    head, entry = _slot_entry(world, "plank", grasp, high)
    assert len(entry) == 1 and len(head) == len(high)


def test_a_carry_among_neighbours_keeps_clear_of_everything_else(panda):
    """The plank's carry ends between its posts, so it is checked with the plank as it is; still it keeps the
    transit clearance from a block that is not its neighbour (a part lying in the kit: the simulator's contacts
    push what passes within a millimetre or two), except near the carry's ends, and may come as close as it fits
    to the posts it touches at its target."""
    plank = trimesh.creation.box((0.008, 0.4, 0.02))
    post = trimesh.creation.box((0.01, 0.03, 0.3))
    block = trimesh.creation.box((0.05, 0.05, 0.05))
    target = Pose([0.5, 0.0, 0.2], [0.0, 1.0, 0.0, 0.0])
    placed = {f"post {i}": Pose([0.5 + sx * (0.004 + 0.0005 + 0.005), sy * 0.17, 0.18], [1, 0, 0, 0])
              for i, (sx, sy) in enumerate(((1, 1), (-1, 1), (1, -1), (-1, -1)))}
    # the block's side 1 mm from the plank's -x face where the plank is 30 cm above its target
    placed["block"] = Pose([0.5 - 0.004 - 0.001 - 0.025, 0.17, 0.5], [1, 0, 0, 0])  # by its end, clear of the hand
    meshes = {"plank": plank, "block": block, **{n: post for n in placed if n.startswith("post")}}
    world = CellWorld(panda, Pose.identity(), {}, {n: ConvexPart.from_mesh(n, m) for n, m in meshes.items()},
                      np.random.default_rng(0))
    world.set_part_poses(placed)
    grasp = Grasp(Pose.identity(), width_m=0.008, opening_m=0.02, score=1.0, centroid_score=1.0, contact_score=1.0)
    task = PartTask("plank", Pose([0.3, 0.3, 0.1], [1, 0, 0, 0]), target, grasp, DOWN,
                    tuple(n for n in placed if n.startswith("post")), "pedestal")
    world.hold("plank", grasp, grasp.width_m, margin_m=0.0)
    exact = world.validity()
    start = np.array([0.0, -0.3, 0.0, -2.2, 0.0, 2.0, 0.8])
    pre = world.solve_ik(Pose([0.5, 0.0, 0.2 + INSERTION_M], target.quat_wxyz), start, exact, "plank", "test")
    by_block = world.solve_ik(Pose([0.5, 0.0, 0.5], target.quat_wxyz), pre, exact, "plank", "test")
    assert exact(pre) and exact(by_block)
    assert not world.validity(transit=True)(pre)  # the posts: within the clearance at the pre-place pose
    far_end = np.array([0.8, -0.5, 0.3, -1.8, 0.2, 1.6, 0.5])
    valid = _among_neighbours_validity(world, task, exact, (far_end, pre))
    assert valid(pre)  # between the posts
    assert not valid(by_block)  # 1 mm from the block, far from both ends
    assert valid.first_invalid(np.stack([pre, by_block])) == 1
    near = _among_neighbours_validity(world, task, exact, (by_block, pre))
    assert near(by_block)  # ... unless it is an end of the carry
    # kept off its neighbours too, it may come between the posts only near an end of the carry
    assert np.linalg.norm(pre - by_block) > NEAR_END_RAD
    assert not _among_neighbours_validity(world, task, exact, (far_end, by_block), off_neighbours=True)(pre)
    assert _among_neighbours_validity(world, task, exact, (far_end, pre), off_neighbours=True)(pre)


def test_a_carry_among_neighbours_passes_them_with_the_part_as_it_is_away_from_its_ends(panda):
    """A part carried among its neighbours may be checked pulled in by HELD_MARGIN_M, so that it can slide along
    the faces it touches at the carry's ends; in mid-carry it must still keep PASSING_CLEARANCE_M from them as it
    is (table_6's shelf, checked pulled in, passed 2 mm into a leg in mid-carry and met it in the simulator), and
    so in the last resort, the carry with no clearance."""
    plank = trimesh.creation.box((0.008, 0.4, 0.02))
    post = trimesh.creation.box((0.01, 0.03, 0.3))
    grasp = Grasp(Pose.identity(), width_m=0.008, opening_m=0.02, score=1.0, centroid_score=1.0, contact_score=1.0)
    down = [0.0, 1.0, 0.0, 0.0]
    start = np.array([0.0, -0.3, 0.0, -2.2, 0.0, 2.0, 0.8])
    far_end = np.array([0.8, -0.5, 0.3, -1.8, 0.2, 1.6, 0.5])

    def carried_past(post_face_off_plank_m: float):
        """(validity among neighbours with far ends, the same with the configuration an end, the configuration)
        with the post's face this far off the plank's -x face (negative: into it) at the TCP [0.5, 0, 0.5]."""
        post_x = 0.5 - 0.004 - post_face_off_plank_m - 0.005
        world = CellWorld(panda, Pose.identity(), {}, {"plank": ConvexPart.from_mesh("plank", plank),
                                                        "post": ConvexPart.from_mesh("post", post)},
                          np.random.default_rng(0))
        world.set_part_poses({"post": Pose([post_x, 0.17, 0.5], [1, 0, 0, 0])})
        task = PartTask("plank", Pose([0.3, 0.3, 0.1], [1, 0, 0, 0]), Pose([0.5, 0.0, 0.2], down), grasp, DOWN,
                        ("post",), "pedestal")
        world.hold("plank", grasp, grasp.width_m, margin_m=HELD_MARGIN_M)
        exact = world.validity()
        q = world.solve_ik(Pose([0.5, 0.0, 0.5], down), start, exact, "plank", "test")
        return ((_among_neighbours_validity(world, task, exact, (far_end, start)),
                 _no_clearance_validity(world, exact, (far_end, start))),
                (_among_neighbours_validity(world, task, exact, (far_end, q)),
                 _no_clearance_validity(world, exact, (far_end, q))), q)

    checks, checks_as_end, q = carried_past(-0.001)  # 1 mm into the plank as it is, 1 mm off it pulled in
    for valid, valid_as_end in zip(checks, checks_as_end):  # among neighbours, then the last resort: no clearance
        assert not valid(q) and valid.first_invalid(q[None]) == 0
        assert valid_as_end(q)  # near an end, the exact check with the part pulled in
    checks, _, q = carried_past(PASSING_CLEARANCE_M + 0.0005)
    assert all(valid(q) for valid in checks)


def test_an_ik_hint_too_close_to_a_joint_limit_is_solved_again(panda):
    world = world_with(panda, {})
    start = np.array([0.0, -0.3, 0.0, -2.2, 0.0, 2.0, 0.8])
    for inside_rad, kept in ((0.5 * JOINT_LIMIT_MARGIN_RAD, False), (2 * JOINT_LIMIT_MARGIN_RAD, True)):
        hint = start.copy()
        hint[6] = panda.lower_limits[6] + inside_rad
        q = world.solve_ik(panda.forward_tcp(hint), start, lambda q: True, "bar", "test", hint_q=hint)
        assert np.array_equal(q, hint) == kept
        assert panda.within_limits(q, JOINT_LIMIT_MARGIN_RAD)
        reached, angle = panda.forward_tcp(q).distance(panda.forward_tcp(hint))
        assert reached < 1e-3 and angle < 1e-2



def test_where_no_ik_solution_is_free_the_message_says_why_kittings_configuration_was_refused(panda):
    """The TCP's pose lies inside a box: kitting's configuration there collides, and so does every other solution.
    The message names the other solutions' first collision and then why kitting's own was not taken (it once
    named only a random restart's collision, which said nothing of the configuration kitting had checked)."""
    up = [1.0, 0.0, 0.0, 0.0]
    box = ConvexPart.from_mesh("box", trimesh.creation.box((0.2, 0.2, 0.2)))
    world = CellWorld(panda, Pose.identity(), {"box": (box, Pose([0.5, 0.0, 0.3], up))}, {},
                      np.random.default_rng(0))
    world.set_part_poses({})
    start = np.array([0.0, -0.3, 0.0, -2.2, 0.0, 2.0, 0.8])
    target = Pose([0.5, 0.0, 0.3], [0.0, 1.0, 0.0, 0.0])
    hint = panda.inverse_tcp(target, np.random.default_rng(0), seed_q=start)
    with pytest.raises(TaskPlanningError) as failure:
        world.solve_ik(target, start, world.validity(), "bar", "release at the target", hint_q=hint)
    assert failure.value.kind == "goal_in_collision"
    assert "; kitting's configuration for it collides (" in str(failure.value)
    assert "'box'" in str(failure.value).split("; kitting's")[1]

def test_a_held_part_too_heavy_for_the_wrist_makes_a_configuration_invalid(panda):
    from planning.payload import mass_properties

    top = trimesh.creation.box((0.6, 0.6, 0.02))  # 4.3 kg of wood
    parts = {"top": ConvexPart.from_mesh("top", top)}
    world = CellWorld(panda, Pose.identity(), {}, parts, np.random.default_rng(0), payloads={
        "top": mass_properties(top)})
    world.set_part_poses({})
    # held by its edge: the part's centre 30 cm from the TCP along the TCP's x axis
    edge = Grasp(Pose([-0.3, 0.0, 0.0], [1, 0, 0, 0]), width_m=0.02, opening_m=0.03, score=1.0, centroid_score=1.0,
                 contact_score=1.0)
    world.hold("top", edge, edge.width_m)
    valid = world.validity()
    qs = np.random.default_rng(5).uniform(panda.lower_limits, panda.upper_limits, (60, 7))
    answers = np.array([valid(q) for q in qs])
    heavy = [q for q, ok in zip(qs, answers) if not ok and "N m at panda_joint" in world._collision_words(q, valid)]
    assert heavy  # refused for the weight, and the message says which joint
    first = valid.first_invalid(qs)
    assert first == (int(np.argmin(answers)) if not answers.all() else None)  # batched: the same answer
    world.hold(None, None, 0.08)
    assert valid.load is not None and world.validity().load is None  # the empty hand carries no load


def test_a_heavy_carry_is_timed_within_the_joint_torques(panda):
    """A 1.8 kg board held 15 cm off its centre, swung about the wrist: timed at the unloaded arm's limits, its
    inverse dynamics need more than the wrist's 12 N m; the task planner times it slower, until every joint stays
    within MOVING_TORQUE_FRACTION of its limit all along. The empty hand keeps the full speed."""
    from cell.task import _timed
    from planning.payload import MOVING_TORQUE_FRACTION, mass_properties

    board = trimesh.creation.box((0.5, 0.3, 0.02))
    parts = {"board": ConvexPart.from_mesh("board", board)}
    world = CellWorld(panda, Pose.identity(), {}, parts, np.random.default_rng(0),
                      payloads={"board": mass_properties(board)})
    world.set_part_poses({})
    grasp = Grasp(Pose([-0.15, 0.0, 0.0], [1, 0, 0, 0]), width_m=0.02, opening_m=0.03, score=1.0,
                  centroid_score=1.0, contact_score=1.0)
    start = np.array([0.0, -0.3, 0.0, -2.2, 0.0, 2.0, 0.8])
    path = np.stack([start, start + [0.0, 0.0, 0.0, 0.0, 0.0, 1.5, 0.0]])  # joint 6 at its acceleration limit

    def peak_share(timed):
        _, qs, qds, qdds = timed.sample(500.0)
        return float(np.max(np.abs(world.torques().moving_torques_nm(qs, qds, qdds)) / world.torques().limits_nm))

    world.hold("board", grasp, grasp.width_m)
    assert world.torques().payload_kg == pytest.approx(1.8)
    fast = time_path(path, PANDA_LIMITS)
    assert peak_share(fast) > 1.0
    slowed = _timed(world, path, lambda q: True, "board", "test")
    assert peak_share(slowed) <= MOVING_TORQUE_FRACTION + 0.02  # checked at 250 Hz, sampled here at 500 Hz
    assert slowed.duration > fast.duration
    world.hold(None, None, 0.08)
    assert world.torques().payload_kg == 0.0
    assert _timed(world, path, lambda q: True, "board", "test").duration == pytest.approx(fast.duration)


def test_a_hand_that_cannot_open_wider_after_the_retreat_opens_at_the_next_approach(panda):
    """The next part is picked with a wider opening than the last was released with. Where a finger opening that
    wide at the end of the retreat would meet the released part (here a thin fin standing beside the fingers, which
    the hand, ignoring its own part at the release, passes), the hand moves on as it is and opens at the start of
    the next approach, which is clear, instead of failing the plan."""
    down_tcp, up = [0.0, 1.0, 0.0, 0.0], [1.0, 0.0, 0.0, 0.0]
    block = trimesh.creation.box((0.03, 0.01, 0.03))
    fin = trimesh.creation.box((0.02, 0.002, 0.1), trimesh.transformations.translation_matrix([0.0, 0.042, 0.05]))
    parts = {"finned": ConvexPart.from_mesh("finned", trimesh.util.concatenate([block, fin])),
             "next": ConvexPart.from_mesh("next", block)}
    world = CellWorld(panda, Pose.identity(), {}, parts, np.random.default_rng(0))
    narrow = Grasp(Pose([0.0, 0.0, 0.0], down_tcp), width_m=0.01, opening_m=0.02, score=1.0, centroid_score=1.0,
                   contact_score=1.0)
    wide = dataclasses.replace(narrow, pick_opening_m=0.07)
    tasks = [PartTask("finned", Pose([0.35, -0.3, 0.115], up), Pose([0.5, 0.0, 0.115], up), narrow, DOWN, (), "pad"),
             PartTask("next", Pose([0.35, 0.3, 0.115], up), Pose([0.5, -0.2, 0.115], up), wide, DOWN, (), "pad")]
    steps = plan_tasks(world, tasks, np.array([0.0, -0.3, 0.0, -2.2, 0.0, 2.0, 0.8])).program.steps
    labels = [step.label for step in steps]
    assert labels[labels.index("finned: retreat") + 1] == "next: move to the pick"  # not opened there
    opening = labels.index("open for next")
    assert labels[opening - 1] == "next: move to the pick" and labels[opening + 1] == "next: approach"
    assert steps[opening].width_m == pytest.approx(0.07)
    # the move there was planned with the hand as narrow as it was released, and it stays clear of the fin
    _, q, _, _ = steps[opening - 1].timed.sample(100.0)
    world.set_part_poses({"finned": tasks[0].world_from_target, "next": tasks[1].world_from_pick})
    world.hold(None, None, narrow.opening_m)
    assert all(world.validity()(config) for config in q)


def test_a_path_that_grazes_between_the_edge_checks_is_planned_around_it(panda):
    """An edge check that looks only at each edge's end steps over a slab of joint space 0.005 rad thick, which the
    re-check of a planned path (every DENSE_CHECK_RAD) lands in. The straight line from start to goal passes the
    edge check and fails the re-check; planned again, every edge is re-checked as the path will be, and the path
    goes around the slab (the straight line, planned three times, used to fail the move)."""

    class SteppingOver:
        def __call__(self, q) -> bool:
            return not (0.1 <= q[0] <= 0.105 and -0.6 < q[1] < 0.0)

        def segment(self, q_from, q_to) -> bool:
            return self(q_to)

    world = world_with(panda, {})
    start = np.array([0.0, -0.3, 0.0, -2.2, 0.0, 2.0, 0.8])
    goal = start + np.array([0.4, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0])
    assert SteppingOver().segment(start, goal) and not dense_path_valid(SteppingOver(), np.stack([start, goal]),
                                                                       DENSE_CHECK_RAD)
    path = world.transit(start, goal, SteppingOver(), "bar", "test")
    assert len(path) > 2 and dense_path_valid(SteppingOver(), path, DENSE_CHECK_RAD)
    np.testing.assert_allclose(path[[0, -1]], [start, goal])


def test_planning_picks_up_at_the_part_that_failed_with_another_grasp(panda):
    """The second of two blocks is held 1.5 m from its grasp point, beyond the arm's reach: planning fails on it
    and the failure carries the program up to it. Planned again from there with a grasp that works, the first
    block's motions are kept as they were (not planned again), the hand opens after their retreat for the new
    grasp's wider pick, and the program ends home. A checkpoint from other tasks is refused."""
    down_tcp, up = [0.0, 1.0, 0.0, 0.0], [1.0, 0.0, 0.0, 0.0]
    block = trimesh.creation.box((0.03, 0.01, 0.03))
    world = CellWorld(panda, Pose.identity(), {}, {n: ConvexPart.from_mesh(n, block) for n in ("first", "second")},
                      np.random.default_rng(0))
    narrow = Grasp(Pose([0.0, 0.0, 0.0], down_tcp), width_m=0.01, opening_m=0.02, score=1.0, centroid_score=1.0,
                   contact_score=1.0)
    wide = dataclasses.replace(narrow, pick_opening_m=0.07)
    tasks = [PartTask("first", Pose([0.35, -0.3, 0.115], up), Pose([0.5, 0.0, 0.115], up), narrow, DOWN, (), "pad"),
             PartTask("second", Pose([0.35, 0.3, 0.115], up), Pose([0.5, -0.2, 0.115], up),
                      dataclasses.replace(wide, part_from_tcp=Pose([0.0, 0.0, -1.5], down_tcp)), DOWN, (), "pad")]
    home_q = np.array([0.0, -0.3, 0.0, -2.2, 0.0, 2.0, 0.8])
    with pytest.raises(TaskPlanningError) as failure:
        plan_tasks(world, tasks, home_q)
    checkpoint = failure.value.checkpoint
    assert failure.value.part == "second" and checkpoint.part == "second" and checkpoint.parts_before == ("first",)
    assert [step.label for step in checkpoint.steps][-1] == "first: retreat"
    assert set(checkpoint.world_from_parts) == {"first", "second"}
    np.testing.assert_allclose(checkpoint.world_from_parts["first"].position, [0.5, 0.0, 0.115])

    tasks[1] = dataclasses.replace(tasks[1], grasp=wide)
    fractions = []
    steps = plan_tasks(world, tasks, home_q, progress=fractions.append, resume=checkpoint).program.steps
    assert all(kept is planned for kept, planned in zip(checkpoint.steps, steps, strict=False))
    labels = [step.label for step in steps]
    assert labels[len(checkpoint.steps):len(checkpoint.steps) + 2] == ["open for the next part",
                                                                        "second: move to the pick"]
    assert steps[len(checkpoint.steps)].width_m == pytest.approx(0.07)
    assert labels[-2:] == ["open", "return home"] and fractions == [0.5, 1.0]
    with pytest.raises(ValueError, match="checkpoint before 'second'"):
        plan_tasks(world, tasks[::-1], home_q, resume=checkpoint)


def test_where_no_path_reaches_the_pre_grasp_the_approach_starts_farther_back(panda):
    """A box stands where the arm passes on its way to a block's pre-grasp. With no time to search (a zero search
    budget: only the straight joint-space line from start to goal is tried), no path reaches the pre-grasp; the
    straight approach is extended 8 cm farther back along its axis, the line to its new start is clear, and the
    block is placed (bookcase_expedit_0373's part_01: a pre-grasp in a pocket among the kit's parts that two 5 s
    searches missed, where one 8 cm farther back was four times as free)."""
    down_tcp, up = [0.0, 1.0, 0.0, 0.0], [1.0, 0.0, 0.0, 0.0]
    block = trimesh.creation.box((0.03, 0.01, 0.03))
    box = ConvexPart.from_mesh("box", trimesh.creation.box((0.05, 0.117, 0.071)))
    world = CellWorld(panda, Pose.identity(), {"box": (box, Pose([0.54, 0.133, 0.256], up))},
                      {"block": ConvexPart.from_mesh("block", block)}, np.random.default_rng(0),
                      MotionSettings(time_limit_s=0.0, wall_limit_s=None))
    grasp = Grasp(Pose([0.0, 0.0, 0.0], down_tcp), width_m=0.01, opening_m=0.02, score=1.0, centroid_score=1.0,
                  contact_score=1.0)
    task = PartTask("block", Pose([0.45, 0.3, 0.115], up), Pose([0.6, 0.4, 0.115], up), grasp, DOWN, (), "pad")
    steps = plan_tasks(world, [task], np.array([0.0, -0.3, 0.0, -2.2, 0.0, 2.0, 0.8])).program.steps
    approach = next(step for step in steps if step.label == "block: approach")
    _, q, _, _ = approach.timed.sample(100.0)
    ends = [panda.forward_tcp(q[0]).position, panda.forward_tcp(q[-1]).position]
    np.testing.assert_allclose(ends[1], [0.45, 0.3, 0.115], atol=1e-4)
    np.testing.assert_allclose(ends[0], [0.45, 0.3, 0.115 + APPROACH_M + FARTHER_APPROACH_M], atol=1e-4)




def test_the_plan_says_how_each_carry_was_checked(panda):
    """A block carried from its pick to its target in free space keeps the full clearance (``clearance``). With a
    plate 1 mm beside it where its lift ends, the grown block cannot start there: the carry is checked with the block
    as it is, keeping the transit clearance from everything except near its ends (``clearance except near its
    ends``), and the plan says so (report.json's ``carry_check``: table_6's shelf once grazed a leg
    in simulation after a carry planned with no clearance, and nothing said which check had planned it)."""
    down_tcp, up = [0.0, 1.0, 0.0, 0.0], [1.0, 0.0, 0.0, 0.0]
    block = ConvexPart.from_mesh("block", trimesh.creation.box((0.08, 0.01, 0.03)))
    grasp = Grasp(Pose([0.0, 0.0, 0.0], down_tcp), width_m=0.01, opening_m=0.02, score=1.0, centroid_score=1.0,
                  contact_score=1.0)
    task = PartTask("block", Pose([0.45, 0.3, 0.115], up), Pose([0.6, 0.0, 0.115], up), grasp, DOWN, (), "pad")
    # a plate level with the block's lower half where its lift ends, 1 mm off its +x end (below the hand, which
    # it clears at the pick)
    plate = ConvexPart.from_mesh("plate", trimesh.creation.box((0.04, 0.04, 0.006)))
    beside_lift_end = Pose([0.45 + 0.04 + 0.001 + 0.02, 0.3, 0.203], up)
    checks = []
    for static in ({}, {"plate": (plate, beside_lift_end)}):
        world = CellWorld(panda, Pose.identity(), static, {"block": block}, np.random.default_rng(0))
        plan = plan_tasks(world, [task], np.array([0.0, -0.3, 0.0, -2.2, 0.0, 2.0, 0.8]))
        checks.append(plan.parts[0].carry_check)
    assert checks == [CARRY_CHECKS[0], CARRY_CHECKS[1]] == ["clearance", "clearance except near its ends"]

def test_a_retreat_keeps_its_clearance_from_parts_in_the_kit(panda):
    """The open hand retreats from a released plank. A block beside the hand, 2 mm from it where the retreat ends
    (0.5 mm farther than the exact check lets it come), blocks the retreat as a part lying in the kit
    (``RETREAT_KIT_CLEARANCE_M``: cabinet_17's shelf retreated 1.5-2 mm from a side panel in the kit and grazed it
    in the simulator), not as a placed part (the fingers may pass close to the parts around the one they
    released); 5 mm farther it blocks nothing."""
    plank, block = trimesh.creation.box((0.008, 0.4, 0.02)), trimesh.creation.box((0.05, 0.05, 0.05))
    world = CellWorld(panda, Pose.identity(), {}, {"plank": ConvexPart.from_mesh("plank", plank),
                                                   "block": ConvexPart.from_mesh("block", block)},
                      np.random.default_rng(0))
    plank_at = Pose([0.5, 0.0, 0.2], [1, 0, 0, 0])
    world.set_part_poses({"plank": plank_at})
    world.hold(None, None, 0.02)
    start = np.array([0.0, -0.3, 0.0, -2.2, 0.0, 2.0, 0.8])
    end = world.solve_ik(Pose([0.5, 0.0, 0.3], [0.0, 1.0, 0.0, 0.0]), start, world.validity(), "plank", "test")

    def block_at(x: float) -> dict[str, Pose]:
        return {"plank": plank_at, "block": Pose([x, 0.0, 0.3], [1, 0, 0, 0])}

    touching, free = 0.5, 0.9  # block centres (x, m): the exact check fails at the first, passes at the second
    world.set_part_poses(block_at(touching))
    assert not world.validity()(end)
    while free - touching > 1e-5:
        middle = 0.5 * (touching + free)
        world.set_part_poses(block_at(middle))
        touching, free = (middle, free) if not world.validity()(end) else (touching, middle)
    assert RETREAT_KIT_CLEARANCE_M > LINK_CLEARANCE_M + 0.0005
    world.set_part_poses(block_at(free + 0.0005))
    assert world.validity()(end)
    assert not _retreat_validity(world, "plank", frozenset({"block"}))(end)
    assert _retreat_validity(world, "plank", frozenset())(end)
    with pytest.raises(TaskPlanningError, match="segment collides 0 cm along .*block"):  # names what it meets
        world.straight_line(end, Pose([0.5, 0.0, 0.3], [0.0, 1.0, 0.0, 0.0]), np.array([0.0, 0.0, 0.05]),
                            _retreat_validity(world, "plank", frozenset({"block"})), "plank", "retreat")
    world.set_part_poses(block_at(free + 0.005))
    assert _retreat_validity(world, "plank", frozenset({"block"}))(end)
