"""From a picture, end to end: ``python -m cell.run --image`` on held-out procedural objects or real furniture.

    python benchmarks/picture_runs.py --set cabinet 3 --first 0 --count 8 --out out/picture_runs
    python benchmarks/picture_runs.py --furniture ../shared/furniture --first 0 --count 42 --out out/picture_runs
    python benchmarks/picture_runs.py --furniture ../shared/furniture --only table_lack_0825 --density 300

Each object is a held-out test object of ``benchmarks/perception_accuracy.py`` (``perception.synth``,
``default_rng([1000, i])``; training used seed 0), written under ``OUT/objects/``, or with ``--furniture`` an
assembly folder of real furniture (never trained on). Its picture is rendered as a user would render it
(``python -m cell.render OBJECT --out OUT/pictures/NAME.png --seed 0``), then the whole command runs in its own
process on that picture and the loose parts (bundled weights, ``--no-animation``, seed 0; output under
``OUT/runs/NAME``; ``--density`` is passed on). Prints a Markdown table: per object the exit code, the stage
that failed, the wall time, the deepest overlap left after the pose repair (what ``cell.run`` refuses above 30 mm)
and the start of the failure's message. A success means the cell built the *predicted* assembly; each run's
``overview.png`` shows how far that is from the picture.
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


def run_object(name: str, folder: Path, out: Path, timeout_s: float, density_kg_m3: float | None = None) -> dict:
    """Render the assembly folder ``folder`` and run the cell on its picture and loose parts; its record."""
    picture = out / "pictures" / f"{name}.png"
    picture.parent.mkdir(parents=True, exist_ok=True)
    subprocess.run([sys.executable, "-m", "cell.render", str(folder), "--out", str(picture), "--seed", "0"],
                   cwd=ROOT, check=True, capture_output=True)
    run_out = out / "runs" / name
    start = time.perf_counter()
    try:
        result = subprocess.run([sys.executable, "-m", "cell.run", "--image", str(picture), "--parts",
                                 str(folder / "parts"), "--out", str(run_out), "--no-animation", "--quiet",
                                 "--seed", "0"] + ([] if density_kg_m3 is None else ["--density", str(density_kg_m3)]),
                                cwd=ROOT, capture_output=True, text=True, timeout=timeout_s)
        exit_code = result.returncode
        last_error = (result.stderr.strip().splitlines() or [""])[-1]
    except subprocess.TimeoutExpired:
        exit_code, last_error = None, ""
    record = {"object": name, "exit_code": exit_code, "seconds": time.perf_counter() - start, "stage": None,
              "deepest_overlap_after_repair_mm": None, "why": last_error}
    report_path = run_out / "report.json"
    if exit_code in (0, 3, 4):  # the exits that write a report (exit 1 and 2 leave an earlier run's folder as it was)
        report = json.loads(report_path.read_text())
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
    records = []
    for name, folder in objects:
        record = run_object(name, folder, args.out, args.timeout, args.density)
        records.append(record)
        print(f"{record['object']}: exit {record['exit_code']}, {record['seconds']:.0f} s", flush=True)
    (args.out / "records.json").write_text(json.dumps(records, indent=1))
    density = f", --density {args.density:g}" if args.density is not None else ""
    print(f"\nMachine: {platform.machine()}, {len(os.sched_getaffinity(0))} cores. {described}{density}.\n")
    print("| object | exit | failed stage | seconds | deepest overlap after repair, mm | why (first words) |")
    print("|---|---|---|---|---|---|")
    for r in records:
        overlap = "-" if r["deepest_overlap_after_repair_mm"] is None else f"{r['deepest_overlap_after_repair_mm']:.0f}"
        exit_code = "timeout" if r["exit_code"] is None else r["exit_code"]
        first = r["why"].split("\n")[0]  # a planning failure's first line: the scene's own placement of the jig
        why = first if len(first) <= WHY_CHARS else first[:WHY_CHARS - 3].rstrip() + "..."
        print(f"| {r['object']} | {exit_code} | {r['stage'] or '-'} | {r['seconds']:.0f} | {overlap} | "
              f"{why.replace('|', '/') or '-'} |")
    done = [r for r in records if r["exit_code"] == 0]
    print(f"\nexit 0: {len(done)} of {len(records)}")


if __name__ == "__main__":
    main()
