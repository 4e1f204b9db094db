"""The mesh intake on broken copies of real parts: volume restored, time per part, and whether the planner still
sequences (and, optionally, the cell builds) the object.

    python benchmarks/mesh_intake.py --furniture ../shared/furniture
    python benchmarks/mesh_intake.py --furniture ../shared/furniture --sequence --objects chair_agne_0007 ...
    python benchmarks/mesh_intake.py --furniture ../shared/furniture --damages soup as_exported --decompose
    python benchmarks/mesh_intake.py --furniture ../shared/furniture --damages as_exported soup --build \\
        --workers 2 --keep out/mesh_builds

Every part of every object (``--objects``: these only) is broken in each way of :data:`planning.mesh_damage.DAMAGES`
and as real models come (``as_exported``: those flaws combined per part at the rates counted on real exports),
seeded by ``[--seed, part index]``, and given to :func:`planning.mesh_intake.intake_mesh` with the side its
assembly would give a one-surface board. Per damage: the parts' volume error against the intake's solid of the
intact part (boards drawn as one surface against their drawn area times the sheet thickness instead, counted
apart), the share within 5%, and the intake's time per part (wall clock, one process). ``--sequence`` writes each
broken object as an assembly folder and runs ``planning.sequence``'s planner on it with the true poses (seed 0,
grasps checked), and on the intact object for comparison; convex decompositions of repaired meshes are new, and
take seconds each the first time (cached on disk after). ``--decompose`` times each object's first convex
decomposition, every part's solid cut into convex pieces with no cache read or written, broken and intact.
``--build`` also runs ``python -m cell.run --poses`` on each broken object whose repaired solids differ from the
intact object's (one that gets byte-identical solids back gives the cell the same input as the intact object, and
is counted apart): as ``benchmarks/cell_assembly.py`` runs them, on ``python -m cell.batch`` (``--workers``; an
object too big for the cell scaled by 0.8, then 0.6), about a minute each; ``--keep DIR`` keeps the output
folders (``DIR/<object>__<damage>_out``) for diagnosis. Prints Markdown tables.
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from functools import partial
from pathlib import Path

import numpy as np

# Run as a script, this file's folder comes first on sys.path, where a module named like a package would hide the
# perception package: look in the repository root instead.
sys.path[:] = [p for p in sys.path if Path(p or ".").resolve() != Path(__file__).resolve().parent]
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from planning.assembly import (  # noqa: E402
    Assembly,
    AssemblyPart,
    load_mesh,
    neighbours_in_part_frame,
    outward_directions,
    read_assembly,
    write_assembly,
)
from planning.convex import convex_pieces  # noqa: E402
from planning.mesh_damage import AS_EXPORTED, DAMAGES, damaged, export_flaws, is_board  # noqa: E402
from planning.mesh_intake import DEFAULT_SHEET_THICKNESS_M, intake_mesh  # noqa: E402

REPO = Path(__file__).resolve().parents[1]


def raw_assembly(folder: Path) -> Assembly:
    """The assembly with its meshes as written (no intake), poses from the intake-read assembly."""
    read = read_assembly(folder)
    parts = [AssemblyPart(p.name, load_mesh(folder / p.mesh_file, p.name), p.assembly_from_part, p.mesh_file)
             for p in read.parts]
    return Assembly(read.name, parts, dict(read.metadata))


def _part_seed(seed: int, index: int) -> int:
    return int(np.random.default_rng([seed, index]).integers(2**31))


def broken_assembly(assembly: Assembly, damage: str, seed: int) -> Assembly:
    parts = [AssemblyPart(p.name, damaged(p.mesh, damage, _part_seed(seed, k)), p.assembly_from_part, p.mesh_file)
             for k, p in enumerate(assembly.parts)]
    return Assembly(assembly.name, parts, dict(assembly.metadata))


def _identical(mesh, other) -> bool:
    """Whether two meshes are the same bytes: the same vertices and faces in the same order."""
    return (mesh.vertices.shape == other.vertices.shape and mesh.faces.shape == other.faces.shape
            and np.array_equal(mesh.vertices, other.vertices) and np.array_equal(mesh.faces, other.faces))


def build(objects: list[tuple[str, Assembly]], rows: dict, args, work: Path) -> None:
    """Build every (damage, broken assembly) through ``python -m cell.run --poses`` on ``python -m cell.batch``, as
    ``benchmarks/cell_assembly.py`` builds the intact ones; each record goes to its damage's row."""
    from benchmarks.cell_assembly import run_scaled
    from cell.batch import Engine

    def on_record(damage: str, record: dict) -> None:
        rows[damage]["build"].append(record)
        failure = (record.get("failure") or {}).get("message", "")
        print(f"  build {record['name']}: exit {record['exit_code']} scale {record['scale']} "
              f"{record['wall_s'] or 0:.0f} s {failure[:160]}", flush=True)

    started = time.perf_counter()
    try:
        with Engine(args.workers, args.scheduler) as engine:
            print(f"building {len(objects)} broken objects on {engine.description}", flush=True)
            run_scaled(objects, engine, work, args.keep, on_record)
    except KeyboardInterrupt:  # Ctrl-C: the tables count the builds that ended
        print("interrupted: the builds that ended are counted below", flush=True)
    print(f"builds: {time.perf_counter() - started:.0f} s wall clock", flush=True)


def first_decomposition_s(solids: list) -> float:
    """Seconds to cut every part's solid into convex pieces, as a first run does (no cache read or written)."""
    start = time.perf_counter()
    for solid in solids:
        convex_pieces(solid, use_cache=False)
    return time.perf_counter() - start


def sequenced(folder: Path, time_budget_s: float) -> tuple[bool, str]:
    from planning.sequence import plan_assembly_sequence

    try:
        result = plan_assembly_sequence(read_assembly(folder), seed=0, time_budget_s=time_budget_s)
    except Exception as exc:  # a traceback is a finding here, not a reason to stop
        return False, f"{exc.__class__.__name__}: {exc}"
    return bool(result.success), "" if result.success else str(result.reason)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--furniture", type=Path, default=REPO.parent / "shared" / "furniture")
    parser.add_argument("--objects", nargs="*", help="object folder names (default: all)")
    parser.add_argument("--damages", nargs="*", default=[*DAMAGES, AS_EXPORTED], choices=[*DAMAGES, AS_EXPORTED])
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--sequence", action="store_true", help="run the sequence planner on each broken object")
    parser.add_argument("--decompose", action="store_true",
                        help="time each object's first convex decomposition (no cache), intact and broken")
    parser.add_argument("--build", action="store_true", help="run python -m cell.run --poses on each broken object")
    parser.add_argument("--time-budget", type=float, default=10.0, help="sequence search budget per object (s)")
    parser.add_argument("--workers", type=int, default=1, help="--build: objects built side by side")
    parser.add_argument("--scheduler", metavar="ADDRESS", help="--build: on an existing Dask cluster instead")
    parser.add_argument("--keep", type=Path, help="--build: keep each build's output folder here")
    args = parser.parse_args(argv)
    folders = sorted(p.parent for p in args.furniture.glob("*/assembly.json"))
    if args.objects:
        folders = [f for f in folders if f.name in set(args.objects)]
    if not folders:
        parser.error(f"no assembly folders under {args.furniture}")
    print(f"{len(folders)} objects, damages: {', '.join(args.damages)}, seed {args.seed}, "
          f"{os.cpu_count()} CPUs, load {os.getloadavg()[0]:.1f}", flush=True)
    rows: dict[str, dict] = {d: {"errors": [], "boards": [], "seconds": [], "seq": [], "build": [], "same": 0,
                                 "decompose": []} for d in args.damages}
    intact_decompose: list[float] = []
    to_build: list[tuple[str, Assembly]] = []  # (damage, broken assembly) whose solids differ from the intact ones
    intact_seq = []
    outliers: list[str] = []
    with tempfile.TemporaryDirectory(prefix="mesh_intake_") as tmp:
        for folder in folders:
            intact = raw_assembly(folder)
            outward = dict(zip((p.name for p in intact.parts), outward_directions(
                [p.mesh for p in intact.parts], [p.assembly_from_part for p in intact.parts])))
            solids = {p.name: intake_mesh(p.mesh, p.name).mesh for p in intact.parts}
            if args.sequence:
                intact_seq.append(sequenced(folder, args.time_budget))
            if args.decompose:
                intact_decompose.append((first_decomposition_s(list(solids.values())), folder.name))
            for damage in args.damages:
                broken = broken_assembly(intact, damage, args.seed)
                row = rows[damage]
                same = True
                broken_solids = []
                for k, (part, original) in enumerate(zip(broken.parts, intact.parts)):
                    start = time.perf_counter()  # as the readers do (planning.assembly.solid_meshes)
                    neighbours = partial(neighbours_in_part_frame, [p.mesh for p in broken.parts],
                                         [p.assembly_from_part for p in broken.parts], k)
                    result = intake_mesh(part.mesh, part.name, outward=outward[part.name], neighbours=neighbours)
                    row["seconds"].append(time.perf_counter() - start)
                    broken_solids.append(result.mesh)
                    same &= _identical(result.mesh, solids[part.name])
                    drawn = (export_flaws(original.mesh, _part_seed(args.seed, k)) if damage == AS_EXPORTED
                             else (damage,))
                    error = result.volume_after / solids[part.name].volume - 1.0
                    if "one_surface" in drawn and is_board(original.mesh):
                        sheet = result.volume_after / (part.mesh.area * DEFAULT_SHEET_THICKNESS_M) - 1.0
                        row["boards"].append((error, sheet))
                        error = min(error, sheet, key=abs)
                    else:
                        row["errors"].append(error)
                    if abs(error) > 0.05 or row["seconds"][-1] > 1.0:
                        outliers.append(f"{folder.name}/{part.name} {damage}: volume {100 * error:+.1f}%, "
                                        f"{row['seconds'][-1]:.1f} s ({'; '.join(result.fixes)})")
                if args.decompose:
                    row["decompose"].append((first_decomposition_s(broken_solids), folder.name))
                if args.sequence:
                    ok, why = sequenced(write_assembly(broken, Path(tmp) / f"{folder.name}_{damage}"),
                                        args.time_budget)
                    row["seq"].append(ok)
                    if not ok:
                        print(f"  not sequenced: {folder.name} {damage}: {why}", flush=True)
                if args.build and same:
                    row["same"] += 1
                elif args.build:
                    to_build.append((damage, Assembly(f"{folder.name}__{damage}", broken.parts,
                                                      dict(broken.metadata))))
            print(f"{folder.name}: done", flush=True)
        if to_build:  # damage by damage, in the order given: an interrupted run has whole rows
            to_build.sort(key=lambda item: args.damages.index(item[0]))
            build(to_build, rows, args, Path(tmp))
    print("\n| damage | parts | median abs. volume error | p95 | max | within 5% | one-surface boards within 5% of "
          "the intact volume / of area x 3 mm | intake median s/part | max s/part |"
          + (" sequenced |" if args.sequence else "")
          + (" first decomposition, median / max s per object |" if args.decompose else "")
          + (" built, of the objects whose solids changed |" if args.build else ""))
    print("|---|---|---|---|---|---|---|---|---|" + "---|" * (args.sequence + args.decompose + args.build))
    for damage, row in rows.items():
        errors = np.abs(np.array(row["errors"])) if row["errors"] else np.zeros(1)
        boards = np.abs(np.array(row["boards"])).reshape(-1, 2)  # against the intact volume, against area x 3 mm
        board_text = (f"{np.count_nonzero(boards[:, 0] <= 0.05)} / {np.count_nonzero(boards[:, 1] <= 0.05)} of "
                      f"{len(boards)}" if len(boards) else "-")
        line = (f"| {damage} | {len(row['errors'])} | {100 * np.median(errors):.2f}% | "
                f"{100 * np.percentile(errors, 95):.1f}% | {100 * errors.max():.1f}% | "
                f"{np.count_nonzero(errors <= 0.05)}/{len(row['errors'])} | {board_text} | "
                f"{np.median(row['seconds']):.3f} | {np.max(row['seconds']):.2f} |")
        if args.sequence:
            line += f" {sum(row['seq'])}/{len(row['seq'])} |"
        if args.decompose:
            seconds, slowest = max(row["decompose"])
            line += f" {np.median([s for s, _ in row['decompose']]):.1f} / {seconds:.1f} ({slowest}) |"
        if args.build:
            built = sum(record["exit_code"] == 0 for record in row["build"])
            line += f" {built}/{len(row['build'])} ({row['same']} identical) |"
        print(line)
    if outliers:
        print(f"\n{len(outliers)} parts off by more than 5% or slower than 1 s:")
        print("\n".join(f"- {line}" for line in outliers))
    if args.sequence:
        print(f"\nintact objects sequenced: {sum(ok for ok, _ in intact_seq)}/{len(intact_seq)}")
    if args.decompose:
        seconds, slowest = max(intact_decompose)
        print(f"\nintact objects, first decomposition: median {np.median([s for s, _ in intact_decompose]):.1f} s, "
              f"max {seconds:.1f} s per object ({slowest})")
    for row in rows.values():
        for record in row["build"]:
            if record["exit_code"] != 0:
                failure = record.get("failure") or {}
                print(f"- not built: {record['name']} (scale {record['scale']}): exit {record['exit_code']}, "
                      f"{failure.get('stage')}: {failure.get('message', '')[:300]}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
