"""Evaluate a trained model with the paper's metrics.

    python -m perception.evaluate --checkpoint runs/compact/model.pt --data data/chair_l3 --json out/eval.json

prints the layout of the paper's Tables 1 and 2 (Part Accuracy, Shape Chamfer, Part Accuracy of visible and of
invisible parts) and writes them to the JSON file (``part_accuracy`` is the overall figure).

In code, :func:`evaluate_samples` takes any iterable of samples in the format of :mod:`perception.data`
(dictionaries of numpy arrays, one view each): samples read from a dataset folder (:func:`evaluate_folder`) and
views rendered on the fly go through the same path.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from collections.abc import Iterable, Iterator
from pathlib import Path

import torch
from torch import nn
from tqdm import tqdm

from perception.config import Config, ConfigError, config_from_dict
from perception.data import ViewDataset, collate, object_files, to_device
from perception.metrics import MetricSummary, evaluate_batch
from perception.model import build_model

METHOD_NAMES = {"ours": "Ours", "b_gru": "B-GRU", "b_insonehot": "B-InsOneHot", "b_global": "B-Global"}


def load_model(path: str | Path, device: str | torch.device = "cpu") -> tuple[nn.Module, Config, str]:
    """Rebuild the network stored in a ``model.pt`` or ``checkpoint.pt`` (both carry their configuration);
    returns (model in eval mode, config, kind)."""
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"checkpoint {path} not found")
    payload = torch.load(path, map_location="cpu", weights_only=False)
    if not isinstance(payload, dict) or "config" not in payload or "model" not in payload:
        raise ValueError(f"{path} is not a perception checkpoint (no config or model weights)")
    config = config_from_dict(payload["config"])
    kind = payload["kind"]
    model = build_model(config.model, kind)
    state = model.state_dict()
    # weights may be stored in float16: cast each back to the network's own dtype
    model.load_state_dict({k: v.to(state[k].dtype) if k in state else v for k, v in payload["model"].items()})
    return model.to(device).eval(), config, kind


def _batches(samples: Iterable[dict], batch_size: int, max_parts: int) -> Iterator[dict]:
    chunk: list[dict] = []
    for sample in samples:
        chunk.append(sample)
        if len(chunk) == batch_size:
            yield collate(chunk, max_parts)
            chunk = []
    if chunk:
        yield collate(chunk, max_parts)


@torch.no_grad()
def predict(model: nn.Module, batch: dict) -> dict:
    """The model's outputs for one padded batch (already on the model's device)."""
    model.eval()
    return model(batch)


@torch.no_grad()
def evaluate_samples(model: nn.Module, samples: Iterable[dict], batch_size: int = 8,
                     device: str | torch.device = "cpu", progress: bool = False, total: int | None = None,
                     max_parts: int = 20) -> dict:
    """Metrics over samples (dictionaries as :func:`perception.data.view_sample` returns, with targets)."""
    summary = MetricSummary()
    bar = tqdm(total=total, unit="sample", disable=not progress, desc="evaluate")
    for batch in _batches(samples, batch_size, max_parts):
        batch = to_device(batch, device)
        summary.add(evaluate_batch(predict(model, batch), batch))
        bar.update(len(batch["name"]))
    bar.close()
    return summary.summary()


def evaluate_folder(model: nn.Module, roots: Iterable[str | Path], split: str = "test", limit: int = 0,
                    batch_size: int = 8, device: str | torch.device = "cpu", progress: bool = False,
                    max_parts: int = 20) -> dict:
    """Metrics over the views of a dataset folder's split (a folder without split subfolders: its files)."""
    dataset = ViewDataset(object_files(list(roots), split), limit)
    if len(dataset) == 0:
        raise FileNotFoundError(f"no {split} samples in {', '.join(map(str, roots))}")
    samples = (dataset[i] for i in range(len(dataset)))
    return evaluate_samples(model, samples, batch_size, device, progress, len(dataset), max_parts)


def format_table(rows: dict[str, dict]) -> str:
    """Rows of figures (name -> summary) in the layout of the paper's tables."""

    def cell(value, digits):
        return "-" if value is None or (isinstance(value, float) and math.isnan(value)) else f"{value:.{digits}f}"

    header = f"{'Method':<16} {'Part Acc. ↑':>11} {'Shape Chamfer ↓':>16} {'PA visible ↑':>13} " \
             f"{'PA invisible ↑':>15} {'samples':>8} {'parts':>7}"
    lines = [header, "-" * len(header)]
    for name, s in rows.items():
        lines.append(f"{name:<16} {cell(s['part_accuracy'], 4):>11} {cell(s['shape_chamfer'], 4):>16} "
                     f"{cell(s['part_accuracy_visible'], 4):>13} {cell(s['part_accuracy_invisible'], 4):>15} "
                     f"{s['samples']:>8} {s['parts']:>7}")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m perception.evaluate", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--checkpoint", required=True, help="model.pt or checkpoint.pt of a training run")
    parser.add_argument("--data", nargs="+", required=True, help="dataset folders")
    parser.add_argument("--split", default="test", choices=["train", "val", "test"])
    parser.add_argument("--json", help="write the figures to this JSON file")
    parser.add_argument("--limit", type=int, default=0, help="evaluate the first N samples only (0: all)")
    parser.add_argument("--batch-size", type=int, default=8)
    parser.add_argument("--no-progress", action="store_true")
    args = parser.parse_args(argv)
    device = "cuda" if torch.cuda.is_available() else "cpu"
    try:
        model, config, kind = load_model(args.checkpoint, device)
        summary = evaluate_folder(model, args.data, args.split, args.limit, args.batch_size, device,
                                  not args.no_progress, config.model.max_parts)
    except (ConfigError, FileNotFoundError, ValueError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    print(format_table({METHOD_NAMES.get(kind, kind): summary}))
    if args.json:
        record = {"model": kind, "checkpoint": Path(args.checkpoint).name, "split": args.split,
                  "image_size": config.model.image_size, **summary}
        Path(args.json).parent.mkdir(parents=True, exist_ok=True)
        Path(args.json).write_text(json.dumps(record, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
