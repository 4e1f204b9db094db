"""Classes of geometrically equivalent parts, as in the paper: two parts are equivalent when their canonical
bounding-box dimensions differ by less than 0.1 on every axis and the chamfer distance between their
normalised point clouds is below 0.02 (under the best of the four right-handed sign flips of the PCA axes,
since a principal axis has no intrinsic direction)."""

from __future__ import annotations

import networkx as nx
import numpy as np
from scipy.spatial import cKDTree

EXTENT_TOLERANCE = 0.1
CHAMFER_TOLERANCE = 0.02
MAX_PART_INSTANCES = 20  # P_max: length of the instance one-hot

_PROPER_FLIPS = np.array([[1, 1, 1], [1, -1, -1], [-1, 1, -1], [-1, -1, 1]], dtype=np.float32)


def aligned_chamfer(points_a: np.ndarray, points_b: np.ndarray, tree_a: cKDTree | None = None,
                    tree_b: cKDTree | None = None) -> float:
    """:func:`~perception.pointcloud.chamfer_distance` between two canonical clouds, minimised over the axis
    sign flips. A flip F is an isometry and its own inverse, so the b -> F(a) distances equal F(b) -> a ones
    and both directions reuse the trees of the unflipped clouds (pass them in to reuse across pairs)."""
    tree_a = tree_a if tree_a is not None else cKDTree(points_a)
    tree_b = tree_b if tree_b is not None else cKDTree(points_b)
    best = np.inf
    for flip in _PROPER_FLIPS:
        d_ab, _ = tree_b.query(points_a * flip)
        d_ba, _ = tree_a.query(points_b * flip)
        best = min(best, float(np.mean(d_ab**2) + np.mean(d_ba**2)))
    return best


def _within_chamfer(points_a, points_b, tree_a: cKDTree, tree_b: cKDTree, tolerance: float) -> bool:
    """Whether :func:`aligned_chamfer` is below ``tolerance``, stopping as soon as the answer is known."""
    for flip in _PROPER_FLIPS:
        d_ab, _ = tree_b.query(points_a * flip)
        one_way = float(np.mean(d_ab**2))
        if one_way >= tolerance:
            continue
        d_ba, _ = tree_a.query(points_b * flip)
        if one_way + float(np.mean(d_ba**2)) < tolerance:
            return True
    return False


def equivalence_classes(points_norm: np.ndarray, extents_norm: np.ndarray,
                        extent_tolerance: float = EXTENT_TOLERANCE,
                        chamfer_tolerance: float = CHAMFER_TOLERANCE) -> np.ndarray:
    """(N,) int64 class id per part, numbered 0.. in order of first appearance.

    points_norm: (N, P, 3) canonical clouds, normalised units. extents_norm: (N, 3) canonical box dimensions.
    Classes are the connected components of the pairwise relation (so equivalence is transitive); a pair already
    connected through others is not compared again.
    """
    n = len(points_norm)
    trees = [cKDTree(p) for p in points_norm]
    graph = nx.utils.UnionFind(range(n))
    for i in range(n):
        for j in range(i + 1, n):
            if graph[i] == graph[j] or np.any(np.abs(extents_norm[i] - extents_norm[j]) >= extent_tolerance):
                continue
            if _within_chamfer(points_norm[i], points_norm[j], trees[i], trees[j], chamfer_tolerance):
                graph.union(i, j)
    classes = np.empty(n, dtype=np.int64)
    roots: dict[int, int] = {}
    for i in range(n):
        classes[i] = roots.setdefault(graph[i], len(roots))
    return classes


def instance_onehot(classes: np.ndarray, max_instances: int = MAX_PART_INSTANCES) -> np.ndarray:
    """(N, max_instances) float32: one-hot of each part's index among the parts of its class."""
    onehot = np.zeros((len(classes), max_instances), dtype=np.float32)
    seen: dict[int, int] = {}
    for i, c in enumerate(classes):
        k = seen.get(int(c), 0)
        if k >= max_instances:
            raise ValueError(f"more than {max_instances} equivalent parts in class {int(c)}")
        onehot[i, k] = 1.0
        seen[int(c)] = k + 1
    return onehot
