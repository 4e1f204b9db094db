"""Does running the network on several orders of the parts, and keeping what agrees best with the picture, raise
Part Accuracy? A measurement of the hypothesis search, not a product feature.

    python benchmarks/picture_hypotheses.py --out out/hypotheses_bench --count 40 [--orders 5]
        [--categories chair table cabinet] [--furniture ../shared/furniture]

The network reads the parts with an instance one-hot, so the same picture and parts in another order give other
poses; the best of five orders is right more often than the first. Test sets as ``benchmarks/picture_solver.py``
builds them (``--count`` fresh level-3 procedural objects per category, ``perception.synth --seed 424242``;
optionally the real assemblies of ``--furniture``). Each object is rendered once, parts in a random order
(:mod:`perception.evaluate_assemblies`), and predicted ``--orders`` times: in that order, then in orders from
``numpy.random.default_rng([7, object, k])``. Each hypothesis is placed upright and repaired as ``cell.run``
repairs it. Rows, level-3 Part Accuracy after repair (and the right-object rate):

- ``first order``: the first hypothesis, what ``cell.run`` builds;
- ``best silhouette``: the hypothesis whose parts, drawn with the picture's camera, score best against the object
  (:class:`perception.solver.SilhouetteScorer`: silhouette IoU plus each part's share on the object);
- ``per-part alternatives``: from that hypothesis, each part in turn takes its pose from another hypothesis where
  the score rises (two passes);
- ``oracle``: the hypothesis with the best Part Accuracy (which the picture alone cannot know).

Prints a Markdown table, the mean per-object gain of ``best silhouette`` over ``first order`` with its standard
error, and writes every object's figures to ``OUT/hypotheses.json``.
"""

from __future__ import annotations

import argparse
import json
import platform
import sys
import time
from pathlib import Path

import numpy as np

sys.path[:] = [p for p in sys.path if Path(p or ".").resolve() != Path(__file__).resolve().parent]
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks.picture_agreement import add_set_arguments, test_sets  # noqa: E402
from cell.render import Appearance, AssemblyRenderer, sample_camera  # noqa: E402
from perception.agreement import object_mask  # noqa: E402
from perception.elevation import image_elevation_deg  # noqa: E402
from perception.evaluate_assemblies import (  # noqa: E402
    DEFAULT_REPAIR,
    assembly_folders,
    network_frame,
    shuffled_parts,
    truth_targets,
)
from perception.metrics import evaluate_assembly  # noqa: E402
from perception.placement import place_parts  # noqa: E402
from perception.predict import prepare_parts, run_network  # noqa: E402
from perception.solver import SilhouetteScorer  # noqa: E402
from perception.weights import load_for_inference  # noqa: E402
from planning.assembly import read_assembly  # noqa: E402
from planning.collision import ConvexPart  # noqa: E402
from planning.pose import Pose  # noqa: E402
from planning.repair import repair_poses  # noqa: E402

ROWS = ("first order", "best silhouette", "per-part alternatives", "oracle")


def evaluate_object(model, folder: Path, index: int, orders: int) -> dict:
    """One object's figures (see the module docstring); the view and the first order as
    :func:`perception.evaluate_assemblies.evaluate_assemblies` draws them with seed 0."""
    assembly = shuffled_parts(read_assembly(folder), 0, index)
    n = len(assembly.parts)
    rng = np.random.default_rng([0, index])
    with AssemblyRenderer(assembly) as renderer:
        camera = sample_camera(rng, assembly.bounds())
        view = renderer.render(camera, Appearance.sample(rng, n, "parts"))
    meshes = [p.mesh for p in assembly.parts]
    convex = [ConvexPart.from_mesh(p.name, p.mesh) for p in assembly.parts]
    pieces = [c.piece_vertices for c in convex]
    parts = prepare_parts(meshes)
    low, high = assembly.bounds()
    gt_quat, gt_trans = truth_targets(view, parts, view.camera_from_assembly.apply(0.5 * (low + high)))
    elevation = image_elevation_deg(view.rgb)
    hypotheses, mask = [], None  # (placement, camera_from_part in the first order's part order)
    for k in range(orders):
        order = np.arange(n) if k == 0 else np.random.default_rng([7, index, k]).permutation(n)
        ordered = parts if k == 0 else prepare_parts([meshes[j] for j in order])
        quat, trans, foreground = run_network(model, view.rgb, ordered, with_foreground=True)
        if k == 0:
            mask, _ = object_mask(view.rgb, foreground)
        placement = place_parts(quat, trans, ordered.normalized, ordered.meshes, image_elevation_deg=elevation)
        camera_from_part = [None] * n
        for j, pose in zip(order, placement.camera_from_part):
            camera_from_part[j] = pose
        hypotheses.append((placement, camera_from_part))

    def part_accuracy(camera_from_part, centre_camera_m) -> np.ndarray:
        quat, trans = network_frame(camera_from_part, parts, centre_camera_m)
        return evaluate_assembly(parts.normalized.points_norm, quat, trans, gt_quat, gt_trans, parts.classes,
                                 view.visible_pixels).correct

    def repaired(camera_from_assembly: Pose, assembly_from_part: list[Pose], centre_camera_m) -> np.ndarray:
        poses = repair_poses(convex, assembly_from_part, DEFAULT_REPAIR)[0]
        return part_accuracy([camera_from_assembly @ p for p in poses], centre_camera_m)

    def scorer_at(camera_from_assembly: Pose, poses: list[Pose]) -> SilhouetteScorer:
        scorer = SilhouetteScorer(pieces, camera_from_assembly, mask)
        scorer.fit(poses)
        return scorer

    def score(placement, camera_from_part) -> float:
        poses = [placement.camera_from_assembly.inverse() @ c for c in camera_from_part]
        scorer = scorer_at(placement.camera_from_assembly, poses)
        masks = [scorer.part_mask(k, p) for k, p in enumerate(poses)]
        return scorer.score([scorer.on_object_share(m) for m in masks], np.sum(masks, axis=0), 0.0)[0]

    correct = [repaired(p.camera_from_assembly, [p.camera_from_assembly.inverse() @ c for c in cam],
                        p.centre_camera_m) for p, cam in hypotheses]
    scores = [score(p, cam) if mask.any() else 0.0 for p, cam in hypotheses]
    best = int(np.argmax(scores))
    chosen = _alternatives(hypotheses, best, pieces, mask, scorer_at) if mask.any() else None
    base = hypotheses[best][0]
    accuracy = [float(np.mean(c)) for c in correct]
    alternatives = (repaired(base.camera_from_assembly, chosen, base.centre_camera_m) if chosen is not None
                    else correct[best])
    return {"name": folder.name, "parts": n, "scores": scores, "part_accuracy": accuracy,
            "correct": {"first order": correct[0].tolist(), "best silhouette": correct[best].tolist(),
                        "per-part alternatives": np.asarray(alternatives).tolist(),
                        "oracle": correct[int(np.argmax(accuracy))].tolist()}}


def _alternatives(hypotheses, best: int, pieces, mask, scorer_at) -> list[Pose]:
    """From hypothesis ``best``, each part in turn takes its pose from another hypothesis where the silhouette score
    rises (two passes); poses in that hypothesis's assembly frame, every hypothesis's parts moved with the
    difference of the object centres the hypotheses estimate."""
    base = hypotheses[best][0]
    to_assembly = base.camera_from_assembly.inverse()
    shift = base.centre_camera_m
    options = [[to_assembly @ Pose(cam[k].position - p.centre_camera_m + shift, cam[k].quat_wxyz)
                for p, cam in hypotheses] for k in range(len(pieces))]
    poses = [options[k][best] for k in range(len(pieces))]
    scorer = scorer_at(base.camera_from_assembly, poses)
    masks = [scorer.part_mask(k, p) for k, p in enumerate(poses)]
    shares = [scorer.on_object_share(m) for m in masks]
    coverage = np.sum(masks, axis=0, dtype=np.int16)
    value = scorer.score(shares, coverage, 0.0)[0]
    for _ in range(2):
        for k in range(len(poses)):
            for option in options[k]:
                drawn = scorer.part_mask(k, option)
                trial_coverage = coverage + drawn.astype(np.int16) - masks[k].astype(np.int16)
                trial_shares = shares[:k] + [scorer.on_object_share(drawn)] + shares[k + 1:]
                trial = scorer.score(trial_shares, trial_coverage, 0.0)[0]
                if trial > value + 1e-6:
                    value, coverage, shares, masks[k], poses[k] = trial, trial_coverage, trial_shares, drawn, option
    return poses


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_set_arguments(parser, "out/hypotheses_bench")
    parser.add_argument("--orders", type=int, default=5, help="hypotheses per object: orders of the parts")
    args = parser.parse_args()
    sets = test_sets(args)
    model, _, _, checkpoint = load_for_inference(None)
    figures_path = args.out / "hypotheses.json"
    results = json.loads(figures_path.read_text()) if figures_path.is_file() else {}
    lines = [f"machine: {platform.machine()}, weights: {checkpoint.name}, {args.orders} orders", "",
             "| set | objects | " + " | ".join(ROWS) + " | gain of best silhouette, per object |",
             "|---|---|" + "---|" * len(ROWS) + "---|"]
    for name, folder in sets.items():
        key = f"{name} | {args.orders}"
        records = results.setdefault(key, [])
        folders = assembly_folders(folder)[:args.count] if name != "real furniture" else assembly_folders(folder)
        for index, object_folder in enumerate(folders):
            if index < len(records):
                continue  # measured by an earlier run into the same --out
            started = time.perf_counter()
            records.append(evaluate_object(model, object_folder, index, args.orders))
            figures_path.write_text(json.dumps(results))
            print(f"{name} {object_folder.name}: " + ", ".join(
                f"{row} {np.mean(records[-1]['correct'][row]):.2f}" for row in ROWS)
                + f" ({time.perf_counter() - started:.0f} s)", flush=True)
        cells = []
        for row in ROWS:
            correct = [np.asarray(r["correct"][row]) for r in records]
            cells.append(f"{np.mean(np.concatenate(correct)):.3f} ({np.mean([c.all() for c in correct]):.2f})")
        gain = np.array([np.mean(r["correct"]["best silhouette"]) - np.mean(r["correct"]["first order"])
                         for r in records])
        lines.append(f"| {name} | {len(records)} | " + " | ".join(cells)
                     + f" | {gain.mean():+.3f} ± {gain.std(ddof=1) / np.sqrt(len(gain)):.3f} |")
    text = "\n".join(lines)
    print("\n" + text)
    (args.out / "hypotheses.md").write_text(text + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
