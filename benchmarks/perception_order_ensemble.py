"""Does averaging over part orders help? Test-time ensembling of a perception checkpoint over K orders of the parts.

    python benchmarks/perception_order_ensemble.py --orders 4 --data data_slim/chair_3 data_slim/table_3 \
        data_slim/cabinet_3 data_slim/chair_mixed data_slim/table_mixed data_slim/cabinet_mixed --split val

The network reads the parts with an instance one-hot, so the same picture and parts given in another order
give (slightly) different poses. Each view is run in its evaluation order (exactly as ``python -m
perception.evaluate`` runs it, so the "single" row reproduces that command's figure) and in ``--orders - 1`` more
random orders (``numpy.random.default_rng(--seed)``). Every extra run's poses are put back in the evaluation
order and, inside each equivalence class, matched to the first run's parts (Hungarian on the chamfer of the posed
clouds), since equivalent parts may trade places between orders. Then, per part:

- ``medoid``: the run whose posed cloud is nearest (summed chamfer) to the other runs' clouds of that part;
- ``mean translation``: that medoid's rotation with the mean translation over the runs;
- ``whole-assembly medoid``: the run whose whole posed assembly is nearest to the others.

Prints Part Accuracy and Shape Chamfer of each, and writes them to ``--json``. A measurement, not a product
feature: the package predicts with one order (``perception.predict``).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np
import torch

from perception.data import ViewDataset, collate, object_files, permute_parts
from perception.evaluate import load_model
from perception.matching import match_within_classes
from perception.metrics import MetricSummary, _subsample_chamfer, evaluate_batch, pose_clouds

CLOUD_POINTS = 64  # points per part (the first of the farthest-point order) in the matching and medoid distances
COMBINATIONS = ("single", "medoid", "mean translation", "whole-assembly medoid")


@torch.no_grad()
def poses_in_orders(model, samples: list[dict], orders: list[list[np.ndarray]], max_parts: int) -> list[list[tuple]]:
    """For every order k and sample b: (quat (n, 4), trans (n, 3)) of the network run on the parts in order
    ``orders[k][b]``, put back in the sample's own order."""
    runs = []
    for order_k in orders:
        out = model(collate([permute_parts(s, o) for s, o in zip(samples, order_k)], max_parts))
        quat, trans = out["quat"].float().numpy(), out["trans"].float().numpy()
        per_sample = []
        for b, order in enumerate(order_k):
            n = len(order)
            q, t = np.empty((n, 4)), np.empty((n, 3))
            q[order], t[order] = quat[b, :n], trans[b, :n]
            per_sample.append((q, t))
        runs.append(per_sample)
    return runs


def match_to_first(points: np.ndarray, classes: np.ndarray, runs: list[tuple]) -> tuple[np.ndarray, np.ndarray]:
    """(K, n, 4) quaternions and (K, n, 3) translations, each run's equivalent parts matched to the first run's."""
    first = pose_clouds(points, *runs[0])
    quats, transs = [runs[0][0]], [runs[0][1]]
    for quat, trans in runs[1:]:
        cost = _subsample_chamfer(first[:, None], pose_clouds(points, quat, trans)[None, :])  # (n, n)
        perm = match_within_classes(cost, classes)
        quats.append(quat[perm])
        transs.append(trans[perm])
    return np.stack(quats), np.stack(transs)


def combine(points: np.ndarray, quats: np.ndarray, transs: np.ndarray) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """Each combination's (quat (n, 4), trans (n, 3)) from the K matched runs."""
    k, n = quats.shape[:2]
    clouds = np.stack([pose_clouds(points, quats[r], transs[r]) for r in range(k)])  # (K, n, m, 3)
    parts = np.arange(n)
    medoid = np.array([_subsample_chamfer(clouds[:, i, None], clouds[None, :, i]).sum(1).argmin() for i in parts])
    whole = np.array([[_subsample_chamfer(clouds[a], clouds[b]).sum() for b in range(k)] for a in range(k)])
    best = int(whole.sum(1).argmin())
    return {"single": (quats[0], transs[0]),
            "medoid": (quats[medoid, parts], transs[medoid, parts]),
            "mean translation": (quats[medoid, parts], transs.mean(0)),
            "whole-assembly medoid": (quats[best], transs[best])}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--data", nargs="+", required=True, help="dataset folders")
    parser.add_argument("--split", default="val", choices=["train", "val", "test"])
    parser.add_argument("--checkpoint", default="perception/weights/compact.pt")
    parser.add_argument("--orders", type=int, default=4, help="part orders per view, the evaluation order included")
    parser.add_argument("--seed", type=int, default=123, help="seed of the extra orders")
    parser.add_argument("--limit", type=int, default=0, help="first N views only (0: all)")
    parser.add_argument("--batch-size", type=int, default=8)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--json", help="write the figures to this JSON file")
    args = parser.parse_args(argv)
    if args.orders < 2:
        parser.error(f"--orders must be at least 2, got {args.orders}")
    torch.set_num_threads(args.threads)
    model, config, _ = load_model(args.checkpoint)
    dataset = ViewDataset(object_files(args.data, args.split), args.limit, shuffle_parts=True, seed=0)
    if len(dataset) == 0:
        print(f"error: no {args.split} views in {', '.join(args.data)}", file=sys.stderr)
        return 2
    rng = np.random.default_rng(args.seed)
    summaries = {name: MetricSummary() for name in COMBINATIONS}
    start = time.perf_counter()
    for first in range(0, len(dataset), args.batch_size):
        samples = [dataset[i] for i in range(first, min(first + args.batch_size, len(dataset)))]
        orders = [[np.arange(len(s["points"])) for s in samples]]
        orders += [[rng.permutation(len(s["points"])) for s in samples] for _ in range(args.orders - 1)]
        runs = poses_in_orders(model, samples, orders, config.model.max_parts)
        batch = collate(samples, config.model.max_parts)
        outputs = {name: (np.zeros(batch["quat"].shape), np.zeros(batch["trans"].shape)) for name in COMBINATIONS}
        for b, sample in enumerate(samples):
            points = sample["points"][:, :CLOUD_POINTS].astype(np.float64)
            quats, transs = match_to_first(points, sample["classes"], [run[b] for run in runs])
            for name, (quat, trans) in combine(points, quats, transs).items():
                outputs[name][0][b, :len(points)], outputs[name][1][b, :len(points)] = quat, trans
        for name, (quat, trans) in outputs.items():
            summaries[name].add(evaluate_batch({"quat": quat, "trans": trans}, batch))
    figures = {name: {key: summaries[name].summary()[key] for key in ("part_accuracy", "shape_chamfer", "samples")}
               for name in COMBINATIONS}
    print(f"{len(dataset)} {args.split} views, {args.orders} part orders each, {time.perf_counter() - start:.0f} s")
    print(f"{'combination':<24} {'Part Acc.':>9} {'Shape Chamfer':>14}")
    for name, f in figures.items():
        print(f"{name:<24} {f['part_accuracy']:>9.4f} {f['shape_chamfer']:>14.4f}")
    if args.json:
        Path(args.json).parent.mkdir(parents=True, exist_ok=True)
        Path(args.json).write_text(json.dumps({"checkpoint": args.checkpoint, "orders": args.orders,
                                               "seed": args.seed, "split": args.split, **figures}, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
