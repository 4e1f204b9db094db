"""What running jobs side by side costs on this machine, apart from any batch tooling: the ceiling of a batch's
speed-up.

    python benchmarks/cores_side_by_side.py [--workers 2] [--seconds 20]

Two fixed workloads, each first alone in one process, then as ``--workers`` copies in as many processes at once;
the wall time of each copy against the time alone is the slowdown, and ``workers / slowdown`` the most any batch of
such jobs can gain:

- ``interpreter``: Python loops over small numpy arrays and dictionaries (most of a ``cell.run`` job: planning,
  collision queries, the simulator's stepping);
- ``memory``: sums over a 256 MB array (what shares the cores' caches and memory bandwidth).

Each workload is sized on the first run to take about ``--seconds`` alone. Prints a Markdown table.
"""

from __future__ import annotations

import argparse
import multiprocessing
import os
import platform
import time

import numpy as np


def interpreter(rounds: int) -> float:
    """Python loops over small arrays and a dictionary; returns a checksum (so nothing is optimised away)."""
    rng = np.random.default_rng(0)
    points = rng.random((64, 3))
    table: dict[int, float] = {}
    total = 0.0
    for k in range(rounds):
        moved = points @ np.eye(3) + k * 1e-6
        total += float(np.linalg.norm(moved[k % 64]))
        table[k % 4096] = total
    return total + len(table)


def memory(rounds: int) -> float:
    """Sums over a 256 MB array, read again each round."""
    data = np.ones(32 * 1024 * 1024, dtype=np.float64)
    return float(sum(data.sum() for _ in range(rounds)))


WORKLOADS = {"interpreter": (interpreter, 20_000), "memory": (memory, 4)}


def timed(name: str, rounds: int) -> float:
    start = time.perf_counter()
    WORKLOADS[name][0](rounds)
    return time.perf_counter() - start


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--seconds", type=float, default=20.0, help="each workload's time alone, about")
    args = parser.parse_args()
    print(f"machine: {platform.machine()}, {os.cpu_count()} cores, load {os.getloadavg()[0]:.1f}")
    print(f"\n| workload | alone s | {args.workers} side by side s, each | slowdown | most speed-up with "
          f"{args.workers} workers |\n|---|---|---|---|---|")
    with multiprocessing.get_context("spawn").Pool(args.workers) as pool:
        for name, (_, probe) in WORKLOADS.items():
            rounds = max(1, round(probe * args.seconds / pool.apply(timed, (name, probe))))
            alone = pool.apply(timed, (name, rounds))
            together = pool.starmap(timed, [(name, rounds)] * args.workers)
            slowdown = float(np.mean(together)) / alone
            print(f"| {name} | {alone:.1f} | {', '.join(f'{t:.1f}' for t in together)} | {slowdown:.3f}x | "
                  f"{args.workers / slowdown:.2f}x |", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
