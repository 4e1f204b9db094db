"""The optimisation loop of one stage: Adam with a cosine schedule, periodic validation with early stopping
(the best weights are kept and restored at the end of the stage), JSON loss records, checkpoints every few
minutes, and clean stops (a signal or ``--stop-after``) that checkpoint first.

Everything a resumed run needs is in :class:`TrainState`; the batches of a step depend only on the seed, the
stage and the step (see :func:`perception.data.epoch_loader`), so a resumed run repeats the uninterrupted one.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field

import torch
from torch import nn
from tqdm import tqdm

from perception.config import StageConfig
from perception.data import batches_per_epoch, epoch_loader, to_device
from perception.train import distributed
from perception.train.checkpoint import cpu_state_dict


@dataclass
class TrainState:
    """Progress of a run. ``stage``: index of the current stage; ``step``: optimiser steps done in it."""

    stage: int = 0
    step: int = 0
    global_step: int = 0
    optimizer: dict | None = None
    best_score: tuple | None = None
    best_step: int = -1
    bad_validations: int = 0
    best_state: dict | None = None
    stopped_early: bool = False
    log: dict = field(default_factory=dict)

    def next_stage(self) -> None:
        self.stage += 1
        self.step = 0
        self.optimizer = None
        self.best_score, self.best_step, self.bad_validations, self.best_state = None, -1, 0, None
        self.stopped_early = False


class StopRequested(Exception):
    """Raised after the checkpoint is written when the run must stop: a signal (``by_signal``) or
    ``--stop-after``."""

    def __init__(self, message: str, by_signal: bool = False):
        super().__init__(message)
        self.by_signal = by_signal


def learning_rate(schedule: StageConfig, step: int, total: int) -> float:
    """Linear warm-up, then cosine decay from ``lr`` to ``lr * min_lr_ratio`` at the last step."""
    warm = min(1.0, (step + 1) / schedule.warmup_steps) if schedule.warmup_steps else 1.0
    progress = step / max(1, total - 1)
    cosine = schedule.min_lr_ratio + (1 - schedule.min_lr_ratio) * 0.5 * (1 + math.cos(math.pi * progress))
    return schedule.lr * warm * cosine


@dataclass
class StageContext:
    """What the loop needs besides the stage and the state."""

    model: nn.Module
    train_set: object
    val_batches: object  # callable returning an iterable of batches (rank 0 only)
    has_val: bool  # whether there are validation samples
    dist: distributed.Dist
    seed: int
    steps: int  # this stage's step budget (config, capped by --max-steps)
    num_workers: int
    max_parts: int
    log_every: int
    checkpoint_seconds: float
    save: object  # callable(state) writing the checkpoint (rank 0)
    write_log: object  # callable(state) writing the JSON log (rank 0)
    stop_after: int | None = None  # global step at which to stop as if interrupted
    stop_flag: object = None  # callable -> bool: a stop signal arrived
    signalled: bool = False  # set when a signal arrived during the stage's last step
    progress: bool = True


def _log_stage(state: TrainState, name: str) -> dict:
    return state.log.setdefault("stages", {}).setdefault(name, {"train": [], "val": []})


def _validate(ctx: StageContext, stage, state: TrainState, trainable: nn.Module) -> None:
    """Validate on rank 0, update the early-stopping state, share the decision with every rank. Without
    validation samples nothing is validated and the stage ends with its last weights."""
    if not ctx.has_val:
        return
    decision = None
    if ctx.dist.main:
        metrics, score = stage.validate(ctx.model, ctx.val_batches())
        improved = state.best_score is None or tuple(score) > tuple(state.best_score)
        if improved:
            state.best_score, state.best_step, state.bad_validations = tuple(score), state.step, 0
            state.best_state = cpu_state_dict(trainable)
        else:
            state.bad_validations += 1
        patience = stage.schedule.patience
        stop = bool(patience and state.bad_validations >= patience)
        _log_stage(state, stage.name)["val"].append({"step": state.step, **metrics, "best": improved})
        decision = (state.best_score, state.best_step, state.bad_validations, stop)
        ctx.write_log(state)
    decision = distributed.broadcast(decision, ctx.dist)
    state.best_score, state.best_step, state.bad_validations, state.stopped_early = decision


def run_stage(ctx: StageContext, stage, state: TrainState) -> None:
    """Train ``stage`` from ``state.step`` to its end; leaves the best weights in the model and the state at the
    start of the next stage (checkpointed)."""
    model, dist = ctx.model, ctx.dist
    schedule: StageConfig = stage.schedule
    trainable = stage.trainable(model)
    stage.set_modes(model)
    net = distributed.wrap(trainable, dist)
    params = [p for p in trainable.parameters() if p.requires_grad]
    optimizer = torch.optim.Adam(params, lr=schedule.lr, weight_decay=schedule.weight_decay, fused=True)
    if state.optimizer is not None:
        optimizer.load_state_dict(state.optimizer)
    per_epoch = batches_per_epoch(ctx.train_set, schedule.batch_size, dist.world)
    if per_epoch < 1:
        raise ValueError(f"{len(ctx.train_set)} training samples: fewer than one batch of {schedule.batch_size} "
                         f"per process")
    record = _log_stage(state, stage.name)
    seconds_before, started = record.get("seconds", 0.0), time.monotonic()
    sums: dict[str, float] = {}
    count = 0
    last_save = time.monotonic()
    bar = tqdm(total=ctx.steps, initial=state.step, desc=stage.name, unit="step",
               disable=not (ctx.progress and dist.main), dynamic_ncols=True)
    while state.step < ctx.steps and not state.stopped_early:
        epoch, offset = divmod(state.step, per_epoch)
        loader = epoch_loader(ctx.train_set, schedule.batch_size, epoch, ctx.seed + 1000 * state.stage, dist.rank,
                              dist.world, offset, True, ctx.num_workers, ctx.max_parts)
        for batch in loader:
            lr = learning_rate(schedule, state.step, ctx.steps)
            for group in optimizer.param_groups:
                group["lr"] = lr
            stage.set_modes(model)
            terms = stage.loss(net, model, to_device(batch, dist.device))
            optimizer.zero_grad(set_to_none=True)
            terms["loss"].backward()
            if schedule.grad_clip:
                torch.nn.utils.clip_grad_norm_(params, schedule.grad_clip)
            optimizer.step()
            state.step += 1
            state.global_step += 1

            for key, value in terms.items():
                if key != "perm":
                    sums[key] = sums.get(key, 0.0) + float(value.detach())
            count += 1
            if not math.isfinite(float(terms["loss"].detach())):
                raise FloatingPointError(f"{stage.name} loss is {float(terms['loss'])} at step {state.step}")
            record["seconds"] = seconds_before + time.monotonic() - started
            if state.step % ctx.log_every == 0 or state.step == ctx.steps:
                record["train"].append({"step": state.step, "lr": lr, "seconds": round(record["seconds"], 2),
                                        **{k: v / count for k, v in sums.items()}})
                bar.set_postfix(loss=f"{sums['loss'] / count:.4f}")
                sums, count = {}, 0
            bar.update()

            at_end = state.step >= ctx.steps
            if (schedule.val_every and state.step % schedule.val_every == 0) or at_end:
                _validate(ctx, stage, state, trainable)
                stage.set_modes(model)
            by_signal = bool(distributed.all_reduce_max(int(bool(ctx.stop_flag and ctx.stop_flag())), dist))
            stop = by_signal or (ctx.stop_after is not None and state.global_step >= ctx.stop_after)
            due = time.monotonic() - last_save >= ctx.checkpoint_seconds
            if (due or stop) and not (at_end or state.stopped_early):
                state.optimizer = optimizer.state_dict()
                ctx.save(state)
                last_save = time.monotonic()
                if stop:
                    bar.close()
                    raise StopRequested(f"stopped after {state.global_step} steps", by_signal)
            if by_signal:  # at the end of the stage: the caller stops after the stage-end checkpoint
                ctx.stop_after, ctx.signalled = state.global_step, True
            if at_end or state.stopped_early:
                break
    bar.close()
    best = distributed.broadcast(state.best_state, dist)  # only rank 0 validates and keeps the best weights
    if best is not None:
        trainable.load_state_dict(best)
    record.update({"steps": state.step, "best_step": state.best_step, "stopped_early": state.stopped_early,
                   "best_score": list(state.best_score) if state.best_score else None})
    state.next_stage()
    ctx.save(state)
