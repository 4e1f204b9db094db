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
