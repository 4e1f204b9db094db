"""Inverse kinematics of the Panda's TCP (``cell.robot.Panda.inverse_tcp``): CPU time per solve, success, accuracy.

    python benchmarks/inverse_kinematics.py --targets 60 --seed 0
    python benchmarks/inverse_kinematics.py --random-poses 300 --seed 0

Targets are the TCP poses of random configurations inside 60% of the joint ranges (seeded); each solve starts from
its target's configuration disturbed by 0.05 rad per joint (seeded), as the planner's straight lines and kitting
seed theirs. Prints solved/targets, mean CPU milliseconds per solve and the largest position error of a solution.

``--random-poses N`` asks instead for N poses drawn uniformly around the arm (positions within 0.9 m of the
shoulder, any orientation; seeded), each from the home configuration, as the kitting's queries for grasps at a
pick or a target are: many of them are out of reach. Prints how many were solved and the mean CPU milliseconds of
a solve and of a refusal.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path[:] = [p for p in sys.path if Path(p or ".").resolve() != Path(__file__).resolve().parent]
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from cell.bullet import BulletClient  # noqa: E402
from cell.robot import IKError, Panda  # noqa: E402
from cell.scene import load_scene  # noqa: E402
from planning.panda_ik import SHOULDER_HEIGHT_M  # noqa: E402
from planning.pose import Pose  # noqa: E402


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--targets", type=int, default=60)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--random-poses", type=int, default=0, help="poses around the arm, from home (see above)")
    args = parser.parse_args()
    rng = np.random.default_rng(args.seed)
    with BulletClient() as client:
        panda = Panda(client, Pose.identity())
        if args.random_poses:
            return _random_poses(panda, rng, args.random_poses)
        cases = []
        for _ in range(args.targets):
            q = rng.uniform(0.6 * panda.lower_limits, 0.6 * panda.upper_limits)
            cases.append((panda.forward_tcp(q), q + rng.normal(0.0, 0.05, 7)))
        started, errors = time.process_time(), []
        for world_from_tcp, seed_q in cases:
            try:
                q = panda.inverse_tcp(world_from_tcp, rng, seed_q=seed_q)
            except IKError:
                continue
            errors.append(panda.forward_tcp(q).distance(world_from_tcp)[0])
        cpu_ms = 1000.0 * (time.process_time() - started) / len(cases)
    print(f"{len(errors)}/{len(cases)} solved, {cpu_ms:.1f} ms CPU per solve, largest position error "
          f"{1000.0 * max(errors, default=float('nan')):.4f} mm")
    return 0


def _random_poses(panda: Panda, rng: np.random.Generator, count: int) -> int:
    home = np.array(load_scene().robot.home_q)
    shoulder = np.array([0.0, 0.0, SHOULDER_HEIGHT_M])
    poses = []
    while len(poses) < count:
        position = shoulder + rng.uniform(-0.9, 0.9, 3)
        if np.linalg.norm(position - shoulder) <= 0.9 and position[2] >= 0.0:
            poses.append(Pose(position, rng.normal(size=4)))
    solved, refused = [], []
    for pose in poses:
        started = time.process_time()
        try:
            panda.inverse_tcp(pose, rng, seed_q=home)
            solved.append(time.process_time() - started)
        except IKError:
            refused.append(time.process_time() - started)
    print(f"{len(solved)}/{count} solved; mean CPU {1000.0 * np.mean(solved):.1f} ms per solve, "
          f"{1000.0 * np.mean(refused):.1f} ms per refusal")
    return 0


if __name__ == "__main__":
    sys.exit(main())
