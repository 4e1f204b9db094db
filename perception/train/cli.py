"""Command line of the training run.

    python -m perception.train --config perception/configs/compact.toml --data data/chair_l3 --out runs/compact
    torchrun --nproc_per_node 2 -m perception.train --config ... --data ... --out ...   # DDP, unchanged

``--config`` also takes a bundled config's name (``compact``, ``paper``, ``tiny``). Running the same command
again after an interruption resumes from ``OUT/checkpoint.pt``.
"""

from __future__ import annotations

import argparse
import sys
from dataclasses import replace

from perception.config import ConfigError, load_config
from perception.model import MODELS
from perception.train.loop import StopRequested
from perception.train.run import train


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(prog="python -m perception.train", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--config", required=True, help="TOML config file or bundled config name")
    parser.add_argument("--data", nargs="+", help="dataset folders (default: data.paths of the config)")
    parser.add_argument("--out", required=True, help="output folder: checkpoint.pt, log.json, model.pt")
    parser.add_argument("--model", default="ours", choices=sorted(MODELS), help="network (default: ours)")
    parser.add_argument("--init", help="start from the weights of this model.pt or checkpoint.pt (fine-tuning, e.g. "
                        "from perception/weights/compact.pt); the config's architecture must match; ignored when "
                        "resuming OUT/checkpoint.pt")
    parser.add_argument("--max-steps", type=int, help="cap every stage at N optimiser steps (smoke runs)")
    parser.add_argument("--stop-after", type=int, help="checkpoint and stop after N steps in all, as an "
                        "interruption would (to test resuming)")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")
    args = parser.parse_args(argv)
    for name in ("max_steps", "stop_after"):
        value = getattr(args, name)
        if value is not None and value < 1:
            parser.error(f"--{name.replace('_', '-')} must be at least 1, got {value}")
    return args


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    try:
        config = load_config(args.config)
        if args.data:
            config = replace(config, data=replace(config.data, paths=tuple(args.data)))
        log = train(config, args.out, kind=args.model, max_steps=args.max_steps, stop_after=args.stop_after,
                    progress=not args.no_progress, init=args.init)
    except StopRequested as stop:
        print(f"{stop}; checkpoint written, run the same command again to resume", file=sys.stderr)
        return 130 if stop.by_signal else 0
    except (ConfigError, FileNotFoundError, ValueError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    if "model_file_mb" in log:  # rank 0
        print(f"done: {log['global_step']} steps; weights in {args.out}/model.pt ({log['model_file_mb']} MB)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
