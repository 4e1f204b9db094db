"""Speed of ``RobotCollisionChecker``: one configuration at a time and in batches, on a cell-like world.

    python -m benchmarks.collision_check [--configurations 3000] [--baseline OLD_robot_collision.py]

World: the table of ``scenes/cell.toml``, a procedural level-3 chair (``default_rng([0, 0])``) on the jig at the
scene's ``world_from_assembly`` with its fixture pads and its first half of parts placed. Configurations: the
scene's home configuration plus Gaussian noise (0.4 rad per joint, seeded, clipped to the joint limits), about
three quarters of them free. ``--baseline`` times another version of ``planning/robot_collision.py`` (e.g. from
``git show eae0a2e:planning/robot_collision.py > /tmp/old.py``) on the same configurations and checks that both
give the same answers. Wall and CPU time per configuration (the machine may be shared).
"""

from __future__ import annotations

import argparse
import importlib.util
import os
import platform
import sys
import time

import numpy as np
import trimesh

from cell.scene import load_scene
from perception.synth import generate
from planning.collision import ConvexPart
from planning.fixture import fixture_pads
from planning.robot_collision import RobotCollisionChecker

LOWER = np.array([-2.9, -1.8, -2.9, -3.0, -2.9, 0.0, -2.9])  # inside panda.urdf's limits, rad
UPPER = np.array([2.9, 1.8, 2.9, -0.1, 2.9, 3.7, 2.9])


def cell_world() -> dict[str, tuple[ConvexPart, np.ndarray]]:
    """name -> (ConvexPart, world_from_part 4x4): table, pads and half of a chair on the jig."""
    scene = load_scene()
    table = scene.table
    world_from_table = np.eye(4)
    world_from_table[:3, 3] = [table.centre_xy[0], table.centre_xy[1], table.top_z - table.size[2] / 2]
    world = {"table": (ConvexPart.from_mesh("table", trimesh.creation.box(table.size)), world_from_table)}
    assembly = generate("chair", "3", np.random.default_rng([0, 0]), "chair")
    world_from_assembly = scene.fixture.world_from_assembly.matrix()
    posed = [p.mesh.copy().apply_transform(p.assembly_from_part.matrix()) for p in assembly.parts]
    for pad in fixture_pads([p.name for p in assembly.parts], posed):
        world[f"pad {pad.part}"] = (ConvexPart.from_mesh("pad", pad.mesh()),
                                    world_from_assembly @ pad.assembly_from_pad.matrix())
    for part in assembly.parts[: len(assembly.parts) // 2]:
        world[part.name] = (ConvexPart.from_mesh(part.name, part.mesh),
                            world_from_assembly @ part.assembly_from_part.matrix())
    return world


def per_configuration_us(function, items) -> tuple[float, float]:
    start, cpu = time.perf_counter(), time.process_time()
    for item in items:
        function(item)
    return ((time.perf_counter() - start) / len(items) * 1e6, (time.process_time() - cpu) / len(items) * 1e6)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--configurations", type=int, default=3000)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--baseline", help="another robot_collision.py to time on the same configurations")
    args = parser.parse_args(argv)
    world = cell_world()
    rng = np.random.default_rng(args.seed)
    home = np.array(load_scene().robot.home_q)
    configurations = np.clip(home + rng.normal(scale=0.4, size=(args.configurations, 7)), LOWER, UPPER)
    checker = RobotCollisionChecker(np.eye(4), world)
    answers = [checker.is_valid(q) for q in configurations]
    print(f"machine: {platform.machine()}, {os.cpu_count()} cores, Python {platform.python_version()}; world: "
          f"{len(world)} obstacles ({len(checker.world_objects)} convex pieces); {len(configurations)} configurations, "
          f"{np.mean(answers):.0%} free\n")
    print("| checker | call | us per configuration (wall) | us per configuration (CPU) |\n|---|---|---|---|")
    if args.baseline:
        spec = importlib.util.spec_from_file_location("baseline_robot_collision", args.baseline)
        module = importlib.util.module_from_spec(spec)
        sys.modules[spec.name] = module
        spec.loader.exec_module(module)
        baseline = module.RobotCollisionChecker(np.eye(4), world)
        if [baseline.is_valid(q) for q in configurations] != answers:
            raise SystemExit("the baseline gives different answers")
        wall, cpu = per_configuration_us(baseline.is_valid, configurations)
        print(f"| baseline ({args.baseline}) | is_valid | {wall:.0f} | {cpu:.0f} |")
    wall, cpu = per_configuration_us(checker.is_valid, configurations)
    print(f"| current | is_valid | {wall:.0f} | {cpu:.0f} |")
    free = configurations[np.array(answers)]
    batches = [free[k:k + 64] for k in range(0, len(free), 64)]
    wall, cpu = per_configuration_us(checker.first_invalid, batches)
    print(f"| current | first_invalid, batches of 64 free configurations | {wall * len(batches) / len(free):.1f} | "
          f"{cpu * len(batches) / len(free):.1f} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
