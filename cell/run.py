"""``python -m cell.run``: one picture and a folder of loose parts in, a verified robot assembly program out.

    python -m cell.run --image scenes/chair/chair.png --parts scenes/chair/parts
    python -m cell.run --parts scenes/chair/parts --poses scenes/chair/assembly.json   # skip perception

Stages: perception (the image and the parts give each part's pose), pose repair, assembly sequence, kitting
(where each part starts), motion (OMPL) and timing (Ruckig) of every pick and place, simulation (PyBullet with
physics, checked against the targets), export. The output folder (``--out``, default ``out/<parts folder's
parent>``) holds ``report.json``, ``overview.png``, ``animation.gif``, ``trajectory.csv`` and ``program.json``
(formats in the README); it appears complete or not at all.

Exit codes: 0 success, 2 bad input (nothing written), 3 planning failed, 4 the simulation check failed (3 and 4
write the report and pictures of what was done, for diagnosis).
"""

from __future__ import annotations

import argparse
import sys
import time
import traceback
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path

from cell.errors import EXIT_BAD_INPUT, EXIT_INTERNAL, EXIT_OK, EXIT_PLANNING, EXIT_SIMULATION, BadInput, StageFailed

STAGES = ("perception", "repair", "sequence", "kitting", "motion", "timing", "simulation", "export")


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(prog="python -m cell.run", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--image", type=Path, help="square RGB picture of the assembled object (224x224 or larger)")
    parser.add_argument("--parts", type=Path, required=True,
                        help="folder of part meshes (.obj/.stl/.ply/...), one file per part, in their own frames")
    parser.add_argument("--poses", type=Path,
                        help="target poses as an assembly.json (assembly folder format): skips perception")
    parser.add_argument("--scene", type=Path, help="robot cell scene file (default: the bundled scenes/cell.toml)")
    parser.add_argument("--out", type=Path, help="output folder (default: out/<name of the parts' parent folder>)")
    parser.add_argument("--seed", type=int, default=0, help="seed of every random choice (default 0)")
    parser.add_argument("--units", choices=["m", "cm", "mm"], default="m", help="units of the mesh files (default m)")
    parser.add_argument("--checkpoint", type=Path, help="perception weights (default: the bundled ones)")
    parser.add_argument("--planner", default="RRTConnect", help="OMPL planner (default RRTConnect)")
    parser.add_argument("--density", type=float, default=None, metavar="KG_M3",
                        help="the parts' material, for their weight (payload, joint torques, simulation; default 600, "
                        "wood; honeycomb board about 300, MDF 750, aluminium 2700)")
    parser.add_argument("--masses", type=Path, metavar="JSON",
                        help='known part masses in kg, as a JSON object {"part name": kg, ...}; parts it leaves out '
                        "weigh their volume at --density")
    parser.add_argument("--sheet-thickness", type=float, default=3.0, metavar="MM",
                        help="thickness given to a part drawn as one surface (a board without thickness), grown "
                        "behind its drawn face (default 3 mm, a hardboard back panel)")
    parser.add_argument("--time-budget", type=float, default=None, metavar="SECONDS",
                        help="seconds of kitting and motion planning per build (standing, then upside down) before "
                        "the planner stops trying other placements of the jig (default 300)")
    parser.add_argument("--no-animation", action="store_true", help="skip animation.gif (faster)")
    parser.add_argument("--quiet", action="store_true", help="no progress, only the summary")
    args = parser.parse_args(argv)
    if args.image is None and args.poses is None:
        parser.error("give --image (perception predicts the poses) or --poses (target poses given)")
    from cell.inputs import MAX_DENSITY_KG_M3, MIN_DENSITY_KG_M3

    if args.density is not None and not MIN_DENSITY_KG_M3 <= args.density <= MAX_DENSITY_KG_M3:  # also refuses nan
        parser.error(f"--density {args.density:g}: give the parts' density in kg/m3, from {MIN_DENSITY_KG_M3:.0f} to "
                     f"{MAX_DENSITY_KG_M3:.0f} (wood is 600 kg/m3, 0.6 g/cm3)")
    if not 0 < args.sheet_thickness <= 100:  # also refuses nan
        parser.error(f"--sheet-thickness {args.sheet_thickness:g}: give the thickness of a one-surface board in mm, "
                     "above 0 and at most 100 (hardboard is 3 mm)")
    if args.time_budget is not None and not args.time_budget > 0:  # also refuses nan
        parser.error(f"--time-budget {args.time_budget:g}: give a number of seconds above 0")
    return args


@dataclass
class Console:
    quiet: bool = False
    stage_seconds: dict[str, float] = field(default_factory=dict)

    def say(self, text: str) -> None:
        if not self.quiet:
            print(text, file=sys.stderr, flush=True)

    @contextmanager
    def stage(self, name: str, detail: str = ""):
        index = STAGES.index(name) + 1
        self.say(f"[{index}/{len(STAGES)}] {name}{': ' + detail if detail else ''}")
        started = time.perf_counter()
        try:
            yield
        finally:
            self.stage_seconds[name] = self.stage_seconds.get(name, 0.0) + time.perf_counter() - started

    def bar(self, total: int, unit: str):
        from tqdm import tqdm

        return tqdm(total=total, unit=unit, disable=self.quiet, file=sys.stderr, leave=False, dynamic_ncols=True)


def _default_out(parts: Path) -> Path:
    parent = parts.resolve().parent.name if parts.resolve().name == "parts" else parts.resolve().name
    return Path("out") / (parent or "run")


def _check_out(out: Path) -> None:
    if out.exists() and (not out.is_dir() or (any(out.iterdir()) and not (out / "report.json").exists())):
        raise BadInput(f"{out}: the output folder exists and does not hold an earlier run (no report.json); "
                       "choose another --out or remove it")


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
    from cell.inputs import InputError, load_image, load_masses, load_parts, load_poses
    from cell.scene import SceneError, load_scene
    from planning.payload import DEFAULT_DENSITY_KG_M3

    out = args.out or _default_out(args.parts)
    _check_out(out)
    try:
        scene = load_scene(args.scene)
        parts = load_parts(args.parts, args.units, args.sheet_thickness / 1000.0)
        image = load_image(args.image) if args.image is not None else None
        given = load_poses(args.poses, parts.names) if args.poses is not None else None
        given_density = load_masses(args.masses, parts) if args.masses is not None else {}
    except (InputError, SceneError) as exc:
        raise BadInput(str(exc)) from exc
    console.say(f"{len(parts.names)} parts from {args.parts}" + (f", image {args.image}" if image is not None else ""))
    from planning.mesh_intake import summary_line

    if summary_line(parts.mesh_intake):
        console.say(summary_line(parts.mesh_intake))
    if given_density:
        rest = len(parts.names) - len(given_density)
        console.say(f"masses of {len(given_density)} part(s) from {args.masses}"
                    + (f"; {rest} other(s) at {args.density or DEFAULT_DENSITY_KG_M3:g} kg/m3" if rest else ""))

    report: dict = {"success": False, "exit_code": None, "failure": None,
                    "inputs": {"image": str(args.image) if args.image else None, "parts": str(args.parts),
                               "poses": str(args.poses) if args.poses else None,
                               "scene": scene.source if args.scene else "scenes/cell.toml", "seed": args.seed,
                               "units": args.units, "density_kg_m3": args.density or DEFAULT_DENSITY_KG_M3,
                               "masses": str(args.masses) if args.masses else None},
                    "stages": console.stage_seconds, "trajectory_duration_s": None,
                    "world_from_assembly": scene.fixture.world_from_assembly.to_dict(), "parts": []}
    report["mesh_intake"] = {"sheet_thickness_m": args.sheet_thickness / 1000.0, "parts": parts.mesh_intake}
    from cell.pipeline import Pipeline, indented

    pipeline = Pipeline(scene, parts, image, given, args, console, report, given_density)
    try:
        pipeline.targets()  # perception or --poses, then repair; bad geometry here is bad input
        exit_code = pipeline.plan_and_simulate()
    except StageFailed as failure:
        report["failure"] = {"stage": failure.stage, "part": failure.part, "message": str(failure)}
        exit_code = failure.exit_code
        print(f"{'planning' if exit_code == EXIT_PLANNING else 'simulation check'} failed at {failure.stage}"
              f"{' (part ' + repr(failure.part) + ')' if failure.part else ''}: {indented(str(failure), '    ')}",
              file=sys.stderr)
    if given is None:  # success or not, the targets are only as good as the prediction
        print(PERCEPTION_HINT, file=sys.stderr)
    report["exit_code"] = exit_code
    report["success"] = exit_code == EXIT_OK
    _write_outputs(out, pipeline, report, console)
    from cell.report import summary_table

    print(summary_table(report))
    verdict = {EXIT_OK: "success", EXIT_PLANNING: "planning failed", EXIT_SIMULATION: "simulation check failed"}
    print(f"{verdict[exit_code]}: {out}/ ({', '.join(sorted(p.name for p in out.iterdir()))})")
    return exit_code


PERCEPTION_HINT = ("note: the targets came from the picture, and the bundled compact model often misplaces parts "
                   "(Part Accuracy per category in benchmarks/RESULTS.md): a success means the cell built the "
                   "predicted assembly, not necessarily the object in the picture; compare the input and the "
                   "predicted assembly in overview.png, and give known poses with --poses ASSEMBLY_JSON to check "
                   "the cell alone")


def _write_outputs(out: Path, pipeline, report: dict, console: Console) -> None:
    """Everything into a fresh sibling folder, then renamed over ``out``: a complete folder or none."""
    from cell.report import write_json
    from planning.assembly import replacing_folder

    with replacing_folder(out) as tmp:
        with console.stage("export", "report, overview, trajectory"):
            pipeline.write(tmp)
        write_json(tmp / "report.json", report)


if __name__ == "__main__":
    sys.exit(main())


__all__ = ["main", "Console", "STAGES"]
