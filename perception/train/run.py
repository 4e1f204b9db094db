"""A training run: build or resume the model, run its stages, export the weights.

Output folder: ``checkpoint.pt`` (full state, rewritten every few minutes and at every stage end; a run started
again with the same ``--out`` resumes from it), ``log.json`` (losses, validation metrics, timing) and, at the
end, ``model.pt`` (configuration + weights only, what evaluation and bundling use).
"""

from __future__ import annotations

import functools
import json
import re
import signal
import sys
import threading
from contextlib import contextmanager
from pathlib import Path

import torch
from torch.utils.data import DataLoader

from perception.config import Config, ConfigError
from perception.data import ViewDataset, collate, object_files, to_device
from perception.model import build_model, count_parameters
from perception.train import distributed
from perception.train.checkpoint import (
    CHECKPOINT,
    FORMAT,
    LOG,
    MODEL,
    atomic_torch_save,
    atomic_write_bytes,
    cpu_state_dict,
    export_model,
    load_checkpoint,
    rng_state,
    seed_everything,
    set_rng_state,
)
from perception.train.loop import StageContext, StopRequested, TrainState, run_stage
from perception.train.stages import stages_for

# the weights model.condition_every_scale adds to the segmentation decoder (zero-initialised)
SCALE_CONDITIONING = re.compile(r"segmentation\.decoder\.ups\.\d+\.fuse\.cond\.weight")

# settings that may change between an interrupted run and its resumption (they do not change the result)
OPERATIONAL = {"train.checkpoint_minutes", "train.num_workers", "train.threads", "data.paths", "data.categories"}


def _flatten(d: dict, prefix: str = "") -> dict:
    out = {}
    for key, value in d.items():
        name = f"{prefix}.{key}" if prefix else key
        out.update(_flatten(value, name) if isinstance(value, dict) else {name: value})
    return out


def check_resumable(saved: dict, config: Config, kind: str, max_steps: int | None) -> None:
    """Refuse to resume a checkpoint made with another model kind, step cap or (result-changing) setting."""
    if saved.get("format") != FORMAT:
        raise ConfigError(f"checkpoint format {saved.get('format')} is not {FORMAT}")
    if saved["kind"] != kind:
        raise ConfigError(f"the checkpoint is of model {saved['kind']!r}, not {kind!r}; choose another --out")
    if saved.get("max_steps") != max_steps:
        raise ConfigError(f"the checkpoint was made with --max-steps {saved.get('max_steps')}, not {max_steps}")
    old, new = _flatten(saved["config"]), _flatten(config.to_dict())
    for name in sorted(set(old) | set(new)):
        if name not in OPERATIONAL and old.get(name) != new.get(name):
            raise ConfigError(f"the checkpoint was made with {name} = {old.get(name)!r}, the config has "
                              f"{new.get(name)!r}; choose another --out or the same config")


@contextmanager
def stop_on_signals():
    """SIGINT/SIGTERM set a flag checked after every step (the run then checkpoints and stops cleanly);
    a second SIGINT interrupts at once."""
    flag = threading.Event()
    if threading.current_thread() is not threading.main_thread():
        yield flag.is_set
        return

    def handler(signum, frame):
        if flag.is_set() and signum == signal.SIGINT:
            raise KeyboardInterrupt
        flag.set()

    previous = {s: signal.signal(s, handler) for s in (signal.SIGINT, signal.SIGTERM)}
    try:
        yield flag.is_set
    finally:
        for s, h in previous.items():
            signal.signal(s, h)


def train(config: Config, out: str | Path, kind: str = "ours", max_steps: int | None = None,
          stop_after: int | None = None, progress: bool = True, init: str | Path | None = None) -> dict:
    """Train (or resume) in ``out``. Returns the final log; raises :class:`StopRequested` after a clean stop.

    ``init``: a ``model.pt``/``checkpoint.pt`` whose weights start a new run (fine-tuning); a run that resumes
    from ``out`` ignores it."""
    out = Path(out)
    dist = distributed.setup()
    try:
        with stop_on_signals() as stop_flag:
            return _train(config, out, kind, max_steps, stop_after, progress, dist, stop_flag, init)
    finally:
        distributed.cleanup(dist)


def _train(config, out, kind, max_steps, stop_after, progress, dist, stop_flag, init=None) -> dict:
    threads = torch.get_num_threads()
    if config.train.threads:
        torch.set_num_threads(config.train.threads)
    try:
        return _run_stages(config, out, kind, max_steps, stop_after, progress, dist, stop_flag, init)
    finally:
        torch.set_num_threads(threads)


def load_initial_weights(model: torch.nn.Module, path: str | Path, kind: str) -> None:
    """Copy the weights of the model file ``path`` into ``model``; a file of another model kind or architecture is
    refused with a :class:`ConfigError` naming the file and the first mismatch."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"--init weights {path} not found")
    payload = load_checkpoint(path)
    if not isinstance(payload, dict) or "model" not in payload:
        raise ConfigError(f"--init {path} is not a perception model file (no model weights)")
    if payload.get("kind") != kind:
        raise ConfigError(f"--init {path} holds model {payload.get('kind')!r}, not {kind!r}")
    own = model.state_dict()
    for name, value in payload["model"].items():
        if name not in own or own[name].shape != value.shape:
            raise ConfigError(f"--init {path}: weight {name} does not fit this config's architecture "
                              f"({tuple(value.shape)} vs {tuple(own[name].shape) if name in own else 'absent'})")
    missing = sorted(set(own) - set(payload["model"]))
    # the per-scale conditioning of model.condition_every_scale starts at zero, so a model trained without it is
    # the same function with it, and can be fine-tuned into it
    added = [name for name in missing if SCALE_CONDITIONING.fullmatch(name)]
    missing = [name for name in missing if name not in added]
    if missing:
        raise ConfigError(f"--init {path} lacks weight {missing[0]} of this config's architecture")
    weights = {k: v.to(own[k].dtype) for k, v in payload["model"].items()}
    weights.update({name: torch.zeros_like(own[name]) for name in added})
    model.load_state_dict(weights)


def _run_stages(config, out, kind, max_steps, stop_after, progress, dist, stop_flag, init=None) -> dict:
    if not config.data.paths:
        raise ConfigError("no training data: give --data DIR or data.paths in the config")
    seed_everything(config.train.seed)
    model = build_model(config.model, kind).to(dist.device)
    if config.train.channels_last:  # kept by every load_state_dict below (it copies into the parameters)
        model.to(memory_format=torch.channels_last)
    state = TrainState()
    checkpoint_path = out / CHECKPOINT
    if checkpoint_path.exists():
        saved = load_checkpoint(checkpoint_path)
        check_resumable(saved, config, kind, max_steps)
        model.load_state_dict(saved["model"])
        state = TrainState(**saved["state"])
        set_rng_state(saved["rng"])
        if dist.main:
            print(f"resuming {checkpoint_path} at stage {state.stage}, step {state.step} "
                  f"({state.global_step} steps done)", flush=True)
    elif init is None and kind == "ours" and "segmentation" not in config.train.stages:
        raise ConfigError("train.stages leaves out the segmentation stage: give --init weights for the "
                          "segmentation network to start from")
    elif init is not None:
        load_initial_weights(model, init, kind)
        model.to(dist.device)
        if dist.main:
            print(f"starting from the weights of {init}", flush=True)

    shuffle, seed = config.train.shuffle_parts, config.train.seed
    train_set = ViewDataset(object_files(config.data.paths, "train", config.data.categories), 0, shuffle, seed)
    val_set = ViewDataset(object_files(config.data.paths, "val", config.data.categories), config.train.val_samples,
                          shuffle, seed)
    max_parts = config.model.max_parts

    if dist.main and len(val_set) == 0:
        print("warning: no validation samples (val/ split): no early stopping, the last weights are kept",
              file=sys.stderr)

    def val_batches():
        size = max(config.train.segmentation.batch_size, config.train.pose.batch_size)
        loader = DataLoader(val_set, batch_size=size, shuffle=False, num_workers=0,
                            collate_fn=functools.partial(collate, max_parts=max_parts))
        return (to_device(b, dist.device) for b in loader)

    state.log.update({"model": kind, "config": config.to_dict(), "parameters": count_parameters(model),
                      "samples": {"train": len(train_set), "val": len(val_set)}, "world_size": dist.world})

    def write_log(current: TrainState) -> None:
        if dist.main:
            current.log["global_step"] = current.global_step
            atomic_write_bytes((json.dumps(current.log, indent=1, default=float) + "\n").encode(), out / LOG)

    def save(current: TrainState) -> None:
        if not dist.main:
            return
        fields = {k: getattr(current, k) for k in current.__dataclass_fields__}
        payload = {"format": FORMAT, "kind": kind, "config": config.to_dict(), "max_steps": max_steps,
                   "model": cpu_state_dict(model), "state": fields, "rng": rng_state()}
        atomic_torch_save(payload, checkpoint_path)
        write_log(current)

    stages = stages_for(model, config)
    if not stages:
        raise ConfigError(f"model {kind!r} has none of the stages train.stages names ({list(config.train.stages)})")
    for index in range(state.stage, len(stages)):
        stage = stages[index]
        steps = stage.schedule.steps if max_steps is None else min(stage.schedule.steps, max_steps)
        ctx = StageContext(model=model, train_set=train_set, val_batches=val_batches, has_val=len(val_set) > 0,
                           dist=dist, seed=config.train.seed, steps=steps, num_workers=config.train.num_workers,
                           max_parts=max_parts, log_every=config.train.log_every,
                           checkpoint_seconds=60.0 * config.train.checkpoint_minutes, save=save,
                           write_log=write_log, stop_after=stop_after, stop_flag=stop_flag, progress=progress)
        run_stage(ctx, stage, state)
        if index + 1 < len(stages) and ctx.stop_after is not None and state.global_step >= ctx.stop_after:
            raise StopRequested(f"stopped after {state.global_step} steps", ctx.signalled)

    state.log["global_step"] = state.global_step
    if dist.main:
        size = export_model(model, kind, config.to_dict(), out / MODEL)
        state.log.update({"finished": True, "model_file": MODEL, "model_file_mb": round(size / 2**20, 3)})
        save(state)
    return state.log
