"""Typed configuration of the perception model and its training, read from TOML files.

A file has the sections ``[model]``, ``[loss]``, ``[train]`` (with sub-tables ``[train.segmentation]`` and
``[train.pose]``, one per training stage) and ``[data]``; every field has a default, so a file names only what it
changes. Unknown fields, wrong types and out-of-range values are refused with the field's dotted name
(``model.image_size must be ...``). Bundled files: ``perception/configs/paper.toml`` (the paper's sizes),
``compact.toml`` (CPU-trainable, the bundled weights) and ``tiny.toml`` (tests).

A file may start from another: a top-level ``base = "compact_gpu"`` (a bundled config's name, or a path relative to
the file's folder) reads that file first, and this file's values replace its values field by field (tables merge,
a list or a value replaces the whole). The fine-tuning configs use it, so that each says only what it changes.
Training runs write the resolved configuration (:func:`config_to_toml`, no ``base``), so a run's record stands on
its own.
"""

from __future__ import annotations

import dataclasses
import json
import types
import typing
from dataclasses import dataclass, field
from pathlib import Path

try:  # Python >= 3.11
    import tomllib
except ModuleNotFoundError:  # pragma: no cover - Python 3.10
    import tomli as tomllib  # type: ignore[no-redef]

CONFIG_DIR = Path(__file__).parent / "configs"
PRECISIONS = ("float32", "bfloat16")  # train.precision


class ConfigError(ValueError):
    """A configuration value is missing, unknown, of the wrong type or out of range (the message names it)."""


@dataclass(frozen=True)
class ModelConfig:
    """Network sizes. F1 = ``point_feature``, F2 = ``part_feature``, F3 = ``hidden`` in the paper's notation."""

    image_size: int = 224  # network input resolution; the 224x224 images are resized to it inside the model
    resnet_width: float = 1.0  # channel multiplier of the ResNet-18 image encoders (1.0: 64-128-256-512)
    mask_encoder_width: float = 1.0  # channel multiplier of the per-part mask encoder (image + mask input)
    decoder_width: float = 1.0  # channel multiplier of the U-Net decoder (1.0: 256-128-64-32-32)
    resnet_blocks: tuple[int, ...] = (2, 2, 2, 2)  # basic blocks per ResNet stage (ResNet-18: 2, 2, 2, 2)
    pointnet_widths: tuple[int, ...] = (64, 64, 64, 128)  # PointNet per-point layers before the F1 layer
    point_feature: int = 512  # F1: PointNet part geometry feature
    part_feature: int = 256  # F2: SLP1 and SLP2 width; f_3d = [SLP1; SLP2] has 2 * F2 features
    hidden: int = 512  # F3: graph node width and pose MLP width
    image_feature: int = 512  # global image feature and per-part mask feature of the pose network
    encoder_points: int = 1000  # points per part fed to the PointNets (the first of the FPS order)
    max_parts: int = 20  # P_max: padding size and instance one-hot length
    knn: int = 5  # phase-2 neighbours per part (nearest predicted centres)
    graph_iterations: int = 2  # message-passing iterations per phase
    gru_hidden: int = 512  # B-GRU hidden state
    # Beyond the paper: the U-Net decoder takes each part's f_3d at every scale (a per-part bias on each up block,
    # the same as concatenating the tiled f_3d there), not only at the bottleneck; the paper's design when false
    condition_every_scale: bool = False

    def __post_init__(self):
        _positive(self, "image_size", "point_feature", "part_feature", "hidden", "image_feature",
                  "encoder_points", "max_parts", "graph_iterations", "gru_hidden")
        _positive(self, "resnet_width", "mask_encoder_width", "decoder_width")
        if self.image_size % 32:
            raise ConfigError(f"model.image_size must be a multiple of 32 (ResNet stride), got {self.image_size}")
        if len(self.resnet_blocks) != 4 or min(self.resnet_blocks) < 1:
            raise ConfigError(f"model.resnet_blocks must be 4 positive counts, got {list(self.resnet_blocks)}")
        if not self.pointnet_widths or min(self.pointnet_widths) < 1:
            raise ConfigError(f"model.pointnet_widths must be positive widths, got {list(self.pointnet_widths)}")
        if not 1 <= self.encoder_points <= 1000:
            raise ConfigError(f"model.encoder_points must be in 1..1000, got {self.encoder_points}")
        if self.knn < 0:
            raise ConfigError(f"model.knn must be >= 0, got {self.knn}")


@dataclass(frozen=True)
class LossConfig:
    """Pose-loss weights (the paper's: 1, 20, 1, 1) and the point subsets the losses use."""

    translation: float = 1.0
    rotation_chamfer: float = 20.0
    rotation_l2: float = 1.0
    shape_chamfer: float = 1.0
    points: int = 1000  # points per part in the per-part losses (the first of the FPS order: evenly spread)
    shape_points: int = 100  # points per part in the whole-shape chamfer (20 parts: 2000 points a shape)
    match_points: int = 100  # points per part in the Hungarian matching cost
    iou_smooth: float = 1.0  # soft-IoU smoothing, pixels: (I + s) / (U + s); an absent part predicted absent: 1
    # Beyond the paper: weight of a per-pixel cross-entropy beside the negative soft-IoU, on the same matching
    # (0: the paper's loss alone). It gives every pixel a gradient from the first step, where the soft IoU of
    # near-uniform masks gives almost none. Measured on the compact model (benchmarks/RESULTS.md): weight 1 gave a
    # lower validation soft IoU after 300 steps from scratch (0.036 against 0.059), so the bundled configs keep 0.
    mask_cross_entropy: float = 0.0
    # Beyond the paper: weight of the crossing penalty (perception.losses.crossing_penalty), how far the predicted
    # poses push points of one part through another part's box to its wrong side (0: the paper's loss). Measured
    # on the compact model (benchmarks/RESULTS.md, "Negative results"): weight 0.25 lowered Part Accuracy and raised the
    # crossings the held-out benchmark counts; weight 0.025, one-sided, changed neither. So the bundled configs keep 0.
    crossing: float = 0.0
    # with the crossing penalty: move only the crossing part (no gradient into the frame of the part it crosses,
    # so the network cannot turn or shift that part to escape the footprint test); False: both parts
    crossing_moves_crossing_part_only: bool = False

    def __post_init__(self):
        for name in ("translation", "rotation_chamfer", "rotation_l2", "shape_chamfer", "iou_smooth",
                     "mask_cross_entropy", "crossing"):
            if getattr(self, name) < 0:
                raise ConfigError(f"loss.{name} must be >= 0, got {getattr(self, name)}")
        for name in ("points", "shape_points", "match_points"):
            if not 1 <= getattr(self, name) <= 1000:
                raise ConfigError(f"loss.{name} must be in 1..1000, got {getattr(self, name)}")


@dataclass(frozen=True)
class StageConfig:
    """Schedule of one training stage: Adam, cosine decay to ``lr * min_lr_ratio``, early stopping."""

    steps: int = 10000  # optimiser steps (upper bound when early stopping ends the stage sooner)
    batch_size: int = 8  # samples per step and per process
    lr: float = 1e-3
    weight_decay: float = 1e-5
    min_lr_ratio: float = 0.05
    warmup_steps: int = 0
    val_every: int = 500  # steps between validations (0: validate only at the end)
    patience: int = 0  # validations without improvement before stopping (0: never stop early)
    grad_clip: float = 10.0  # max gradient norm (0: off)

    def __post_init__(self):
        _positive(self, "steps", "batch_size", "lr")
        if self.batch_size < 2:
            raise ConfigError(f"{{stage}}.batch_size must be >= 2 (batch norm over the batch), got {self.batch_size}")
        for name in ("weight_decay", "min_lr_ratio", "warmup_steps", "val_every", "patience", "grad_clip"):
            if getattr(self, name) < 0:
                raise ConfigError(f"{{stage}}.{name} must be >= 0, got {getattr(self, name)}")


@dataclass(frozen=True)
class TrainConfig:
    seed: int = 0
    segmentation: StageConfig = field(default_factory=StageConfig)
    pose: StageConfig = field(default_factory=StageConfig)
    freeze_segmentation: bool = True  # pose stage: the segmentation network is frozen (the paper's two stages)
    checkpoint_minutes: float = 5.0  # wall-clock minutes between checkpoints (and at every stage end)
    val_samples: int = 200  # validation samples used (the first of the sorted val split; 0: all)
    log_every: int = 10  # steps between loss records in the JSON log
    num_workers: int = 0  # DataLoader worker processes
    threads: int = 0  # torch CPU threads per process (0: torch's default)
    # the stages to run, of those the model has (the baselines have "pose" only); ["pose"] fine-tunes the pose
    # network of a model started with --init, its segmentation network left as it is
    stages: tuple[str, ...] = ("segmentation", "pose")
    # present every training and validation sample's parts in a random order (perception.data.permute_parts):
    # the procedural generators list parts in a fixed order (seat, back, legs, ...) that users' parts lack
    shuffle_parts: bool = True
    # speed, for CPUs with AVX-512 BF16 or AMX and for GPUs (together 1.7x faster pose steps of the compact model on
    # the 2-core machine, benchmarks/training_step_speed.py; both change the numbers in the last bits, so a run
    # resumes only under the same values):
    # channels_last: convolution weights in channels-last memory layout (oneDNN's and cuDNN's fast path);
    # precision "bfloat16": the training forward passes under torch.autocast (the losses, validation and the
    # saved weights stay float32)
    channels_last: bool = False
    precision: str = "float32"

    def __post_init__(self):
        _positive(self, "checkpoint_minutes", "log_every")
        if self.precision not in PRECISIONS:
            raise ConfigError(f"train.precision must be one of {list(PRECISIONS)}, got {self.precision!r}")
        unknown = [name for name in self.stages if name not in ("segmentation", "pose")]
        if unknown or not self.stages or len(set(self.stages)) != len(self.stages):
            raise ConfigError(f"train.stages must name segmentation and/or pose once each, got {list(self.stages)}")
        for name in ("val_samples", "num_workers", "threads"):
            if getattr(self, name) < 0:
                raise ConfigError(f"train.{name} must be >= 0, got {getattr(self, name)}")


@dataclass(frozen=True)
class DataConfig:
    paths: tuple[str, ...] = ()  # dataset folders (each with train/ val/ test/), relative to the working folder
    categories: tuple[str, ...] = ()  # keep only objects of these categories (file-name prefix); empty: all


@dataclass(frozen=True)
class Config:
    model: ModelConfig = field(default_factory=ModelConfig)
    loss: LossConfig = field(default_factory=LossConfig)
    train: TrainConfig = field(default_factory=TrainConfig)
    data: DataConfig = field(default_factory=DataConfig)

    def to_dict(self) -> dict:
        return _to_plain(dataclasses.asdict(self))


def _positive(obj, *names: str) -> None:
    section = {ModelConfig: "model", StageConfig: "{stage}", TrainConfig: "train"}.get(type(obj), "?")
    for name in names:
        value = getattr(obj, name)
        if value <= 0:
            raise ConfigError(f"{section}.{name} must be > 0, got {value}")


def _to_plain(value):
    if isinstance(value, dict):
        return {k: _to_plain(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_to_plain(v) for v in value]
    return value


def _convert(value, hint, name: str):
    """Check/convert one TOML value against a field's type hint."""
    origin = typing.get_origin(hint)
    if dataclasses.is_dataclass(hint):
        if not isinstance(value, dict):
            raise ConfigError(f"{name} must be a table, got {value!r}")
        return _build(hint, value, name)
    if origin is tuple:
        if not isinstance(value, (list, tuple)):
            raise ConfigError(f"{name} must be a list, got {value!r}")
        item = typing.get_args(hint)[0]
        return tuple(_convert(v, item, f"{name}[{i}]") for i, v in enumerate(value))
    if origin in (typing.Union, types.UnionType):
        raise ConfigError(f"{name}: union types are not supported")  # pragma: no cover
    if hint is bool:
        if not isinstance(value, bool):
            raise ConfigError(f"{name} must be true or false, got {value!r}")
        return value
    if hint is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise ConfigError(f"{name} must be an integer, got {value!r}")
        return value
    if hint is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ConfigError(f"{name} must be a number, got {value!r}")
        return float(value)
    if hint is str:
        if not isinstance(value, str):
            raise ConfigError(f"{name} must be a string, got {value!r}")
        return value
    raise ConfigError(f"{name}: unsupported type {hint}")  # pragma: no cover


def _build(cls, data: dict, prefix: str):
    hints = typing.get_type_hints(cls)
    names = {f.name for f in dataclasses.fields(cls)}
    unknown = sorted(set(data) - names)
    if unknown:
        where = f"{prefix}." if prefix else ""
        raise ConfigError(f"unknown field {where}{unknown[0]} (known: {', '.join(sorted(names))})")
    kwargs = {key: _convert(value, hints[key], f"{prefix}.{key}" if prefix else key) for key, value in data.items()}
    try:
        return cls(**kwargs)
    except ConfigError as exc:
        raise ConfigError(str(exc).replace("{stage}", prefix)) from None


def config_from_dict(data: dict) -> Config:
    """Build and validate a :class:`Config` from nested dictionaries (as read from TOML or a checkpoint)."""
    return _build(Config, data, "")


BASE_KEY = "base"  # top-level key of a config file naming the file it starts from


def _resolve_path(name: str | Path, folder: Path | None = None) -> Path:
    """A config file path: ``name`` itself (relative to ``folder`` where given), else a bundled config's name."""
    path = Path(name)
    if folder is not None and not path.is_absolute():
        path = folder / path
    if not path.exists() and not Path(name).suffix and (CONFIG_DIR / f"{name}.toml").exists():
        path = CONFIG_DIR / f"{name}.toml"
    return path


def _merge(base: dict, override: dict) -> dict:
    """``base`` with ``override``'s values in place: tables merge recursively, anything else replaces."""
    merged = dict(base)
    for key, value in override.items():
        merged[key] = _merge(merged[key], value) if isinstance(value, dict) and isinstance(merged.get(key), dict) \
            else value
    return merged


def _read_toml(path: Path, chain: tuple[Path, ...] = ()) -> dict:
    """The tables of a config file with its ``base`` chain merged in (the file's own values last)."""
    try:
        with open(path, "rb") as handle:
            data = tomllib.load(handle)
    except FileNotFoundError:
        where = f" (the base of {chain[-1]})" if chain else ""
        raise ConfigError(f"config file {path}{where} not found") from None
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{path}: {exc}") from None
    if BASE_KEY not in data:
        return data
    base = data.pop(BASE_KEY)
    if not isinstance(base, str) or not base:
        raise ConfigError(f"{path}: {BASE_KEY} must be a config name or path, got {base!r}")
    base_path = _resolve_path(base, path.parent)
    chain = (*chain, path)
    if base_path.resolve() in {p.resolve() for p in chain}:
        raise ConfigError(f"{path}: {BASE_KEY} = {base!r} makes a cycle: "
                          + " -> ".join(str(p) for p in (*chain, base_path)))
    return _merge(_read_toml(base_path, chain), data)


def load_config(path: str | Path) -> Config:
    """Read a TOML config file, its ``base`` chain merged in. ``path`` may also be a bundled config's name
    (``compact``, ``paper``, ``tiny``)."""
    path = _resolve_path(path)
    data = _read_toml(path)
    try:
        return config_from_dict(data)
    except ConfigError as exc:
        raise ConfigError(f"{path}: {exc}") from None


def _toml_value(value, name: str) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, int):
        return str(value)
    if isinstance(value, float):
        if value != value or value in (float("inf"), float("-inf")):
            raise ConfigError(f"{name} = {value} cannot be written to TOML")
        return repr(value)
    if isinstance(value, str):
        return json.dumps(value)  # a JSON string is a valid TOML basic string
    if isinstance(value, (list, tuple)):
        return "[" + ", ".join(_toml_value(v, f"{name}[{i}]") for i, v in enumerate(value)) + "]"
    raise ConfigError(f"{name}: cannot write {type(value).__name__} to TOML")  # pragma: no cover


def config_to_toml(config: Config, header: str = "") -> str:
    """The TOML text of ``config`` (``load_config`` reads it back to an equal config); ``header``: comment
    lines put first."""
    lines = [f"# {line}".rstrip() for line in header.splitlines()]

    def table(name: str, data: dict) -> None:
        scalars = {k: v for k, v in data.items() if not isinstance(v, dict)}
        lines.extend(["", f"[{name}]"] if lines else [f"[{name}]"])
        lines.extend(f"{key} = {_toml_value(value, f'{name}.{key}')}" for key, value in scalars.items())
        for key, value in data.items():
            if isinstance(value, dict):
                table(f"{name}.{key}", value)

    for name, data in config.to_dict().items():
        table(name, data)
    return "\n".join(lines) + "\n"
