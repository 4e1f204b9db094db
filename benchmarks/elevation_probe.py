"""Can the picture alone give the camera's elevation, and so "up"? A probe for the up-axis target of issue 3.

The training cameras have no roll, so up in the camera frame is ``(0, -cos e, -sin e)`` for one unknown, the
elevation ``e`` (``perception/upright.py``); an error in ``e`` is the up-axis error. This trains a small CNN from
scratch on the CPU to regress ``e`` from the rendered image (56x56, the 224x224 picture averaged over 4x4 blocks),
on the ``train`` split of built dataset folders, and reports its error on their ``test`` split (objects never
trained on), against the parts-based estimate's 31.7% within 5 degrees (`benchmarks/RESULTS.md`). The network and
its input are :mod:`perception.elevation`'s; ``OUT/elevation.pt`` is the weights file it loads.

    python benchmarks/elevation_probe.py --data data/gpu_chair_3 data/gpu_table_3 data/gpu_cabinet_3 \\
        data/gpu_chair_mixed data/gpu_table_mixed data/gpu_cabinet_mixed --minutes 20 --out out/elevation_probe

``--extra-train DIR ...`` adds the ``train`` splits of more folders (their ``test`` splits are not scored, so the
test figures stay comparable), such as objects built with ``perception.dataset build --stretch``.
``--furniture DIR`` also scores the trained head, and the bundled one (``perception/weights/elevation.pt``), on
every assembly folder under ``DIR`` rendered once as ``python -m perception.evaluate --assemblies DIR --seed 1``
renders it: the pictures of ``benchmarks/perception_accuracy.py --furniture``.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np
import torch
from torch import nn

# Run as a script, this file's folder comes first on sys.path and its name would hide the perception package.
sys.path[:] = [p for p in sys.path if Path(p or ".").resolve() != Path(__file__).resolve().parent]

from perception.dataset import list_objects  # noqa: E402
from perception.elevation import ElevationNet, downsample, load_elevation_model  # noqa: E402
from planning.pose import Pose  # noqa: E402


def load_split(folders: list[str], split: str) -> tuple[np.ndarray, np.ndarray]:
    """(images (N, 3, 56, 56) uint8, elevations (N,) degrees) of every view of every object of ``split``."""
    images, elevations = [], []
    for folder in folders:
        for path in list_objects(folder, split):
            with np.load(path, allow_pickle=False) as data:
                views = data["images"]  # (V, 224, 224, 3)
                quats = data["camera_from_assembly_quat_wxyz"]
            images.append(downsample(views))
            for q in quats:
                up = Pose(np.zeros(3), q).rotation[:, 2]  # assembly +z in the camera frame
                elevations.append(float(np.degrees(np.arcsin(np.clip(-up[2], -1.0, 1.0)))))
    return np.concatenate(images), np.asarray(elevations, dtype=np.float32)


FURNITURE_SEED = 1  # benchmarks/perception_accuracy.py's RENDER_SEED


def furniture_views(root: Path, seed: int = FURNITURE_SEED) -> tuple[list[str], np.ndarray, np.ndarray]:
    """(names, images (N, 3, 56, 56) uint8, elevations (N,) degrees): one rendering of every assembly folder under
    ``root``, drawn exactly as :func:`perception.evaluate_assemblies.evaluate_assemblies` draws its first view."""
    from cell.render import render_assembly
    from perception.evaluate_assemblies import assembly_folders, shuffled_parts
    from planning.assembly import read_assembly

    names, images, elevations = [], [], []
    for index, folder in enumerate(assembly_folders(root)):
        view = render_assembly(shuffled_parts(read_assembly(folder), seed, index), np.random.default_rng([seed, index]))
        up = view.camera_from_assembly.rotation[:, 2]  # assembly +z in the camera frame
        names.append(folder.name)
        images.append(downsample(view.rgb))
        elevations.append(float(np.degrees(np.arcsin(np.clip(-up[2], -1.0, 1.0)))))
    return names, np.stack(images), np.asarray(elevations, dtype=np.float32)


def error_figures(err: np.ndarray) -> dict:
    return {"mean_deg": float(err.mean()), "median_deg": float(np.median(err)),
            "p95_deg": float(np.percentile(err, 95)), "within_5_deg": float(np.mean(err <= 5))}


def errors_deg(model: nn.Module, images: np.ndarray, elevations: np.ndarray, mean: float, scale: float) -> np.ndarray:
    """Absolute elevation errors (degrees) of ``model`` on ``images``; the model's train/eval mode is kept."""
    training = model.training
    model.eval()
    out = []
    with torch.no_grad():
        for start in range(0, len(images), 256):
            pred = model(torch.from_numpy(images[start:start + 256])) * scale + mean
            out.append(np.abs(pred.numpy() - elevations[start:start + 256]))
    model.train(training)
    return np.concatenate(out)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--data", nargs="+", required=True, help="dataset folders built by perception.dataset")
    parser.add_argument("--extra-train", nargs="+", default=[], help="more folders whose train split is added "
                        "(their test split is not scored)")
    parser.add_argument("--furniture", type=Path, help="also score on one rendering of each assembly folder here")
    parser.add_argument("--minutes", type=float, default=20.0, help="training time on this machine")
    parser.add_argument("--steps", type=int, help="train exactly this many steps instead (repeats a run)")
    parser.add_argument("--batch", type=int, default=64)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", type=Path, default=Path("out/elevation_probe"))
    args = parser.parse_args()
    torch.manual_seed(args.seed)
    rng = np.random.default_rng(args.seed)
    started = time.perf_counter()
    train_x, train_y = load_split(args.data + args.extra_train, "train")
    test_x, test_y = load_split(args.data, "test")
    print(f"{len(train_x)} training and {len(test_x)} test views loaded in {time.perf_counter() - started:.0f} s; "
          f"elevations {train_y.min():.1f}-{train_y.max():.1f} degrees", flush=True)
    mean, scale = float(train_y.mean()), float(train_y.std())
    baseline = np.abs(test_y - mean)  # always guessing the mean elevation
    model = ElevationNet()
    optimizer = torch.optim.AdamW(model.parameters(), lr=2e-3, weight_decay=1e-4)
    deadline = time.perf_counter() + 60.0 * args.minutes
    step, history = 0, []
    while (step < args.steps) if args.steps else (time.perf_counter() < deadline):
        batch = rng.integers(0, len(train_x), args.batch)
        images = torch.from_numpy(train_x[batch])
        if rng.random() < 0.5:  # a mirrored picture has the same elevation
            images = images.flip(3)
        target = torch.from_numpy((train_y[batch] - mean) / scale)
        loss = nn.functional.smooth_l1_loss(model(images), target, beta=0.1)
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        optimizer.step()
        step += 1
        if step % 500 == 0:
            err = errors_deg(model, test_x[:1000], test_y[:1000], mean, scale)
            history.append({"step": step, "seconds": round(time.perf_counter() - started, 1),
                            "test_mean_deg": float(err.mean()), "within_5": float(np.mean(err <= 5))})
            print(history[-1], flush=True)
    err = errors_deg(model, test_x, test_y, mean, scale)
    result = {"train_views": len(train_x), "test_views": len(test_x), "steps": step, "minutes": args.minutes,
              **error_figures(err),
              "guess_the_mean": {"mean_deg": float(baseline.mean()), "within_5_deg": float(np.mean(baseline <= 5))},
              "history": history}
    if args.furniture:
        names, real_x, real_y = furniture_views(args.furniture)
        real = {"trained": errors_deg(model, real_x, real_y, mean, scale)}
        bundled = load_elevation_model()
        if bundled is not None:
            bundled_model, bundled_mean, bundled_scale = bundled
            real["bundled"] = errors_deg(bundled_model, real_x, real_y, bundled_mean, bundled_scale)
        result["furniture"] = {name: error_figures(err) for name, err in real.items()}
        result["furniture"]["per_object_deg"] = {name: {k: round(float(err[i]), 2) for k, err in real.items()}
                                                 for i, name in enumerate(names)}
        for name, err in real.items():
            print(f"{args.furniture.name}, {len(names)} objects, {name} head: elevation error mean {err.mean():.2f}, "
                  f"p95 {np.percentile(err, 95):.2f} degrees; within 5 degrees {100 * np.mean(err <= 5):.1f}%")
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "result.json").write_text(json.dumps(result, indent=1) + "\n")
    torch.save({"model": model.state_dict(), "mean": mean, "scale": scale}, args.out / "elevation.pt")
    print(f"test: elevation error mean {result['mean_deg']:.2f}, median {result['median_deg']:.2f}, p95 "
          f"{result['p95_deg']:.2f} degrees; within 5 degrees {100 * result['within_5_deg']:.1f}% "
          f"(guessing the mean: {100 * result['guess_the_mean']['within_5_deg']:.1f}%); {step} steps")
    return 0


if __name__ == "__main__":
    sys.exit(main())
