"""How fast the segmentation network fits a few training views: a probe of its learning speed, not of accuracy.

    python benchmarks/segmentation_fit.py --data data/chair_l3 --objects 8 --steps 100 [--every-scale]

Takes the first ``--objects`` objects of DATA's training split (all their views, one batch), builds the compact
model from scratch (``--config``, default ``compact``; ``--every-scale`` sets ``model.condition_every_scale``) and
runs ``--steps`` Adam steps of the segmentation loss on that one batch, printing the matched soft IoU every
``--every`` steps and, at the end, in eval mode. One thread, seeded: the same command prints the same figures.
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import time
from pathlib import Path

import torch

sys.path[:] = [p for p in sys.path if Path(p or ".").resolve() != Path(__file__).resolve().parent]

from perception.config import load_config  # noqa: E402
from perception.data import ViewDataset, collate, object_files  # noqa: E402
from perception.losses import segmentation_loss  # noqa: E402
from perception.model import build_model  # noqa: E402


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--data", type=Path, required=True, help="a dataset folder (perception.dataset build)")
    parser.add_argument("--config", default="compact")
    parser.add_argument("--objects", type=int, default=8)
    parser.add_argument("--steps", type=int, default=100)
    parser.add_argument("--every", type=int, default=25, help="print every N steps")
    parser.add_argument("--lr", type=float, default=3e-3)
    parser.add_argument("--every-scale", action="store_true", help="f_3d at every decoder scale")
    args = parser.parse_args()
    torch.manual_seed(0)
    torch.set_num_threads(1)
    config = load_config(args.config)
    if args.every_scale:
        config = dataclasses.replace(config, model=dataclasses.replace(config.model, condition_every_scale=True))
    files = object_files([args.data], "train")[: args.objects]
    if not files:
        print(f"error: no training objects in {args.data}", file=sys.stderr)
        return 2
    views = ViewDataset(files)
    batch = collate([views[i] for i in range(len(views))], config.model.max_parts)
    model = build_model(config.model)
    optimiser = torch.optim.Adam(model.segmentation.parameters(), lr=args.lr)
    model.train()
    started = time.perf_counter()
    print(f"{len(views)} views of {len(files)} objects, condition_every_scale={config.model.condition_every_scale}")
    for step in range(args.steps + 1):
        terms = segmentation_loss(model.segmentation(batch), batch, config.loss)
        if step % args.every == 0:
            print(f"step {step}: soft IoU {float(terms['soft_iou']):.3f} ({time.perf_counter() - started:.0f} s)",
                  flush=True)
        if step == args.steps:
            break
        optimiser.zero_grad()
        terms["loss"].backward()
        optimiser.step()
    model.eval()
    with torch.no_grad():
        final = segmentation_loss(model.segmentation(batch), batch, config.loss)
    print(f"eval mode: soft IoU {float(final['soft_iou']):.3f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
