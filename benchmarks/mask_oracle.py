"""What limits the paper's network: its masks or its pose module? Part Accuracy of one checkpoint of Ours on
the same views twice, once with the masks its segmentation network predicts and once with the true instance
masks (one-hot from the rendered part labels) given to its pose module in their place.

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

import torch

# Run as a script, this file's folder comes first on sys.path and its name would hide the perception package.
sys.path[:] = [p for p in sys.path if Path(p or ".").resolve() != Path(__file__).resolve().parent]

from perception.data import ViewDataset, object_files  # noqa: E402
from perception.evaluate import _batches, load_model  # noqa: E402
from perception.metrics import MetricSummary, evaluate_batch  # noqa: E402


def truth_masks(batch: dict) -> torch.Tensor:
    """(B, P, H, W) float one-hot instance masks from the rendered part labels (-1: background)."""
    labels = batch["part_labels"]
    parts = torch.arange(batch["valid"].shape[1]).view(1, -1, 1, 1)
    return (labels.unsqueeze(1) == parts).float()


@torch.no_grad()
def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--checkpoint", type=Path, required=True)
    parser.add_argument("--data", nargs="+", required=True, help="dataset folders (full, not slim, for 'test')")
    parser.add_argument("--split", default="test")
    parser.add_argument("--limit", type=int, default=300, help="views, evenly spread over the files")
    parser.add_argument("--json", type=Path)
    args = parser.parse_args()
    torch.manual_seed(0)
    model, config, kind = load_model(args.checkpoint)
    if kind != "ours":
        parser.error(f"{args.checkpoint} holds {kind!r}: only Ours has masks")
    model.eval()
    results = {}
    for folder in args.data:
        samples = ViewDataset(object_files([folder], args.split), args.limit)
        predicted, oracle = MetricSummary(), MetricSummary()
        for batch in _batches(samples, 8, config.model.max_parts):
            predicted.add(evaluate_batch(model(batch), batch))
            oracle.add(evaluate_batch(model(batch, truth_masks(batch)), batch))
        results[Path(folder).name] = {"views": len(samples), "predicted_masks": predicted.summary(),
                                      "truth_masks": oracle.summary()}
        a, b = predicted.summary(), oracle.summary()
        print(f"{Path(folder).name}: {len(samples)} views, Part Accuracy {a['part_accuracy']:.3f} with predicted "
              f"masks, {b['part_accuracy']:.3f} with the true masks (Shape Chamfer {a['shape_chamfer']:.4f} / "
              f"{b['shape_chamfer']:.4f})", flush=True)
    if args.json:
        args.json.write_text(json.dumps(results, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
