"""The input readers of ``python -m cell.run`` on what CAD exports and cameras give: non-square pictures cropped
or padded (with a note), materials and textures beside the meshes skipped (with a note), masses as JSON text."""

import json

import numpy as np
import pytest
import trimesh
from PIL import Image

from cell.errors import BadMasses, BadPicture
from cell.inputs import IMAGE_SIZE_PX, load_image, load_masses, load_parts

GREEN, RED, WHITE = (0, 200, 0), (220, 0, 0), (250, 250, 250)


def _photo(path, size=(640, 480), margin_px=80):
    """A 640x480 picture: a green object in the middle, red bands ``margin_px`` wide at its left and right."""
    rgb = np.zeros((size[1], size[0], 3), dtype=np.uint8)
    rgb[:] = GREEN
    rgb[:, :margin_px] = RED
    rgb[:, size[0] - margin_px:] = RED
    Image.fromarray(rgb).save(path)
    return path


def test_a_landscape_picture_is_centre_cropped_with_a_note(tmp_path):
    """640x480: the middle 480x480 (the red side bands, 80 px each, cut away) resized to 224x224."""
    notes = []
    picture = load_image(_photo(tmp_path / "photo.png"), notes=notes)
    assert picture.shape == (IMAGE_SIZE_PX, IMAGE_SIZE_PX, 3) and picture.dtype == np.uint8
    assert np.all(picture == GREEN)
    [note] = notes
    assert "photo.png: the image is 640x480, not square: centre-cropped to 480x480" in note
    assert note.endswith("then resized to 224x224")


def test_a_picture_is_padded_with_its_border_colour_when_asked(tmp_path):
    """A 480x640 portrait, white around a green object: padded to 640x640 with white (its border's median colour)
    on the left and right, 80 px each, i.e. 28 of the 224 columns."""
    rgb = np.full((640, 480, 3), WHITE, dtype=np.uint8)
    rgb[200:440, 140:340] = GREEN
    Image.fromarray(rgb).save(tmp_path / "portrait.png")
    notes = []
    picture = load_image(tmp_path / "portrait.png", pad=True, notes=notes).astype(int)
    assert np.all(picture[:, :27] == WHITE) and np.all(picture[:, -27:] == WHITE)
    centre = picture[IMAGE_SIZE_PX // 2, IMAGE_SIZE_PX // 2]
    assert tuple(centre) == GREEN
    assert notes == [str(tmp_path / "portrait.png") + ": the image is 480x640, not square: padded to 640x640 "
                     "with its border colour rgb(250, 250, 250), then resized to 224x224"]


def test_a_square_picture_and_an_array_need_no_note(tmp_path):
    notes = []
    rgb = np.random.default_rng(0).integers(0, 256, (448, 448, 3), dtype=np.uint8)
    Image.fromarray(rgb).save(tmp_path / "square.png")
    from_file = load_image(tmp_path / "square.png", notes=notes)
    from_array = load_image(rgb, notes=notes)
    assert notes == [] and np.array_equal(from_file, from_array)
    with pytest.raises(BadPicture, match=r"image array 200x100: the image is only 200x100; give at least 224x224"):
        load_image(np.zeros((100, 200, 3), dtype=np.uint8))
    with pytest.raises(BadPicture, match=r"give an \(H, W, 3\) uint8 RGB array"):
        load_image(np.zeros((224, 224), dtype=np.uint8))


def test_materials_and_textures_beside_the_meshes_are_skipped_with_a_note(tmp_path):
    """What a CAD or web export writes: seat.obj with seat.mtl and its texture, and a glTF's buffer."""
    folder = tmp_path / "parts"
    folder.mkdir()
    trimesh.creation.box([0.4, 0.4, 0.02]).export(folder / "seat.obj")
    trimesh.creation.box([0.04, 0.04, 0.4]).export(folder / "leg.stl")
    (folder / "seat.mtl").write_text("newmtl wood\nmap_Kd wood.jpg\n")
    Image.new("RGB", (8, 8)).save(folder / "wood.jpg")
    (folder / "leg.bin").write_bytes(b"\x00" * 16)
    notes = []
    parts = load_parts(folder, notes=notes)
    assert parts.names == ["leg", "seat"]
    assert [p.name for p in parts.skipped] == ["leg.bin", "seat.mtl", "wood.jpg"]
    assert notes == [f"{folder}: skipped 3 file(s) that are not parts (materials, textures): leg.bin, seat.mtl, "
                     "wood.jpg"]


def test_masses_are_read_from_a_file_or_json_text(tmp_path):
    """The same masses from a file, from JSON text (``--masses '{"seat": 1.4}'``) and from a dict."""
    folder = tmp_path / "parts"
    folder.mkdir()
    trimesh.creation.box([0.1, 0.1, 0.1]).export(folder / "seat.obj")  # 1 litre
    parts = load_parts(folder)
    (tmp_path / "masses.json").write_text(json.dumps({"seat": 1.4}))
    for source in (tmp_path / "masses.json", str(tmp_path / "masses.json"), ' {"seat": 1.4}', {"seat": 1.4}):
        assert load_masses(source, parts) == {"seat": pytest.approx(1400.0)}
    with pytest.raises(BadMasses, match=r"masses file does not exist \(--masses takes a JSON file or the JSON"):
        load_masses(tmp_path / "seat.json", parts)
