"""Procedural furniture generator (perception.synth): structure, geometry, contacts, determinism, CLI.

All checks use real geometry: contacts are measured with python-fcl, interpenetration with trimesh's signed
distance, independently of the generator's own joint list.
"""

from __future__ import annotations

import itertools
import subprocess
import sys
from collections import Counter
from pathlib import Path

import fcl
import networkx as nx
import numpy as np
import pytest
import trimesh

from perception.synth import CATEGORIES, LEVELS, generate
from perception.synth.cabinet import DRAWER_BACK_ROOM_M, DRAWER_SIDE_GAP_M
from perception.synth.chair import SLAT_GAP_M
from perception.synth.merge import assemblable
from planning.assembly import read_assembly, write_assembly
from planning.sequence import plan_assembly_sequence

REPO = Path(__file__).resolve().parents[1]
SEEDS = range(16)
TOUCH = 5e-4  # parts within 0.5 mm touch
PENETRATION = 5e-4  # no point of one part deeper than 0.5 mm inside another
GRIPPER = 0.07  # smallest oriented-bounding-box extent a Panda parallel gripper can take (8 cm opening)
MIN_THICKNESS = 0.005

_CACHE: dict[tuple[str, str, int], object] = {}


def _object(category: str, level: str, seed: int):
    key = (category, level, seed)
    if key not in _CACHE:
        _CACHE[key] = generate(
            category, level, np.random.default_rng([seed, 0]), f"{category}_{level}_{seed}"
        )
    return _CACHE[key]


def _world_meshes(assembly) -> list[trimesh.Trimesh]:
    return assembly.meshes_in_assembly_frame()


def _fcl_object(mesh: trimesh.Trimesh) -> fcl.CollisionObject:
    model = fcl.BVHModel()
    model.beginModel(len(mesh.vertices), len(mesh.faces))
    model.addSubModel(np.asarray(mesh.vertices, dtype=np.float64), np.asarray(mesh.faces, dtype=np.int32))
    model.endModel()
    return fcl.CollisionObject(model, fcl.Transform())


def _distances(meshes: list[trimesh.Trimesh]) -> dict[tuple[int, int], float]:
    """Distance between every pair of parts whose bounding boxes come within the touch tolerance."""
    objects = [_fcl_object(m) for m in meshes]
    bounds = [m.bounds for m in meshes]
    out = {}
    for i, j in itertools.combinations(range(len(meshes)), 2):
        if np.any(bounds[i][0] > bounds[j][1] + TOUCH) or np.any(bounds[j][0] > bounds[i][1] + TOUCH):
            continue
        result = fcl.DistanceResult()
        out[(i, j)] = max(0.0, fcl.distance(objects[i], objects[j], fcl.DistanceRequest(), result))
    return out


def _contact_graph(meshes: list[trimesh.Trimesh]) -> nx.Graph:
    graph = nx.Graph()
    graph.add_nodes_from(range(len(meshes)))
    graph.add_edges_from(pair for pair, d in _distances(meshes).items() if d <= TOUCH)
    return graph


def _max_penetration(meshes: list[trimesh.Trimesh], seed: int) -> tuple[float, str]:
    """Deepest point of any part inside any other (ordered pairs with overlapping bounding boxes)."""
    worst, where = 0.0, ""
    samples = []
    for k, mesh in enumerate(meshes):
        points, _ = trimesh.sample.sample_surface(mesh, 150, seed=seed * 1000 + k)
        samples.append(np.concatenate([points, mesh.vertices]))
    for i, j in itertools.permutations(range(len(meshes)), 2):
        bi, bj = meshes[i].bounds, meshes[j].bounds
        if np.any(bi[0] >= bj[1] - PENETRATION) or np.any(bj[0] >= bi[1] - PENETRATION):
            continue  # bounding boxes overlap by less than the tolerance: no deep point possible
        pts = samples[i]
        inside = np.all((pts > bj[0] + PENETRATION) & (pts < bj[1] - PENETRATION), axis=1)
        if not inside.any():
            continue
        depth = float(np.max(trimesh.proximity.signed_distance(meshes[j], pts[inside])))
        if depth > worst:
            worst, where = depth, f"{i} in {j}"
    return worst, where


# ---------------------------------------------------------------------------------------------------------
# structure
# ---------------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("level", LEVELS)
@pytest.mark.parametrize("category", CATEGORIES)
def test_structure_and_metadata(category, level):
    for seed in SEEDS:
        a = _object(category, level, seed)
        names = a.part_names
        assert 2 <= len(names) <= 20, (category, level, seed, len(names))
        assert len(set(names)) == len(names)
        meta = a.metadata
        assert meta["category"] == category and meta["level"] == level
        assert meta["generator"] == "perception.synth"
        assert isinstance(meta["variant"], dict) and meta["variant"]
        for key, value in meta["variant"].items():
            assert isinstance(key, str) and isinstance(value, (str, int, float)), (key, value)
        for pair in meta["joints"]:
            assert len(pair) == 2 and pair[0] in names and pair[1] in names and pair[0] != pair[1]
        if level == "mixed":
            level3 = _object(category, "3", seed)
            assert len(names) < len(level3.parts)
            assert meta["level3_part_count"] == len(level3.parts)
            members = sorted(m for group in meta["groups"].values() for m in group)
            assert members == sorted(level3.part_names)


@pytest.mark.parametrize("level", LEVELS)
@pytest.mark.parametrize("category", CATEGORIES)
def test_meshes_floor_centre_size(category, level):
    for seed in SEEDS:
        a = _object(category, level, seed)
        for part in a.parts:
            mesh = part.mesh
            assert mesh.is_watertight, (seed, part.name)
            assert mesh.volume > 0, (seed, part.name)
            extents = mesh.bounding_box_oriented.primitive.extents
            assert extents.min() >= MIN_THICKNESS - 1e-9, (seed, part.name, extents)
            # part frame centred at its bounding-box centre
            np.testing.assert_allclose(mesh.bounds.mean(axis=0), 0.0, atol=1e-9)
            if level == "3":
                assert extents.min() <= GRIPPER, (seed, part.name, extents)
        lo, hi = a.bounds()
        assert abs(lo[2]) <= 1e-6, (seed, lo)
        np.testing.assert_allclose(0.5 * (lo[:2] + hi[:2]), 0.0, atol=1e-6)
        assert 0.25 <= hi[2] <= 0.6, (seed, hi[2])
        assert np.all(hi[:2] - lo[:2] <= 0.62), (seed, hi - lo)


# ---------------------------------------------------------------------------------------------------------
# contacts
# ---------------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("level", LEVELS)
@pytest.mark.parametrize("category", CATEGORIES)
def test_contacts(category, level):
    for seed in SEEDS:
        a = _object(category, level, seed)
        meshes = _world_meshes(a)
        distances = _distances(meshes)
        graph = nx.Graph()
        graph.add_nodes_from(range(len(meshes)))
        graph.add_edges_from(pair for pair, d in distances.items() if d <= TOUCH)
        assert nx.is_connected(graph), (
            seed,
            [[a.part_names[i] for i in c] for c in nx.connected_components(graph)],
        )
        index = {n: i for i, n in enumerate(a.part_names)}
        for name_a, name_b in a.metadata["joints"]:
            i, j = sorted((index[name_a], index[name_b]))
            assert distances.get((i, j), np.inf) <= TOUCH, (seed, name_a, name_b, distances.get((i, j)))


@pytest.mark.parametrize("category", CATEGORIES)
def test_no_interpenetration(category):
    for seed in SEEDS:
        a = _object(category, "3", seed)
        depth, where = _max_penetration(_world_meshes(a), seed)
        assert depth <= PENETRATION, (seed, depth, where, a.part_names)


def test_checks_detect_faults():
    """The contact and penetration checks above do catch a part that floats or sinks by 3 mm."""
    table = next(
        t
        for t in (generate("table", "3", np.random.default_rng([s, 0]), "t") for s in range(100))
        if t.metadata["variant"]["base"] == "legs"
    )
    meshes = _world_meshes(table)
    top = table.part_names.index("top")
    assert nx.is_connected(_contact_graph(meshes)) and _max_penetration(meshes, 0)[0] <= PENETRATION
    raised = [m.copy() for m in meshes]
    raised[top].apply_translation([0.0, 0.0, 0.003])
    assert not nx.is_connected(_contact_graph(raised))
    sunk = [m.copy() for m in meshes]
    sunk[top].apply_translation([0.0, 0.0, -0.003])
    assert _max_penetration(sunk, 0)[0] > 0.002


def test_mixed_parts_are_merged_level3_parts():
    for category in CATEGORIES:
        for seed in SEEDS:
            level3, mixed = _object(category, "3", seed), _object(category, "mixed", seed)
            world3 = dict(zip(level3.part_names, _world_meshes(level3)))
            for name, mesh in zip(mixed.part_names, _world_meshes(mixed)):
                members = mixed.metadata["groups"][name]
                expected = np.concatenate([world3[m].vertices for m in members])
                np.testing.assert_allclose(mesh.vertices, expected, atol=1e-9)
                if len(members) > 1:
                    assert name.startswith("group_")
                    np.testing.assert_array_equal(mixed.part(name).assembly_from_part.quat_wxyz, [1, 0, 0, 0])


# ---------------------------------------------------------------------------------------------------------
# room for a robot hand, designed assembly order, assemblability
# ---------------------------------------------------------------------------------------------------------


def _bounds(assembly) -> dict[str, np.ndarray]:
    """World-frame axis-aligned bounds (2, 3) of every part."""
    out = {}
    for p in assembly.parts:
        world = p.assembly_from_part.apply(p.mesh.vertices)
        out[p.name] = np.stack([world.min(axis=0), world.max(axis=0)])
    return out


def test_cabinet_clearances():
    """Fingers fit where the hand must hold cabinet parts: beside and under drawers, behind drawer backs, under
    the top's edge, under the bottom's front edge; the interior hangs on the back until the sides go on."""
    eps = 1e-9
    seen: Counter = Counter()
    for seed in range(40):
        a = generate("cabinet", "3", np.random.default_rng([seed, 0]), "c")
        v, bb = a.metadata["variant"], _bounds(a)
        inner_left, inner_right = bb["side_left"][1, 0], bb["side_right"][0, 0]
        y_front, back_front = bb["side_left"][0, 1], bb["back"][0, 1]
        side_top = bb["side_left"][1, 2]
        fronts = [n for n in a.part_names if n.startswith("door") or (n.startswith("drawer") and n.endswith("_front"))]
        for k in range(1, v["drawers"] + 1):
            d = f"drawer_{k}"
            seen["drawer"] += 1
            assert bb[f"{d}_side_left"][0, 0] - inner_left >= DRAWER_SIDE_GAP_M - eps, (seed, d)
            assert inner_right - bb[f"{d}_side_right"][1, 0] >= DRAWER_SIDE_GAP_M - eps, (seed, d)
            assert bb[f"{d}_bottom"][0, 2] - bb[f"{d}_side_left"][0, 2] >= 0.03 - eps, (seed, d)
            assert back_front - bb[f"{d}_back"][1, 1] >= DRAWER_BACK_ROOM_M - eps, (seed, d)
            box_depth = bb[f"{d}_side_left"][1, 1] - bb[f"{d}_side_left"][0, 1]
            assert box_depth <= bb[f"{d}_bottom"][1, 0] - bb[f"{d}_bottom"][0, 0] + eps, (seed, d)
            if k < v["drawers"]:  # every drawer but the lowest stands on runners reaching the back
                seen["runners"] += 1
                for lr in ("left", "right"):
                    runner = bb[f"{d}_runner_{lr}"]
                    assert abs(runner[1, 1] - back_front) < 1e-6, (seed, d)
                    assert abs(runner[1, 2] - bb[f"{d}_side_left"][0, 2]) < 1e-6, (seed, d)
        for name in fronts:
            assert bb[name][0, 2] >= 0.015 - eps, (seed, name)  # clear of the floor
        front_face = min((bb[n][0, 1] for n in fronts), default=y_front)
        fronts_top = max((bb[n][1, 2] for n in fronts), default=-np.inf)
        if v["top"] == "overlay":
            seen["overlay"] += 1
            assert front_face - bb["top"][0, 1] >= 0.02 - eps, seed
            assert inner_left - bb["top"][0, 0] >= bb["side_left"][1, 0] - bb["side_left"][0, 0] + 0.02 - eps, seed
        else:
            seen["inset"] += 1
            assert bb["top"][0, 2] - fronts_top >= 0.034 - eps, seed
        assert bb["bottom"][1, 1] - bb["bottom"][0, 1] <= bb["bottom"][1, 0] - bb["bottom"][0, 0] + eps, seed
        if v["base"] == "plinth":
            seen["plinth"] += 1
            assert bb["plinth_front"][0, 1] - y_front >= 0.025 - eps, seed
        if "divider" in bb and (v["drawer_position"] == "bottom" or v["doors"]):
            seen["divider grip"] += 1
            below = [n for n in fronts if bb[n][1, 2] < bb["divider"][0, 2]]
            assert bb["divider"][0, 2] - max(bb[n][1, 2] for n in below) >= 0.034 - eps, seed
        assert bb["back"][1, 2] <= side_top - 0.002 + eps, seed
        doors = [n for n in fronts if n.startswith("door")]
        for shelf in [n for n in a.part_names if n.startswith("shelf") and doors]:
            door_top = bb[doors[0]][1, 2]
            assert bb[shelf][1, 2] <= door_top - 0.025 + eps or bb[shelf][0, 2] >= door_top, (seed, shelf)
        for name in [n for n in a.part_names if n.startswith(("shelf", "divider")) or "_runner_" in n]:
            assert abs(bb[name][1, 1] - back_front) < 1e-6, (seed, name)
    assert all(seen[k] > 0 for k in ("drawer", "runners", "overlay", "inset", "plinth", "divider grip")), seen


def test_chair_slats_leave_finger_room():
    """Seat slats and back slats stand SLAT_GAP_M or more apart, and as far from the rails and posts beside them."""
    seen: Counter = Counter()
    for seed in range(60):
        a = generate("chair", "3", np.random.default_rng([seed, 0]), "c")
        v, bb = a.metadata["variant"], _bounds(a)
        slats = sorted(n for n in a.part_names if n.startswith("seat_slat_"))
        if slats:  # across x, between the side rails
            spans = sorted((bb[n][0, 0], bb[n][1, 0]) for n in slats)
            edges = [bb["seat_rail_left"][1, 0], *(x for span in spans for x in span), bb["seat_rail_right"][0, 0]]
            assert np.diff(edges)[::2].min() >= SLAT_GAP_M - 1e-9, (seed, "seat")
            seen["seat"] += 1
        slats = sorted(n for n in a.part_names if n.startswith("back_slat_"))
        prefix = "leg_rear" if v["posts"] == "leg_extension" else "back_post"
        posts = [f"{prefix}_left", f"{prefix}_right"]
        if v["back"] == "vertical_slats":  # across x, between the posts
            spans = sorted((bb[n][0, 0], bb[n][1, 0]) for n in slats)
            edges = [bb[posts[0]][1, 0], *(x for span in spans for x in span), bb[posts[1]][0, 0]]
            assert np.diff(edges)[::2].min() >= SLAT_GAP_M - 1e-9, (seed, "vertical")
            seen["vertical"] += 1
        elif v["back"] == "horizontal_slats":  # along z, between the seat and the top rail
            spans = sorted((bb[n][0, 2], bb[n][1, 2]) for n in slats)
            edges = [v["seat_height"], *(z for span in spans for z in span), bb["back_top_rail"][0, 2]]
            assert np.diff(edges)[::2].min() >= SLAT_GAP_M - 1e-4, (seed, "horizontal")
            seen["horizontal"] += 1
    assert min(seen["seat"], seen["vertical"], seen["horizontal"]) > 0, seen


@pytest.mark.parametrize("category", ["chair", "cabinet"])
def test_stages_and_mixed_groups(category):
    """Level-3 chairs and cabinets record their designed assembly order; mixed groups never straddle another
    part's stage and never span more stages than the generator allows."""
    for seed in SEEDS:
        level3, mixed = _object(category, "3", seed), _object(category, "mixed", seed)
        stages = level3.metadata["stages"]
        span = level3.metadata.get("max_stage_span", np.inf)
        assert sorted(stages) == sorted(level3.part_names)
        assert "stages" not in mixed.metadata and "max_stage_span" not in mixed.metadata
        for members in mixed.metadata["groups"].values():
            lo, hi = min(stages[m] for m in members), max(stages[m] for m in members)
            assert hi - lo <= span, (seed, members)
            assert not any(lo < stages[n] < hi for n in level3.part_names if n not in members), (seed, members)


@pytest.mark.parametrize("category", CATEGORIES)
def test_mixed_merges_lock_no_part_in(category):
    for seed in range(8):
        mixed = _object(category, "mixed", seed)
        assert assemblable(mixed), (category, seed, mixed.metadata["groups"])


@pytest.mark.parametrize("level", LEVELS)
@pytest.mark.parametrize("category", CATEGORIES)
def test_panda_can_assemble(category, level):
    """The sequence planner (with the Panda hand's grasps) finds an assembly order for a handful of objects."""
    for seed in range(3):
        a = generate(category, level, np.random.default_rng([2468, seed]), f"{category}_{level}_{seed}")
        result = plan_assembly_sequence(a, seed=seed)
        assert result.success, (category, level, seed, a.metadata["variant"], result.reason, result.blocking)


# ---------------------------------------------------------------------------------------------------------
# identical parts, determinism, variety
# ---------------------------------------------------------------------------------------------------------


def test_interchangeable_parts_identical():
    chair_legs = tables_legs = 0
    for seed in range(30):
        a = generate("chair", "3", np.random.default_rng([seed, 0]), "c")
        legs = [p for p in a.parts if p.name in ("leg_front_left", "leg_front_right")]
        if len(legs) == 2:
            np.testing.assert_array_equal(legs[0].mesh.vertices, legs[1].mesh.vertices)
            chair_legs += 1
        slats = [p for p in a.parts if p.name.startswith("back_slat_")]
        for s in slats[1:]:
            np.testing.assert_array_equal(s.mesh.vertices, slats[0].mesh.vertices)
        t = generate("table", "3", np.random.default_rng([seed, 0]), "t")
        legs = [p for p in t.parts if p.name.startswith("leg_")]
        for leg in legs[1:]:
            np.testing.assert_array_equal(leg.mesh.vertices, legs[0].mesh.vertices)
        tables_legs += len(legs) > 1
    assert chair_legs > 0 and tables_legs > 0


@pytest.mark.parametrize("level", LEVELS)
@pytest.mark.parametrize("category", CATEGORIES)
def test_deterministic(category, level):
    for seed in (3, 11):
        a = generate(category, level, np.random.default_rng(seed), "x")
        b = generate(category, level, np.random.default_rng(seed), "x")
        assert a.part_names == b.part_names
        assert a.metadata == b.metadata
        for pa, pb in zip(a.parts, b.parts):
            np.testing.assert_array_equal(pa.mesh.vertices, pb.mesh.vertices)
            np.testing.assert_array_equal(pa.mesh.faces, pb.mesh.faces)
            np.testing.assert_array_equal(pa.assembly_from_part.position, pb.assembly_from_part.position)
            np.testing.assert_array_equal(pa.assembly_from_part.quat_wxyz, pb.assembly_from_part.quat_wxyz)


_MAIN_CHOICES = {
    "chair": ("legs", "seat", "back", "stretchers"),
    "table": ("top", "base", "legs", "stretchers"),
    "cabinet": ("base", "shelves", "doors", "drawers"),
}


@pytest.mark.parametrize("category", CATEGORIES)
def test_variety(category):
    variants = [
        generate(category, "3", np.random.default_rng([s, 0]), "v").metadata["variant"] for s in range(30)
    ]
    for key in _MAIN_CHOICES[category]:
        relevant = [v for v in variants if key != "legs" or v.get("base", "legs") == "legs"]
        values = Counter(v[key] for v in relevant)
        assert len(values) >= 3, (category, key, values)
    heights = [v["height"] for v in variants]
    assert max(heights) - min(heights) > 0.1


# ---------------------------------------------------------------------------------------------------------
# API, files, CLI
# ---------------------------------------------------------------------------------------------------------


def test_bad_arguments():
    rng = np.random.default_rng(0)
    with pytest.raises(ValueError, match="category"):
        generate("sofa", "3", rng, "x")
    with pytest.raises(ValueError, match="level"):
        generate("chair", "2", rng, "x")
    with pytest.raises(ValueError, match="Generator"):
        generate("chair", "3", 0, "x")


@pytest.mark.parametrize("level", LEVELS)
def test_round_trip(tmp_path, level):
    for category in CATEGORIES:
        a = generate(category, level, np.random.default_rng(7), f"{category}_rt")
        folder = write_assembly(a, tmp_path / f"{category}_{level}")
        b = read_assembly(folder)
        assert b.part_names == a.part_names
        assert b.metadata["variant"] == a.metadata["variant"]
        assert b.metadata["joints"] == a.metadata["joints"]
        for pa, pb in zip(a.parts, b.parts):
            np.testing.assert_allclose(pb.mesh.vertices, pa.mesh.vertices, atol=1e-6)
            np.testing.assert_array_equal(pb.mesh.faces, pa.mesh.faces)
            assert pb.assembly_from_part.is_close(
                pa.assembly_from_part, atol_position=1e-6, atol_angle_rad=1e-6
            )


def _cli(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "perception.synth", *args],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=120,
    )


def test_cli_writes_folders(tmp_path):
    out = tmp_path / "synth"
    result = _cli("--category", "table", "--level", "mixed", "--count", "3", "--seed", "5", "--out", str(out))
    assert result.returncode == 0, result.stderr
    folders = sorted(p.name for p in out.iterdir())
    assert folders == [f"table_mixed_s5_{i:05d}" for i in range(3)]
    for i, name in enumerate(folders):
        a = read_assembly(out / name)
        assert a.metadata["category"] == "table" and a.metadata["level"] == "mixed"
        # object i is the same whatever the count
        expected = generate("table", "mixed", np.random.default_rng([5, i]), name)
        assert a.part_names == expected.part_names
    # refuses to overwrite without --overwrite
    again = _cli("--category", "table", "--level", "mixed", "--count", "1", "--seed", "5", "--out", str(out))
    assert again.returncode != 0 and "overwrite" in again.stderr
    forced = _cli(
        "--category",
        "table",
        "--level",
        "mixed",
        "--count",
        "1",
        "--seed",
        "5",
        "--out",
        str(out),
        "--overwrite",
    )
    assert forced.returncode == 0, forced.stderr


def test_cli_bad_category(tmp_path):
    result = _cli("--category", "sofa", "--level", "3", "--count", "1", "--seed", "0", "--out", str(tmp_path))
    assert result.returncode == 2
    assert "sofa" in result.stderr
    result = _cli(
        "--category", "chair", "--level", "3", "--count", "0", "--seed", "0", "--out", str(tmp_path)
    )
    assert result.returncode == 2
