"""Evaluate a trained model with the paper's metrics.

    python -m perception.evaluate --checkpoint runs/compact/model.pt --data data/chair_l3 --json out/eval.json
    python -m perception.evaluate --assemblies ASSEMBLIES_DIR --views 2 --json out/eval.json [--seed 0]

prints the layout of the paper's Tables 1 and 2 (Part Accuracy, Shape Chamfer, Part Accuracy of visible and of
invisible parts) and writes them to the JSON file (``part_accuracy`` is the overall figure). ``--data`` reads
views from dataset folders; ``--assemblies`` renders every assembly folder under a folder on the fly and also
reports connectivity and the figures after pose repair, the up-axis error, inference time and peak memory
(:mod:`perception.evaluate_assemblies`). ``--checkpoint`` defaults to the bundled weights. Each view's parts reach
the network in a random order drawn from ``--seed``, as a user's parts come (procedural objects list them in the
generator's fixed order, which an order-reading network such as B-GRU would exploit); ``--keep-part-order`` keeps
the files' order.

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
                    max_parts: int = 20, shuffle_parts: bool = True, seed: int = 0) -> dict:
    """Metrics over the views of a dataset folder's split (a folder without split subfolders: its files), each
    view's parts in a random order drawn from ``seed`` (``shuffle_parts``; see :class:`ViewDataset`)."""
    dataset = ViewDataset(object_files(list(roots), split), limit, shuffle_parts, seed)
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


def format_extras(figures: dict) -> str:
    """The figures beyond the paper's table that ``--assemblies`` measures, one line each."""
    c, up, t = figures["connectivity"], figures["up_error_deg"], figures["inference_s"]
    lines = [f"connectivity (parts touching another): truth {c['truth']:.3f}, predicted {c['predicted']:.3f}, "
             f"repaired {c['repaired']:.3f}; objects in one piece: truth {c['truth_connected']:.3f}, "
             f"predicted {c['predicted_connected']:.3f}, repaired {c['repaired_connected']:.3f}; every part on a "
             f"path to the floor: truth {c['truth_grounded']:.3f}, predicted {c['predicted_grounded']:.3f}, "
             f"repaired {c['repaired_grounded']:.3f}"] if "after_repair" \
        in figures else []
    if "deepest_penetration_m" in figures:
        before, after = figures["deepest_penetration_m"]["before"], figures["deepest_penetration_m"]["after"]
        lines.append(f"deepest penetration between two parts (mm): before repair mean {1000 * before['mean']:.1f}, "
                     f"p95 {1000 * before['p95']:.1f}; after mean {1000 * after['mean']:.1f}, "
                     f"p95 {1000 * after['p95']:.1f}")
    if "crossing_after_repair" in figures:
        crossing = figures["crossing_after_repair"]
        lines.append(f"parts still crossing after repair (a pair overlapping by over "
                     f"{1000 * crossing['threshold_m']:.0f} mm): {crossing['views']:.3f} of the views; the deepest "
                     f"pair equivalent parts in {crossing['deepest_pair_equivalent']:.3f} of those; PA (mean over "
                     f"views) {crossing['part_accuracy_crossing']:.3f} there, {crossing['part_accuracy_other']:.3f} in "
                     "the others")
    if "right_object_rate" in figures:
        repaired = figures.get("after_repair", {}).get("right_object_rate")
        lines.append(f"right objects (every part passes PA): {figures['right_object_rate']:.3f} of the views"
                     + (f", {repaired:.3f} after repair" if repaired is not None else ""))
    lines.append(f"up-axis error (deg): mean {up['mean']:.2f}, median {up['median']:.2f}, p95 {up['p95']:.2f}, "
                 f"max {up['max']:.2f}; within 5 deg: {up['within_5_deg']:.3f}")
    lines.append(f"depth of the object centre, error (m): mean {figures['depth_error_m']['mean']:.4f}, "
                 f"p95 {figures['depth_error_m']['p95']:.4f}")
    cpu = figures["inference_cpu_s"]
    lines.append(f"CPU inference per object (s, wall clock): mean {t['mean']:.3f}, median {t['median']:.3f}, "
                 f"p95 {t['p95']:.3f}, max {t['max']:.3f}; CPU time mean {cpu['mean']:.3f}, p95 {cpu['p95']:.3f}; "
                 f"peak memory {figures['peak_memory_mb']:.0f} MB (process)")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m perception.evaluate", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    source = parser.add_mutually_exclusive_group(required=True)
    source.add_argument("--data", nargs="+", help="dataset folders")
    source.add_argument("--assemblies", help="a folder of assembly folders, rendered on the fly")
    parser.add_argument("--checkpoint", help="model.pt or checkpoint.pt of a training run (default: the bundled "
                        "weights, perception/weights/compact.pt)")
    parser.add_argument("--model", choices=sorted(METHOD_NAMES), help="refuse a checkpoint of another network")
    parser.add_argument("--split", default="test", choices=["train", "val", "test"], help="with --data")
    parser.add_argument("--views", type=int, default=1, help="with --assemblies: renderings per object")
    parser.add_argument("--seed", type=int, default=0, help="object i renders from numpy.random.default_rng([seed, "
                        "i]) (--assemblies); the parts' random order is drawn from it too")
    parser.add_argument("--keep-part-order", action="store_true", help="give the network the parts in the order "
                        "of the files, not in a random order (procedural objects list them in a fixed order)")
    parser.add_argument("--no-repair", action="store_true", help="with --assemblies: skip connectivity and repair")
    parser.add_argument("--materials", choices=["parts", "one", "few"], default="parts",
                        help="with --assemblies: a colour per part (default), one shared material, or two or three")
    parser.add_argument("--solver", action="store_true", help="with --assemblies: also fit each prediction to its "
                        "picture (perception.solver) and report it under after_solver, network / solver / repair")
    parser.add_argument("--json", help="write the figures to this JSON file")
    parser.add_argument("--limit", type=int, default=0, help="evaluate the first N samples (--data) or assembly "
                        "folders (--assemblies) only (0: all)")
    parser.add_argument("--batch-size", type=int, default=8)
    parser.add_argument("--threads", type=int, help="torch CPU threads (default: 1 with --assemblies, one object at a "
                        "time as predict runs it; torch's setting with --data)")
    parser.add_argument("--no-progress", action="store_true")
    args = parser.parse_args(argv)
    for name in ("views", "batch_size", "threads"):
        value = getattr(args, name)
        if value is not None and value < 1:
            parser.error(f"--{name.replace('_', '-')} must be at least 1, got {value}")
    from perception.weights import INFERENCE_THREADS, inference_threads, resolve_checkpoint

    device = "cuda" if torch.cuda.is_available() and not args.assemblies else "cpu"
    threads = args.threads if args.threads or not args.assemblies else INFERENCE_THREADS
    try:
        checkpoint = resolve_checkpoint(args.checkpoint)
        model, config, kind = load_model(checkpoint, device)
        if args.model and kind != args.model:
            raise ValueError(f"{checkpoint} holds model {kind!r}, not {args.model!r}")
        if args.assemblies:
            from perception.evaluate_assemblies import evaluate_assemblies
            from perception.solver import SolverSettings

            with inference_threads(threads):
                summary = evaluate_assemblies(model, args.assemblies, args.views, args.seed, not args.no_repair,
                                              config.model.max_parts, args.limit, not args.no_progress,
                                              shuffle_parts=not args.keep_part_order,
                                              solver=SolverSettings() if args.solver else None,
                                              materials=args.materials)
        else:
            with inference_threads(threads):
                summary = evaluate_folder(model, args.data, args.split, args.limit, args.batch_size, device,
                                          not args.no_progress, config.model.max_parts, not args.keep_part_order,
                                          args.seed)
    except (ConfigError, FileNotFoundError, ValueError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    name = METHOD_NAMES.get(kind, kind)
    rows = {name: summary}
    if "after_repair" in summary:
        rows[f"{name} + repair"] = summary["after_repair"]
    if "after_solver" in summary:
        stages = summary["after_solver"]["stages"]
        print("picture solver, level-3 Part Accuracy (right objects: every part passes) over "
              f"{summary['after_solver']['views']} views: " + "; ".join(
                  f"{stage} {v['part_accuracy']:.3f} ({v['right_object_rate']:.3f})" for stage, v in stages.items()))
    print(format_table(rows))
    if args.assemblies:
        print(format_extras(summary))
    if args.json:
        record = {"model": kind, "checkpoint": Path(checkpoint).name, "image_size": config.model.image_size,
                  **({"assemblies": Path(args.assemblies).name, "views": args.views, "materials": args.materials}
                     if args.assemblies
                     else {"split": args.split}), "seed": args.seed, "shuffle_parts": not args.keep_part_order,
                  **summary}
        Path(args.json).parent.mkdir(parents=True, exist_ok=True)
        Path(args.json).write_text(json.dumps(record, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
