"""perception.predict with a real (tiny, few-step) trained model: frame algebra, metres, up, clear errors."""

import numpy as np
import pytest
import torch

from cell.render import render_assembly
from perception import weights
from perception.evaluate_assemblies import truth_targets
from perception.placement import place_parts
from perception.predict import MissingPredictionWeights, PredictionError, predict, prepare_parts
from perception.synth import generate
from perception.upright import angle_deg
from planning.pose import Pose, quat_angle_rad


@pytest.fixture(scope="module")
def checkpoint(tiny_checkpoint):
    return tiny_checkpoint


@pytest.fixture(scope="module")
def scene():
    """A procedural table never trained on and one rendered view of it."""
    assembly = generate("table", "3", np.random.default_rng([1000, 2]), "table_test")
    return assembly, render_assembly(assembly, np.random.default_rng(5))


def meshes_of(assembly, scale=1.0):
    out = {}
    for part in assembly.parts:
        mesh = part.mesh.copy()
        mesh.apply_scale(scale)
        out[part.name] = mesh
    return out


def test_camera_pose_is_camera_from_assembly_times_assembly_pose(checkpoint, scene):
    assembly, view = scene
    prediction = predict(view.rgb, meshes_of(assembly), checkpoint)
    assert prediction.names == assembly.part_names
    for name in prediction.names:
        composed = prediction.camera_from_assembly @ prediction.assembly_from_part[name]
        assert np.allclose(composed.position, prediction.camera_from_part[name].position, atol=1e-9)
        assert quat_angle_rad(composed.quat_wxyz, prediction.camera_from_part[name].quat_wxyz) < 1e-7
    # the assembly frame: lowest point at z = 0, origin at the footprint centre, z along the estimated up
    placed = np.concatenate([prediction.assembly_from_part[p.name].apply(p.mesh.vertices) for p in assembly.parts])
    assert placed[:, 2].min() == pytest.approx(0.0, abs=1e-9)
    assert np.allclose(0.5 * (placed.min(0) + placed.max(0))[:2], 0.0, atol=1e-9)
    assert np.allclose(prediction.camera_from_assembly.rotation[:, 2], prediction.up.up_camera, atol=1e-9)
    assert prediction.summary()["parts"] == len(assembly.parts)


def test_truth_shortcut_gives_back_the_true_poses_and_up(scene):
    """The network's exact targets fed through the way back: true camera poses (metres) and the true up."""
    assembly, view = scene
    parts = prepare_parts([p.mesh for p in assembly.parts])
    bounds = assembly.bounds()
    quat, trans = truth_targets(view, parts, view.camera_from_assembly.apply(0.5 * (bounds[0] + bounds[1])))
    placement = place_parts(quat, trans, parts.normalized, parts.meshes)
    for predicted, true in zip(placement.camera_from_part, view.camera_from_part):
        assert np.linalg.norm(predicted.position - true.position) < 0.003  # metres
        assert np.degrees(quat_angle_rad(predicted.quat_wxyz, true.quat_wxyz)) < 1e-4
    assert angle_deg(placement.up.up_camera, view.camera_from_assembly.rotation[:, 2]) < 0.01
    # the assembly frames differ by a quarter turn about z at most (yaw is chosen, not known) and share the origin
    true_from_predicted = view.camera_from_assembly.inverse() @ placement.camera_from_assembly
    rotation = true_from_predicted.rotation
    assert abs(rotation[2, 2] - 1.0) < 1e-6
    yaw = np.degrees(np.arctan2(rotation[1, 0], rotation[0, 0]))
    assert min(abs(yaw - k) for k in (-180, -90, 0, 90, 180)) < 0.5
    assert np.linalg.norm(true_from_predicted.position) < 0.003


def test_poses_scale_with_the_meshes_in_metres(checkpoint, scene):
    """A twice larger object fills the same picture from twice the distance: every position doubles."""
    assembly, view = scene
    small = predict(view.rgb, meshes_of(assembly), checkpoint)
    large = predict(view.rgb, meshes_of(assembly, 2.0), checkpoint)
    for name in small.names:
        for frame in ("camera_from_part", "assembly_from_part"):
            a, b = getattr(small, frame)[name], getattr(large, frame)[name]
            assert np.allclose(b.position, 2.0 * a.position, rtol=1e-4, atol=1e-6)
            assert quat_angle_rad(a.quat_wxyz, b.quat_wxyz) < 1e-4


def test_a_list_of_meshes_is_keyed_by_index_and_threads_are_restored(checkpoint, scene):
    assembly, view = scene
    before = torch.get_num_threads()
    prediction = predict(view.rgb, [p.mesh for p in assembly.parts], checkpoint, threads=1)
    assert prediction.names == list(range(len(assembly.parts)))
    assert isinstance(prediction.camera_from_part[0], Pose)
    assert torch.get_num_threads() == before


@pytest.mark.parametrize("image, message", [
    (np.zeros((128, 128, 3), np.uint8), "got shape (128, 128, 3)"),
    (np.zeros((224, 224), np.uint8), "got shape (224, 224)"),
    (np.zeros((224, 224, 3), np.float32), "got float32"),
])
def test_a_bad_image_is_refused_naming_the_value(checkpoint, scene, image, message):
    with pytest.raises(PredictionError, match=message.replace("(", r"\(").replace(")", r"\)")):
        predict(image, meshes_of(scene[0]), checkpoint)


def test_bad_meshes_are_refused_naming_the_part(checkpoint, scene):
    assembly, view = scene
    with pytest.raises(PredictionError, match="empty"):
        predict(view.rgb, {}, checkpoint)
    with pytest.raises(PredictionError, match="'top'.*trimesh.Trimesh, got str"):
        predict(view.rgb, {"top": "top.obj"}, checkpoint)
    with pytest.raises(PredictionError, match="21 part meshes"):
        predict(view.rgb, [assembly.parts[0].mesh] * 21, checkpoint)


def test_a_missing_weights_file_names_the_file_and_the_training_command(scene, tmp_path, monkeypatch):
    assembly, view = scene
    missing = tmp_path / "nowhere" / "model.pt"
    with pytest.raises(MissingPredictionWeights, match=r"nowhere/model.pt not found.*python -m perception.train"):
        predict(view.rgb, meshes_of(assembly), missing)
    monkeypatch.setattr(weights, "BUNDLED_WEIGHTS", tmp_path / "weights" / "compact.pt")
    with pytest.raises(FileNotFoundError, match=r"bundled perception weights .*weights/compact.pt not found"):
        predict(view.rgb, meshes_of(assembly))


def test_bundled_weights_predict_an_upright_object(scene):
    assembly, view = scene
    prediction = predict(view.rgb, meshes_of(assembly))
    assert prediction.kind == "ours" and prediction.checkpoint == weights.BUNDLED_WEIGHTS.resolve()
    assert angle_deg(prediction.up.up_camera, view.camera_from_assembly.rotation[:, 2]) < 30.0


def test_bundled_elevation_head_reads_the_camera_from_the_picture(scene):
    """The bundled elevation head, on a table never trained on seen from four training cameras: the elevation
    within a few degrees; predict takes up from it, or from the parts when told not to."""
    from perception.elevation import image_elevation_deg

    assembly, view = scene
    errors = []
    for seed in range(4):
        other = render_assembly(assembly, np.random.default_rng([7, seed]))
        up = other.camera_from_assembly.rotation[:, 2]
        true_deg = float(np.degrees(np.arcsin(-up[2])))
        errors.append(abs(image_elevation_deg(other.rgb) - true_deg))
    assert np.median(errors) < 5.0, errors
    assert predict(view.rgb, meshes_of(assembly)).up.method == "image"
    assert predict(view.rgb, meshes_of(assembly), image_elevation=False).up.method != "image"
