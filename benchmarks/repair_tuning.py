"""Repair settings compared on a tuning set: connectivity and Part Accuracy after :func:`planning.repair.repair_poses`
for several :class:`planning.repair.RepairSettings`, on Ours' predictions of procedural objects that neither
training (seed 0) nor the held-out test sets (seed 1000) use.

    python benchmarks/repair_tuning.py --count 25 --setting connect_distance_m=0.08 \
        --setting connect_distance_m=0.08,max_translation_m=0.08

Objects: ``--count`` per category (chair, table, cabinet, or ``--categories``) and level (3, mixed), drawn as
``python -m perception.synth --seed 2000`` draws them, parts in a random order, one view each rendered and
predicted as ``perception.evaluate --assemblies`` does (bundled weights, up from the picture); or with
``--furniture DIR`` each assembly folder in DIR once (the real furniture, which the held-out benchmark reports too:
choose settings on the procedural tuning set and use this as a check, not to tune). The network runs
once per object; every setting then repairs the same predicted poses. The first row is the default settings.
Columns: connectivity (parts touching another), one piece (objects whose parts form one connected whole), grounded
(objects whose every part has a path of contacts to the floor, which a standing build needs), sequenced (objects
for which :func:`planning.disassembly.plan_sequence` finds a standing order: every part leaves along a free line
and leaves the rest supported; grasps are not checked, so this is an upper bound on what the cell's sequence stage
finds). The pieces still
apart after the default repair are listed by their distance to the nearest part outside them, which is what
``connect_distance_m`` and ``max_translation_m`` decide. Prints a Markdown table.
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import time
from pathlib import Path

import numpy as np

# Run as a script, this file's folder comes first on sys.path and its name would hide the perception package.
sys.path[:] = [p for p in sys.path if Path(p or ".").resolve() != Path(__file__).resolve().parent]

from cell.render import render_assembly  # noqa: E402
from perception.elevation import image_elevation_deg  # noqa: E402
from perception.evaluate_assemblies import (  # noqa: E402
    assembly_folders,
    connectivity,
    grounded,
    network_frame,
    shuffled_parts,
    truth_targets,
)
from perception.metrics import evaluate_assembly  # noqa: E402
from perception.placement import place_parts  # noqa: E402
from perception.predict import prepare_parts, run_network  # noqa: E402
from perception.synth import generate  # noqa: E402
from perception.weights import BUNDLED_WEIGHTS, inference_threads, load_for_inference  # noqa: E402
from planning.assembly import read_assembly  # noqa: E402
from planning.collision import MAX_FITTING_OVERLAP_M, ConvexPart, signed_distance  # noqa: E402
from planning.contact import contact_graph, pieces  # noqa: E402
from planning.disassembly import plan_sequence  # noqa: E402
from planning.repair import RepairSettings, repair_poses  # noqa: E402

CATEGORIES = ("chair", "table", "cabinet")
LEVELS = ("3", "mixed")
TUNING_SEED = 2000  # geometry: neither training (seed 0) nor the test sets (seed 1000)


def parse_setting(text: str) -> RepairSettings:
    """``key=value,key=value`` over the defaults of :class:`RepairSettings`."""
    fields = {f.name: f.type for f in dataclasses.fields(RepairSettings)}
    values = {}
    for item in filter(None, text.split(",")):
        key, _, value = item.partition("=")
        if key not in fields or not value:
            raise SystemExit(f"--setting: {item!r} is not KEY=VALUE with KEY in {sorted(fields)}")
        values[key] = int(value) if fields[key] in ("int", int) else float(value)
    return RepairSettings(**values)


def tuning_assemblies(count: int, categories=CATEGORIES, furniture: Path | None = None):
    """Yield (label, assembly, index): ``count`` procedural objects per category and level, or with ``furniture``
    every assembly folder in it, in name order (label "real")."""
    if furniture is not None:
        for i, folder in enumerate(assembly_folders(furniture)):
            yield "real", read_assembly(folder), i
        return
    for category in categories:
        for level in LEVELS:
            for i in range(count):
                yield (f"{category} {level}",
                       generate(category, level, np.random.default_rng([TUNING_SEED, i]), f"{category}_{i}"), i)


def predicted_objects(count: int, model, max_parts: int, categories=CATEGORIES, furniture: Path | None = None):
    """Yield (label, convex parts, predicted assembly_from_part, scoring context) per object."""
    for label, assembly, i in tuning_assemblies(count, categories, furniture):
        assembly = shuffled_parts(assembly, TUNING_SEED, i)
        parts = prepare_parts([p.mesh for p in assembly.parts])
        view = render_assembly(assembly, np.random.default_rng([1, i]))
        bounds = assembly.bounds()
        gt = truth_targets(view, parts, view.camera_from_assembly.apply(0.5 * (bounds[0] + bounds[1])))
        quat, trans = run_network(model, view.rgb, parts, max_parts)
        placement = place_parts(quat, trans, parts.normalized, parts.meshes,
                                image_elevation_deg=image_elevation_deg(view.rgb))
        convex = [ConvexPart.from_mesh(p.name, p.mesh) for p in assembly.parts]
        yield label, convex, placement, (parts, gt, view.visible_pixels)


def piece_gaps_m(convex: list[ConvexPart], poses, contacts) -> list[float]:
    """For each piece but the largest (:func:`planning.contact.pieces` of ``contacts``, the parts' contact graph):
    the distance from its parts to the nearest part outside it (metres), what ``connect_distance_m`` and the bounds
    decide."""
    index = {part.name: i for i, part in enumerate(convex)}
    gaps = []
    for piece in pieces(contacts)[1:]:
        inside = [index[name] for name in piece]
        distances = [signed_distance(convex[i], poses[i], other, poses[j], 1.0) for i in inside
                     for j, other in enumerate(convex) if other.name not in piece]
        gaps.append(min((d.distance_m for d in distances if d.measured), default=float("inf")))
    return gaps


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--count", type=int, default=25, help="objects per category and level")
    parser.add_argument("--categories", nargs="+", choices=CATEGORIES, default=list(CATEGORIES),
                        help="only these categories (default: all)")
    parser.add_argument("--furniture", type=Path, help="the assembly folders in this folder instead (e.g. "
                        "../shared/furniture, real furniture never trained on), each once")
    parser.add_argument("--setting", action="append", default=[], help="KEY=VALUE[,KEY=VALUE] of RepairSettings "
                        "(repeatable); the defaults are always measured first")
    args = parser.parse_args()
    if args.furniture is not None:
        try:
            assembly_folders(args.furniture)
        except FileNotFoundError as exc:
            raise SystemExit(f"--furniture: {exc}") from exc
    settings = {"default": RepairSettings()} | {text: parse_setting(text) for text in args.setting}
    model, config, _, _ = load_for_inference(BUNDLED_WEIGHTS)
    keys = ("connectivity", "one_piece", "grounded", "sequenced", "pa", "moved_mm", "penetration_mm", "crossing",
            "label")
    rows = {name: {key: [] for key in keys} for name in settings}
    gaps: list[float] = []
    start = time.perf_counter()
    with inference_threads(1):
        for label, convex, placement, (parts, gt, visible) in predicted_objects(args.count, model,
                                                                                config.model.max_parts,
                                                                                args.categories, args.furniture):
            for name, setting in settings.items():
                repaired, report = repair_poses(convex, placement.assembly_from_part, setting)
                contacts = contact_graph(convex, repaired)
                fraction, whole = connectivity(contacts)
                quat, trans = network_frame([placement.camera_from_assembly @ p for p in repaired], parts,
                                            placement.centre_camera_m)
                result = evaluate_assembly(parts.normalized.points_norm, quat, trans, *gt, parts.classes, visible)
                row = rows[name]
                row["connectivity"].append(fraction)
                row["one_piece"].append(float(whole))
                row["grounded"].append(float(grounded(contacts)))
                row["sequenced"].append(float(plan_sequence(convex, repaired).success))
                row["pa"].append(float(np.mean(result.correct)))
                row["moved_mm"].append(1000 * max(report.translation_m.values()))
                row["penetration_mm"].append(1000 * report.deepest_penetration_after_m)
                row["crossing"].append(float(report.deepest_penetration_after_m > MAX_FITTING_OVERLAP_M))
                row["label"].append(label)
                if name == "default":
                    gaps += piece_gaps_m(convex, repaired, contacts)
            print(f"{label}: {len(rows['default']['pa'])} objects, {time.perf_counter() - start:.0f} s", flush=True)
    where = f"from {args.furniture}" if args.furniture is not None else f"(seed {TUNING_SEED})"
    print(f"\n{len(rows['default']['pa'])} objects {where}, {time.perf_counter() - start:.0f} s\n")
    print("| settings | connectivity | one piece | grounded | sequenced | PA repaired | largest move mean / max mm | "
          "deepest penetration after mean / max mm | crossing after repair |")
    print("|---|---|---|---|---|---|---|---|---|")
    for name, row in rows.items():
        print(f"| {name} | {np.mean(row['connectivity']):.3f} | {np.mean(row['one_piece']):.3f} | "
              f"{np.mean(row['grounded']):.3f} | {np.mean(row['sequenced']):.3f} | "
              f"{np.mean(row['pa']):.3f} | {np.mean(row['moved_mm']):.1f} / {np.max(row['moved_mm']):.1f} | "
              f"{np.mean(row['penetration_mm']):.1f} / {np.max(row['penetration_mm']):.1f} | "
              f"{np.mean(row['crossing']):.3f} |")
    labels = list(dict.fromkeys(rows["default"]["label"]))
    print(f"\nPer set, PA repaired / views with a pair still overlapping by more than "
          f"{1000 * MAX_FITTING_OVERLAP_M:.0f} mm after repair (what python -m cell.run refuses):\n")
    print("| settings | " + " | ".join(labels) + " |")
    print("|---|" + "---|" * len(labels))
    for name, row in rows.items():
        label, pa, crossing = np.array(row["label"]), np.array(row["pa"]), np.array(row["crossing"])
        cells = [f"{np.mean(pa[label == x]):.3f} / {np.mean(crossing[label == x]):.2f}" for x in labels]
        print(f"| {name} | " + " | ".join(cells) + " |")
    gaps_mm = 1000 * np.array(gaps)
    print(f"\nPieces apart from the largest after the default repair: {len(gaps)}; distance to the nearest part "
          "outside (mm): "
          + ", ".join(f"<= {b}: {int(np.sum(gaps_mm <= b))}" for b in (10, 25, 50, 75, 100, 150, 250))
          + f", more: {int(np.sum(gaps_mm > 250))}")


if __name__ == "__main__":
    main()
