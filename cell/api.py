"""The library behind ``python -m cell.run``: :func:`assemble` (one call, checked options) and :func:`run_checked`
(what the command line calls with its parsed arguments), both returning an :class:`AssemblyResult`.

Bad input raises a :class:`cell.errors.BadInput` subclass before anything is planned or written; a run that plans
and fails returns its exit code (3 planning, 4 the simulation check) and the :class:`Failure`, with the report
and pictures of what was done written to ``out`` as on success.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

from cell.console import Console
from cell.errors import (
    EXIT_DISAGREES,
    EXIT_OK,
    EXIT_PLANNING,
    EXIT_SIMULATION,
    BadCheckpoint,
    BadOption,
    BadOutput,
    StageFailed,
)

if TYPE_CHECKING:
    import numpy as np

    from cell.program import Program
    from cell.scene import Scene
    from cell.sim_result import SimulationResult
    from planning.assembly import Assembly
    from planning.pose import Pose

MAX_SEED = 2**32 - 1
UNITS = ("m", "cm", "mm")
MAX_SHEET_THICKNESS_MM = 100.0
BAG_STORAGES = ("mcap", "sqlite3")  # rosbag2 storage of the exported bag (cell.ros2_export)
PERCEPTION_HINT = ("note: the targets came from the picture, and the bundled model often misplaces parts (Part "
                   "Accuracy per category in benchmarks/RESULTS.md); the run plans only a predicted assembly whose "
                   "outline and edges between parts match the picture's (report.json: picture_agreement), and "
                   "overview.png shows both; give known poses with --poses ASSEMBLY_JSON to check the cell alone")


@dataclass(frozen=True)
class Options:
    """How a run plans (the stages read these as ``Pipeline.args``). ``poses`` is where given target poses came
    from, as messages name it (``None`` when they come from the picture)."""

    seed: int = 0  # of every random choice, 0 to MAX_SEED
    units: str = "m"  # of the mesh files: m, cm or mm
    checkpoint: Path | None = None  # perception weights (None: the bundled ones)
    planner: str = "RRTConnect"  # OMPL planner, one of planning.motion.available_planners()
    density: float | None = None  # kg/m3 of the parts (None: planning.payload.DEFAULT_DENSITY_KG_M3, wood)
    time_budget: float | None = None  # seconds of kitting and motion planning per build (None: the default)
    no_animation: bool = False  # skip animation.gif
    pad: bool = False  # pad a non-square picture to a square instead of cropping it
    poses: str | None = None
    accept_prediction: bool = False  # build a prediction that does not match its picture (else exit 5)
    bag_storage: str = "mcap"  # the ROS 2 bag: "mcap" (trajectory.mcap) or "sqlite3" (trajectory_bag/)
    sheet_thickness_mm: float = 3.0  # a part drawn as one surface becomes a board this thick (planning.mesh_intake)


@dataclass(frozen=True)
class Failure:
    """Where a run that planned stopped: the stage (``cell.console.STAGES``), the message, the part if one."""

    stage: str
    message: str
    part: str | None = None


@dataclass(frozen=True)
class AssemblyResult:
    """What a run gives: exit code 0 (built), 3 (planning failed), 4 (the simulation check failed) or 5 (the
    assembly predicted from the picture does not match the picture: nothing planned). ``success``: built and, from a
    picture, agreeing with it (``report["picture_agreement"]``)."""

    exit_code: int
    target: Assembly | None  # the target assembly (assembly frame: metres, +z up, floor at z = 0)
    order: list[str]  # the parts in assembly order, as far as one was planned ([] before the sequence stage)
    program: Program | None  # the timed robot program, once within the Panda's limits (else None)
    simulation: SimulationResult | None  # the simulated execution of the program and each part's final error
    report: dict  # what report.json holds (cell.report)
    failure: Failure | None = None
    out: Path | None = None  # the folder written (None: nothing written)
    notes: list[str] = field(default_factory=list)  # what the input readers changed or skipped

    @property
    def success(self) -> bool:
        return bool(self.report.get("success"))


def check_options(options: Options, cli: bool = False) -> None:
    """Raise :class:`BadOption` for an option out of range, named as on the command line (``cli``) or as the
    keyword of :func:`assemble`."""
    def named(key: str, value) -> str:
        return f"--{key.replace('_', '-')} {value}" if cli else f"{key}={value!r}"

    seed = options.seed
    if isinstance(seed, bool) or not isinstance(seed, int) or not 0 <= seed <= MAX_SEED:
        raise BadOption(f"{named('seed', seed)}: give a whole number from 0 to {MAX_SEED} (the seed of every random "
                        "choice)")
    if options.units not in UNITS:
        raise BadOption(f"{named('units', options.units)}: give the units of the mesh files, one of "
                        f"{', '.join(UNITS)}")
    thickness = options.sheet_thickness_mm
    if not (_is_number(thickness) and 0 < thickness <= MAX_SHEET_THICKNESS_MM):
        raise BadOption(f"{named('sheet_thickness', thickness)}: give the thickness of a one-surface board in mm, "
                        f"above 0 and at most {MAX_SHEET_THICKNESS_MM:g} (hardboard is 3 mm)")
    if options.bag_storage not in BAG_STORAGES:
        raise BadOption(f"{named('bag_storage', options.bag_storage)}: give one of {', '.join(BAG_STORAGES)}")
    from planning.motion import available_planners

    planners = available_planners()
    if options.planner not in planners:
        raise BadOption(f"{named('planner', options.planner)}: not a planner this cell runs; choose one of "
                        f"{', '.join(planners)} (OMPL's names, case-sensitive)")
    from cell.inputs import MAX_DENSITY_KG_M3, MIN_DENSITY_KG_M3

    density = options.density
    if density is not None and not (_is_number(density) and MIN_DENSITY_KG_M3 <= density <= MAX_DENSITY_KG_M3):
        shown = f"{density:g}" if _is_number(density) else repr(density)
        raise BadOption(f"{named('density', shown) if cli else named('density', density)}: give the parts' density "
                        f"in kg/m3, from {MIN_DENSITY_KG_M3:.0f} to {MAX_DENSITY_KG_M3:.0f} (wood is 600 kg/m3, "
                        "0.6 g/cm3)")
    budget = options.time_budget
    if budget is not None and not (_is_number(budget) and budget > 0 and math.isfinite(budget)):
        shown = f"{budget:g}" if _is_number(budget) else repr(budget)
        raise BadOption(f"{named('time_budget', shown) if cli else named('time_budget', budget)}: give a number "
                        "of seconds above 0")


def _is_number(value) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool) and not math.isnan(value)


def assemble(parts: str | Path, image: str | Path | np.ndarray | None = None,
             poses: str | Path | Mapping[str, Pose] | None = None, scene: str | Path | Scene | None = None,
             out: str | Path | None = None, *, seed: int = 0, units: str = "m", checkpoint: str | Path | None = None,
             planner: str = "RRTConnect", density: float | None = None,
             masses: str | Path | Mapping[str, float] | None = None, time_budget: float | None = None,
             pad: bool = False, animation: bool = True, accept_prediction: bool = False, bag_storage: str = "mcap",
             sheet_thickness_mm: float = 3.0, verbose: bool = False) -> AssemblyResult:
    """Assemble the parts in ``parts`` (a folder of mesh files, one part each) into the object in ``image`` (a
    picture file or an (H, W, 3) uint8 RGB array: perception predicts the target poses) or at ``poses`` (an
    ``assembly.json``, or a mapping of part name to ``assembly_from_part`` :class:`Pose`: perception is skipped).

    ``scene``: a scene file or :class:`cell.scene.Scene` (default: the bundled ``scenes/cell.toml``). ``out``: the
    folder to write ``report.json``, ``overview.png``, ``animation.gif``, ``trajectory.csv``, ``program.json`` and
    the ROS 2 bag to, complete or not at all (``None``: nothing is written). The keywords are the options of
    ``python -m cell.run`` (``masses``: a JSON file, JSON text or a mapping of part name to kg; ``animation=False``
    is ``--no-animation``); ``verbose`` prints the stages as the command does.

    Raises a :class:`cell.errors.BadInput` subclass for bad input, before anything is planned or written."""
    if image is None and poses is None:
        raise BadOption("give image= (perception predicts the poses) or poses= (target poses given)")
    options = Options(seed=seed, units=units, checkpoint=None if checkpoint is None else Path(checkpoint),
                      planner=planner, density=density, time_budget=time_budget, no_animation=not animation,
                      pad=pad, poses=_label(poses, "poses"), accept_prediction=accept_prediction,
                      bag_storage=bag_storage, sheet_thickness_mm=sheet_thickness_mm)
    check_options(options)
    console = Console(quiet=not verbose, silent=not verbose)
    return run_checked(Path(parts), image, poses, scene, None if out is None else Path(out), masses, options,
                       console)


def _label(source, what: str) -> str | None:
    """How the report and messages name an input: its path, or what it is when given in memory."""
    if source is None:
        return None
    if isinstance(source, str | Path):
        return str(source)
    return f"{what} given in memory"


def check_out(out: Path) -> None:
    if out.exists() and (not out.is_dir() or (any(out.iterdir()) and not (out / "report.json").exists())):
        raise BadOutput(f"{out}: the output folder exists and does not hold an earlier run (no report.json); "
                        "choose another --out or remove it")


def check_checkpoint(checkpoint: Path | None) -> None:
    """Load the perception weights (kept for the prediction) or raise :class:`BadCheckpoint` naming the file."""
    from perception.weights import MissingWeightsError, load_for_inference

    try:
        load_for_inference(checkpoint)
    except MissingWeightsError as exc:
        raise BadCheckpoint(str(exc)) from exc
    except Exception as exc:  # whatever the file holds, it is not a network this package can load
        raise BadCheckpoint(f"{checkpoint}: not a perception model ({exc.__class__.__name__}: {exc}); give a "
                            "model.pt or checkpoint.pt written by python -m perception.train, or leave out "
                            "--checkpoint for the bundled weights") from exc


def run_checked(parts: Path, image, poses, scene, out: Path | None, masses, options: Options,
                console: Console) -> AssemblyResult:
    """Read and check every input, then run the stages (:class:`cell.pipeline.Pipeline`) and write ``out``
    (``None``: nothing). ``options`` must have passed :func:`check_options`."""
    from cell.inputs import load_image, load_masses, load_parts
    from cell.scene import Scene, load_scene
    from planning.payload import DEFAULT_DENSITY_KG_M3

    if out is not None:
        check_out(out)
    notes: list[str] = []
    scene_config = scene if isinstance(scene, Scene) else load_scene(scene)
    loaded = load_parts(parts, options.units, notes, options.sheet_thickness_mm / 1000.0, poses)
    picture = load_image(image, options.pad, notes) if image is not None else None
    given = loaded.poses
    given_density = load_masses(masses, loaded) if masses is not None else {}
    if picture is not None and given is None:
        check_checkpoint(options.checkpoint)
    elif options.checkpoint is not None:
        notes.append(f"--checkpoint {options.checkpoint} is not used: the target poses are given")
    image_label = _label(image, "image")
    masses_label = masses if isinstance(masses, Mapping) else _label(masses, "masses")
    for note in notes:
        console.notice(f"note: {note}")
    console.say(f"{len(loaded.names)} parts from {parts}" + (f", image {image_label}" if picture is not None else ""))
    from planning.mesh_intake import summary_line

    repaired = summary_line(loaded.mesh_intake)
    if repaired:
        console.say(repaired)
    if given_density:
        rest = len(loaded.names) - len(given_density)
        console.say(f"masses of {len(given_density)} part(s) from {masses_label}"
                    + (f"; {rest} other(s) at {options.density or DEFAULT_DENSITY_KG_M3:g} kg/m3" if rest else ""))

    report: dict = {"success": False, "exit_code": None, "failure": None,
                    "inputs": {"image": image_label, "parts": str(parts), "poses": options.poses,
                               "scene": scene_config.source if scene is not None else "scenes/cell.toml",
                               "seed": options.seed, "units": options.units,
                               "density_kg_m3": options.density or DEFAULT_DENSITY_KG_M3, "masses": masses_label,
                               "notes": notes},
                    "stages": console.stage_seconds, "trajectory_duration_s": None,
                    "world_from_assembly": scene_config.fixture.world_from_assembly.to_dict(), "parts": [],
                    "mesh_intake": {"sheet_thickness_m": options.sheet_thickness_mm / 1000.0,
                                    "parts": loaded.mesh_intake}}
    from cell.pipeline import Pipeline, indented

    pipeline = Pipeline(scene_config, loaded, picture, given, options, console, report, given_density)
    failure = None
    try:
        pipeline.targets()  # perception or the given poses, then repair; bad geometry here is bad input
        exit_code = pipeline.plan_and_simulate()
    except StageFailed as stopped:
        failure = Failure(stopped.stage, str(stopped), stopped.part)
        report["failure"] = {"stage": failure.stage, "part": failure.part, "message": failure.message}
        exit_code = stopped.exit_code
        what = {EXIT_PLANNING: "planning failed", EXIT_SIMULATION: "simulation check failed",
                EXIT_DISAGREES: "stopped"}[exit_code]
        console.notice(f"{what} at {failure.stage}{' (part ' + repr(failure.part) + ')' if failure.part else ''}: "
                       f"{indented(failure.message, '    ')}")
    if given is None:  # success or not, the targets are only as good as the prediction
        console.notice(PERCEPTION_HINT)
    report["exit_code"] = exit_code
    agreement = report.get("picture_agreement")
    report["built"] = exit_code == EXIT_OK
    # from a picture, success means built *and* the object built agrees with the picture
    report["success"] = exit_code == EXIT_OK and (agreement is None or agreement["agrees"])
    if out is not None:
        _write_outputs(out, pipeline, report, console)
    order = [entry["name"] for entry in sorted((e for e in report["parts"] if e.get("order") is not None),
                                               key=lambda e: e["order"])]
    program = pipeline.plan.program if pipeline.plan is not None and pipeline.samples is not None else None
    return AssemblyResult(exit_code, pipeline.target, order, program, pipeline.simulation, report, failure, out,
                          notes)


def _write_outputs(out: Path, pipeline, report: dict, console: Console) -> None:
    """Everything into a fresh sibling folder, then renamed over ``out``: a complete folder or none."""
    from cell.report import write_json
    from planning.assembly import replacing_folder

    with replacing_folder(out) as tmp:
        with console.stage("export", "report, overview, trajectory"):
            pipeline.write(tmp)
        write_json(tmp / "report.json", report)


def verdict(report: dict) -> str:
    """The run's outcome in words, for its last line."""
    if report["exit_code"] == EXIT_OK:
        return ("success" if report["success"] else
                "built the predicted assembly, which does not match the picture (--accept-prediction)")
    return {EXIT_PLANNING: "planning failed", EXIT_SIMULATION: "simulation check failed",
            EXIT_DISAGREES: "the predicted assembly does not match the picture; nothing planned"}[report["exit_code"]]

__all__ = ["assemble", "run_checked", "check_options", "Options", "AssemblyResult", "Failure", "PERCEPTION_HINT",
           "verdict"]
