"""The assembly folder format: round trip, the real furniture, and each malformed file rejected by name."""

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
import trimesh

from planning.assembly import (
    Assembly,
    AssemblyError,
    AssemblyPart,
    read_assembly,
    read_poses,
    stretched,
    write_assembly,
)
from planning.pose import Pose

FURNITURE = Path(__file__).resolve().parents[2] / "shared" / "furniture"


def two_box_stack() -> Assembly:
    bottom = trimesh.creation.box([0.2, 0.2, 0.05])
    top = trimesh.creation.box([0.1, 0.1, 0.05])
    return Assembly("stack", [
        AssemblyPart("bottom", bottom, Pose([0, 0, 0.025], [1, 0, 0, 0])),
        AssemblyPart("top", top, Pose([0, 0, 0.075], [np.cos(0.3), 0, 0, np.sin(0.3)])),
    ], metadata={"source": "test"})


@pytest.fixture
def folder(tmp_path) -> Path:
    return write_assembly(two_box_stack(), tmp_path / "stack")


def edit_json(folder: Path, change) -> None:
    path = folder / "assembly.json"
    data = json.loads(path.read_text())
    change(data)
    path.write_text(json.dumps(data))


def test_round_trip(folder):
    original = two_box_stack()
    loaded = read_assembly(folder)
    assert loaded.part_names == ["bottom", "top"]
    assert loaded.metadata["source"] == "test"
    for a, b in zip(original.parts, loaded.parts):
        np.testing.assert_allclose(a.mesh.vertices, b.mesh.vertices, atol=1e-6)
        assert a.assembly_from_part.is_close(b.assembly_from_part, atol_position=1e-9, atol_angle_rad=1e-8)
    np.testing.assert_allclose(loaded.bounds(), [[-0.1, -0.1, 0.0], [0.1, 0.1, 0.1]], atol=1e-9)
    assert set(read_poses(folder / "assembly.json")) == {"bottom", "top"}


def test_write_refuses_to_overwrite_and_leaves_no_temporary(folder):
    with pytest.raises(FileExistsError):
        write_assembly(two_box_stack(), folder)
    assert sorted(p.name for p in folder.parent.iterdir()) == ["stack"]


def test_units_are_converted(folder):
    edit_json(folder, lambda d: d.update(units="mm"))
    loaded = read_assembly(folder)
    assert loaded.parts[0].mesh.extents[0] == pytest.approx(0.2e-3)
    assert loaded.parts[1].assembly_from_part.position[2] == pytest.approx(0.075e-3)


@pytest.mark.skipif(not FURNITURE.is_dir(), reason="shared furniture not present")
def test_reads_every_real_assembly():
    folders = sorted(p for p in FURNITURE.iterdir() if (p / "assembly.json").is_file())
    assert len(folders) == 42
    for path in folders:
        assembly = read_assembly(path)
        assert assembly.bounds()[0, 2] == pytest.approx(0.0, abs=2e-3), path.name


def set_part(index, key, value):
    def change(data):
        data["parts"][index][key] = value
    return change


BAD_CASES = [
    ("missing mesh", set_part(1, "mesh", "parts/nowhere.obj"), r"part 'top'.*nowhere\.obj does not exist"),
    ("NaN position", set_part(0, "pose", {"position": [0, float("nan"), 0], "quat_wxyz": [1, 0, 0, 0]}),
     r"part 'bottom'.*NaN"),
    ("non-unit quaternion", set_part(1, "pose", {"position": [0, 0, 0], "quat_wxyz": [1, 1, 0, 0]}),
     r"part 'top'.*not a unit quaternion.*norm 1\.41"),
    ("short quaternion", set_part(1, "pose", {"position": [0, 0, 0], "quat_wxyz": [1, 0, 0]}),
     r"part 'top'.*quat_wxyz must be a list of 4 numbers"),
    ("duplicate names", set_part(1, "name", "bottom"), r"'bottom' appears more than once"),
    ("unknown units", lambda d: d.update(units="inch"), r"unknown units 'inch'"),
    ("too many parts", lambda d: d.update(parts=[dict(d["parts"][0], name=f"p{i}") for i in range(21)]),
     r"21 parts, more than the 20"),
    ("no parts", lambda d: d.update(parts=[]), r"'parts' is empty"),
    ("wrong up axis", lambda d: d.update(up="+y"), r"up axis '\+y'"),
]


@pytest.mark.parametrize("label,change,message", BAD_CASES, ids=[c[0] for c in BAD_CASES])
def test_bad_assembly_json_is_rejected_by_name(folder, label, change, message):
    edit_json(folder, change)
    with pytest.raises(AssemblyError, match=message) as info:
        read_assembly(folder)
    assert "assembly.json" in str(info.value)


def test_unreadable_and_empty_meshes(folder):
    (folder / "parts" / "top.obj").write_text("this is not a mesh\n")
    with pytest.raises(AssemblyError, match=r"part 'top'.*(holds no triangles|cannot be read)"):
        read_assembly(folder)
    (folder / "parts" / "top.obj").write_bytes(b"")
    with pytest.raises(AssemblyError, match=r"part 'top'"):
        read_assembly(folder)


def test_degenerate_mesh(folder):
    (folder / "parts" / "top.obj").write_text("v 0 0 0\nv 1 0 0\nv 2 0 0\nf 1 2 3\n")
    with pytest.raises(AssemblyError, match=r"part 'top'.*(degenerate|no triangles)"):
        read_assembly(folder)


def test_invalid_json(folder):
    (folder / "assembly.json").write_text("{not json")
    with pytest.raises(AssemblyError, match=r"assembly\.json: not valid JSON"):
        read_assembly(folder)
    shutil.rmtree(folder)
    with pytest.raises(AssemblyError, match="does not exist"):
        read_assembly(folder)


def test_stretched_moves_every_vertex_by_the_axis_factors():
    """The top box is turned 0.6 rad about z, so its mesh must shear in its own frame to stay a stretched box."""
    stack, factors = two_box_stack(), np.array([2.0, 0.5, 1.5])
    longer = stretched(stack, factors)
    for before, after in zip(stack.meshes_in_assembly_frame(), longer.meshes_in_assembly_frame()):
        np.testing.assert_allclose(after.vertices, before.vertices * factors, atol=1e-12)
    np.testing.assert_allclose(longer.bounds(), stack.bounds() * factors, atol=1e-12)
    assert longer.bounds()[0, 2] == 0.0  # still on the floor
    for before, after in zip(stack.parts, longer.parts):  # rotations kept, the input untouched
        np.testing.assert_allclose(after.assembly_from_part.quat_wxyz, before.assembly_from_part.quat_wxyz)
    np.testing.assert_allclose(stack.parts[1].mesh.extents, [0.1, 0.1, 0.05])
    with pytest.raises(ValueError, match="three positive numbers"):
        stretched(stack, [1.0, 0.0, 1.0])
