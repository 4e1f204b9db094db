"""``python -m perception.dataset build --category chair --level 3 --count N --views K --seed S --out DIR``
``python -m perception.dataset slim DIR --points 256 --out SLIM_DIR`` (a training-only copy to ship elsewhere)"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from cell.render import MATERIALS
from perception.dataset.build import BuildConfig, build


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m perception.dataset", description=__doc__)
    commands = parser.add_subparsers(dest="command", required=True)
    b = commands.add_parser("build", help="generate, render and store procedural training objects")
    b.add_argument("--category", required=True, choices=["chair", "table", "cabinet"])
    b.add_argument("--level", required=True, choices=["3", "mixed"])
    b.add_argument("--count", type=int, required=True, help="number of objects")
    b.add_argument("--views", type=int, default=4, help="rendered views per object (samples = count x views)")
    b.add_argument("--seed", type=int, default=0)
    b.add_argument("--out", type=Path, required=True)
    b.add_argument("--workers", type=int, default=1)
    b.add_argument("--renderer", choices=["tiny", "egl", "auto"], default="tiny")
    b.add_argument("--stretch", type=float, default=1.0, help="scale each object by a random factor in "
                   "[1/STRETCH, STRETCH] along each axis before rendering (1: the generator's proportions)")
    b.add_argument("--materials", choices=[*MATERIALS, "mixed"], default="parts",
                   help="parts: a colour per part; one: one shared material; few: two or three; mixed: each object "
                   "one of these (half with a colour per part)")
    s = commands.add_parser("slim", help="a training-only copy: the arrays training reads, each part cloud cut to "
                            "its first --points points, quantised to int8 (to ship a dataset to a GPU machine)")
    s.add_argument("source", type=Path, help="a folder made by build")
    s.add_argument("--points", type=int, required=True,
                   help="points kept per part: at least the config's model.encoder_points and loss.points")
    s.add_argument("--count", type=int, help="only the objects of index below COUNT: the objects that build "
                   "--count COUNT makes")
    s.add_argument("--out", type=Path, required=True)
    args = parser.parse_args(argv)
    if args.command == "slim":
        return _slim(args)
    for name in ("count", "views", "workers"):
        if getattr(args, name) < 1:
            parser.error(f"--{name} must be at least 1, got {getattr(args, name)}")
    if not args.stretch >= 1.0 or args.stretch == float("inf"):
        parser.error(f"--stretch must be a finite number of at least 1, got {args.stretch}")
    config = BuildConfig(args.category, args.level, args.count, args.views, args.seed, args.renderer, args.stretch,
                         args.materials)
    try:
        stats = build(config, args.out, workers=args.workers)
    except ValueError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    print(f"{stats['objects_built']} objects ({stats['samples_built']} samples) in {stats['seconds']:.1f} s: "
          f"{stats['samples_per_second']:.1f} samples/s -> {args.out}")
    return 0


def _slim(args: argparse.Namespace) -> int:
    from perception.dataset.slim import slim_dataset

    try:
        stats = slim_dataset(args.source, args.out, args.points, args.count)
    except (ValueError, OSError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    print(f"{stats['objects']} objects: {stats['source_mb']:.1f} MB -> {stats['slim_mb']:.1f} MB in {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
