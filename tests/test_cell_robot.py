"""The cell's scene file and the Panda's kinematics."""

import numpy as np
import pytest

from cell.bullet import BulletClient
from cell.robot import IKError, IKSettings, Panda, pose_rng
from cell.scene import SceneError, load_scene
from planning import panda_ik
from planning.pose import Pose


@pytest.fixture(scope="module")
def panda():
    with BulletClient() as client:
        yield Panda(client, Pose.identity())


def test_default_scene_loads():
    scene = load_scene()
    assert scene.fixture.world_from_assembly.position[2] == pytest.approx(0.12)
    assert len(scene.robot.home_q) == 7


def test_bad_scene_values_are_named(tmp_path):
    text = load_scene().source
    good = open(text).read()
    path = tmp_path / "scene.toml"
    path.write_text(good.replace("home_q = [0.0, -0.6, 0.0, -2.2, 0.0, 1.6, 0.785]", "home_q = [0.0, 1.0]"))
    with pytest.raises(SceneError, match=r"scene\.toml: \[robot\] home_q must be a list of 7"):
        load_scene(path)
    path.write_text(good.replace("world_from_base = { position = [0.0, 0.0, 0.0], quat_wxyz = [1.0, 0.0, 0.0, 0.0] }",
                                 "world_from_base = { position = [0.0, 0.0, 0.0], quat_wxyz = [2.0, 0.0, 0.0, 0.0] }"))
    with pytest.raises(SceneError, match=r"\[robot\] world_from_base: quaternion .* norm 2"):
        load_scene(path)
    path.write_text(good.replace("payload_kg = 3.0", "payload_kg = -1"))
    with pytest.raises(SceneError, match=r"\[robot\] payload_kg must be positive, got -1"):
        load_scene(path)
    path.write_text(good.replace("payload_kg = 3.0", "payload_kg = 5.0"))
    assert load_scene(path).robot.payload_kg == 5.0
    path.write_text(good.replace("payload_kg = 3.0\n", ""))  # older scene files: the rated payload
    assert load_scene(path).robot.payload_kg == 3.0
    assert load_scene(path).fixture.upside_down is True
    path.write_text(good.replace("upside_down = true", 'upside_down = "no"'))
    with pytest.raises(SceneError, match=r"\[fixture\] upside_down must be true or false, got 'no'"):
        load_scene(path)
    path.write_text(good.replace("upside_down = true", "upside_down = false"))
    assert load_scene(path).fixture.upside_down is False
    # a misspelled key would leave the default in force unnoticed: refused, naming the key, its table and the keys
    path.write_text(good.replace("random_seed = 0", "random_sed = 0"))
    with pytest.raises(SceneError, match=r"scene\.toml: the top level has no key 'random_sed' \(did you mean "
                       r"'random_seed'\?\); its keys are random_seed, robot, table, fixture, kitting, camera"):
        load_scene(path)
    path.write_text(good.replace("jig_margin = 0.12", "jig_margin = 0.12\nclearance = 0.05"))
    with pytest.raises(SceneError, match=r"\[kitting\] has no key 'clearance'; its keys are inner_radius, "):
        load_scene(path)
    path.write_text(good.replace("quat_wxyz = [1.0, 0.0, 0.0, 0.0] }", "quat_wxyz = [1.0, 0.0, 0.0, 0.0], quat = 1 }"))
    with pytest.raises(SceneError, match=r"\[robot\] world_from_base has no key 'quat' \(did you mean 'quat_wxyz'"):
        load_scene(path)
    path.write_text("not = [toml")
    with pytest.raises(SceneError, match="not valid TOML"):
        load_scene(path)
    with pytest.raises(SceneError, match="does not exist"):
        load_scene(tmp_path / "missing.toml")


def test_inverse_kinematics_top_down_grasps(panda):
    rng = np.random.default_rng(0)
    solved = 0
    trials = 40
    for _ in range(trials):
        position = [rng.uniform(0.3, 0.6), rng.uniform(-0.4, 0.4), rng.uniform(0.05, 0.45)]  # the cell's work zone
        yaw = rng.uniform(-np.pi, np.pi)
        # approach (TCP +z) pointing down, closing axis turned by yaw
        target = Pose(position, [0.0, np.cos(yaw / 2), np.sin(yaw / 2), 0.0])
        try:
            q = panda.inverse_tcp(target, rng, seed_q=np.array(load_scene().robot.home_q))
        except IKError:
            continue
        solved += 1
        assert panda.within_limits(q)
        dp, da = panda.forward_tcp(q).distance(target)
        assert dp <= 2e-5 and da <= 2e-4  # polished: parts fit with fractions of a millimetre to spare
    assert solved >= 0.95 * trials


def test_the_random_starts_for_a_target_follow_from_its_pose_and_the_seed_alone():
    pose = Pose([0.4, -0.1, 0.3], [0.0, 0.6, 0.8, 0.0])
    draws = pose_rng(pose, 3).uniform(size=5)
    assert np.array_equal(draws, pose_rng(pose, 3).uniform(size=5))
    # the same rotation written with the opposite quaternion sign
    assert np.array_equal(draws, pose_rng(Pose(pose.position, -pose.quat_wxyz), 3).uniform(size=5))
    assert not np.array_equal(draws, pose_rng(pose, 4).uniform(size=5))
    moved = Pose(pose.position + [1e-4, 0.0, 0.0], pose.quat_wxyz)  # a tenth of a millimetre away
    assert not np.array_equal(draws, pose_rng(moved, 3).uniform(size=5))


def test_unreachable_target_raises_with_its_pose(panda):
    with pytest.raises(IKError, match="no arm configuration within the joint limits places the TCP at Pose"):
        panda.inverse_tcp(Pose([2.0, 0.0, 0.5], [1, 0, 0, 0]), np.random.default_rng(1))
    # a single start is not checked in closed form: its own rounds fail
    with pytest.raises(IKError, match="no inverse kinematics for the TCP at Pose.*1 starts"):
        panda.inverse_tcp(Pose([2.0, 0.0, 0.5], [1, 0, 0, 0]), np.random.default_rng(1),
                          settings=IKSettings(restarts=1))


def test_the_closed_form_agrees_with_the_simulators_kinematics(panda):
    rng = np.random.default_rng(3)
    for _ in range(20):
        q = rng.uniform(panda.lower_limits, panda.upper_limits)
        assert np.abs(panda_ik.forward_tcp(q) - panda.forward_tcp(q).matrix()).max() < 1e-5
        assert panda.closed_form_reaches(panda.forward_tcp(q))


def test_the_closed_form_refuses_only_what_no_start_reaches(panda):
    """Poses drawn around the arm, any orientation: every one that the twelve starts reach, the closed form reaches
    too; the ones it refuses, no start reaches (checked with the check switched off)."""
    rng = np.random.default_rng(4)
    unchecked = IKSettings(closed_form_samples=0)
    refused = 0
    for _ in range(40):
        pose = Pose([rng.uniform(-0.3, 0.8), rng.uniform(-0.7, 0.7), rng.uniform(0.0, 0.9)], rng.normal(size=4))
        reaches = panda.closed_form_reaches(pose)
        try:
            panda.inverse_tcp(pose, np.random.default_rng(0), seed_q=np.array(load_scene().robot.home_q),
                              settings=unchecked)
            assert reaches, pose
        except IKError:
            refused += not reaches
    assert refused >= 5  # the check has work to do


def test_tcp_jacobian_matches_finite_differences(panda):
    q = np.array([0.3, -0.4, 0.2, -2.0, 0.1, 1.8, 0.6])
    jacobian = panda.tcp_jacobian(q)
    eps = 1e-4  # central differences (PyBullet's link poses carry single-precision noise)
    for j in range(7):
        plus, minus = q.copy(), q.copy()
        plus[j] += eps
        minus[j] -= eps
        a, b = panda.forward_tcp(plus), panda.forward_tcp(minus)
        linear = (a.position - b.position) / (2 * eps)
        turn = a.rotation @ b.rotation.T
        angular = np.array([turn[2, 1] - turn[1, 2], turn[0, 2] - turn[2, 0], turn[1, 0] - turn[0, 1]]) / (4 * eps)
        assert np.allclose(jacobian[:3, j], linear, atol=1e-3), (j, jacobian[:3, j], linear)
        assert np.allclose(jacobian[3:, j], angular, atol=1e-3), (j, jacobian[3:, j], angular)
