"""From a picture, end to end: ``python -m cell.run --image`` on held-out procedural objects or real furniture.

    python benchmarks/picture_runs.py --set cabinet 3 --first 0 --count 8 --out out/picture_runs
    python benchmarks/picture_runs.py --furniture ../shared/furniture --first 0 --count 42 --out out/picture_runs
    python benchmarks/picture_runs.py --furniture ../shared/furniture --only table_lack_0825 --density 300

Each object is a held-out test object of ``benchmarks/perception_accuracy.py`` (``perception.synth``,
``default_rng([1000, i])``; training used seed 0), written under ``OUT/objects/``, or with ``--furniture`` an
assembly folder of real furniture (never trained on). Its picture is rendered as a user would render it
(``python -m cell.render OBJECT --out OUT/pictures/NAME.png --seed 0``), then the whole command runs in its own
process on that picture and the loose parts (bundled weights, ``--no-animation``, seed 0; output under
``OUT/runs/NAME``, its log in ``OUT/runs/.batch/``; ``--density`` is passed on), as a job of ``python -m
cell.batch``: one after another, or ``--workers N`` side by side on a local Dask cluster. Prints a Markdown table:
per object the exit code, the stage that failed, the wall time, the deepest overlap left after the pose repair
(what ``cell.run`` refuses above 30 mm) and the start of the failure's message. Exit 5: the predicted assembly
did not match the picture and nothing was planned; a success means the cell built the predicted assembly and it
matches the picture (``report.json``'s ``picture_agreement``); each run's ``overview.png`` shows both.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

sys.path[:] = [p for p in sys.path if Path(p or ".").resolve() != Path(__file__).resolve().parent]
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from cell.batch import Engine  # noqa: E402
from cell.batch_jobs import Job  # noqa: E402
from perception.synth import generate  # noqa: E402
from planning.assembly import write_assembly  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
TEST_SEED = 1000  # the held-out sets of benchmarks/perception_accuracy.py
WHY_CHARS = 90  # of a failure's message in the table (records.json keeps it whole)


def held_out_object(category: str, level: str, index: int, out: Path) -> tuple[str, Path]:
    """(name, folder) of a held-out test object, written under ``out/objects`` the first time."""
    name = f"{category}_{level}_s{TEST_SEED}_{index:05d}"
    folder = out / "objects" / name
    if not (folder / "assembly.json").exists():
        write_assembly(generate(category, level, np.random.default_rng([TEST_SEED, index]), name), folder,
                       overwrite=True)
    return name, folder


def render_picture(name: str, folder: Path, out: Path) -> Path:
    """Render the assembly folder ``folder`` as a user would (``python -m cell.render``): ``OUT/pictures/NAME.png``."""
    picture = out / "pictures" / f"{name}.png"
    picture.parent.mkdir(parents=True, exist_ok=True)
    subprocess.run([sys.executable, "-m", "cell.render", str(folder), "--out", str(picture), "--seed", "0"],
                   cwd=ROOT, check=True, capture_output=True)
    return picture


def picture_job(name: str, folder: Path, picture: Path, timeout_s: float, density_kg_m3: float | None) -> Job:
    """The cell on the picture and the loose parts: a job of ``python -m cell.batch``."""
    options = {"seed": 0, "animation": False} | ({} if density_kg_m3 is None else {"density": density_kg_m3})
    folder = folder.resolve()  # a job's paths are absolute: it runs wherever its worker runs
    return Job(name, str(folder), folder / "parts", image=picture.resolve(), options=options, timeout_s=timeout_s)


def record_of(name: str, result: dict, run_out: Path) -> dict:
    """An object's record from its batch record (``cell.batch``) and, where written, its ``report.json``."""
    why = (result["message"] or "").strip().split("\n")[0] if result["status"] != "timeout" else ""
    record = {"object": name, "exit_code": result["exit_code"], "status": result["status"],
              "seconds": result["wall_s"], "stage": None, "deepest_overlap_after_repair_mm": None, "why": why}
    if result["out"] is not None:  # the exits that write a report (0, 3, 4)
        report = json.loads((run_out / "report.json").read_text())
        record["stage"] = (report.get("failure") or {}).get("stage")
        record["why"] = (report.get("failure") or {}).get("message", "")
        pairs = report.get("repair", {}).get("overlapping_pairs_after", [])
        record["deepest_overlap_after_repair_mm"] = 1000 * max((p["depth_m"] for p in pairs), default=0.0)
    return record


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--set", nargs=2, metavar=("CATEGORY", "LEVEL"), default=["cabinet", "3"],
                        help="category (chair, table, cabinet) and level (3, mixed)")
    parser.add_argument("--first", type=int, default=0, help="index of the first test object")
    parser.add_argument("--count", type=int, help="objects to run (default: 8 of --set; every folder of --furniture "
                                                  "from --first on, or every one named with --only)")
    parser.add_argument("--out", type=Path, default=Path("out/picture_runs"))
    parser.add_argument("--timeout", type=float, default=900.0, help="seconds per run")
    parser.add_argument("--furniture", type=Path, help="run these assembly folders instead (e.g. ../shared/furniture, "
                        "in name order; --first and --count select among them)")
    parser.add_argument("--only", nargs="+", metavar="NAME", help="with --furniture: only these folders")
    parser.add_argument("--density", type=float, help="the parts' density for python -m cell.run (kg/m3)")
    parser.add_argument("--workers", type=int, default=1, help="objects run side by side on a local cluster "
                        "(default 1: one after another)")
    parser.add_argument("--scheduler", metavar="ADDRESS", help="run on an existing Dask cluster instead")
    args = parser.parse_args()
    if args.furniture is not None:
        from perception.evaluate_assemblies import assembly_folders

        try:
            folders = assembly_folders(args.furniture)
        except FileNotFoundError as exc:
            raise SystemExit(f"--furniture: {exc}") from exc
        if args.only:
            missing = sorted(set(args.only) - {f.name for f in folders})
            if missing:
                raise SystemExit(f"--only: no assembly folder {', '.join(missing)} in {args.furniture}")
            folders = [f for f in folders if f.name in args.only]
        count = len(folders) if args.count is None else args.count
        objects = [(folder.name, folder) for folder in folders[args.first:args.first + count]]
        if not objects:
            raise SystemExit(f"--furniture {args.furniture}: no assembly folders at --first {args.first}")
        described = (f"{args.furniture.name}, " + (f"{len(objects)} folders named with --only" if args.only else
                     f"folders {args.first}-{args.first + len(objects) - 1} in name order"))
    else:
        category, level = args.set
        args.count = 8 if args.count is None else args.count
        objects = [held_out_object(category, level, index, args.out)
                   for index in range(args.first, args.first + args.count)]
        described = f"{category} {level}, test objects {args.first}-{args.first + args.count - 1}"
    jobs = [picture_job(name, folder, render_picture(name, folder, args.out), args.timeout, args.density)
            for name, folder in objects]
    finished: dict[str, dict] = {}

    def on_result(job: Job, result: dict) -> None:
        record = finished[job.name] = record_of(job.name, result, args.out / "runs" / job.name)
        print(f"{record['object']}: exit {record['exit_code']}, {record['seconds'] or 0:.0f} s", flush=True)

    started = time.perf_counter()
    with Engine(args.workers, args.scheduler) as engine:
        print(f"running {len(jobs)} objects on {engine.description}", flush=True)
        engine.run(jobs, args.out / "runs", on_result)
    print(f"wall clock: {time.perf_counter() - started:.0f} s for {len(jobs)} objects", flush=True)
    records = [finished[name] for name, _ in objects]
    (args.out / "records.json").write_text(json.dumps(records, indent=1))
    density = f", --density {args.density:g}" if args.density is not None else ""
    print(f"\nMachine: {platform.machine()}, {len(os.sched_getaffinity(0))} cores. {described}{density}.\n")
    print("| object | exit | failed stage | seconds | deepest overlap after repair, mm | why (first words) |")
    print("|---|---|---|---|---|---|")
    for r in records:
        overlap = "-" if r["deepest_overlap_after_repair_mm"] is None else f"{r['deepest_overlap_after_repair_mm']:.0f}"
        exit_code = r["status"] if r["exit_code"] is None else r["exit_code"]  # a timeout, a lost worker
        first = r["why"].split("\n")[0]  # a planning failure's first line: the scene's own placement of the jig
        why = first if len(first) <= WHY_CHARS else first[:WHY_CHARS - 3].rstrip() + "..."
        seconds = "-" if r["seconds"] is None else f"{r['seconds']:.0f}"
        print(f"| {r['object']} | {exit_code} | {r['stage'] or '-'} | {seconds} | {overlap} | "
              f"{why.replace('|', '/') or '-'} |")
    done = [r for r in records if r["exit_code"] == 0]
    print(f"\nexit 0: {len(done)} of {len(records)}")


if __name__ == "__main__":
    main()
