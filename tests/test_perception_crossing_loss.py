"""The crossing penalty (beyond the paper): two thin panels, one put through the other by the prediction, cost
the depth it went through; passing beside a panel, staying on the true side or matching the truth costs nothing;
the gradient pushes the panels back apart; pose_losses adds it with its weight only when asked."""

from dataclasses import replace

import numpy as np
import pytest
import torch

from perception.config import load_config
from perception.losses import crossing_penalty, pose_losses

HALF_THICKNESS = 0.01
GAP = 0.1  # true height of panel 1 above panel 0, normalised units


def panels(seed=0):
    """(1, 2, 400, 3): two identical thin panels (1.0 x 0.6 x 0.02) in their own frames, thinnest axis z."""
    rng = np.random.default_rng(seed)
    cloud = rng.uniform(-1, 1, (400, 3)) * np.array([0.5, 0.3, HALF_THICKNESS])
    cloud[:8] = np.array([0.5, 0.3, HALF_THICKNESS]) * np.sign(rng.normal(size=(8, 3)))  # the box's corners
    return torch.tensor(np.stack([cloud, cloud]), dtype=torch.float32).unsqueeze(0)


def penalty(pred_trans, true_trans=((0, 0, 0), (0, 0, GAP)), pred_quat=None):
    points = panels()
    identity = torch.tensor([[[1.0, 0, 0, 0]] * 2])
    pred_quat = identity if pred_quat is None else pred_quat
    return crossing_penalty(points, pred_quat, torch.tensor([pred_trans], dtype=torch.float32), identity,
                            torch.tensor([true_trans], dtype=torch.float32), torch.ones(1, 2, dtype=torch.bool),
                            points)


def test_a_panel_put_through_the_other_costs_the_depth_it_went_through():
    # panel 1 belongs 0.1 above panel 0; predicted 0.1 below it, it went 0.1 + 0.01 past panel 0's lower face
    # (and panel 0 as far past panel 1's upper face, seen from panel 1)
    assert float(penalty(((0, 0, 0), (0, 0, -GAP)))) == pytest.approx(GAP + HALF_THICKNESS, abs=2e-3)
    deeper = float(penalty(((0, 0, 0), (0, 0, -2 * GAP))))
    assert deeper == pytest.approx(2 * GAP + HALF_THICKNESS, abs=2e-3)
    # both at one height, each half-way into the other: only the half past the upper face counts
    assert 0 < float(penalty(((0, 0, 0), (0, 0, 0.0)))) < 2 * HALF_THICKNESS


@pytest.mark.parametrize("pred_trans", [
    ((0, 0, 0), (0, 0, GAP)),  # the truth
    ((0, 0, 0), (0.2, 0.1, 0.3)),  # off, but on its true side
    ((0, 0, 0), (2.0, 0, -GAP)),  # below panel 0 but beside it: went round, not through
    ((0.5, 0.5, 0.5), (0.5, 0.5, 0.5 + GAP)),  # both moved together
])
def test_no_cost_without_a_crossing(pred_trans):
    assert float(penalty(pred_trans)) == 0.0


def test_rotation_is_in_the_panels_frames():
    # both panels turned 90 degrees about x together: the truth seen from either panel is unchanged
    quat = torch.tensor([[[np.cos(np.pi / 4), np.sin(np.pi / 4), 0, 0]] * 2], dtype=torch.float32)
    assert float(penalty(((0, 0, 0), (0, -GAP, 0)), pred_quat=quat)) == 0.0  # panel 1 on panel 0's + z side
    # (rounding may put the 8 corner points of 400 just outside the footprint: 2% less)
    assert float(penalty(((0, 0, 0), (0, GAP, 0)), pred_quat=quat)) == pytest.approx(GAP + HALF_THICKNESS,
                                                                                     rel=0.03)


def test_the_gradient_pushes_the_panels_back_apart():
    trans = torch.tensor([[[0.0, 0, 0], [0, 0, -GAP]]], requires_grad=True)
    points = panels()
    identity = torch.tensor([[[1.0, 0, 0, 0]] * 2])
    truth = torch.tensor([[[0.0, 0, 0], [0, 0, GAP]]])
    value = crossing_penalty(points, identity, trans, identity, truth, torch.ones(1, 2, dtype=torch.bool), points)
    value.backward()
    assert trans.grad[0, 1, 2] < 0 < trans.grad[0, 0, 2]  # descent lifts panel 1 and lowers panel 0
    assert float(trans.grad[0, :, :2].abs().max()) == 0.0  # and does not slide them sideways


def test_moving_the_crossing_part_only_keeps_the_crossed_frame_still():
    """Two identical panels put through each other: moving the crossing part only leaves the value as it is,
    and each panel's translation gradient is then its own crossing's alone, half of the two-sided one (where
    each panel also receives the push of the other's crossing through its frame)."""
    points = panels()
    identity = torch.tensor([[[1.0, 0, 0, 0]] * 2])
    truth = torch.tensor([[[0.0, 0, 0], [0, 0, GAP]]])
    valid = torch.ones(1, 2, dtype=torch.bool)
    grads = []
    for one_sided in (False, True):
        trans = torch.tensor([[[0.0, 0, 0], [0, 0, -GAP]]], requires_grad=True)
        value = crossing_penalty(points, identity, trans, identity, truth, valid, points, one_sided)
        value.backward()
        grads.append((float(value.detach()), trans.grad.clone()))
    (both_value, both), (one_value, one) = grads
    assert one_value == pytest.approx(both_value)
    assert one[0, 1, 2] < 0 < one[0, 0, 2]
    assert torch.allclose(one, both / 2)


def test_pose_losses_add_the_penalty_only_when_weighted():
    config = load_config("tiny").loss
    assert config.crossing == 0.0  # the paper's loss by default
    points = panels()[:, :, :50].repeat(2, 1, 1, 1)
    batch = {"points": torch.cat([points, torch.zeros(2, 1, 50, 3)], dim=1),
             "valid": torch.tensor([[True, True, False]] * 2), "classes": torch.tensor([[0, 1, 2]] * 2),
             "quat": torch.tensor([[[1.0, 0, 0, 0]] * 3] * 2), "trans": torch.tensor([[[0.0, 0, 0], [0, 0, GAP],
                                                                                     [0, 0, 0]]] * 2)}
    crossed = batch["trans"].clone()
    crossed[:, 1, 2] = -GAP
    paper = pose_losses(batch["quat"], crossed, batch, config)
    assert "crossing" not in paper
    weighted = pose_losses(batch["quat"], crossed, batch, replace(config, crossing=0.5))
    # (told apart by their classes: two equivalent panels would be matched the other way round, and panel 1
    # below panel 0 is then the true pair of panels, only lower)
    assert float(weighted["crossing"]) > GAP
    assert float(weighted["loss"]) == pytest.approx(float(paper["loss"]) + 0.5 * float(weighted["crossing"]))
    truth = pose_losses(batch["quat"], batch["trans"], batch, replace(config, crossing=0.5))
    assert float(truth["crossing"]) == 0.0
