"""Training data: same seed same arrays, resumable, split by object, labels consistent with the images."""

import json
import subprocess
import sys

import numpy as np
import pytest

from perception.dataset import list_objects, load_object
from perception.dataset.build import BuildConfig, build, materials_of, object_path, split_of

CONFIG = BuildConfig(category="chair", level="3", count=10, views=2, seed=5)


@pytest.fixture(scope="module")
def built(tmp_path_factory):
    out = tmp_path_factory.mktemp("data") / "chairs"
    build(CONFIG, out, workers=2, progress=False)
    return out


def test_split_by_object(built):
    assert [split_of(i) for i in range(10)] == ["train"] * 8 + ["val", "test"]
    assert len(list_objects(built, "train")) == 8
    assert len(list_objects(built, "val")) == 1 and len(list_objects(built, "test")) == 1
    assert json.loads((built / "dataset.json").read_text())["seed"] == 5


def test_fields_are_consistent(built):
    sample = load_object(list_objects(built, "train")[0])
    n = len(sample["part_names"])
    assert 2 <= n <= 20
    assert sample["points_norm"].shape == (n, 1000, 3)
    assert sample["images"].shape == (2, 224, 224, 3) and sample["images"].dtype == np.uint8
    assert sample["part_labels"].shape == (2, 224, 224)
    assert sample["pose_quat_wxyz"].shape == (2, n, 4) and sample["pose_translation_norm"].shape == (2, n, 3)
    np.testing.assert_allclose(np.linalg.norm(sample["pose_quat_wxyz"], axis=-1), 1.0, atol=1e-5)
    # visibility counts are the mask sizes, and some part of the chair is seen in every view
    for k in range(2):
        counts = np.bincount(sample["part_labels"][k][sample["part_labels"][k] >= 0].astype(int), minlength=n)
        assert counts.tolist() == sample["visible_pixels"][k].tolist()
        assert counts.sum() > 1000
    # instance one-hots count up inside each class
    for c in np.unique(sample["equivalence_class"]):
        members = np.flatnonzero(sample["equivalence_class"] == c)
        assert sample["instance_onehot"][members].argmax(axis=1).tolist() == list(range(len(members)))


def test_same_seed_same_arrays_and_resume(built, tmp_path):
    # rebuild two objects in one process: identical to the two-worker build
    other = tmp_path / "again"
    build(BuildConfig("chair", "3", 2, 2, 5), other, workers=1, progress=False)
    for i in range(2):
        a, b = load_object(object_path(built, CONFIG, i)), load_object(object_path(other, CONFIG, i))
        assert a.keys() == b.keys()
        for key in a:
            assert np.array_equal(a[key], b[key]), key
    # resume: asking for more objects builds only the missing ones
    stats = build(BuildConfig("chair", "3", 3, 2, 5), other, workers=1, progress=False)
    assert stats["objects_built"] == 1
    # a different seed gives other objects
    third = tmp_path / "third"
    build(BuildConfig("chair", "3", 1, 2, 6), third, workers=1, progress=False)
    first_other_seed = load_object(list_objects(third, "train")[0])
    assert not np.array_equal(first_other_seed["images"], load_object(object_path(built, CONFIG, 0))["images"])


def test_cli_refuses_other_settings_in_same_folder(built):
    result = subprocess.run(
        [sys.executable, "-m", "perception.dataset", "build", "--category", "chair", "--level", "3", "--count", "1",
         "--views", "3", "--seed", "5", "--out", str(built)],
        capture_output=True, text=True,
    )
    assert result.returncode == 2
    assert "views: 2 there, 3 asked" in result.stderr
    assert "Traceback" not in result.stderr


def test_slim_copy_is_what_training_reads(built, tmp_path):
    """A slim copy keeps the train and val objects below --count, each cloud's first points as int8 with a
    per-part scale (read back within 1/254 of the part's largest coordinate), and every other array training
    reads unchanged; training runs on it."""
    from perception.data import ViewDataset, object_files
    from perception.train.cli import main as train_main

    slim = tmp_path / "slim"
    command = [sys.executable, "-m", "perception.dataset", "slim", str(built), "--points", "64", "--count", "9",
               "--out", str(slim)]
    result = subprocess.run(command, capture_output=True, text=True)
    assert result.returncode == 0, result.stderr
    assert len(list_objects(slim, "train")) == 8 and len(list_objects(slim, "val")) == 1
    assert not (slim / "test").exists()
    assert json.loads((slim / "dataset.json").read_text())["slim"]["points"] == 64
    stored = load_object(list_objects(slim, "train")[0])
    assert stored["points_norm"].dtype == np.int8 and stored["points_norm"].shape[1] == 64
    full, cut = ViewDataset(object_files([built], "train")), ViewDataset(object_files([slim], "train"))
    assert len(full) == len(cut) == 16
    for i in (0, 7, 15):
        a, b = full[i], cut[i]
        assert a["name"] == b["name"] and b["points"].dtype == np.float32
        scale = np.abs(a["points"][:, :64]).max(axis=(1, 2))
        assert np.all(np.abs(a["points"][:, :64] - b["points"]).max(axis=(1, 2)) <= scale / 254 + 1e-7)
        for key in ("image", "part_labels", "instance_onehot", "classes", "visible_pixels", "quat", "trans"):
            assert np.array_equal(a[key], b[key]), key
    # the same folder with other arguments is refused; a bad source names itself
    again = subprocess.run([*command[:-4], "--points", "32", "--out", str(slim)], capture_output=True, text=True)
    assert again.returncode == 2 and "other arguments" in again.stderr and "Traceback" not in again.stderr
    missing = subprocess.run([sys.executable, "-m", "perception.dataset", "slim", str(tmp_path / "none"),
                              "--points", "64", "--out", str(tmp_path / "x")], capture_output=True, text=True)
    assert missing.returncode == 2 and str(tmp_path / "none") in missing.stderr
    assert train_main(["--config", "tiny", "--data", str(slim), "--out", str(tmp_path / "run"), "--no-progress",
                       "--max-steps", "1"]) == 0


def test_parts_in_a_random_order_describe_the_same_object(built):
    """permute_parts moves every per-part array and the pixel labels with the part, renumbers the equivalence
    classes by first appearance and recounts the instance one-hots; the inverse order gives the sample back."""
    from perception.data import ViewDataset, object_files, permute_parts, shuffle_order

    original = ViewDataset(object_files([built], "train"))[0]
    n = len(original["points"])
    order = shuffle_order(n, seed=3, index=0)
    assert sorted(order) == list(range(n)) and not np.array_equal(order, np.arange(n))
    moved = permute_parts(original, order)
    for k, old in enumerate(order):
        assert np.array_equal(moved["points"][k], original["points"][old])
        assert np.array_equal(moved["quat"][k], original["quat"][old])
        assert np.array_equal(moved["trans"][k], original["trans"][old])
        assert moved["visible_pixels"][k] == original["visible_pixels"][old]
        assert np.array_equal(moved["part_labels"] == k, original["part_labels"] == old)
    assert np.array_equal(moved["part_labels"] == -1, original["part_labels"] == -1)
    # same grouping of parts, ids in order of first appearance, one-hot = index among its class
    same = moved["classes"][:, None] == moved["classes"][None, :]
    assert np.array_equal(same, (original["classes"][:, None] == original["classes"][None, :])[np.ix_(order, order)])
    _, first = np.unique(moved["classes"], return_index=True)
    assert np.all(np.diff(first) > 0)
    for k in range(n):
        assert moved["instance_onehot"][k].argmax() == int(np.sum(moved["classes"][:k] == moved["classes"][k]))
    back = permute_parts(moved, np.argsort(order))
    for key in ("points", "quat", "trans", "visible_pixels", "part_labels", "classes", "instance_onehot"):
        assert np.array_equal(back[key], original[key]), key
    with pytest.raises(ValueError, match="is not an order of its"):
        permute_parts(original, np.zeros(n, dtype=int))


def test_dataset_draws_a_part_order_per_sample_and_epoch(built):
    """Shuffled: the same order for the same sample and epoch (every run, every worker), another in another
    epoch; unshuffled: the files' order."""
    from perception.data import ViewDataset, object_files

    files = object_files([built], "train")
    plain = ViewDataset(files)
    shuffled, again = ViewDataset(files, shuffle_parts=True, seed=1), ViewDataset(files, shuffle_parts=True, seed=1)
    assert np.array_equal(plain[2]["points"], load_object(files[1])["points_norm"])  # 2 views per object

    def order_of(sample, reference):
        return [next(j for j in range(len(reference)) if np.array_equal(p, reference[j])) for p in sample]

    reference = plain[2]["points"]
    first = order_of(shuffled[2]["points"], reference)
    assert first == order_of(again[2]["points"], reference) and first != list(range(len(reference)))
    shuffled.set_epoch(1)
    assert order_of(shuffled[2]["points"], reference) != first


def test_stretched_build_changes_proportions_not_the_labels(tmp_path):
    """--stretch scales each object along its axes before rendering; the camera labels stay exact, so the
    truth up (assembly +z in the camera frame) is the same formula, and an older folder's dataset.json without
    the key still resumes."""
    plain, wide = BuildConfig("table", "3", 1, 1, 5), BuildConfig("table", "3", 1, 1, 5, stretch=2.0)
    build(plain, tmp_path / "plain", progress=False)
    build(wide, tmp_path / "wide", progress=False)
    a, b = (load_object(object_path(tmp_path / name, plain, 0)) for name in ("plain", "wide"))
    extent_a = np.ptp(a["assembly_from_part_position_m"], axis=0)
    extent_b = np.ptp(b["assembly_from_part_position_m"], axis=0)
    factors = extent_b / extent_a
    assert np.all(factors >= 0.5 - 1e-9) and np.all(factors <= 2.0 + 1e-9) and np.ptp(factors) > 0.05
    assert not np.array_equal(a["images"], b["images"])
    np.testing.assert_allclose(a["camera_from_assembly_quat_wxyz"], b["camera_from_assembly_quat_wxyz"], atol=1e-9)
    config_path = tmp_path / "plain" / "dataset.json"
    older = json.loads(config_path.read_text())
    del older["stretch"]
    config_path.write_text(json.dumps(older))
    assert build(plain, tmp_path / "plain", progress=False)["objects_built"] == 0
    with pytest.raises(ValueError, match="stretch: 1.0 there, 2.0 asked"):
        build(wide, tmp_path / "plain", progress=False)


def test_one_material_build_changes_the_colours_not_the_labels(tmp_path):
    """--materials one: the same views (camera, backdrop, light) with every part in one material; mixed draws
    each object's mode from its own seed."""
    coloured = BuildConfig("table", "3", 1, 1, 5)
    one = BuildConfig("table", "3", 1, 1, 5, materials="one")
    build(coloured, tmp_path / "coloured", progress=False)
    build(one, tmp_path / "one", progress=False)
    a, b = (load_object(object_path(tmp_path / name, coloured, 0)) for name in ("coloured", "one"))
    assert not np.array_equal(a["images"], b["images"])
    np.testing.assert_array_equal(a["part_labels"], b["part_labels"])
    np.testing.assert_array_equal(a["pose_translation_norm"], b["pose_translation_norm"])
    background = a["part_labels"][0] < 0
    np.testing.assert_array_equal(a["images"][0][background], b["images"][0][background])
    mixed = BuildConfig("table", "3", 40, 1, 5, materials="mixed")
    drawn = [materials_of(mixed, i) for i in range(40)]
    assert drawn == [materials_of(mixed, i) for i in range(40)] and set(drawn) == {"parts", "one", "few"}
