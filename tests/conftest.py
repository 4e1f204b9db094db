"""Fixtures shared by several test files."""

import pytest


@pytest.fixture(scope="session")
def tiny_checkpoint(tmp_path_factory):
    """A real perception network (tiny config), trained for two steps on four procedural chairs: weights for
    tests of the code paths around the network (its accuracy is not the point)."""
    from perception.dataset.build import BuildConfig, build
    from perception.train.checkpoint import MODEL
    from perception.train.cli import main as train_main

    root = tmp_path_factory.mktemp("tiny_model")
    build(BuildConfig(category="chair", level="3", count=4, views=1, seed=3), root / "data", progress=False)
    assert train_main(["--config", "tiny", "--data", str(root / "data"), "--out", str(root / "run"),
                       "--max-steps", "2", "--no-progress"]) == 0
    return root / "run" / MODEL


@pytest.fixture
def tray():
    """An upturned tray (metres): a top lying on four walls flush under its edges. Standing, the top comes last,
    from above, and the walls leave a parallel-jaw hand no edge to hold it by."""
    import trimesh

    from planning.assembly import Assembly, AssemblyPart
    from planning.pose import Pose

    length, width, thick, height = 0.30, 0.20, 0.018, 0.10
    boards = {"top": ((length, width, thick), (0.0, 0.0, height + thick / 2)),
              "long_left": ((length, thick, height), (0.0, -(width - thick) / 2, height / 2)),
              "long_right": ((length, thick, height), (0.0, (width - thick) / 2, height / 2)),
              "end_front": ((thick, width - 2 * thick, height), (-(length - thick) / 2, 0.0, height / 2)),
              "end_back": ((thick, width - 2 * thick, height), ((length - thick) / 2, 0.0, height / 2))}
    return Assembly("tray", [AssemblyPart(name, trimesh.creation.box(size), Pose(centre, [1, 0, 0, 0]),
                                          f"parts/{name}.obj") for name, (size, centre) in boards.items()])
