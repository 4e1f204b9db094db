"""Seconds per training step of the compact model's pose stage under each speed setting of the config:
``train.precision`` (float32, bfloat16 autocast) x ``train.channels_last`` (off, on).

    python benchmarks/training_step_speed.py --data data_slim/chair_3 data_slim/table_3 --batch 32 --steps 4

Every setting trains a fresh copy of the bundled weights (``perception/weights/compact.pt``) on the same batches
(the first ``--batch`` x ``--steps`` training views, parts shuffled as in training), as
:class:`perception.train.stages.PoseStage` does: the frozen segmentation network's masks, the pose network's
forward pass, the losses, backward and an Adam step. The first step of each setting warms up and is not timed;
the table gives the median of the others and the loss of the first step (equal to bfloat16's precision across
settings). Threads: ``--threads`` (default 2, the standard machine's cores). ``--device cuda`` measures a GPU
(each step synchronised before its clock stops).
"""

from __future__ import annotations

import argparse
import copy
import dataclasses
import statistics
import sys
import time
from pathlib import Path

import torch

# Run as a script, this file's folder comes first on sys.path and its name would hide the perception package.
sys.path[:] = [p for p in sys.path if Path(p or ".").resolve() != Path(__file__).resolve().parent]

from perception.data import ViewDataset, collate, object_files, to_device  # noqa: E402
from perception.train.stages import PoseStage  # noqa: E402
from perception.weights import BUNDLED_WEIGHTS, load_for_inference  # noqa: E402

SETTINGS = [("float32", False), ("float32", True), ("bfloat16", False), ("bfloat16", True)]


def step_seconds(model, config, batches) -> tuple[list[float], float]:
    """Train ``model`` one step per batch; (seconds of each step, loss of the first)."""
    stage = PoseStage(config)
    stage.set_modes(model)
    net = stage.trainable(model)
    optimizer = torch.optim.Adam([p for p in net.parameters() if p.requires_grad], lr=1e-4)
    seconds, first_loss = [], None
    for batch in batches:
        start = time.perf_counter()
        terms = stage.loss(net, model, batch)
        optimizer.zero_grad(set_to_none=True)
        terms["loss"].backward()
        optimizer.step()
        if batch["image"].is_cuda:
            torch.cuda.synchronize()
        seconds.append(time.perf_counter() - start)
        first_loss = float(terms["loss"].detach()) if first_loss is None else first_loss
    return seconds, first_loss


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--data", nargs="+", required=True, help="dataset folders (their train splits)")
    parser.add_argument("--batch", type=int, default=32)
    parser.add_argument("--steps", type=int, default=4, help="steps per setting, the first one untimed")
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--device", default="cpu", help="torch device (default cpu)")
    args = parser.parse_args()
    if args.steps < 2:
        parser.error("--steps must be at least 2 (the first step is not timed)")
    torch.set_num_threads(args.threads)
    torch.manual_seed(0)
    base, config, _, _ = load_for_inference(BUNDLED_WEIGHTS)
    dataset = ViewDataset(object_files(args.data, "train"), shuffle_parts=True, seed=0)
    needed = args.batch * args.steps
    if len(dataset) < needed:
        raise SystemExit(f"{len(dataset)} training views in {args.data}: fewer than --batch x --steps = {needed}")
    batches = [to_device(collate([dataset[k * args.batch + i] for i in range(args.batch)], config.model.max_parts),
                         args.device) for k in range(args.steps)]
    parts = sum(int(b["valid"].sum()) for b in batches) / len(batches)
    print(f"Ours, pose stage, batch {args.batch} ({parts:.0f} parts per batch on average), {args.threads} threads, "
          f"{args.steps - 1} timed steps per setting, device {args.device}, torch {torch.__version__}\n")
    print("| precision | channels_last | s per step (median) | first loss |")
    print("|---|---|---|---|")
    for precision, channels_last in SETTINGS:
        model = copy.deepcopy(base).to(args.device)
        if channels_last:
            model.to(memory_format=torch.channels_last)
        setting = dataclasses.replace(config, train=dataclasses.replace(config.train, precision=precision,
                                                                        channels_last=channels_last))
        seconds, loss = step_seconds(model, setting, batches)
        print(f"| {precision} | {'on' if channels_last else 'off'} | {statistics.median(seconds[1:]):.2f} | "
              f"{loss:.4f} |", flush=True)


if __name__ == "__main__":
    main()
