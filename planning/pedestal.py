"""What a part lies on in the kit: a pedestal, a box on the table inset from the part's footprint so that the
fingers reach under its edge (as the jig's pads, :mod:`planning.fixture`), and for a part that would roll or that
stands on its edge, chocks: posts beside its ends that cradle it. A narrow part bent along its length (a curved
rail) may lie on posts instead, under its ends and its centre of mass, that follow it.

Frames: a pedestal's box centre is ``world_from_pedestal`` (world frame, metres, +z up); its chocks and posts are
posed in the pedestal's frame; the part lies in a *rest* frame (:mod:`planning.stability`) whose x-y plane is the
pedestal's top.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np
import trimesh
from scipy.optimize import linprog

from planning.convex import convex_pieces
from planning.fixture import FINGER_CLEARANCE_M, MIN_PAD_FRACTION
from planning.pose import Pose
from planning.stability import SUPPORT_MARGIN_M, centre_of_mass, touching_points

NARROW_PART_M = 0.05  # a footprint narrower than this is grasped from beside: its pedestal is as wide as it ...
NARROW_INSET_M = 0.005  # ... less this on each side ...
NARROW_MIN_WIDTH_M = 0.008  # ... but at least this wide (or as wide as the part), to stand on
CHOCK_LENGTH_M = 0.02  # a chock's extent along the part ...
CHOCK_WIDTH_M = 0.01  # ... and across it
CHOCK_END_INSET_M = 0.002  # chocks stop this short of the part's ends
CHOCK_HEIGHT_FRACTION = 0.35  # a chock rises this fraction of the part's height above the pedestal's top ...
CHOCK_MAX_HEIGHT_M = 0.01  # ... at most this much
CHOCK_CLEARANCE_M = 0.0005  # between a chock and the part's side
CHOCK_LEAN_M = 0.004  # chocks rise so that a board pivoting on its foot onto them moves its top by this ...
CHOCK_TALL_FRACTION = 0.25  # ... with chocks rising at most this fraction of its height above the pedestal
CHOCK_CONTACT_SLOP_M = 0.0003  # a part between chocks moves this much farther than their clearance: the simulated
# part is inset by 0.25 mm (half the joint clearance) and sinks about 0.05 mm into a contact
ELONGATED_RATIO = 2.0  # only a footprint at least this many times longer than wide is cradled
POST_LENGTH_M = 0.02  # a post under a bent bar: its extent along the bar ...
POST_END_INSET_M = 0.01  # ... the end posts' centres this far inside the bar's ends beyond half that length
POST_TOUCH_M = 0.001  # an end post moves out to where the bar's underside comes within this of its lowest point
POST_RISE_M = 0.005  # posts rise to the bar's underside where that lies at most this above its lowest point
_PEDESTAL_MESHES: dict[tuple, trimesh.Trimesh] = {}
_PEDESTAL_MESHES_KEPT = 512


@dataclass(frozen=True)
class Pedestal:
    """A box standing on the table under a part (``size_m``, its centre at ``world_from_pedestal``), and for a
    part that would roll (a round leg), chocks: posts beside both ends of the part, from the table to a little
    above the pedestal's top, that cradle it (``chocks``: (size, pedestal_from_chock) per post, box centres).
    ``posts``: further boxes from the table up to the part that it lies on too, their tops within a few millimetres
    of the pedestal's top (same form as ``chocks``; :func:`posts_under`, whose first post is the box of
    ``size_m``)."""

    size_m: tuple[float, float, float]
    world_from_pedestal: Pose  # box centre
    chocks: tuple[tuple[tuple[float, float, float], Pose], ...] = ()
    posts: tuple[tuple[tuple[float, float, float], Pose], ...] = ()

    def mesh(self) -> trimesh.Trimesh:
        """The pedestal, its posts and its chocks (separate boxes; pedestal frame, metres). Pedestals of the same
        shape share one mesh (kitting asks for it thousands of times): do not modify it."""
        key = (tuple(self.size_m), *(tuple((tuple(size), pose.position.tobytes(), pose.quat_wxyz.tobytes())
                                           for size, pose in boxes) for boxes in (self.chocks, self.posts)))
        mesh = _PEDESTAL_MESHES.get(key)
        if mesh is None:
            boxes = [trimesh.creation.box(self.size_m)]
            boxes += [trimesh.creation.box(size, transform=pose.matrix()) for size, pose in self.posts + self.chocks]
            mesh = trimesh.util.concatenate(boxes) if len(boxes) > 1 else boxes[0]
            if len(_PEDESTAL_MESHES) >= _PEDESTAL_MESHES_KEPT:
                _PEDESTAL_MESHES.pop(next(iter(_PEDESTAL_MESHES)))
            _PEDESTAL_MESHES[key] = mesh
        return mesh


def pedestal_for(half_extent_xy: np.ndarray, world_from_rest: Pose, height_m: float, wide: bool = False) -> Pedestal:
    """A pedestal under a footprint of half extents ``half_extent_xy`` centred in the ``rest`` frame (whose x-y
    plane is the pedestal's top), inset for the fingers along the footprint's wide sides; ``wide``: inset by
    :data:`NARROW_INSET_M` only, all round (a frame lying flat falls around the inset one, through its opening)."""
    extent = 2.0 * np.asarray(half_extent_xy, dtype=np.float64)
    inset = np.minimum(FINGER_CLEARANCE_M, 0.5 * (1.0 - MIN_PAD_FRACTION) * extent)
    # across a narrow part the fingers close from beside it, not from under it: support it full width
    inset = np.where((extent < NARROW_PART_M) | wide, NARROW_INSET_M, inset)
    size = np.maximum(extent - 2 * inset, np.minimum(extent, NARROW_MIN_WIDTH_M))
    rest_from_pedestal = Pose([0.0, 0.0, -0.5 * height_m], [1.0, 0.0, 0.0, 0.0])
    return Pedestal((float(size[0]), float(size[1]), height_m), world_from_rest @ rest_from_pedestal)


def chocks_for(mesh: trimesh.Trimesh, rest_from_part: np.ndarray, height_m: float,
               support_rest_xy: np.ndarray) -> tuple | None:
    """Chocks (see :class:`Pedestal`; pedestal frame, the pedestal ``height_m`` tall and centred under the rest
    frame's origin) that cradle an elongated part lying in its rest pose, or None when they would not make it
    rest: the part's contact line on the support (``support_rest_xy``, rest frame x-y) must hold its centre of
    mass along the part, and the chocks hold it across."""
    rested = mesh.vertices @ rest_from_part[:3, :3].T + rest_from_part[:3, 3]
    span = rested.max(axis=0) - rested.min(axis=0)
    along = 0 if span[0] >= span[1] else 1
    if span[along] < ELONGATED_RATIO * span[1 - along]:
        return None
    com_rest = rest_from_part[:3, :3] @ centre_of_mass(mesh) + rest_from_part[:3, 3]
    touching = touching_points(mesh, rest_from_part, support_rest_xy)
    if len(touching) < 2 or not (touching[:, along].min() + SUPPORT_MARGIN_M < com_rest[along]
                                 < touching[:, along].max() - SUPPORT_MARGIN_M):
        return None
    return cradle_chocks(mesh, rest_from_part, height_m, inwards=False)


def cradle_chocks(mesh: trimesh.Trimesh, rest_from_part: np.ndarray, height_m: float,
                  inwards: bool = True) -> tuple | None:
    """The chocks of :func:`chocks_for` for an elongated part lying in its rest pose, whatever it touches the
    support with (whether it rests there is the caller's to judge), or None when it is not elongated: a pair of
    posts beside it at each end, where its cross-section comes below the chocks' top; ``inwards``: else nearer its
    middle (a tapered leg's thin end lies above them), else None."""
    rested = mesh.vertices @ rest_from_part[:3, :3].T + rest_from_part[:3, 3]
    span = rested.max(axis=0) - rested.min(axis=0)
    along = 0 if span[0] >= span[1] else 1
    across = 1 - along
    if span[along] < ELONGATED_RATIO * span[across]:
        return None
    com_along = float((rest_from_part[:3, :3] @ centre_of_mass(mesh) + rest_from_part[:3, 3])[along])
    rise = min(CHOCK_HEIGHT_FRACTION * span[2], CHOCK_MAX_HEIGHT_M)  # low, for a round leg lying down
    if span[2] > ELONGATED_RATIO * span[across]:
        # a board standing on its edge leans on its chocks by their clearance over their height: they rise far
        # enough that, pivoting on its foot, its top moves about CHOCK_LEAN_M (on 1 cm chocks a 3 mm panel 25 cm
        # tall leans by centimetres), capped at a quarter of its height (chocks rising to half of it blocked the
        # carries past them); its foot may slide too, and the simulated part is smaller: standing_lean_m
        rise = max(rise, min(CHOCK_CLEARANCE_M * span[2] / CHOCK_LEAN_M, CHOCK_TALL_FRACTION * span[2]))
    chocks = []
    for end in (rested[:, along].min() + CHOCK_END_INSET_M, rested[:, along].max() - CHOCK_END_INSET_M):
        inward = 1.0 if end < com_along else -1.0
        steps = max(int(inward * (com_along - end) // CHOCK_LENGTH_M), 1) if inwards else 1  # up to its middle
        for _ in range(steps):
            lo, hi = sorted((end, end + inward * CHOCK_LENGTH_M))
            beside = _section_below(mesh, rest_from_part, along, 0.5 * (lo + hi), rise)
            if len(beside):
                break
            end += inward * CHOCK_LENGTH_M
        if len(beside) == 0:
            return None
        # the chock clears the part all along its length (a bent bar runs across it), and the part's convex
        # pieces, which the simulation gives it and which bulge beyond the mesh: chocks set from the mesh's section
        # at their middle had chair_ivar_0668's frame of tubes 1.3 mm into them from the start, wedged there
        in_slab = rested[(rested[:, along] >= lo) & (rested[:, along] <= hi) & (rested[:, 2] <= rise)]
        beside = np.concatenate([beside, in_slab, *(_section_below(mesh, rest_from_part, along, at, rise)
                                                    for at in (lo, hi)),
                                 _pieces_beside(mesh, rest_from_part, along, lo, hi, rise)])
        for side in (-1.0, 1.0):
            face = (beside[:, across].max() if side > 0 else -beside[:, across].min()) + CHOCK_CLEARANCE_M
            centre = np.zeros(3)
            centre[along] = 0.5 * (lo + hi)
            centre[across] = side * (face + 0.5 * CHOCK_WIDTH_M)
            centre[2] = 0.5 * rise  # pedestal frame: the post spans the pedestal's height plus the rise
            size = np.zeros(3)
            size[along], size[across], size[2] = hi - lo, CHOCK_WIDTH_M, height_m + rise
            chocks.append((tuple(float(v) for v in size), Pose(centre, [1.0, 0.0, 0.0, 0.0])))
    return tuple(chocks)


def standing_lean_m(mesh: trimesh.Trimesh, rest_from_part: np.ndarray, pedestal: Pedestal,
                    height_m: float) -> float:
    """How far the top of a board standing on its edge between the ``pedestal``'s chocks (as
    :func:`cradle_chocks` makes them; the pedestal ``height_m`` tall) may move from where it stands, metres: its
    foot slides across the gap c to one side (c: the chocks' clearance and :data:`CHOCK_CONTACT_SLOP_M`) and it
    leans over the chocks on the other side, 2 c over their rise, up to its height H: ``c (1 + 2 H / rise)``; 0 for
    a part that does not stand on its edge there, or has no chocks."""
    if not pedestal.chocks:
        return 0.0
    rested = mesh.vertices @ rest_from_part[:3, :3].T + rest_from_part[:3, 3]
    span = rested.max(axis=0) - rested.min(axis=0)
    if span[2] <= ELONGATED_RATIO * min(span[0], span[1]):
        return 0.0
    rise = min(size[2] for size, _ in pedestal.chocks) - height_m
    gap = CHOCK_CLEARANCE_M + CHOCK_CONTACT_SLOP_M
    return float(gap * (1.0 + 2.0 * span[2] / rise)) if rise > 0.0 else 0.0


def _section_below(mesh: trimesh.Trimesh, rest_from_part: np.ndarray, axis: int, at: float,
                   below_z: float) -> np.ndarray:
    """Points (rest frame) of the part's cross-section by the plane ``rest[axis] = at`` lying below ``below_z``."""
    rested = trimesh.Trimesh(mesh.vertices @ rest_from_part[:3, :3].T + rest_from_part[:3, 3], mesh.faces,
                             process=False)
    normal = np.zeros(3)
    normal[axis] = 1.0
    segments = trimesh.intersections.mesh_plane(rested, normal, normal * at)
    if len(segments) == 0:
        return np.zeros((0, 3))
    t = np.linspace(0.0, 1.0, 11)[None, :, None]
    points = (segments[:, :1] * (1 - t) + segments[:, 1:] * t).reshape(-1, 3)
    return points[points[:, 2] <= below_z]


def _pieces_beside(mesh: trimesh.Trimesh, rest_from_part: np.ndarray, axis: int, lo: float, hi: float,
                   below_z: float) -> np.ndarray:
    """The points (rest frame) of the part's convex pieces (:func:`planning.convex.convex_pieces`, the shapes the
    simulation gives it) farthest to either side across ``axis`` within the slab ``lo <= rest[axis] <= hi`` below
    ``below_z``, two per piece that reaches into it: what a chock beside that stretch of the part must clear."""
    across = np.zeros(3)
    across[1 - axis] = 1.0
    slab = np.zeros((3, 3))
    slab[0, axis], slab[1, axis], slab[2, 2] = -1.0, 1.0, 1.0
    slab_b = np.array([-lo, hi, below_z])
    rotation, shift = rest_from_part[:3, :3], rest_from_part[:3, 3]
    points = [np.zeros((0, 3))]
    for piece in convex_pieces(mesh):
        normals = np.asarray(piece.face_normals) @ rotation.T  # rest frame: normals @ x <= offsets inside
        offsets = np.einsum("ij,ij->i", np.asarray(piece.face_normals), piece.triangles[:, 0]) + normals @ shift
        a_ub, b_ub = np.vstack([normals, slab]), np.concatenate([offsets + 1e-9, slab_b])
        for sign in (-1.0, 1.0):
            result = linprog(-sign * across, A_ub=a_ub, b_ub=b_ub, bounds=(None, None), method="highs")
            if result.status != 0:
                break  # the piece does not reach into the slab
            points.append(result.x[None, :])
    return np.concatenate(points)


def cut_back(pedestal: Pedestal, side: tuple[int, int], cut_m: float) -> Pedestal:
    """``pedestal`` (no chocks, no posts) with its top cut back by ``cut_m`` from its side ``side`` = (axis, sign)
    (0: x, 1: y of its own frame); the opposite edge stays where it is."""
    if pedestal.chocks or pedestal.posts:
        raise ValueError("only a plain box pedestal is cut back")
    axis, sign = side
    size = list(pedestal.size_m)
    size[axis] -= cut_m
    shift = np.zeros(3)
    shift[axis] = -sign * 0.5 * cut_m
    return dataclasses.replace(pedestal, size_m=tuple(size), world_from_pedestal=pedestal.world_from_pedestal
                               @ Pose(shift, [1.0, 0.0, 0.0, 0.0]))


def top_boxes(pedestal: Pedestal) -> list[tuple[np.ndarray, np.ndarray]]:
    """(min, max) x-y corners of the pedestal's top and of each of its posts' tops, in the frame it is posed in
    (unrotated about z)."""
    out = []
    for size, pose in [(pedestal.size_m, Pose([0, 0, 0], [1, 0, 0, 0])), *pedestal.posts]:
        centre, half = pedestal.world_from_pedestal.position[:2] + pose.position[:2], 0.5 * np.array(size[:2])
        out.append((centre - half, centre + half))
    return out


def top_box(pedestal: Pedestal) -> tuple[np.ndarray, np.ndarray]:
    """(min, max) x-y corners of the pedestal's own top (its main box, not its posts), in the frame it is posed in
    (unrotated about z)."""
    return top_boxes(pedestal)[0]


def posts_under(mesh: trimesh.Trimesh, rest_from_part: np.ndarray, height_m: float) -> Pedestal | None:
    """A pedestal of posts for a narrow elongated part lying in its rest pose (the pedestal posed in the rest
    frame, its posts in the pedestal's frame, metres; the pedestal ``height_m`` tall at z = 0): a post
    :data:`POST_LENGTH_M` long under each end and one under its centre of mass, each under the part's
    cross-section there (as wide as the narrowest section over the post's length, less :data:`NARROW_INSET_M` each
    side, at least :data:`NARROW_MIN_WIDTH_M`) and rising to the part's underside there, where that comes within
    :data:`POST_RISE_M` of its lowest point (a part settled tilted on its chocks); an end post moves out to where
    the part first comes down (an arch stands on its very ends); posts that would overlap are not doubled. A bar
    bent along its length (a curved chair rail) lies on them with its sides free for the fingers all along, where
    the one box under its footprint stands out beside it. None when the part is not narrow and elongated, its
    lowest point lies farther than :data:`POST_RISE_M` from z = 0, or fewer than two posts touch it. Whether it
    rests on them is the caller's to check."""
    rested = mesh.vertices @ rest_from_part[:3, :3].T + rest_from_part[:3, 3]
    span = rested.max(axis=0) - rested.min(axis=0)
    along = 0 if span[0] >= span[1] else 1
    across = 1 - along
    half = 0.5 * POST_LENGTH_M
    lowest = float(rested[:, 2].min())
    if (span[along] < ELONGATED_RATIO * span[across] or span[across] >= NARROW_PART_M
            or span[along] < 2.0 * (POST_LENGTH_M + POST_END_INSET_M) or abs(lowest) > POST_RISE_M):
        return None
    com_along = float((rest_from_part[:3, :3] @ centre_of_mass(mesh) + rest_from_part[:3, 3])[along])
    low = rested[rested[:, 2] <= lowest + POST_TOUCH_M, along]  # where its underside comes down lowest

    def post_at(at: float):
        """(centre, size) of the post centred ``at`` along the part (its top at the part's underside there, in the
        rest frame), or None where the part's underside there is higher than :data:`POST_RISE_M` above its
        lowest point."""
        sections = [_section_below(mesh, rest_from_part, along, at + shift, np.inf)
                    for shift in (0.0, -0.9 * half, 0.9 * half)]
        if len(sections[0]) == 0:
            return None
        over = rested[np.abs(rested[:, along] - at) <= half, 2]  # the part's vertices over the post
        top = min([float(section[:, 2].min()) for section in sections if len(section)] + over.tolist())
        if top > lowest + POST_RISE_M:
            return None
        # across, within the part all along the post: the narrowest of its sections there (a bent bar runs across)
        lo = max(section[:, across].min() for section in sections if len(section))
        hi = min(section[:, across].max() for section in sections if len(section))
        if hi <= lo:
            lo, hi = sections[0][:, across].min(), sections[0][:, across].max()
        width = max(hi - lo - 2.0 * NARROW_INSET_M, min(hi - lo, NARROW_MIN_WIDTH_M))
        centre, size = np.zeros(3), np.zeros(3)
        centre[along], centre[across], centre[2] = at, 0.5 * (lo + hi), 0.5 * (top - height_m)
        size[along], size[across], size[2] = POST_LENGTH_M, width, height_m + top
        return centre, tuple(float(v) for v in size)

    # the end posts inside the part's ends, or where it first comes down there (an arch stands on its very ends)
    first = (rested[:, along].min() + half + POST_END_INSET_M, low.min() + half)
    last = (rested[:, along].max() - half - POST_END_INSET_M, low.max() - half)
    ends = [next((post for post in map(post_at, options) if post is not None), None) for options in (first, last)]
    middle = post_at(float(np.clip(com_along, first[0], last[0])))
    boxes = []
    for post in (ends[0], ends[1], middle):  # the ends first; a post overlapping one already placed is left out
        if post is not None and all(abs(post[0][along] - other[0][along]) >= POST_LENGTH_M for other in boxes):
            boxes.append(post)
    if len(boxes) < 2:
        return None
    boxes.sort(key=lambda post: post[0][along])
    (main_centre, main_size), others = boxes[0], boxes[1:]
    world_from_pedestal = Pose(main_centre, [1.0, 0.0, 0.0, 0.0])
    posts = tuple((size, Pose(centre - main_centre, [1.0, 0.0, 0.0, 0.0])) for centre, size in others)
    return Pedestal(main_size, world_from_pedestal, posts=posts)
