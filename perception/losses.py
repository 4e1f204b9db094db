"""Training losses, each after Hungarian matching inside equivalence classes (:mod:`perception.matching`).

Segmentation: negative soft-IoU between predicted and ground-truth part masks (optionally with a per-pixel
cross-entropy on the same matching, beyond the paper: ``loss.mask_cross_entropy``). Pose (the paper's weights):

    1 x translation L2      squared distance between predicted and true translation
    20 x rotated-point chamfer  chamfer between the part cloud rotated by the predicted and by the true quaternion
    1 x rotated-point L2    mean squared distance between corresponding points under the two rotations
    1 x whole-shape chamfer chamfer between all parts posed by the prediction and by the truth

Beyond the paper, ``loss.crossing`` (0 in the paper's configs) weighs :func:`crossing_penalty`: how far points of
one part are pushed through another part's box to its wrong side, which the four terms above do not single out
(two parts each a few centimetres off can pass through each other at a small cost in every term).

Prediction i is compared with the ground-truth part it is matched to, using part i's own cloud under both
poses. The matching cost of a candidate pair is the sum of the first three (weighted) terms for that pair, on a
subset of points. Per-part terms are averaged over the valid parts of the batch, the shape term over objects.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

from perception.config import LossConfig
from perception.matching import batch_match, gather_parts
from perception.model.geometry import chamfer, masked_chamfer, pose_points, quat_to_matrix, rotate
from perception.model.padding import pack

# ---------------------------------------------------------------------------------------------- segmentation


def target_labels(part_labels: torch.Tensor, max_parts: int, size: int) -> torch.Tensor:
    """(B, H, W) part index per pixel (-1 background) -> (B, size, size) long, background = ``max_parts``. When
    downscaled, each output pixel takes the label covering most of its area (background included)."""
    labels = part_labels.clone().long()
    labels[labels < 0] = max_parts  # background as the last channel
    if labels.shape[-1] != size:
        channels = torch.arange(max_parts + 1, device=labels.device).view(1, -1, 1, 1)
        coverage = F.interpolate((labels.unsqueeze(1) == channels).float(), size=(size, size), mode="area")
        labels = coverage.argmax(dim=1)
    return labels


def target_masks(part_labels: torch.Tensor, max_parts: int, size: int) -> torch.Tensor:
    """(B, H, W) part index per pixel (-1 background) -> (B, P, size, size) one-hot masks of
    :func:`target_labels`, so masks stay exclusive and a perfect prediction has soft IoU 1."""
    return one_hot_masks(target_labels(part_labels, max_parts, size), max_parts)


def one_hot_masks(labels: torch.Tensor, max_parts: int) -> torch.Tensor:
    """(B, S, S) labels of :func:`target_labels` -> (B, P, S, S) one-hot part masks (background in none)."""
    parts = torch.arange(max_parts, device=labels.device).view(1, -1, 1, 1)
    return (labels.unsqueeze(1) == parts).float()


def soft_iou_matrix(pred: torch.Tensor, target: torch.Tensor, smooth: float = 1.0) -> torch.Tensor:
    """(B, P, P): soft IoU (I + s) / (U + s) between predicted mask i and target mask j, with I = sum(p g),
    U = sum(p) + sum(g) - I over pixels. A part absent from both has IoU 1."""
    inter = torch.einsum("bihw,bjhw->bij", pred, target)
    union = pred.sum(dim=(2, 3)).unsqueeze(2) + target.sum(dim=(2, 3)).unsqueeze(1) - inter
    return (inter + smooth) / (union + smooth)


def matched_cross_entropy(logits: torch.Tensor, labels: torch.Tensor, perm: torch.Tensor) -> torch.Tensor:
    """Mean per-pixel cross-entropy of the softmax over [part logits; background logit 0] against the true
    labels relabelled by the matching: a pixel of ground-truth part ``perm[b, i]`` is prediction i's.
    ``logits`` (B, P, S, S) (-inf in padded slots), ``labels`` (B, S, S) from :func:`target_labels`."""
    b, p = perm.shape
    inverse = torch.empty_like(perm)
    inverse.scatter_(1, perm, torch.arange(p, device=perm.device).expand(b, p))  # ground truth j -> prediction
    lookup = torch.cat([inverse, torch.full((b, 1), p, dtype=perm.dtype, device=perm.device)], dim=1)
    relabelled = torch.gather(lookup, 1, labels.reshape(b, -1)).reshape(labels.shape)
    full = torch.cat([logits, logits.new_zeros(b, 1, *logits.shape[2:])], dim=1)
    return F.cross_entropy(full, relabelled)


def segmentation_loss(outputs: dict, batch: dict, config: LossConfig) -> dict:
    """``loss`` = -(mean matched soft IoU over valid parts) + ``mask_cross_entropy`` x the matched per-pixel
    cross-entropy; ``soft_iou`` the mean itself and ``cross_entropy`` (both detached). ``outputs``: the
    segmentation network's (``masks``, and ``mask_logits`` when the cross-entropy weight is not 0)."""
    masks, valid = outputs["masks"], batch["valid"]
    labels = target_labels(batch["part_labels"], masks.shape[1], masks.shape[-1])
    target = one_hot_masks(labels, masks.shape[1])
    iou = soft_iou_matrix(masks, target, config.iou_smooth)
    perm = batch_match(-iou, batch["classes"], valid)
    matched = torch.gather(iou, 2, perm.unsqueeze(-1)).squeeze(-1)
    mean = matched[valid].mean()
    terms = {"loss": -mean, "soft_iou": mean.detach()}
    if config.mask_cross_entropy:
        entropy = matched_cross_entropy(outputs["mask_logits"], labels, perm)
        terms["loss"] = terms["loss"] + config.mask_cross_entropy * entropy
        terms["cross_entropy"] = entropy.detach()
    return terms


# ---------------------------------------------------------------------------------------------- pose


def pair_costs(points: torch.Tensor, quat: torch.Tensor, trans: torch.Tensor, gt_quat: torch.Tensor,
               gt_trans: torch.Tensor, classes: torch.Tensor, valid: torch.Tensor,
               config: LossConfig) -> torch.Tensor:
    """(B, P, P) matching cost of prediction i against ground-truth part j, finite only for valid pairs in one
    class: the weighted translation, rotated-point chamfer and rotated-point L2 terms on part i's cloud
    (its first ``match_points`` points). Computed without gradient, for the pairs that need it only."""
    with torch.no_grad():
        b, p = classes.shape
        same = (classes.unsqueeze(2) == classes.unsqueeze(1)) & valid.unsqueeze(2) & valid.unsqueeze(1)
        shared = same.sum(dim=2) > 1  # parts with an equivalent partner: only they can be exchanged
        pairs = same & shared.unsqueeze(2)
        cost = torch.full((b, p, p), float("inf"), device=quat.device)
        eye = torch.eye(p, dtype=torch.bool, device=quat.device).expand(b, p, p)
        cost = cost.masked_fill(eye & valid.unsqueeze(2), 0.0)  # a part alone in its class matches itself
        bi, i, j = pairs.nonzero(as_tuple=True)
        if len(bi):
            pts = points[bi, i, : config.match_points]
            rot_pred = rotate(pts, quat[bi, i])
            rot_true = rotate(pts, gt_quat[bi, j])
            terms = (config.translation * (trans[bi, i] - gt_trans[bi, j]).pow(2).sum(-1)
                     + config.rotation_chamfer * chamfer(rot_pred, rot_true)
                     + config.rotation_l2 * (rot_pred - rot_true).pow(2).sum(-1).mean(-1))
            cost[bi, i, j] = terms.float()
        return cost


def pose_losses(quat: torch.Tensor, trans: torch.Tensor, batch: dict, config: LossConfig) -> dict:
    """The four pose losses and their weighted sum ``loss`` for one set of predictions (B, P, 4) / (B, P, 3);
    also ``perm`` (B, P), the ground-truth part matched to each prediction."""
    valid, points = batch["valid"], batch["points"]
    cost = pair_costs(points, quat, trans, batch["quat"], batch["trans"], batch["classes"], valid, config)
    perm = batch_match(cost, batch["classes"], valid)
    gt_quat, gt_trans = gather_parts(batch["quat"], perm), gather_parts(batch["trans"], perm)

    pts = pack(points[:, :, : config.points], valid)  # (M, m, 3)
    q, t, gq, gt = (pack(x, valid) for x in (quat, trans, gt_quat, gt_trans))
    rot_pred, rot_true = rotate(pts, q), rotate(pts, gq)
    translation = (t - gt).pow(2).sum(-1).mean()
    rotation_chamfer = chamfer(rot_pred, rot_true).mean()
    rotation_l2 = (rot_pred - rot_true).pow(2).sum(-1).mean()

    s = config.shape_points
    shape_pts = points[:, :, :s]
    b, p = valid.shape
    shape_pred = pose_points(shape_pts, quat, trans).reshape(b, p * s, 3)
    shape_true = pose_points(shape_pts, gt_quat, gt_trans).reshape(b, p * s, 3)
    point_valid = valid.unsqueeze(2).expand(b, p, s).reshape(b, p * s)
    shape_chamfer = masked_chamfer(shape_pred, point_valid, shape_true, point_valid).mean()

    loss = (config.translation * translation + config.rotation_chamfer * rotation_chamfer
            + config.rotation_l2 * rotation_l2 + config.shape_chamfer * shape_chamfer)
    terms = {"loss": loss, "translation": translation, "rotation_chamfer": rotation_chamfer,
             "rotation_l2": rotation_l2, "shape_chamfer": shape_chamfer, "perm": perm}
    if config.crossing:
        crossing = crossing_penalty(shape_pts, quat, trans, gt_quat, gt_trans, valid,
                                    points[:, :, : config.points], config.crossing_moves_crossing_part_only)
        terms["loss"] = loss + config.crossing * crossing
        terms["crossing"] = crossing
    return terms


def crossing_penalty(points: torch.Tensor, quat: torch.Tensor, trans: torch.Tensor, gt_quat: torch.Tensor,
                     gt_trans: torch.Tensor, valid: torch.Tensor, box_points: torch.Tensor,
                     move_crossing_part_only: bool = False) -> torch.Tensor:
    """How far the predicted poses push parts through each other, in normalised shape units (scalar >= 0).

    Each part j's box is the axis-aligned box of ``box_points`` (B, P, M, 3) in its own (PCA) frame, and its
    thinnest axis n is its *normal*: for a panel, the axis one crosses it along. A point of part i that the true
    poses put outside j's slab (|n coordinate| >= half thickness) has a true side of j. Where the predicted poses
    put that point within j's footprint (in the box along the two other axes, edges included), the penalty is how
    far the point would have to move along n to reach j's face on its true side (0 when it is already there). The
    penalty of a pair is the mean over part i's ``points`` (B, P, N, 3); the result sums over j and averages over
    the valid parts i. ``gt_quat``/``gt_trans``: the true poses matched to each prediction.
    ``move_crossing_part_only``: the gradient reaches part i's pose only, not the frame of the part j it crosses.
    """
    lo, hi = box_points.amin(dim=2), box_points.amax(dim=2)  # (B, P, 3) in each part's own frame
    half, centre = (hi - lo) / 2, (hi + lo) / 2
    b, p = valid.shape
    normal = half.argmin(dim=-1)  # (B, P)
    axes = torch.arange(3, device=points.device)
    in_plane = axes.view(1, 1, 3) != normal.unsqueeze(-1)  # (B, P, 3)

    def in_box_frames(q: torch.Tensor, t: torch.Tensor, fixed_frames: bool = False) -> torch.Tensor:
        """(B, I, J, N, 3): part i's points posed by (q, t), in part j's box frame (relative to its centre);
        ``fixed_frames``: no gradient through part j's frame."""
        world = pose_points(points, q, t)  # (B, I, N, 3)
        q_j, t_j = (q.detach(), t.detach()) if fixed_frames else (q, t)
        rot_j = quat_to_matrix(q_j)  # (B, J, 3, 3); local = R_j^T (x - t_j)
        rel = world.unsqueeze(2) - t_j.view(b, 1, p, 1, 3)  # (B, I, J, N, 3)
        local = torch.einsum("bijnk,bjkl->bijnl", rel, rot_j)
        return local - centre.view(b, 1, p, 1, 3)

    def along_normal(local: torch.Tensor) -> torch.Tensor:
        """(B, I, J, N): the coordinate along part j's normal of :func:`in_box_frames`' points."""
        return local.gather(-1, normal.view(b, 1, p, 1, 1).expand(*local.shape[:-1], 1)).squeeze(-1)

    half_n = half.gather(-1, normal.unsqueeze(-1)).view(b, 1, p, 1)  # part j's half thickness
    with torch.no_grad():
        true_n = along_normal(in_box_frames(gt_quat, gt_trans))
        side = torch.sign(true_n)
        outside_slab = true_n.abs() >= half_n
    pred_local = in_box_frames(quat, trans, move_crossing_part_only)
    pred_n = along_normal(pred_local)
    within = ((pred_local.detach().abs() <= half.view(b, 1, p, 1, 3)) | ~in_plane.view(b, 1, p, 1, 3)).all(-1)
    depth = torch.relu(half_n - side * pred_n) * (outside_slab & within)
    pairs = valid.unsqueeze(2) & valid.unsqueeze(1) & ~torch.eye(p, dtype=torch.bool, device=valid.device)
    per_part = (depth.mean(-1) * pairs).sum(-1)  # (B, I)
    return per_part[valid].mean()


def model_pose_loss(outputs: dict, batch: dict, config: LossConfig) -> dict:
    """Sum of :func:`pose_losses` over every supervised phase of ``outputs["poses"]`` (two for the paper's
    model, one for the baselines). Logged terms are those of the final phase."""
    total = 0.0
    for quat, trans in outputs["poses"]:
        terms = pose_losses(quat, trans, batch, config)
        total = total + terms["loss"]
    logged = {k: v.detach() for k, v in terms.items() if k not in ("loss", "perm")}
    return {"loss": total, **logged, "final": terms["loss"].detach()}
