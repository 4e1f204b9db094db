"""The user's inputs to ``python -m cell.run``, read and checked before anything is computed.

Every problem raises :class:`InputError` with a message naming the file, the part or the value at fault and,
where there is one, the fix.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import trimesh

from planning.assembly import ASSEMBLY_FILE, MAX_PARTS, UNIT_TO_METRES, AssemblyError, load_mesh, read_poses, solid_mesh
from planning.mesh_intake import DEFAULT_SHEET_THICKNESS_M
from planning.pose import Pose

MESH_SUFFIXES = (".obj", ".stl", ".ply", ".off", ".glb", ".gltf")
IMAGE_SIZE_PX = 224  # what the network sees; larger square pictures are resized
MAX_IMAGE_SIDE_PX = 4096
MIN_IMAGE_SIDE_PX = 64
LARGEST_PLAUSIBLE_PART_M = 3.0  # a furniture part longer than this is a unit mistake, not furniture
MIN_DENSITY_KG_M3 = 10.0  # lighter than the lightest foam: a value in g/cm3 (wood is 0.6 there) or a typo
MAX_DENSITY_KG_M3 = 25000.0  # denser than any solid: a typo or a mass in grams, not a material


class InputError(ValueError):
    """Bad input; the message names the culprit."""


@dataclass(frozen=True)
class Parts:
    names: list[str]  # file stems, sorted
    meshes: list[trimesh.Trimesh]  # own frames, metres: each part's solid (planning.mesh_intake)
    files: list[Path]
    mesh_intake: dict[str, dict] = field(default_factory=dict)  # part name: what the intake did to its mesh


def load_parts(folder: str | Path, units: str = "m", sheet_thickness_m: float = DEFAULT_SHEET_THICKNESS_M) -> Parts:
    """Every mesh file of ``folder`` (one part each, named after the file), in metres, each turned into the part's
    solid by :mod:`planning.mesh_intake` (one-surface boards ``sheet_thickness_m`` thick, behind the drawn face)."""
    folder = Path(folder)
    if not folder.exists():
        raise InputError(f"{folder}: parts folder does not exist")
    if not folder.is_dir():
        raise InputError(f"{folder}: --parts must be a folder of mesh files, this is a file")
    files = sorted(p for p in folder.iterdir() if not p.name.startswith("."))
    others = [p for p in files if p.is_dir() or p.suffix.lower() not in MESH_SUFFIXES]
    if others:
        raise InputError(f"{others[0]}: not a mesh file (the parts folder may hold only "
                         f"{', '.join(MESH_SUFFIXES)} files, one part each)")
    if not files:
        raise InputError(f"{folder}: parts folder is empty (expected one mesh file per part: "
                         f"{', '.join(MESH_SUFFIXES)})")
    if len(files) > MAX_PARTS:
        raise InputError(f"{folder}: {len(files)} parts, more than the {MAX_PARTS} the method supports")
    names = [p.stem for p in files]
    duplicates = sorted({n for n in names if names.count(n) > 1})
    if duplicates:
        raise InputError(f"{folder}: several files for part {duplicates[0]!r} (one mesh file per part name)")
    meshes, intake = [], {}
    for name, path in zip(names, files):
        try:
            mesh, intake[name] = solid_mesh(load_mesh(path, f"part {name!r}", UNIT_TO_METRES[units]),
                                            f"part {name!r} ({path})", sheet_thickness_m)
        except AssemblyError as exc:
            raise InputError(str(exc)) from exc
        meshes.append(mesh)
    largest = max(float(np.max(m.extents)) for m in meshes)
    if largest > LARGEST_PLAUSIBLE_PART_M:
        worst = names[int(np.argmax([np.max(m.extents) for m in meshes]))]
        hint = ("the files look like millimetres: rerun with --units mm" if units == "m" and largest > 100
                else "the files look like centimetres: rerun with --units cm" if units == "m"
                else "check the units of the files")
        raise InputError(f"{folder}: part {worst!r} is {largest:g} {units} across, too large for furniture parts in "
                         f"{'metres' if units == 'm' else units}; {hint}")
    return Parts(names, meshes, files, intake)


def load_image(path: str | Path) -> np.ndarray:
    """The picture as a (224, 224, 3) uint8 RGB array; a larger square RGB picture is resized."""
    from PIL import Image, UnidentifiedImageError

    path = Path(path)
    if not path.exists():
        raise InputError(f"{path}: image file does not exist")
    if not path.is_file():
        raise InputError(f"{path}: --image must be an image file, this is a folder")
    try:
        with Image.open(path) as image:
            image.load()
            mode, size = image.mode, image.size
            if mode in ("RGBA", "LA", "PA") or (mode == "P" and "transparency" in image.info):
                raise InputError(f"{path}: the image has an alpha channel ({mode}); flatten it onto a background "
                                 "and save it as RGB")
            if mode in ("L", "1", "I", "I;16", "F"):
                raise InputError(f"{path}: the image is grayscale ({mode}); the method needs an RGB photo or "
                                 "rendering")
            if mode != "RGB":
                raise InputError(f"{path}: unsupported colour mode {mode}; save it as 8-bit RGB")
            width, height = size
            if width != height:
                raise InputError(f"{path}: the image is {width}x{height}; it must be square (crop it around the "
                                 f"object, at least {IMAGE_SIZE_PX}x{IMAGE_SIZE_PX})")
            if width > MAX_IMAGE_SIDE_PX:
                raise InputError(f"{path}: the image is {width}x{height}, larger than {MAX_IMAGE_SIDE_PX}x"
                                 f"{MAX_IMAGE_SIDE_PX}; resize it to {IMAGE_SIZE_PX}x{IMAGE_SIZE_PX}")
            if width < MIN_IMAGE_SIDE_PX:
                raise InputError(f"{path}: the image is only {width}x{height}; give at least "
                                 f"{IMAGE_SIZE_PX}x{IMAGE_SIZE_PX}")
            if width != IMAGE_SIZE_PX:
                image = image.resize((IMAGE_SIZE_PX, IMAGE_SIZE_PX), Image.Resampling.BILINEAR)
            return np.asarray(image, dtype=np.uint8).copy()
    except InputError:
        raise
    except (UnidentifiedImageError, OSError, ValueError) as exc:
        raise InputError(f"{path}: not a readable image file ({exc.__class__.__name__}: {exc})") from exc


def load_poses(path: str | Path, part_names: list[str]) -> dict[str, Pose]:
    """Target poses ``assembly_from_part`` from an ``assembly.json`` (or a folder holding one), metres; every
    part of the parts folder must appear exactly once."""
    path = Path(path)
    if path.is_dir():
        path = path / ASSEMBLY_FILE
    try:
        poses = read_poses(path)
    except AssemblyError as exc:
        raise InputError(str(exc)) from exc
    missing = sorted(set(part_names) - set(poses))
    extra = sorted(set(poses) - set(part_names))
    if missing:
        raise InputError(f"{path}: no pose for part(s) {', '.join(missing)} of the parts folder")
    if extra:
        raise InputError(f"{path}: pose(s) for {', '.join(extra)}, which the parts folder does not hold")
    return poses


def load_masses(path: str | Path, parts: Parts) -> dict[str, float]:
    """The density (kg/m3) of each part named in a JSON object of part masses ``{"part name": kg, ...}``: its
    mass spread evenly over its volume (the mesh's, or its convex pieces' where the mesh is not closed); parts it
    leaves out weigh their volume at ``--density``. Each density must lie between :data:`MIN_DENSITY_KG_M3` and
    :data:`MAX_DENSITY_KG_M3`: anything else is a unit mistake (grams, a mesh in the wrong unit) or a typo."""
    import json
    import math

    from planning.payload import volume_m3

    path = Path(path)
    if not path.is_file():
        raise InputError(f"{path}: masses file does not exist" if not path.exists()
                         else f"{path}: --masses must be a JSON file, this is a folder")
    try:
        masses = json.loads(path.read_text(encoding="utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise InputError(f"{path}: not a readable JSON file ({exc})") from exc
    if not isinstance(masses, dict) or not masses:
        raise InputError(f'{path}: expected a JSON object of part masses in kg, such as {{"{parts.names[0]}": 1.5}}')
    unknown = sorted(set(masses) - set(parts.names))
    if unknown:
        raise InputError(f"{path}: mass for {', '.join(repr(n) for n in unknown)}, which the parts folder does not "
                         f"hold (its parts: {', '.join(parts.names)})")
    meshes = dict(zip(parts.names, parts.meshes))
    checked = {}
    for name, kg in masses.items():
        if isinstance(kg, bool) or not isinstance(kg, (int, float)) or not math.isfinite(kg) or kg <= 0:
            raise InputError(f"{path}: part {name!r}: mass {kg!r} is not a number of kilograms above 0")
        litres = volume_m3(meshes[name]) * 1000.0
        if not litres > 0:
            raise InputError(f"{path}: part {name!r} has no volume (a flat or open mesh), so its mass cannot be "
                             "spread over it; give a closed mesh")
        density = kg / litres * 1000.0
        if not MIN_DENSITY_KG_M3 <= density <= MAX_DENSITY_KG_M3:
            raise InputError(f"{path}: part {name!r}: {kg:g} kg in its {litres:.3g} litres is {density:.4g} kg/m3, "
                             f"{'lighter' if density < MIN_DENSITY_KG_M3 else 'denser'} than any furniture material; "
                             "give masses in kg (and the meshes' units with --units)")
        checked[name] = density
    return checked
