"""The user's inputs to ``python -m cell.run`` and :func:`cell.assemble`, read and checked before anything is
computed.

Every problem raises a :class:`cell.errors.BadInput` (:class:`BadParts`, :class:`BadPicture`, :class:`BadPoses`,
:class:`BadMasses`) with a message naming the file, the part or the value at fault and, where there is one, the
fix. What the readers changed or skipped (a picture cropped to square, a texture beside a mesh) they add to the
list ``notes``, to be shown and reported.
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import trimesh

from cell.errors import BadInput, BadMasses, BadParts, BadPicture, BadPoses
from planning.assembly import (
    ASSEMBLY_FILE,
    MAX_PARTS,
    UNIT_TO_METRES,
    AssemblyError,
    load_mesh,
    read_poses,
    solid_meshes,
)
from planning.mesh_intake import DEFAULT_SHEET_THICKNESS_M
from planning.pose import Pose

MESH_SUFFIXES = (".obj", ".stl", ".ply", ".off", ".glb", ".gltf")
# what CAD and web exports write beside a mesh (materials, textures, glTF buffers): skipped with a note
COMPANION_SUFFIXES = (".mtl", ".png", ".jpg", ".jpeg", ".tga", ".bmp", ".gif", ".tif", ".tiff", ".webp", ".dds",
                      ".ktx2", ".exr", ".hdr", ".bin")
IMAGE_SIZE_PX = 224  # what the network sees: a picture's square (cropped or padded) is resized to this
MAX_IMAGE_SIDE_PX = 4096
MIN_IMAGE_SIDE_PX = IMAGE_SIZE_PX  # a smaller picture would be enlarged, adding no detail: refused
LARGEST_PLAUSIBLE_PART_M = 3.0  # a furniture part longer than this is a unit mistake, not furniture
SMALLEST_PLAUSIBLE_LARGEST_PART_M = 0.02  # an object whose largest part is shorter is a unit mistake, not furniture
TYPICAL_LARGEST_PART_M = 0.5  # where two units give plausible sizes, the one nearer this (in ratio) is suggested first
MIN_DENSITY_KG_M3 = 10.0  # lighter than the lightest foam: a value in g/cm3 (wood is 0.6 there) or a typo
MAX_DENSITY_KG_M3 = 25000.0  # denser than any solid: a typo or a mass in grams, not a material


InputError = BadInput  # bad input; the message names the culprit


@dataclass(frozen=True)
class Parts:
    names: list[str]  # file stems, sorted
    meshes: list[trimesh.Trimesh]  # own frames, metres: each part's solid (planning.mesh_intake)
    files: list[Path]
    skipped: list[Path] = field(default_factory=list)  # companion files (materials, textures), not parts
    mesh_intake: dict[str, dict] = field(default_factory=dict)  # part name: what the intake did to its mesh
    poses: dict[str, Pose] | None = None  # the target poses given with them (load_poses), read once


def load_parts(folder: str | Path, units: str = "m", notes: list[str] | None = None,
               sheet_thickness_m: float = DEFAULT_SHEET_THICKNESS_M,
               poses: str | Path | Mapping[str, Pose] | None = None) -> Parts:
    """Every mesh file of ``folder`` (one part each, named after the file), in metres, each turned into the part's
    solid by :mod:`planning.mesh_intake` (:func:`planning.assembly.solid_meshes`): where the target ``poses`` are
    given (:func:`load_poses`), a one-surface board grows to meet the part beside it, or ``sheet_thickness_m``
    thick away from the part touching it or from the assembly's centre; else behind the drawn face.
    Companion files of the meshes (:data:`COMPANION_SUFFIXES`: ``.mtl`` materials, textures) are skipped, with a
    note. The poses read come back in ``Parts.poses``."""
    folder = Path(folder)
    if not folder.exists():
        raise BadParts(f"{folder}: parts folder does not exist")
    if not folder.is_dir():
        raise BadParts(f"{folder}: --parts must be a folder of mesh files, this is a file")
    entries = sorted(p for p in folder.iterdir() if not p.name.startswith("."))
    skipped = [p for p in entries if p.is_file() and p.suffix.lower() in COMPANION_SUFFIXES]
    files = [p for p in entries if p not in skipped]
    others = [p for p in files if p.is_dir() or p.suffix.lower() not in MESH_SUFFIXES]
    if others:
        raise BadParts(f"{others[0]}: not a mesh file (the parts folder may hold only "
                       f"{', '.join(MESH_SUFFIXES)} files, one part each, and their materials and textures)")
    if not files:
        raise BadParts(f"{folder}: parts folder is empty (expected one mesh file per part: "
                       f"{', '.join(MESH_SUFFIXES)})")
    if len(files) > MAX_PARTS:
        raise BadParts(f"{folder}: {len(files)} parts, more than the {MAX_PARTS} the method supports")
    names = [p.stem for p in files]
    duplicates = sorted({n for n in names if names.count(n) > 1})
    if duplicates:
        raise BadParts(f"{folder}: several files for part {duplicates[0]!r} (one mesh file per part name)")
    meshes = []
    for name, path in zip(names, files):
        try:
            meshes.append(load_mesh(path, f"part {name!r}", UNIT_TO_METRES[units]))
        except AssemblyError as exc:
            raise BadParts(str(exc)) from exc
    _check_size(folder, names, meshes, units)  # on the meshes as given: a unit mistake is named as one
    given = None if poses is None else load_poses(poses, names)
    try:
        repaired = solid_meshes(meshes, [f"part {name!r} ({path})" for name, path in zip(names, files)],
                                sheet_thickness_m, None if given is None else [given[name] for name in names])
    except AssemblyError as exc:
        raise BadParts(str(exc)) from exc
    solids = [solid for solid, _ in repaired]
    intake = {name: record for name, (_, record) in zip(names, repaired)}
    if skipped and notes is not None:
        shown = ", ".join(p.name for p in skipped[:6]) + (f" and {len(skipped) - 6} more" if len(skipped) > 6 else "")
        notes.append(f"{folder}: skipped {len(skipped)} file(s) that are not parts (materials, textures): {shown}")
    return Parts(names, solids, files, skipped, intake, given)


def _check_size(folder: Path, names: list[str], meshes: list[trimesh.Trimesh], units: str) -> None:
    """Refuse parts too large or too small to be furniture in ``units``: a unit mistake, with the ``--units``
    that makes them furniture-sized where one does."""
    extents = [float(np.max(m.extents)) for m in meshes]  # metres
    largest = max(extents)
    worst = names[int(np.argmax(extents))]
    in_units = largest / UNIT_TO_METRES[units]  # the number in the files
    fitting = [u for u in ("m", "cm", "mm") if u != units
               and SMALLEST_PLAUSIBLE_LARGEST_PART_M <= in_units * UNIT_TO_METRES[u] <= LARGEST_PLAUSIBLE_PART_M]
    # where two units fit (a 257 mm rail read as centimetres is a 2.57 m part), the likelier one first: its
    # largest part nearer a typical one
    fitting.sort(key=lambda u: abs(np.log(in_units * UNIT_TO_METRES[u] / TYPICAL_LARGEST_PART_M)))
    unit_words = {"m": "metres", "cm": "centimetres", "mm": "millimetres"}
    hint = None
    if fitting:
        sizes = "; ".join(f"in {unit_words[u]} it is {in_units * UNIT_TO_METRES[u]:.3g} m" for u in fitting)
        hint = (f"the files look like {unit_words[fitting[0]]}" + (f" ({sizes})" if len(fitting) > 1 else "")
                + f": rerun with --units {fitting[0]}")
    if largest > LARGEST_PLAUSIBLE_PART_M:
        hint = hint or "check the units of the files"
        raise BadParts(f"{folder}: part {worst!r} is {in_units:g} {units} across, too large for furniture parts in "
                       f"{unit_words[units]}; {hint}")
    if largest < SMALLEST_PLAUSIBLE_LARGEST_PART_M:
        hint = hint or ("even read as metres (--units m, the largest unit) the parts are this small: scale the "
                        "meshes to the object's real size")
        raise BadParts(f"{folder}: the largest part, {worst!r}, is {in_units:g} {units} across "
                       f"({largest * 1000:.3g} mm), too small for furniture parts in {unit_words[units]}; {hint}")


def load_image(source, pad: bool = False, notes: list[str] | None = None) -> np.ndarray:
    """The picture as a (224, 224, 3) uint8 RGB array. ``source``: an image file, or an (H, W, 3) uint8 RGB array.

    A picture of at least 224 pixels on its shorter side and at most 4096 on its longer: a non-square one is
    centre-cropped to a square (``pad``: padded to a square with the colour of its border instead), and the square
    resized to 224x224; what was done is added to ``notes``. Smaller, larger, grayscale or transparent pictures
    raise :class:`BadPicture`."""
    from PIL import Image, UnidentifiedImageError

    if isinstance(source, np.ndarray):
        array = source
        if array.ndim != 3 or array.shape[2] != 3 or array.dtype != np.uint8:
            raise BadPicture(f"image array of shape {array.shape} and dtype {array.dtype}: give an (H, W, 3) uint8 "
                             "RGB array")
        return _square_picture(Image.fromarray(array), f"image array {array.shape[1]}x{array.shape[0]}", pad, notes)
    path = Path(source)
    if not path.exists():
        raise BadPicture(f"{path}: image file does not exist")
    if not path.is_file():
        raise BadPicture(f"{path}: --image must be an image file, this is a folder")
    try:
        with Image.open(path) as image:
            image.load()
            mode = image.mode
            if mode in ("RGBA", "LA", "PA") or (mode == "P" and "transparency" in image.info):
                raise BadPicture(f"{path}: the image has an alpha channel ({mode}); flatten it onto a background "
                                 "and save it as RGB")
            if mode in ("L", "1", "I", "I;16", "F"):
                raise BadPicture(f"{path}: the image is grayscale ({mode}); the method needs an RGB photo or "
                                 "rendering")
            if mode != "RGB":
                raise BadPicture(f"{path}: unsupported colour mode {mode}; save it as 8-bit RGB")
            return _square_picture(image, str(path), pad, notes)
    except BadInput:
        raise
    except (UnidentifiedImageError, OSError, ValueError) as exc:
        raise BadPicture(f"{path}: not a readable image file ({exc.__class__.__name__}: {exc})") from exc


def _square_picture(image, where: str, pad: bool, notes: list[str] | None) -> np.ndarray:
    """An RGB PIL image, checked for size, made square (cropped about its centre, or padded) and resized."""
    from PIL import Image

    width, height = image.size
    if max(width, height) > MAX_IMAGE_SIDE_PX:
        raise BadPicture(f"{where}: the image is {width}x{height}, larger than {MAX_IMAGE_SIDE_PX}x"
                         f"{MAX_IMAGE_SIDE_PX}; resize it to {IMAGE_SIZE_PX} pixels on its shorter side")
    if min(width, height) < MIN_IMAGE_SIDE_PX:
        raise BadPicture(f"{where}: the image is only {width}x{height}; give at least {IMAGE_SIZE_PX}x"
                         f"{IMAGE_SIZE_PX} ({IMAGE_SIZE_PX} pixels on its shorter side: the network sees "
                         f"{IMAGE_SIZE_PX}x{IMAGE_SIZE_PX}, and an enlarged picture adds no detail)")
    done = []
    if width != height:
        if pad:
            side = max(width, height)
            rgb = np.asarray(image, dtype=np.uint8)
            border = np.concatenate([rgb[0], rgb[-1], rgb[:, 0], rgb[:, -1]])
            colour = tuple(int(v) for v in np.median(border, axis=0))
            square = Image.new("RGB", (side, side), colour)
            square.paste(image, ((side - width) // 2, (side - height) // 2))
            image = square
            done.append(f"padded to {side}x{side} with its border colour rgb{colour}")
        else:
            side = min(width, height)
            left, top = (width - side) // 2, (height - side) // 2
            image = image.crop((left, top, left + side, top + side))
            done.append(f"centre-cropped to {side}x{side} (--pad pads it to a square instead)")
    if image.size[0] != IMAGE_SIZE_PX:
        image = image.resize((IMAGE_SIZE_PX, IMAGE_SIZE_PX), Image.Resampling.BILINEAR)
    if done and notes is not None:
        notes.append(f"{where}: the image is {width}x{height}, not square: {done[0]}, then resized to "
                     f"{IMAGE_SIZE_PX}x{IMAGE_SIZE_PX}")
    return np.asarray(image, dtype=np.uint8).copy()


def load_poses(source: str | Path | Mapping[str, Pose], part_names: list[str]) -> dict[str, Pose]:
    """Target poses ``assembly_from_part`` (metres) from an ``assembly.json`` (or a folder holding one), or given
    as a mapping of part name to :class:`Pose`; every part of the parts folder must appear exactly once."""
    if isinstance(source, Mapping):
        where = "poses"
        poses = dict(source)
        wrong = [name for name, pose in poses.items() if not isinstance(pose, Pose)]
        if wrong:
            raise BadPoses(f"poses: part {wrong[0]!r}: {type(poses[wrong[0]]).__name__} is not a "
                           "planning.pose.Pose (give Pose(position_m, quat_wxyz))")
    else:
        path = Path(source)
        if path.is_dir():
            path = path / ASSEMBLY_FILE
        where = str(path)
        try:
            poses = read_poses(path)
        except AssemblyError as exc:
            raise BadPoses(str(exc)) from exc
    missing = sorted(set(part_names) - set(poses))
    extra = sorted(set(poses) - set(part_names))
    if missing:
        raise BadPoses(f"{where}: no pose for part(s) {', '.join(missing)} of the parts folder")
    if extra:
        raise BadPoses(f"{where}: pose(s) for {', '.join(extra)}, which the parts folder does not hold")
    return poses


def read_masses(source: str | Path | Mapping[str, float]) -> tuple[object, str]:
    """(the masses as read, what to call them in messages) from ``source``: a JSON file, the JSON text itself (it
    starts with ``{``), or a mapping of part name to kilograms."""
    if isinstance(source, Mapping):
        return dict(source), "masses"
    if isinstance(source, str) and source.lstrip().startswith("{"):
        try:
            return json.loads(source), "--masses"
        except json.JSONDecodeError as exc:
            raise BadMasses(f"--masses {source!r}: not valid JSON ({exc}); write it as '{{\"part name\": kg}}', "
                            "in single quotes in a shell") from exc
    path = Path(source)
    if not path.is_file():
        raise BadMasses(f"{path}: masses file does not exist (--masses takes a JSON file or the JSON itself, "
                        "'{\"part name\": kg}')" if not path.exists()
                        else f"{path}: --masses must be a JSON file, this is a folder")
    try:
        return json.loads(path.read_text(encoding="utf-8")), str(path)
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise BadMasses(f"{path}: not a readable JSON file ({exc})") from exc


def load_masses(source: str | Path | Mapping[str, float], parts: Parts) -> dict[str, float]:
    """The density (kg/m3) of each part named in a JSON object of part masses ``{"part name": kg, ...}`` (a file,
    the JSON text, or a mapping: :func:`read_masses`): its mass spread evenly over its volume (the mesh's, or its
    convex pieces' where the mesh is not closed); parts it leaves out weigh their volume at ``--density``. Each
    density must lie between :data:`MIN_DENSITY_KG_M3` and :data:`MAX_DENSITY_KG_M3`: anything else is a unit
    mistake (grams, a mesh in the wrong unit) or a typo."""
    import math

    from planning.payload import volume_m3

    masses, path = read_masses(source)
    if not isinstance(masses, dict) or not masses:
        raise BadMasses(f'{path}: expected a JSON object of part masses in kg, such as {{"{parts.names[0]}": 1.5}}')
    unknown = sorted(set(masses) - set(parts.names))
    if unknown:
        raise BadMasses(f"{path}: mass for {', '.join(repr(n) for n in unknown)}, which the parts folder does not "
                         f"hold (its parts: {', '.join(parts.names)})")
    meshes = dict(zip(parts.names, parts.meshes))
    checked = {}
    for name, kg in masses.items():
        if isinstance(kg, bool) or not isinstance(kg, (int, float)) or not math.isfinite(kg) or kg <= 0:
            raise BadMasses(f"{path}: part {name!r}: mass {kg!r} is not a number of kilograms above 0")
        litres = volume_m3(meshes[name]) * 1000.0
        if not litres > 0:
            raise BadMasses(f"{path}: part {name!r} has no volume (a flat or open mesh), so its mass cannot be "
                             "spread over it; give a closed mesh")
        density = kg / litres * 1000.0
        if not MIN_DENSITY_KG_M3 <= density <= MAX_DENSITY_KG_M3:
            raise BadMasses(f"{path}: part {name!r}: {kg:g} kg in its {litres:.3g} litres is {density:.4g} kg/m3, "
                             f"{'lighter' if density < MIN_DENSITY_KG_M3 else 'denser'} than any furniture material; "
                             "give masses in kg (and the meshes' units with --units)")
        checked[name] = density
    return checked
