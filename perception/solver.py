"""Test-time fitting of a predicted assembly to its picture: move parts until their drawing covers the object.

The network places most parts with the right orientation but many at the wrong place: equivalent parts (legs,
slats) drawn together at 55-75% of their true spacing, a rail floating beside the seat (``benchmarks/
mask_oracle.py``). The user gives us the part meshes and the picture exactly, so the drawing of a candidate
assembly can be compared with the object in the picture (:mod:`perception.agreement`) and the parts moved until
they agree with it, before the pose repair makes them touch:

- **Scorer** (:class:`SilhouetteScorer`): each part drawn with the picture's camera as the union of its convex
  pieces' projected outlines (one polygon per piece: cheap enough for thousands of candidates per second on one
  core), the parts' silhouettes summed into one coverage image; the score is the silhouette IoU with the object
  (after the drawing's fit for the camera distance, :func:`perception.agreement.fit_silhouette`), plus the mean
  share of each part's drawn pixels on the object, less penalties for parts below the floor and for moving or
  turning away from the network's placement.
- **Search** (:func:`solve`): from the network's assembly, discrete moves, each kept only where the score rises,
  and only for parts drawn partly off the object: quarter and half turns about the assembly's axes; the members of
  an equivalence class spread or drawn together about their centre in the floor plane (legs); each part moved to
  where its outline best fills object pixels no other part covers (:func:`_relocations`); then steps in the
  picture's plane at the part's depth, halving.

On the procedural test sets the search raises its score but lowers Part Accuracy (``benchmarks/
picture_solver.py``): one picture does not fix a part's depth, and the silhouette rewards whichever part fills a
hole. ``cell.run`` does not use it; ``python -m perception.evaluate --assemblies DIR --solver`` measures it.

Frames: the upright assembly frame (+z up, floor at z = 0, metres) for the moves; the picture's OpenCV camera
frame for drawing. Deterministic (no random numbers).
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
from PIL import Image, ImageDraw
from scipy.spatial import ConvexHull, QhullError

from perception.agreement import NEAR_PLANE_M, fit_silhouette, iou, picture_intrinsics
from planning.pose import Pose


@dataclass(frozen=True)
class SolverSettings:
    """The search's moves and the score's weights (fractions of the object's largest extent where a length).

    steps: translation steps tried for each part, along ``image_plane_moves`` (the picture's x and y axes at the
    part's depth) or else the assembly's axes. rounds: passes over the parts per step. spreads: factors by which
    the members of an equivalence class are spread about their centre in the floor plane. relocation_rounds /
    relocation_peaks: passes of moves to where a part's outline best fills uncovered object pixels, and how many
    such places are tried per part; background_weight: what a background pixel it would cover costs against an
    object pixel it fills; keep_height: such a move keeps the part's height (a move in the floor plane) unless
    the picture sees that plane edge-on. movable_below: only parts with less than this share of their drawn pixels
    on the object move or turn. fit_drawing: scale and shift the drawing onto the object first (the network's
    camera distance is uncertain). on_object_weight: weight of the mean share of each part's pixels on the object
    beside the silhouette IoU. move_weight / turn_weight / floor_weight: penalties per extent moved from the
    network's placement, per quarter turn from its orientation, per extent below the floor. max_seconds: the
    search stops after this much wall time."""

    steps: tuple[float, ...] = (0.16, 0.08, 0.04, 0.02)
    spreads: tuple[float, ...] = (0.6, 0.8, 1.25, 1.5, 1.8)
    on_object_weight: float = 0.3
    move_weight: float = 0.02
    floor_weight: float = 2.0
    rounds: int = 2
    turn_weight: float = 0.01
    image_plane_moves: bool = True
    relocation_rounds: int = 2
    relocation_peaks: int = 3
    background_weight: float = 1.0
    keep_height: bool = True
    movable_below: float = 0.85
    fit_drawing: bool = True
    max_seconds: float = 10.0


@dataclass
class SolverResult:
    """assembly_from_part: the fitted poses (same order as given). score_before / score_after: the scorer's value;
    iou_before / iou_after: the silhouette IoU alone; moves: how many moves were kept; seconds: wall time."""

    assembly_from_part: list[Pose]
    score_before: float
    score_after: float
    iou_before: float
    iou_after: float
    moves: int
    seconds: float
    moved_m: dict = field(default_factory=dict)

    def to_dict(self, names: Sequence) -> dict:
        return {"score_before": round(self.score_before, 4), "score_after": round(self.score_after, 4),
                "silhouette_iou_before": round(self.iou_before, 4), "silhouette_iou_after": round(self.iou_after, 4),
                "moves": self.moves, "seconds": round(self.seconds, 3),
                "moved_m": {str(n): round(self.moved_m.get(k, 0.0), 4) for k, n in enumerate(names)}}


class SilhouetteScorer:
    """Draws parts (their convex pieces, part frame, metres) at assembly poses with the picture's camera and scores
    the drawing against ``object_px`` (H, W) bool. ``camera_from_assembly``: the assembly frame in the picture's
    OpenCV camera frame. The drawing is placed by the fit of the first assembly drawn (:meth:`fit`)."""

    def __init__(self, piece_vertices: Sequence[Sequence[np.ndarray]], camera_from_assembly: Pose,
                 object_px: np.ndarray, settings: SolverSettings = SolverSettings(),
                 intrinsics: np.ndarray | None = None) -> None:
        self.pieces = [[np.asarray(v, dtype=np.float64) for v in part] for part in piece_vertices]
        self.camera_from_assembly = camera_from_assembly
        self.object_px = np.asarray(object_px, dtype=bool)
        self.size = self.object_px.shape[0]
        self.intrinsics = picture_intrinsics(self.size) if intrinsics is None else intrinsics
        self.settings = settings
        self.scale, self.shift, self.centre = 1.0, np.zeros(2), np.zeros(2)

    def outlines_px(self, k: int, assembly_from_part: Pose) -> list[np.ndarray]:
        """Part ``k``'s pieces' outlines, each (M, 2) pixels (u, v) before the fit, nearest the camera first."""
        camera_from_part = self.camera_from_assembly @ assembly_from_part
        outlines = []
        for vertices in self.pieces[k]:
            camera = camera_from_part.apply(vertices)
            if np.any(camera[:, 2] <= NEAR_PLANE_M):
                continue
            uvw = camera @ self.intrinsics.T
            uv = uvw[:, :2] / uvw[:, 2:3]
            try:
                outlines.append(uv[ConvexHull(uv).vertices])
            except (QhullError, ValueError):  # a piece seen edge-on: a segment; its bounding box is as thin
                low, high = uv.min(axis=0), uv.max(axis=0)
                outlines.append(np.array([low, [high[0], low[1]], high, [low[0], high[1]]]))
        return outlines

    def fit(self, poses: Sequence[Pose]) -> None:
        """Fit the drawing's scale and shift (the camera's distance and aim) to the object, for ``poses``."""
        triangles = [np.stack([np.tile(o[0], (len(o) - 2, 1)), o[1:-1], o[2:]], axis=1)
                     for k, pose in enumerate(poses) for o in self.outlines_px(k, pose) if len(o) >= 3]
        everything = np.concatenate(triangles) if triangles else np.zeros((0, 3, 2))
        self.scale, self.shift, self.centre = fit_silhouette(everything, self.object_px)

    def part_mask(self, k: int, assembly_from_part: Pose) -> np.ndarray:
        """(H, W) bool: part ``k`` drawn at ``assembly_from_part`` and placed by the fit."""
        image = Image.new("1", (self.size, self.size), 0)
        draw = ImageDraw.Draw(image)
        for outline in self.outlines_px(k, assembly_from_part):
            points = self.centre + self.scale * (outline - self.centre) + self.shift
            draw.polygon([tuple(p) for p in points], fill=1, outline=1)
        return np.asarray(image, dtype=bool)

    def on_object_share(self, mask: np.ndarray) -> float:
        """The share of a part's drawn pixels (``mask``) that lie on the object (0 for a part drawn nowhere)."""
        pixels = np.count_nonzero(mask)
        return float(np.count_nonzero(mask & self.object_px) / pixels) if pixels else 0.0

    def score(self, shares: Sequence[float], coverage: np.ndarray, penalty: float) -> tuple[float, float]:
        """(score, silhouette IoU) of parts whose drawings sum to ``coverage``, each with its share on the object
        (:meth:`on_object_share`), less ``penalty``."""
        silhouette = iou(coverage > 0, self.object_px)
        return silhouette + self.settings.on_object_weight * float(np.mean(shares)) - penalty, silhouette


def _turns() -> list[np.ndarray]:
    """The quarter and half turns about the x, y and z axes: 9 rotation matrices."""
    turns = []
    for axis in range(3):
        for quarters in (1, 2, 3):
            angle = quarters * np.pi / 2.0
            c, s = np.cos(angle), np.sin(angle)
            i, j = [a for a in range(3) if a != axis]
            turn = np.eye(3)
            turn[i, i], turn[i, j], turn[j, i], turn[j, j] = c, -s, s, c
            turns.append(np.round(turn))
    return turns


_TURNS = _turns()


def _relocations(scorer: SilhouetteScorer, k: int, pose: Pose, mask: np.ndarray, coverage: np.ndarray,
                 settings: SolverSettings) -> list[np.ndarray]:
    """Moves (assembly frame, metres, in the plane facing the camera at the part's depth) that bring part ``k``'s
    outline where it best fills object pixels no other part covers, against background it would cover: the peaks
    of that gain's cross-correlation with the part's drawn outline (FFT), best first. A thin leg drawn a few pixels
    beside its place gains nothing from a small step (outlines only score where they overlap), so its moves come
    from the picture, not from a step size."""
    from scipy.signal import fftconvolve

    rows, cols = np.nonzero(mask)
    if not len(rows):
        return []
    template = mask[rows.min():rows.max() + 1, cols.min():cols.max() + 1].astype(np.float32)
    others = (coverage - mask.astype(np.int16)) > 0
    gain = (scorer.object_px & ~others).astype(np.float32) - settings.background_weight * (~scorer.object_px)
    # gain summed under the template placed with its top-left corner at each pixel
    field = fftconvolve(gain, template[::-1, ::-1], mode="full")[template.shape[0] - 1:, template.shape[1] - 1:]
    here = field[rows.min(), cols.min()]
    centre_camera = (scorer.camera_from_assembly @ pose).apply(np.concatenate(scorer.pieces[k]).mean(axis=0)[None])[0]
    rotation = scorer.camera_from_assembly.rotation  # camera from assembly
    f_px = scorer.intrinsics[0, 0] * scorer.scale  # pixels per unit of x / z, as drawn after the fit
    # the picture's (u, v) change per metre moved along each assembly axis, at the part's centre (2, 3)
    x, y, z = centre_camera
    jacobian = f_px * np.array([[1.0 / z, 0.0, -x / z**2], [0.0, 1.0 / z, -y / z**2]]) @ rotation
    level = jacobian[:, :2]  # a move on the level of the part (x, y in the assembly frame), keeping its height
    on_level = settings.keep_height and abs(np.linalg.det(level)) > 0.1 * np.prod(np.linalg.norm(level, axis=0))
    to_move = np.linalg.inv(level) if on_level else np.linalg.pinv(jacobian)
    moves, field = [], field.copy()
    for _ in range(settings.relocation_peaks):
        top = np.unravel_index(int(np.argmax(field)), field.shape)
        if field[top] <= here + 1.0:
            break
        dv, du = top[0] - rows.min(), top[1] - cols.min()
        delta = to_move @ np.array([du, dv], dtype=np.float64)
        moves.append(np.array([delta[0], delta[1], 0.0]) if on_level else delta)
        field[max(0, top[0] - 4):top[0] + 5, max(0, top[1] - 4):top[1] + 5] = -np.inf
    return moves


def _lowest_z(pieces: Sequence[np.ndarray], pose: Pose) -> float:
    return min(float(pose.apply(v)[:, 2].min()) for v in pieces)


def solve(piece_vertices: Sequence[Sequence[np.ndarray]], classes: Sequence[int], assembly_from_part: Sequence[Pose],
          camera_from_assembly: Pose, object_px: np.ndarray,
          settings: SolverSettings = SolverSettings()) -> SolverResult:
    """The parts moved until their drawing best covers the object in the picture (see the module docstring).

    piece_vertices: per part, its convex pieces' vertices (part frame, metres; :class:`planning.collision.
    ConvexPart` ``piece_vertices``). classes: per part, its equivalence class (:func:`perception.equivalence.
    equivalence_classes`). assembly_from_part: the network's poses (upright assembly frame, metres).
    camera_from_assembly: the picture's camera. object_px: (H, W) bool, the object in the picture
    (:func:`perception.agreement.object_mask`)."""
    started = time.perf_counter()
    poses = list(assembly_from_part)
    original = [p.position.copy() for p in poses]
    original_rotation = [p.rotation for p in poses]
    scorer = SilhouetteScorer(piece_vertices, camera_from_assembly, object_px, settings)
    if settings.fit_drawing:
        scorer.fit(poses)
    everything = np.concatenate([pose.apply(v) for part, pose in zip(scorer.pieces, poses) for v in part])
    extent_m = float(np.max(everything.max(axis=0) - everything.min(axis=0)))
    masks = [scorer.part_mask(k, pose) for k, pose in enumerate(poses)]
    coverage = np.sum(masks, axis=0, dtype=np.int16)
    lowest = [_lowest_z(scorer.pieces[k], pose) for k, pose in enumerate(poses)]
    floor_m = min(0.0, min(lowest))  # the network's assembly may already reach below z = 0; judge from there

    def penalty_of(k: int, pose: Pose, low: float) -> float:
        moved = np.linalg.norm(pose.position - original[k]) / extent_m
        below = max(0.0, floor_m - low) / extent_m
        cos_turn = np.clip((np.trace(original_rotation[k].T @ pose.rotation) - 1.0) / 2.0, -1.0, 1.0)
        quarters = np.arccos(cos_turn) / (np.pi / 2.0)
        return settings.move_weight * moved + settings.floor_weight * below + settings.turn_weight * quarters

    penalties = [penalty_of(k, pose, lowest[k]) for k, pose in enumerate(poses)]
    shares = [scorer.on_object_share(mask) for mask in masks]
    best, silhouette_before = scorer.score(shares, coverage, sum(penalties))
    score_before, moves = best, 0

    def try_moves(changes: dict[int, Pose]) -> bool:
        """Apply ``changes`` (part -> new pose) if the score rises."""
        nonlocal best, coverage, moves
        new_masks = {k: scorer.part_mask(k, pose) for k, pose in changes.items()}
        new_coverage = coverage.copy()
        trial_shares, trial_penalties, new_lowest = list(shares), list(penalties), {}
        for k, mask in new_masks.items():
            new_coverage += mask.astype(np.int16) - masks[k].astype(np.int16)
            trial_shares[k] = scorer.on_object_share(mask)
            new_lowest[k] = _lowest_z(scorer.pieces[k], changes[k])
            trial_penalties[k] = penalty_of(k, changes[k], new_lowest[k])
        value, _ = scorer.score(trial_shares, new_coverage, sum(trial_penalties))
        if value <= best + 1e-6:
            return False
        best, coverage, moves = value, new_coverage, moves + 1
        for k, pose in changes.items():
            poses[k], masks[k], penalties[k], lowest[k] = pose, new_masks[k], trial_penalties[k], new_lowest[k]
            shares[k] = trial_shares[k]
        return True

    def moved(pose: Pose, delta_m: np.ndarray) -> Pose:
        return Pose(pose.position + delta_m, pose.quat_wxyz)

    centres_part = [np.concatenate(part).mean(axis=0) for part in scorer.pieces]

    def turned(k: int, turn: np.ndarray) -> Pose:
        """Part ``k`` turned by ``turn`` (3, 3, assembly frame) about its own centre."""
        centre = poses[k].apply(centres_part[k])
        rotation = turn @ poses[k].rotation
        return Pose.from_rotation(rotation, centre - rotation @ centres_part[k])

    def movable(k: int) -> bool:
        """Whether part ``k`` is drawn off the object enough to be moved: a part drawn on the object already is
        where the picture allows it, and moving it to cover pixels of another part's place only trades errors."""
        return not masks[k].any() or shares[k] < settings.movable_below

    def out_of_time() -> bool:
        return time.perf_counter() - started > settings.max_seconds

    classes = np.asarray(classes)
    groups = [np.flatnonzero(classes == c) for c in np.unique(classes)]
    groups = [g for g in groups if len(g) >= 2]
    for k in range(len(poses)):  # quarter and half turns about the assembly's axes
        for turn in _TURNS if movable(k) else ():
            if out_of_time():
                break
            try_moves({k: turned(k, turn)})
    for group in groups:  # equivalent parts spread about their centre in the floor plane
        centres = np.array([poses[k].position for k in group])
        middle = centres.mean(axis=0)
        for factor in settings.spreads:
            offset = (centres - middle) * np.array([factor - 1.0, factor - 1.0, 0.0])
            if try_moves({k: moved(poses[k], d) for k, d in zip(group, offset)}):
                centres = np.array([poses[k].position for k in group])
    for _ in range(settings.relocation_rounds):  # each part to where its outline best fills what no other covers
        for k in range(len(poses)):
            if out_of_time() or not movable(k):
                continue
            for delta in _relocations(scorer, k, poses[k], masks[k], coverage, settings):
                if try_moves({k: moved(poses[k], delta)}):
                    break
    axes = camera_from_assembly.rotation[:2] if settings.image_plane_moves else np.eye(3)
    for step in settings.steps:
        for _ in range(settings.rounds):
            improved = False
            for k in filter(movable, range(len(poses))):
                for axis in axes:
                    for sign in (1.0, -1.0):
                        if out_of_time():
                            break
                        improved |= try_moves({k: moved(poses[k], sign * step * extent_m * axis)})
            if not improved:
                break
    silhouette_after = iou(coverage > 0, scorer.object_px)
    return SolverResult(poses, score_before, best, silhouette_before, silhouette_after, moves,
                        time.perf_counter() - started,
                        {k: float(np.linalg.norm(p.position - o)) for k, (p, o) in enumerate(zip(poses, original))})


__all__ = ["SilhouetteScorer", "SolverResult", "SolverSettings", "solve"]
