"""Exported programs as a controller receives and plays them, checked against Franka's published limits.

    python -m benchmarks.controller_replay OUT_FOLDER [OUT_FOLDER ...] [--json results.json]

For each output folder of ``python -m cell.run`` (``trajectory.csv``, ``trajectory.mcap``):

- the bag read back with rosbags: every ``JointTrajectory`` point against the CSV row at its time stamp (exact, at
  the CSV's 9 decimals), counted as mismatches;
- each trajectory played back as ros2_control's ``joint_trajectory_controller`` plays it
  (``planning.controller_replay.replay``: its spline between the points, commanded at 1 kHz);
- on the CSV and on that playback: the smallest distance to the datasheet position ranges (rad; negative: outside),
  and the peaks of velocity, acceleration and jerk (the commanded acceleration's change per 1 ms cycle; the CSV's
  by finite differences) as fractions of the published limits, and how far the playback strays from the CSV (rad).

The limits are written out here (Franka's datasheets for the Panda / FER and the FR3, chosen by the program's
``robot``), not taken from the code under test.
"""

from __future__ import annotations

import argparse
import csv
import json
from pathlib import Path

import numpy as np

# per robot model (program.json's "robot"): lower, upper (rad), velocity, acceleration, jerk (rad/s^n)
DATASHEETS = {
    "panda": (np.array([-2.8973, -1.7628, -2.8973, -3.0718, -2.8973, -0.0175, -2.8973]),
              np.array([2.8973, 1.7628, 2.8973, -0.0698, 2.8973, 3.7525, 2.8973]),
              np.array([2.175, 2.175, 2.175, 2.175, 2.61, 2.61, 2.61]),
              np.array([15.0, 7.5, 10.0, 12.5, 15.0, 20.0, 20.0]),
              np.array([7500.0, 3750.0, 5000.0, 6250.0, 7500.0, 10000.0, 10000.0])),
    "fr3": (np.array([-2.7437, -1.7837, -2.9007, -3.0421, -2.8065, 0.5445, -3.0159]),
            np.array([2.7437, 1.7837, 2.9007, -0.1518, 2.8065, 4.5169, 3.0159]),
            np.array([2.62, 2.62, 2.62, 2.62, 5.26, 4.18, 5.26]),
            np.full(7, 10.0),
            np.full(7, 5000.0)),
}


def measure(folder: Path) -> dict:
    from rosbags.highlevel import AnyReader

    from planning.controller_replay import ControllerTrajectory, replay

    robot = json.loads((folder / "program.json").read_text())["robot"]
    LOWER, UPPER, VELOCITY, ACCELERATION, JERK = DATASHEETS[robot]  # noqa: N806 (the datasheet's constants)
    with open(folder / "trajectory.csv", newline="") as handle:
        table = np.array(list(csv.reader(handle))[1:], dtype=np.float64)
    q, qd, qdd = table[:, 1:8], table[:, 8:15], table[:, 15:22]
    result = {"folder": str(folder), "robot": robot, "duration_s": float(table[-1, 0]), "motions": 0, "points": 0,
              "mismatches": 0,
              "csv": {"margin_rad": float(np.min([q - LOWER, UPPER - q])),
                      "velocity": float((np.abs(qd) / VELOCITY).max()),
                      "acceleration": float((np.abs(qdd) / ACCELERATION).max()),
                      "jerk": float((np.abs(np.diff(qdd, axis=0)) * 1000.0 / JERK).max())},
              "playback": {"margin_rad": np.inf, "velocity": 0.0, "acceleration": 0.0, "jerk": 0.0,
                           "deviation_rad": 0.0}}
    playback = result["playback"]
    with AnyReader([folder / "trajectory.mcap"]) as reader:
        for connection, stamp, raw in reader.messages():
            if connection.msgtype != "trajectory_msgs/msg/JointTrajectory":
                continue
            message = reader.deserialize(raw, connection.msgtype)
            ns = np.array([p.time_from_start.sec * 10 ** 9 + p.time_from_start.nanosec for p in message.points])
            rows = (stamp + ns) // 10 ** 6
            points = [np.array([getattr(p, name) for p in message.points])
                      for name in ("positions", "velocities", "accelerations")]
            result["motions"] += 1
            result["points"] += len(rows)
            result["mismatches"] += int(sum(np.any(np.round(values, 9) != table[rows, columns], axis=1).sum()
                                            for values, columns in zip(points, (slice(1, 8), slice(8, 15),
                                                                                slice(15, 22)))))
            played = replay(ControllerTrajectory(ns / 1e9, *points))
            own = q[rows[0]:rows[0] + len(played["q"])]
            playback["margin_rad"] = min(playback["margin_rad"],
                                         float(np.min([played["q"] - LOWER, UPPER - played["q"]])))
            for key, name, limit in (("qd", "velocity", VELOCITY), ("qdd", "acceleration", ACCELERATION),
                                     ("jerk", "jerk", JERK)):
                playback[name] = max(playback[name], float((np.abs(played[key]) / limit).max()))
            playback["deviation_rad"] = max(playback["deviation_rad"], float(np.abs(played["q"] - own).max()))
    return result


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("folders", type=Path, nargs="+")
    parser.add_argument("--json", type=Path, help="write the measurements here")
    args = parser.parse_args()
    results = []
    print("folder | s | motions | points/s | bag != csv | margin csv / playback (rad) | velocity, acceleration, "
          "jerk of the limits, csv / playback | playback off the csv (rad)")
    for folder in args.folders:
        r = measure(folder)
        results.append(r)
        c, p = r["csv"], r["playback"]
        print(f"{folder.name} | {r['duration_s']:.1f} | {r['motions']} | {r['points'] / r['duration_s']:.0f} | "
              f"{r['mismatches']} | {c['margin_rad']:.4f} / {p['margin_rad']:.4f} | "
              f"{c['velocity']:.3f} {c['acceleration']:.3f} {c['jerk']:.3f} / "
              f"{p['velocity']:.3f} {p['acceleration']:.3f} {p['jerk']:.3f} | {p['deviation_rad']:.1e}")
    if args.json:
        args.json.write_text(json.dumps(results, indent=1) + "\n")


if __name__ == "__main__":
    main()
