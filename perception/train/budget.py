"""Train several models side by side on one machine within a wall-clock budget (a GPU held for minutes).

    python -m perception.train.budget --config compact_gpu --minutes 7 --data DIR [DIR ...] --out runs/gpu \\
        --models ours b_gru b_insonehot b_global

1. *Probe*: every model trains ``--probe-steps`` steps of each of its stages, all at once (as they will run),
   in ``OUT/probe/MODEL``; the seconds per step of each stage come from their logs (the first logged steps,
   start-up and warm-up, are left out).
2. *Plan*: each model gets the steps that fill the budget at those speeds (Ours gives
   ``--segmentation-share`` of its time to the segmentation stage), validating ``--validations`` times per
   stage. The plan is written as a complete config, ``OUT/MODEL/config.toml``: the record of what ran, and the
   command to repeat it anywhere is ``python -m perception.train --config OUT/MODEL/config.toml --model MODEL``.
3. *Train*: the models train side by side with ``python -m perception.train``. A run still going at the
   deadline is stopped with SIGTERM (it checkpoints), and its weights are exported from that checkpoint to
   ``OUT/MODEL/model.pt`` (the best validated weights of the stage it was in where there are some), so every
   model ends with a weights file.

``OUT/budget.json`` records the probe's speeds, the plan, and each run's exit code and wall time.
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import subprocess
import sys
import time
from dataclasses import replace
from pathlib import Path

from perception.config import Config, ConfigError, config_from_dict, config_to_toml, load_config
from perception.model import MODELS, build_model
from perception.train.checkpoint import CHECKPOINT, LOG, MODEL, export_model, load_checkpoint


def stage_names(kind: str, config: Config) -> list[str]:
    """The stages a run of model ``kind`` trains under ``config``."""
    own = ["segmentation", "pose"] if kind == "ours" else ["pose"]
    return [name for name in own if name in config.train.stages]


def seconds_per_step(log: dict, stage: str) -> float:
    """Seconds per optimiser step of ``stage`` in a training log, from its loss records after the first one
    (start-up, CUDA warm-up and the first data loads fall before it)."""
    records = log["stages"][stage]["train"]
    if len(records) < 2:
        raise ValueError(f"stage {stage} logged {len(records)} loss records; probe with more steps")
    first, last = records[0], records[-1]
    return (last["seconds"] - first["seconds"]) / (last["step"] - first["step"])


def plan_steps(speeds: dict[str, dict[str, float]], seconds: float, segmentation_share: float,
               validation_share: float, equal_pose_steps: bool = False) -> dict[str, dict[str, int]]:
    """Optimiser steps per model and stage that fill ``seconds`` of training at ``speeds`` (seconds per step),
    ``validation_share`` of the time set aside for validation. ``equal_pose_steps``: every model's pose stage
    gets the fewest pose steps any model can fit, so that the models compare at equal steps (the faster ones
    finish early) rather than at equal time."""
    usable = seconds * (1.0 - validation_share)
    plan = {}
    for kind, stages in speeds.items():
        shares = {"segmentation": segmentation_share, "pose": 1.0 - segmentation_share} if len(stages) == 2 \
            else {name: 1.0 for name in stages}
        plan[kind] = {name: max(1, int(usable * shares[name] / stages[name])) for name in stages}
    if equal_pose_steps:
        fewest = min(stages["pose"] for stages in plan.values())
        plan = {kind: {**stages, "pose": fewest} for kind, stages in plan.items()}
    return plan


def planned_config(base: Config, steps: dict[str, int], validations: int) -> Config:
    """``base`` with each stage's steps set and validation every ``steps / validations`` steps."""
    train = base.train
    for name, count in steps.items():
        stage = getattr(train, name)
        every = max(1, count // max(1, validations))
        train = replace(train, **{name: replace(stage, steps=count, val_every=every,
                                                warmup_steps=min(stage.warmup_steps, count // 10))})
    return replace(base, train=train)


def export_from_checkpoint(path: Path, out: Path) -> dict:
    """Export the weights of a stopped run's checkpoint (the best validated weights of its current stage where
    there are some) to the model file ``out``; returns what was exported."""
    saved = load_checkpoint(path)
    kind = saved["kind"]
    config = config_from_dict(saved["config"])
    model = build_model(config.model, kind)
    model.load_state_dict(saved["model"])
    state = saved["state"]
    stages = stage_names(kind, config)
    stage = stages[min(state["stage"], len(stages) - 1)]
    best = state.get("best_state")
    if best:
        trainable = model.segmentation if stage == "segmentation" else (
            model.pose if kind == "ours" and config.train.freeze_segmentation else model)
        trainable.load_state_dict(best)
    export_model(model, kind, config.to_dict(), out)
    return {"stage": stage, "step": state["step"], "best_step": state.get("best_step"), "best_weights": bool(best)}


def _launch(kind: str, config_path: Path, data: list[str], out: Path, init: str | None = None) -> subprocess.Popen:
    command = [sys.executable, "-m", "perception.train", "--config", str(config_path), "--model", kind,
               "--out", str(out), "--no-progress", "--data", *data]
    if init is not None:
        command += ["--init", init]
    out.mkdir(parents=True, exist_ok=True)
    with open(out / "stdout.txt", "ab") as log:  # the child keeps its own copy of the file
        return subprocess.Popen(command, stdout=log, stderr=subprocess.STDOUT)


def _wait(procs: dict[str, subprocess.Popen], deadline: float, grace: float = 120.0) -> dict[str, dict]:
    """Wait for every process until ``deadline`` (monotonic seconds); SIGTERM the rest, then give them ``grace``
    seconds to checkpoint before killing them."""
    started = time.monotonic()
    ended: dict[str, float] = {}

    def poll() -> None:
        for kind, proc in procs.items():
            if kind not in ended and proc.poll() is not None:
                ended[kind] = time.monotonic()

    while len(ended) < len(procs) and time.monotonic() < deadline:
        poll()
        time.sleep(0.5)
    poll()
    stopped = [kind for kind in procs if kind not in ended]
    for kind in stopped:
        procs[kind].send_signal(signal.SIGTERM)
    while len(ended) < len(procs) and time.monotonic() < deadline + grace:
        poll()
        time.sleep(0.5)
    for kind, proc in procs.items():
        if kind not in ended:
            proc.kill()
            proc.wait()
            ended[kind] = time.monotonic()
    return {kind: {"returncode": proc.returncode, "stopped_at_deadline": kind in stopped,
                   "seconds": round(ended[kind] - started, 1)} for kind, proc in procs.items()}


def run_budget(config: Config, kinds: list[str], data: list[str], out: Path, minutes: float, probe_steps: int,
               segmentation_share: float, validations: int, validation_share: float,
               init: dict[str, str] | None = None, margin_s: float = 45.0, min_train_s: float = 60.0,
               equal_pose_steps: bool = False) -> dict:
    """The three steps of the module docstring; ``init``: model kind -> weights file its runs start from;
    ``margin_s``: seconds kept back from the plan for the runs' start-up, last validation and export."""
    init = init or {}
    begun = time.monotonic()
    deadline = begun + 60.0 * minutes
    out.mkdir(parents=True, exist_ok=True)
    record: dict = {"minutes": minutes, "models": kinds, "data": data, "probe_steps": probe_steps}

    # 1. probe, all models at once
    probe_config = planned_config(config, {name: probe_steps for name in ("segmentation", "pose")}, 0)
    probe_config = replace(probe_config, train=replace(probe_config.train, val_samples=max(
        2 * max(config.train.segmentation.batch_size, config.train.pose.batch_size), 16),
        log_every=max(1, probe_steps // 4)))
    (out / "probe").mkdir(exist_ok=True)
    probe_path = out / "probe" / "config.toml"
    probe_path.write_text(config_to_toml(probe_config, "speed probe of perception.train.budget"))
    procs = {kind: _launch(kind, probe_path, data, out / "probe" / kind, init.get(kind)) for kind in kinds}
    probed = _wait(procs, deadline)
    speeds = {}
    for kind in kinds:
        if probed[kind]["returncode"] != 0:
            tail = (out / "probe" / kind / "stdout.txt").read_text(errors="replace")[-2000:]
            raise RuntimeError(f"the speed probe of {kind} failed (exit {probed[kind]['returncode']}):\n{tail}")
        log = json.loads((out / "probe" / kind / LOG).read_text())
        speeds[kind] = {name: seconds_per_step(log, name) for name in stage_names(kind, config)}
    record["probe"] = {"seconds": round(time.monotonic() - begun, 1), "seconds_per_step": speeds}
    print(f"probe: {json.dumps(speeds)} in {record['probe']['seconds']} s", flush=True)

    # 2. plan: the time left, less a margin for start-up, the final validation and export
    remaining = deadline - time.monotonic() - margin_s
    if remaining < min_train_s:
        raise RuntimeError(f"{remaining:.0f} s left after the probe: give more --minutes")
    plan = plan_steps(speeds, remaining, segmentation_share, validation_share, equal_pose_steps)
    record["plan"] = {"train_seconds": round(remaining, 1), "steps": plan}
    print(f"plan: {json.dumps(plan)} for {remaining:.0f} s", flush=True)

    # 3. train side by side
    procs = {}
    for kind in kinds:
        planned = planned_config(config, plan[kind], validations)
        planned = replace(planned, data=replace(planned.data, paths=tuple(data)))
        run_dir = out / kind
        run_dir.mkdir(parents=True, exist_ok=True)
        path = run_dir / "config.toml"
        path.write_text(config_to_toml(planned, f"written by perception.train.budget ({minutes} minutes, "
                                       f"{len(kinds)} model{'s side by side' if len(kinds) > 1 else ''}); repeat with\n"
                                       f"python -m perception.train --config {path} --model {kind} --out DIR"
                                       + (f" --init {init[kind]}" if kind in init else "")))
        procs[kind] = _launch(kind, path, data, run_dir, init.get(kind))
    record["runs"] = _wait(procs, deadline)
    for kind in kinds:
        run = record["runs"][kind]
        if not (out / kind / MODEL).exists() and (out / kind / CHECKPOINT).exists():
            run["exported_from_checkpoint"] = export_from_checkpoint(out / kind / CHECKPOINT, out / kind / MODEL)
        run["model_file"] = (out / kind / MODEL).exists()
        if (out / kind / LOG).exists():
            run["finished"] = bool(json.loads((out / kind / LOG).read_text()).get("finished"))
    record["seconds"] = round(time.monotonic() - begun, 1)
    (out / "budget.json").write_text(json.dumps(record, indent=1) + "\n")
    return record


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m perception.train.budget", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--config", required=True, help="TOML config or bundled config name (its steps are "
                        "replaced by the plan)")
    parser.add_argument("--data", nargs="+", required=True, help="dataset folders")
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--models", nargs="+", default=["ours"], choices=sorted(MODELS))
    parser.add_argument("--minutes", type=float, required=True, help="wall-clock budget, probe included")
    parser.add_argument("--probe-steps", type=int, default=40)
    parser.add_argument("--segmentation-share", type=float, default=0.5,
                        help="share of Ours' training time given to the segmentation stage")
    parser.add_argument("--validations", type=int, default=10, help="validations per stage")
    parser.add_argument("--validation-share", type=float, default=0.1,
                        help="share of the time set aside for validation")
    parser.add_argument("--init", action="append", default=[], metavar="MODEL=WEIGHTS",
                        help="start MODEL's runs from these weights (repeatable; see perception.train --init)")
    parser.add_argument("--equal-pose-steps", action="store_true", help="give every model the same number of pose "
                        "steps (the fewest any model fits): a comparison at equal steps, not equal time")
    args = parser.parse_args(argv)
    if args.probe_steps < 8:
        parser.error(f"--probe-steps must be at least 8, got {args.probe_steps}")
    if not 0 < args.segmentation_share < 1 or not 0 <= args.validation_share < 1:
        parser.error("--segmentation-share must be in (0, 1) and --validation-share in [0, 1)")
    init = {}
    for item in args.init:
        kind, sep, path = item.partition("=")
        if not sep or kind not in args.models or not Path(path).is_file():
            parser.error(f"--init {item}: give MODEL=WEIGHTS, MODEL one of --models and WEIGHTS an existing file")
        init[kind] = path
    try:
        config = load_config(args.config)
        record = run_budget(config, args.models, args.data, args.out, args.minutes, args.probe_steps,
                            args.segmentation_share, args.validations, args.validation_share, init,
                            equal_pose_steps=args.equal_pose_steps)
    except (ConfigError, RuntimeError, FileNotFoundError, ValueError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    for kind, run in record["runs"].items():
        print(f"{kind}: exit {run['returncode']}, {run['seconds']} s"
              f"{', finished' if run.get('finished') else ''}"
              f"{', stopped at the deadline' if run['stopped_at_deadline'] and not run.get('finished') else ''}"
              + (f", weights exported from its checkpoint in the {run['exported_from_checkpoint']['stage']} stage"
                 if "exported_from_checkpoint" in run else ""))
    return 0 if all(run["model_file"] for run in record["runs"].values()) else 1


if __name__ == "__main__":
    os.environ.setdefault("PYTHONUNBUFFERED", "1")
    sys.exit(main())
