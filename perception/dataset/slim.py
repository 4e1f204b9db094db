"""A training-only copy of a dataset folder, small enough to ship to another machine (a GPU host).

A built object file is dominated by its part clouds: 1000 float32 points per part, about 150 kB of a 16-part
chair's 160 kB, while its rendered views compress to a few kB each. A network whose config reads only the first
``model.encoder_points`` / ``loss.points`` of each cloud (the clouds are stored in farthest-point order, so a
prefix is an even subsample) needs no more than that prefix. :func:`slim_dataset` keeps, for the ``train`` and
``val`` splits, only the arrays training reads (:data:`perception.data.OBJECT_KEYS` and
:data:`perception.data.VIEW_KEYS`), with each cloud cut to its first ``points`` points and quantised to int8 with
a per-part scale, ``points_scale`` (:func:`perception.data.part_points` reads them back as float32). The
rounding is at most 1/254 of the part's largest coordinate: below 0.002 in the normalised units where the
largest part's diagonal is 1, against the 0.1 chamfer of Part Accuracy. A level-3 chair with four views then takes about
27 kB instead of 164 kB (256 points per part).

Evaluation (``python -m perception.evaluate --data``) needs the full files: slim folders are for training.

    python -m perception.dataset slim data/chair_l3 --points 256 --out data_slim/chair_l3
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from perception.data import OBJECT_KEYS, VIEW_KEYS
from perception.dataset import list_objects
from perception.dataset.build import CONFIG_FILE, save_sample

TRAINING_SPLITS = ("train", "val")


def slim_object(arrays: dict, points: int) -> dict[str, np.ndarray]:
    """The arrays of one object file that training reads, clouds cut to ``points`` points per part and quantised
    to int8 with a per-part scale (``points_scale``)."""
    missing = [key for key in OBJECT_KEYS + VIEW_KEYS if key not in arrays]
    if missing:
        raise ValueError(f"lacks {missing[0]!r}: not an object file of perception.dataset build")
    out = {key: np.asarray(arrays[key]) for key in OBJECT_KEYS + VIEW_KEYS}
    clouds = np.asarray(arrays["points_norm"][:, :points], dtype=np.float64)
    scale = np.abs(clouds).max(axis=(1, 2))
    scale = np.where(scale > 0, scale, 1.0)
    out["points_norm"] = np.round(clouds / scale[:, None, None] * 127.0).astype(np.int8)
    out["points_scale"] = scale.astype(np.float32)
    return out


def object_index(path: Path) -> int:
    """The object index of a built object file (the last ``_`` field of its name: ``chair_3_s0_00042``)."""
    try:
        return int(path.stem.rsplit("_", 1)[1])
    except (IndexError, ValueError):
        raise ValueError(f"{path.name} is not named like an object file of perception.dataset build") from None


def slim_dataset(src: str | Path, out: str | Path, points: int, count: int | None = None) -> dict:
    """Write the slim copy of dataset folder ``src`` to ``out`` (train and val splits; an existing slim file is
    kept, so an interrupted run resumes). ``count``: only the objects of index below it, which are exactly those
    ``build --count COUNT`` with the same other arguments makes (each object has its own seed). Returns counts
    and sizes."""
    src, out = Path(src), Path(out)
    if not 1 <= points <= 1000:
        raise ValueError(f"--points must be in 1..1000, got {points}")
    if not (src / CONFIG_FILE).is_file():
        raise ValueError(f"{src} is not a dataset folder (no {CONFIG_FILE}; build one with "
                         f"python -m perception.dataset build)")
    if out.resolve() == src.resolve():
        raise ValueError(f"--out {out} is the source folder; choose another")
    info = json.loads((src / CONFIG_FILE).read_text())
    if count is not None:
        if count < 1 or count > info.get("count", count):
            raise ValueError(f"--count must be in 1..{info.get('count')} (the objects {src} holds), got {count}")
        info["count"] = count
    info["slim"] = {"points": points, "dtype": "int8", "splits": list(TRAINING_SPLITS)}
    if (out / CONFIG_FILE).is_file() and json.loads((out / CONFIG_FILE).read_text()) != info:
        raise ValueError(f"{out} holds a slim copy made with other arguments ({out / CONFIG_FILE}); choose "
                         f"another --out")
    out.mkdir(parents=True, exist_ok=True)
    (out / CONFIG_FILE).write_text(json.dumps(info, indent=1) + "\n")
    files = src_bytes = out_bytes = 0
    for split in TRAINING_SPLITS:
        (out / split).mkdir(exist_ok=True)
        for path in list_objects(src, split):
            if count is not None and object_index(path) >= count:
                continue
            target = out / split / path.name
            if not target.exists():
                with np.load(path, allow_pickle=False) as data:
                    arrays = {key: data[key] for key in OBJECT_KEYS + VIEW_KEYS if key in data.files}
                try:
                    save_sample(slim_object(arrays, points), target)
                except ValueError as exc:
                    raise ValueError(f"{path}: {exc}") from None
            files += 1
            src_bytes += path.stat().st_size
            out_bytes += target.stat().st_size
    return {"objects": files, "source_mb": src_bytes / 2**20, "slim_mb": out_bytes / 2**20}
