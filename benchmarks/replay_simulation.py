"""Capture one assembly program and simulate it again under other settings: compare simulator settings on the
very same program, in seconds instead of a full planning run.

    # plan and simulate as ``python -m cell.run`` does, and keep what the simulation was given
    python benchmarks/replay_simulation.py capture chair.pkl -- --parts DIR --poses DIR/assembly.json --out OUT
    # simulate that program again, at another rate or with other SimSettings fields
    python benchmarks/replay_simulation.py replay chair.pkl --rate-hz 240 --set insertion_contact_breaking_m=0.005

``capture`` runs ``cell.run`` with the given arguments and writes the inputs of its simulation (the program, the
parts, the static bodies, the robot's base and the settings) to a pickle; ``replay`` loads it, applies the changes,
simulates and prints each part's final error and the run's verdict (``--json`` writes them too). The program's
timed motions are stored as samples at :data:`DENSE_HZ` and interpolated linearly (Ruckig's trajectories cannot be
pickled): a replay at the captured settings reproduces the captured run to within a few hundredths of a millimetre,
not bit for bit. The file is read back by this script only (its samples' class lives here), and pickles run code
when loaded: replay only files you captured yourself.
"""

from __future__ import annotations

import argparse
import json
import pickle
import runpy
import sys
from dataclasses import dataclass, fields, replace
from pathlib import Path

import numpy as np
import trimesh

import cell.simulate as simulate
from cell.program import MotionStep, Program
from planning.timing import TimedPath

DENSE_HZ = 3840.0  # samples per second of a captured motion (a multiple of 240, 480 and 960 Hz)


@dataclass
class SampledPath(TimedPath):
    """A :class:`TimedPath` known only by its samples (``times`` (N,) seconds; ``q``, ``qd``, ``qdd`` (N, 7)),
    interpolated linearly between them."""

    times: np.ndarray | None = None
    q: np.ndarray | None = None
    qd: np.ndarray | None = None
    qdd: np.ndarray | None = None

    @classmethod
    def of(cls, timed: TimedPath, rate_hz: float = DENSE_HZ) -> SampledPath:
        times = np.linspace(0.0, timed.duration, max(2, int(np.ceil(timed.duration * rate_hz)) + 1))
        q, qd, qdd = timed.at_times(times)
        return cls(timed.waypoints, timed.via_velocities, [], timed.durations, times, q, qd, qdd)

    def at_times(self, times: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        return tuple(np.stack([np.interp(times, self.times, table[:, j]) for j in range(table.shape[1])], axis=1)
                     for table in (self.q, self.qd, self.qdd))


def frozen(program: Program) -> Program:
    """``program`` with every motion replaced by its samples (picklable)."""
    steps = [MotionStep(s.label, SampledPath.of(s.timed), s.part) if isinstance(s, MotionStep) else s
             for s in program.steps]
    return Program(steps, program.initial_width_m)


def _fresh_mesh(mesh: trimesh.Trimesh) -> trimesh.Trimesh:
    # an unpickled mesh keeps caches that trimesh's proximity queries trip over: rebuild it from its arrays
    return trimesh.Trimesh(mesh.vertices.copy(), mesh.faces.copy(), process=False)


def capture(path: Path, run_args: list[str]) -> int:
    """Run ``python -m cell.run RUN_ARGS``, writing its simulation's inputs to ``path``; returns its exit code."""
    original = simulate.simulate_program
    path.unlink(missing_ok=True)  # what is there afterwards is this run's

    def capturing(program, parts, static_bodies, world_from_robot_base, settings=None, **kwargs):
        settings = settings if settings is not None else simulate.SimSettings()
        with open(path, "wb") as handle:
            pickle.dump({"program": frozen(program), "parts": list(parts), "static_bodies": list(static_bodies),
                         "world_from_robot_base": world_from_robot_base, "settings": settings}, handle)
        return original(program, parts, static_bodies, world_from_robot_base, settings, **kwargs)

    simulate.simulate_program = capturing
    sys.argv = ["cell.run", *run_args]
    try:
        runpy.run_module("cell.run", run_name="__main__")
    except SystemExit as exit_:
        code = exit_.code if isinstance(exit_.code, int) else 1
    else:
        code = 0
    finally:
        simulate.simulate_program = original
    if not path.exists():
        print(f"no simulation ran (exit code {code}): nothing captured in {path}", file=sys.stderr)
        return code or 1
    print(f"captured in {path}")
    return code


def _setting(text: str) -> tuple[str, float | None]:
    """``NAME=VALUE`` of ``--set``: a numeric :class:`SimSettings` field and its value (``None`` where allowed)."""
    name, _, value = text.partition("=")
    defaults = simulate.SimSettings()
    known = sorted(f.name for f in fields(simulate.SimSettings)
                   if isinstance(getattr(defaults, f.name), float | int | None))
    if name not in known or not value:
        raise SystemExit(f"--set {text!r}: expected NAME=VALUE, NAME one of SimSettings' numeric fields "
                         f"({', '.join(known)})")
    if value == "None":
        return name, None
    try:
        return name, float(value)
    except ValueError:
        raise SystemExit(f"--set {text!r}: {value!r} is not a number") from None


def replay(path: Path, rate_hz: float | None, changes: list[str], json_path: Path | None) -> int:
    if not path.is_file():
        raise SystemExit(f"{path}: no such capture (make one with: replay_simulation.py capture {path} -- ...)")
    with open(path, "rb") as handle:
        captured = pickle.load(handle)
    updates = dict(_setting(text) for text in changes)
    if rate_hz is not None:
        updates["rate_hz"] = rate_hz
    try:
        settings = replace(captured["settings"], **updates)
    except ValueError as error:
        raise SystemExit(str(error)) from None
    parts = [replace(p, mesh=_fresh_mesh(p.mesh)) for p in captured["parts"]]
    static_bodies = [replace(b, mesh=_fresh_mesh(b.mesh)) for b in captured["static_bodies"]]
    result = simulate.simulate_program(captured["program"], parts, static_bodies, captured["world_from_robot_base"],
                                       settings)
    print(f"{path.name} at {settings.rate_hz:.0f} Hz {' '.join(changes)}: "
          f"{'success' if result.success else 'FAILED: ' + result.failure_words()}")
    for part in result.parts:
        print(f"  {part.name:<16} {part.position_error_m * 1000:7.2f} mm {part.rotation_error_deg:6.2f} deg")
    if json_path is not None:
        json_path.write_text(json.dumps({"capture": path.name, "rate_hz": settings.rate_hz, "changes": changes,
                                         "success": result.success, "why": result.failure_words(),
                                         "parts": [p.to_json() for p in result.parts]}, indent=1))
    return 0 if result.success else 4


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    commands = parser.add_subparsers(dest="command", required=True)
    cap = commands.add_parser("capture", help="run cell.run and keep its simulation's inputs")
    cap.add_argument("pickle", type=Path)
    cap.add_argument("run_args", nargs=argparse.REMAINDER, help="-- then cell.run's arguments")
    rep = commands.add_parser("replay", help="simulate a captured program again")
    rep.add_argument("pickle", type=Path)
    rep.add_argument("--rate-hz", type=float, default=None, help="physics steps per second (default: as captured)")
    rep.add_argument("--set", action="append", default=[], metavar="NAME=VALUE", help="a SimSettings field")
    rep.add_argument("--json", type=Path, default=None, help="write the result here")
    args = parser.parse_args(argv)
    if args.command == "capture":
        run_args = args.run_args[1:] if args.run_args[:1] == ["--"] else args.run_args
        return capture(args.pickle, run_args)
    return replay(args.pickle, args.rate_hz, args.set, args.json)


if __name__ == "__main__":
    sys.exit(main())
