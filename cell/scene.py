"""Typed scene files: the robot cell as data (``scenes/*.toml``), loaded with defaults and validated.

Every field is documented in ``scenes/cell.toml``, the default scene. A value at fault is named with its file
and key in a :class:`SceneError`; so is a key the scene format does not have (a misspelling would otherwise leave
the default in force unnoticed).
"""

from __future__ import annotations

import math
import tomllib
from dataclasses import dataclass
from pathlib import Path

from cell.errors import BadScene
from planning.payload import PANDA_PAYLOAD_KG
from planning.pose import Pose
from planning.robot_limits import DATASHEET_MARGIN_RAD, ROBOT_MODELS, RobotLimits
from scenes import scenes_root

DEFAULT_SCENE = "cell.toml"
# every key of the scene format: top-level keys and each table's, the tables of inline poses under "pose"
SCENE_KEYS = {
    "": ("random_seed", "robot", "table", "fixture", "kitting", "camera"),
    "robot": ("model", "urdf", "world_from_base", "home_q", "payload_kg"),
    "table": ("top_z", "size", "centre_xy"),
    "fixture": ("world_from_assembly", "upside_down"),
    "kitting": ("inner_radius", "outer_radius", "pedestal_height", "gap", "jig_margin"),
    "camera": ("eye", "target", "fov_deg", "width_px", "height_px"),
    "pose": ("position", "quat_wxyz"),
}
SceneError = BadScene  # a malformed scene file; the message names the file and the key


@dataclass(frozen=True)
class RobotConfig:
    """``urdf``: the simulation model (pybullet_data's Panda); ``model``: the real arm whose published limits the
    program keeps within (``panda`` or ``fr3``, :mod:`planning.robot_limits`)."""

    urdf: str
    world_from_base: Pose
    home_q: tuple[float, ...]
    payload_kg: float = PANDA_PAYLOAD_KG  # the heaviest part the arm may carry
    model: str = "panda"

    @property
    def limits(self) -> RobotLimits:
        return ROBOT_MODELS[self.model]


@dataclass(frozen=True)
class TableConfig:
    top_z: float
    size: tuple[float, float, float]
    centre_xy: tuple[float, float]


@dataclass(frozen=True)
class FixtureConfig:
    """The jig: where the assembly frame lies in the world, and whether an object that no plan builds standing may
    be built upside down (turned over about the assembly frame's x axis, for something to turn it back after)."""

    world_from_assembly: Pose
    upside_down: bool = True


@dataclass(frozen=True)
class KittingConfig:
    """The ring around the robot base where loose parts lie (metres): footprint centres between
    ``inner_radius`` and ``outer_radius`` from the base, ``gap`` between footprints, nothing within
    ``jig_margin`` of the assembly's footprint on the jig."""

    inner_radius: float
    outer_radius: float
    pedestal_height: float
    gap: float
    jig_margin: float


@dataclass(frozen=True)
class CameraConfig:
    eye: tuple[float, float, float]
    target: tuple[float, float, float]
    fov_deg: float
    width_px: int
    height_px: int


@dataclass(frozen=True)
class Scene:
    robot: RobotConfig
    table: TableConfig
    fixture: FixtureConfig
    kitting: KittingConfig
    camera: CameraConfig
    random_seed: int
    source: str


class _Reader:
    def __init__(self, data: dict, source: str) -> None:
        self.data, self.source = data, source

    def section(self, name: str) -> dict:
        value = self.data.get(name)
        if not isinstance(value, dict):
            raise SceneError(f"{self.source}: missing section [{name}]")
        return value

    def numbers(self, section: str, key: str, count: int | None = None) -> tuple[float, ...]:
        value = self.section(section).get(key)
        if (not isinstance(value, list) or (count is not None and len(value) != count)
                or not all(isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)
                           for v in value)):
            size = f"{count} " if count else ""
            raise SceneError(f"{self.source}: [{section}] {key} must be a list of {size}finite numbers, got {value!r}")
        return tuple(float(v) for v in value)

    def number(self, section: str, key: str, positive: bool = False) -> float:
        value = self.section(section).get(key)
        if not isinstance(value, (int, float)) or isinstance(value, bool) or not math.isfinite(value):
            raise SceneError(f"{self.source}: [{section}] {key} must be a finite number, got {value!r}")
        if positive and value <= 0:
            raise SceneError(f"{self.source}: [{section}] {key} must be positive, got {value!r}")
        return float(value)

    def flag(self, section: str, key: str, default: bool) -> bool:
        value = self.section(section).get(key, default)
        if not isinstance(value, bool):
            raise SceneError(f"{self.source}: [{section}] {key} must be true or false, got {value!r}")
        return value

    def pose(self, section: str, key: str) -> Pose:
        value = self.section(section).get(key)
        if not isinstance(value, dict):
            raise SceneError(f"{self.source}: [{section}] {key} must be {{ position = [...], quat_wxyz = [...] }}")
        _check_keys(value, "pose", f"[{section}] {key}", self.source)
        sub = _Reader({"pose": value}, self.source)
        position = sub.numbers("pose", "position", 3)
        quat = sub.numbers("pose", "quat_wxyz", 4)
        try:
            return Pose.from_checked_quat(position, quat)
        except ValueError as exc:
            raise SceneError(f"{self.source}: [{section}] {key}: {exc}") from exc


def _check_keys(table: dict, kind: str, where: str, source: str) -> None:
    """Refuse a key of ``table`` (a table of kind ``kind`` in :data:`SCENE_KEYS`, at ``where``) that the scene
    format does not have, naming it and the valid keys."""
    valid = SCENE_KEYS[kind]
    unknown = [key for key in table if key not in valid]
    if unknown:
        import difflib

        close = difflib.get_close_matches(unknown[0], valid, n=1)
        guess = f" (did you mean {close[0]!r}?)" if close else ""
        raise SceneError(f"{source}: {where} has no key {unknown[0]!r}{guess}; its keys are {', '.join(valid)}")


def _kitting(r: _Reader) -> KittingConfig:
    kitting = KittingConfig(*(r.number("kitting", key, positive=True)
                              for key in ("inner_radius", "outer_radius", "pedestal_height", "gap", "jig_margin")))
    if kitting.outer_radius <= kitting.inner_radius:
        raise SceneError(f"{r.source}: [kitting] outer_radius ({kitting.outer_radius}) must exceed inner_radius "
                         f"({kitting.inner_radius})")
    return kitting


def load_scene(path: str | Path | None = None) -> Scene:
    """Load a scene file (default: the bundled ``scenes/cell.toml``)."""
    path = Path(path) if path is not None else scenes_root() / DEFAULT_SCENE
    if not path.is_file():
        raise SceneError(f"{path}: scene file does not exist")
    try:
        data = tomllib.loads(path.read_text(encoding="utf-8"))
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
        raise SceneError(f"{path}: not valid TOML ({exc})") from exc
    r = _Reader(data, str(path))
    _check_keys(data, "", "the top level", str(path))
    for section in SCENE_KEYS:
        if section and section != "pose" and isinstance(data.get(section), dict):
            _check_keys(data[section], section, f"[{section}]", str(path))
    urdf = r.section("robot").get("urdf")
    if not isinstance(urdf, str) or not urdf:
        raise SceneError(f"{path}: [robot] urdf must be a path inside pybullet_data or the scene folder")
    model = r.section("robot").get("model", "panda")
    if model not in ROBOT_MODELS:
        raise SceneError(f"{path}: [robot] model must be one of {', '.join(sorted(ROBOT_MODELS))} (the real arm whose "
                         f"published limits the program keeps within), got {model!r}")
    seed = data.get("random_seed", 0)
    if not isinstance(seed, int) or isinstance(seed, bool):
        raise SceneError(f"{path}: random_seed must be an integer, got {seed!r}")
    home_q = r.numbers("robot", "home_q", 7)
    limits = ROBOT_MODELS[model]
    for j, value in enumerate(home_q):
        if not limits.lower_rad[j] + DATASHEET_MARGIN_RAD <= value <= limits.upper_rad[j] - DATASHEET_MARGIN_RAD:
            raise SceneError(f"{path}: [robot] home_q: joint {j + 1} at {value:g} rad lies outside the "
                             f"{limits.description}'s range {limits.lower_rad[j]:g}..{limits.upper_rad[j]:g} rad (less "
                             f"{DATASHEET_MARGIN_RAD:g} rad at each end)")
    width = r.number("camera", "width_px", positive=True)
    height = r.number("camera", "height_px", positive=True)
    return Scene(
        robot=RobotConfig(urdf, r.pose("robot", "world_from_base"), home_q,
                          r.number("robot", "payload_kg", positive=True) if "payload_kg" in r.section("robot")
                          else ROBOT_MODELS[model].payload_kg, model),
        table=TableConfig(r.number("table", "top_z"), r.numbers("table", "size", 3),
                          r.numbers("table", "centre_xy", 2)),
        fixture=FixtureConfig(r.pose("fixture", "world_from_assembly"), r.flag("fixture", "upside_down", True)),
        kitting=_kitting(r),
        camera=CameraConfig(r.numbers("camera", "eye", 3), r.numbers("camera", "target", 3),
                            r.number("camera", "fov_deg", positive=True), int(width), int(height)),
        random_seed=seed,
        source=str(path),
    )
