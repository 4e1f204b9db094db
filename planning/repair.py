"""Repair of predicted poses: align near-parallel faces, snap near-contacts into contact, resolve
interpenetration, without moving any part by more than a bound.

Predicted assemblies have parts floating a few millimetres apart or sunk into each other (the paper's main
failure). The repair, all in the assembly frame (metres, +z up, floor at z = 0):

1. **Align**: furniture is built along three axes, so a part whose own axes lie within
   ``align_tolerance_deg`` of the assembly axes is rotated onto them (its near-parallel faces become parallel).
2. **Contacts**: a few rounds of pairwise corrections along the contact normal (signed distances between convex
   pieces, :mod:`planning.collision`): a penetrating pair is pushed apart, a pair with a gap below
   ``snap_distance_m`` is pulled together; the floor is fixed, parts near it are set on it. Each correction is
   shared between the two parts.
3. **Connect**: every piece of furniture is one connected whole, so while the parts form several pieces (sets
   joined by contacts, :func:`planning.contact.pieces`, the floor not counted), a piece is moved whole, by
   translation, into contact with its nearest part of another piece within ``connect_distance_m``: pieces off the
   floor first (a predicted top and the legs hanging from it, short of the floor, come down onto the aprons; the
   legs on the floor stay), then smaller ones (a lone part joins its neighbour). Then the contact rounds run
   again. The rounds may part a joined piece again (its neighbours move with their other contacts), so this step
   repeats, at most ``connect_passes`` times.
4. **Bound**: a part's total displacement is clamped to ``max_translation_m`` (``crossing_translation_m`` for the
   parts of step 5) and its rotation to ``max_rotation_deg`` (step 1; step 5 may turn crossed parts further).
5. **Uncross**: a pair the prediction crossed (a panel through a panel, most often in cabinets) overlaps by more
   than the bound can undo, and no cell can build that. The parts of every pair still overlapping by more than
   ``crossing_depth_m`` (the most ``python -m cell.run`` accepts) get the wider bound ``crossing_translation_m``
   and are turned onto the assembly axes when within ``crossing_align_tolerance_deg`` of them (180: always; a
   panel tilted 20-40 degrees through its neighbours is the usual crossing, and a tilted panel cannot be parted
   from an upright carcass by moving it), the other parts keep theirs, and steps 2-3 run again; at most
   ``crossing_passes`` times (never when ``crossing_translation_m`` is no wider than ``max_translation_m``). Only
   crossed parts may move or turn further, so assemblies without a crossing come out as before.
6. **Rest**: where no part touches the floor at the end (a repaired assembly in one piece, hanging 15-30 mm above
   it because the rounds lifted its lowest part, or because its lowest part joined a hanging piece), the whole
   assembly is lowered onto the floor when it is at most ``rest_distance_m`` above it. This moves no part
   relative to another; each part's reported displacement includes it, so a part may end up to
   ``rest_distance_m`` beyond its bound from step 4.

Aligning (steps 1 and 5) takes each mesh's own axes for the part's: furniture parts are modelled along their own
axes (every procedural part, and every one of the 267 parts of ``../shared/furniture`` sits in its assembly turned
by one of the 24 axis rotations, 257 of them unturned).

The report says how far each part moved, and which pairs still overlap.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from planning.collision import MAX_FITTING_OVERLAP_M, ConvexPart, overlapping_pairs, signed_distance
from planning.contact import FLOOR, contact_graph, pieces
from planning.pose import AXIS_ROTATIONS, Pose, matrix_to_quat, quat_angle_rad


@dataclass(frozen=True)
class RepairSettings:
    align_tolerance_deg: float = 8.0
    snap_distance_m: float = 0.01
    penetration_tolerance_m: float = 0.0005
    max_translation_m: float = 0.05
    max_rotation_deg: float = 10.0
    iterations: int = 40
    connect_distance_m: float = 0.05  # a piece joins its nearest part of another within this (0: never)
    connect_passes: int = 3  # join, then contact rounds, at most this many times
    crossing_translation_m: float = 0.12  # bound for the parts of crossed pairs (<= max_translation_m: no step 5)
    crossing_depth_m: float = MAX_FITTING_OVERLAP_M  # a pair overlapping by more than this after step 4 is crossed
    crossing_passes: int = 2  # widen the bound for newly crossed pairs, then contact rounds, at most this often
    crossing_align_tolerance_deg: float = 180.0  # step 5 aligns crossed parts within this (180: always)
    rest_distance_m: float = 0.05  # step 6 lowers a whole assembly hanging at most this far above the floor (0: never)


@dataclass(frozen=True)
class RepairReport:
    """How far each part moved (metres, degrees), the deepest penetration before and after (metres), and the
    pairs that still overlap by more than ``penetration_tolerance_m`` after: (name a, name b, depth in metres),
    deepest first; the parts of crossed pairs (step 5: the wider bound, turned onto the axes), in part order; how
    far step 6 lowered the whole assembly onto the floor (metres, 0 when it did not)."""

    translation_m: dict[str, float]
    rotation_deg: dict[str, float]
    deepest_penetration_before_m: float
    deepest_penetration_after_m: float
    overlapping_pairs_after: tuple[tuple[str, str, float], ...] = ()
    crossed_parts: tuple[str, ...] = ()
    lowered_m: float = 0.0


def snap_rotation_to_axes(rotation: np.ndarray, tolerance_deg: float) -> np.ndarray:
    """The nearest of the 24 rotations onto the coordinate axes if within ``tolerance_deg`` of ``rotation``
    (every rotation is within 62.8 degrees of one), else ``rotation``."""
    # the angle between R and S grows as trace(R^T S) falls
    nearest = AXIS_ROTATIONS[int(np.argmax(np.einsum("ij,kij->k", rotation, AXIS_ROTATIONS)))]
    angle = quat_angle_rad(matrix_to_quat(rotation), matrix_to_quat(nearest))
    return nearest if np.degrees(angle) <= tolerance_deg else rotation


def _centre(part: ConvexPart) -> np.ndarray:
    """Centre of the part's box, part frame: the point whose displacement counts as the part's."""
    return 0.5 * (part.vertices.min(axis=0) + part.vertices.max(axis=0))


def _aligned(part: ConvexPart, pose: Pose, tolerance_deg: float) -> Pose:
    """``pose`` turned onto the assembly axes when within ``tolerance_deg`` of them (:func:`snap_rotation_to_axes`),
    about the part's centre, so that aligning does not move it."""
    rotation = snap_rotation_to_axes(pose.rotation, tolerance_deg)
    centre_world = pose.apply(_centre(part))
    return Pose.from_rotation(rotation, centre_world - rotation @ _centre(part))


def _clamped(part: ConvexPart, original: Pose, candidate: Pose, bound_m: float) -> Pose:
    """``candidate`` with its centre moved back towards ``original``'s to within ``bound_m`` (metres)."""
    centre = _centre(part)
    offset = candidate.apply(centre) - original.apply(centre)
    norm = float(np.linalg.norm(offset))
    if norm <= bound_m:
        return candidate
    target = original.apply(centre) + offset * (bound_m / norm)
    return Pose(target - candidate.rotation @ centre, candidate.quat_wxyz)


def _deepest_penetration(parts: list[ConvexPart], poses: list[Pose]) -> float:
    return max((depth for _, _, depth in overlapping_pairs(parts, poses)), default=0.0)


def _contact_rounds(parts: list[ConvexPart], original: list[Pose], current: list[Pose], settings: RepairSettings,
                    floor_z_m: float, bounds_m: list[float]) -> list[Pose]:
    """Step 2: pairwise corrections along contact normals until nothing moves (at most ``iterations`` rounds);
    ``bounds_m``: how far each part may end up from ``original`` (metres)."""
    n = len(parts)
    for _ in range(settings.iterations):
        shifts = np.zeros((n, 3))
        counts = np.zeros(n)
        for i in range(n):
            lowest = float(current[i].apply(parts[i].vertices)[:, 2].min()) - floor_z_m
            if lowest < settings.snap_distance_m:
                shifts[i, 2] += -lowest  # onto the floor (up out of it, or down onto it)
                counts[i] += 1
            for j in range(i + 1, n):
                result = signed_distance(parts[i], current[i], parts[j], current[j], settings.snap_distance_m)
                if not result.measured or result.distance_m > settings.snap_distance_m:
                    continue
                if abs(result.distance_m) <= settings.penetration_tolerance_m or result.normal_ab is None:
                    continue
                # move b along normal_ab by -distance (apart when penetrating, together when apart), half each
                correction = -result.distance_m * result.normal_ab
                shifts[i] -= 0.5 * correction
                shifts[j] += 0.5 * correction
                counts[i] += 1
                counts[j] += 1
        if not np.any(counts):
            break
        moved = np.where(counts[:, None] > 0, shifts / np.maximum(counts, 1)[:, None], 0.0)
        current = [_clamped(p, o, Pose(c.position + m, c.quat_wxyz), bound)
                   for p, o, c, m, bound in zip(parts, original, current, moved, bounds_m)]
    return current


def _piece_size_m(parts: list[ConvexPart], poses: list[Pose], members: list[int]) -> float:
    """Diagonal of the box around a piece's parts (metres)."""
    corners = np.concatenate([parts[i].bounds(poses[i]) for i in members])
    return float(np.linalg.norm(np.ptp(corners, axis=0)))


def _join_move(parts: list[ConvexPart], poses: list[Pose], members: list[int], distance_m: float) -> np.ndarray | None:
    """The translation (metres) that puts the piece ``members`` in contact with its nearest part outside it, when
    that part is within ``distance_m``; None otherwise."""
    inside = set(members)
    nearest = None
    for i in members:
        for j in range(len(parts)):
            if j in inside:
                continue
            result = signed_distance(parts[i], poses[i], parts[j], poses[j], distance_m)
            if result.measured and result.normal_ab is not None and 0 < result.distance_m <= distance_m and (
                    nearest is None or result.distance_m < nearest.distance_m):
                nearest = result
    # normal_ab points from the piece to its nearest part: close the gap
    return None if nearest is None else nearest.distance_m * nearest.normal_ab


def _connect_pieces(parts: list[ConvexPart], original: list[Pose], current: list[Pose],
                    settings: RepairSettings, bounds_m: list[float]) -> list[Pose]:
    """Step 3: while the assembly is in several pieces (parts joined by contacts, the floor not counted), a piece
    is moved whole, by translation, onto its nearest part of another piece when that is within
    ``connect_distance_m`` and every part of it stays within its bound; pieces off the floor first (what touches
    the floor stands), then smaller ones. Returns ``current`` itself when nothing moved."""
    if len(parts) < 2:
        return current
    index = {part.name: k for k, part in enumerate(parts)}
    joined = list(current)
    stuck: set[frozenset] = set()
    for _ in range(len(parts)):  # each join merges two pieces at least: at most n - 1 joins
        graph = contact_graph(parts, joined)
        found = pieces(graph)
        if len(found) < 2:
            break
        standing = set(graph.neighbors(FLOOR))
        movable = sorted((sorted(index[name] for name in piece) for piece in found if frozenset(piece) not in stuck),
                         key=lambda m: (any(parts[i].name in standing for i in m), _piece_size_m(parts, joined, m), m))
        for members in movable:
            move = _join_move(parts, joined, members, settings.connect_distance_m)
            if move is not None:
                candidates = {i: Pose(joined[i].position + move, joined[i].quat_wxyz) for i in members}
                # a move cut short by the bound would leave the piece apart anyway
                if all(_clamped(parts[i], original[i], c, bounds_m[i]) is c for i, c in candidates.items()):
                    for i, candidate in candidates.items():
                        joined[i] = candidate
                    break
            stuck.add(frozenset(parts[i].name for i in members))
        else:
            break
    return joined if any(a is not b for a, b in zip(joined, current)) else current


def _contact_and_connect(parts: list[ConvexPart], original: list[Pose], current: list[Pose],
                         settings: RepairSettings, floor_z_m: float, bounds_m: list[float]) -> list[Pose]:
    """Steps 2 and 3: contact rounds, then join the pieces and run the rounds again, repeated."""
    current = _contact_rounds(parts, original, current, settings, floor_z_m, bounds_m)
    for _ in range(settings.connect_passes if settings.connect_distance_m > 0 else 0):
        # the contact rounds after a join move the joined part's neighbours too and may part it again: join anew
        joined = _connect_pieces(parts, original, current, settings, bounds_m)
        if joined is current:
            break
        current = _contact_rounds(parts, original, joined, settings, floor_z_m, bounds_m)
    return current


def _rested(parts: list[ConvexPart], current: list[Pose], settings: RepairSettings,
            floor_z_m: float) -> tuple[list[Pose], float]:
    """Step 6: ``current`` lowered whole onto the floor when no part touches it (the floor contact of
    :func:`planning.contact.contact_graph`) and its lowest point is at most ``rest_distance_m`` above it; and how
    far it was lowered (metres)."""
    if settings.rest_distance_m <= 0 or not parts or contact_graph(parts, current, floor_z_m).degree(FLOOR) > 0:
        return current, 0.0
    height = min(float(pose.apply(part.vertices)[:, 2].min()) for part, pose in zip(parts, current)) - floor_z_m
    if not 0.0 < height <= settings.rest_distance_m:
        return current, 0.0  # lowered only part of the way, it would still hang
    return [Pose(pose.position - [0.0, 0.0, height], pose.quat_wxyz) for pose in current], height


def repair_poses(parts: list[ConvexPart], poses: list[Pose], settings: RepairSettings = RepairSettings(),
                 floor_z_m: float = 0.0) -> tuple[list[Pose], RepairReport]:
    """Repaired ``assembly_from_part`` poses (same order as ``parts``) and the report."""
    original = list(poses)
    before = _deepest_penetration(parts, original)
    align_deg = min(settings.align_tolerance_deg, settings.max_rotation_deg)
    current = [_aligned(part, pose, align_deg) for part, pose in zip(parts, original)]
    bounds_m = [settings.max_translation_m] * len(parts)
    current = _contact_and_connect(parts, original, current, settings, floor_z_m, bounds_m)
    overlapping_after = overlapping_pairs(parts, current)
    index = {part.name: k for k, part in enumerate(parts)}
    for _ in range(settings.crossing_passes if settings.crossing_translation_m > settings.max_translation_m else 0):
        crossed = {index[name] for a, b, depth in overlapping_after if depth > settings.crossing_depth_m
                   for name in (a, b)}
        if all(bounds_m[k] >= settings.crossing_translation_m for k in crossed):
            break  # no crossed part left that a wider bound could still move
        for k in crossed:
            bounds_m[k] = settings.crossing_translation_m
            if settings.crossing_align_tolerance_deg > align_deg:
                current[k] = _aligned(parts[k], current[k], settings.crossing_align_tolerance_deg)
        current = _contact_and_connect(parts, original, current, settings, floor_z_m, bounds_m)
        overlapping_after = overlapping_pairs(parts, current)
    current, lowered_m = _rested(parts, current, settings, floor_z_m)
    report = RepairReport(
        translation_m={p.name: float(np.linalg.norm(c.apply(_centre(p)) - o.apply(_centre(p))))
                       for p, o, c in zip(parts, original, current)},
        rotation_deg={p.name: float(np.degrees(quat_angle_rad(o.quat_wxyz, c.quat_wxyz)))
                      for p, o, c in zip(parts, original, current)},
        deepest_penetration_before_m=before,
        deepest_penetration_after_m=overlapping_after[0][2] if overlapping_after else 0.0,
        overlapping_pairs_after=tuple(pair for pair in overlapping_after if pair[2] > settings.penetration_tolerance_m),
        crossed_parts=tuple(p.name for p, bound in zip(parts, bounds_m) if bound > settings.max_translation_m),
        lowered_m=lowered_m,
    )
    return current, report
