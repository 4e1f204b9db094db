"""The verdict of a run from a picture: the predicted assembly drawn against the object in the picture."""

import json

import numpy as np
import pytest
from PIL import Image

from cell.render import render_assembly
from cell.run import main
from perception.agreement import (
    MAX_PIXEL_NOISE,
    draw_silhouette,
    fit_silhouette,
    object_mask,
    picture_agreement,
    pixel_noise,
    plain_background,
)
from perception.synth import generate
from planning.pose import Pose
from scenes import sample_folder, sample_image


@pytest.fixture(scope="module")
def chair_view():
    assembly = generate("chair", "3", np.random.default_rng([11, 0]), "chair")
    return assembly, render_assembly(assembly, np.random.default_rng(5))


def _camera_poses(assembly, view, moved: dict | None = None):
    moved = moved or {}
    return [view.camera_from_assembly @ Pose(p.assembly_from_part.position + moved.get(p.name, 0.0),
                                             p.assembly_from_part.quat_wxyz) for p in assembly.parts]


def test_the_backdrop_of_a_render_gives_its_exact_silhouette(chair_view):
    _, view = chair_view
    background = plain_background(view.rgb)
    assert background is not None
    truth, found = view.part_labels >= 0, ~background
    assert np.count_nonzero(truth & found) / np.count_nonzero(truth | found) > 0.95


def test_the_true_assembly_agrees_and_a_part_moved_off_the_object_does_not(chair_view):
    assembly, view = chair_view
    mask, source = object_mask(view.rgb, None)
    names = [p.name for p in assembly.parts]
    meshes = [p.mesh for p in assembly.parts]
    truth = picture_agreement(mask, names, meshes, _camera_poses(assembly, view))
    assert source == "plain background"
    assert truth.silhouette_iou > 0.9 and truth.scale == pytest.approx(1.0, abs=0.05)
    leg = next(n for n in names if n.startswith("leg"))
    moved = picture_agreement(mask, names, meshes, _camera_poses(assembly, view, {leg: np.array([0.0, 0.0, 0.5])}))
    assert moved.on_object[leg] < truth.on_object[leg] - 0.4, (moved.on_object[leg], truth.on_object[leg])
    seat = max(assembly.parts, key=lambda p: p.mesh.area).name  # the largest part moved changes the silhouette
    moved = picture_agreement(mask, names, meshes, _camera_poses(assembly, view, {seat: np.array([0.0, 0.0, 0.3])}))
    assert moved.silhouette_iou < truth.silhouette_iou - 0.1


def test_the_fit_undoes_a_wrong_distance_but_not_a_wrong_layout():
    square = np.array([[[80, 80], [140, 80], [140, 140]], [[80, 80], [140, 140], [80, 140]]], dtype=np.float64)
    target = draw_silhouette(square, 224)
    smaller = 110 + 0.85 * (square - 110) + np.array([6.0, -4.0])  # farther away and off centre
    scale, shift, centre = fit_silhouette(smaller, target)
    fitted = draw_silhouette(smaller, 224, centre, scale, shift)
    assert np.count_nonzero(fitted & target) / np.count_nonzero(fitted | target) > 0.95


def test_pixel_noise_tells_noise_from_pictures():
    assert pixel_noise(np.asarray(Image.open(sample_image("chair")).convert("RGB"))) < MAX_PIXEL_NOISE / 3
    noise = np.random.default_rng(0).integers(0, 256, (224, 224, 3)).astype(np.uint8)
    assert pixel_noise(noise) > MAX_PIXEL_NOISE


@pytest.mark.parametrize("kind", ["black", "grey", "noise"])
def test_a_picture_with_no_object_is_bad_input(kind, tmp_path, capsys):
    pixels = {"black": np.zeros((224, 224, 3), np.uint8), "grey": np.full((224, 224, 3), 128, np.uint8),
              "noise": np.random.default_rng(1).integers(0, 256, (224, 224, 3)).astype(np.uint8)}[kind]
    image = tmp_path / f"{kind}.png"
    Image.fromarray(pixels).save(image)
    out = tmp_path / "out"
    code = main(["--image", str(image), "--parts", str(sample_folder("chair") / "parts"), "--out", str(out),
                 "--quiet"])
    err = capsys.readouterr().err
    assert code == 2, err
    assert str(image) in err and ("no object" in err or "noise" in err) and "Traceback" not in err
    assert not out.exists()


def test_the_bundled_chair_picture_is_not_built_as_the_wrong_chair(tmp_path, capsys):
    """The bundled network's prediction for the sample chair puts parts beside the chair: the run stops before
    planning (exit 5), says why and writes the report and the overview with the silhouettes compared."""
    out = tmp_path / "out"
    code = main(["--image", str(sample_image("chair")), "--parts", str(sample_folder("chair") / "parts"), "--out",
                 str(out), "--quiet"])
    captured = capsys.readouterr()
    report = json.loads((out / "report.json").read_text())
    agreement = report["picture_agreement"]
    assert code == 5 and report["exit_code"] == 5, captured.err
    assert not report["success"] and not report["built"] and not agreement["agrees"]
    assert agreement["silhouette_iou"] < 0.8 and report["failure"]["part"] in agreement["on_object"]
    assert "does not match the picture" in captured.err and "--accept-prediction" in captured.err
    assert sorted(p.name for p in out.iterdir()) == ["overview.png", "report.json"]
    width, height = Image.open(out / "overview.png").size
    assert width == 3 * height  # input | silhouettes compared | predicted assembly


def test_a_shelf_at_the_wrong_height_keeps_the_outline_but_not_the_edges():
    """An open cabinet's outline does not show where its shelf is; the picture's edges do."""
    assembly = generate("cabinet", "3", np.random.default_rng([11, 2]), "cabinet")
    view = render_assembly(assembly, np.random.default_rng(5))
    mask, _ = object_mask(view.rgb, None)
    names, meshes = [p.name for p in assembly.parts], [p.mesh for p in assembly.parts]
    assert "shelf_1" in names and not any(name.startswith("door") for name in names)
    truth = picture_agreement(mask, names, meshes, _camera_poses(assembly, view), image=view.rgb)
    moved = picture_agreement(mask, names, meshes,
                              _camera_poses(assembly, view, {"shelf_1": np.array([0.0, 0.0, 0.08])}), image=view.rgb)
    assert truth.edge_recall >= 0.95 and truth.silhouette_iou > 0.95
    assert moved.silhouette_iou > 0.95 and moved.edge_recall < truth.edge_recall - 0.04
