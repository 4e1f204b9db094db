"""``python -m cell.run``: one picture and a folder of loose parts in, a verified robot assembly program out.

    python -m cell.run --image scenes/chair/chair.png --parts scenes/chair/parts
    python -m cell.run --parts scenes/chair/parts --poses scenes/chair/assembly.json   # skip perception

(the same as ``image-assembly run ...``; from Python, :func:`cell.assemble`, which this command calls).

Stages: perception (the image and the parts give each part's pose), pose repair, assembly sequence, kitting
(where each part starts), motion (OMPL) and timing (Ruckig) of every pick and place, simulation (PyBullet with
physics, checked against the targets), export. The output folder (``--out``, default ``out/<parts folder's
parent>``) holds ``report.json``, ``overview.png``, ``animation.gif``, ``trajectory.csv``, ``program.json`` and
the ROS 2 bag ``trajectory.mcap`` (formats in docs/formats.md); it appears complete or not at all.

Exit codes: 0 success, 2 bad input (nothing written), 3 planning failed, 4 the simulation check failed, 5 the
assembly predicted from the picture does not match the picture (nothing planned; ``--accept-prediction`` builds it
anyway); 3, 4 and 5 write the report and pictures of what was done, for diagnosis.
"""

from __future__ import annotations

import argparse
import sys
import traceback
from pathlib import Path

from cell.api import PERCEPTION_HINT, Options, check_options, check_out, run_checked, verdict
from cell.console import STAGES, Console
from cell.errors import EXIT_BAD_INPUT, EXIT_INTERNAL, BadInput, BadOption

MASSES_HELP = ('known part masses in kg: a JSON file, or the JSON itself in single quotes, {"part name": kg, ...} '
               """(e.g. --masses '{"seat": 1.4}'); parts it leaves out weigh their volume at --density""")


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(prog="python -m cell.run", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--image", type=Path, help="RGB picture of the assembled object, at least 224x224; a "
                        "non-square one is centre-cropped to a square (see --pad), then resized to 224x224")
    parser.add_argument("--parts", type=Path, required=True,
                        help="folder of part meshes (.obj/.stl/.ply/...), one file per part, in their own frames; "
                        "materials and textures beside them (.mtl, .png, .jpg) are skipped")
    parser.add_argument("--poses", type=Path,
                        help="target poses as an assembly.json (assembly folder format): skips perception")
    parser.add_argument("--scene", type=Path, help="robot cell scene file (default: the bundled scenes/cell.toml)")
    parser.add_argument("--out", type=Path, help="output folder (default: out/<name of the parts' parent folder>)")
    parser.add_argument("--seed", type=int, default=0, help="seed of every random choice, 0 to 4294967295 "
                        "(default 0)")
    parser.add_argument("--units", choices=["m", "cm", "mm"], default="m", help="units of the mesh files (default m)")
    parser.add_argument("--checkpoint", type=Path, help="perception weights (default: the bundled ones)")
    parser.add_argument("--planner", default="RRTConnect", help="OMPL planner: RRTConnect (default), RRT, RRTstar, "
                        "PRM, KPIECE1, BKPIECE1, LBKPIECE1 or BITstar")
    parser.add_argument("--density", type=float, default=None, metavar="KG_M3",
                        help="the parts' material, for their weight (payload, joint torques, simulation; default 600, "
                        "wood; honeycomb board about 300, MDF 750, aluminium 2700)")
    parser.add_argument("--masses", metavar="FILE_OR_JSON", help=MASSES_HELP)
    parser.add_argument("--sheet-thickness", type=float, default=3.0, metavar="MM",
                        help="thickness given to a part drawn as one surface (a board without thickness) where no "
                        "part up to 60 mm beside it gives its thickness (with --poses: it grows to meet such a part, "
                        "else away from a part touching it or from the assembly's centre; without: behind its drawn "
                        "face); default 3 mm, a hardboard back panel")
    parser.add_argument("--time-budget", type=float, default=None, metavar="SECONDS",
                        help="seconds of kitting and motion planning per build (standing, then upside down) before "
                        "the planner stops trying other placements of the jig (default 300)")
    parser.add_argument("--accept-prediction", action="store_true",
                        help="build the assembly predicted from the picture even where it does not match the picture "
                        "(exit 5 otherwise); the report then says it was built, not that it succeeded")
    parser.add_argument("--bag-storage", choices=["mcap", "sqlite3"], default="mcap",
                        help="the ROS 2 bag of the program: trajectory.mcap (mcap, ROS 2 Jazzy's default; the "
                        "default) or the rosbag2 folder trajectory_bag (sqlite3, ROS 2 Humble's default)")
    parser.add_argument("--pad", action="store_true", help="pad a non-square picture to a square with its border "
                        "colour instead of cropping it")
    parser.add_argument("--no-animation", action="store_true", help="skip animation.gif (faster)")
    parser.add_argument("--quiet", action="store_true", help="no progress, only notes, failures and the summary")
    args = parser.parse_args(argv)
    if args.image is None and args.poses is None:
        parser.error("give --image (perception predicts the poses) or --poses (target poses given)")
    try:
        check_options(options_from_args(args), cli=True)
    except BadOption as exc:
        parser.error(str(exc))
    return args


def options_from_args(args: argparse.Namespace) -> Options:
    return Options(seed=args.seed, units=args.units, checkpoint=args.checkpoint, planner=args.planner,
                   density=args.density, time_budget=args.time_budget, no_animation=args.no_animation, pad=args.pad,
                   poses=str(args.poses) if args.poses is not None else None,
                   accept_prediction=args.accept_prediction, bag_storage=args.bag_storage,
                   sheet_thickness_mm=args.sheet_thickness)


def _default_out(parts: Path) -> Path:
    parent = parts.resolve().parent.name if parts.resolve().name == "parts" else parts.resolve().name
    return Path("out") / (parent or "run")


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    console = Console(args.quiet)
    try:
        return _run(args, console)
    except BadInput as exc:
        print(f"error: {exc}", file=sys.stderr)
        return EXIT_BAD_INPUT
    except KeyboardInterrupt:
        print("interrupted: nothing written", file=sys.stderr)
        return 130
    except Exception as exc:  # a bug: say so plainly, with the trace for the report
        print(f"internal error ({exc.__class__.__name__}: {exc}); please report it with this trace:\n"
              f"{traceback.format_exc()}", file=sys.stderr)
        return EXIT_INTERNAL


def _run(args: argparse.Namespace, console: Console) -> int:
    from cell.report import summary_table

    out = args.out or _default_out(args.parts)
    result = run_checked(args.parts, args.image, args.poses, args.scene, out, args.masses, options_from_args(args),
                         console)
    print(summary_table(result.report))
    print(f"{verdict(result.report)}: {out}/ ({', '.join(sorted(p.name for p in out.iterdir()))})")
    return result.exit_code


if __name__ == "__main__":
    sys.exit(main())


__all__ = ["main", "parse_args", "Console", "STAGES", "PERCEPTION_HINT", "check_out"]
