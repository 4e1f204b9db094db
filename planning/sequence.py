"""Assembly sequence of an assembly folder: ``python -m planning.sequence ASSEMBLY_DIR [--poses JSON] [--json OUT]``.

Prints a table (step, part, insertion direction, grasp, supporting parts) and writes it as JSON. Exit codes:
0 a sequence was found, 3 none exists (the reason is printed), 2 bad input.
"""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Iterator, Mapping
from pathlib import Path

import numpy as np

from planning.assembly import Assembly, AssemblyError, read_assembly, read_poses
from planning.collision import ConvexPart, box_distance, world_bounds
from planning.convex import mesh_key
from planning.disassembly import OFF_FLOOR, UNSUPPORTING, SequenceResult, _direction_label, plan_sequence
from planning.fixture import PAD_HEIGHT_M, fixture_pads
from planning.grasp import Grasp, antipodal_grasps, feasible_grasps
from planning.gripper import clearance_gripper
from planning.mesh_intake import summary_line
from planning.pose import Pose
from planning.robot_collision import LINK_CLEARANCE_M

HAND_REACH_M = 0.2  # parts farther than this from a part's target cannot touch the hand holding it


def with_poses(assembly: Assembly, poses: dict[str, Pose], source: str) -> Assembly:
    """``assembly`` with its target poses replaced by ``poses`` (every part named exactly once)."""
    names = set(assembly.part_names)
    missing, extra = sorted(names - set(poses)), sorted(set(poses) - names)
    if missing or extra:
        details = "; ".join(filter(None, [
            f"missing parts: {', '.join(missing)}" if missing else "",
            f"parts not in the assembly: {', '.join(extra)}" if extra else "",
        ]))
        raise AssemblyError(f"{source}: poses do not match the assembly's parts ({details})")
    parts = [type(p)(p.name, p.mesh, poses[p.name], p.mesh_file) for p in assembly.parts]
    return Assembly(assembly.name, parts, dict(assembly.metadata), dict(assembly.mesh_intake))


class GraspCandidates(Mapping):
    """Antipodal grasp candidates per part name (part frame), computed on first access and shared between parts
    with identical meshes: a part draws its sampling seed from ``default_rng([seed, i])``, ``i`` the index of the
    first part in the assembly with the same mesh (:func:`planning.convex.mesh_key`), so identical boards get one
    candidate set, computed once (:func:`planning.grasp.antipodal_grasps` caches by mesh and seed)."""

    def __init__(self, assembly: Assembly, seed: int = 0) -> None:
        self._meshes = {p.name: p.mesh for p in assembly.parts}
        first: dict[str, int] = {}
        self._seed_index = {p.name: first.setdefault(mesh_key(p.mesh), i) for i, p in enumerate(assembly.parts)}
        self._seed = seed
        self._computed: dict[str, list[Grasp]] = {}

    def __getitem__(self, name: str) -> list[Grasp]:
        if name not in self._computed:
            if name not in self._meshes:
                raise KeyError(name)
            rng = np.random.default_rng([self._seed, self._seed_index[name]])
            self._computed[name] = antipodal_grasps(self._meshes[name], rng)
        return self._computed[name]

    def __iter__(self) -> Iterator[str]:
        return iter(self._meshes)

    def __len__(self) -> int:
        return len(self._meshes)

    def computed(self) -> dict[str, list[Grasp]]:
        """The candidate lists computed so far (nothing is computed by this call)."""
        return dict(self._computed)


class GraspChecker:
    """Grasp feasibility at the target: antipodal candidates per part (:class:`GraspCandidates`, part frame,
    computed when first needed), checked against the parts present near the target, the fixture pads
    (:mod:`planning.fixture`) and the cell's table under them."""

    def __init__(self, assembly: Assembly, seed: int = 0) -> None:
        self.assembly = assembly
        self.candidates = GraspCandidates(assembly, seed)
        self.bounds = {p.name: world_bounds(p.mesh, p.assembly_from_part) for p in assembly.parts}
        self.pads = fixture_pads(assembly.part_names, assembly.meshes_in_assembly_frame())
        self.pad_obstacles = [(pad.mesh(), pad.assembly_from_pad) for pad in self.pads]

    def feasible(self, name: str, present: frozenset, insertion_direction: np.ndarray) -> list[Grasp]:
        """The grasps of part ``name`` that the hand can use at its target among the parts ``present``, inserted
        along ``insertion_direction`` (assembly frame), best first."""
        candidates = self.candidates[name]
        if not candidates:
            return []
        part = self.assembly.part(name)
        near = [self.assembly.part(n) for n in sorted(present)
                if box_distance(self.bounds[name], self.bounds[n]) < HAND_REACH_M]
        obstacles = [(p.mesh, p.assembly_from_part) for p in near] + self.pad_obstacles
        return feasible_grasps(candidates, part.assembly_from_part, obstacles, insertion_direction,
                               floor_z=-PAD_HEIGHT_M, closed_gripper=clearance_gripper(LINK_CLEARANCE_M))

    def __call__(self, name: str, present: frozenset, insertion_direction: np.ndarray) -> Grasp | None:
        feasible = self.feasible(name, present, insertion_direction)
        return feasible[0] if feasible else None


def plan_assembly_sequence(assembly: Assembly, seed: int = 0, check_grasps: bool = True,
                           time_budget_s: float = 10.0, grasp_check=None,
                           max_overlap_exit_m: float | None = None) -> SequenceResult:
    """Assembly order of ``assembly`` at its poses (metres, +z up, floor at z = 0). ``grasp_check``: replaces the
    hand's check at the target (:class:`GraspChecker`), e.g. one that asks the arm too (``cell.plan``).
    ``max_overlap_exit_m``: as in :func:`planning.disassembly.plan_sequence`."""
    parts = [ConvexPart.from_mesh(p.name, p.mesh) for p in assembly.parts]
    poses = [p.assembly_from_part for p in assembly.parts]
    checker = (grasp_check or GraspChecker(assembly, seed)) if check_grasps else None
    result = plan_sequence(parts, poses, checker, time_budget_s=time_budget_s, max_overlap_exit_m=max_overlap_exit_m)
    if not result.success and isinstance(checker, GraspChecker):
        graspless = [n for n, c in checker.candidates.items() if not c]  # computes the ones not asked for yet
        if graspless:
            from planning.grasp import explain_no_grasp

            result.reason += "; no grasp at all: " + "; ".join(
                explain_no_grasp(assembly.part(n).mesh, part_name=n) for n in graspless)
    return result


def failure_summary(result: SequenceResult, limit: int = 2) -> str:
    """``result.reason`` with why the first ``limit`` parts of the sub-assembly the search could not take apart
    stayed in, the parts blocked or without a grasp before those whose removal would leave others unsupported
    (those follow from the first)."""
    ranked = sorted(result.blocking.items(), key=lambda item: (result.blocking_kind.get(item[0]) == UNSUPPORTING,
                                                               item[0]))
    if not ranked or OFF_FLOOR in result.blocking_kind.values():  # refused before any search: said in full
        return result.reason
    why = "; ".join(f"{part!r}: {text}" for part, text in ranked[:limit])
    more = f"; {len(ranked) - limit} more in report.json" if len(ranked) > limit else ""
    return f"{result.reason} (why: {why}{more})"


def result_to_json(assembly: Assembly, result: SequenceResult) -> dict:
    steps = []
    for index, step in enumerate(result.steps, start=1):
        grasp = step.grasp if isinstance(step.grasp, Grasp) else None
        steps.append({
            "step": index,
            "part": step.part,
            "insertion_direction": [round(float(v), 6) for v in step.insertion_direction],
            "grasp": None if grasp is None else {
                "part_from_tcp": grasp.part_from_tcp.to_dict(),
                "width_m": round(grasp.width_m, 6),
                "opening_m": round(grasp.opening_m, 6),
                "score": round(grasp.score, 4),
            },
            "fastened_to": list(step.fastened_to),
            "rests_on": list(step.rests_on),
        })
    return {
        "assembly": assembly.name,
        "success": result.success,
        "reason": result.reason,
        "blocking": result.blocking,
        "blocking_kind": result.blocking_kind,
        "seconds": round(result.seconds, 4),
        "steps": steps,
    }


def format_table(assembly: Assembly, result: SequenceResult) -> str:
    rows = [("step", "part", "insert", "grasp", "fastened to (rests on)")]
    for index, step in enumerate(result.steps, start=1):
        grasp = step.grasp if isinstance(step.grasp, Grasp) else None
        if grasp is not None:
            approach = assembly.part(step.part).assembly_from_part.rotation @ grasp.approach_part
            grasp_text = f"{grasp.width_m * 100:.1f} cm, approach {_direction_label(approach)}"
        else:
            grasp_text = "-"
        fastened = ", ".join(step.fastened_to) or "-"
        if step.rests_on:
            fastened += f" ({', '.join(step.rests_on)})"
        rows.append((str(index), step.part, _direction_label(step.insertion_direction), grasp_text, fastened))
    widths = [max(len(r[i]) for r in rows) for i in range(len(rows[0]))]
    lines = ["  ".join(cell.ljust(w) for cell, w in zip(row, widths)).rstrip() for row in rows]
    lines.insert(1, "  ".join("-" * w for w in widths))
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m planning.sequence", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("assembly", type=Path, help="assembly folder (assembly.json + parts/)")
    parser.add_argument("--poses", type=Path, help="assembly.json whose poses replace the folder's")
    parser.add_argument("--json", type=Path, help="write the sequence here")
    parser.add_argument("--seed", type=int, default=0, help="seed of the grasp sampling")
    parser.add_argument("--time-budget", type=float, default=10.0, help="seconds for the search")
    parser.add_argument("--no-grasps", action="store_true", help="skip the grasp check")
    args = parser.parse_args(argv)
    try:
        assembly = read_assembly(args.assembly)
        if args.poses is not None:
            assembly = with_poses(assembly, read_poses(args.poses), str(args.poses))
    except AssemblyError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    if summary_line(assembly.mesh_intake):
        print(summary_line(assembly.mesh_intake), file=sys.stderr)
    result = plan_assembly_sequence(assembly, args.seed, not args.no_grasps, args.time_budget)
    if result.success:
        print(f"{assembly.name}: {len(result.steps)} steps ({result.seconds:.2f} s)")
        print(format_table(assembly, result))
    else:
        print(f"{assembly.name}: no assembly sequence: {result.reason}", file=sys.stderr)
        for part, why in result.blocking.items():
            print(f"  {part}: {why}", file=sys.stderr)
    if args.json is not None:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        tmp = args.json.with_suffix(args.json.suffix + ".tmp")
        tmp.write_text(json.dumps(result_to_json(assembly, result), indent=1) + "\n")
        tmp.replace(args.json)
    return 0 if result.success else 3


if __name__ == "__main__":
    sys.exit(main())
