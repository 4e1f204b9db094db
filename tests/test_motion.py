"""Joint-space planning with OMPL around a real obstacle, checked with the real collision model."""

import time

import numpy as np
import pytest
import trimesh

from cell.scene import load_scene
from planning.collision import ConvexPart
from planning.motion import MotionPlanningError, MotionSettings, plan_joint_path, query_seed, straight_line_valid
from planning.robot_collision import RobotCollisionChecker

LOWER = np.array([-2.9671, -1.8326, -2.9671, -3.1416, -2.9671, -0.0873, -2.9671])
UPPER = np.array([2.9671, 1.8326, 2.9671, 0.0, 2.9671, 3.8223, 2.9671])


def world_with_wall():
    table = ConvexPart.from_mesh("table", trimesh.creation.box([1.2, 1.6, 0.05]))
    wall = ConvexPart.from_mesh("wall", trimesh.creation.box([0.3, 0.04, 0.5]))
    world_from_table, world_from_wall = np.eye(4), np.eye(4)
    world_from_table[:3, 3] = [0.45, 0.0, -0.025]
    world_from_wall[:3, 3] = [0.5, 0.0, 0.25]
    return RobotCollisionChecker(np.eye(4), {"table": (table, world_from_table), "wall": (wall, world_from_wall)})


def test_plans_around_a_wall():
    checker = world_with_wall()
    home = np.array(load_scene().robot.home_q)
    start = home.copy()
    start[0] = 0.8  # arm swung to the left of the wall
    goal = home.copy()
    goal[0] = -0.8  # ... and to its right
    assert checker.is_valid(start) and checker.is_valid(goal)
    assert not straight_line_valid(checker.is_valid, start, goal)  # the direct swing hits the wall
    path = plan_joint_path(checker.is_valid, start, goal, LOWER, UPPER, MotionSettings(time_limit_s=20.0))
    np.testing.assert_allclose(path[0], start)
    np.testing.assert_allclose(path[-1], goal)
    for a, b in zip(path[:-1], path[1:]):
        assert straight_line_valid(checker.is_valid, a, b, step_rad=0.01)


def test_typed_failures():
    checker = world_with_wall()
    home = np.array(load_scene().robot.home_q)
    into_table = np.array([0.0, 1.5, 0.0, -0.5, 0.0, 1.0, 0.0])
    with pytest.raises(MotionPlanningError) as info:
        plan_joint_path(checker.is_valid, into_table, home, LOWER, UPPER)
    assert info.value.kind == "start_in_collision"
    with pytest.raises(MotionPlanningError) as info:
        plan_joint_path(checker.is_valid, home, into_table, LOWER, UPPER)
    assert info.value.kind == "goal_in_collision"
    with pytest.raises(MotionPlanningError) as info:
        plan_joint_path(checker.is_valid, home, home, LOWER, UPPER, MotionSettings(planner="Magic"))
    assert info.value.kind == "invalid_request"


def test_plans_around_a_wall_with_segment_checks():
    checker = world_with_wall()
    home = np.array(load_scene().robot.home_q)
    start, goal = home.copy(), home.copy()
    start[0], goal[0] = 0.8, -0.8
    calls = []

    def segment_valid(q_from, q_to):
        calls.append(1)
        return checker.segment_valid(q_from, q_to)

    path = plan_joint_path(checker.is_valid, start, goal, LOWER, UPPER, MotionSettings(time_limit_s=20.0),
                           segment_valid=segment_valid)
    assert len(calls) > 1  # the straight swing and then the planner's edges went through it
    np.testing.assert_allclose(path[[0, -1]], [start, goal])
    for a, b in zip(path[:-1], path[1:]):  # an independent dense check: every 2 mrad per joint
        assert straight_line_valid(checker.is_valid, a, b, step_rad=0.002)


def test_a_query_plans_the_same_path_whatever_was_planned_before_it():
    """OMPL seeds its generators from one sequence per process; each query restarts it from a seed of its own
    (the settings' seed and the query), so one part's path in a cell program does not change when a search
    anywhere before it is added or dropped."""
    checker = world_with_wall()
    home = np.array(load_scene().robot.home_q)
    start, goal = home.copy(), home.copy()
    start[0], goal[0] = 0.8, -0.8
    settings = MotionSettings(time_limit_s=20.0, simplify=False)  # the searched path, not a shortened one

    def plan(q_from, q_to, plan_settings=settings):
        return plan_joint_path(checker.is_valid, q_from, q_to, LOWER, UPPER, plan_settings,
                               segment_valid=checker.segment_valid)

    first = plan(start, goal)
    plan(goal, start)  # another query in between, drawing from OMPL's sequence
    np.testing.assert_array_equal(plan(start, goal), first)
    other_seed = plan(start, goal, MotionSettings(time_limit_s=20.0, simplify=False, seed=1))
    assert other_seed.shape != first.shape or not np.array_equal(other_seed, first)
    assert query_seed(0, start, goal) != query_seed(0, goal, start) != query_seed(1, goal, start)


def test_segment_check_decides_the_edges():
    # every configuration is valid, but no edge may cross joint 1 = 0: there is no path
    start, goal = np.zeros(7), np.zeros(7)
    start[0], goal[0] = -0.5, 0.5

    def segment_valid(q_from, q_to):
        return bool(np.sign(q_from[0]) == np.sign(q_to[0]))

    with pytest.raises(MotionPlanningError) as info:
        plan_joint_path(lambda q: True, start, goal, LOWER, UPPER, MotionSettings(time_limit_s=0.3),
                        segment_valid=segment_valid)
    assert info.value.kind == "timeout"
    path = plan_joint_path(lambda q: True, start, goal, LOWER, UPPER, MotionSettings(time_limit_s=0.3))
    assert len(path) == 2  # without it the straight line is taken


def test_a_query_with_no_path_is_searched_again_before_it_fails():
    """A failed search is followed by a fresh one (new random trees) up to ``MotionSettings.searches`` times; the
    error says how many ran and what ended them. The query has no path: no edge may cross joint 1 = 0."""
    start, goal = np.zeros(7), np.zeros(7)
    start[0], goal[0] = -0.5, 0.5

    def segment_valid(q_from, q_to):
        return bool(np.sign(q_from[0]) == np.sign(q_to[0]))

    for searches, words in ((2, "found no path within 0.2 s of searching, in each of 2 searches"),
                            (1, "found no path within 0.2 s of searching")):
        started = time.perf_counter()
        with pytest.raises(MotionPlanningError) as info:
            plan_joint_path(lambda q: True, start, goal, LOWER, UPPER,
                            MotionSettings(time_limit_s=0.2, searches=searches), segment_valid=segment_valid)
        assert info.value.kind == "timeout" and str(info.value).endswith(words)
        assert time.perf_counter() - started >= 0.2 * searches  # each search ran out its time

    checks = iter(range(10**9))  # a count of the work: each termination check counts 1 ms
    with pytest.raises(MotionPlanningError, match=r"found no path within 0.2 s of searching, counted in collision "
                                                  r"checks$"):
        plan_joint_path(lambda q: True, start, goal, LOWER, UPPER, MotionSettings(time_limit_s=0.2, searches=1),
                        segment_valid=segment_valid, work=lambda: next(checks) * 1e-3)

    def slow_segment_valid(q_from, q_to):  # the search's thread waits: it does not work
        time.sleep(0.01)
        return segment_valid(q_from, q_to)

    started = time.perf_counter()
    with pytest.raises(MotionPlanningError, match=r"found no path within 0.3 s by the clock \(the machine is busy\)$"):
        plan_joint_path(lambda q: True, start, goal, LOWER, UPPER, MotionSettings(time_limit_s=5.0, wall_limit_s=0.3,
                                                                                searches=1),
                        segment_valid=slow_segment_valid)
    assert 0.3 <= time.perf_counter() - started < 2.0


_HARD_QUERY = """
import sys, time, numpy as np
from planning.motion import MotionPlanningError, MotionSettings, plan_joint_path
delay_s, wall_s = float(sys.argv[1]), None if sys.argv[2] == "none" else float(sys.argv[2])
start, goal = np.zeros(7), np.zeros(7)
start[0], goal[0] = -0.5, 0.5

def free(q):  # a block of joint space between start and goal: about 2600 checks to find the way around
    time.sleep(delay_s)
    return not (abs(q[0]) < 0.2 and abs(q[1]) < 1.5 and abs(q[2]) < 1.5)

settings = MotionSettings(time_limit_s=0.5, wall_limit_s=wall_s, searches=1, simplify=False)
try:
    print(np.round(plan_joint_path(free, start, goal, np.full(7, -2.5), np.full(7, 2.5), settings), 9).tolist())
except MotionPlanningError as exc:
    print(exc)
"""


def test_a_search_gets_as_far_on_a_busy_machine():
    """A query that takes about 2600 checks, its thread kept waiting 1 ms at each (as on a busy machine, about
    2.6 s): the search's 0.5 s are of its own work, so the busy machine finds the idle one's path (OMPL seeded
    alike). Stopped by the clock at 0.5 s, as searches used to be, the busy one runs out of time."""
    import subprocess
    import sys

    def run(delay_s: str, wall_s: str) -> str:
        return subprocess.run([sys.executable, "-c", _HARD_QUERY, delay_s, wall_s], capture_output=True,
                              text=True, check=True).stdout

    idle, busy = run("0", "none"), run("0.001", "none")
    assert idle.startswith("[[-0.5") and idle == busy
    busy = run("0.001", "0.5")
    assert busy.startswith("RRTConnect found no path within 0.5 s by the clock")




_COUNTED_QUERY = """
import sys, time, numpy as np
sys.path.insert(0, "tests")
from test_motion import LOWER, UPPER, world_with_wall
from planning.motion import MotionPlanningError, MotionSettings, plan_joint_path
from planning.robot_collision import checking_work_s
burn_s, counted = float(sys.argv[1]), sys.argv[2] == "counted"
checker = world_with_wall()
start, goal = np.array([0.0, -0.6, 0.0, -2.2, 0.0, 1.6, 0.785]), np.array([0.0, -0.6, 0.0, -2.2, 0.0, 1.6, 0.785])
start[0], goal[0] = -0.5, 0.5

def valid(q):  # the real check, and a block of joint space between start and goal; then a slower machine
    free = checker.is_valid(q) and not (abs(q[0]) < 0.2 and abs(q[1] + 0.6) < 1.5 and abs(q[2]) < 1.5)
    started = time.thread_time()
    while time.thread_time() - started < burn_s:
        pass
    return free

settings = MotionSettings(time_limit_s=2.0, wall_limit_s=None, searches=1, simplify=False)
try:
    path = plan_joint_path(valid, start, goal, LOWER, UPPER, settings, work=checking_work_s if counted else None)
    print(np.round(path, 9).tolist())
except MotionPlanningError as exc:
    print(exc)
"""


def test_a_search_limited_by_collision_checks_plans_the_same_path_on_a_slower_machine():
    """A query of about 2,200 checks of the real checker, which :func:`checking_work_s` counts as 0.9 s (about
    0.5 s of CPU time on a desktop core). Each check made 2 ms slower (a slower or shared core: the search's own CPU
    time grows past 4 s, twice its limit, so that no machine's speed decides the outcome), a search limited to 2 s
    of CPU time runs out; limited to 2 s of collision checking as counted, it plans the idle machine's path exactly
    (OMPL seeded alike): a cell program does not depend on the machine that planned it, or on what else ran
    there."""
    import subprocess
    import sys

    def run(burn_s: str, limit: str) -> str:
        return subprocess.run([sys.executable, "-c", _COUNTED_QUERY, burn_s, limit], capture_output=True, text=True,
                              check=True).stdout

    idle = run("0", "counted")
    assert idle.startswith("[[-0.5") and run("0.002", "counted") == idle
    assert run("0", "cpu") == idle
    assert run("0.002", "cpu").startswith("RRTConnect found no path within 2.0 s of searching\n")
