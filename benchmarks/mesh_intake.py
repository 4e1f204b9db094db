"""The mesh intake on broken copies of real parts: volume restored, time per part, and whether the planner still
sequences (and, optionally, the cell builds) the object.

    python benchmarks/mesh_intake.py --furniture ../shared/furniture
    python benchmarks/mesh_intake.py --furniture ../shared/furniture --sequence --objects chair_agne_0007 ...
    python benchmarks/mesh_intake.py --furniture ../shared/furniture --objects table_hemnes_0539 --damages soup \\
        --build

Every part of every object (``--objects``: these only) is broken in each way of :data:`planning.mesh_damage.DAMAGES`
(seeded by ``[--seed, part index]``) and given to :func:`planning.mesh_intake.intake_mesh` with the side its
assembly would give a one-surface board. Per damage: the parts' volume error against the intake's solid of the
intact part (boards drawn as one surface against their drawn area times the sheet thickness instead, counted
apart), the share within 5%, and the intake's time per part (wall clock, one process). ``--sequence`` writes each
broken object as an assembly folder and runs ``planning.sequence``'s planner on it with the true poses (seed 0,
grasps checked), and on the intact object for comparison; convex decompositions of repaired meshes are new, and
take seconds each the first time (cached on disk after). ``--build`` also runs ``python -m cell.run --poses`` on
each broken object (minutes each: give a few ``--objects`` and ``--damages``). Prints Markdown tables.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

# Run as a script, this file's folder comes first on sys.path, where a module named like a package would hide the
# perception package: look in the repository root instead.
sys.path[:] = [p for p in sys.path if Path(p or ".").resolve() != Path(__file__).resolve().parent]
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from planning.assembly import Assembly, AssemblyPart, load_mesh, read_assembly, write_assembly  # noqa: E402
from planning.mesh_damage import DAMAGES, damaged, is_board  # noqa: E402
from planning.mesh_intake import DEFAULT_SHEET_THICKNESS_M, intake_mesh  # noqa: E402

REPO = Path(__file__).resolve().parents[1]


def raw_assembly(folder: Path) -> Assembly:
    """The assembly with its meshes as written (no intake), poses from the intake-read assembly."""
    read = read_assembly(folder)
    parts = [AssemblyPart(p.name, load_mesh(folder / p.mesh_file, p.name), p.assembly_from_part, p.mesh_file)
             for p in read.parts]
    return Assembly(read.name, parts, dict(read.metadata))


def outward_directions(assembly: Assembly) -> dict[str, np.ndarray]:
    """Per part, the direction (part frame) away from the assembly's centre, as the assembly reader gives it."""
    centre = assembly.bounds().mean(axis=0)
    return {p.name: p.assembly_from_part.rotation.T @ (p.assembly_from_part.apply(p.mesh.bounds.mean(axis=0)) - centre)
            for p in assembly.parts}


def broken_assembly(assembly: Assembly, damage: str, seed: int) -> Assembly:
    parts = [AssemblyPart(p.name, damaged(p.mesh, damage, int(np.random.default_rng([seed, k]).integers(2**31))),
                          p.assembly_from_part, p.mesh_file) for k, p in enumerate(assembly.parts)]
    return Assembly(assembly.name, parts, dict(assembly.metadata))


def sequenced(folder: Path, time_budget_s: float) -> tuple[bool, str]:
    from planning.sequence import plan_assembly_sequence

    try:
        result = plan_assembly_sequence(read_assembly(folder), seed=0, time_budget_s=time_budget_s)
    except Exception as exc:  # a traceback is a finding here, not a reason to stop
        return False, f"{exc.__class__.__name__}: {exc}"
    return bool(result.success), "" if result.success else str(result.reason)


def built(folder: Path, out: Path) -> tuple[int, float]:
    start = time.perf_counter()
    done = subprocess.run([sys.executable, "-m", "cell.run", "--parts", str(folder / "parts"), "--poses",
                           str(folder / "assembly.json"), "--out", str(out), "--no-animation", "--quiet"],
                          cwd=REPO, capture_output=True, text=True)
    return done.returncode, time.perf_counter() - start


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--furniture", type=Path, default=REPO.parent / "shared" / "furniture")
    parser.add_argument("--objects", nargs="*", help="object folder names (default: all)")
    parser.add_argument("--damages", nargs="*", default=list(DAMAGES), choices=DAMAGES)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--sequence", action="store_true", help="run the sequence planner on each broken object")
    parser.add_argument("--build", action="store_true", help="run python -m cell.run --poses on each broken object")
    parser.add_argument("--time-budget", type=float, default=10.0, help="sequence search budget per object (s)")
    args = parser.parse_args(argv)
    folders = sorted(p.parent for p in args.furniture.glob("*/assembly.json"))
    if args.objects:
        folders = [f for f in folders if f.name in set(args.objects)]
    if not folders:
        parser.error(f"no assembly folders under {args.furniture}")
    print(f"{len(folders)} objects, damages: {', '.join(args.damages)}, seed {args.seed}, "
          f"{os.cpu_count()} CPUs, load {os.getloadavg()[0]:.1f}", flush=True)
    rows: dict[str, dict] = {d: {"errors": [], "boards": [], "seconds": [], "seq": [], "build": []}
                             for d in args.damages}
    intact_seq = []
    outliers: list[str] = []
    with tempfile.TemporaryDirectory(prefix="mesh_intake_") as tmp:
        for folder in folders:
            intact = raw_assembly(folder)
            outward = outward_directions(intact)
            volumes = {p.name: intake_mesh(p.mesh, p.name).volume_after for p in intact.parts}
            if args.sequence:
                intact_seq.append(sequenced(folder, args.time_budget))
            for damage in args.damages:
                broken = broken_assembly(intact, damage, args.seed)
                row = rows[damage]
                for part, original in zip(broken.parts, intact.parts):
                    start = time.perf_counter()
                    result = intake_mesh(part.mesh, part.name, outward=outward[part.name])
                    row["seconds"].append(time.perf_counter() - start)
                    if damage == "one_surface" and is_board(original.mesh):
                        error = result.volume_after / (part.mesh.area * DEFAULT_SHEET_THICKNESS_M) - 1.0
                        row["boards"].append(error)
                    else:
                        error = result.volume_after / volumes[part.name] - 1.0
                        row["errors"].append(error)
                    if abs(error) > 0.05 or row["seconds"][-1] > 1.0:
                        outliers.append(f"{folder.name}/{part.name} {damage}: volume {100 * error:+.1f}%, "
                                        f"{row['seconds'][-1]:.1f} s ({'; '.join(result.fixes)})")
                if args.sequence or args.build:
                    where = write_assembly(broken, Path(tmp) / f"{folder.name}_{damage}")
                    if args.sequence:
                        ok, why = sequenced(where, args.time_budget)
                        row["seq"].append(ok)
                        if not ok:
                            print(f"  not sequenced: {folder.name} {damage}: {why}", flush=True)
                    if args.build:
                        code, seconds = built(where, Path(tmp) / f"out_{folder.name}_{damage}")
                        row["build"].append(code == 0)
                        print(f"  build {folder.name} {damage}: exit {code} in {seconds:.0f} s", flush=True)
            print(f"{folder.name}: done", flush=True)
    print("\n| damage | parts | median abs. volume error | p95 | max | within 5% | one-surface boards (within 5% of "
          "area x 3 mm) | intake median s/part | max s/part |" + (" sequenced |" if args.sequence else "")
          + (" built |" if args.build else ""))
    print("|---|---|---|---|---|---|---|---|---|" + ("---|" if args.sequence else "") + ("---|" if args.build else ""))
    for damage, row in rows.items():
        errors = np.abs(np.array(row["errors"])) if row["errors"] else np.zeros(1)
        boards = np.abs(np.array(row["boards"]))
        board_text = f"{np.count_nonzero(boards <= 0.05)}/{len(boards)}" if len(boards) else "-"
        line = (f"| {damage} | {len(row['errors'])} | {100 * np.median(errors):.2f}% | "
                f"{100 * np.percentile(errors, 95):.1f}% | {100 * errors.max():.1f}% | "
                f"{np.count_nonzero(errors <= 0.05)}/{len(row['errors'])} | {board_text} | "
                f"{np.median(row['seconds']):.3f} | {np.max(row['seconds']):.2f} |")
        if args.sequence:
            line += f" {sum(row['seq'])}/{len(row['seq'])} |"
        if args.build:
            line += f" {sum(row['build'])}/{len(row['build'])} |"
        print(line)
    if outliers:
        print(f"\n{len(outliers)} parts off by more than 5% or slower than 1 s:")
        print("\n".join(f"- {line}" for line in outliers))
    if args.sequence:
        print(f"\nintact objects sequenced: {sum(ok for ok, _ in intact_seq)}/{len(intact_seq)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
