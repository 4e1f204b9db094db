"""``python -m cell.batch``: many objects at once, each one ``python -m cell.run`` in its own process, on a Dask
cluster: a local one of ``--workers`` processes, or an existing one (``--scheduler tcp://host:8786``).

    python -m cell.batch ../furniture --out out/batch --workers 2 --no-animation --junit out/batch/junit.xml
    python -m cell.batch jobs.csv --scheduler tcp://head-node:8786 --timeout 1200

INPUT is an assembly folder (``parts/`` and ``assembly.json``), a folder of them, or a job list (``.csv`` or
``.json``; keys in ``cell/batch_jobs.py``: parts, poses or image, options). The options given here (``--seed``,
``--no-animation``, ...) apply to every job whose list gives no value. Each job writes ``OUT/<name>/`` exactly as
``cell.run`` does (complete or absent); ``OUT/summary.csv`` and ``OUT/summary.json`` (rewritten as each job ends)
hold every object's exit code, stage, failure, times and errors; ``--junit FILE`` writes one test case per object.
``OUT/.batch/`` keeps each job's log and the fingerprint of its inputs.

A rerun skips each job whose output folder is complete (its report.json written from the same inputs and
options; ``--rerun`` runs them all again). A job that crashes, runs past ``--timeout`` (its process is killed) or
loses its worker is run once more, then reported as such; a failed job leaves no output folder. Ctrl-C stops the
running jobs, writes the summary and says what finished; the same command goes on with the rest.

Exit codes: 0 every object succeeded, 1 at least one did not (the summary says which and why), 2 bad batch input
(nothing run), 130 interrupted.
"""

from __future__ import annotations

import argparse
import itertools
import json
import os
import shutil
import signal
import sys
import time
from pathlib import Path

from cell.batch_jobs import RUN_OPTIONS, BatchInputError, Job, read_jobs
from cell.batch_report import FIELDS, STATUSES, progress_line, summary_table, write_junit, write_summary
from cell.batch_worker import REPORTED_EXITS, remove_partial, run_job

EXIT_ALL_SUCCEEDED, EXIT_SOME_FAILED, EXIT_BAD_INPUT, EXIT_INTERRUPTED = 0, 1, 2, 130
DEFAULT_TIMEOUT_S = 1800.0
SCHEDULER_TIMEOUT_S = 30.0  # to reach an existing cluster's scheduler
STOP_WAIT_S = 15.0  # after Ctrl-C, for the running jobs to be stopped and say so
STATE_FOLDER = ".batch"  # under --out: <name>.json (fingerprint and record), <name>.log (the job's output)
STATUS_OF_EXIT = {0: "success", 1: "internal error", 2: "bad input", 3: "planning failed", 4: "simulation failed",
                  5: "disagrees with picture"}
INSTALL_HINT = 'pip install -e ".[cluster]"'


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(prog="python -m cell.batch", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("inputs", type=Path, nargs="+", metavar="INPUT",
                        help="assembly folder, folder of assembly folders, or job list (.csv or .json)")
    parser.add_argument("--out", type=Path, default=Path("out/batch"), help="output folder (default out/batch)")
    parser.add_argument("--workers", type=int, help="local cluster: worker processes, one job each at a time "
                        "(default: the cores)")
    parser.add_argument("--scheduler", metavar="ADDRESS", help="an existing Dask cluster's scheduler "
                        "(tcp://host:8786, or its scheduler file, a .json) instead of a local cluster; its workers "
                        "must see the same paths")
    parser.add_argument("--junit", type=Path, metavar="FILE", help="write a JUnit XML report: one test case per object")
    parser.add_argument("--timeout", type=float, default=DEFAULT_TIMEOUT_S, metavar="S",
                        help=f"seconds before a job's process is killed (default {DEFAULT_TIMEOUT_S:.0f})")
    parser.add_argument("--rerun", action="store_true", help="run every job again, even those already complete")
    defaults = parser.add_argument_group("cell.run options for every job (a job list's own value wins)")
    for key, option in RUN_OPTIONS.items():
        if option.kind in ("switch", "flag"):  # given: the job's value is false (a switch) or true (a flag)
            value = option.kind == "flag"
            defaults.add_argument(option.flag, dest=key, action="store_true" if value else "store_false",
                                  default=None, help=f"{option.flag.removeprefix('--').replace('-', ' ')} ({key} "
                                  f"{str(value).lower()})")
        else:
            kind = {"int": int, "float": float, "path": Path}.get(option.kind, str)
            defaults.add_argument(option.flag, dest=key, type=kind, help=option.help,
                                  choices=["m", "cm", "mm"] if option.kind == "units" else None)
    args = parser.parse_args(argv)
    if args.workers is not None and args.scheduler:
        parser.error("--workers sizes the local cluster; an existing cluster (--scheduler) has its own workers")
    if args.workers is not None and args.workers < 1:
        parser.error(f"--workers {args.workers}: give 1 or more")
    if not args.timeout > 0:
        parser.error(f"--timeout {args.timeout:g}: give a number of seconds above 0")
    return args


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    try:
        import distributed  # noqa: F401
    except ImportError:
        print(f"error: python -m cell.batch runs its jobs on Dask distributed, which is not installed: "
              f"{INSTALL_HINT} (or pip install \"dask[distributed]\")", file=sys.stderr)
        return EXIT_BAD_INPUT
    defaults = {key: getattr(args, key) for key in RUN_OPTIONS}
    defaults = {k: v.resolve() if isinstance(v, Path) else v for k, v in defaults.items()}
    try:
        jobs = read_jobs(args.inputs, defaults, args.timeout)
        _check_out(args.out, args.junit)
    except BatchInputError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return EXIT_BAD_INPUT
    return run_batch(jobs, args.out.resolve(), args.workers, args.scheduler, args.junit, args.rerun)


def _check_out(out: Path, junit: Path | None) -> None:
    if out.exists() and not out.is_dir():
        raise BatchInputError(f"--out {out}: a file, not a folder")
    if junit is not None and junit.is_dir():
        raise BatchInputError(f"--junit {junit}: a folder; give the XML file's name")


def run_batch(jobs: list[Job], out: Path, workers: int | None = None, scheduler: str | None = None,
              junit: Path | None = None, rerun: bool = False) -> int:
    """Run ``jobs`` (skipping those complete under ``out`` unless ``rerun``), print progress and the table,
    write the summaries; the batch's exit code."""
    started = time.perf_counter()
    records: dict[str, dict] = {}
    for job in jobs if not rerun else []:
        done = _resumed_record(job, out)
        if done is not None:
            records[job.name] = done
    to_run = [job for job in jobs if job.name not in records]
    total, finished = len(jobs), len(records)
    for job in jobs:
        if job.name in records:
            print(progress_line(records[job.name], list(records).index(job.name) + 1, total), flush=True)

    def in_order() -> list[dict]:
        return [records[job.name] for job in jobs if job.name in records]

    def on_result(job: Job, record: dict) -> None:
        nonlocal finished
        records[job.name] = record
        if record["status"] != "not run":
            finished += 1
            print(progress_line(record, finished, total), flush=True)
        write_summary(out, in_order(), time.perf_counter() - started)

    interrupted = False
    if to_run:
        try:
            with Engine(workers, scheduler) as engine:
                print(f"{len(to_run)} of {total} objects to run on {engine.description}"
                      + (f"; {total - len(to_run)} complete before" if len(to_run) < total else ""), flush=True)
                engine.run(to_run, out, on_result)
        except KeyboardInterrupt:
            interrupted = True
        except BatchInputError as exc:
            print(f"error: {exc}", file=sys.stderr)
            return EXIT_BAD_INPUT
    final = [records.get(job.name) or _not_run(job) for job in jobs]
    write_summary(out, final, time.perf_counter() - started)
    if junit is not None:
        write_junit(junit, final)
    print()
    print(summary_table(final))
    print(f"summary: {out / 'summary.csv'}, {out / 'summary.json'}" + (f"; JUnit: {junit}" if junit else ""))
    if interrupted:
        done = [r["name"] for r in final if STATUSES[r["status"]] != "skipped"]
        print(f"interrupted: {len(done)} of {total} objects finished ({', '.join(done) or 'none'}); the others "
              "have no output folder; run the same command again to go on with them", file=sys.stderr)
        return EXIT_INTERRUPTED
    return EXIT_ALL_SUCCEEDED if all(r["status"] == "success" for r in final) else EXIT_SOME_FAILED


def _state_paths(job: Job, out: Path) -> tuple[Path, Path]:
    return out / STATE_FOLDER / f"{job.name}.json", out / STATE_FOLDER / f"{job.name}.log"


def _resumed_record(job: Job, out: Path) -> dict | None:
    """The stored record of ``job`` if its output folder is complete and came from the same inputs, else None."""
    state_path, _ = _state_paths(job, out)
    if not state_path.is_file() or not (out / job.name / "report.json").is_file():
        return None
    try:
        state = json.loads(state_path.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None
    if state.get("fingerprint") != job.fingerprint():
        return None
    return {**state["record"], "resumed": True}


def _not_run(job: Job) -> dict:
    return {**dict.fromkeys(FIELDS), "name": job.name, "status": "not run", "attempts": 0, "resumed": False}


class Engine:
    """A Dask client: to a local cluster of ``workers`` single-threaded processes, or to ``scheduler``."""

    def __init__(self, workers: int | None = None, scheduler: str | None = None) -> None:
        self.workers = workers or len(os.sched_getaffinity(0))
        self.scheduler = scheduler
        self.client = self.cluster = None

    def __enter__(self) -> Engine:
        import logging
        import uuid

        import dask
        from distributed import Client, Event, LocalCluster

        if self.scheduler:
            where = {"scheduler_file": self.scheduler} if self.scheduler.endswith(".json") else {
                "address": self.scheduler}
            try:
                self.client = Client(**where, timeout=SCHEDULER_TIMEOUT_S)
            except (OSError, ValueError) as exc:  # unreachable (OSError covers timeouts), or not an address
                raise BatchInputError(f"--scheduler {self.scheduler}: no Dask scheduler reached ({exc}); start one "
                                      "with `dask scheduler` (docs/batch.md)") from exc
            count = len(self.client.nthreads())
            self.description = f"the cluster at {self.scheduler} ({count} workers now)"
        else:
            # a worker that dies fails its job at once (not rescheduled by Dask): run() retries it once, and says so.
            # The worker processes start with Ctrl-C ignored: it stops the batch through run(), job by job.
            interrupt = signal.signal(signal.SIGINT, signal.SIG_IGN)
            try:
                with dask.config.set({"distributed.scheduler.allowed-failures": 0}):
                    self.cluster = LocalCluster(n_workers=self.workers, threads_per_worker=1, processes=True,
                                                dashboard_address=None, memory_limit=0, silence_logs=logging.CRITICAL)
            finally:
                signal.signal(signal.SIGINT, interrupt)
            self.client = Client(self.cluster)
            self.description = f"a local cluster of {self.workers} worker process{'es' * (self.workers > 1)}"
        self.stop_name = f"cell-batch-stop-{uuid.uuid4().hex}"
        self.stop = Event(self.stop_name, client=self.client)
        return self

    def __exit__(self, *exc) -> None:
        self.client.close()
        if self.cluster is not None:
            self.cluster.close()

    def run(self, jobs: list[Job], out: Path, on_result) -> None:
        """Run ``jobs`` into ``out/<name>``, calling ``on_result(job, record)`` as each ends (retried once after a
        crash, a timeout or a lost worker); ``on_result`` may return more jobs to run (a job of a name that has
        ended replaces its output folder). On Ctrl-C the running jobs are stopped, each reported, then
        KeyboardInterrupt is raised again."""
        from distributed import KilledWorker, as_completed, wait

        out.mkdir(parents=True, exist_ok=True)
        pending: dict = {}  # future -> (job, attempt, why the first attempt was retried)
        count = itertools.count(1)  # of the tasks: each its own key, even for one name
        replaceable: dict[str, bool] = {}  # name -> its output folder is cell.run's: absent, or a run's (a report)

        def submit(job: Job, attempt: int, retried_after: str | None) -> None:
            if attempt == 1:
                folder = out / job.name
                replaceable[job.name] = (folder / "report.json").is_file() or not folder.exists()
            _forget(job, out)
            future = self.client.submit(run_job, job.run_arguments(), str(out / job.name), job.timeout_s,
                                        self.stop_name, key=f"cell.run-{job.name}-{next(count)}-{self.stop_name[-8:]}",
                                        pure=False)
            pending[future] = (job, attempt, retried_after)
            completed.add(future)

        def finish(future, result: dict) -> None:
            job, attempt, retried_after = pending.pop(future)
            reason = _retry_reason(result)
            if reason is not None and attempt == 1 and not self.stop.is_set():
                print(f"{job.name}: {reason} ({_first_words(result, job.timeout_s)}); running it once more", flush=True)
                submit(job, 2, reason)
                return
            record = job_record(job, out / job.name, result, attempt, retried_after)
            if record["out"] is None and replaceable[job.name]:  # an earlier run's folder, or one a kill cut short
                shutil.rmtree(out / job.name, ignore_errors=True)
            _remember(job, out, record, result.get("log", ""))
            for more in on_result(job, record) or ():
                if not self.stop.is_set():
                    submit(more, 1, None)

        completed = as_completed()
        try:
            for job in jobs:
                submit(job, 1, None)
            for future in completed:
                finish(future, _result(future, KilledWorker))
        except KeyboardInterrupt:
            print("stopping the running jobs (Ctrl-C again to quit at once)", file=sys.stderr, flush=True)
            self.stop.set()  # each running job kills its process; the queued ones return without running
            wait(list(pending), timeout=STOP_WAIT_S)
            for future in list(pending):
                result = _result(future, KilledWorker) if future.done() else {}
                if result.get("outcome") != "finished":  # it did not end by itself: stopped, or lost on the way
                    result = {"outcome": "stopped", "exit_code": None, "wall_s": result.get("wall_s"),
                              "log": result.get("log", "")}
                finish(future, result)
            raise


def _result(future, killed_worker) -> dict:
    try:
        return future.result()
    except killed_worker:
        return {"outcome": "worker lost", "exit_code": None, "wall_s": None, "log": ""}
    except Exception as exc:  # the task itself failed before or around the process (it is not cell.run's error)
        return {"outcome": "crashed", "exit_code": None, "wall_s": None, "log": f"{type(exc).__name__}: {exc}"}


def _forget(job: Job, out: Path) -> None:
    """Before a job runs: its stored state goes (the folder no longer counts as complete) and so does anything a
    killed run left half written."""
    state_path, _ = _state_paths(job, out)
    state_path.unlink(missing_ok=True)
    remove_partial(out / job.name)


def _remember(job: Job, out: Path, record: dict, log: str) -> None:
    state_path, log_path = _state_paths(job, out)
    state_path.parent.mkdir(parents=True, exist_ok=True)
    log_path.write_text(log, encoding="utf-8")
    if record["out"] is not None:  # complete: a rerun of the same inputs skips it
        state_path.write_text(json.dumps({"fingerprint": job.fingerprint(), "record": record}, indent=1) + "\n",
                              encoding="utf-8")


def _retry_reason(result: dict) -> str | None:
    if result["outcome"] in ("timeout", "worker lost", "crashed"):
        return result["outcome"]
    code = result["exit_code"]
    if result["outcome"] == "finished" and code not in (0, 2, 3, 4, 5):
        return "internal error" if code == 1 else "crashed"
    return None


def _first_words(result: dict, timeout_s: float | None) -> str:
    if result["outcome"] == "timeout":
        return f"killed after {timeout_s:g} s"
    if result["outcome"] == "worker lost":
        return "its worker process died"
    return _error_message(result.get("log", "")).split("\n")[0][:120] or result["outcome"]


def _error_message(log: str) -> str:
    """What cell.run printed about its failure: from the ``error:`` or ``internal error`` line to the end."""
    lines = log.rstrip().split("\n")
    for k, line in enumerate(lines):
        if line.startswith(("error:", "internal error", "usage:", "Traceback")):
            return "\n".join(lines[k:]).removeprefix("error: ")[:4000]
    return "\n".join(lines[-5:]).strip()


def job_record(job: Job, folder: Path, result: dict, attempts: int = 1, retried_after: str | None = None) -> dict:
    """The summary's record of ``job`` from its worker's ``result`` and, where written, its ``report.json``."""
    record = {**dict.fromkeys(FIELDS), "name": job.name, "exit_code": result["exit_code"],
              "wall_s": None if result["wall_s"] is None else round(result["wall_s"], 3), "attempts": attempts,
              "retried_after": retried_after, "resumed": False}
    outcome, code = result["outcome"], result["exit_code"]
    if outcome == "timeout":
        record.update(status="timeout", message=f"killed after {job.timeout_s:g} s (--timeout)")
    elif outcome == "worker lost":
        record.update(status="worker lost", message="the worker process running it died (killed, out of memory, or "
                      "its machine lost)")
    elif outcome in ("stopped", "not run"):
        record.update(status="interrupted" if outcome == "stopped" and result["wall_s"] else "not run")
    elif outcome == "crashed":
        record.update(status="crashed", message=result["log"])
    elif code in REPORTED_EXITS and (folder / "report.json").is_file():
        report = json.loads((folder / "report.json").read_text(encoding="utf-8"))
        failure = report.get("failure") or {}
        parts = report.get("parts", [])
        errors = [(p.get("position_error_m"), p.get("rotation_error_deg")) for p in parts]
        record.update(status=STATUS_OF_EXIT[code], stage=failure.get("stage"), part=failure.get("part"),
                      message=failure.get("message"), parts=len(parts),
                      trajectory_duration_s=_rounded(report.get("trajectory_duration_s")),
                      parts_within_tolerance=sum(bool(p.get("within_tolerance")) for p in parts),
                      out=str(folder))
        if parts and all(e[0] is not None and e[1] is not None for e in errors):
            record.update(max_position_error_mm=round(1000 * max(e[0] for e in errors), 3),
                          max_rotation_error_deg=round(max(e[1] for e in errors), 3))
    else:
        status = STATUS_OF_EXIT.get(code, "crashed") if code not in REPORTED_EXITS else "crashed"
        if code is not None and code < 0:
            message = f"killed by signal {signal.Signals(-code).name}"
        else:
            message = _error_message(result["log"]) or f"exit code {code}"
        record.update(status=status, message=message)
    return record


def _rounded(value: float | None) -> float | None:
    return None if value is None else round(value, 3)


if __name__ == "__main__":
    sys.exit(main())


__all__ = ["Engine", "job_record", "main", "run_batch"]
