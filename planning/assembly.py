"""The assembly folder format: ground truth and target poses everywhere in the project.

Layout (the same as ``shared/furniture``)::

    <object>/assembly.json
    <object>/parts/<part>.obj     one mesh per part, in that part's own frame

``assembly.json``::

    {"name": ..., "units": "m", "up": "+z",
     "parts": [{"name": "part_00", "mesh": "parts/part_00.obj",
                "pose": {"position": [x, y, z], "quat_wxyz": [w, x, y, z]}}, ...]}

A part's pose is ``assembly_from_part``: ``x_assembly = R(q) @ x_part + position``. The assembly frame has +z up,
the lowest point of the assembled object at z = 0 and its origin at the centre of the footprint. Other keys
(``source``, ``license``, ...) are kept as ``metadata`` and written back unchanged.

:func:`read_assembly` validates everything and raises :class:`AssemblyError` naming the file, the part and the
value at fault. Meshes are returned in metres whatever the file's ``units``.
"""

from __future__ import annotations

import contextlib
import json
import math
import os
import shutil
import tempfile
from dataclasses import dataclass, field
from functools import partial
from pathlib import Path

import numpy as np
import trimesh

from planning.mesh_intake import DEFAULT_SHEET_THICKNESS_M, SHEET_REACH_M, MeshIntakeError, intake_mesh
from planning.pose import Pose

MAX_PARTS = 20
UNIT_TO_METRES = {"m": 1.0, "cm": 0.01, "mm": 0.001}
ASSEMBLY_FILE = "assembly.json"


class AssemblyError(ValueError):
    """A malformed assembly folder; the message names the file, the part and the value at fault."""


@dataclass
class AssemblyPart:
    """One part: its mesh in its own frame (metres) and its pose ``assembly_from_part``."""

    name: str
    mesh: trimesh.Trimesh
    assembly_from_part: Pose
    mesh_file: str = ""  # path relative to the assembly folder, e.g. "parts/part_00.obj"


@dataclass
class Assembly:
    """An assembled object: parts with meshes (metres, part frames) and poses in the assembly frame (+z up)."""

    name: str
    parts: list[AssemblyPart]
    metadata: dict = field(default_factory=dict)
    mesh_intake: dict = field(default_factory=dict)  # part name: what planning.mesh_intake did to its mesh (read)

    @property
    def part_names(self) -> list[str]:
        return [p.name for p in self.parts]

    def part(self, name: str) -> AssemblyPart:
        for p in self.parts:
            if p.name == name:
                return p
        raise KeyError(f"assembly {self.name!r} has no part {name!r} (parts: {', '.join(self.part_names)})")

    def meshes_in_assembly_frame(self) -> list[trimesh.Trimesh]:
        """Each part's mesh moved to its pose (copies), metres, assembly frame."""
        out = []
        for p in self.parts:
            m = p.mesh.copy()
            m.apply_transform(p.assembly_from_part.matrix())
            out.append(m)
        return out

    def bounds(self) -> np.ndarray:
        """(2, 3) axis-aligned bounds of the assembled object, metres, assembly frame."""
        corners = np.concatenate([m.bounds for m in self.meshes_in_assembly_frame()])
        return np.stack([corners.min(axis=0), corners.max(axis=0)])


def stretched(assembly: Assembly, factors_xyz) -> Assembly:
    """``assembly`` scaled by ``factors_xyz`` (three positive numbers) along the assembly frame's x, y and z, about
    its origin: a longer, lower, deeper variant of the same object (the floor stays at z = 0, the footprint's
    centre at the origin). Each part keeps its rotation R, its position is scaled, and its mesh (its own frame,
    metres) is deformed by R^T S R, so that every vertex lands where S takes it in the assembly frame."""
    factors = np.asarray(factors_xyz, dtype=np.float64).reshape(-1)
    if factors.shape != (3,) or not np.all(np.isfinite(factors)) or np.any(factors <= 0):
        raise ValueError(f"stretch factors must be three positive numbers, got {np.asarray(factors_xyz).tolist()}")
    parts = []
    for part in assembly.parts:
        pose = part.assembly_from_part
        deform = np.eye(4)
        deform[:3, :3] = pose.rotation.T @ np.diag(factors) @ pose.rotation
        mesh = part.mesh.copy()
        mesh.apply_transform(deform)
        parts.append(AssemblyPart(part.name, mesh, Pose(factors * pose.position, pose.quat_wxyz), part.mesh_file))
    return Assembly(assembly.name, parts, dict(assembly.metadata))


# ---------------------------------------------------------------------------------------------------------
# reading
# ---------------------------------------------------------------------------------------------------------


def load_mesh(path: Path, where: str, scale_to_metres: float = 1.0) -> trimesh.Trimesh:
    """Load and validate one mesh file (metres after ``scale_to_metres``), as it is written (no repair: see
    :func:`solid_meshes`); :class:`AssemblyError` names ``where``."""
    if not path.is_file():
        raise AssemblyError(f"{where}: mesh file {path} does not exist")
    try:
        loaded = trimesh.load(path, force="mesh", process=False)
    except Exception as exc:  # trimesh raises many types on corrupt files
        # bytes that are neither a binary mesh nor text end in trimesh's search for a text encoding
        reason = ("its bytes are neither text nor a binary mesh: a corrupt file, or another format under a mesh "
                  "suffix" if isinstance(exc, (ImportError, UnicodeError)) else str(exc))
        raise AssemblyError(f"{where}: mesh file {path} cannot be read as a {path.suffix.lower() or 'mesh'} mesh "
                            f"({reason}); export the part again as .obj, .stl or .ply") from exc
    if not isinstance(loaded, trimesh.Trimesh) or len(loaded.faces) == 0 or len(loaded.vertices) < 3:
        raise AssemblyError(f"{where}: mesh file {path} holds no triangles")
    if not np.all(np.isfinite(loaded.vertices)):
        raise AssemblyError(f"{where}: mesh file {path} has non-finite vertex coordinates")
    if loaded.area <= 0 or float(np.max(loaded.extents)) <= 0:
        raise AssemblyError(f"{where}: mesh file {path} is degenerate (zero area)")
    if scale_to_metres != 1.0:
        loaded.apply_scale(scale_to_metres)
    return loaded


def outward_directions(meshes: list[trimesh.Trimesh], assembly_from_part: list[Pose]) -> list[np.ndarray]:
    """Per part, the direction (3,) in its own frame from the assembly's centre (the middle of its bounds) to the
    part's centre: the side a one-surface board grows to where no neighbour decides (:func:`solid_meshes`)."""
    placed = [pose.apply(np.asarray(m.vertices)) for m, pose in zip(meshes, assembly_from_part)]
    low = np.min([v.min(axis=0) for v in placed], axis=0)
    high = np.max([v.max(axis=0) for v in placed], axis=0)
    centre = 0.5 * (low + high)
    return [pose.rotation.T @ (pose.apply(m.bounds.mean(axis=0)) - centre)
            for m, pose in zip(meshes, assembly_from_part)]


def _outward_faces(mesh: trimesh.Trimesh) -> np.ndarray:
    """``mesh``'s faces, all reversed where it encloses a negative volume (drawn inside-out), so that a ray enters
    it through faces turned towards the ray (an open or mixed mesh keeps its faces: rays enter through those drawn
    the right way)."""
    faces = np.asarray(mesh.faces)
    with np.errstate(all="ignore"):
        volume = float(trimesh.triangles.mass_properties(mesh.triangles, skip_inertia=True).volume)
    return faces[:, ::-1] if volume < 0 else faces


def neighbours_in_part_frame(meshes: list[trimesh.Trimesh], assembly_from_part: list[Pose], index: int,
                             reach_m: float = SHEET_REACH_M) -> trimesh.Trimesh:
    """What a one-surface board of part ``index`` may grow to meet (:func:`planning.mesh_intake.intake_mesh`), as
    one mesh placed in part ``index``'s frame (empty when nothing is near): the meshes of the other parts whose
    bounds come within ``reach_m`` of its own (their faces turned outwards, :func:`_outward_faces`), and the floor
    (the plane z = 0 of the assembly frame, as a slab under the part) where the part comes within ``reach_m`` of
    it."""
    def assembly_bounds(k: int) -> np.ndarray:  # (2, 3) of the mesh's bounding box's corners, placed
        corners = trimesh.bounds.corners(meshes[k].bounds)
        placed = assembly_from_part[k].apply(corners)
        return np.stack([placed.min(axis=0), placed.max(axis=0)])

    own = assembly_bounds(index)
    low, high = own[0] - reach_m, own[1] + reach_m
    rotation_t, position = assembly_from_part[index].rotation.T, assembly_from_part[index].position
    near = []
    for k, mesh in enumerate(meshes):
        if k == index:
            continue
        bounds = assembly_bounds(k)
        if np.any(bounds[1] < low) or np.any(bounds[0] > high):
            continue
        rotation = rotation_t @ assembly_from_part[k].rotation  # part k's frame to part index's
        offset = rotation_t @ (assembly_from_part[k].position - position)
        near.append(trimesh.Trimesh(np.asarray(mesh.vertices) @ rotation.T + offset, _outward_faces(mesh),
                                    process=False))
    if low[2] <= 0.0:
        floor = trimesh.creation.box(bounds=[[low[0], low[1], -reach_m], [high[0], high[1], 0.0]])
        near.append(trimesh.Trimesh((np.asarray(floor.vertices) - position) @ rotation_t.T, floor.faces,
                                    process=False))
    return trimesh.util.concatenate(near) if near else trimesh.Trimesh()


def solid_meshes(meshes: list[trimesh.Trimesh], wheres: list[str],
                 sheet_thickness_m: float = DEFAULT_SHEET_THICKNESS_M,
                 assembly_from_part: list[Pose] | None = None) -> list[tuple[trimesh.Trimesh, dict]]:
    """The solid of each part mesh (metres, part frame) through :func:`planning.mesh_intake.intake_mesh`, and the
    intake's record: ``[(mesh, record)]``. With the parts' poses, a one-surface board grows against the parts
    placed around it (:func:`neighbours_in_part_frame`), else away from the assembly's centre
    (:func:`outward_directions`); without them, behind its drawn face. A mesh that no repair makes a solid raises
    :class:`AssemblyError` naming its ``where``."""
    outwards = ([None] * len(meshes) if assembly_from_part is None
                else outward_directions(meshes, assembly_from_part))
    out = []
    for index, (mesh, where, outward) in enumerate(zip(meshes, wheres, outwards)):
        neighbours = None if assembly_from_part is None else partial(neighbours_in_part_frame, meshes,
                                                                          assembly_from_part, index)
        try:
            intake = intake_mesh(mesh, where, sheet_thickness_m, outward, neighbours=neighbours)
        except MeshIntakeError as exc:
            raise AssemblyError(str(exc)) from exc
        out.append((intake.mesh, intake.to_json()))
    return out


def _parse_pose(entry: object, where: str) -> Pose:
    if not isinstance(entry, dict) or "position" not in entry or "quat_wxyz" not in entry:
        raise AssemblyError(f"{where}: 'pose' must be an object with 'position' and 'quat_wxyz', got {entry!r}")
    position, quat = entry["position"], entry["quat_wxyz"]
    for key, value, size in (("position", position, 3), ("quat_wxyz", quat, 4)):
        if (
            not isinstance(value, list)
            or len(value) != size
            or not all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in value)
        ):
            raise AssemblyError(f"{where}: pose.{key} must be a list of {size} numbers, got {value!r}")
        if not all(math.isfinite(v) for v in value):
            raise AssemblyError(f"{where}: pose.{key} {value} contains NaN or infinity")
    norm = math.sqrt(sum(v * v for v in quat))
    if abs(norm - 1.0) > 1e-3:
        raise AssemblyError(
            f"{where}: pose.quat_wxyz {quat} is not a unit quaternion (norm {norm:.6f}); write (w, x, y, z) with norm 1"
        )
    return Pose(np.array(position, dtype=np.float64), np.array(quat, dtype=np.float64))


def read_assembly_json(json_path: str | os.PathLike) -> dict:
    """Parse and shape-check an ``assembly.json`` without loading meshes. Returns the raw dictionary."""
    json_path = Path(json_path)
    if not json_path.is_file():
        raise AssemblyError(f"{json_path}: file does not exist")
    try:
        data = json.loads(json_path.read_text(encoding="utf-8"))
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise AssemblyError(f"{json_path}: not valid JSON ({exc})") from exc
    if not isinstance(data, dict) or not isinstance(data.get("parts"), list):
        raise AssemblyError(f"{json_path}: expected an object with a 'parts' list")
    units = data.get("units", "m")
    if units not in UNIT_TO_METRES:
        raise AssemblyError(
            f"{json_path}: unknown units {units!r}; use one of {', '.join(repr(u) for u in UNIT_TO_METRES)}"
        )
    up = data.get("up", "+z")
    if up != "+z":
        raise AssemblyError(f"{json_path}: up axis {up!r} is not supported; the assembly frame must be '+z' up")
    parts = data["parts"]
    if len(parts) == 0:
        raise AssemblyError(f"{json_path}: 'parts' is empty")
    if len(parts) > MAX_PARTS:
        raise AssemblyError(f"{json_path}: {len(parts)} parts, more than the {MAX_PARTS} the project supports")
    seen: set[str] = set()
    for index, part in enumerate(parts):
        if not isinstance(part, dict) or not isinstance(part.get("name"), str) or not part["name"]:
            raise AssemblyError(f"{json_path}: parts[{index}] needs a non-empty string 'name'")
        if part["name"] in seen:
            raise AssemblyError(f"{json_path}: part name {part['name']!r} appears more than once")
        seen.add(part["name"])
        if not isinstance(part.get("mesh"), str):
            raise AssemblyError(f"{json_path}: part {part['name']!r} needs a string 'mesh' path")
    return data


def read_poses(json_path: str | os.PathLike) -> dict[str, Pose]:
    """Read only the poses of an ``assembly.json`` (for ``--poses``): ``{part name: assembly_from_part}``, metres."""
    json_path = Path(json_path)
    data = read_assembly_json(json_path)
    scale = UNIT_TO_METRES[data.get("units", "m")]
    poses = {}
    for part in data["parts"]:
        pose = _parse_pose(part.get("pose"), f"{json_path}: part {part['name']!r}")
        poses[part["name"]] = Pose(pose.position * scale, pose.quat_wxyz)
    return poses


def read_assembly(folder: str | os.PathLike, sheet_thickness_m: float = DEFAULT_SHEET_THICKNESS_M) -> Assembly:
    """Read and validate an assembly folder. Meshes and positions come back in metres, each mesh the part's solid
    (:func:`solid_meshes`: a clean closed mesh as it is; a one-surface board grown to meet the part beside it, or
    ``sheet_thickness_m`` thick), what the intake did in ``mesh_intake``."""
    folder = Path(folder)
    json_path = folder / ASSEMBLY_FILE
    if not folder.is_dir():
        raise AssemblyError(f"{folder}: assembly folder does not exist")
    data = read_assembly_json(json_path)
    scale = UNIT_TO_METRES[data.get("units", "m")]
    parts = []
    for entry in data["parts"]:
        where = f"{json_path}: part {entry['name']!r}"
        pose = _parse_pose(entry.get("pose"), where)
        mesh = load_mesh(folder / entry["mesh"], where, scale)
        parts.append(AssemblyPart(entry["name"], mesh, Pose(pose.position * scale, pose.quat_wxyz), entry["mesh"]))
    records = {}
    solids = solid_meshes([p.mesh for p in parts], [f"{json_path}: part {p.name!r}" for p in parts],
                          sheet_thickness_m, [p.assembly_from_part for p in parts])
    for part, (solid, record) in zip(parts, solids):
        part.mesh, records[part.name] = solid, record
    metadata = {k: v for k, v in data.items() if k not in ("name", "parts", "units", "up")}
    return Assembly(name=str(data.get("name", folder.name)), parts=parts, metadata=metadata, mesh_intake=records)


# ---------------------------------------------------------------------------------------------------------
# writing
# ---------------------------------------------------------------------------------------------------------


def assembly_to_json(assembly: Assembly) -> dict:
    parts = []
    for p in assembly.parts:
        mesh_file = p.mesh_file or f"parts/{p.name}.obj"
        parts.append({"name": p.name, "mesh": mesh_file, "pose": p.assembly_from_part.to_dict()})
    return {"name": assembly.name, "units": "m", "up": "+z", **assembly.metadata, "parts": parts}


@contextlib.contextmanager
def replacing_folder(folder: str | os.PathLike):
    """Write a folder whole or not at all: yields a fresh temporary sibling to fill, which replaces ``folder``
    (an existing one is removed) when the block ends without an exception, and is removed when it raises."""
    folder = Path(folder)
    folder.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{folder.name}.", dir=folder.parent))
    try:
        yield tmp
        if folder.exists():
            shutil.rmtree(folder)
        os.replace(tmp, folder)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise


def write_assembly(assembly: Assembly, folder: str | os.PathLike, overwrite: bool = False) -> Path:
    """Write ``assembly`` as an assembly folder (metres). The folder appears whole or not at all: everything is
    written to a temporary sibling and renamed into place."""
    folder = Path(folder)
    if len(assembly.parts) > MAX_PARTS:
        raise AssemblyError(f"{assembly.name}: {len(assembly.parts)} parts, more than {MAX_PARTS}")
    names = assembly.part_names
    if len(set(names)) != len(names):
        raise AssemblyError(f"{assembly.name}: duplicate part names {names}")
    if folder.exists() and not overwrite:
        raise FileExistsError(f"{folder} already exists")
    with replacing_folder(folder) as tmp:
        document = assembly_to_json(assembly)
        for part, entry in zip(assembly.parts, document["parts"]):
            target = tmp / entry["mesh"]
            target.parent.mkdir(parents=True, exist_ok=True)
            target.write_text(trimesh.exchange.obj.export_obj(part.mesh, include_normals=False, include_texture=False))
        (tmp / ASSEMBLY_FILE).write_text(json.dumps(document, indent=1) + "\n", encoding="utf-8")
    return folder
