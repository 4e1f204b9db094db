"""Training samples for the perception model: one view of one object, padded into batches.

A *sample* is a dictionary of numpy arrays for one view (n valid parts):

    image            (224, 224, 3) uint8        part_labels    (224, 224) int8, part index or -1
    points           (n, 1000, 3)  float32      instance_onehot (n, 20)   float32
    classes          (n,)          int64        visible_pixels (n,)       int64
    quat             (n, 4)        float32      trans          (n, 3)     float32   (targets; optional)
    name             str

:func:`view_sample` cuts one out of an object file's arrays; any code that renders views on the fly can build the
same dictionaries and evaluate them (:func:`perception.evaluate.evaluate_samples`). :func:`collate` pads a list
of samples to P_max part slots with a validity mask.
"""

from __future__ import annotations

import functools
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import torch
from torch.utils.data import DataLoader, Dataset, DistributedSampler, Sampler

from perception.dataset import list_objects
from perception.equivalence import instance_onehot

OBJECT_KEYS = ("points_norm", "instance_onehot", "equivalence_class")
OPTIONAL_OBJECT_KEYS = ("points_scale",)  # slim datasets only
VIEW_KEYS = ("images", "part_labels", "visible_pixels", "pose_quat_wxyz", "pose_translation_norm")
IDENTITY = np.array([1.0, 0.0, 0.0, 0.0], dtype=np.float32)


def part_points(arrays: dict) -> np.ndarray:
    """The part clouds (n, m, 3) as float32. A slim dataset (:mod:`perception.dataset.slim`) stores them as int8
    with a per-part scale ``points_scale`` (n,): point = int8 value / 127 x scale."""
    points = np.asarray(arrays["points_norm"])
    if points.dtype == np.int8:
        scale = np.asarray(arrays["points_scale"], dtype=np.float32)[:, None, None] / 127.0
        return points.astype(np.float32) * scale
    return points.astype(np.float32, copy=False)


def view_sample(arrays: dict, view: int, name: str = "") -> dict:
    """The sample of view ``view`` of one object (arrays as in :mod:`perception.dataset.sample`)."""
    return {
        "image": np.asarray(arrays["images"][view]),
        "part_labels": np.asarray(arrays["part_labels"][view]),
        "points": part_points(arrays),
        "instance_onehot": np.asarray(arrays["instance_onehot"], dtype=np.float32),
        "classes": np.asarray(arrays["equivalence_class"], dtype=np.int64),
        "visible_pixels": np.asarray(arrays["visible_pixels"][view], dtype=np.int64),
        "quat": np.asarray(arrays["pose_quat_wxyz"][view], dtype=np.float32),
        "trans": np.asarray(arrays["pose_translation_norm"][view], dtype=np.float32),
        "name": f"{name}/view{view}",
    }


def permute_parts(sample: dict, order: np.ndarray) -> dict:
    """``sample`` with its parts in the order ``order`` (new part k is old part ``order[k]``): every per-part
    array is reindexed, the pixel labels renamed, the equivalence classes renumbered in order of first appearance
    and the instance one-hots recomputed, exactly as if the object had listed its parts in that order.

    The parts of a procedural object come in the order its generator builds them (seat, back, legs, ...), a
    regularity that users' parts do not have; a network that reads the order (B-GRU) learns it. Training and
    evaluation therefore present the parts in a random order (:class:`ViewDataset`, ``shuffle_parts``)."""
    order = np.asarray(order, dtype=np.int64)
    n = len(sample["points"])
    if sorted(order.tolist()) != list(range(n)):
        raise ValueError(f"{sample.get('name', 'sample')}: {order.tolist()} is not an order of its {n} parts")
    out = dict(sample)
    for key in ("points", "visible_pixels", "quat", "trans"):
        if key in sample:
            out[key] = np.asarray(sample[key])[order]
    _, first, inverse = np.unique(np.asarray(sample["classes"])[order], return_index=True, return_inverse=True)
    rank = np.argsort(np.argsort(first))  # class ids numbered by first appearance in the new order
    out["classes"] = rank[inverse.reshape(-1)].astype(np.int64)
    out["instance_onehot"] = instance_onehot(out["classes"], np.asarray(sample["instance_onehot"]).shape[1])
    if "part_labels" in sample:
        labels = np.asarray(sample["part_labels"])
        new_index = np.empty(n, dtype=np.int64)
        new_index[order] = np.arange(n)
        out["part_labels"] = np.where(labels >= 0, new_index[np.maximum(labels, 0)], labels).astype(labels.dtype)
    return out


def shuffle_order(n_parts: int, seed: int, index: int, epoch: int = 0) -> np.ndarray:
    """The random part order of sample ``index`` in ``epoch`` (a permutation of ``range(n_parts)``), from
    ``numpy.random.default_rng([seed, epoch, index])``: the same on every run and every worker."""
    return np.random.default_rng([seed, epoch, index]).permutation(n_parts)


def object_files(roots: Sequence[str | Path], split: str, categories: Sequence[str] = ()) -> list[Path]:
    """Object files of one split from several dataset folders, optionally only some categories (the file name's
    first ``_`` field). A folder without split subfolders counts as the split itself."""
    files: list[Path] = []
    for root in roots:
        root = Path(root)
        if not root.is_dir():
            raise FileNotFoundError(f"dataset folder {root} not found")
        found = list_objects(root, split) if (root / split).is_dir() else sorted(root.glob("*.npz"))
        files += found
    if categories:
        files = [f for f in files if f.name.split("_")[0] in set(categories)]
    return files


class ViewDataset(Dataset):
    """Every view of every object file: index i -> (file, view). Files are read lazily, one sample at a time
    (only the arrays a sample needs are decompressed). ``limit``: at most this many views, evenly spread.
    ``shuffle_parts``: present each sample's parts in a random order (:func:`permute_parts`) drawn by
    :func:`shuffle_order` from ``seed``, the sample's index and the epoch (:meth:`set_epoch`); ``False``: the
    order of the file."""

    def __init__(self, files: Sequence[str | Path], limit: int = 0, shuffle_parts: bool = False, seed: int = 0):
        self.shuffle_parts, self.seed, self.epoch = shuffle_parts, seed, 0
        self.index: list[tuple[Path, int]] = []
        for path in files:
            with np.load(path, allow_pickle=False) as data:
                views = data["pose_quat_wxyz"].shape[0]
            self.index += [(Path(path), k) for k in range(views)]
        if limit and limit < len(self.index):
            # evenly spread over the sorted files, so that a limited validation set sees every category and
            # dataset folder rather than the first one only
            picks = np.linspace(0, len(self.index) - 1, limit).round().astype(int)
            self.index = [self.index[k] for k in picks]

    def __len__(self) -> int:
        return len(self.index)

    def set_epoch(self, epoch: int) -> None:
        """Draw the part orders of epoch ``epoch`` (the loaders' workers copy the dataset when they start)."""
        self.epoch = epoch

    def __getitem__(self, i: int) -> dict:
        path, view = self.index[i]
        with np.load(path, allow_pickle=False) as data:
            arrays = {key: data[key] for key in OBJECT_KEYS + OPTIONAL_OBJECT_KEYS if key in data.files}
            arrays.update({key: data[key][view: view + 1] for key in VIEW_KEYS})
        sample = view_sample(arrays, 0)
        sample["name"] = f"{path.stem}/view{view}"
        if self.shuffle_parts:
            sample = permute_parts(sample, shuffle_order(len(sample["points"]), self.seed, i, self.epoch))
        return sample


def collate(samples: Sequence[dict], max_parts: int = 20) -> dict:
    """Pad samples to ``max_parts`` part slots. Returns torch tensors:

    image (B, 3, H, W) uint8, part_labels (B, H, W) int64, points (B, P, N, 3), instance_onehot (B, P, 20),
    classes (B, P) (-1 padded), valid (B, P) bool, visible_pixels (B, P), quat (B, P, 4) (identity padded),
    trans (B, P, 3), n_parts (B,), and ``name`` (list of str). Valid parts fill the first slots.
    """
    b = len(samples)
    n_points = samples[0]["points"].shape[1]
    onehot_dim = samples[0]["instance_onehot"].shape[1]
    points = np.zeros((b, max_parts, n_points, 3), np.float32)
    onehot = np.zeros((b, max_parts, onehot_dim), np.float32)
    classes = np.full((b, max_parts), -1, np.int64)
    valid = np.zeros((b, max_parts), bool)
    visible = np.zeros((b, max_parts), np.int64)
    quat = np.tile(IDENTITY, (b, max_parts, 1))
    trans = np.zeros((b, max_parts, 3), np.float32)
    for i, s in enumerate(samples):
        n = len(s["points"])
        if n > max_parts:
            raise ValueError(f"{s.get('name', 'sample')} has {n} parts, more than {max_parts}")
        points[i, :n], onehot[i, :n], classes[i, :n] = s["points"], s["instance_onehot"], s["classes"]
        valid[i, :n] = True
        visible[i, :n] = s["visible_pixels"]
        if "quat" in s:
            quat[i, :n], trans[i, :n] = s["quat"], s["trans"]
    return {
        "image": torch.from_numpy(np.stack([s["image"] for s in samples])).permute(0, 3, 1, 2).contiguous(),
        "part_labels": torch.from_numpy(np.stack([s["part_labels"] for s in samples]).astype(np.int64)),
        "points": torch.from_numpy(points),
        "instance_onehot": torch.from_numpy(onehot),
        "classes": torch.from_numpy(classes),
        "valid": torch.from_numpy(valid),
        "visible_pixels": torch.from_numpy(visible),
        "quat": torch.from_numpy(quat),
        "trans": torch.from_numpy(trans),
        "n_parts": torch.from_numpy(valid.sum(1)),
        "name": [s.get("name", "") for s in samples],
    }


def to_device(batch: dict, device: torch.device | str) -> dict:
    return {k: v.to(device, non_blocking=True) if torch.is_tensor(v) else v for k, v in batch.items()}


class SkipSampler(Sampler):
    """Yields a sampler's indices after dropping the first ``skip`` (to resume mid-epoch)."""

    def __init__(self, sampler: Sampler, skip: int = 0):
        self.sampler, self.skip = sampler, skip

    def __iter__(self):
        for position, index in enumerate(self.sampler):
            if position >= self.skip:
                yield index

    def __len__(self) -> int:
        return max(0, len(self.sampler) - self.skip)


def epoch_loader(dataset: Dataset, batch_size: int, epoch: int, seed: int, rank: int = 0, world: int = 1,
                 skip_batches: int = 0, shuffle: bool = True, num_workers: int = 0, max_parts: int = 20,
                 drop_last: bool = True) -> DataLoader:
    """The batches of one epoch for one process: a :class:`DistributedSampler` (also with one process) seeded
    by ``seed`` and ``epoch``, so the order depends on nothing else and a resumed run sees the same batches;
    ``skip_batches`` drops the batches already trained on."""
    sampler = DistributedSampler(dataset, num_replicas=world, rank=rank, shuffle=shuffle, seed=seed,
                                 drop_last=drop_last)
    sampler.set_epoch(epoch)
    if hasattr(dataset, "set_epoch"):
        dataset.set_epoch(epoch)  # before the workers start and copy it
    # a generator of its own: the loader's worker seeds come from it, not from the global torch RNG
    generator = torch.Generator().manual_seed(seed * 100003 + epoch)
    return DataLoader(dataset, batch_size=batch_size, sampler=SkipSampler(sampler, skip_batches * batch_size),
                      num_workers=num_workers, drop_last=drop_last, generator=generator,
                      collate_fn=functools.partial(collate, max_parts=max_parts))


def batches_per_epoch(dataset: Dataset, batch_size: int, world: int = 1) -> int:
    per_rank = len(dataset) // world  # DistributedSampler with drop_last
    return per_rank // batch_size
