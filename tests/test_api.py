"""The Python API (``cell.assemble``) and the ``image-assembly`` command: the documented example run as written,
bad input raised as typed errors with nothing written, each subcommand the same as its ``python -m`` form."""

import contextlib
import io
import json
import subprocess
import sys
import textwrap
import tomllib
from pathlib import Path

import numpy as np
import pytest

import cell
from cell.cli import COMMANDS
from cell.cli import main as cli_main
from planning.pose import Pose
from scenes import sample_folder

ROOT = Path(__file__).resolve().parent.parent


def api_example() -> str:
    """The example of ``cell``'s docstring (the README's), as code."""
    doc = cell.__doc__
    block = doc[doc.index("::\n") + 3:]
    lines = []
    for line in block.splitlines():
        if line.strip() and not line.startswith("    "):
            break
        lines.append(line)
    return textwrap.dedent("\n".join(lines)).strip() + "\n"


def test_the_documented_example_assembles_the_sample_chair(monkeypatch):
    """The example, run as written from the repository root (its paths are the README's): the bundled chair with
    its true poses is planned, simulated and verified."""
    code = api_example()
    assert len(code.splitlines()) == 5 and "cell.assemble(" in code
    monkeypatch.chdir(ROOT)
    namespace: dict = {}
    printed = io.StringIO()
    with contextlib.redirect_stdout(printed):
        exec(compile(code, "cell example", "exec"), namespace)
    result = namespace["result"]
    assert isinstance(result, cell.AssemblyResult)
    assert result.exit_code == 0 and result.success and result.failure is None, result.failure
    names = sorted(p.stem for p in (sample_folder("chair") / "parts").iterdir())
    assert sorted(result.order) == names and result.order[0].startswith("leg")
    assert result.target is not None and sorted(result.target.part_names) == names
    assert result.simulation.success and result.program.duration_s > 0
    assert result.report["exit_code"] == 0 and result.report["inputs"]["notes"] == []
    assert result.out is None  # no out=: nothing written
    lines = printed.getvalue().splitlines()
    assert lines[0] == "0 " + " > ".join(result.order)
    assert lines[1] == f"{result.program.duration_s:.0f} s robot program, simulated: True"


def _bad_calls(tmp: Path, chair: Path) -> dict:
    """case -> (keyword arguments of cell.assemble, the error class, words of its message)."""
    parts, poses = chair / "parts", chair / "assembly.json"
    truth = json.loads(poses.read_text())["parts"]
    given = {p["name"]: Pose(p["pose"]["position"], p["pose"]["quat_wxyz"]) for p in truth}
    (tmp / "random.pt").write_bytes(np.random.default_rng(0).bytes(4096))
    (tmp / "precious").mkdir()
    (tmp / "precious" / "thesis.tex").write_text("keep me")
    scene = tmp / "scene.toml"
    scene.write_text((ROOT / "scenes" / "cell.toml").read_text().replace("payload_kg = 3.0", "payload_kgg = 1.0"))
    sunk = dict(given, seat=Pose([0.0, 0.0, -0.3], [1.0, 0.0, 0.0, 0.0]))
    picture = np.zeros((224, 224, 3), dtype=np.uint8)
    return {
        "neither picture nor poses": ({"parts": parts}, cell.BadOption, "give image= (perception predicts"),
        "negative seed": ({"parts": parts, "poses": poses, "seed": -1}, cell.BadOption,
                          "seed=-1: give a whole number from 0 to 4294967295"),
        "unknown planner": ({"parts": parts, "poses": poses, "planner": "FooPlanner"}, cell.BadOption,
                            "planner='FooPlanner': not a planner this cell runs; choose one of RRTConnect"),
        "density in g/cm3": ({"parts": parts, "poses": poses, "density": 0.6}, cell.BadOption,
                             "density=0.6: give the parts' density in kg/m3"),
        "missing parts folder": ({"parts": tmp / "none", "poses": poses}, cell.BadParts,
                                 "parts folder does not exist"),
        "pose of no part": ({"parts": parts, "poses": dict(given, shelf=Pose.identity())}, cell.BadPoses,
                            "poses: pose(s) for shelf, which the parts folder does not hold"),
        "pose not a Pose": ({"parts": parts, "poses": dict(given, seat=[0, 0, 0])}, cell.BadPoses,
                            "poses: part 'seat': list is not a planning.pose.Pose"),
        "small picture array": ({"parts": parts, "image": picture[:100, :100]}, cell.BadPicture,
                                "image array 100x100: the image is only 100x100"),
        "checkpoint of random bytes": ({"parts": parts, "image": picture, "checkpoint": tmp / "random.pt"},
                                       cell.BadCheckpoint, "random.pt: not a perception model"),
        "mass of no part": ({"parts": parts, "poses": poses, "masses": {"shelf": 1.0}}, cell.BadMasses,
                            "masses: mass for 'shelf', which the parts folder does not hold"),
        "misspelled scene key": ({"parts": parts, "poses": poses, "scene": scene}, cell.BadScene,
                                 "[robot] has no key 'payload_kgg'"),
        "output folder of something else": ({"parts": parts, "poses": poses, "out": tmp / "precious"},
                                            cell.BadOutput, "does not hold an earlier run"),
        "part under the floor": ({"parts": parts, "poses": sunk}, cell.BadTarget,
                                 "poses given in memory: part 'seat' reaches"),
    }


def test_bad_input_raises_a_typed_error_and_writes_nothing(tmp_path):
    chair = sample_folder("chair")
    for case, (arguments, error, words) in _bad_calls(tmp_path, chair).items():
        arguments.setdefault("out", tmp_path / "out")
        with pytest.raises(error) as raised:
            cell.assemble(**arguments)
        assert isinstance(raised.value, cell.BadInput) and isinstance(raised.value, ValueError)
        assert words in str(raised.value), (case, str(raised.value))
        assert not (tmp_path / "out").exists(), case
        assert not [p for p in tmp_path.iterdir() if p.name.startswith(".out")], case
    assert (tmp_path / "precious" / "thesis.tex").read_text() == "keep me"


def test_the_command_prints_its_version_and_lists_its_subcommands():
    pyproject = tomllib.loads((ROOT / "pyproject.toml").read_text())
    assert pyproject["project"]["scripts"]["image-assembly"] == "cell.cli:main"
    shown = subprocess.run([sys.executable, "-m", "cell.cli", "--version"], capture_output=True, text=True,
                           cwd=ROOT, timeout=60)
    assert shown.returncode == 0 and shown.stdout == f"image-assembly {pyproject['project']['version']}\n"
    listed = subprocess.run([sys.executable, "-m", "cell.cli", "--help"], capture_output=True, text=True, cwd=ROOT,
                            timeout=60)
    assert listed.returncode == 0
    for name in ("run", "batch", "sequence", "synth", "render", "train", "evaluate"):
        assert f"  {name} " in listed.stdout
    assert cli_main(["assemble"]) == 2


def test_each_subcommand_runs_its_module(tmp_path, capsys):
    """``image-assembly synth ...`` writes what ``python -m perception.synth ...`` writes; ``image-assembly run``
    refuses what ``python -m cell.run`` refuses, with its exit code."""
    from perception.synth.__main__ import main as synth_main

    arguments = ["--category", "chair", "--level", "mixed", "--count", "1", "--seed", "3"]
    assert cli_main(["synth", *arguments, "--out", str(tmp_path / "a")]) == 0
    assert synth_main([*arguments, "--out", str(tmp_path / "b")]) == 0
    [a], [b] = (sorted((tmp_path / side).iterdir()) for side in "ab")
    assert a.name == b.name and (a / "assembly.json").read_bytes() == (b / "assembly.json").read_bytes()
    capsys.readouterr()
    with pytest.raises(SystemExit) as usage:
        cli_main(["run", "--parts", str(a / "parts")])
    assert usage.value.code == 2 and "give --image" in capsys.readouterr().err
    assert cli_main(["run", "--parts", str(tmp_path / "none"), "--poses", str(a / "assembly.json")]) == 2
    assert "parts folder does not exist" in capsys.readouterr().err
    assert set(COMMANDS) >= {"run", "batch", "sequence", "synth", "render", "train", "evaluate"}
