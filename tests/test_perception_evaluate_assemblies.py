"""``python -m perception.evaluate --assemblies``: render assembly folders on the fly, score, write JSON."""

import json
import subprocess
import sys

import numpy as np
import pytest

from perception.evaluate import main as evaluate_main
from perception.evaluate_assemblies import assembly_folders, evaluate_assemblies
from perception.synth import generate
from perception.weights import load_for_inference
from planning.assembly import write_assembly


@pytest.fixture(scope="module")
def checkpoint(tiny_checkpoint):
    return tiny_checkpoint


@pytest.fixture(scope="module")
def folder(tmp_path_factory):
    """Two small procedural objects (seeds never trained on) as assembly folders, and a stray file."""
    root = tmp_path_factory.mktemp("assemblies")
    for i, category in enumerate(("table", "cabinet")):
        write_assembly(generate(category, "mixed", np.random.default_rng([1000, i]), f"{category}_{i}"),
                       root / f"{category}_{i}")
    (root / "README.md").write_text("not an assembly\n")
    return root


def test_cli_writes_part_accuracy_and_the_extra_figures(checkpoint, folder, tmp_path):
    report = tmp_path / "eval.json"
    result = subprocess.run(
        [sys.executable, "-m", "perception.evaluate", "--assemblies", str(folder), "--views", "2", "--seed", "4",
         "--checkpoint", str(checkpoint), "--json", str(report), "--no-progress"], capture_output=True, text=True)
    assert result.returncode == 0, result.stderr
    for heading in ("Part Acc.", "Shape Chamfer", "PA visible", "PA invisible", "Ours + repair", "up-axis error",
                    "connectivity", "CPU inference per object"):
        assert heading in result.stdout
    figures = json.loads(report.read_text())
    assert 0.0 <= figures["part_accuracy"] <= 1.0
    assert figures["objects"] == 2 and figures["samples"] == 4 and figures["views"] == 2
    assert figures["connectivity"]["truth"] == 1.0  # designed objects touch where they join
    assert figures["connectivity"]["truth_grounded"] == 1.0  # and every part has a path to the floor
    assert 0.0 <= figures["connectivity"]["repaired_grounded"] <= 1.0
    assert "every part on a path to the floor" in result.stdout
    assert 0.0 <= figures["after_repair"]["part_accuracy"] <= 1.0
    assert 0.0 <= figures["up_error_deg"]["mean"] <= 90.0 and figures["inference_s"]["mean"] > 0
    assert figures["peak_memory_mb"] > 0 and len(figures["per_object"]) == 4
    assert "parts still crossing after repair" in result.stdout
    assert "right objects (every part passes PA)" in result.stdout
    right = np.mean([o["part_accuracy"] == 1.0 for o in figures["per_object"]])
    assert figures["right_object_rate"] == pytest.approx(right)
    # the share of crossing views is the per-view deepest overlaps over the threshold, counted
    overlaps = [o["deepest_overlap_after"] for o in figures["per_object"]]
    crossing = [o for o in overlaps if o is not None and o["depth_m"] > figures["crossing_after_repair"]["threshold_m"]]
    assert figures["crossing_after_repair"]["views"] == pytest.approx(len(crossing) / 4)
    crossing_names = {o["name"] for o in figures["per_object"] if o["deepest_overlap_after"] in crossing}
    for key, views in (("part_accuracy_crossing", [o for o in figures["per_object"] if o["name"] in crossing_names]),
                       ("part_accuracy_other", [o for o in figures["per_object"] if o["name"] not in crossing_names])):
        expected = np.mean([o["part_accuracy"] for o in views]) if views else None
        assert (np.isnan(figures["crossing_after_repair"][key]) if expected is None
                else figures["crossing_after_repair"][key] == pytest.approx(expected))
    assert all(len(o["parts"]) == 2 and o["depth_m"] > 0 and isinstance(o["equivalent"], bool)
               for o in overlaps if o is not None)


def test_same_seed_gives_the_same_figures(checkpoint, folder):
    model, config, _, _ = load_for_inference(checkpoint)
    a = evaluate_assemblies(model, folder, views=1, seed=7, repair=False)
    b = evaluate_assemblies(model, folder, views=1, seed=7, repair=False)
    assert a["part_accuracy"] == b["part_accuracy"] and a["shape_chamfer"] == b["shape_chamfer"]
    assert "after_repair" not in a


def test_bad_arguments_exit_2_naming_the_value(checkpoint, folder, tmp_path, capsys):
    assert evaluate_main(["--assemblies", str(tmp_path / "none"), "--checkpoint", str(checkpoint)]) == 2
    assert "none not found" in capsys.readouterr().err
    assert evaluate_main(["--assemblies", str(folder), "--checkpoint", str(checkpoint), "--model", "b_gru"]) == 2
    assert "holds model 'ours', not 'b_gru'" in capsys.readouterr().err
    assert evaluate_main(["--assemblies", str(folder), "--checkpoint", str(tmp_path / "missing.pt")]) == 2
    assert "missing.pt not found" in capsys.readouterr().err
    with pytest.raises(FileNotFoundError, match="no assembly folders"):
        assembly_folders(tmp_path)


def test_parts_reach_the_network_in_a_random_order(checkpoint, folder):
    """Each object's parts are reordered by its own seeded draw (names and poses kept), and --keep-part-order
    gives the network the order of assembly.json instead."""
    from perception.evaluate_assemblies import shuffled_parts
    from planning.assembly import read_assembly

    assembly = read_assembly(assembly_folders(folder)[0])
    orders = [shuffled_parts(assembly, seed, 0).part_names for seed in (0, 1, 2)]
    assert orders[0] == shuffled_parts(assembly, 0, 0).part_names
    assert all(sorted(order) == sorted(assembly.part_names) for order in orders)
    assert any(order != assembly.part_names for order in orders)
    moved = shuffled_parts(assembly, 0, 0)
    for part in moved.parts:
        assert part.assembly_from_part is assembly.part(part.name).assembly_from_part
    model, _, _, _ = load_for_inference(checkpoint)
    kept = evaluate_assemblies(model, folder, views=1, seed=7, repair=False, shuffle_parts=False)
    shuffled = evaluate_assemblies(model, folder, views=1, seed=7, repair=False)
    assert kept["parts"] == shuffled["parts"] and kept["samples"] == shuffled["samples"] == 2


def test_grounded_needs_every_part_on_a_path_to_the_floor():
    """The sample table as designed stands; its top lifted 5 cm touches nothing that leads to the floor."""
    from perception.evaluate_assemblies import grounded
    from planning.assembly import read_assembly
    from planning.collision import ConvexPart
    from planning.contact import contact_graph
    from planning.pose import Pose
    from scenes import sample_folder

    table = read_assembly(sample_folder("table"))
    convex = [ConvexPart.from_mesh(p.name, p.mesh) for p in table.parts]
    poses = [p.assembly_from_part for p in table.parts]
    assert grounded(contact_graph(convex, poses))
    top = max(range(len(poses)), key=lambda k: float(poses[k].apply(table.parts[k].mesh.vertices)[:, 2].max()))
    lifted = list(poses)
    lifted[top] = Pose(poses[top].position + [0.0, 0.0, 0.05], poses[top].quat_wxyz)
    assert not grounded(contact_graph(convex, lifted))


def test_an_unreadable_object_is_reported_and_the_rest_evaluated(checkpoint, folder, tmp_path):
    import shutil

    root = tmp_path / "assemblies"
    shutil.copytree(folder, root)
    broken = root / "broken_0"
    broken.mkdir()
    (broken / "assembly.json").write_text("{not json")
    model, *_ = load_for_inference(checkpoint)
    figures = evaluate_assemblies(model, root, views=1, seed=7, repair=False)
    assert figures["objects"] == 2 and len(figures["per_object"]) == 2
    assert [u["name"] for u in figures["unreadable"]] == ["broken_0"] and "assembly.json" in figures["unreadable"][0][
        "error"]


def test_the_solver_and_one_material_pictures_are_reported(checkpoint, folder, tmp_path):
    """--solver adds the ablation (network, + repair, + solver, + solver and repair) under after_solver, each with
    its Part Accuracy and right-object rate, and per object part_accuracy_solved; --materials one renders the
    same views with one shared material and says so in the JSON."""
    report = tmp_path / "eval.json"
    result = subprocess.run(
        [sys.executable, "-m", "perception.evaluate", "--assemblies", str(folder), "--seed", "4", "--solver",
         "--materials", "one", "--checkpoint", str(checkpoint), "--json", str(report), "--no-progress"],
        capture_output=True, text=True)
    assert result.returncode == 0, result.stderr
    assert "picture solver" in result.stdout
    figures = json.loads(report.read_text())
    assert figures["materials"] == "one"
    solver = figures["after_solver"]
    assert solver["views"] == 2 and set(solver["stages"]) == {"network", "repair", "solver", "solver_repair"}
    assert solver["stages"]["network"]["part_accuracy"] == pytest.approx(figures["part_accuracy"])
    assert solver["stages"]["repair"]["part_accuracy"] == pytest.approx(figures["after_repair"]["part_accuracy"])
    assert solver["part_accuracy"] == solver["stages"]["solver_repair"]["part_accuracy"]
    objects = figures["per_object"]
    right = np.mean([o["part_accuracy_solved"] == 1.0 for o in objects])
    assert solver["right_object_rate"] == pytest.approx(right)
    assert all(0.0 <= o["part_accuracy_solved"] <= 1.0 and o["solver"]["seconds"] > 0 for o in objects)
