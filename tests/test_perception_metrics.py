"""Matching and the paper's metrics on hand-made cases."""

import numpy as np
import pytest
import torch

from perception.matching import batch_match, match_within_classes
from perception.metrics import MetricSummary, evaluate_assembly, part_accuracy_difference, pose_clouds
from perception.pointcloud import chamfer_distance


def stick(length=1.0, width=0.1, points=1000, seed=0):
    """A long thin box along x with a knob at +x: no rotational symmetry."""
    rng = np.random.default_rng(seed)
    p = rng.uniform(-0.5, 0.5, (points, 3)) * np.array([length, width, width])
    p[: points // 10] = rng.normal(0, 0.03, (points // 10, 3)) + np.array([0.5 * length, 0.1, 0])
    return p.astype(np.float32)


def z_rotation(degrees):
    half = np.radians(degrees) / 2
    return np.array([np.cos(half), 0, 0, np.sin(half)])


def chair_like():
    """Four identical legs (class 0), a seat (class 1) and a back (class 2), with their true poses."""
    leg, seat, back = stick(0.5, 0.05, seed=1), stick(1.0, 0.05, seed=2), stick(0.8, 0.2, seed=3)
    points = np.stack([leg, leg, leg, leg, seat, back])
    classes = np.array([0, 0, 0, 0, 1, 2])
    rng = np.random.default_rng(0)
    quat = rng.normal(size=(6, 4))
    quat /= np.linalg.norm(quat, axis=1, keepdims=True)
    trans = np.array([[0.4, 0.4, 0], [-0.4, 0.4, 0], [0.4, -0.4, 0], [-0.4, -0.4, 0], [0, 0, 0.3], [0, 0.4, 0.6]])
    return points, classes, quat, trans


def test_identical_poses_are_perfect():
    points, classes, quat, trans = chair_like()
    result = evaluate_assembly(points, quat, trans, quat, trans, classes)
    assert result.correct.all() and result.shape_chamfer == 0.0
    np.testing.assert_allclose(result.part_chamfer, 0.0, atol=1e-12)
    summary = MetricSummary()
    summary.add(result)
    figures = summary.summary()
    assert figures["part_accuracy"] == 1.0 and figures["shape_chamfer"] == 0.0 and figures["parts"] == 6


def test_swapped_equivalent_parts_still_correct():
    points, classes, quat, trans = chair_like()
    order = np.array([2, 0, 3, 1, 4, 5])  # legs predicted in another order
    result = evaluate_assembly(points, quat[order], trans[order], quat, trans, classes)
    assert result.correct.all()
    assert result.match[:4].tolist() == [2, 0, 3, 1]
    assert result.shape_chamfer < 1e-12
    # the same exchange across classes is an error
    order = np.array([0, 1, 2, 3, 5, 4])
    assert not evaluate_assembly(points, quat[order], trans[order], quat, trans, classes).correct[4:].any()


def test_quarter_turn_of_asymmetric_part_fails():
    points, classes, quat, trans = chair_like()
    wrong = quat.copy()
    w1, x1, y1, z1 = quat[4]
    w2, _, _, z2 = z_rotation(90)  # a 90-degree turn of the long part about its own z axis
    wrong[4] = [w1 * w2 - z1 * z2, x1 * w2 + y1 * z2, y1 * w2 - x1 * z2, w1 * z2 + z1 * w2]
    result = evaluate_assembly(points, wrong, trans, quat, trans, classes)
    assert not result.correct[4] and result.correct[[0, 1, 2, 3, 5]].all()
    summary = MetricSummary()
    summary.add(result)
    assert summary.summary()["part_accuracy"] == 5 / 6
    assert result.shape_chamfer > 0
    # the part chamfer is the project's chamfer distance between the two posed clouds
    posed = pose_clouds(points[4:5], wrong[4:5], trans[4:5])[0]
    true = pose_clouds(points[4:5], quat[4:5], trans[4:5])[0]
    assert abs(result.part_chamfer[4] - chamfer_distance(posed, true)) < 1e-9


def test_visible_and_invisible_accuracy_and_torch_inputs():
    points, classes, quat, trans = chair_like()
    far = trans.copy()
    far[5] += 1.0  # the back misplaced
    visible = np.array([10, 10, 10, 10, 10, 0])  # ... and invisible
    result = evaluate_assembly(torch.from_numpy(points), torch.from_numpy(quat), torch.from_numpy(far),
                               torch.from_numpy(quat), torch.from_numpy(trans), torch.from_numpy(classes), visible)
    summary = MetricSummary()
    summary.add(result)
    figures = summary.summary()
    assert figures["part_accuracy_visible"] == 1.0 and figures["part_accuracy_invisible"] == 0.0
    assert figures["visible_parts"] == 5 and figures["invisible_parts"] == 1


def test_matching_recovers_permutation_inside_classes_only():
    rng = np.random.default_rng(0)
    classes = np.array([0, 1, 0, 0, 2, 1])
    truth = np.array([3, 5, 0, 2, 4, 1])  # a permutation inside each class
    cost = rng.uniform(1, 2, (6, 6))
    cost[np.arange(6), truth] = 0.0
    cost[0, 4] = -100.0  # cheap but across classes: must not be used
    perm = match_within_classes(cost, classes)
    assert perm.tolist() == truth.tolist()
    assert (classes[perm] == classes).all()


def test_batch_matching_respects_padding():
    cost = torch.rand(2, 5, 5)
    cost[0, 0, 1] = cost[0, 1, 0] = -1.0
    classes = torch.tensor([[0, 0, 1, -1, -1], [0, 1, 1, 1, -1]])
    valid = classes >= 0
    perm = batch_match(cost, classes, valid)
    assert perm[0].tolist()[:3] == [1, 0, 2] and perm[0].tolist()[3:] == [3, 4]
    assert perm[1, 4].item() == 4 and sorted(perm[1, 1:4].tolist()) == [1, 2, 3]


def test_paired_difference_of_part_accuracy():
    """The difference is the pooled Part Accuracy's; its interval is narrow when one method wins on every object,
    wide and across zero when the methods trade wins, and an empty or inconsistent count is refused."""
    rng = np.random.default_rng(5)
    parts = rng.integers(4, 15, size=200)
    b = rng.binomial(parts, 0.5)
    better = np.minimum(b + 1, parts)  # one part more on every object
    win = part_accuracy_difference(better, b, parts)
    assert win.difference == pytest.approx((better.sum() - b.sum()) / parts.sum())
    assert win.significant and 0 < win.low < win.difference < win.high and win.objects == 200
    traded = part_accuracy_difference(rng.binomial(parts, 0.5), rng.binomial(parts, 0.5), parts)
    assert traded.low < 0 < traded.high and not traded.significant
    assert part_accuracy_difference(b, better, parts).high < 0  # the other way round
    assert part_accuracy_difference(better, b, parts, seed=1) != win  # another resampling draw
    with pytest.raises(ValueError, match="one count per object"):
        part_accuracy_difference(b, better[:-1], parts)
    with pytest.raises(ValueError, match="at most as many"):
        part_accuracy_difference(parts + 1, b, parts)
