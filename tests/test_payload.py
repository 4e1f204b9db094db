"""Payload limits: a part's mass properties from its mesh, and how much a heavy carry is slowed."""

import numpy as np
import pytest
import trimesh

from cell.task import PANDA_LIMITS
from planning.payload import MIN_SCALE, carry_limits, carry_scale, mass_properties
from planning.pose import Pose

GRASP_AT_CENTRE = Pose(np.zeros(3), np.array([1.0, 0.0, 0.0, 0.0]))


def edge_grasp(distance_m):
    return Pose(np.array([distance_m, 0.0, 0.0]), np.array([1.0, 0.0, 0.0, 0.0]))


def test_mass_properties_of_a_box():
    box = trimesh.creation.box(extents=(0.5, 0.3, 0.03))
    box.apply_translation((0.1, 0.0, 0.0))
    props = mass_properties(box, 600.0)
    assert props.mass_kg == pytest.approx(600.0 * 0.5 * 0.3 * 0.03)
    np.testing.assert_allclose(props.part_from_com.position, (0.1, 0.0, 0.0), atol=1e-9)
    largest = props.mass_kg * (0.5 ** 2 + 0.3 ** 2) / 12.0  # about the plate's normal
    assert max(props.inertia_kg_m2) == pytest.approx(largest)


def test_light_parts_keep_the_full_limits():
    stick = mass_properties(trimesh.creation.box(extents=(0.2, 0.02, 0.02)))  # 48 g
    assert carry_scale(stick, edge_grasp(0.08), 18.0) == 1.0
    assert carry_limits(PANDA_LIMITS, stick, edge_grasp(0.08)) is PANDA_LIMITS


def test_a_heavy_top_held_by_its_edge_is_carried_slower_the_farther_it_is_held():
    top = mass_properties(trimesh.creation.box(extents=(0.52, 0.32, 0.034)))  # 3.4 kg of wood
    near, far = carry_scale(top, edge_grasp(0.05), 18.0), carry_scale(top, edge_grasp(0.14), 18.0)
    assert MIN_SCALE <= far < near < 1.0
    slowed = carry_limits(PANDA_LIMITS, top, edge_grasp(0.14))
    np.testing.assert_allclose(slowed.acceleration, PANDA_LIMITS.acceleration * far)
    np.testing.assert_allclose(slowed.velocity, PANDA_LIMITS.velocity * np.sqrt(far))
    np.testing.assert_allclose(slowed.jerk, PANDA_LIMITS.jerk * far ** 1.5)
    # too heavy for the wrist even at rest: the slowest carry, not a negative limit
    anvil = mass_properties(trimesh.creation.box(extents=(0.3, 0.3, 0.3)), 2000.0)
    assert carry_scale(anvil, edge_grasp(0.15), 18.0) == MIN_SCALE


def _identified_panda(client):
    """The Panda in ``client`` (gravity on) with the simulator's identified link masses and inertias: (Panda, link
    name -> link index). PyBullet builds its inverse-dynamics model on the first call: change dynamics before."""
    from cell.robot import Panda
    from planning.payload import PANDA_LINK_DYNAMICS

    pb, cid = client.pb, client.client_id
    pb.setGravity(0.0, 0.0, -9.81, physicsClientId=cid)
    panda = Panda(client, Pose.identity())
    index = {pb.getJointInfo(panda.body, j, physicsClientId=cid)[12].decode(): j
             for j in range(pb.getNumJoints(panda.body, physicsClientId=cid))}
    for link, (mass, inertia) in PANDA_LINK_DYNAMICS.items():
        pb.changeDynamics(panda.body, index[link], mass=mass, localInertiaDiagonal=inertia, physicsClientId=cid)
    return panda, index


def _pybullet_gravity_torques(q, payload_kg=0.0, tcp_from_com=None):
    """Joint torques holding the Panda (the simulator's link masses) still at ``q``, from PyBullet's own inverse
    dynamics; a payload is a point mass welded to the TCP link at ``tcp_from_com`` (metres)."""
    from cell.bullet import BulletClient

    with BulletClient() as client:
        pb, cid = client.pb, client.client_id
        panda, index = _identified_panda(client)
        tau = np.array(pb.calculateInverseDynamics(panda.body, list(q) + [0.04, 0.04], [0.0] * 9, [0.0] * 9,
                                                   physicsClientId=cid)[:7])
        if payload_kg:  # the point mass's weight, through PyBullet's Jacobian at the TCP link
            linear, _ = pb.calculateJacobian(panda.body, index["panda_grasptarget"], list(tcp_from_com),
                                             list(q) + [0.04, 0.04], [0.0] * 9, [0.0] * 9, physicsClientId=cid)
            tau += np.array(linear)[:, :7].T @ np.array([0.0, 0.0, payload_kg * 9.81])
        return tau


def test_holding_torques_agree_with_pybullets_inverse_dynamics():
    from planning.payload import JointTorques, MassProperties
    from planning.robot_collision import RobotCollisionChecker

    checker = RobotCollisionChecker(np.eye(4), {})
    arm_only = JointTorques(checker)
    payload = MassProperties(2.5, Pose([0.0, 0.0, 0.0], [1.0, 0.0, 0.0, 0.0]), (0.01, 0.01, 0.01))
    tcp_from_part = Pose([0.25, 0.05, 0.02], [1.0, 0.0, 0.0, 0.0])  # held 25 cm off its centre of mass
    loaded = JointTorques(checker, payload, tcp_from_part)
    rng = np.random.default_rng(7)
    for q in rng.uniform(-1.5, 1.5, (4, 7)):
        np.testing.assert_allclose(arm_only.torques_nm(q[None])[0], _pybullet_gravity_torques(q), atol=1e-6)
        np.testing.assert_allclose(loaded.torques_nm(q[None])[0],
                                   _pybullet_gravity_torques(q, 2.5, tcp_from_part.position), atol=1e-6)


def test_a_heavy_part_held_far_out_is_refused_where_the_wrist_cannot_hold_it():
    from planning.payload import HOLDING_TORQUE_FRACTION, JointTorques, MassProperties
    from planning.robot_collision import RobotCollisionChecker

    checker = RobotCollisionChecker(np.eye(4), {})
    top = MassProperties(3.3, Pose([0.0, 0.0, 0.0], [1.0, 0.0, 0.0, 0.0]), (0.05, 0.05, 0.1))
    held_at_edge = JointTorques(checker, top, Pose([0.3, 0.0, 0.0], [1.0, 0.0, 0.0, 0.0]))
    held_at_centre = JointTorques(checker, top, Pose.identity())
    qs = np.random.default_rng(3).uniform(-2.0, 2.0, (200, 7))
    edge, centre = held_at_edge.within(qs), held_at_centre.within(qs)
    assert centre.mean() > 0.9  # 3.3 kg at the TCP: almost anywhere
    assert 0.1 < edge.mean() < 0.9  # 30 cm out: only where the wrist does not bear the moment
    assert edge.mean() < centre.mean() - 0.1  # refused far more often held 30 cm out than at its centre
    worst = qs[np.argmin(edge)]
    assert not edge[np.argmin(edge)] and "panda_joint" in held_at_edge.words(worst)
    assert HOLDING_TORQUE_FRACTION < 1.0


def test_moving_torques_agree_with_pybullets_inverse_dynamics():
    """Newton-Euler torques of the arm in motion, alone and with a payload (a mass and principal inertias at the
    TCP), against PyBullet's own inverse dynamics with the same link masses and inertias."""
    from cell.bullet import BulletClient
    from planning.payload import JointTorques, MassProperties
    from planning.robot_collision import RobotCollisionChecker

    checker = RobotCollisionChecker(np.eye(4), {})
    payload = MassProperties(2.0, Pose.identity(), (0.02, 0.03, 0.05))
    models = {"arm": JointTorques(checker), "loaded": JointTorques(checker, payload, Pose.identity())}
    rng = np.random.default_rng(11)
    states = [(rng.uniform(-1.5, 1.5, 7), rng.uniform(-2.0, 2.0, 7), rng.uniform(-10.0, 10.0, 7)) for _ in range(3)]
    for name, model in models.items():
        with BulletClient() as client:
            pb, cid = client.pb, client.client_id
            panda, index = _identified_panda(client)
            if name == "loaded":  # the massless TCP link carries the payload
                pb.changeDynamics(panda.body, index["panda_grasptarget"], mass=payload.mass_kg,
                                  localInertiaDiagonal=payload.inertia_kg_m2, physicsClientId=cid)
            for q, qd, qdd in states:
                expected = pb.calculateInverseDynamics(panda.body, list(q) + [0.04, 0.04], list(qd) + [0.0, 0.0],
                                                       list(qdd) + [0.0, 0.0], physicsClientId=cid)[:7]
                np.testing.assert_allclose(model.moving_torques_nm(q, qd, qdd)[0], expected, atol=1e-6)
            at_rest = model.moving_torques_nm(states[0][0], np.zeros(7), np.zeros(7))[0]
            np.testing.assert_allclose(at_rest, model.torques_nm(states[0][0][None])[0], atol=1e-9)
    moving = states[1]
    assert not np.allclose(models["arm"].moving_torques_nm(*moving), models["loaded"].moving_torques_nm(*moving))


def test_flange_load_matches_the_arm_held_part_in_pybullet():
    """The SetLoad numbers of a held part: its centre of mass and inertia in the flange frame (panda_link8), checked
    against PyBullet's forward kinematics of the flange and the TCP (PyBullet keeps link poses to about 1e-8 m)."""
    from cell.bullet import BulletClient
    from cell.robot import Panda
    from planning.payload import flange_load

    box = trimesh.creation.box(extents=(0.4, 0.1, 0.02))
    box.apply_translation((0.05, 0.01, 0.0))
    props = mass_properties(box, 600.0)
    part_from_tcp = Pose.from_rotation(trimesh.transformations.rotation_matrix(0.7, (0.3, 1.0, 0.2))[:3, :3],
                                       (0.12, 0.0, 0.01))
    load = flange_load(props, part_from_tcp)
    with BulletClient() as client:
        panda = Panda(client, Pose.identity())
        q = np.array([0.3, -0.5, 0.2, -2.0, 0.4, 1.7, 0.6])
        world_from_tcp = panda.forward_tcp(q)
        link8 = [j for j in range(panda.pb.getNumJoints(panda.body, physicsClientId=panda.cid))
                 if panda.pb.getJointInfo(panda.body, j, physicsClientId=panda.cid)[12] == b"panda_link8"][0]
        state = panda.pb.getLinkState(panda.body, link8, computeForwardKinematics=True, physicsClientId=panda.cid)
        world_from_flange = Pose.from_pybullet(state[4], state[5])
    world_from_part = world_from_tcp @ part_from_tcp.inverse()
    com_world = (world_from_part @ props.part_from_com).position
    np.testing.assert_allclose(load.flange_from_com_m, world_from_flange.inverse().apply(com_world), atol=1e-7)
    axes_world = (world_from_part @ props.part_from_com).rotation
    inertia_world = axes_world @ np.diag(props.inertia_kg_m2) @ axes_world.T
    flange_axes = world_from_flange.rotation
    np.testing.assert_allclose(load.inertia_kg_m2, flange_axes.T @ inertia_world @ flange_axes, atol=1e-9)
    assert load.mass_kg == pytest.approx(600.0 * 0.4 * 0.1 * 0.02)
