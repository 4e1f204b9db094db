"""End to end on a tiny dataset: training both stages, a checkpoint, resuming to the same weights as an
uninterrupted run, evaluation writing the paper's figures."""

import json
import math
import subprocess
import sys

import pytest
import torch

from perception.config import CONFIG_DIR, load_config
from perception.data import ViewDataset, collate, object_files
from perception.dataset.build import BuildConfig, build
from perception.evaluate import load_model
from perception.model import build_model
from perception.train.checkpoint import CHECKPOINT, LOG, MODEL
from perception.train.cli import main
from perception.train.run import SCALE_CONDITIONING, load_initial_weights


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    out = tmp_path_factory.mktemp("perception") / "chairs"
    build(BuildConfig(category="chair", level="3", count=10, views=2, seed=3), out, progress=False)
    return out


@pytest.fixture(scope="module")
def uninterrupted(data, tmp_path_factory):
    out = tmp_path_factory.mktemp("run") / "full"
    assert main(["--config", "tiny", "--data", str(data), "--out", str(out), "--no-progress"]) == 0
    return out


def weights(path):
    return torch.load(path, map_location="cpu", weights_only=False)["model"]


def test_training_writes_checkpoint_log_and_weights(uninterrupted):
    assert (uninterrupted / CHECKPOINT).exists() and (uninterrupted / MODEL).exists()
    log = json.loads((uninterrupted / LOG).read_text())
    assert log["finished"] and log["global_step"] == 6
    for stage in ("segmentation", "pose"):
        records = log["stages"][stage]["train"]
        assert records and all(math.isfinite(r["loss"]) for r in records)
        assert log["stages"][stage]["val"]
    assert 0 <= log["stages"]["pose"]["val"][-1]["val_part_accuracy"] <= 1
    saved = torch.load(uninterrupted / MODEL, map_location="cpu", weights_only=False)
    assert saved["kind"] == "ours" and saved["config"]["model"]["image_size"] == 64
    assert saved["config"]["data"]["paths"] == []  # a bundled weights file names no training data location


def test_resume_gives_the_uninterrupted_weights(data, uninterrupted, tmp_path):
    out = tmp_path / "resumed"
    args = ["--config", "tiny", "--data", str(data), "--out", str(out), "--no-progress"]
    assert main([*args, "--stop-after", "2"]) == 0  # interrupted inside the segmentation stage
    state = torch.load(out / CHECKPOINT, map_location="cpu", weights_only=False)["state"]
    assert (state["stage"], state["step"]) == (0, 2) and not (out / MODEL).exists()
    assert main([*args, "--stop-after", "4"]) == 0  # ... and inside the pose stage
    assert main(args) == 0
    assert json.loads((out / LOG).read_text())["global_step"] == 6
    a, b = weights(uninterrupted / MODEL), weights(out / MODEL)
    assert a.keys() == b.keys()
    assert [k for k in a if not torch.equal(a[k], b[k])] == []


def test_resume_refuses_another_model(data, uninterrupted, tmp_path, capsys):
    out = tmp_path / "other"
    args = ["--config", "tiny", "--data", str(data), "--out", str(out), "--no-progress"]
    assert main([*args, "--stop-after", "1", "--model", "b_global"]) == 0
    assert main(args) == 2
    assert "b_global" in capsys.readouterr().err


def test_init_starts_from_given_weights_and_refuses_another_model(data, uninterrupted, tmp_path, capsys):
    start = weights(uninterrupted / MODEL)
    out = tmp_path / "finetune"
    args = ["--config", "tiny", "--data", str(data), "--out", str(out), "--no-progress",
            "--init", str(uninterrupted / MODEL)]
    assert main([*args, "--stop-after", "1"]) == 0  # one segmentation step: the pose network is untouched
    after = torch.load(out / CHECKPOINT, map_location="cpu", weights_only=False)["model"]
    pose = [k for k in start if not k.startswith("segmentation.")]
    assert pose and all(torch.equal(start[k], after[k]) for k in pose)
    assert any(not torch.equal(start[k], after[k]) for k in start if k.startswith("segmentation."))
    fresh = tmp_path / "fresh"
    assert main(["--config", "tiny", "--data", str(data), "--out", str(fresh), "--no-progress",
                 "--stop-after", "1"]) == 0
    random = torch.load(fresh / CHECKPOINT, map_location="cpu", weights_only=False)["model"]
    assert any(not torch.equal(start[k], random[k]) for k in pose)
    # a baseline's weights do not fit the paper's network: refused, naming the file
    gru = tmp_path / "gru"
    assert main(["--config", "tiny", "--data", str(data), "--out", str(gru), "--no-progress", "--model", "b_gru",
                 "--max-steps", "1"]) == 0
    capsys.readouterr()
    assert main(["--config", "tiny", "--data", str(data), "--out", str(tmp_path / "wrong"), "--no-progress",
                 "--init", str(gru / MODEL)]) == 2
    err = capsys.readouterr().err
    assert str(gru / MODEL) in err and "b_gru" in err


def test_a_model_fine_tunes_into_the_decoder_conditioned_at_every_scale(data, uninterrupted, tmp_path):
    """Weights trained with the paper's decoder (f_3d at the bottleneck only) start a model whose decoder takes
    f_3d at every scale: its added weights start at zero, so it is the same function at first, and they train."""
    config_file = tmp_path / "every_scale.toml"
    text = (CONFIG_DIR / "tiny.toml").read_text()
    config_file.write_text(text.replace("[model]\n", "[model]\ncondition_every_scale = true\n", 1))
    paper, _, _ = load_model(uninterrupted / MODEL)
    every = build_model(load_config(config_file).model)
    load_initial_weights(every, uninterrupted / MODEL, "ours")
    added = [k for k in every.state_dict() if k not in paper.state_dict()]
    assert added and all(SCALE_CONDITIONING.fullmatch(k) for k in added)
    sample = collate([ViewDataset(object_files([data], "train"))[0], ViewDataset(object_files([data], "train"))[1]])
    every.eval()
    with torch.no_grad():
        assert torch.allclose(paper.segmentation(sample)["masks"], every.segmentation(sample)["masks"])
    out = tmp_path / "every"
    assert main(["--config", str(config_file), "--data", str(data), "--out", str(out), "--no-progress",
                 "--init", str(uninterrupted / MODEL), "--stop-after", "1"]) == 0
    after = torch.load(out / CHECKPOINT, map_location="cpu", weights_only=False)["model"]
    assert all(after[k].abs().sum() > 0 for k in added)
    # without the option, a file that lacks other weights is still refused
    assert main(["--config", "tiny", "--data", str(data), "--out", str(tmp_path / "back"), "--no-progress",
                 "--init", str(out / CHECKPOINT), "--stop-after", "1"]) == 2


def test_bfloat16_channels_last_run_resumes_and_exports_float32_weights(data, uninterrupted, tmp_path, capsys):
    """train.precision = "bfloat16" with train.channels_last: both stages train with finite losses, a resumed run
    repeats the uninterrupted one, and the exported weights are float32 that load into the default layout."""
    config_file = tmp_path / "fast.toml"
    config_file.write_text((CONFIG_DIR / "tiny.toml").read_text().replace(
        "[train]\n", '[train]\nprecision = "bfloat16"\nchannels_last = true\n'))
    args = ["--config", str(config_file), "--data", str(data), "--no-progress"]
    assert main([*args, "--out", str(tmp_path / "full")]) == 0
    log = json.loads((tmp_path / "full" / LOG).read_text())
    assert log["finished"] and log["config"]["train"]["precision"] == "bfloat16"
    assert all(math.isfinite(r["loss"]) for stage in log["stages"].values() for r in stage["train"])
    resumed = tmp_path / "resumed"
    assert main([*args, "--out", str(resumed), "--stop-after", "4"]) == 0
    assert main([*args, "--out", str(resumed)]) == 0
    a, b = weights(tmp_path / "full" / MODEL), weights(resumed / MODEL)
    assert [k for k in a if not torch.equal(a[k], b[k])] == []
    assert all(v.dtype == torch.float32 for v in a.values() if v.is_floating_point())
    assert any(not torch.equal(a[k], v) for k, v in weights(uninterrupted / MODEL).items())  # it trained
    model, config, _ = load_model(tmp_path / "full" / MODEL)  # the default layout, for inference
    assert config.train.channels_last and model.state_dict().keys() == a.keys()
    # a float32 run in the default layout does not resume this checkpoint: the numbers would differ
    capsys.readouterr()
    assert main(["--config", "tiny", "--data", str(data), "--out", str(resumed), "--no-progress"]) == 2
    assert "train.channels_last" in capsys.readouterr().err


def test_bfloat16_forward_gives_nearly_the_float32_pose_loss(data, uninterrupted):
    """The autocast forward computes the same losses to bfloat16's precision (the outputs reach the losses as
    float32)."""
    from dataclasses import replace

    from perception.train.stages import PoseStage

    model, config, _ = load_model(uninterrupted / MODEL)
    batch = collate([ViewDataset(object_files([data], "train"))[k] for k in range(4)])
    losses = {}
    for precision in ("float32", "bfloat16"):
        stage = PoseStage(replace(config, train=replace(config.train, precision=precision)))
        stage.set_modes(model)
        model.eval()  # the batch statistics of four samples aside, the same function
        with torch.no_grad():
            terms = stage.loss(stage.trainable(model), model, batch)
        assert terms["loss"].dtype == torch.float32
        losses[precision] = float(terms["loss"])
    assert losses["bfloat16"] == pytest.approx(losses["float32"], rel=0.05)
    assert losses["bfloat16"] != losses["float32"]  # autocast did run


def test_baseline_trains(data, tmp_path):
    out = tmp_path / "gru"
    assert main(["--config", "tiny", "--data", str(data), "--out", str(out), "--no-progress", "--model", "b_gru",
                 "--max-steps", "2"]) == 0
    log = json.loads((out / LOG).read_text())
    assert list(log["stages"]) == ["pose"] and log["global_step"] == 2


def test_evaluate_cli_writes_part_accuracy(data, uninterrupted, tmp_path):
    report = tmp_path / "eval.json"
    result = subprocess.run(
        [sys.executable, "-m", "perception.evaluate", "--checkpoint", str(uninterrupted / MODEL), "--data", str(data),
         "--json", str(report), "--no-progress"], capture_output=True, text=True)
    assert result.returncode == 0, result.stderr
    assert "Part Acc." in result.stdout and "Shape Chamfer" in result.stdout
    figures = json.loads(report.read_text())
    assert 0.0 <= figures["part_accuracy"] <= 1.0 and figures["samples"] == 2
    assert figures["shape_chamfer"] >= 0
    # the parts reach the network in a random order unless --keep-part-order; the record says which
    from perception.evaluate import main as evaluate_main

    kept = tmp_path / "kept.json"
    assert evaluate_main(["--checkpoint", str(uninterrupted / MODEL), "--data", str(data), "--json", str(kept),
                          "--no-progress", "--keep-part-order"]) == 0
    assert figures["shuffle_parts"] is True and json.loads(kept.read_text())["shuffle_parts"] is False
    assert json.loads(kept.read_text())["parts"] == figures["parts"]


def test_torchrun_two_processes(data, tmp_path):
    out = tmp_path / "ddp"
    torchrun = [sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc_per_node", "2"]
    result = subprocess.run(
        [*torchrun, "-m", "perception.train", "--config", "tiny", "--data", str(data), "--out", str(out),
         "--model", "b_insonehot", "--max-steps", "2", "--no-progress"], capture_output=True, text=True)
    assert result.returncode == 0, result.stderr[-2000:]
    log = json.loads((out / LOG).read_text())
    assert log["world_size"] == 2 and log["global_step"] == 2 and (out / MODEL).exists()


def test_pose_stage_alone_fine_tunes_the_pose_network(data, uninterrupted, tmp_path, capsys):
    """train.stages = ["pose"] trains the pose network of given weights and leaves the segmentation network
    as it is; without --init there is no segmentation network to keep, and the run is refused."""
    config_file = tmp_path / "pose_only.toml"
    config_file.write_text((CONFIG_DIR / "tiny.toml").read_text().replace("[train]\n", '[train]\nstages = ["pose"]\n'))
    out = tmp_path / "pose"
    assert main(["--config", str(config_file), "--data", str(data), "--out", str(out), "--no-progress",
                 "--init", str(uninterrupted / MODEL)]) == 0
    assert list(json.loads((out / LOG).read_text())["stages"]) == ["pose"]
    start, after = weights(uninterrupted / MODEL), weights(out / MODEL)
    assert all(torch.equal(start[k], after[k]) for k in start if k.startswith("segmentation."))
    assert any(not torch.equal(start[k], after[k]) for k in start if k.startswith("pose."))
    capsys.readouterr()
    assert main(["--config", str(config_file), "--data", str(data), "--out", str(tmp_path / "none"),
                 "--no-progress"]) == 2
    assert "--init" in capsys.readouterr().err
    # a baseline has no segmentation stage to run alone
    seg_only = tmp_path / "seg_only.toml"
    seg_only.write_text(config_file.read_text().replace('stages = ["pose"]', 'stages = ["segmentation"]'))
    assert main(["--config", str(seg_only), "--data", str(data), "--out", str(tmp_path / "gru"), "--no-progress",
                 "--model", "b_gru"]) == 2
    assert "has none of the stages" in capsys.readouterr().err


def test_budget_plan_fills_the_time_at_the_probed_speeds():
    from perception.train.budget import plan_steps, planned_config, seconds_per_step

    log = {"stages": {"pose": {"train": [{"step": 10, "seconds": 3.0}, {"step": 20, "seconds": 4.0},
                                         {"step": 40, "seconds": 6.0}]}}}
    assert seconds_per_step(log, "pose") == pytest.approx(0.1)
    plan = plan_steps({"ours": {"segmentation": 0.2, "pose": 0.1}, "b_gru": {"pose": 0.05}}, 100.0, 0.5, 0.1)
    assert plan == {"ours": {"segmentation": 225, "pose": 450}, "b_gru": {"pose": 1800}}
    # at equal steps every model gets the pose steps of the slowest
    equal = plan_steps({"ours": {"segmentation": 0.2, "pose": 0.1}, "b_gru": {"pose": 0.05}}, 100.0, 0.5, 0.1, True)
    assert equal == {"ours": {"segmentation": 225, "pose": 450}, "b_gru": {"pose": 450}}
    config = planned_config(load_config("compact_gpu"), plan["ours"], validations=9)
    assert (config.train.segmentation.steps, config.train.segmentation.val_every) == (225, 25)
    assert (config.train.pose.steps, config.train.pose.val_every) == (450, 50)
    assert config.train.segmentation.warmup_steps == 22  # at most a tenth of the stage


def test_budget_trains_side_by_side_and_exports_a_stopped_run(data, tmp_path):
    """A short budget end to end (probe, plan, two models side by side), then a run stopped mid-stage whose
    checkpoint is exported to a weights file that evaluation loads."""
    from perception.train.budget import export_from_checkpoint, run_budget

    out = tmp_path / "budget"
    record = run_budget(load_config("tiny"), ["ours", "b_global"], [str(data)], out, minutes=0.6, probe_steps=8,
                        segmentation_share=0.5, validations=2, validation_share=0.1, margin_s=5.0, min_train_s=5.0)
    assert set(record["plan"]["steps"]) == {"ours", "b_global"}
    assert set(record["plan"]["steps"]["ours"]) == {"segmentation", "pose"}
    for kind in ("ours", "b_global"):
        assert record["runs"][kind]["model_file"] and load_model(out / kind / MODEL)[2] == kind
        assert load_config(out / kind / "config.toml").train.pose.steps == record["plan"]["steps"][kind]["pose"]
    assert json.loads((out / "budget.json").read_text())["plan"] == record["plan"]

    stopped = tmp_path / "stopped"
    assert main(["--config", "tiny", "--data", str(data), "--out", str(stopped), "--no-progress",
                 "--stop-after", "5"]) == 0  # inside the pose stage, after one validation of it
    exported = export_from_checkpoint(stopped / CHECKPOINT, stopped / MODEL)
    assert exported["stage"] == "pose" and exported["best_weights"]
    model, _, kind = load_model(stopped / MODEL)
    assert kind == "ours"
    assert torch.load(stopped / MODEL, map_location="cpu", weights_only=False)["config"]["data"]["paths"] == []
