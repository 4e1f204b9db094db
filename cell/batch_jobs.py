"""The jobs of ``python -m cell.batch``: what each object's ``python -m cell.run`` is given, read from the batch's
inputs and checked before anything runs.

An input is an assembly folder (``parts/`` and ``assembly.json``: the cell builds it from its given poses), a
folder of assembly folders, or a job list: a ``.csv`` file (a header row of keys, one job a row, empty cells not
given) or a ``.json`` file (a list of objects). A job's keys:

- ``name``: the job's output folder under ``--out`` (default: the assembly folder's name, or the name of the
  parts folder's parent when the parts folder is called ``parts``, as ``cell.run`` names its own)
- ``assembly``: an assembly folder; stands for ``parts`` = its ``parts/`` and, unless ``image`` is given,
  ``poses`` = its ``assembly.json``
- ``parts``, ``poses``, ``image``: as ``cell.run --parts``, ``--poses``, ``--image`` (``poses`` or ``image``)
- the options of ``cell.run`` (:data:`RUN_OPTIONS`): ``seed``, ``units``, ``scene``, ``checkpoint``,
  ``planner``, ``density``, ``masses``, ``time_budget``, ``animation`` and ``accept_prediction`` (true or false),
  ``bag_storage``
- ``timeout``: seconds before this job's process is killed (default ``--timeout``)

Relative paths in a job list are relative to the list's folder. Every problem raises :class:`BatchInputError`
naming the file, the row and the key or value at fault.
"""

from __future__ import annotations

import csv
import hashlib
import json
import math
import re
from dataclasses import dataclass, field
from pathlib import Path

from cell.api import Options, check_options
from cell.errors import BadOption
from planning.assembly import ASSEMBLY_FILE

JOB_LIST_SUFFIXES = (".csv", ".json")
NAME_PATTERN = re.compile(r"[A-Za-z0-9_][A-Za-z0-9_.+-]*")  # a plain folder name, never hidden


class BatchInputError(ValueError):
    """Bad batch input; the message names the culprit."""


@dataclass(frozen=True)
class RunOption:
    flag: str  # cell.run's option
    kind: str  # "int", "float", "text", "path", "units", "switch" (given false adds the flag) or "flag" (given true
    # adds it)
    help: str


# job key -> how it is passed to cell.run
RUN_OPTIONS = {
    "seed": RunOption("--seed", "int", "seed of every random choice"),
    "units": RunOption("--units", "units", "units of the mesh files (m, cm, mm)"),
    "scene": RunOption("--scene", "path", "robot cell scene file"),
    "checkpoint": RunOption("--checkpoint", "path", "perception weights"),
    "planner": RunOption("--planner", "text", "OMPL planner"),
    "density": RunOption("--density", "float", "the parts' density, kg/m3"),
    "masses": RunOption("--masses", "path", "known part masses, a JSON file"),
    "time_budget": RunOption("--time-budget", "float", "seconds of kitting and motion planning per build"),
    "animation": RunOption("--no-animation", "switch", "write animation.gif (true or false)"),
    "accept_prediction": RunOption("--accept-prediction", "flag", "build a prediction that does not match its "
                                   "picture (true or false)"),
    "bag_storage": RunOption("--bag-storage", "text", "the ROS 2 bag's storage: mcap or sqlite3"),
}
# the job keys that are cell.api.Options fields, checked as cell.run checks them
CHECKED_OPTIONS = ("seed", "units", "planner", "density", "time_budget", "accept_prediction", "bag_storage")
JOB_KEYS = ("name", "assembly", "parts", "poses", "image", "timeout", *RUN_OPTIONS)


@dataclass(frozen=True)
class Job:
    """One object's ``python -m cell.run``: its paths are absolute, its options checked."""

    name: str
    source: str  # where the job was given, for messages: a folder, or "list.csv row 3"
    parts: Path
    poses: Path | None = None
    image: Path | None = None
    options: dict = field(default_factory=dict)  # job key in RUN_OPTIONS -> value
    timeout_s: float | None = None  # None: the batch's --timeout

    def run_arguments(self) -> list[str]:
        """The arguments of ``python -m cell.run`` for this job, without ``--out``."""
        arguments = ["--parts", str(self.parts)]
        if self.poses is not None:
            arguments += ["--poses", str(self.poses)]
        if self.image is not None:
            arguments += ["--image", str(self.image)]
        for key, value in sorted(self.options.items()):
            option = RUN_OPTIONS[key]
            if option.kind in ("switch", "flag"):
                arguments += [option.flag] if value == (option.kind == "flag") else []
            else:
                arguments += [option.flag, str(value)]
        return arguments

    def input_files(self) -> list[Path]:
        """Every file whose content the run depends on: the meshes, the poses, the picture and the option files."""
        files = sorted(p for p in self.parts.rglob("*") if p.is_file()) if self.parts.is_dir() else [self.parts]
        files += [p for p in (self.poses, self.image) if p is not None]
        files += [Path(self.options[k]) for k in sorted(self.options) if RUN_OPTIONS[k].kind == "path"]
        return files

    def fingerprint(self) -> str:
        """sha256 of the arguments and of every input file's bytes: equal fingerprints, the same run."""
        digest = hashlib.sha256(json.dumps(self.run_arguments()).encode())
        for path in self.input_files():
            digest.update(str(path).encode() + b"\0")
            digest.update(path.read_bytes() if path.is_file() else b"<missing>")
        return digest.hexdigest()


def read_jobs(inputs: list[Path], defaults: dict | None = None, timeout_s: float | None = None) -> list[Job]:
    """The jobs of the batch's inputs, in the order given; ``defaults`` (job keys) apply where a job gives no
    value. Raises :class:`BatchInputError` on a missing path, an unknown key, a bad value or two jobs with one
    output folder."""
    defaults = {k: v for k, v in (defaults or {}).items() if v is not None}
    jobs: list[Job] = []
    for path in inputs:
        if path.suffix.lower() in JOB_LIST_SUFFIXES and not path.is_dir():
            if not path.is_file():
                raise BatchInputError(f"{path}: job list not found")
            entries = _read_job_list(path)
            jobs += [_job({**defaults, **entry}, where, path.parent) for where, entry in entries]
        elif (path / ASSEMBLY_FILE).is_file():
            jobs.append(_job({**defaults, "assembly": str(path)}, str(path), Path.cwd()))
        elif path.is_dir():
            folders = sorted(p for p in path.iterdir() if (p / ASSEMBLY_FILE).is_file())
            if not folders:
                raise BatchInputError(f"{path}: neither an assembly folder (parts/ and {ASSEMBLY_FILE}) nor a folder "
                                      f"of them (none of its subfolders holds an {ASSEMBLY_FILE})")
            jobs += [_job({**defaults, "assembly": str(f)}, str(f), Path.cwd()) for f in folders]
        elif path.exists():
            raise BatchInputError(f"{path}: give an assembly folder, a folder of them, or a job list "
                                  f"({' or '.join(JOB_LIST_SUFFIXES)} file)")
        else:
            raise BatchInputError(f"{path}: no such folder or job list")
    if not jobs:
        raise BatchInputError("no jobs: the inputs hold no objects")
    seen: dict[str, Job] = {}
    for job in jobs:
        if job.name in seen:
            raise BatchInputError(f"{job.source} and {seen[job.name].source}: both write the output folder "
                                  f"{job.name!r}; give each a different 'name' in a job list")
        seen[job.name] = job
    if timeout_s is not None:
        jobs = [job if job.timeout_s is not None else _with_timeout(job, timeout_s) for job in jobs]
    return jobs


def _with_timeout(job: Job, timeout_s: float) -> Job:
    return Job(job.name, job.source, job.parts, job.poses, job.image, job.options, timeout_s)


def _read_job_list(path: Path) -> list[tuple[str, dict]]:
    """(where, entry) per job of a CSV or JSON job list, in its order."""
    if path.suffix.lower() == ".csv":
        with open(path, newline="", encoding="utf-8") as handle:
            reader = csv.DictReader(handle)
            if not reader.fieldnames:
                raise BatchInputError(f"{path}: empty job list (expected a header row of keys: {', '.join(JOB_KEYS)})")
            rows = list(reader)
        entries = []
        for number, row in enumerate(rows, start=2):  # the header is row 1
            if None in row:
                raise BatchInputError(f"{path} row {number}: more cells than the header has keys")
            entries.append((f"{path} row {number}", {k.strip(): v.strip() for k, v in row.items()
                                                      if v is not None and v.strip() != ""}))
        return entries
    try:
        document = json.loads(path.read_text(encoding="utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise BatchInputError(f"{path}: not a readable JSON job list ({exc})") from exc
    if not isinstance(document, list) or not all(isinstance(entry, dict) for entry in document):
        raise BatchInputError(f"{path}: a JSON job list is a list of objects, one per job "
                              '([{"assembly": "chair"}, {"parts": "...", "poses": "..."}])')
    return [(f"{path} job {k + 1}", {key: value for key, value in entry.items() if value is not None})
            for k, entry in enumerate(document)]


def _job(entry: dict, where: str, base: Path) -> Job:
    unknown = sorted(set(entry) - set(JOB_KEYS))
    if unknown:
        raise BatchInputError(f"{where}: unknown key {unknown[0]!r} (a job's keys: {', '.join(JOB_KEYS)})")

    def path_of(key: str, kind: str) -> Path:
        path = (base / Path(str(entry[key])).expanduser()).resolve()
        if kind == "folder" and not path.is_dir():
            raise BatchInputError(f"{where}: {key} {entry[key]}: {'not a folder' if path.exists() else 'not found'}")
        if kind == "file" and not path.is_file():
            raise BatchInputError(f"{where}: {key} {entry[key]}: {'not a file' if path.exists() else 'not found'}")
        return path

    if "assembly" in entry:
        if "parts" in entry or "poses" in entry:
            raise BatchInputError(f"{where}: give either 'assembly' or 'parts' and 'poses', not both")
        folder = path_of("assembly", "folder")
        if not (folder / ASSEMBLY_FILE).is_file():
            raise BatchInputError(f"{where}: assembly {entry['assembly']}: no {ASSEMBLY_FILE} in it (an assembly "
                                  f"folder holds parts/ and {ASSEMBLY_FILE})")
        parts = folder / "parts"
        if not parts.is_dir():
            raise BatchInputError(f"{where}: assembly {entry['assembly']}: no parts/ folder in it")
        poses = None if "image" in entry else folder / ASSEMBLY_FILE
        default_name = folder.name
    elif "parts" in entry:
        parts = path_of("parts", "folder")
        poses = path_of("poses", "file") if "poses" in entry else None
        default_name = parts.parent.name if parts.name == "parts" else parts.name
    else:
        raise BatchInputError(f"{where}: give the parts ('parts', or an assembly folder as 'assembly')")
    image = path_of("image", "file") if "image" in entry else None
    if poses is None and image is None:
        raise BatchInputError(f"{where}: give 'poses' (the target poses) or 'image' (perception predicts them)")
    name = str(entry.get("name", default_name))
    if not NAME_PATTERN.fullmatch(name):
        raise BatchInputError(f"{where}: name {name!r}: an output folder's name takes letters, digits and _ . + - "
                              "(not starting with . or -)")
    options = {}
    for key, option in RUN_OPTIONS.items():
        if key in entry:
            options[key] = path_of(key, "file") if option.kind == "path" else _value(entry[key], option.kind, key,
                                                                                       where)
    timeout_s = _value(entry["timeout"], "float", "timeout", where) if "timeout" in entry else None
    if timeout_s is not None and not timeout_s > 0:
        raise BatchInputError(f"{where}: timeout {timeout_s:g}: give a number of seconds above 0")
    try:  # the options' ranges as cell.run checks them (seed, planner, density, time budget, ...)
        check_options(Options(**{key: options[key] for key in CHECKED_OPTIONS if key in options}))
    except BadOption as exc:
        raise BatchInputError(f"{where}: {exc}") from None
    return Job(name, where, parts, poses, image, options, timeout_s)


def _value(value, kind: str, key: str, where: str):
    """A job list's value (text from a CSV, or JSON) as ``kind``."""
    try:
        if kind == "int":
            if isinstance(value, bool) or (isinstance(value, float) and not value.is_integer()):
                raise ValueError
            return int(value)
        if kind == "float":
            if isinstance(value, bool):
                raise ValueError
            number = float(value)
            if not math.isfinite(number):
                raise ValueError
            return number
        if kind in ("switch", "flag"):
            words = {"true": True, "yes": True, "1": True, "false": False, "no": False, "0": False}
            if isinstance(value, bool):
                return value
            return words[str(value).strip().lower()]
        if kind == "units":
            if value not in ("m", "cm", "mm"):
                raise ValueError
            return value
        return str(value)
    except (ValueError, KeyError, TypeError):
        expected = {"int": "a whole number", "float": "a number", "switch": "true or false", "flag": "true or false",
                    "units": "m, cm or mm"}.get(kind, "text")
        raise BatchInputError(f"{where}: {key} {value!r}: expected {expected}") from None


__all__ = ["BatchInputError", "Job", "JOB_KEYS", "RUN_OPTIONS", "read_jobs"]
