"""Simulated assembly with truth poses: ``python -m cell.run --poses`` on procedural and real objects.

    python benchmarks/cell_assembly.py --procedural 20 --furniture ../shared/furniture --json out/bench_cell.json

Each object runs through the whole command (sequence, kitting, motion, timing, simulation, export) in its own
process, exactly as a user runs it (``--no-animation``, seed 0), as a job of ``python -m cell.batch``: one after
another, or ``--workers N`` side by side on a local Dask cluster (``--scheduler ADDRESS``: an existing one).
Procedural objects are ``perception.synth`` level-3 objects ``default_rng([2000, i])`` (seeds never used for
training). An object, procedural or real, whose parts do not fit the cell (kitting area, reach, or a part heavier
than the Panda's rated 3 kg payload; "reach" includes a part none of whose grasps the arm reaches at its target
with the jig where the scene puts it) is scaled down by 0.8 and then 0.6 and run again (a part's mass goes with
the cube of the scale); the scale used is reported. Prints a Markdown table (success rate, median errors, plan
and simulation times, and the most of its planning time budget any build used) and names every failure with its
stage and reason. Targets (issue 5): 100% procedural, >= 90% real, final errors <= 5 mm and <= 3 degrees.
``--keep DIR`` keeps every object's output folder (``DIR/<object>_out``: report, overview, program; each job's log
in ``DIR/.batch/``) for diagnosis; ``--only 3 8`` runs just those procedural objects, ``--only-furniture
chair_ivar_0668`` just those real ones.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path[:] = [p for p in sys.path if Path(p or ".").resolve() != Path(__file__).resolve().parent]
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from cell.batch import Engine  # noqa: E402
from cell.batch_jobs import Job  # noqa: E402
from perception.synth import generate  # noqa: E402
from planning.assembly import Assembly, AssemblyError, AssemblyPart, read_assembly, write_assembly  # noqa: E402
from planning.pose import Pose  # noqa: E402

SCALES = (1.0, 0.8, 0.6)
JOB_TIMEOUT_S = 1200.0
# what the pipeline says of an object too big for the cell: its kitting ring, the arm's reach (the inputs' check of
# the targets), the payload; and, where the jig's first placement failed (the message's first clause), every grasp
# of a part at its target beyond the arm's reach
TOO_BIG = ("too large for this cell", "out of the Panda's reach", "more than the Panda's rated payload")
BEYOND_REACH_FIRST = "each grasp tried there is beyond the arm's reach"


def scaled(assembly: Assembly, factor: float) -> Assembly:
    parts = []
    for part in assembly.parts:
        mesh = part.mesh.copy()
        mesh.apply_scale(factor)
        pose = part.assembly_from_part
        parts.append(AssemblyPart(part.name, mesh, Pose(pose.position * factor, pose.quat_wxyz), part.mesh_file))
    return Assembly(assembly.name, parts, dict(assembly.metadata))


def record_of(name: str, parts: int, result: dict, out: Path) -> dict:
    """An object's record from its batch record (``cell.batch``) and, where written, its ``report.json``."""
    record = {"name": name, "exit_code": result["exit_code"], "wall_s": result["wall_s"], "parts": parts}
    report_path = out / "report.json"
    if result["out"] is not None and report_path.is_file():
        report = json.loads(report_path.read_text())
        record["stages"] = report["stages"]
        record["failure"] = report["failure"]
        record["trajectory_s"] = report["trajectory_duration_s"]
        # CPU seconds of planning, per build tried (standing, upside down), against the budget of each
        record["planning_cpu_s"] = report.get("planning_cpu_s", {})
        record["time_budget_s"] = report.get("time_budget_s")
        errors = [(p.get("position_error_m"), p.get("rotation_error_deg")) for p in report["parts"]]
        if all(e[0] is not None for e in errors):
            record["max_position_error_mm"] = 1000 * max(e[0] for e in errors)
            record["max_rotation_error_deg"] = max(e[1] for e in errors)
        simulation = report.get("simulation") or {}
        record["unplanned_contacts"] = len(simulation.get("unplanned_contacts", []))
        record["limit_violations"] = len(simulation.get("limit_violations", []))
    else:
        stage = "input" if result["status"] == "bad input" else result["status"]  # no report: a timeout, a crash
        record["failure"] = {"stage": stage, "message": (result["message"] or result["status"]).strip()}
    return record


def run_scaled(objects: list[tuple[str, Assembly]], engine: Engine, work: Path, keep: Path | None, on_record) -> None:
    """Run every (label, assembly) through ``python -m cell.run`` on the batch ``engine`` (each in its own process);
    one too big for the cell runs again at the next smaller scale as soon as that is known. ``on_record(label,
    record)`` as each object's record is final."""
    runs = keep or work / "runs"
    sources = {}  # job name -> (label, assembly, scale)

    def job_at(label: str, assembly: Assembly, factor: float) -> Job:
        folder = write_assembly(scaled(assembly, factor) if factor != 1.0 else assembly,
                                work / f"scale_{factor}" / assembly.name, overwrite=True)
        job = Job(f"{assembly.name}_out", str(folder), folder / "parts", folder / "assembly.json",
                  options={"animation": False}, timeout_s=JOB_TIMEOUT_S)
        sources[job.name] = (label, assembly, factor)
        return job

    def on_result(job: Job, result: dict) -> list[Job]:
        label, assembly, factor = sources[job.name]
        record = record_of(assembly.name, len(assembly.parts), result, runs / job.name)
        record["scale"] = factor
        message = (record.get("failure") or {}).get("message", "")
        too_big = any(words in message for words in TOO_BIG) or BEYOND_REACH_FIRST in message.split("\n")[0]
        if too_big and factor != SCALES[-1]:
            return [job_at(label, assembly, SCALES[SCALES.index(factor) + 1])]
        on_record(label, record)
        return []

    engine.run([job_at(label, assembly, 1.0) for label, assembly in objects], runs, on_result)


def med(values: list[float]) -> str:
    return f"{np.median(values):.1f}" if values else "-"


def table(label: str, records: list[dict]) -> str:
    ok = [r for r in records if r["exit_code"] == 0]
    pos = [r["max_position_error_mm"] for r in records if "max_position_error_mm" in r]
    rot = [r["max_rotation_error_deg"] for r in records if "max_rotation_error_deg" in r]
    plan = [sum(r["stages"].get(k, 0.0) for k in ("sequence", "kitting", "motion", "timing")) for r in records
            if "stages" in r]
    sim = [r["stages"].get("simulation", 0.0) for r in records if "stages" in r and "simulation" in r["stages"]]
    # the most of its budget any build used (CPU seconds), with the object's name
    used = [(seconds / r["time_budget_s"], seconds, r["name"]) for r in records if r.get("time_budget_s")
            for seconds in r.get("planning_cpu_s", {}).values()]
    most = max(used, default=None)
    wall = [r["wall_s"] for r in records if r["wall_s"] is not None]  # none when its worker was lost
    most_words = "-" if most is None else f"{most[1]:.0f} s ({100 * most[0]:.0f}%, {most[2]})"
    return (f"| {label} | {len(records)} | {100 * len(ok) / max(1, len(records)):.0f}% | {med(pos)} | {med(rot)} | "
            f"{med(plan)} | {most_words} | {med(sim)} | {med(wall)} |")


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--procedural", type=int, default=20, help="objects per category (level 3)")
    parser.add_argument("--categories", nargs="+", default=["chair", "table", "cabinet"])
    parser.add_argument("--furniture", type=Path, help="folder of real assembly folders")
    parser.add_argument("--json", type=Path, help="write every record here (after each object)")
    parser.add_argument("--keep", type=Path, help="keep each object's output folder (report.json, overview.png, "
                        "...) under this folder, for diagnosis")
    parser.add_argument("--only", type=int, nargs="+", help="procedural object indices to run (default: all)")
    parser.add_argument("--only-furniture", nargs="+", metavar="NAME",
                        help="real objects (folder names under --furniture) to run (default: all)")
    parser.add_argument("--workers", type=int, default=1, help="objects run side by side on a local cluster "
                        "(default 1: one after another)")
    parser.add_argument("--scheduler", metavar="ADDRESS", help="run on an existing Dask cluster instead")
    args = parser.parse_args()
    print(f"machine: {platform.machine()}, {os.cpu_count()} cores, load {os.getloadavg()[0]:.1f}", flush=True)
    objects = []  # (label, assembly) in the order of the tables
    for category in args.categories if args.procedural else []:
        for i in args.only or range(args.procedural):
            objects.append((category, generate(category, "3", np.random.default_rng([2000, i]), f"{category}_{i}")))
    if args.furniture:
        folders = sorted(p for p in args.furniture.iterdir() if (p / "assembly.json").is_file())
        unknown = set(args.only_furniture or ()) - {f.name for f in folders}
        if unknown:
            parser.error(f"--only-furniture: no assembly folder {', '.join(sorted(unknown))} in {args.furniture}")
        for folder in folders:
            if args.only_furniture and folder.name not in args.only_furniture:
                continue
            try:
                objects.append(("furniture", read_assembly(folder)))
            except AssemblyError as exc:  # reported, and the rest still run
                print(f"{folder.name}: not read ({exc})", flush=True)
    order = {assembly.name: k for k, (_, assembly) in enumerate(objects)}
    everything: dict[str, list[dict]] = {}

    def on_record(label: str, r: dict) -> None:
        everything.setdefault(label, []).append(r)
        everything[label].sort(key=lambda record: order[record["name"]])
        save(args.json, everything)
        print(f"{r['name']}: exit {r['exit_code']} scale {r['scale']} {r['wall_s'] or 0:.0f} s "
              f"{(r.get('failure') or {}).get('message', '')[:160]}", flush=True)

    started = time.perf_counter()
    with tempfile.TemporaryDirectory() as tmp, Engine(args.workers, args.scheduler) as engine:
        print(f"running {len(objects)} objects on {engine.description}", flush=True)
        run_scaled(objects, engine, Path(tmp), args.keep, on_record)
    print(f"wall clock: {time.perf_counter() - started:.0f} s for {len(objects)} objects", flush=True)
    everything = {label: everything[label] for label in dict.fromkeys(label for label, _ in objects)
                  if label in everything}
    rows = [table("real furniture" if label == "furniture" else f"{label} (level 3)", records)
            for label, records in everything.items()]
    print("\n| set | objects | success | median max position error mm | median max rotation error deg | "
          "median plan s | most planning CPU of the budget | median simulation s | median wall s |")
    print("|---|---|---|---|---|---|---|---|---|")
    print("\n".join(rows))
    for label, records in everything.items():
        for r in records:
            if r["exit_code"] != 0:
                failure = r.get("failure") or {}
                print(f"- {label} {r['name']} (scale {r.get('scale', 1.0)}): exit {r['exit_code']}, "
                      f"{failure.get('stage')}: {failure.get('message', '')[:300]}")
    return 0


def save(path: Path | None, everything: dict) -> None:
    """Write every record so far (after each object: an interrupted run keeps what it measured)."""
    if path is not None:
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(json.dumps(everything, indent=1, default=float) + "\n")


if __name__ == "__main__":
    sys.exit(main())
