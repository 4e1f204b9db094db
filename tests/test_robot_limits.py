"""The real arm's published limits bound what the planner may use; the simulation model's wider ranges do not."""

import numpy as np
import pytest

from cell.bullet import BulletClient
from cell.robot import Panda
from cell.scene import SceneError, load_scene
from planning.pose import Pose
from planning.robot_limits import FR3, PANDA
from scenes import scenes_root

# Franka's datasheets, written out here on purpose (not imported from the code under test)
PANDA_LOWER = [-2.8973, -1.7628, -2.8973, -3.0718, -2.8973, -0.0175, -2.8973]
PANDA_UPPER = [2.8973, 1.7628, 2.8973, -0.0698, 2.8973, 3.7525, 2.8973]
FR3_LOWER = [-2.7437, -1.7837, -2.9007, -3.0421, -2.8065, 0.5445, -3.0159]
FR3_UPPER = [2.7437, 1.7837, 2.9007, -0.1518, 2.8065, 4.5169, 3.0159]


@pytest.mark.parametrize("limits, lower, upper", [(PANDA, PANDA_LOWER, PANDA_UPPER), (FR3, FR3_LOWER, FR3_UPPER)])
def test_the_planner_keeps_inside_the_datasheet_and_the_simulation_model(limits, lower, upper):
    with BulletClient() as client:
        panda = Panda(client, Pose.identity(), limits=limits)
        assert np.all(panda.lower_limits >= np.array(lower) + 0.01 - 1e-12)
        assert np.all(panda.upper_limits <= np.array(upper) - 0.01 + 1e-12)
        assert np.all(panda.lower_limits >= panda.sim_lower_limits)
        assert np.all(panda.upper_limits <= panda.sim_upper_limits)
        # inverse kinematics only returns configurations inside them
        rng = np.random.default_rng(7)
        for _ in range(5):
            q = rng.uniform(panda.lower_limits, panda.upper_limits)
            solution = panda.inverse_tcp(panda.forward_tcp(q), rng, seed_q=q)
            assert panda.within_limits(solution)


def test_the_pybullet_model_is_wider_than_a_real_panda():
    """Why the datasheet matters: pybullet_data's joint 4 reaches -3.1416 rad, a real Panda stops at -3.0718."""
    with BulletClient() as client:
        panda = Panda(client, Pose.identity())
        assert panda.sim_lower_limits[3] < PANDA_LOWER[3] - 0.05
        assert panda.lower_limits[3] == pytest.approx(PANDA_LOWER[3] + 0.01)


def test_scene_files_name_the_arm():
    assert load_scene().robot.limits is PANDA
    fr3 = load_scene(scenes_root() / "cell_fr3.toml")
    assert fr3.robot.limits is FR3 and fr3.robot.model == "fr3"


@pytest.mark.parametrize("edit, words", [
    (('model = "panda"', 'model = "ur5"'), ["model", "'ur5'", "fr3", "panda"]),
    (("home_q = [0.0, -0.6, 0.0, -2.2,", "home_q = [0.0, -0.6, 0.0, -3.1,"), ["home_q", "joint 4", "-3.1"]),
])
def test_a_scene_with_an_unknown_arm_or_a_home_outside_its_range_is_refused(edit, words, tmp_path):
    text = (scenes_root() / "cell.toml").read_text()
    assert edit[0] in text
    path = tmp_path / "scene.toml"
    path.write_text(text.replace(*edit))
    with pytest.raises(SceneError) as error:
        load_scene(path)
    assert all(word in str(error.value) for word in words), str(error.value)
