"""Path timing against TOPP-RA 0.6.10 and against stopping at every waypoint, on planned pick-and-place paths.

    python -m benchmarks.timing --queries 60 --seed 0

Paths: the queries of ``benchmarks/motion.py`` (same seed, same objects; ends kept when free in our collision
model), planned by ``planning.motion.plan_joint_path`` with ``RobotCollisionChecker.segment_valid``. Every path is
timed four ways with the Panda's limits (``cell.robot``: velocity, acceleration and, for Ruckig, jerk):

- ours: ``planning.timing.time_path`` with the query's collision check (``RobotCollisionChecker.first_invalid``:
  blends at the waypoints, re-checked every 4 ms, slower blends and finally stops where a blend would collide),
  jerk-limited;
- rest-to-rest: Ruckig from waypoint to waypoint, stopping at each (``time_waypoints`` with zero via velocities);
- TOPP-RA: time-optimal under velocity and acceleration limits (no jerk limit) along a cubic spline through the
  waypoints (chord-length parameter, not-a-knot ends: what MPlib does after planning, with a better parameter),
  ``ParametrizeConstAccel``. The spline is not the planned polyline: its largest joint-space distance from the
  polyline is reported, and whether it collides (every 4 ms of the TOPP-RA trajectory, contact in our collision
  model without the clearances our planner keeps: ``benchmarks.motion.OurPlanner.touches``);
- TOPP-RA on the polyline itself: a corner can only be passed at rest without jerk or blend, so each straight
  segment is timed rest-to-rest by TOPP-RA and the durations are summed (the time-optimal "stop at every
  waypoint" without jerk limit).

Ours is checked independently at 1 kHz: finite-difference velocity, acceleration and jerk against the limits
(1 % tolerance for the differencing), start and end at rest on the first and last waypoint.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import time
from pathlib import Path

import numpy as np

from benchmarks.motion import OurPlanner, Query, build_queries
from cell.robot import ACCELERATION_LIMITS, JERK_LIMITS, VELOCITY_LIMITS
from cell.scene import load_scene
from planning.timing import JointLimits, time_path, time_waypoints

LIMITS = JointLimits(VELOCITY_LIMITS, ACCELERATION_LIMITS, JERK_LIMITS)
LOWER = np.array([-2.9671, -1.8326, -2.9671, -3.1416, -2.9671, -0.0873, -2.9671])  # panda.urdf, rad
UPPER = np.array([2.9671, 1.8326, 2.9671, 0.0, 2.9671, 3.8223, 2.9671])
RATE_HZ = 1000.0


def toppra_spline(waypoints: np.ndarray, limits: JointLimits):
    """TOPP-RA along a cubic spline through ``waypoints`` (K, 7): (trajectory, spline path)."""
    import toppra as ta
    from toppra import algorithm, constraint

    chord = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(waypoints, axis=0), axis=1))])
    path = ta.SplineInterpolator(chord / chord[-1], waypoints)
    velocity = constraint.JointVelocityConstraint(np.stack([-limits.velocity, limits.velocity], axis=1))
    acceleration = constraint.JointAccelerationConstraint(np.stack([-limits.acceleration, limits.acceleration],
                                                                   axis=1))
    instance = algorithm.TOPPRA([velocity, acceleration], path, parametrizer="ParametrizeConstAccel")
    return instance.compute_trajectory(0.0, 0.0), path


def toppra_polyline_s(waypoints: np.ndarray, limits: JointLimits) -> float:
    """Seconds to follow the polyline exactly with TOPP-RA, at rest at every corner (segment by segment)."""
    return float(sum(toppra_spline(np.stack([a, b]), limits)[0].duration
                     for a, b in zip(waypoints[:-1], waypoints[1:])))


def jerk_limited(timed, waypoints: np.ndarray, limits: JointLimits) -> tuple[bool, float]:
    """Whether the timed motion, sampled at 1 kHz, keeps velocity, acceleration and jerk within the limits (first,
    second and third finite differences of the positions alone, 1 % tolerance) and starts and ends at rest on the
    path's ends; and its largest jerk as a fraction of the limit."""
    t, q, qd, _ = timed.sample(RATE_HZ)
    dt = float(np.median(np.diff(t)))
    velocity = np.diff(q, axis=0) / dt
    acceleration = np.diff(q, n=2, axis=0) / dt**2
    jerk = np.diff(q, n=3, axis=0) / dt**3
    ok = (np.all(np.abs(velocity) <= limits.velocity * 1.01) and np.all(np.abs(acceleration) <= limits.acceleration
                                                                         * 1.01)
          and np.all(np.abs(jerk) <= limits.jerk * 1.01)
          and np.allclose(q[[0, -1]], waypoints[[0, -1]], atol=1e-6) and np.allclose(qd[[0, -1]], 0.0, atol=1e-6))
    return bool(ok), float((np.abs(jerk) / limits.jerk).max())


def distance_to_polyline(points: np.ndarray, waypoints: np.ndarray) -> float:
    """Largest joint-space distance (rad) from ``points`` (N, 7) to the polyline through ``waypoints``."""
    best = np.full(len(points), np.inf)
    for a, b in zip(waypoints[:-1], waypoints[1:]):
        direction = b - a
        s = np.clip((points - a) @ direction / max(float(direction @ direction), 1e-12), 0.0, 1.0)
        best = np.minimum(best, np.linalg.norm(points - (a + s[:, None] * direction), axis=1))
    return float(best.max())


def time_one(query: Query, path: np.ndarray, ours: OurPlanner) -> dict:
    ours.set_world(query.obstacles, query.held, query.opening_m)
    start = time.perf_counter()
    timed = time_path(path, LIMITS, first_invalid=ours.checker.first_invalid)
    seconds = time.perf_counter() - start
    stopping = time_waypoints(path, LIMITS, np.zeros_like(path))
    limited, jerk_fraction = jerk_limited(timed, path, LIMITS)
    _, q_ours, _, _ = timed.sample(RATE_HZ)
    record = {"query": query.name, "waypoints": len(path), "ours_s": timed.duration, "rest_to_rest_s":
              stopping.duration, "ours_compute_s": seconds, "ours_jerk_limited": limited,
              "ours_max_jerk_fraction": jerk_fraction, "ours_deviation_rad": distance_to_polyline(q_ours, path),
              "ours_stops": int(np.sum(~np.any(timed.via_velocities[1:-1], axis=1)))}
    trajectory, spline = toppra_spline(path, LIMITS)
    times = np.arange(0.0, trajectory.duration, 1.0 / RATE_HZ)
    samples = trajectory(times)
    record.update({
        "toppra_s": float(trajectory.duration),
        "toppra_polyline_s": toppra_polyline_s(path, LIMITS),
        "toppra_max_jerk_fraction": float((np.abs(np.diff(samples, n=3, axis=0)) * RATE_HZ**3 / LIMITS.jerk).max()),
        "toppra_deviation_rad": distance_to_polyline(spline(np.linspace(0.0, 1.0, 2000)), path),
        # every 4 ms, contact in our model without the clearances its planner keeps (OurPlanner.touches)
        "toppra_collides": any(ours.touches(q) for q in samples[::4]),
    })
    return record


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--queries", type=int, default=60)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--time-limit", type=float, default=5.0, help="planning time limit per query (s)")
    parser.add_argument("--json", type=Path, help="write per-path results here")
    args = parser.parse_args(argv)
    import toppra as ta

    ta.setup_logging("WARNING")
    scene = load_scene()
    ours = OurPlanner(scene, LOWER, UPPER, args.time_limit, args.seed)
    print(f"machine: {platform.machine()}, {os.cpu_count()} cores, Python {platform.python_version()}; seed "
          f"{args.seed}", flush=True)
    queries, skipped = build_queries(scene, [ours], args.seed, args.queries)
    records = []
    for query in queries:
        ours.set_world(query.obstacles, query.held, query.opening_m)
        path = ours.plan(query)
        if path is None:
            print(f"{query.name}: no path", flush=True)
            continue
        record = time_one(query, path, ours)
        records.append(record)
        print(f"{query.name:55s} {len(path):2d} wp  ours {record['ours_s']:5.2f} s  rest "
              f"{record['rest_to_rest_s']:5.2f}  TOPP-RA {record['toppra_s']:5.2f} (polyline "
              f"{record['toppra_polyline_s']:5.2f})  ratio {record['ours_s'] / record['toppra_s']:4.2f}  "
              f"jerk-limited {record['ours_jerk_limited']}", flush=True)
    ours_s = np.array([r["ours_s"] for r in records])
    ratio = ours_s / np.array([r["toppra_s"] for r in records])
    ratio_polyline = ours_s / np.array([r["toppra_polyline_s"] for r in records])
    ratio_rest = ours_s / np.array([r["rest_to_rest_s"] for r in records])
    multi = np.array([r["waypoints"] > 2 for r in records])
    print(f"\npaths: {len(records)} ({multi.sum()} with interior waypoints)")
    print("| ours / reference | median | worst | median, paths with interior waypoints | worst, those |")
    print("|---|---|---|---|---|")
    for label, values in (("TOPP-RA (spline through the waypoints)", ratio),
                          ("TOPP-RA on the polyline (rest at corners)", ratio_polyline),
                          ("Ruckig rest-to-rest at every waypoint", ratio_rest)):
        inner = values[multi] if multi.any() else np.array([np.nan])
        print(f"| {label} | {np.median(values):.3f} | {values.max():.3f} | {np.median(inner):.3f} | "
              f"{inner.max():.3f} |")
    print(f"\nours jerk-limited (1 kHz finite differences): {sum(r['ours_jerk_limited'] for r in records)}/"
          f"{len(records)}; largest jerk {max(r['ours_max_jerk_fraction'] for r in records):.2f} x limit; "
          f"TOPP-RA's largest jerk {max(r['toppra_max_jerk_fraction'] for r in records):.1f} x limit (finite "
          "differences at 1 kHz; its acceleration jumps)")
    print(f"ours leaves the polyline by up to {max(r['ours_deviation_rad'] for r in records):.3f} rad (median "
          f"{np.median([r['ours_deviation_rad'] for r in records]):.3f}); total duration of all paths: ours "
          f"{sum(r['ours_s'] for r in records):.1f} s, TOPP-RA {sum(r['toppra_s'] for r in records):.1f} s, "
          f"rest-to-rest {sum(r['rest_to_rest_s'] for r in records):.1f} s")
    print(f"TOPP-RA's spline leaves the polyline by up to {max(r['toppra_deviation_rad'] for r in records):.3f} rad "
          f"(median {np.median([r['toppra_deviation_rad'] for r in records]):.3f}); collides on "
          f"{sum(r['toppra_collides'] for r in records)}/{len(records)} paths")
    print(f"ours: stops at {sum(r['ours_stops'] for r in records)} of "
          f"{sum(r['waypoints'] - 2 for r in records)} interior waypoints; timing took median "
          f"{1000 * np.median([r['ours_compute_s'] for r in records]):.0f} ms per path (dense re-check included)")
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps({"seed": args.seed, "records": records, "skipped": skipped}, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
