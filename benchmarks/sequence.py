"""Assembly sequence planning with truth poses: success rate and planning time per object.

    python benchmarks/sequence.py --procedural 50 --furniture ../shared/furniture

Procedural objects are ``perception.synth`` objects ``default_rng([seed, i])`` for i < N, per category and level;
real objects are every assembly folder under ``--furniture``. All objects are planned one after another in one
process (seed 0, grasps checked); the time of an object is the wall time of ``plan_assembly_sequence`` on it,
generation and reading excluded. The last column is the median CPU time of the process over the same span, which
other work on a shared machine inflates less. Convex decompositions of non-convex meshes come from the disk cache
when present (decomposing a real mesh takes seconds, once). Prints a Markdown table for benchmarks/RESULTS.md,
the load average at the start and after each set, and names every failure with its reason.
Targets (issue 4): 100% procedural, >= 95% real; median <= 1 s and p95 <= 5 s per object.
"""

from __future__ import annotations

import argparse
import os
import platform
import sys
import time
from pathlib import Path

import numpy as np

# Run as a script, this file's folder comes first on sys.path, where a module named like a package would hide the
# perception package: look in the repository root instead.
sys.path[:] = [p for p in sys.path if Path(p or ".").resolve() != Path(__file__).resolve().parent]
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from perception.synth import generate  # noqa: E402
from planning.assembly import read_assembly  # noqa: E402
from planning.sequence import plan_assembly_sequence  # noqa: E402


def summarise(label: str, seconds: list[float], cpu_seconds: list[float], failures: list[tuple[str, str]],
              count: int) -> str:
    times = np.array(seconds)
    rate = (count - len(failures)) / count
    return (f"| {label} | {count} | {100 * rate:.0f}% | {np.median(times):.2f} | {np.percentile(times, 95):.2f} | "
            f"{times.max():.2f} | {np.median(cpu_seconds):.2f} |")


def run_set(label: str, assemblies, time_budget_s: float) -> tuple[str, list[tuple[str, str]]]:
    seconds, cpu_seconds, failures, count = [], [], [], 0
    for assembly in assemblies:
        start, start_cpu = time.perf_counter(), time.process_time()
        result = plan_assembly_sequence(assembly, seed=0, time_budget_s=time_budget_s)
        seconds.append(time.perf_counter() - start)
        cpu_seconds.append(time.process_time() - start_cpu)
        count += 1
        if not result.success:
            detail = "; ".join(f"{k}: {v}" for k, v in list(result.blocking.items())[:3])
            failures.append((assembly.name, f"{result.reason} [{detail}]"))
    row = summarise(label, seconds, cpu_seconds, failures, count)
    print(row, flush=True)
    _LOADS.append(f"{label}: {_load()}")
    return row, failures


_LOADS: list[str] = []


def _load() -> str:
    return " ".join(f"{v:.1f}" for v in os.getloadavg())


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--procedural", type=int, default=50, help="objects per category and level (0: none)")
    parser.add_argument("--seed", type=int, default=2024)
    parser.add_argument("--furniture", type=Path, help="folder of real assembly folders")
    parser.add_argument("--time-budget", type=float, default=10.0)
    args = parser.parse_args()
    print(f"machine: {platform.machine()}, {os.cpu_count()} cores, load average {_load()} (1, 5, 15 min); "
          f"time budget {args.time_budget:.0f} s per object\n")
    print("| set | objects | success | median s | p95 s | max s | median CPU s |\n|---|---|---|---|---|---|---|")
    failures = []
    if args.procedural > 0:
        for category in ("chair", "table", "cabinet"):
            for level in ("3", "mixed"):
                objects = (generate(category, level, np.random.default_rng([args.seed, i]),
                                    f"{category}_{level}_{i:03d}") for i in range(args.procedural))
                failures += run_set(f"{category} level {level}", objects, args.time_budget)[1]
    if args.furniture is not None:
        folders = sorted(p for p in args.furniture.iterdir() if (p / "assembly.json").is_file())
        failures += run_set("real furniture", (read_assembly(p) for p in folders), args.time_budget)[1]
    print("\nload average (1, 5, 15 min) after each set: " + "; ".join(_LOADS))
    if failures:
        print("\nfailures:")
        for name, reason in failures:
            print(f"- {name}: {reason}")


if __name__ == "__main__":
    main()
