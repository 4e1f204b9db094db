"""Forward kinematics in numpy against PyBullet's, and the robot's collision checker."""

import numpy as np
import trimesh

from cell.bullet import BulletClient
from cell.robot import Panda
from cell.scene import load_scene
from planning.collision import ConvexPart
from planning.pose import Pose
from planning.robot_collision import RobotCollisionChecker


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
    checker = RobotCollisionChecker(np.eye(4), {})
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
