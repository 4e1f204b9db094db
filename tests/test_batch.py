"""``python -m cell.batch``: real ``cell.run`` jobs on a local Dask cluster of two worker processes (the summary,
the JUnit file, the retry of a timed-out job, the resume), and every bad batch input refused before anything runs."""

import csv
import json
import subprocess
import sys
import xml.etree.ElementTree as ET
from pathlib import Path

import pytest
import trimesh

from cell.batch import main
from cell.batch_jobs import read_jobs
from planning.assembly import Assembly, AssemblyPart, write_assembly
from planning.pose import Pose


def _board(root: Path, name: str, size_m: tuple[float, float, float]) -> Path:
    """An assembly folder of one board lying flat (the smallest object the cell builds: one pick and place)."""
    board = AssemblyPart("board", trimesh.creation.box(size_m), Pose([0.0, 0.0, size_m[2] / 2], [1, 0, 0, 0]),
                         "parts/board.obj")
    return write_assembly(Assembly(name, [board]), root / name)


@pytest.fixture(scope="module")
def objects(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("objects")
    _board(root, "board", (0.2, 0.1, 0.02))
    _board(root, "plate", (0.15, 0.12, 0.02))
    return root


def _job_list(objects: Path) -> Path:
    """Two objects that build; one whose planning budget is spent at once (planning fails, a report is written);
    one whose parts are too heavy at the given density (bad input: nothing written); one killed by its timeout."""
    jobs = [{"assembly": "board"}, {"assembly": "plate"},
            {"assembly": "plate", "name": "rushed", "time_budget": 0.001},
            {"parts": "board/parts", "poses": "board/assembly.json", "name": "heavy", "density": 20000},
            {"assembly": "board", "name": "slow", "timeout": 1.5}]
    path = objects / "jobs.json"
    path.write_text(json.dumps(jobs))
    return path


def _batch(arguments: list[str]) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "cell.batch", *arguments], capture_output=True, text=True,
                          timeout=600)


@pytest.mark.slow
def test_a_batch_on_a_local_cluster_reports_each_object_and_resumes(objects, tmp_path):
    pytest.importorskip("distributed", reason='Dask distributed is not installed (pip install -e ".[cluster]")')
    out, junit = tmp_path / "batch", tmp_path / "junit.xml"
    arguments = [str(_job_list(objects)), "--out", str(out), "--workers", "2", "--junit", str(junit),
                 "--no-animation", "--seed", "0"]
    first = _batch(arguments)
    assert first.returncode == 1, first.stdout + first.stderr  # some objects did not succeed
    assert "on a local cluster of 2 worker processes" in first.stdout
    summary = json.loads((out / "summary.json").read_text())
    records = {r["name"]: r for r in summary["objects"]}
    assert list(records) == ["board", "plate", "rushed", "heavy", "slow"]  # the job list's order
    assert summary["counts"] == {"objects": 5, "passed": 2, "failure": 1, "error": 2, "skipped": 0}

    for name in ("board", "plate"):
        record = records[name]
        assert (record["status"], record["exit_code"], record["attempts"]) == ("success", 0, 1)
        report = json.loads((out / name / "report.json").read_text())
        assert report["success"] and report["inputs"]["seed"] == 0
        assert record["trajectory_duration_s"] == pytest.approx(report["trajectory_duration_s"], abs=1e-3)
        assert record["max_position_error_mm"] <= 5.0 and record["parts_within_tolerance"] == 1
        assert sorted(p.name for p in (out / name).iterdir()) == ["overview.png", "program.json", "report.json",
                                                                  "trajectory.csv", "trajectory.mcap"]  # no GIF
    rushed = records["rushed"]
    report = json.loads((out / "rushed" / "report.json").read_text())
    assert (rushed["status"], rushed["exit_code"]) == ("planning failed", 3)
    assert rushed["stage"] == report["failure"]["stage"] and rushed["message"] == report["failure"]["message"]
    assert "time budget" in rushed["message"]
    heavy = records["heavy"]
    assert (heavy["status"], heavy["exit_code"], heavy["out"], heavy["attempts"]) == ("bad input", 2, None, 1)
    assert "more than the Panda's rated payload" in heavy["message"]
    slow = records["slow"]
    assert (slow["status"], slow["exit_code"], slow["attempts"], slow["retried_after"]) == ("timeout", None, 2,
                                                                                           "timeout")
    # nothing of the failed jobs is left: no output folder, no half-written temporary folder
    assert sorted(p.name for p in out.iterdir()) == [".batch", "board", "plate", "rushed", "summary.csv",
                                                     "summary.json"]
    with open(out / "summary.csv", newline="") as handle:
        rows = list(csv.DictReader(handle))
    assert [(r["name"], r["status"], r["exit_code"]) for r in rows] == [
        ("board", "success", "0"), ("plate", "success", "0"), ("rushed", "planning failed", "3"),
        ("heavy", "bad input", "2"), ("slow", "timeout", "")]

    root = ET.parse(junit).getroot()
    suite = root.find("testsuite")
    assert {k: suite.get(k) for k in ("tests", "failures", "errors", "skipped")} == {
        "tests": "5", "failures": "1", "errors": "2", "skipped": "0"}
    cases = {case.get("name"): case for case in suite.iter("testcase")}
    assert list(cases) == ["board", "plate", "rushed", "heavy", "slow"]
    assert list(cases["board"]) == [cases["board"].find("system-out")]  # passed: no failure, no error
    failure = cases["rushed"].find("failure")
    assert failure.get("type") == "planning failed"
    assert failure.get("message").startswith(f"planning failed at {rushed['stage']}: ")
    assert cases["heavy"].find("error").get("type") == "bad input"
    assert "killed after 1.5 s" in cases["slow"].find("error").get("message")

    # the same command again: the complete jobs (same inputs) are not run again, the others are
    board_report = (out / "board" / "report.json").stat().st_mtime_ns
    second = _batch(arguments)
    assert second.returncode == 1, second.stdout + second.stderr
    assert "2 of 5 objects to run" in second.stdout and "3 complete before" in second.stdout
    first_records = records
    records = {r["name"]: r for r in json.loads((out / "summary.json").read_text())["objects"]}
    assert [records[n]["resumed"] for n in records] == [True, True, True, False, False]
    assert records["board"] == {**first_records["board"], "resumed": True}  # the record of the run that made it
    assert (out / "board" / "report.json").stat().st_mtime_ns == board_report
    assert records["slow"]["status"] == "timeout" and records["heavy"]["status"] == "bad input"

    # the same result as one cell.run of that object: byte-identical trajectory
    from cell.run import main as run_main

    direct = tmp_path / "direct"
    assert run_main(["--parts", str(objects / "board" / "parts"), "--poses", str(objects / "board" / "assembly.json"),
                     "--out", str(direct), "--no-animation", "--seed", "0", "--quiet"]) == 0
    assert (direct / "trajectory.csv").read_bytes() == (out / "board" / "trajectory.csv").read_bytes()


@pytest.mark.slow
def test_a_job_whose_worker_dies_is_reported_and_run_once_more(objects, tmp_path):
    """The worker process running a job is killed (as the kernel's OOM killer or a lost machine would): its
    cell.run process dies with it, the job is run once more on the restarted worker, and the record says why."""
    pytest.importorskip("distributed", reason='Dask distributed is not installed (pip install -e ".[cluster]")')
    import time

    import psutil

    out = tmp_path / "batch"
    batch = subprocess.Popen([sys.executable, "-m", "cell.batch", str(objects / "board"), "--out", str(out),
                              "--workers", "1", "--no-animation", "--seed", "0"], stdout=subprocess.PIPE,
                             stderr=subprocess.STDOUT, text=True)
    try:
        job, deadline = None, time.monotonic() + 120
        while job is None and time.monotonic() < deadline and batch.poll() is None:
            job = next((p for p in psutil.Process(batch.pid).children(recursive=True)
                        if "cell.run" in " ".join(p.cmdline())), None)
            time.sleep(0.2)
        assert job is not None, "no cell.run process started"
        worker = job.parent()
        worker.kill()
        job.wait(timeout=30)  # the job dies with its worker (no orphaned cell.run)
        output, _ = batch.communicate(timeout=300)
    finally:
        if batch.poll() is None:
            batch.kill()
    assert batch.returncode == 0, output
    assert "board: worker lost" in output and "running it once more" in output
    record = json.loads((out / "summary.json").read_text())["objects"][0]
    assert (record["status"], record["attempts"], record["retried_after"]) == ("success", 2, "worker lost")
    assert json.loads((out / "board" / "report.json").read_text())["success"]


# --- bad batch input: exit 2, the culprit named, nothing run ----------------------------------------------------


def _refused(arguments: list[str], capsys) -> str:
    assert main(arguments) == 2
    return capsys.readouterr().err


def test_a_missing_input_folder_is_named(tmp_path, capsys):
    pytest.importorskip("distributed")
    error = _refused([str(tmp_path / "nowhere"), "--out", str(tmp_path / "out")], capsys)
    assert f"{tmp_path / 'nowhere'}: no such folder or job list" in error
    assert not (tmp_path / "out").exists()


def test_a_job_list_with_an_unknown_key_or_a_bad_value_is_named(objects, tmp_path, capsys):
    pytest.importorskip("distributed")
    jobs = tmp_path / "jobs.json"
    jobs.write_text(json.dumps([{"assembly": str(objects / "board")}, {"assembly": str(objects / "plate"),
                                                                       "sed": 3}]))
    error = _refused([str(jobs), "--out", str(tmp_path / "out")], capsys)
    assert f"{jobs} job 2: unknown key 'sed'" in error
    table = tmp_path / "jobs.csv"
    table.write_text(f"assembly,seed\n{objects / 'board'},1\n{objects / 'plate'},one\n")
    assert f"{table} row 3: seed 'one': expected a whole number" in _refused([str(table)], capsys)
    table.write_text(f"parts,poses\n{objects / 'board' / 'parts'},{objects / 'board' / 'missing.json'}\n")
    assert f"{table} row 2: poses {objects / 'board' / 'missing.json'}: not found" in _refused([str(table)], capsys)
    table.write_text(f"assembly,planner,density\n{objects / 'board'},FooPlanner,600\n{objects / 'plate'},RRT,5\n")
    assert f"{table} row 2: planner='FooPlanner': not a planner" in _refused([str(table)], capsys)
    table.write_text(f"assembly,density\n{objects / 'plate'},5\n")
    assert f"{table} row 2: density=5.0: give the parts' density in kg/m3" in _refused([str(table)], capsys)
    assert not (tmp_path / "out").exists()


def test_two_jobs_with_one_output_folder_are_refused(objects, tmp_path, capsys):
    pytest.importorskip("distributed")
    error = _refused([str(objects / "board"), str(objects), "--out", str(tmp_path / "out")], capsys)
    assert "both write the output folder 'board'" in error


def test_without_dask_the_message_says_what_to_install(objects, monkeypatch, capsys):
    monkeypatch.setitem(sys.modules, "distributed", None)  # as if not installed: importing it raises ImportError
    assert 'pip install -e ".[cluster]"' in _refused([str(objects)], capsys)


def test_a_job_runs_again_when_an_input_file_changes(objects, tmp_path):
    """The fingerprint that a rerun compares covers the files' bytes and the options, not only their names."""
    folder = _board(tmp_path, "box", (0.2, 0.1, 0.02))
    before = read_jobs([folder])[0].fingerprint()
    assert read_jobs([folder])[0].fingerprint() == before
    assert read_jobs([folder], {"seed": 1})[0].fingerprint() != before
    mesh = folder / "parts" / "board.obj"
    mesh.write_text(mesh.read_text().replace("0.1", "0.1000001", 1))
    assert read_jobs([folder])[0].fingerprint() != before
