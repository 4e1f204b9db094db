"""What limits the paper's network: its masks or its pose module? Part Accuracy of one checkpoint of Ours on
the same views twice, once with the masks its segmentation network predicts and once with the true instance
masks (one-hot from the rendered part labels) given to its pose module in their place.

Then, with its own masks, where its failed parts go wrong: the share of them that would pass with the true
rotation (their predicted translation kept) and with the true translation (their predicted rotation kept), the
median error of the predicted translation along each camera axis (x right, y down, z depth; normalised units) for
failed and for correct parts, the soft IoU of each part's predicted mask with the true mask of the part it is
matched to (at the mask's resolution), and how far apart Ours puts equivalent parts: for each part with an
equivalent, the distance from its predicted translation to the nearest predicted translation of an equivalent part,
against the same distance between the true translations (medians, normalised units; a network that cannot tell
equivalent parts apart hedges and draws them together).

    python benchmarks/mask_oracle.py --checkpoint perception/weights/compact.pt --data data/gpu_chair_3 \\
        data/gpu_table_3 data/gpu_cabinet_3 --split test --limit 300

The pose module was trained on predicted masks, so the truth masks are an input it has not seen: the gap is a
lower bound on what perfect masks would give after training on them.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
import torch

# Run as a script, this file's folder comes first on sys.path and its name would hide the perception package.
sys.path[:] = [p for p in sys.path if Path(p or ".").resolve() != Path(__file__).resolve().parent]

from perception.data import ViewDataset, object_files  # noqa: E402
from perception.evaluate import _batches, load_model  # noqa: E402
from perception.metrics import MetricSummary, as_numpy, evaluate_assembly, evaluate_batch  # noqa: E402


def truth_masks(batch: dict) -> torch.Tensor:
    """(B, P, H, W) float one-hot instance masks from the rendered part labels (-1: background)."""
    labels = batch["part_labels"]
    parts = torch.arange(batch["valid"].shape[1]).view(1, -1, 1, 1)
    return (labels.unsqueeze(1) == parts).float()


def nearest_equivalent_distance(trans: np.ndarray, classes: np.ndarray) -> np.ndarray:
    """(N,) distance from each part's translation (N, 3) to the nearest translation of another part of its
    equivalence class; nan for a part alone in its class."""
    distance = np.linalg.norm(trans[:, None] - trans[None], axis=-1)
    distance[(classes[:, None] != classes[None]) | np.eye(len(trans), dtype=bool)] = np.inf
    nearest = distance.min(axis=1)
    return np.where(np.isfinite(nearest), nearest, np.nan)


def failure_breakdown(outputs: dict, batch: dict) -> dict[str, np.ndarray]:
    """Per part of every object of a batch (concatenated): ``correct``; ``pass_true_rotation`` and
    ``pass_true_translation`` (correct once that half of the pose is replaced by its matched true value);
    ``translation_error`` (3,) predicted minus true, camera axes, normalised units; ``mask_iou`` of the predicted
    mask with the matched part's true mask (nan where that part shows no pixel at the mask's resolution);
    ``spacing_predicted`` and ``spacing_true``: distance to the nearest equivalent part's translation, predicted
    and true (nan for a part with no equivalent)."""
    masks = outputs["masks"]
    truth = torch.nn.functional.interpolate(truth_masks(batch), size=masks.shape[-2:], mode="nearest")
    rows: dict[str, list] = {key: [] for key in ("correct", "pass_true_rotation", "pass_true_translation",
                                                 "translation_error", "mask_iou", "spacing_predicted",
                                                 "spacing_true")}
    for b, valid in enumerate(as_numpy(batch["valid"])):
        idx = np.flatnonzero(valid)
        points, classes = as_numpy(batch["points"][b])[idx], as_numpy(batch["classes"][b])[idx]
        quat, trans = as_numpy(outputs["quat"][b])[idx], as_numpy(outputs["trans"][b])[idx]
        true_quat, true_trans = as_numpy(batch["quat"][b])[idx], as_numpy(batch["trans"][b])[idx]
        result = evaluate_assembly(points, quat, trans, true_quat, true_trans, classes)
        match = result.match
        rows["correct"].append(result.correct)
        rows["pass_true_rotation"].append(
            evaluate_assembly(points, true_quat[match], trans, true_quat, true_trans, classes).correct)
        rows["pass_true_translation"].append(
            evaluate_assembly(points, quat, true_trans[match], true_quat, true_trans, classes).correct)
        rows["translation_error"].append(trans - true_trans[match])
        rows["spacing_predicted"].append(nearest_equivalent_distance(trans, classes))
        rows["spacing_true"].append(nearest_equivalent_distance(true_trans[match], classes))
        predicted, true = as_numpy(masks[b])[idx], as_numpy(truth[b])[idx][match]
        union = np.maximum(predicted, true).sum((1, 2))
        rows["mask_iou"].append(np.where(true.sum((1, 2)) > 0, np.minimum(predicted, true).sum((1, 2))
                                         / np.maximum(union, 1e-9), np.nan))
    return {key: np.concatenate(value) for key, value in rows.items()}


def summarise_failures(parts: dict[str, np.ndarray]) -> dict:
    """The figures of :func:`failure_breakdown`'s parts (see the module docstring)."""
    failed, correct = ~parts["correct"], parts["correct"]

    def share(mask):
        return float(mask[failed].mean()) if failed.any() else float("nan")

    def axes(mask):
        return [round(float(v), 4) for v in np.median(np.abs(parts["translation_error"][mask]), axis=0)] \
            if mask.any() else None

    def iou(mask):
        return float(np.nanmean(parts["mask_iou"][mask])) if np.isfinite(parts["mask_iou"][mask]).any() \
            else float("nan")

    def spacing(key):
        return round(float(np.nanmedian(parts[key])), 4) if np.isfinite(parts[key]).any() else float("nan")

    return {"parts": int(len(failed)), "failed": int(failed.sum()),
            "failed_pass_with_true_rotation": share(parts["pass_true_rotation"]),
            "failed_pass_with_true_translation": share(parts["pass_true_translation"]),
            "median_abs_translation_error_xyz": {"failed": axes(failed), "correct": axes(correct)},
            "mask_soft_iou": {"failed": iou(failed), "correct": iou(correct)},
            "equivalent_spacing": {"predicted": spacing("spacing_predicted"), "true": spacing("spacing_true")}}


@torch.no_grad()
def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--checkpoint", type=Path, required=True)
    parser.add_argument("--data", nargs="+", required=True, help="dataset folders (full, not slim, for 'test')")
    parser.add_argument("--split", default="test")
    parser.add_argument("--limit", type=int, default=300, help="views, evenly spread over the files")
    parser.add_argument("--seed", type=int, default=0, help="each view's parts reach the network in a random order "
                        "drawn from it, as in perception.evaluate")
    parser.add_argument("--json", type=Path)
    args = parser.parse_args()
    torch.manual_seed(0)
    model, config, kind = load_model(args.checkpoint)
    if kind != "ours":
        parser.error(f"{args.checkpoint} holds {kind!r}: only Ours has masks")
    model.eval()
    results = {}
    for folder in args.data:
        samples = ViewDataset(object_files([folder], args.split), args.limit, shuffle_parts=True, seed=args.seed)
        predicted, oracle, breakdowns = MetricSummary(), MetricSummary(), []
        for batch in _batches(samples, 8, config.model.max_parts):
            outputs = model(batch)
            predicted.add(evaluate_batch(outputs, batch))
            breakdowns.append(failure_breakdown(outputs, batch))
            oracle.add(evaluate_batch(model(batch, truth_masks(batch)), batch))
        failures = summarise_failures({key: np.concatenate([b[key] for b in breakdowns]) for key in breakdowns[0]})
        results[Path(folder).name] = {"views": len(samples), "predicted_masks": predicted.summary(),
                                      "truth_masks": oracle.summary(), "failures": failures}
        a, b = predicted.summary(), oracle.summary()
        print(f"{Path(folder).name}: {len(samples)} views, Part Accuracy {a['part_accuracy']:.3f} with predicted "
              f"masks, {b['part_accuracy']:.3f} with the true masks (Shape Chamfer {a['shape_chamfer']:.4f} / "
              f"{b['shape_chamfer']:.4f})", flush=True)
        errors = failures["median_abs_translation_error_xyz"]
        print(f"  {failures['failed']} of {failures['parts']} parts failed; with the true rotation "
              f"{failures['failed_pass_with_true_rotation']:.2f} of them pass, with the true translation "
              f"{failures['failed_pass_with_true_translation']:.2f}; median |translation error| x, y, depth: failed "
              f"{errors['failed']}, correct {errors['correct']}; mask soft IoU failed "
              f"{failures['mask_soft_iou']['failed']:.3f}, correct {failures['mask_soft_iou']['correct']:.3f}; "
              f"equivalent parts' median spacing predicted {failures['equivalent_spacing']['predicted']}, true "
              f"{failures['equivalent_spacing']['true']}", flush=True)
    if args.json:
        args.json.write_text(json.dumps(results, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
