"""What ``python -m cell.batch`` writes about a batch: ``summary.csv``, ``summary.json``, the printed progress and
table, and the JUnit XML file for CI systems (one test case per object).

A record (one per object, the rows of ``summary.csv`` and the ``objects`` of ``summary.json``)::

    {"name", "status" (STATUSES), "exit_code" (cell.run's; null when it timed out, lost its worker or did not run),
     "stage", "part", "message" (the failure, from report.json or from the error cell.run printed),
     "wall_s" (the job's process, seconds), "trajectory_duration_s" (the robot program, seconds),
     "max_position_error_mm", "max_rotation_error_deg" (the worst part's final error in the simulation),
     "parts", "parts_within_tolerance", "attempts", "retried_after" (why a first attempt was retried),
     "resumed" (true: a complete output of the same inputs was found, not run again), "out" (its output folder,
     null when it has none)}
"""

from __future__ import annotations

import csv
import io
import json
import os
import xml.etree.ElementTree as ET
from pathlib import Path

FIELDS = ("name", "status", "exit_code", "stage", "part", "message", "wall_s", "trajectory_duration_s",
          "max_position_error_mm", "max_rotation_error_deg", "parts", "parts_within_tolerance", "attempts",
          "retried_after", "resumed", "out")
# status -> how a CI system sees the object's test case
PASSED, FAILED, ERROR, SKIPPED = "passed", "failure", "error", "skipped"
STATUSES = {"success": PASSED, "planning failed": FAILED, "simulation failed": FAILED,
            "disagrees with picture": FAILED, "bad input": ERROR,
            "internal error": ERROR, "crashed": ERROR, "timeout": ERROR, "worker lost": ERROR,
            "interrupted": SKIPPED, "not run": SKIPPED}
MESSAGE_CHARS = 60  # of a failure's message in the printed table (the summary keeps it whole)


def _replace_text(path: Path, text: str) -> None:
    """Write ``path`` whole or not at all (a temporary sibling renamed over it)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    try:
        with open(tmp, "w", encoding="utf-8", newline="") as file:
            file.write(text)
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


def counts(records: list[dict]) -> dict:
    """How many objects ended each way (a CI system's view), and in all."""
    tally = {"objects": len(records), PASSED: 0, FAILED: 0, ERROR: 0, SKIPPED: 0}
    for record in records:
        tally[STATUSES[record["status"]]] += 1
    return tally


def write_summary(out: Path, records: list[dict], wall_s: float) -> None:
    """``summary.json`` and ``summary.csv`` in ``out``, each written whole."""
    document = {"counts": counts(records), "wall_s": round(wall_s, 3), "objects": records}
    _replace_text(out / "summary.json", json.dumps(document, indent=1, allow_nan=False) + "\n")
    rows = io.StringIO()
    writer = csv.DictWriter(rows, fieldnames=FIELDS, extrasaction="ignore")
    writer.writeheader()
    for record in records:
        writer.writerow({k: "" if record.get(k) is None else record[k] for k in FIELDS})
    _replace_text(out / "summary.csv", rows.getvalue())


def _seconds(value) -> str:
    return "-" if value is None else f"{value:.0f}"


def _first_line(message: str | None, chars: int) -> str:
    first = (message or "").strip().split("\n")[0]
    return first if len(first) <= chars else first[:chars - 3].rstrip() + "..."


def progress_line(record: dict, done: int, total: int) -> str:
    """One line as an object finishes: ``[3/10] chair_0: planning failed at motion (exit 3), 52 s, ...``."""
    status = record["status"]
    if record.get("stage"):
        status += f" at {record['stage']}"
    details = [] if record["exit_code"] is None else [f"exit {record['exit_code']}"]
    if record.get("resumed"):
        details.append("done before, not run again")
    else:
        details.append(f"{_seconds(record['wall_s'])} s")
    if record.get("attempts", 1) > 1:
        details.append(f"attempt {record['attempts']} after {record['retried_after']}")
    line = f"[{done}/{total}] {record['name']}: {status} ({', '.join(details)})"
    if record.get("message") and STATUSES[status.split(' at ')[0]] != PASSED:
        line += f": {_first_line(record['message'], 2 * MESSAGE_CHARS)}"
    return line


def summary_table(records: list[dict]) -> str:
    """Every object: status, exit, failed stage, wall and program seconds, worst final errors, the message."""
    rows = [("object", "status", "exit", "stage", "wall s", "program s", "pos err mm", "rot err deg", "message")]
    for r in records:
        rows.append((r["name"], r["status"] + (" (resumed)" if r.get("resumed") else ""),
                     "-" if r["exit_code"] is None else str(r["exit_code"]), r.get("stage") or "-",
                     _seconds(r.get("wall_s")),
                     "-" if r.get("trajectory_duration_s") is None else f"{r['trajectory_duration_s']:.1f}",
                     "-" if r.get("max_position_error_mm") is None else f"{r['max_position_error_mm']:.1f}",
                     "-" if r.get("max_rotation_error_deg") is None else f"{r['max_rotation_error_deg']:.1f}",
                     _first_line(r.get("message"), MESSAGE_CHARS) or "-"))
    widths = [max(len(row[k]) for row in rows) for k in range(len(rows[0]))]
    lines = ["  ".join(cell.ljust(w) for cell, w in zip(row, widths)).rstrip() for row in rows]
    lines.insert(1, "  ".join("-" * w for w in widths))
    tally = counts(records)
    lines.append("")
    objects = f"{tally['objects']} object{'s' * (tally['objects'] != 1)}"
    lines.append(f"{objects}: {tally[PASSED]} succeeded, {tally[FAILED]} failed, {tally[ERROR]} errors, "
                 f"{tally[SKIPPED]} not run")
    return "\n".join(lines)


def write_junit(path: Path, records: list[dict], suite: str = "cell.batch") -> None:
    """JUnit XML: one test case per object (its time the job's wall time); a planning or simulation failure is
    a ``failure``, bad input, a crash, a timeout or a lost worker an ``error``, an object not run ``skipped``,
    each with the stage and the message."""
    tally = counts(records)
    total_s = sum(r.get("wall_s") or 0.0 for r in records if not r.get("resumed"))
    attributes = {"name": suite, "tests": str(tally["objects"]), "failures": str(tally[FAILED]),
                  "errors": str(tally[ERROR]), "skipped": str(tally[SKIPPED]), "time": f"{total_s:.3f}"}
    root = ET.Element("testsuites", attributes)
    suite_element = ET.SubElement(root, "testsuite", attributes)
    for r in records:
        case = ET.SubElement(suite_element, "testcase", {"classname": suite, "name": r["name"],
                                                         "time": f"{(r.get('wall_s') or 0.0):.3f}"})
        kind = STATUSES[r["status"]]
        if kind != PASSED:
            where = f"{r['status']}" + (f" at {r['stage']}" if r.get("stage") else "")
            if r.get("part") and repr(r["part"]) not in (r.get("message") or ""):
                where += f" (part {r['part']!r})"
            message = f"{where}: {_first_line(r.get('message'), 500)}" if r.get("message") else where
            element = ET.SubElement(case, kind, {"message": message, "type": r["status"]})
            if kind != SKIPPED:
                element.text = (f"exit code {r['exit_code']}\n" if r["exit_code"] is not None else "") + (
                    r.get("message") or "")
        if r.get("out"):
            ET.SubElement(case, "system-out").text = f"output folder: {r['out']}"
    ET.indent(root)
    _replace_text(path, ET.tostring(root, encoding="unicode", xml_declaration=True) + "\n")


__all__ = ["FIELDS", "STATUSES", "counts", "progress_line", "summary_table", "write_junit", "write_summary"]
