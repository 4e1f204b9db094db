"""Training-data throughput: samples (rendered 224x224 views with their labels) per second.

    python benchmarks/dataset_build.py --category chair --level 3 --count 60 --views 4 --workers 2

Builds into a temporary folder (nothing is kept) and prints one line per category plus a Markdown row for
benchmarks/RESULTS.md. Target (issue 2): >= 10 samples/s on 2 cores.
"""

from __future__ import annotations

import argparse
import os
import platform
import tempfile
from pathlib import Path

from perception.dataset.build import BuildConfig, build


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--category", nargs="+", default=["chair", "table", "cabinet"])
    parser.add_argument("--level", default="3", choices=["3", "mixed"])
    parser.add_argument("--count", type=int, default=60, help="objects per category")
    parser.add_argument("--views", type=int, default=4)
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--seed", type=int, default=1000)
    args = parser.parse_args()
    print(f"machine: {platform.processor() or platform.machine()}, {os.cpu_count()} cores, "
          f"{args.workers} workers, {args.count} objects x {args.views} views per category")
    rows = []
    for category in args.category:
        config = BuildConfig(category, args.level, args.count, args.views, args.seed)
        with tempfile.TemporaryDirectory() as tmp:
            stats = build(config, Path(tmp) / "data", workers=args.workers, progress=False)
            size_mb = sum(f.stat().st_size for f in Path(tmp).rglob("*.npz")) / 1e6
        per_sample_kb = 1000 * size_mb / max(stats["samples_built"], 1)
        print(f"{category:8s} level {args.level}: {stats['samples_per_second']:.1f} samples/s "
              f"({stats['samples_built']} samples in {stats['seconds']:.1f} s, {per_sample_kb:.0f} kB/sample)")
        rows.append(f"| {category} | {args.level} | {args.views} | {args.workers} | "
                    f"{stats['samples_per_second']:.1f} | {per_sample_kb:.0f} |")
    print("\n| category | level | views/object | workers | samples/s | kB/sample |\n|---|---|---|---|---|---|")
    print("\n".join(rows))


if __name__ == "__main__":
    main()
