"""The program as a controller receives it: trajectory.mcap (read back with rosbags, every point and time stamp
compared with trajectory.csv), the controller replay check, and program.json loaded back (cell.program.load)."""

import csv
import json
import re
from types import SimpleNamespace

import numpy as np
import pytest
import trimesh
from rosbags.highlevel import AnyReader

from cell.errors import EXIT_PLANNING, StageFailed
from cell.program import (
    GripperStep,
    LimitViolation,
    MotionPoints,
    MotionStep,
    Program,
    load,
    motion_points,
    program_json,
    write_exports,
)
from cell.robot import ACCELERATION_LIMITS, JERK_LIMITS, VELOCITY_LIMITS
from planning.controller_replay import ControllerTrajectory
from planning.payload import NO_LOAD, flange_load, mass_properties
from planning.pose import Pose
from planning.timing import JointLimits, time_path

LOWER = np.array([-2.8973, -1.7628, -2.8973, -3.0718, -2.8973, -0.0175, -2.8973])
UPPER = np.array([2.8973, 1.7628, 2.8973, -0.0698, 2.8973, 3.7525, 2.8973])
HOME = np.array([0.0, -0.6, 0.0, -2.2, 0.0, 1.6, 0.785])
A = HOME + [0.4, 0.2, 0.0, 0.3, 0.0, -0.2, 0.0]
B = HOME + [-0.4, 0.1, 0.2, 0.2, 0.1, 0.0, -0.3]
LIMITS = JointLimits(0.9 * VELOCITY_LIMITS, 0.9 * ACCELERATION_LIMITS, 0.9 * JERK_LIMITS)  # as the planner times
LEG_WIDTH_M = 0.03
LEG = mass_properties(trimesh.creation.box(extents=(0.03, 0.03, 0.4)), 600.0)
GRASP = Pose(np.array([0.0, 0.0, 0.1]), np.array([0.0, 1.0, 0.0, 0.0]))  # part_from_tcp: fingers from above


def pick_and_place(robot="panda", limits=LIMITS) -> Program:
    """A pick and place as the planner writes it: a grasp squeezed 4 mm for the simulator, the leg's load."""
    return Program([
        MotionStep("leg: approach", time_path(np.stack([HOME, A]), limits)),
        GripperStep("leg: close", LEG_WIDTH_M - 0.004, "leg", kind="grasp", grasp_width_m=LEG_WIDTH_M, force_n=20.0,
                    load=flange_load(LEG, GRASP)),
        MotionStep("leg: carry", time_path(np.stack([A, HOME, B]), limits), "leg"),
        GripperStep("leg: open", 0.05, "leg", load=NO_LOAD),
        MotionStep("return home", time_path(np.stack([B, HOME]), limits)),
    ], initial_width_m=0.05, robot=robot)


@pytest.fixture(scope="module")
def exported(tmp_path_factory):
    folder = tmp_path_factory.mktemp("export")
    program = pick_and_place()
    write_exports(program, folder, LOWER, UPPER)
    with open(folder / "trajectory.csv") as handle:
        rows = list(csv.reader(handle))
    return program, folder, np.array(rows[1:], dtype=float)


def read_bag(path):
    with AnyReader([path]) as reader:
        return [(c.topic, c.msgtype, t, reader.deserialize(raw, c.msgtype)) for c, t, raw in reader.messages()]


def test_the_bag_holds_every_step_in_order(exported):
    program, folder, _ = exported
    assert sorted(p.name for p in folder.iterdir()) == ["program.json", "trajectory.csv", "trajectory.mcap"]
    messages = read_bag(folder / "trajectory.mcap")
    assert [(topic, msgtype) for topic, msgtype, _, _ in messages] == [
        ("/fer_arm_controller/joint_trajectory", "trajectory_msgs/msg/JointTrajectory"),
        ("/franka_gripper/grasp/goal", "franka_msgs/action/Grasp_Goal"),
        ("/service_server/set_load/request", "geometry_msgs/msg/InertiaStamped"),
        ("/fer_arm_controller/joint_trajectory", "trajectory_msgs/msg/JointTrajectory"),
        ("/franka_gripper/move/goal", "franka_msgs/action/Move_Goal"),
        ("/service_server/set_load/request", "geometry_msgs/msg/InertiaStamped"),
        ("/fer_arm_controller/joint_trajectory", "trajectory_msgs/msg/JointTrajectory"),
    ]
    times = [t for _, _, t, _ in messages]
    assert times == sorted(times) and times[0] == 0
    grasp, load_on, move, load_off = messages[1][3], messages[2][3], messages[4][3], messages[5][3]
    assert grasp.width == LEG_WIDTH_M  # the part's width, not the simulator's squeeze
    assert (grasp.epsilon.inner, grasp.epsilon.outer, grasp.speed, grasp.force) == (0.005, 0.005, 0.1, 20.0)
    assert (move.width, move.speed) == (0.05, 0.1)
    # the load starts when the grasp ends: 500 ms (the gripper step) after the goal
    assert messages[2][2] - messages[1][2] == 500_000_000
    assert load_on.header.frame_id == "fer_link8" and load_on.inertia.m == pytest.approx(LEG.mass_kg)
    # held 0.1 m beyond the TCP along the part's z: its centre 0.105 + 0.1 m out along the flange's z
    np.testing.assert_allclose([load_on.inertia.com.x, load_on.inertia.com.y, load_on.inertia.com.z],
                               [0.0, 0.0, 0.205], atol=1e-9)
    assert load_off.inertia.m == 0.0


def test_every_point_and_time_stamp_is_a_row_of_the_csv(exported):
    program, folder, table = exported
    t_csv = table[:, 0]
    points = 0
    for topic, _, stamp_ns, message in read_bag(folder / "trajectory.mcap"):
        if not topic.endswith("joint_trajectory"):
            continue
        assert message.joint_names == [f"fer_joint{k}" for k in range(1, 8)]
        assert (message.header.stamp.sec, message.header.stamp.nanosec) == (0, 0)  # start on arrival
        for point in message.points:
            ns = stamp_ns + point.time_from_start.sec * 1_000_000_000 + point.time_from_start.nanosec
            assert ns % 1_000_000 == 0  # on the 1 kHz control cycle
            row = ns // 1_000_000
            assert t_csv[row] == row / 1000.0
            assert len(point.effort) == 0
            for values, columns in ((point.positions, slice(1, 8)), (point.velocities, slice(8, 15)),
                                    (point.accelerations, slice(15, 22))):
                assert values.dtype == np.float64
                np.testing.assert_array_equal(np.round(values, 9), table[row, columns])  # the CSV keeps 9 decimals
            points += 1
        assert message.points[0].time_from_start.sec == message.points[0].time_from_start.nanosec == 0
        np.testing.assert_allclose(message.points[0].velocities, 0.0, atol=1e-12)  # from rest to rest
        np.testing.assert_allclose(message.points[-1].velocities, 0.0, atol=1e-12)
    # every 10 ms, closer in places, the three motions' last points at the next step's first row
    assert len(table) / 10 < points < len(table) / 2


def test_sqlite3_storage_writes_a_humble_bag_folder_with_the_same_messages(exported, tmp_path):
    program, folder, _ = exported
    write_exports(program, tmp_path, LOWER, UPPER, bag_storage="sqlite3")
    assert (tmp_path / "trajectory_bag" / "metadata.yaml").exists() and not (tmp_path / "trajectory.mcap").exists()
    mcap, sqlite = read_bag(folder / "trajectory.mcap"), read_bag(tmp_path / "trajectory_bag")
    assert [(m[0], m[2]) for m in sqlite] == [(m[0], m[2]) for m in mcap]
    np.testing.assert_array_equal(sqlite[3][3].points[7].accelerations, mcap[3][3].points[7].accelerations)


def test_the_fr3_gets_its_own_joint_names_and_controller(tmp_path):
    """Timed within the FR3's own limits (its datasheet, written out here: 2.62 / 5.26 / 4.18 rad/s, 10 rad/s^2,
    5000 rad/s^3), checked against them; the Panda's timing would break the FR3's acceleration limit."""
    fr3 = JointLimits(0.9 * np.array([2.62, 2.62, 2.62, 2.62, 5.26, 4.18, 5.26]), 0.9 * np.full(7, 10.0),
                      0.9 * np.full(7, 5000.0))
    fr3_lower = np.array([-2.7437, -1.7837, -2.9007, -3.0421, -2.8065, 0.5445, -3.0159])
    fr3_upper = np.array([2.7437, 1.7837, 2.9007, -0.1518, 2.8065, 4.5169, 3.0159])
    with pytest.raises(LimitViolation, match=r"acceleration .* is over its limit"):
        write_exports(pick_and_place("fr3"), tmp_path / "panda_timed", fr3_lower, fr3_upper)
    assert not (tmp_path / "panda_timed").exists()
    write_exports(pick_and_place("fr3", fr3), tmp_path, fr3_lower, fr3_upper)
    messages = read_bag(tmp_path / "trajectory.mcap")
    assert messages[0][0] == "/fr3_arm_controller/joint_trajectory"
    assert messages[0][3].joint_names[0] == "fr3_joint1" and messages[2][3].header.frame_id == "fr3_link8"
    assert json.loads((tmp_path / "program.json").read_text())["joint_names"][6] == "fr3_joint7"


def test_program_json_says_what_each_step_is(exported):
    _, folder, table = exported
    document = json.loads((folder / "program.json").read_text())
    assert document["robot"] == "panda" and document["csv_rate_hz"] == 1000.0 and document["point_rate_hz"] == 100.0
    assert [s["type"] for s in document["steps"]] == ["motion", "gripper", "payload", "motion", "gripper", "payload",
                                                      "motion"]
    grasp, load_on, release, load_off = (document["steps"][k] for k in (1, 2, 4, 5))
    assert grasp["kind"] == "grasp" and grasp["width_m"] == LEG_WIDTH_M and grasp["force_n"] == 20.0
    assert grasp["simulated_width_m"] == pytest.approx(LEG_WIDTH_M - 0.004)
    assert grasp["epsilon_m"] == {"inner": 0.005, "outer": 0.005} and grasp["speed_m_s"] == 0.1
    assert release["kind"] == "move" and release["width_m"] == 0.05
    assert load_on["part"] == "leg" and load_on["frame"] == "fer_link8" and load_off["mass_kg"] == 0.0
    assert load_on["start_s"] == grasp["start_s"] + grasp["duration_s"]
    assert document["duration_s"] == table[-1, 0]


def test_program_json_loads_back_into_the_same_program(exported):
    program, folder, table = exported
    document = json.loads((folder / "program.json").read_text())
    loaded = load(folder / "program.json")
    assert loaded.robot == "panda" and loaded.initial_width_m == program.initial_width_m
    assert [type(s) for s in loaded.steps] == [type(s) for s in program.steps]
    assert [(s.label, s.part) for s in loaded.steps] == [(s.label, s.part) for s in program.steps]
    for mine, theirs in zip(loaded.steps, program.steps):
        if isinstance(mine, GripperStep):
            assert (mine.kind, mine.width_m, mine.grasp_width_m, mine.force_n, mine.load) == (
                theirs.kind, theirs.width_m, theirs.grasp_width_m, theirs.force_n, theirs.load)
        else:
            assert isinstance(mine.timed, ControllerTrajectory) and mine.cycles == theirs.cycles
    assert program_json(loaded) == document  # written again, the same file
    # sampled, the loaded program is the controller's playback: the CSV at the points, within 1e-5 rad between
    samples = loaded.sample()
    np.testing.assert_array_equal(samples["t"], table[:, 0])
    assert np.abs(samples["q"] - table[:, 1:8]).max() < 1e-5
    np.testing.assert_array_equal(samples["gripper_width"], table[:, 22])
    for motion in motion_points(loaded, samples):
        np.testing.assert_array_equal(np.round(samples["q"][motion.rows], 9), table[motion.rows, 1:8])


def test_a_broken_program_json_is_refused_by_name(exported, tmp_path):
    _, folder, _ = exported
    document = json.loads((folder / "program.json").read_text())
    del document["steps"][1]["force_n"]
    (tmp_path / "program.json").write_text(json.dumps(document))
    with pytest.raises(ValueError, match=r"program.json, step 2: KeyError: 'force_n'"):
        load(tmp_path / "program.json")


def thinned(program: Program, samples, every: int, step: int) -> list[MotionPoints]:
    """The program's points, with those of motion ``step`` tampered: only every ``every``-th control cycle (and its
    last)."""
    points = motion_points(program, samples)
    for k, motion in enumerate(points):
        if motion.step == step:
            rows = np.arange(motion.rows[0], motion.rows[-1], every)
            points[k] = MotionPoints(step, np.append(rows, motion.rows[-1]))
    return points


def test_thinned_points_that_overshoot_are_refused_by_step_and_joint(tmp_path):
    """The carry's points 40 ms apart: the controller's quintic between them accelerates joint 1 beyond its
    15 rad/s^2 (the motion itself keeps to 90% of it)."""
    program = pick_and_place()
    samples = program.sample()
    with pytest.raises(LimitViolation, match=r"^step 3 \('leg: carry'\), as the joint trajectory controller plays its "
                                             r"\d+ points: joint 1 \(fer_joint1\) acceleration -15\.\d+ at 0\.\d+ s "
                                             r"into the step passes its limit -15\.0000"):
        write_exports(program, tmp_path / "out", LOWER, UPPER, samples, thinned(program, samples, 40, 2))
    assert not (tmp_path / "out").exists()


def test_the_pipeline_stops_at_a_program_the_controller_would_play_over_a_limit():
    """A program timed at 100% of the published limits (the planner keeps 10% from them): its own samples keep the
    velocity and acceleration limits, but the controller's playback changes its acceleration faster than the jerk
    limit between points where the motion's jerk switches; the pipeline fails it at timing (exit 3) before anything
    is exported."""
    from cell.pipeline import Pipeline

    program = pick_and_place(limits=JointLimits(VELOCITY_LIMITS, ACCELERATION_LIMITS, JERK_LIMITS))
    pipeline = Pipeline.__new__(Pipeline)  # only its limit check: the plan is this program
    pipeline.plan = SimpleNamespace(program=program, joint_limits=(LOWER, UPPER))
    pipeline.samples = pipeline.points = None
    with pytest.raises(StageFailed) as failure:
        pipeline._check_limits()
    assert failure.value.exit_code == EXIT_PLANNING and failure.value.stage == "timing"
    assert re.match(r"the exported program breaks a limit at step \d \('[^']+'\), as the joint trajectory "
                    r"controller plays its \d+ points: joint \d \(fer_joint\d\) jerk -?\d+\.\d+ at ",
                    str(failure.value)), str(failure.value)
    assert pipeline.samples is None  # nothing to export
