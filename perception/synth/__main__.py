"""Command line: write procedurally generated furniture as assembly folders.

    python -m perception.synth --category chair --level 3 --count 100 --seed 0 --out data/synth

writes ``<out>/<category>_<level>_s<seed>_<index:05d>/``; object ``i`` is drawn from
``np.random.default_rng([seed, i])``, so it is the same whatever ``--count`` is. Existing object folders are
refused unless ``--overwrite``. Bad arguments exit with status 2.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from perception.synth import CATEGORIES, LEVELS, generate
from planning.assembly import write_assembly


def _positive_int(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not an integer") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be at least 1, got {value}")
    return value


def _seed(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not an integer") from None
    if value < 0:
        raise argparse.ArgumentTypeError(f"must be a non-negative integer, got {value}")
    return value


def folder_name(category: str, level: str, seed: int, index: int) -> str:
    return f"{category}_{level}_s{seed}_{index:05d}"


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="python -m perception.synth",
        description="Write procedurally generated table-top furniture as assembly folders.",
    )
    parser.add_argument("--category", required=True, choices=CATEGORIES, help="kind of furniture")
    parser.add_argument(
        "--level", required=True, choices=LEVELS, help="3: finest parts; mixed: merged groups"
    )
    parser.add_argument("--count", required=True, type=_positive_int, help="number of objects to write")
    parser.add_argument("--seed", required=True, type=_seed, help="object i uses default_rng([seed, i])")
    parser.add_argument("--out", required=True, type=Path, help="folder to write the object folders into")
    parser.add_argument("--overwrite", action="store_true", help="replace object folders that already exist")
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    names = [folder_name(args.category, args.level, args.seed, i) for i in range(args.count)]
    if args.out.exists() and not args.out.is_dir():
        parser.error(f"--out {args.out} exists and is not a folder")
    if not args.overwrite:
        existing = [n for n in names if (args.out / n).exists()]
        if existing:
            more = f" and {len(existing) - 1} more" if len(existing) > 1 else ""
            parser.error(f"{args.out / existing[0]}{more} already exist(s); pass --overwrite to replace them")
    for i, name in enumerate(names):
        assembly = generate(args.category, args.level, np.random.default_rng([args.seed, i]), name)
        folder = write_assembly(assembly, args.out / name, overwrite=args.overwrite)
        print(f"{folder}  {len(assembly.parts)} parts", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
