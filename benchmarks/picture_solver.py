"""Does fitting the prediction to its picture (perception.solver) raise Part Accuracy? The ablation, per set.

    python benchmarks/picture_solver.py --out out/solver_bench --count 40 [--materials parts one]
        [--variants default "no relocations"] [--categories chair table cabinet] [--furniture ../shared/furniture]
    python benchmarks/picture_solver.py --out out/solver_bench --categories --furniture ../shared/furniture

Test sets: ``--count`` fresh level-3 procedural objects per category, drawn as ``python -m perception.synth --seed
424242`` draws them (never used for training; the same sets as ``benchmarks/picture_agreement.py``), written once
under ``OUT/sets/``; optionally the real assemblies of ``--furniture``. Each object is rendered once
(:mod:`perception.evaluate_assemblies`, parts in a random order, the parts coloured as ``--materials`` says: the
same views in every mode), predicted with the bundled weights, and scored four ways: the network alone, after the
pose repair (what ``cell.run`` builds today), after the solver, and after the solver and the repair. Each figure
is level-3 Part Accuracy over all parts, and the right-object rate: the share of objects whose every part passes.
``--variants`` names solver settings from :data:`VARIANTS` (the default settings, and the search with one kind
of move left out or alone). Prints a Markdown table and writes every figure to ``OUT/solver.json``.
"""

from __future__ import annotations

import argparse
import json
import platform
import sys
from pathlib import Path

sys.path[:] = [p for p in sys.path if Path(p or ".").resolve() != Path(__file__).resolve().parent]
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks.picture_agreement import add_set_arguments, test_sets  # noqa: E402
from cell.render import MATERIALS  # noqa: E402
from perception.evaluate_assemblies import evaluate_assemblies  # noqa: E402
from perception.solver import SolverSettings  # noqa: E402
from perception.weights import load_for_inference  # noqa: E402

NOTHING_MOVES = {"steps": (), "spreads": (), "relocation_rounds": 0}
VARIANTS = {
    "default": {},
    "no relocations": {"relocation_rounds": 0},
    "relocations only": {"steps": (), "spreads": (), "turn_weight": 10.0},
    "turns only": {**NOTHING_MOVES},
    "steps only, assembly axes": {"spreads": (), "relocation_rounds": 0, "turn_weight": 10.0,
                                  "image_plane_moves": False},
    "every part movable": {"movable_below": 1.01},
    "no drawing fit": {"fit_drawing": False},
}
STAGES = ("network", "repair", "solver", "solver_repair")


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_set_arguments(parser, "out/solver_bench")
    parser.add_argument("--materials", nargs="+", choices=MATERIALS, default=["parts"])
    parser.add_argument("--variants", nargs="+", choices=sorted(VARIANTS), default=["default"])
    parser.add_argument("--seed", type=int, default=0, help="views and part orders")
    args = parser.parse_args()
    sets = test_sets(args)
    model, _, _, checkpoint = load_for_inference(None)
    figures_path = args.out / "solver.json"
    results = json.loads(figures_path.read_text()) if figures_path.is_file() else {}
    lines = [f"machine: {platform.machine()}, weights: {checkpoint.name}", "",
             "| set | pictures | solver settings | views | network | + repair | + solver | + solver + repair | "
             "solver s, median / max |", "|---|---|---|---|---|---|---|---|---|"]
    for name, folder in sets.items():
        for materials in args.materials:
            for variant in args.variants:
                key = f"{name} | {materials} | {variant}"
                if key not in results:
                    figures = evaluate_assemblies(model, folder, views=1, seed=args.seed, progress=True,
                                                  solver=SolverSettings(**VARIANTS[variant]), materials=materials)
                    results[key] = {**figures["after_solver"], "per_object": [
                        {k: o.get(k) for k in ("name", "part_accuracy", "part_accuracy_repaired",
                                               "part_accuracy_solved", "part_accuracy_solved_before_repair")}
                        for o in figures["per_object"]]}
                    figures_path.write_text(json.dumps(results, indent=1))
                r = results[key]
                cells = " | ".join(f"{r['stages'][s]['part_accuracy']:.3f} ({r['stages'][s]['right_object_rate']:.2f})"
                                   for s in STAGES)
                lines.append(f"| {name} | {materials} | {variant} | {r['views']} | {cells} | "
                             f"{r['seconds']['median']:.2f} / {r['seconds']['max']:.2f} |")
                print(lines[-1], flush=True)
    text = "\n".join(lines)
    print("\n" + text)
    (args.out / "solver.md").write_text(text + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
