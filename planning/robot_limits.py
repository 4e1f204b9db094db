"""Franka's published limits for the arms the cell plans for: what a real controller accepts.

The simulation model (pybullet_data's ``franka_panda/panda.urdf``) has wider joint ranges than a real arm (its joint
4 reaches -3.1416 rad where a Panda stops at -3.0718), so a program planned within the URDF alone can abort on the
robot. Everything that reaches the exported program (inverse kinematics, the motion planner, Ruckig's timing and
the export check) takes its limits from here; the URDF only bounds what the simulator can show.

Units: radians, rad/s, rad/s^2, rad/s^3, N m, kg. Joints 1-7 in order.

- Panda (Franka Emika Robot, "FER"): Franka's datasheet and libfranka's documented limits; franka_ros2 names its
  joints ``fer_joint1..7``.
- FR3 (Franka Research 3): its own datasheet; franka_ros2 names its joints ``fr3_joint1..7``. Its kinematics
  (Denavit-Hartenberg parameters) are the Panda's, so the cell simulates it with the Panda's model and plans it
  within the FR3's own ranges.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

# the planner keeps every configuration, and Ruckig every sample, at least this far inside a datasheet position
# range: a controller's own tracking error near a range's end then does not trip the arm's limit monitor
DATASHEET_MARGIN_RAD = 0.01


@dataclass(frozen=True)
class RobotLimits:
    """One arm's published limits. ``model``: the name used in scene files (``[robot] model``); ``ros_arm_id``: the
    arm's id in franka_ros2, which names its joints ``<id>_joint1..7`` and its flange ``<id>_link8``; arrays (7,)
    float64 in joint order."""

    model: str
    description: str
    ros_arm_id: str
    lower_rad: np.ndarray
    upper_rad: np.ndarray
    velocity_rad_s: np.ndarray
    acceleration_rad_s2: np.ndarray
    jerk_rad_s3: np.ndarray
    torque_nm: np.ndarray
    payload_kg: float

    @property
    def ros_joint_names(self) -> tuple[str, ...]:
        return tuple(f"{self.ros_arm_id}_joint{k}" for k in range(1, 8))

    @property
    def ros_flange_frame(self) -> str:
        return f"{self.ros_arm_id}_link8"

    def planning_range(self, sim_lower_rad: np.ndarray, sim_upper_rad: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(lower, upper) rad: the datasheet range less :data:`DATASHEET_MARGIN_RAD` at each end, within the
        simulation model's range (``sim_lower_rad``, ``sim_upper_rad``, from its URDF) too."""
        lower = np.maximum(self.lower_rad + DATASHEET_MARGIN_RAD, np.asarray(sim_lower_rad, dtype=np.float64))
        upper = np.minimum(self.upper_rad - DATASHEET_MARGIN_RAD, np.asarray(sim_upper_rad, dtype=np.float64))
        if np.any(lower >= upper):
            raise ValueError(f"{self.model}: its datasheet ranges and the simulation model's do not overlap")
        return lower, upper


def _array(values) -> np.ndarray:
    array = np.array(values, dtype=np.float64)
    array.setflags(write=False)
    return array


PANDA = RobotLimits(
    model="panda",
    description="Franka Emika Panda (FER)",
    ros_arm_id="fer",  # Franka Emika Robot
    lower_rad=_array([-2.8973, -1.7628, -2.8973, -3.0718, -2.8973, -0.0175, -2.8973]),
    upper_rad=_array([2.8973, 1.7628, 2.8973, -0.0698, 2.8973, 3.7525, 2.8973]),
    velocity_rad_s=_array([2.175, 2.175, 2.175, 2.175, 2.61, 2.61, 2.61]),
    acceleration_rad_s2=_array([15.0, 7.5, 10.0, 12.5, 15.0, 20.0, 20.0]),
    jerk_rad_s3=_array([7500.0, 3750.0, 5000.0, 6250.0, 7500.0, 10000.0, 10000.0]),
    torque_nm=_array([87.0, 87.0, 87.0, 87.0, 12.0, 12.0, 12.0]),
    payload_kg=3.0,
)

FR3 = RobotLimits(
    model="fr3",
    description="Franka Research 3 (FR3)",
    ros_arm_id="fr3",
    lower_rad=_array([-2.7437, -1.7837, -2.9007, -3.0421, -2.8065, 0.5445, -3.0159]),
    upper_rad=_array([2.7437, 1.7837, 2.9007, -0.1518, 2.8065, 4.5169, 3.0159]),
    velocity_rad_s=_array([2.62, 2.62, 2.62, 2.62, 5.26, 4.18, 5.26]),
    acceleration_rad_s2=_array([10.0] * 7),
    jerk_rad_s3=_array([5000.0] * 7),
    torque_nm=_array([87.0, 87.0, 87.0, 87.0, 12.0, 12.0, 12.0]),
    payload_kg=3.0,
)

ROBOT_MODELS: dict[str, RobotLimits] = {limits.model: limits for limits in (PANDA, FR3)}


def robot_limits(model: str) -> RobotLimits:
    """The limits of ``model`` (``panda`` or ``fr3``); a KeyError naming the known models otherwise."""
    try:
        return ROBOT_MODELS[model]
    except KeyError:
        raise KeyError(f"unknown robot model {model!r}; known: {', '.join(sorted(ROBOT_MODELS))}") from None


__all__ = ["DATASHEET_MARGIN_RAD", "FR3", "PANDA", "ROBOT_MODELS", "RobotLimits", "robot_limits"]
