"""The program as a ROS 2 bag (rosbag2, written with ``rosbags``): what each controller of a Franka arm receives, in
order, at the time the program sends it (nanoseconds from the program's start).

Topics (``<arm_id>``: ``fer`` for the Panda, ``fr3`` for the FR3, :attr:`planning.robot_limits.RobotLimits.ros_arm_id`):

- ``/<arm_id>_arm_controller/joint_trajectory``: ``trajectory_msgs/msg/JointTrajectory``, one per motion, for
  ros2_control's ``joint_trajectory_controller``: ``header.stamp`` zero (start on arrival), the joint names as
  franka_ros2 names them, the points of :func:`cell.program.motion_points` (positions, velocities, accelerations,
  empty effort, ``time_from_start``): rows of ``trajectory.csv``.
- ``/franka_gripper/grasp/goal``: ``franka_msgs/action/Grasp_Goal`` (width: the part's, epsilon inner and outer,
  speed, force) and ``/franka_gripper/move/goal``: ``franka_msgs/action/Move_Goal`` (width, speed), the goals of
  franka_gripper's ``grasp`` and ``move`` actions; the arm waits for each result.
- ``/service_server/set_load/request``: ``geometry_msgs/msg/InertiaStamped``, after each grasp and release: the
  load the arm then carries, in the flange frame (``header.frame_id`` ``<arm_id>_link8``), for franka_ros2's
  ``SetLoad`` service (``mass`` = ``inertia.m``, ``center_of_mass`` = ``inertia.com``, ``load_inertia`` = the
  matrix of ``ixx .. izz``, column-major). (A service request is no message type a bag reader can rebuild; the
  standard message carries the same numbers.)

``franka_msgs`` is not among rosbags' bundled types: its goals are registered from their ``.msg`` text.
"""

from __future__ import annotations

import shutil
import tempfile
from pathlib import Path

import numpy as np

from cell.program import GripperStep, MotionPoints, Program, arm_limits, controller_joint_names, flange_frame

BAG_STORAGES = ("mcap", "sqlite3")
MCAP_FILE = "trajectory.mcap"  # storage "mcap": one file (ROS 2 Jazzy's default storage)
SQLITE3_FOLDER = "trajectory_bag"  # storage "sqlite3": a rosbag2 folder (ROS 2 Humble's default storage)
GRASP_TOPIC = "/franka_gripper/grasp/goal"
MOVE_TOPIC = "/franka_gripper/move/goal"
LOAD_TOPIC = "/service_server/set_load/request"
FRANKA_MSGS = {
    "franka_msgs/msg/GraspEpsilon": "float64 inner\nfloat64 outer\n",
    "franka_msgs/action/Grasp_Goal": "float64 width\nfranka_msgs/msg/GraspEpsilon epsilon\nfloat64 speed\n"
                                     "float64 force\n",
    "franka_msgs/action/Move_Goal": "float64 width\nfloat64 speed\n",
}


def trajectory_topic(robot: str) -> str:
    return f"/{arm_limits(robot).ros_arm_id}_arm_controller/joint_trajectory"


def typestore(storage: str = "mcap"):
    """rosbags' ROS 2 types (Jazzy's for MCAP, Humble's for sqlite3) with franka_msgs' gripper goals."""
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    store = get_typestore(Stores.ROS2_JAZZY if storage == "mcap" else Stores.ROS2_HUMBLE)
    types = {}
    for name, text in FRANKA_MSGS.items():
        types.update(get_types_from_msg(text, name))
    store.register(types)
    return store


def bag_messages(program: Program, samples: dict[str, np.ndarray], points: list[MotionPoints], store):
    """(topic, type name, time in ns from the program's start, message) in order: see the module's docstring."""
    t = store.types
    Duration, Time = t["builtin_interfaces/msg/Duration"], t["builtin_interfaces/msg/Time"]
    Header = t["std_msgs/msg/Header"]
    Trajectory, Point = t["trajectory_msgs/msg/JointTrajectory"], t["trajectory_msgs/msg/JointTrajectoryPoint"]
    Grasp, Epsilon, Move = (t["franka_msgs/action/Grasp_Goal"], t["franka_msgs/msg/GraspEpsilon"],
                            t["franka_msgs/action/Move_Goal"])
    Inertia, InertiaStamped, Vector3 = (t["geometry_msgs/msg/Inertia"], t["geometry_msgs/msg/InertiaStamped"],
                                        t["geometry_msgs/msg/Vector3"])
    names = controller_joint_names(program.robot)
    by_step = {m.step: m for m in points}
    starts_ns = np.concatenate([[0], np.cumsum(program.step_cycles())]) * 1_000_000
    messages = []
    for index, step in enumerate(program.steps):
        start = int(starts_ns[index])
        if not isinstance(step, GripperStep):
            motion = by_step[index]
            rows = motion.rows
            message = Trajectory(Header(Time(0, 0), ""), list(names), [
                Point(np.array(samples["q"][r], dtype=np.float64), np.array(samples["qd"][r], dtype=np.float64),
                      np.array(samples["qdd"][r], dtype=np.float64), np.zeros(0, dtype=np.float64),
                      Duration(int(ns // 1_000_000_000), int(ns % 1_000_000_000)))
                for r, ns in zip(rows, motion.time_from_start_ns())])
            messages.append((trajectory_topic(program.robot), Trajectory.__msgtype__, start, message))
            continue
        if step.kind == "grasp":
            messages.append((GRASP_TOPIC, Grasp.__msgtype__, start,
                             Grasp(step.goal_width_m, Epsilon(step.epsilon_inner_m, step.epsilon_outer_m),
                                   step.speed_m_s, step.force_n)))
        else:
            messages.append((MOVE_TOPIC, Move.__msgtype__, start, Move(step.goal_width_m, step.speed_m_s)))
        if step.load is not None:
            end = int(starts_ns[index + 1])
            (ixx, ixy, ixz), (_, iyy, iyz), (_, _, izz) = step.load.inertia_kg_m2
            stamp = Time(end // 1_000_000_000, end % 1_000_000_000)
            messages.append((LOAD_TOPIC, InertiaStamped.__msgtype__, end, InertiaStamped(
                Header(stamp, flange_frame(program.robot)),
                Inertia(step.load.mass_kg, Vector3(*step.load.flange_from_com_m), ixx, ixy, ixz, iyy, iyz, izz))))
    return messages


def write_bag(program: Program, samples: dict[str, np.ndarray], points: list[MotionPoints], folder: Path,
              storage: str = "mcap") -> Path:
    """Write the program's bag into ``folder``: ``trajectory.mcap`` (storage "mcap", a rosbag2 MCAP file) or the
    rosbag2 folder ``trajectory_bag`` (storage "sqlite3"); returns its path. ``samples``:
    ``program.sample(CSV_RATE_HZ)``, ``points``: the motions' checked points (:func:`cell.program.motion_points`)."""
    from rosbags.rosbag2 import StoragePlugin, Writer

    if storage not in BAG_STORAGES:
        raise ValueError(f"bag storage must be one of {', '.join(BAG_STORAGES)}, got {storage!r}")
    store = typestore(storage)
    messages = bag_messages(program, samples, points, store)
    with tempfile.TemporaryDirectory(dir=folder, prefix=".bag-") as scratch:
        name = "trajectory" if storage == "mcap" else SQLITE3_FOLDER
        bag = Path(scratch) / name
        plugin, version = (StoragePlugin.MCAP, 9) if storage == "mcap" else (StoragePlugin.SQLITE3, 8)
        with Writer(bag, version=version, storage_plugin=plugin) as writer:
            connections = {}
            for topic, msgtype, time_ns, message in messages:
                if topic not in connections:
                    connections[topic] = writer.add_connection(topic, msgtype, typestore=store)
                writer.write(connections[topic], time_ns, store.serialize_cdr(message, msgtype))
        if storage == "mcap":
            target = folder / MCAP_FILE
            shutil.move(str(bag / f"{name}.mcap"), target)
        else:
            target = folder / SQLITE3_FOLDER
            shutil.move(str(bag), target)
    return target
