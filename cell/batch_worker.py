"""One job of ``python -m cell.batch`` on a Dask worker: ``python -m cell.run`` in its own process (PyBullet and
OMPL state stay in it), killed past its timeout or when the batch stops, leaving nothing half written."""

from __future__ import annotations

import ctypes
import os
import re
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

from cell.errors import EXIT_DISAGREES, EXIT_OK, EXIT_PLANNING, EXIT_SIMULATION

POLL_S = 1.0  # how often a running job looks at the clock and the stop signal
# the cell.run exits that write a complete output folder
REPORTED_EXITS = (EXIT_OK, EXIT_PLANNING, EXIT_SIMULATION, EXIT_DISAGREES)
PACKAGE_ROOT = Path(__file__).resolve().parents[1]  # where the job's cell.run imports this same code from


def _die_with_parent_setup():
    """A function for ``Popen(preexec_fn=...)`` that has Linux kill the job when the worker thread that
    started it dies (the worker killed or lost), so that no job outlives its worker; None elsewhere."""
    if not sys.platform.startswith("linux"):
        return None
    prctl, set_parent_death_signal = ctypes.CDLL(None, use_errno=True).prctl, 1  # PR_SET_PDEATHSIG
    return lambda: prctl(set_parent_death_signal, int(signal.SIGKILL))


def run_job(arguments: list[str], out: str, timeout_s: float | None, stop_name: str) -> dict:
    """Run ``python -m cell.run ARGUMENTS --out OUT --quiet`` in its own process (on a Dask worker); kill it past
    ``timeout_s`` or when the batch's stop event ``stop_name`` is set. Returns ``outcome`` ("finished",
    "timeout", "stopped"), ``exit_code`` (None unless finished), ``wall_s`` and ``log`` (its output)."""
    from distributed import Event

    stop = Event(stop_name)
    if stop.is_set():
        return {"outcome": "stopped", "exit_code": None, "wall_s": None, "log": ""}
    folder = Path(out)
    command = [sys.executable, "-m", "cell.run", *arguments, "--out", str(folder), "--quiet"]
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(p for p in (str(PACKAGE_ROOT), os.environ.get("PYTHONPATH"))
                                                       if p)}
    started = time.perf_counter()
    process = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL,
                               text=True, env=env, cwd=folder.parent, start_new_session=True,
                               preexec_fn=_die_with_parent_setup())
    outcome = "finished"
    while True:
        try:
            log, _ = process.communicate(timeout=POLL_S)
            break
        except subprocess.TimeoutExpired:
            if timeout_s is not None and time.perf_counter() - started > timeout_s:
                outcome = "timeout"
            elif _is_set(stop):
                outcome = "stopped"
            else:
                continue
            log = _end(process)
            if process.returncode in REPORTED_EXITS:  # it had finished by itself, its output complete
                outcome = "finished"
            break
    wall_s = time.perf_counter() - started
    if outcome != "finished" or process.returncode not in REPORTED_EXITS:
        remove_partial(folder)
    return {"outcome": outcome, "exit_code": process.returncode if outcome == "finished" else None,
            "wall_s": wall_s, "log": log}


def _is_set(stop) -> bool:
    try:
        return stop.is_set()
    except Exception:  # the scheduler is unreachable: the worker is going away, and the job with it
        return False


def _end(process: subprocess.Popen) -> str:
    """Kill ``process`` (not Ctrl-C: an interrupt can land where a library swallows it and the run goes on); what
    it was writing is left to :func:`remove_partial`. Its output so far."""
    process.kill()
    log, _ = process.communicate()
    return log


def remove_partial(folder: Path) -> None:
    """Remove what a killed ``cell.run --out FOLDER`` left half written: its temporary siblings
    (``planning.assembly.replacing_folder``: ``.<name>.<8 random characters>``)."""
    pattern = re.compile(rf"\.{re.escape(folder.name)}\.[a-z0-9_]{{8}}")
    if folder.parent.is_dir():
        for path in folder.parent.iterdir():
            if pattern.fullmatch(path.name) and path.is_dir():
                shutil.rmtree(path, ignore_errors=True)


__all__ = ["POLL_S", "REPORTED_EXITS", "remove_partial", "run_job"]
