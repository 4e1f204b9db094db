"""How well the picture-agreement verdict of ``python -m cell.run --image`` tells right assemblies from wrong ones.

    python benchmarks/picture_agreement.py --out out/agreement_bench --count 40 [--furniture ../shared/furniture]

Test sets: ``--count`` fresh level-3 procedural objects per category, drawn as ``python -m perception.synth --seed
424242`` draws them (never used for training), written once under ``OUT/sets/``; optionally the real assemblies of
``--furniture``. Each object is rendered once (:mod:`perception.evaluate_assemblies`, parts in a random order),
predicted with the bundled weights and repaired as ``cell.run`` repairs it; then the repaired assembly and the true
one are drawn against the object in the picture (:mod:`perception.agreement`: the silhouette IoU and the share of
the picture's edges inside the object that the drawing explains). An object is *right* when every part passes Part
Accuracy after repair. Prints, per set and pair of thresholds (the silhouette's with the edges' in use, then the
edges' with the silhouette's): how many of the predictions pass the verdict, how many of those are right (the wrong
ones that pass are what the verdict must avoid), how many right predictions it refuses, and how many true assemblies
(drawn with the true camera) pass: a threshold must let nearly all of those through.
Writes every figure to ``OUT/agreement.json``.
"""

from __future__ import annotations

import argparse
import json
import platform
import subprocess
import sys
from pathlib import Path

import numpy as np

sys.path[:] = [p for p in sys.path if Path(p or ".").resolve() != Path(__file__).resolve().parent]
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from cell.pipeline import MIN_EDGE_RECALL, MIN_SILHOUETTE_IOU  # noqa: E402
from perception.evaluate_assemblies import evaluate_assemblies  # noqa: E402
from perception.weights import load_for_inference  # noqa: E402

IOU_THRESHOLDS = (0.0, 0.6, 0.7, 0.8, 0.85, 0.9)
EDGE_THRESHOLDS = (0.0, 0.7, 0.8, 0.85, 0.9)
CATEGORIES = ("chair", "table", "cabinet")


def build_sets(out: Path, count: int, categories=CATEGORIES) -> dict[str, Path]:
    """``count`` fresh level-3 objects per category (``perception.synth --seed 424242``, never used for training),
    written once under ``out/sets/``: label -> folder."""
    sets = {}
    for category in categories:
        folder = out / "sets" / f"{category}_3"
        if not folder.is_dir() or len(list(folder.iterdir())) < count:
            subprocess.run([sys.executable, "-m", "perception.synth", "--category", category, "--level", "3",
                            "--count", str(count), "--seed", "424242", "--out", str(folder), "--overwrite"],
                           check=True, capture_output=True)
        sets[f"{category} (level 3)"] = folder
    return sets


def add_set_arguments(parser: argparse.ArgumentParser, out: str) -> None:
    """The test-set options the picture benchmarks share: ``--out`` (default ``out``), ``--count``,
    ``--categories`` and ``--furniture`` (:func:`test_sets` reads them)."""
    parser.add_argument("--out", type=Path, default=Path(out))
    parser.add_argument("--count", type=int, default=40, help="procedural objects per category")
    parser.add_argument("--categories", nargs="*", choices=CATEGORIES, default=list(CATEGORIES),
                        help="procedural sets (none: only --furniture)")
    parser.add_argument("--furniture", type=Path, help="folder of real assembly folders (../shared/furniture)")


def test_sets(args: argparse.Namespace) -> dict[str, Path]:
    """The sets :func:`add_set_arguments`' options name, label -> folder: the procedural ones built once under
    ``--out`` (:func:`build_sets`), then the real furniture where given."""
    args.out.mkdir(parents=True, exist_ok=True)
    sets = build_sets(args.out, args.count, args.categories)
    if args.furniture is not None:
        sets["real furniture"] = args.furniture
    return sets


def rows_of(figures: dict) -> list[dict]:
    rows = []
    for o in figures["per_object"]:
        agreement = o["picture_agreement"]
        if not agreement:
            continue
        rows.append({"name": o["name"], "right": bool(o["part_accuracy_repaired"] == 1.0),
                     "part_accuracy_repaired": o["part_accuracy_repaired"], **agreement})
    return rows


def _passes(r: dict, who: str, min_iou: float, min_edge: float) -> bool:
    return r[f"{who}_iou"] >= min_iou and (r[f"{who}_edge_recall"] or 0.0) >= min_edge


def table(name: str, rows: list[dict]) -> list[str]:
    right = sum(r["right"] for r in rows)
    lines = [f"\n{name}: {len(rows)} objects, {right} right (every part passes PA after repair); median silhouette "
             f"IoU truth {np.median([r['truth_iou'] for r in rows]):.3f}, prediction "
             f"{np.median([r['repaired_iou'] for r in rows]):.3f}; median edges explained truth "
             f"{np.median([r['truth_edge_recall'] for r in rows]):.3f}, prediction "
             f"{np.median([r['repaired_edge_recall'] for r in rows]):.3f}\n",
             "| silhouette IoU at least | edges explained at least | predictions passing | of them right | "
             "wrong passing | right refused | truth passing |", "|---|---|---|---|---|---|---|"]
    grid = [(t, MIN_EDGE_RECALL) for t in IOU_THRESHOLDS] + [(MIN_SILHOUETTE_IOU, e) for e in EDGE_THRESHOLDS
                                                         if e != MIN_EDGE_RECALL]
    for min_iou, min_edge in grid:
        passing = [r for r in rows if _passes(r, "repaired", min_iou, min_edge)]
        good = sum(r["right"] for r in passing)
        used = abs(min_iou - MIN_SILHOUETTE_IOU) < 1e-9 and abs(min_edge - MIN_EDGE_RECALL) < 1e-9
        truth = sum(_passes(r, "truth", min_iou, min_edge) for r in rows)
        lines.append(f"| {min_iou:.2f} | {min_edge:.2f}{' (used)' if used else ''} | {len(passing)} | {good} | "
                     f"{len(passing) - good} | {right - good} | {truth} of {len(rows)} |")
    return lines


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_set_arguments(parser, "out/agreement_bench")
    parser.add_argument("--seed", type=int, default=0, help="views and part orders")
    args = parser.parse_args()
    sets = test_sets(args)
    model, _, _, checkpoint = load_for_inference(None)
    results, lines = {}, [f"machine: {platform.machine()}, weights: {checkpoint.name}"]
    for name, folder in sets.items():
        figures = evaluate_assemblies(model, folder, views=1, seed=args.seed, progress=True)
        results[name] = rows_of(figures)
        lines += table(name, results[name])
        (args.out / "agreement.json").write_text(json.dumps(results, indent=1))
    text = "\n".join(lines)
    print(text)
    (args.out / "agreement.md").write_text(text + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
