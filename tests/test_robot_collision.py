"""Forward kinematics in numpy against PyBullet's, and the robot's collision checker."""

import fcl
import numpy as np
import trimesh

from cell.bullet import BulletClient
from cell.robot import Panda
from cell.scene import load_scene
from planning.collision import ConvexPart
from planning.gripper import convex_to_fcl
from planning.pose import Pose
from planning.robot_collision import (
    ALLOWED_SELF_PAIRS,
    ARM_JOINTS,
    BASE_LINK,
    FINGER_JOINTS,
    Collision,
    RobotCollisionChecker,
)


def table_world():
    table = ConvexPart.from_mesh("table", trimesh.creation.box([1.2, 1.6, 0.05]))
    world_from_table = np.eye(4)
    world_from_table[:3, 3] = [0.45, 0.0, -0.025]
    return {"table": (table, world_from_table)}


def test_forward_kinematics_matches_pybullet():
    checker = RobotCollisionChecker(np.eye(4), {})
    rng = np.random.default_rng(0)
    with BulletClient() as client:
        panda = Panda(client, Pose.identity())
        for _ in range(10):
            q = rng.uniform(panda.lower_limits, panda.upper_limits)
            expected = panda.forward_tcp(q).matrix()
            np.testing.assert_allclose(checker.world_from_tcp(q), expected, atol=1e-6)


def test_home_is_free_and_arm_into_table_is_not():
    checker = RobotCollisionChecker(np.eye(4), table_world())
    assert checker.first_collision(np.array(load_scene().robot.home_q)) is None
    hit = checker.first_collision(np.array([0.0, 1.5, 0.0, -0.5, 0.0, 1.0, 0.0]))  # reaching down through the table
    assert hit is not None and hit.b == "table"


def test_self_collision_is_found():
    checker = RobotCollisionChecker(np.eye(4), {}, self_clearance_m=0.0)
    # the elbow folded fully: the forearm lies against the shoulder
    folded = np.array([0.65, -0.89, -2.26, -3.04, -2.69, 0.82, 0.34])
    hit = checker.first_collision(folded)
    assert hit is not None and {hit.a, hit.b} == {"panda_link1", "panda_link5"}
    # PyBullet agrees that the two links meet there (its link index is the index of the joint above the link)
    with BulletClient() as client:
        panda = Panda(client, Pose.identity())
        panda.set_arm(folded)
        pb = client.pb
        points = pb.getClosestPoints(panda.body, panda.body, 0.0, linkIndexA=0, linkIndexB=4,
                                     physicsClientId=client.client_id)
        assert len(points) > 0


def test_self_clearance_covers_the_simulators_larger_links():
    """PyBullet's link hulls carry a margin: where this model's links are still a millimetre or two apart, the
    simulator reports them touching. With the default clearance, every configuration on the way to the folded elbow
    that PyBullet sees in self-contact is invalid here too, and the exact model (no clearance) misses some."""
    home = np.array(load_scene().robot.home_q)
    folded = np.array([0.65, -0.89, -2.26, -3.04, -2.69, 0.82, 0.34])
    padded, exact = RobotCollisionChecker(np.eye(4), {}), RobotCollisionChecker(np.eye(4), {}, self_clearance_m=0.0)
    missed_by_exact = 0
    with BulletClient() as client:
        panda = Panda(client, Pose.identity())
        for fraction in np.linspace(0.85, 0.95, 41):
            q = home + fraction * (folded - home)
            panda.set_arm(q)
            touching = len(client.pb.getClosestPoints(panda.body, panda.body, 0.0, linkIndexA=0, linkIndexB=4,
                                                      physicsClientId=client.client_id)) > 0
            if touching:
                assert not padded.is_valid(q), fraction
                missed_by_exact += exact.is_valid(q)
    assert missed_by_exact > 0


def test_held_part_collides_with_world():
    checker = RobotCollisionChecker(np.eye(4), table_world())
    q = np.array(load_scene().robot.home_q)
    tcp_height = checker.world_from_tcp(q)[2, 3]
    part = ConvexPart.from_mesh("plank", trimesh.creation.box([0.05, 0.05, 2 * tcp_height + 0.1]))
    checker.hold(part, np.eye(4), opening_m=0.05)  # a plank sticking down through the table
    hit = checker.first_collision(q)
    assert hit is not None and hit.a == "held plank" and hit.b == "table"
    checker.hold(None)
    assert checker.first_collision(q) is None


def cluttered_world():
    """The table, a wall in front of the robot, a post beside it and a tilted bar behind: real boxes, world frame,
    metres."""
    world = table_world()
    for name, size, position in (("wall", [0.3, 0.04, 0.5], [0.5, 0.0, 0.25]),
                                 ("post", [0.06, 0.06, 0.6], [0.1, 0.45, 0.3])):
        world_from_box = np.eye(4)
        world_from_box[:3, 3] = position
        world[name] = (ConvexPart.from_mesh(name, trimesh.creation.box(size)), world_from_box)
    world_from_bar = trimesh.transformations.euler_matrix(0.4, 0.3, 0.7)  # turned: its boxes are not axis-aligned
    world_from_bar[:3, 3] = [-0.3, -0.35, 0.35]
    world["bar"] = (ConvexPart.from_mesh("bar", trimesh.creation.box([0.5, 0.05, 0.03])), world_from_bar)
    return world


def brute_force_valid(checker, world, q, held=None):
    """Every link hull against every world piece and every checked link pair with FCL, no broad phase, link poses
    from the URDF chain: an independent reference for the checker's answer."""
    positions = dict(zip(ARM_JOINTS, q)) | {finger: checker.opening_m / 2 for finger in FINGER_JOINTS}
    base_from_link = checker.chain.link_poses(positions)
    links = []
    for link, meshes in checker.chain.collision.items():
        for mesh, link_from_mesh in meshes:
            hull = mesh.convex_hull
            matrix = base_from_link[link] @ link_from_mesh
            links.append((link, fcl.CollisionObject(convex_to_fcl(hull.vertices, hull.faces),
                                                    fcl.Transform(matrix[:3, :3], matrix[:3, 3]))))
    pieces = [fcl.CollisionObject(g, fcl.Transform(m[:3, :3], m[:3, 3]))
              for part, m in world.values() for g in part.geometries]
    if held is not None:  # (ConvexPart, tcp_from_part): its pieces go with the TCP
        world_from_part = base_from_link["panda_grasptarget"] @ held[1]
        links += [("held", fcl.CollisionObject(g, fcl.Transform(world_from_part[:3, :3], world_from_part[:3, 3])))
                  for g in held[0].geometries]

    def touch(a, b, clearance=0.0):
        if clearance > 0.0:  # GJK distance, -1 when overlapping
            return fcl.distance(a, b, fcl.DistanceRequest(), fcl.DistanceResult()) < clearance
        return fcl.collide(a, b, fcl.CollisionRequest(), fcl.CollisionResult()) > 0

    def world_clearance(link):  # the fingers and the held part may touch, other links keep their clearance
        return 0.0 if link in ("held", "panda_leftfinger", "panda_rightfinger") else checker.link_clearance_m

    if any(touch(obj, piece, world_clearance(link)) for link, obj in links if link != BASE_LINK for piece in pieces):
        return False
    links = [(name, obj) for name, obj in links if name != "held"]  # the held part is not checked against links
    return not any(touch(a, b, checker.self_clearance_m) for i, (name_a, a) in enumerate(links)
                   for name_b, b in links[i + 1:]
                   if name_a != name_b and frozenset((name_a, name_b)) not in ALLOWED_SELF_PAIRS)


def test_agrees_with_brute_force_fcl():
    world = cluttered_world()
    checker = RobotCollisionChecker(np.eye(4), world)
    rng = np.random.default_rng(3)
    home = np.array(load_scene().robot.home_q)
    lower = np.array([-2.9, -1.8, -2.9, -3.0, -2.9, 0.0, -2.9])
    upper = np.array([2.9, 1.8, 2.9, -0.1, 2.9, 3.7, 2.9])
    configurations = np.concatenate([rng.uniform(lower, upper, (150, 7)),
                                     np.clip(home + rng.normal(scale=0.5, size=(150, 7)), lower, upper)])
    ours = [checker.is_valid(q) for q in configurations]
    reference = [brute_force_valid(checker, world, q) for q in configurations]
    assert ours == reference
    assert 0.2 < np.mean(ours) < 0.9  # both answers occur: the comparison means something
    # holding a turned plank, in batches
    tcp_from_part = trimesh.transformations.euler_matrix(0.3, 0.0, 0.5)
    tcp_from_part[:3, 3] = [0.0, 0.0, 0.05]
    plank = ConvexPart.from_mesh("plank", trimesh.creation.box([0.35, 0.03, 0.02]))
    checker.hold(plank, tcp_from_part, opening_m=0.03)
    reference = np.array([brute_force_valid(checker, world, q, (plank, tcp_from_part)) for q in configurations])
    assert 0.2 < reference.mean() < 0.9
    for start in range(0, len(configurations), 25):
        chunk = reference[start:start + 25]
        expected = None if chunk.all() else int(np.argmin(chunk))
        assert checker.first_invalid(configurations[start:start + 25]) == expected


def test_set_obstacles_replaces_the_world():
    checker = RobotCollisionChecker(np.eye(4), table_world())
    into_table = np.array([-1.2, 1.5, 0.0, -0.5, 0.0, 1.0, 0.0])  # down through the table, right of the wall
    assert checker.first_collision(into_table).b == "table"
    world = cluttered_world()
    del world["table"]
    checker.set_obstacles(world)
    assert checker.is_valid(into_table)  # the same configuration, answered again after the world changed
    assert checker.obstacle_names == {"wall", "post", "bar"}
    # reaching forward at the wall's height: home with the shoulder lowered towards the wall
    reach = np.array([0.0, 0.6, 0.0, -1.2, 0.0, 1.8, 0.785])
    hit = checker.first_collision(reach)
    assert hit is not None and hit.b == "wall"
    checker.set_obstacles({})
    assert checker.is_valid(reach) and checker.is_valid(into_table)


def test_ignore_skips_named_obstacles_for_one_query():
    world = table_world()
    world["table copy"] = world["table"]
    checker = RobotCollisionChecker(np.eye(4), world)
    into_table = np.array([0.0, 1.5, 0.0, -0.5, 0.0, 1.0, 0.0])
    assert checker.first_collision(into_table).b == "table"
    assert checker.first_collision(into_table, ignore=frozenset({"table"})).b == "table copy"
    assert checker.is_valid(into_table, ignore=frozenset({"table", "table copy"}))
    assert checker.is_valid(into_table, ignore=frozenset({"table", "table copy", "not in the world"}))
    assert not checker.is_valid(into_table)  # the ignore list does not stick
    assert not checker.is_valid(into_table, ignore=frozenset({"not in the world"}))


def test_ignore_applies_to_the_held_part_but_not_to_self_collision():
    checker = RobotCollisionChecker(np.eye(4), table_world())
    q = np.array(load_scene().robot.home_q)
    assert checker.is_valid(q)
    tcp_height = checker.world_from_tcp(q)[2, 3]
    checker.hold(ConvexPart.from_mesh("plank", trimesh.creation.box([0.05, 0.05, 2 * tcp_height + 0.1])), np.eye(4),
                 opening_m=0.05)
    assert not checker.is_valid(q)  # same q as before holding: the cached poses must not hide the plank
    assert checker.is_valid(q, ignore=frozenset({"table"}))
    checker.hold(None)
    folded = np.array([0.65, -0.89, -2.26, -3.04, -2.69, 0.82, 0.34])
    assert not checker.is_valid(folded, ignore=frozenset({"table"}))


def test_held_ignore_spares_the_held_part_but_not_the_robot():
    """A neighbour the held part is planned to touch (``held_ignore``) must still be cleared by the fingers."""
    checker = RobotCollisionChecker(np.eye(4), {})
    q = np.array(load_scene().robot.home_q)
    world_from_tcp = checker.world_from_tcp(q)
    # a 2 cm cube in the hand, and a 1 cm slab through the TCP that cuts the cube and both open fingers
    checker.hold(ConvexPart.from_mesh("cube", trimesh.creation.box([0.02, 0.02, 0.02])), np.eye(4), opening_m=0.08)
    slab = ConvexPart.from_mesh("slab", trimesh.creation.box([0.2, 0.2, 0.01]))
    checker.set_obstacles({"slab": (slab, world_from_tcp)})
    hit = checker.first_collision(q, held_ignore=frozenset({"slab"}))
    assert hit is not None and hit.a != "held cube" and hit.b == "slab"  # the fingers or hand still meet it
    assert checker.first_collision(q, ignore=frozenset({"slab"})) is None
    # a pebble inside the cube, which only the cube reaches: held_ignore makes it free
    pebble = ConvexPart.from_mesh("pebble", trimesh.creation.box([0.004, 0.004, 0.004]))
    checker.set_obstacles({"pebble": (pebble, world_from_tcp)})
    assert checker.first_collision(q).a == "held cube"
    assert checker.is_valid(q, held_ignore=frozenset({"pebble"}))
    assert not checker.segment_valid(q + 0.01, q)  # the batch path honours the masks too
    assert checker.segment_valid(q + 0.01, q, held_ignore=frozenset({"pebble"}))


def test_hand_ignore_spares_the_hand_but_not_the_arms_links():
    """The part being picked (``hand_ignore``): the hand closes around it, the wrist must not touch it."""
    checker = RobotCollisionChecker(np.eye(4), {})
    q = np.array(load_scene().robot.home_q)
    world_from_tcp = checker.world_from_tcp(q)
    slab = ConvexPart.from_mesh("slab", trimesh.creation.box([0.2, 0.2, 0.01]))
    checker.set_obstacles({"slab": (slab, world_from_tcp)})  # through the TCP: the fingers meet it
    assert checker.first_collision(q).a in ("panda_leftfinger", "panda_rightfinger", "panda_hand")
    assert checker.is_valid(q, hand_ignore=frozenset({"slab"}))
    # a board as wide as the wrist 12 cm above the TCP: the links above the hand meet it, hand_ignore or not
    above = np.eye(4)
    above[:3, 3] = world_from_tcp[:3, 3] + [0.0, 0.0, 0.2]
    board = ConvexPart.from_mesh("board", trimesh.creation.box([0.3, 0.3, 0.01]))
    checker.set_obstacles({"board": (board, above)})
    hit = checker.first_collision(q, hand_ignore=frozenset({"board"}))
    assert hit is not None and hit.a.startswith("panda_link") and hit.b == "board"
    assert not checker.segment_valid(q + 0.01, q, hand_ignore=frozenset({"board"}))  # the batch path too
    assert checker.is_valid(q, ignore=frozenset({"board"}))


def test_a_held_only_checker_checks_the_held_part_and_nothing_of_the_robot():
    """``held_only``: the held part against the world, not the arm's links against it nor against each other (a
    check added to one that covers the robot)."""
    q = np.array(load_scene().robot.home_q)
    full, held_only = RobotCollisionChecker(np.eye(4), {}), RobotCollisionChecker(np.eye(4), {}, held_only=True)
    world_from_tcp = full.world_from_tcp(q)
    above = np.eye(4)
    above[:3, 3] = world_from_tcp[:3, 3] + [0.0, 0.0, 0.2]
    board = {"board": (ConvexPart.from_mesh("board", trimesh.creation.box([0.3, 0.3, 0.01])), above)}
    pebble = {"pebble": (ConvexPart.from_mesh("pebble", trimesh.creation.box([0.004, 0.004, 0.004])),
                         world_from_tcp)}
    folded = np.array([0.65, -0.89, -2.26, -3.04, -2.69, 0.82, 0.34])  # the forearm against the shoulder
    for checker in (full, held_only):
        checker.hold(ConvexPart.from_mesh("cube", trimesh.creation.box([0.02, 0.02, 0.02])), np.eye(4),
                     opening_m=0.08)
    for checker in (full, held_only):  # a board the wrist meets 20 cm above the TCP, and the folded elbow
        checker.set_obstacles(board)
    assert full.first_collision(q).a.startswith("panda_link") and held_only.first_collision(q) is None
    assert not full.is_valid(folded) and held_only.first_invalid(np.stack([q, folded])) is None
    for checker in (full, held_only):  # a pebble inside the cube in the hand, which only the cube reaches
        checker.set_obstacles(pebble)
    assert held_only.first_collision(q).a == "held cube" and full.first_collision(q).a == "held cube"
    assert not held_only.segment_valid(q + 0.01, q)
    held_only.hold(None)
    assert held_only.is_valid(q)


def test_finger_opening_moves_the_fingers():
    checker = RobotCollisionChecker(np.eye(4), {})
    q = np.array(load_scene().robot.home_q)
    world_from_tcp = checker.world_from_tcp(q)
    sliver = ConvexPart.from_mesh("sliver", trimesh.creation.box([0.01, 0.01, 0.02]))  # between the pads
    checker.set_obstacles({"sliver": (sliver, world_from_tcp)})
    checker.hold(None, opening_m=0.08)
    assert checker.is_valid(q)
    checker.hold(None, opening_m=0.0)  # the fingers close on the sliver
    hit = checker.first_collision(q)
    assert hit is not None and hit.a in ("panda_leftfinger", "panda_rightfinger") and hit.b == "sliver"
    # the TCP does not depend on the opening, and FK stays exact after the change
    np.testing.assert_allclose(checker.world_from_tcp(q), world_from_tcp, atol=1e-12)


def test_batch_answers_match_single_queries():
    world = cluttered_world()
    checker = RobotCollisionChecker(np.eye(4), world)
    rng = np.random.default_rng(5)
    home = np.array(load_scene().robot.home_q)
    configurations = home + rng.normal(scale=0.6, size=(120, 7))
    single = np.array([checker.is_valid(q) for q in configurations])
    assert 0 < single.sum() < len(single)
    for start in range(0, 120, 10):
        chunk = configurations[start:start + 10]
        expected = None if single[start:start + 10].all() else int(np.argmin(single[start:start + 10]))
        assert checker.first_invalid(chunk) == expected
    order = np.arange(120)[::-1]  # the first invalid one in the order given
    assert checker.first_invalid(configurations, order=order) == int(np.flatnonzero(~single)[-1])


def test_segment_spacing_bounds_how_far_any_point_moves():
    checker = RobotCollisionChecker(np.eye(4), {})
    checker.hold(ConvexPart.from_mesh("plank", trimesh.creation.box([0.4, 0.03, 0.03])), np.eye(4), opening_m=0.03)
    rng = np.random.default_rng(2)
    lower = np.array([-2.9, -1.8, -2.9, -3.0, -2.9, 0.0, -2.9])
    upper = np.array([2.9, 1.8, 2.9, -0.1, 2.9, 3.7, 2.9])
    box = trimesh.creation.box([0.4, 0.03, 0.03]).vertices  # corners of the held plank, part frame = TCP frame
    for _ in range(6):
        q_from, q_to = rng.uniform(lower, upper), rng.uniform(lower, upper)
        steps = checker.segment_samples(q_from, q_to, max_step_m=0.02)
        fine = q_from + np.linspace(0.0, 1.0, 10 * steps + 1)[:, None] * (q_to - q_from)
        # points of the hand and of the plank, from the URDF chain: farthest travel between two checked samples
        points = []
        for q in fine:
            world_from_tcp = checker.world_from_tcp(q)
            points.append(box @ world_from_tcp[:3, :3].T + world_from_tcp[:3, 3])
        points = np.array(points)
        travel = np.linalg.norm(np.diff(points, axis=0), axis=2).reshape(steps, 10, -1).sum(axis=1)
        assert 0.002 < travel.max() <= 0.02  # bounded, and not absurdly loose


def test_segment_check_finds_a_thin_foil_that_a_coarse_check_misses():
    home = np.array(load_scene().robot.home_q)
    checker = RobotCollisionChecker(np.eye(4), {}, finger_clearance_m=0.0)  # the fingers' exact hulls
    # a 1 x 0.3 x 1 cm foil where the left fingertip passes when joint 1 is at 0.075 rad
    at = home.copy()
    at[0] = 0.075
    world_from_foil = np.eye(4)
    world_from_foil[:3, 3] = checker.world_from_tcp(at)[:3, :3] @ [0.0, 0.04, 0.0] + checker.world_from_tcp(at)[:3, 3]
    foil = ConvexPart.from_mesh("foil", trimesh.creation.box([0.01, 0.003, 0.01]))
    checker.set_obstacles({"foil": (foil, world_from_foil)})
    assert checker.first_collision(at) == Collision("panda_leftfinger", "foil")
    left, right = home.copy(), home.copy()
    left[0], right[0] = 0.365, -0.335  # across the foil: the fingers touch it at 0.07..0.13 and -0.20..-0.14 rad
    coarse = [left + (right - left) * t for t in np.linspace(0.0, 1.0, 8)]  # every 0.1 rad: all free
    assert all(checker.is_valid(q) for q in coarse)
    assert not checker.segment_valid(left, right)
    assert checker.segment_valid(left, right, ignore=frozenset({"foil"}))
    assert checker.segment_valid(left, left + 0.2 * (right - left))  # the part of the swing before the foil


def test_fingers_keep_their_clearance_from_everything_they_do_not_grasp():
    """PyBullet's finger hulls stop about 1.1 mm short of a face: a finger 0.5 mm from a rail touches it there."""
    q = np.array(load_scene().robot.home_q)
    exact = RobotCollisionChecker(np.eye(4), {}, finger_clearance_m=0.0)
    world_from_tcp = exact.world_from_tcp(q)
    # a rail beside the open left finger (TCP +y), its near face 0.5 mm outside the finger's hull
    rail = ConvexPart.from_mesh("rail", trimesh.creation.box([0.01, 0.01, 0.01]))
    placed = world_from_tcp.copy()

    def place(offset):
        placed[:3, 3] = world_from_tcp[:3, 3] + world_from_tcp[:3, :3] @ [0.0, offset, 0.0]
        exact.set_obstacles({"rail": (rail, placed)})

    inside, outside = 0.04, 0.15  # the rail's centre on the finger; beyond it
    place(inside)
    assert not exact.is_valid(q)
    while outside - inside > 1e-6:  # where its face meets the finger's outer side
        middle = 0.5 * (inside + outside)
        place(middle)
        inside, outside = (inside, middle) if exact.is_valid(q) else (middle, outside)
    place(outside + 0.0005)
    assert exact.is_valid(q)
    padded = RobotCollisionChecker(np.eye(4), {"rail": (rail, placed)})
    hit = padded.first_collision(q)
    assert hit is not None and hit.a == "panda_leftfinger" and hit.b == "rail"
    assert padded.is_valid(q, ignore=frozenset({"rail"}))  # what it grasps is ignored, so it may touch that
