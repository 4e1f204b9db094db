"""Bundled samples: found from any working directory, valid, and rendered by the render command."""

import subprocess
import sys

import numpy as np
import pytest
from PIL import Image

from planning.assembly import read_assembly
from scenes import SAMPLE_CATEGORIES, sample_folder, sample_image


@pytest.mark.parametrize("category", SAMPLE_CATEGORIES)
def test_bundled_samples_are_valid_level3_objects(category):
    assembly = read_assembly(sample_folder(category))
    assert 2 <= len(assembly.parts) <= 20
    assert assembly.bounds()[0, 2] == pytest.approx(0.0, abs=1e-6)
    assert 0.25 <= assembly.bounds()[1, 2] <= 0.6
    image = np.asarray(Image.open(sample_image(category)))
    assert image.shape == (224, 224, 3)


def test_samples_found_from_another_working_directory(tmp_path):
    code = "from scenes import sample_folder; print(sample_folder('chair') / 'assembly.json')"
    out = subprocess.run([sys.executable, "-c", code], cwd=tmp_path, capture_output=True, text=True, check=True)
    assert out.stdout.strip().endswith("assembly.json")
    assert (sample_folder("chair") / "assembly.json").is_file()


def test_render_command(tmp_path):
    target = tmp_path / "view.png"
    result = subprocess.run([sys.executable, "-m", "cell.render", str(sample_folder("table")), "--masks",
                             "--out", str(target), "--seed", "3"], capture_output=True, text=True, cwd=tmp_path)
    assert result.returncode == 0, result.stderr
    assert Image.open(target).size == (448, 224)
    assert "pybullet build time" not in result.stdout + result.stderr
    assert "9 parts" in result.stdout


def test_render_command_names_a_bad_folder(tmp_path):
    result = subprocess.run([sys.executable, "-m", "cell.render", str(tmp_path / "nothing"), "--out",
                             str(tmp_path / "v.png")], capture_output=True, text=True)
    assert result.returncode == 2
    assert "nothing" in result.stderr and "does not exist" in result.stderr
    assert "Traceback" not in result.stderr
    assert not (tmp_path / "v.png").exists()
