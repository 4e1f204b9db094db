"""The paper's evaluation metrics (Tables 1 and 2), on numpy arrays or torch tensors.

- Part Accuracy: the fraction of parts whose chamfer distance between the part cloud posed by the prediction and
  by the ground truth is below 0.1 (normalised units), after matching predictions to ground-truth parts inside
  equivalence classes (matching cost: that same chamfer distance, on 100 points per part). Also for visible
  parts (more than 0 pixels in the ground-truth mask) and invisible ones. Counted over all parts of all samples.
- Shape Chamfer: the chamfer distance between the whole predicted shape (all parts posed by the prediction) and
  the whole true shape; averaged over samples.

Chamfer distances are :func:`perception.pointcloud.chamfer_distance` (squared nearest-neighbour distances, mean
per direction, summed), on every point of every part.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from perception.matching import match_within_classes
from perception.pointcloud import chamfer_distance

PART_ACCURACY_THRESHOLD = 0.1
MATCH_POINTS = 100


def as_numpy(x) -> np.ndarray:
    if hasattr(x, "detach"):
        x = x.detach().cpu().numpy()
    return np.asarray(x)


def quat_to_matrices(quat: np.ndarray) -> np.ndarray:
    """(n, 3, 3) rotation matrices of quaternions (n, 4), w first (normalised here)."""
    q = np.asarray(quat, dtype=np.float64)
    w, x, y, z = (q / np.linalg.norm(q, axis=-1, keepdims=True)).T
    return np.stack([
        1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w),
        2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w),
        2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y),
    ], axis=-1).reshape(-1, 3, 3)


def pose_clouds(points: np.ndarray, quat: np.ndarray, trans: np.ndarray) -> np.ndarray:
    """(n, N, 3) clouds posed by (n, 4) quaternions and (n, 3) translations."""
    return np.einsum("nij,npj->npi", quat_to_matrices(quat), points) + np.asarray(trans)[:, None, :]


@dataclass
class AssemblyResult:
    """Per-sample outcome: per part (in prediction order) the chamfer to its matched ground truth, whether it
    is correct, whether its matched ground-truth part is visible; and the shape chamfer."""

    part_chamfer: np.ndarray
    correct: np.ndarray
    visible: np.ndarray
    shape_chamfer: float
    match: np.ndarray


def _subsample_chamfer(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Chamfer distances between clouds a (..., m, 3) and b (..., m, 3) by brute force (small m)."""
    d = (a**2).sum(-1)[..., :, None] + (b**2).sum(-1)[..., None, :] - 2.0 * a @ np.swapaxes(b, -1, -2)
    d = np.maximum(d, 0.0)
    return d.min(-1).mean(-1) + d.min(-2).mean(-1)


def evaluate_assembly(points, quat, trans, gt_quat, gt_trans, classes, visible_pixels=None,
                      threshold: float = PART_ACCURACY_THRESHOLD, match_points: int = MATCH_POINTS) -> AssemblyResult:
    """Metrics of one object with n parts: points (n, N, 3) canonical clouds, predicted and true poses (n, 4),
    (n, 3), classes (n,), visible_pixels (n,) ground-truth mask sizes (``None``: all visible).

    Prediction i is compared with ground-truth part j on its own cloud (posed by prediction i and by the true
    pose of j). The matching inside each class minimises the chamfer distance on the first ``match_points``
    points of each cloud (the dataset's clouds are in farthest-point order, so these are evenly spread); the
    reported chamfer of each matched pair uses every point."""
    points, classes = as_numpy(points).astype(np.float64), as_numpy(classes)
    gt_quat, gt_trans = as_numpy(gt_quat).astype(np.float64), as_numpy(gt_trans).astype(np.float64)
    n = len(points)
    pred = pose_clouds(points, as_numpy(quat), as_numpy(trans))
    cost = np.full((n, n), np.inf)
    for c in np.unique(classes):
        members = np.flatnonzero(classes == c)
        if len(members) == 1:
            cost[members[0], members[0]] = 0.0
            continue
        sub = points[members, :match_points]  # (c, m, 3)
        rotations = quat_to_matrices(gt_quat[members])  # (c, 3, 3): true pose of each member j
        true = np.einsum("jab,ima->ijmb", rotations.transpose(0, 2, 1), sub) + gt_trans[members][None, :, None]
        cost[np.ix_(members, members)] = _subsample_chamfer(pred[members, None, :match_points], true)
    match = match_within_classes(cost, classes)
    true_matched = pose_clouds(points, gt_quat[match], gt_trans[match])
    part_chamfer = np.array([chamfer_distance(pred[i], true_matched[i]) for i in range(n)])
    visible = np.ones(n, bool) if visible_pixels is None else as_numpy(visible_pixels)[match] > 0
    true_shape = pose_clouds(points, gt_quat, gt_trans)
    shape = chamfer_distance(pred.reshape(-1, 3), true_shape.reshape(-1, 3))
    return AssemblyResult(part_chamfer, part_chamfer < threshold, visible, shape, match)


def evaluate_batch(outputs: dict, batch: dict, threshold: float = PART_ACCURACY_THRESHOLD) -> list[AssemblyResult]:
    """:func:`evaluate_assembly` for every object of a padded batch (final predictions ``quat``/``trans``)."""
    results = []
    valid = as_numpy(batch["valid"])
    for b in range(len(valid)):
        idx = np.flatnonzero(valid[b])
        results.append(evaluate_assembly(
            as_numpy(batch["points"][b])[idx], as_numpy(outputs["quat"][b])[idx], as_numpy(outputs["trans"][b])[idx],
            as_numpy(batch["quat"][b])[idx], as_numpy(batch["trans"][b])[idx], as_numpy(batch["classes"][b])[idx],
            as_numpy(batch["visible_pixels"][b])[idx], threshold))
    return results


@dataclass
class MetricSummary:
    """Accumulates :class:`AssemblyResult` s; :meth:`summary` gives the table's figures."""

    results: list[AssemblyResult] = field(default_factory=list)

    def add(self, results) -> None:
        self.results.extend([results] if isinstance(results, AssemblyResult) else results)

    def summary(self) -> dict:
        if not self.results:
            return {"samples": 0, "parts": 0, "part_accuracy": float("nan"), "shape_chamfer": float("nan"),
                    "part_accuracy_visible": float("nan"), "part_accuracy_invisible": float("nan"),
                    "visible_parts": 0, "invisible_parts": 0}
        correct = np.concatenate([r.correct for r in self.results])
        visible = np.concatenate([r.visible for r in self.results])

        def fraction(mask):
            return float(correct[mask].mean()) if mask.any() else float("nan")

        return {
            "samples": len(self.results),
            "parts": int(len(correct)),
            "part_accuracy": fraction(np.ones_like(correct)),
            "shape_chamfer": float(np.mean([r.shape_chamfer for r in self.results])),
            "part_accuracy_visible": fraction(visible),
            "part_accuracy_invisible": fraction(~visible),
            "visible_parts": int(visible.sum()),
            "invisible_parts": int((~visible).sum()),
        }


@dataclass(frozen=True)
class PairedDifference:
    """Part Accuracy of method A minus that of method B on the same objects, with a bootstrap confidence
    interval (``low``, ``high``); ``objects``: how many objects were paired."""

    difference: float
    low: float
    high: float
    objects: int

    @property
    def significant(self) -> bool:
        """The interval excludes zero."""
        return self.low > 0 or self.high < 0


def part_accuracy_difference(correct_a: np.ndarray, correct_b: np.ndarray, parts: np.ndarray,
                             resamples: int = 2000, confidence: float = 0.95, seed: int = 0) -> PairedDifference:
    """Paired bootstrap over objects of the Part Accuracy difference of two methods scored on the same objects.

    correct_a, correct_b: (K,) parts each method placed correctly in object k; parts: (K,) parts of object k.
    Part Accuracy counts over all parts (sum of correct / sum of parts); each resample draws K objects with
    replacement (``numpy.random.default_rng(seed)``), the same objects for both methods, so the interval reflects
    which objects a test set happens to hold and not the methods' shared difficulty."""
    correct_a, correct_b, parts = (np.asarray(x, dtype=np.float64) for x in (correct_a, correct_b, parts))
    if not (correct_a.shape == correct_b.shape == parts.shape) or parts.ndim != 1 or len(parts) == 0:
        raise ValueError(f"one count per object and method expected, got shapes {correct_a.shape}, "
                         f"{correct_b.shape}, {parts.shape}")
    if np.any(parts <= 0) or np.any(correct_a > parts) or np.any(correct_b > parts):
        raise ValueError("every object needs parts > 0 and at most as many correct parts")
    difference = (correct_a.sum() - correct_b.sum()) / parts.sum()
    picks = np.random.default_rng(seed).integers(0, len(parts), size=(resamples, len(parts)))
    samples = (correct_a[picks].sum(1) - correct_b[picks].sum(1)) / parts[picks].sum(1)
    tail = 100 * (1 - confidence) / 2
    low, high = np.percentile(samples, [tail, 100 - tail])
    return PairedDifference(float(difference), float(low), float(high), len(parts))
