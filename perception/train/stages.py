"""The training stages: what each trains, its loss and its validation.

The paper's model trains in two stages: ``segmentation`` (the conditional U-Net, loss: negative soft-IoU, with
``loss.mask_cross_entropy`` x a per-pixel cross-entropy;
validated by the mean matched soft IoU), then ``pose`` (the pose network on the masks predicted by the
segmentation network, frozen by default; loss: the four pose losses on both phases; validated by Part
Accuracy, ties broken by the pose loss). With ``train.freeze_segmentation = false`` the pose stage fine-tunes
both networks on the sum of the pose and segmentation losses. The baselines have the pose stage only.

With ``train.precision = "bfloat16"`` the training forward passes run under ``torch.autocast`` and their outputs
are cast back to float32 before the losses (whose matching hands costs to scipy); validation runs in float32.
"""

from __future__ import annotations

import torch
from torch import nn

from perception.config import Config, StageConfig
from perception.losses import model_pose_loss, segmentation_loss
from perception.metrics import MetricSummary, evaluate_batch
from perception.model import AssemblyNet


def to_float32(value):
    """``value`` with every floating-point tensor in it (nested in dicts, lists and tuples) as float32."""
    if torch.is_tensor(value):
        return value.float() if value.is_floating_point() else value
    if isinstance(value, dict):
        return {key: to_float32(item) for key, item in value.items()}
    if isinstance(value, (list, tuple)):
        return type(value)(to_float32(item) for item in value)
    return value


class Forward:
    """Runs a stage's training forward passes at ``train.precision``: ``forward(fn, batch, *args)`` is
    ``fn(batch, *args)``, under bfloat16 autocast on the batch's device (outputs cast back to float32) when the
    config asks for it."""

    def __init__(self, config: Config):
        self.bfloat16 = config.train.precision == "bfloat16"

    def __call__(self, fn, batch: dict, *args):
        if not self.bfloat16:
            return fn(batch, *args)
        with torch.autocast(device_type=batch["image"].device.type, dtype=torch.bfloat16):
            return to_float32(fn(batch, *args))


class SegmentationStage:
    name = "segmentation"

    def __init__(self, config: Config):
        self.config = config
        self.schedule: StageConfig = config.train.segmentation
        self.forward = Forward(config)

    def trainable(self, model: nn.Module) -> nn.Module:
        return model.segmentation

    def set_modes(self, model: nn.Module) -> None:
        model.train()
        for p in model.parameters():
            p.requires_grad_(False)
        for p in model.segmentation.parameters():
            p.requires_grad_(True)

    def loss(self, net: nn.Module, model: nn.Module, batch: dict) -> dict:
        return segmentation_loss(self.forward(net, batch), batch, self.config.loss)

    @torch.no_grad()
    def validate(self, model: nn.Module, batches) -> tuple[dict, tuple]:
        model.eval()
        total, parts = 0.0, 0
        for batch in batches:
            terms = segmentation_loss(model.segmentation(batch), batch, self.config.loss)
            n = int(batch["valid"].sum())
            total += float(terms["soft_iou"]) * n
            parts += n
        iou = total / max(parts, 1)
        return {"val_soft_iou": iou}, (iou,)


class PoseStage:
    name = "pose"

    def __init__(self, config: Config):
        self.config = config
        self.schedule: StageConfig = config.train.pose
        self.freeze = config.train.freeze_segmentation
        self.forward = Forward(config)

    def _frozen(self, model: nn.Module) -> bool:
        return isinstance(model, AssemblyNet) and self.freeze

    def trainable(self, model: nn.Module) -> nn.Module:
        return model.pose if self._frozen(model) else model

    def set_modes(self, model: nn.Module) -> None:
        model.train()
        for p in model.parameters():
            p.requires_grad_(True)
        if self._frozen(model):
            model.segmentation.eval()  # frozen batch-norm statistics too
            for p in model.segmentation.parameters():
                p.requires_grad_(False)

    def loss(self, net: nn.Module, model: nn.Module, batch: dict) -> dict:
        if self._frozen(model):
            with torch.no_grad():
                masks = self.forward(model.segmentation, batch)["masks"]
            out = self.forward(net, batch, masks)
            out["quat"], out["trans"] = out["poses"][-1]
            return model_pose_loss(out, batch, self.config.loss)
        out = self.forward(net, batch)
        terms = model_pose_loss(out, batch, self.config.loss)
        if isinstance(model, AssemblyNet):  # fine-tuning both networks: keep the masks supervised
            seg = segmentation_loss(out, batch, self.config.loss)
            terms["loss"] = terms["loss"] + seg["loss"]
            terms["soft_iou"] = seg["soft_iou"]
        return terms

    @torch.no_grad()
    def validate(self, model: nn.Module, batches) -> tuple[dict, tuple]:
        model.eval()
        summary = MetricSummary()
        loss, count = 0.0, 0
        for batch in batches:
            out = model(batch)
            summary.add(evaluate_batch(out, batch))
            loss += float(model_pose_loss(out, batch, self.config.loss)["final"]) * len(batch["name"])
            count += len(batch["name"])
        figures = summary.summary()
        metrics = {"val_part_accuracy": figures["part_accuracy"], "val_shape_chamfer": figures["shape_chamfer"],
                   "val_part_accuracy_visible": figures["part_accuracy_visible"],
                   "val_part_accuracy_invisible": figures["part_accuracy_invisible"],
                   "val_pose_loss": loss / max(count, 1)}
        return metrics, (figures["part_accuracy"], -metrics["val_pose_loss"])


def stages_for(model: nn.Module, config: Config) -> list:
    """The stages ``model`` trains, in order: those it has (the baselines have no segmentation) of
    ``train.stages``."""
    own = [SegmentationStage(config), PoseStage(config)] if isinstance(model, AssemblyNet) else [PoseStage(config)]
    return [stage for stage in own if stage.name in config.train.stages]
