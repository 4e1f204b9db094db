"""Build a training set of procedural objects: ``python -m perception.dataset build ...``.

Each object is one compressed ``.npz`` under ``<out>/<split>/`` holding its parts and K views (fields in
:mod:`perception.dataset.sample`). Object i is generated from ``numpy.random.default_rng([seed, i])`` (the same
object as ``python -m perception.synth`` with that seed) and rendered from ``default_rng([seed, i, 1])``, so the
same arguments give the same arrays, whatever the number of workers. The split is by object: i % 10 == 8 is
validation, i % 10 == 9 test, the rest training. Files are written atomically and existing ones are skipped, so
an interrupted build resumes where it stopped.

``stretch`` > 1 scales each object, before rendering, by a random factor along each of its assembly frame's axes
(log-uniform in [1/stretch, stretch], from ``default_rng([seed, i, 2])``; :func:`planning.assembly.stretched`):
proportions the generators do not draw (long low units, tall narrow shelves), for networks that should not read
the category's usual proportions (the elevation head).

``materials``: how the parts are coloured (:data:`cell.render.MATERIALS`: a colour per part, the default; one
shared material; two or three), or ``mixed`` (:func:`materials_of`), so that a network trained on it does not lean
on each part having its own colour, which a photo of a wooden chair does not give.
"""

from __future__ import annotations

import json
import multiprocessing
import os
import tempfile
import time
from dataclasses import MISSING, asdict, dataclass, fields
from pathlib import Path

import numpy as np
from tqdm import tqdm

from perception.dataset.sample import object_sample
from planning.assembly import stretched

CONFIG_FILE = "dataset.json"


@dataclass(frozen=True)
class BuildConfig:
    category: str
    level: str
    count: int  # objects
    views: int  # rendered views per object: count * views samples in all
    seed: int
    renderer: str = "tiny"
    stretch: float = 1.0  # largest per-axis scale factor (1: the generator's proportions)
    materials: str = "parts"  # one of cell.render.MATERIALS, or "mixed": one of them per object (materials_of)


def split_of(index: int) -> str:
    return {8: "val", 9: "test"}.get(index % 10, "train")


def object_name(config: BuildConfig, index: int) -> str:
    return f"{config.category}_{config.level}_s{config.seed}_{index:05d}"


def object_path(out: Path, config: BuildConfig, index: int) -> Path:
    return out / split_of(index) / f"{object_name(config, index)}.npz"


def materials_of(config: BuildConfig, index: int) -> str:
    """How object ``index``'s parts are coloured (:data:`cell.render.MATERIALS`): ``config.materials``, or for
    ``mixed`` one of them drawn from ``default_rng([seed, index, 3])``, a colour per part for half the objects and
    one or a few shared materials for a quarter each."""
    if config.materials != "mixed":
        return config.materials
    return str(np.random.default_rng([config.seed, index, 3]).choice(["parts", "parts", "one", "few"]))


def build_object(config: BuildConfig, index: int) -> dict:
    """Generate, normalise and render object ``index``; returns its arrays."""
    from perception.synth import generate

    assembly = generate(config.category, config.level, np.random.default_rng([config.seed, index]),
                        object_name(config, index))
    if config.stretch > 1.0:
        span = np.log(config.stretch)
        assembly = stretched(assembly, np.exp(np.random.default_rng([config.seed, index, 2]).uniform(-span, span, 3)))
    sample = object_sample(assembly, config.views, np.random.default_rng([config.seed, index, 1]),
                           renderer=config.renderer, materials=materials_of(config, index))
    sample["object_name"] = np.array(assembly.name)
    return sample


def save_sample(sample: dict, path: Path) -> None:
    """Write atomically: a temporary file in the same folder, renamed into place."""
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.stem}.", suffix=".npz", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as handle:
            np.savez_compressed(handle, **sample)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def _work(job: tuple[BuildConfig, int, str]) -> int:
    config, index, out = job
    path = object_path(Path(out), config, index)
    if not path.exists():
        save_sample(build_object(config, index), path)
    return index


def _check_config(out: Path, config: BuildConfig) -> None:
    config_path = out / CONFIG_FILE
    if config_path.exists():
        defaults = {f.name: f.default for f in fields(BuildConfig) if f.default is not MISSING}
        # a key a folder's dataset.json lacks was added since: the folder was built with its default
        existing = {**defaults, **json.loads(config_path.read_text())}
        mismatched = {k: (existing.get(k), v) for k, v in asdict(config).items()
                      if k != "count" and existing.get(k) != v}
        if mismatched:
            details = ", ".join(f"{k}: {a!r} there, {b!r} asked" for k, (a, b) in mismatched.items())
            raise ValueError(f"{config_path} was built with other settings ({details}); choose another --out")
    out.mkdir(parents=True, exist_ok=True)
    config_path.write_text(json.dumps(asdict(config), indent=1) + "\n")


def build(config: BuildConfig, out: Path, workers: int = 1, progress: bool = True) -> dict:
    """Build (or resume) the dataset; returns timing figures."""
    _check_config(out, config)
    todo = [i for i in range(config.count) if not object_path(out, config, i).exists()]
    start = time.perf_counter()
    jobs = [(config, i, str(out)) for i in todo]
    bar = tqdm(total=config.count, initial=config.count - len(todo), unit="obj", disable=not progress,
               desc=f"{config.category} level {config.level}")
    if workers <= 1:
        for job in jobs:
            _work(job)
            bar.update()
    else:
        with multiprocessing.get_context("fork").Pool(workers) as pool:
            for _ in pool.imap_unordered(_work, jobs, chunksize=1):
                bar.update()
    bar.close()
    seconds = time.perf_counter() - start
    samples = len(todo) * config.views
    return {"objects_built": len(todo), "samples_built": samples, "seconds": seconds,
            "samples_per_second": samples / seconds if seconds > 0 and samples else 0.0}
