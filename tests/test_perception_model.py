"""Networks and losses on a batch of two objects with different part counts: shapes, unit quaternions, padding
that never reaches valid outputs, zero losses for perfect predictions, gradients to every parameter."""

from dataclasses import replace

import numpy as np
import pytest
import torch

from perception.config import load_config
from perception.data import collate
from perception.equivalence import instance_onehot
from perception.losses import model_pose_loss, pose_losses, segmentation_loss, target_masks
from perception.model import MODELS, build_model
from perception.model.graph import AssemblyGraph, knn_adjacency
from perception.model.pointnet import PartEncoder
from perception.model.resnet import ResNetEncoder
from perception.model.unet import SegmentationNet

CONFIG = load_config("tiny")
CLASSES = ([0, 0, 1], [0, 1, 1, 2, 2, 3])


def sample(classes, seed):
    rng = np.random.default_rng(seed)
    classes = np.asarray(classes)
    n = len(classes)
    clouds = {c: (rng.uniform(-0.5, 0.5, (1000, 3)) * rng.uniform(0.05, 1.0, 3)).astype(np.float32)
              for c in np.unique(classes)}
    quat = rng.normal(size=(n, 4)).astype(np.float32)
    quat /= np.linalg.norm(quat, axis=1, keepdims=True)
    labels = np.full((224, 224), -1, np.int8)
    for i in range(n):  # a square per part
        labels[20 + 30 * i: 45 + 30 * i, 30 + 20 * i: 80 + 20 * i] = i
    return {"image": rng.integers(0, 256, (224, 224, 3), dtype=np.uint8), "part_labels": labels,
            "points": np.stack([clouds[c] for c in classes]), "instance_onehot": instance_onehot(classes),
            "classes": classes.astype(np.int64), "visible_pixels": np.bincount(labels[labels >= 0], minlength=n),
            "quat": quat, "trans": rng.uniform(-0.5, 0.5, (n, 3)).astype(np.float32), "name": f"s{seed}"}


@pytest.fixture(scope="module")
def batch():
    return collate([sample(c, i) for i, c in enumerate(CLASSES)])


def scramble_padding(batch, seed=1):
    """The same batch with other values in every padded slot."""
    g = torch.Generator().manual_seed(seed)
    out = dict(batch)
    pad = ~batch["valid"]
    for key in ("points", "instance_onehot", "quat", "trans"):
        x = batch[key].clone()
        x[pad] = torch.rand(x[pad].shape, generator=g)
        out[key] = x
    classes = batch["classes"].clone()
    classes[pad] = 0
    out["classes"] = classes
    return out


@pytest.mark.parametrize("kind", sorted(MODELS))
def test_shapes_unit_quaternions_and_padding(kind, batch):
    torch.manual_seed(0)
    model = build_model(CONFIG.model, kind).eval()
    with torch.no_grad():
        out = model(batch)
        other = model(scramble_padding(batch))
    valid = batch["valid"]
    assert len(out["poses"]) == (2 if kind == "ours" else 1)
    for quat, trans in out["poses"]:
        assert quat.shape == (2, 20, 4) and trans.shape == (2, 20, 3)
        torch.testing.assert_close(quat[valid].norm(dim=-1), torch.ones(int(valid.sum())))
    for key in ("quat", "trans"):
        torch.testing.assert_close(out[key][valid], other[key][valid], rtol=0, atol=1e-6)
    if kind == "ours":
        s = CONFIG.model.image_size
        assert out["masks"].shape == (2, 20, s, s) and out["background"].shape == (2, s, s)
        total = out["masks"].sum(1) + out["background"]
        torch.testing.assert_close(total, torch.ones_like(total))
        assert (out["masks"][~valid] == 0).all()  # padded slots own no pixel
        torch.testing.assert_close(out["masks"][valid], other["masks"][valid], rtol=0, atol=1e-6)


def test_part_encoder_graph_and_segmentation_modules(batch):
    torch.manual_seed(0)
    m = CONFIG.model
    encoder, graph = PartEncoder(m).eval(), AssemblyGraph(24, m.hidden, m.graph_iterations, m.knn).eval()
    segmentation = SegmentationNet(m).eval()
    other = scramble_padding(batch)
    valid = batch["valid"]
    nodes = torch.randn(2, 20, 24)
    other_nodes = torch.where(valid.unsqueeze(-1), nodes, torch.randn(2, 20, 24))
    with torch.no_grad():
        f_geo, f_3d = encoder(batch["points"], batch["instance_onehot"], valid)
        f_geo2, f_3d2 = encoder(other["points"], other["instance_onehot"], valid)
        poses = graph(nodes, batch["classes"], valid)
        poses2 = graph(other_nodes, other["classes"], valid)
        seg = segmentation(batch)
    assert f_geo.shape == (2, 20, m.point_feature) and f_3d.shape == (2, 20, 2 * m.part_feature)
    assert (f_3d[~valid] == 0).all() and (f_geo[~valid] == 0).all()
    torch.testing.assert_close(f_3d, f_3d2, rtol=0, atol=1e-6)
    for (q1, t1), (q2, t2) in zip(poses, poses2):
        assert q1.shape == (2, 20, 4) and t1.shape == (2, 20, 3)
        assert (q1[valid][:, 0] >= 0).all()  # the project's written form
        torch.testing.assert_close(q1[valid], q2[valid], rtol=0, atol=1e-6)
        torch.testing.assert_close(t1[valid], t2[valid], rtol=0, atol=1e-6)
    assert seg["mask_logits"].shape == (2, 20, m.image_size, m.image_size)
    assert torch.isinf(seg["mask_logits"][~valid]).all()


def test_resnet_bottleneck_and_split_stem():
    encoder = ResNetEncoder(3, width=0.125, blocks=(1, 1, 1, 1), extra_channels=1).eval()
    image, extra = torch.randn(2, 3, 224, 224), torch.rand(5, 1, 224, 224)
    index = torch.tensor([0, 0, 1, 1, 1])
    with torch.no_grad():
        split = encoder.forward_split(image, index, extra)
        joint = encoder(torch.cat([image[index], extra], 1))
    assert split[-1].shape == (5, 64, 7, 7)  # 512 x 7 x 7 at width 1
    for a, b in zip(split, joint):
        torch.testing.assert_close(a, b, rtol=1e-4, atol=1e-4)


def test_knn_graph_uses_valid_parts_only():
    centres = torch.tensor([[[0.0, 0, 0], [1, 0, 0], [2, 0, 0], [0.1, 0, 0]]])
    valid = torch.tensor([[True, True, True, False]])
    adjacency = knn_adjacency(centres, valid, 1)
    assert adjacency[0].tolist() == [[0, 1, 0, 0], [1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 0, 0]]
    assert knn_adjacency(centres, valid, 5)[0, 0].tolist() == [0, 1, 1, 0]


def test_losses_vanish_for_perfect_predictions(batch):
    terms = pose_losses(batch["quat"], batch["trans"], batch, CONFIG.loss)
    for key in ("loss", "translation", "rotation_chamfer", "rotation_l2", "shape_chamfer"):
        assert abs(float(terms[key])) < 1e-5, key
    # equivalent parts predicted in exchanged slots: still perfect after matching
    order = torch.tensor([1, 0, 2] + list(range(3, 20)))
    swapped = {k: batch[k][0, order] for k in ("quat", "trans")}
    quat, trans = batch["quat"].clone(), batch["trans"].clone()
    quat[0], trans[0] = swapped["quat"], swapped["trans"]
    terms = pose_losses(quat, trans, batch, CONFIG.loss)
    assert float(terms["loss"]) < 1e-5 and terms["perm"][0, :3].tolist() == [1, 0, 2]
    # a wrong pose costs something
    assert float(pose_losses(batch["quat"], batch["trans"] + 0.1, batch, CONFIG.loss)["translation"]) > 0.02
    # perfect masks: soft IoU 1
    masks = target_masks(batch["part_labels"], 20, 64)
    seg = segmentation_loss({"masks": masks}, batch, CONFIG.loss)
    assert abs(float(seg["loss"]) + 1.0) < 1e-6


def test_mask_cross_entropy_follows_the_matching(batch):
    """The per-pixel cross-entropy is taken after the within-class matching: confident logits for the true
    masks with two equivalent parts' channels exchanged cost (almost) nothing; the same logits with two
    parts of different classes exchanged cost a lot."""
    config = replace(CONFIG.loss, mask_cross_entropy=1.0)
    masks = target_masks(batch["part_labels"], 20, 64)
    valid = batch["valid"]

    def outputs(order):  # order: object 0's channel order; object 1 keeps its own
        orders = torch.stack([torch.tensor(order), torch.arange(20)])
        chosen = torch.gather(masks, 1, orders[:, :, None, None].expand_as(masks))
        logits = (chosen * 2 - 1) * 30.0  # +30 inside a mask, -30 outside; background logit 0
        logits = logits.masked_fill(~valid[:, :, None, None], float("-inf"))
        return {"mask_logits": logits, "masks": torch.softmax(torch.cat(
            [logits, logits.new_zeros(logits.shape[0], 1, 64, 64)], 1), 1)[:, :-1]}

    identity = list(range(20))
    same_class = [1, 0, *identity[2:]]  # object 0's parts 0 and 1 are equivalent, part 2 is not
    cross_class = [2, 1, 0, *identity[3:]]
    exact = segmentation_loss(outputs(identity), batch, config)
    swapped = segmentation_loss(outputs(same_class), batch, config)
    wrong = segmentation_loss(outputs(cross_class), batch, config)
    assert float(exact["cross_entropy"]) < 1e-6 and float(swapped["cross_entropy"]) < 1e-6
    assert float(wrong["cross_entropy"]) > 0.1
    assert torch.isfinite(wrong["loss"])


@pytest.mark.parametrize("kind", sorted(MODELS))
def test_gradients_reach_every_parameter(kind, batch):
    torch.manual_seed(0)
    model = build_model(CONFIG.model, kind).train()
    out = model(batch)
    loss = model_pose_loss(out, batch, CONFIG.loss)["loss"]
    if kind == "ours":
        loss = loss + segmentation_loss(out, batch, replace(CONFIG.loss, mask_cross_entropy=1.0))["loss"]
    assert torch.isfinite(loss)
    loss.backward()
    missing = [n for n, p in model.named_parameters() if p.grad is None or not torch.isfinite(p.grad).all()]
    assert not missing
    zero = [n for n, p in model.named_parameters() if not p.grad.abs().sum() > 0]
    # the only parameter with an identically zero gradient: the edge-feature weight of phase 1, whose edges all
    # carry feature 0 (equivalence edges)
    assert all(".phase1." in n and n.endswith(".edge.weight") for n in zero), zero
