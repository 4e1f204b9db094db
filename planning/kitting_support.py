"""What a part lies on in the kitting area, in each of its rest poses.

:class:`SupportChoice` keeps, per part and rest pose (the rest frame: the part's footprint centred on the origin,
its underside at z = 0), the pedestal it rests on (:mod:`planning.pedestal`): a box inset from its footprint, with
chocks beside a part that would roll; where the fingers closing on a frame of thin bars would reach into the box,
one cut back from a side; posts under a narrow part bent along its length; and the poses a part settles in under
physics when it rests in none as laid. Whether a part rests is judged by the geometry
(:func:`planning.stability.rests_stably`) and, when given, a physics check (``rests``, ``settles``; see
:func:`planning.kitting.plan_kitting`). Frames: rest frames as above (metres, +z up).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Sequence

import numpy as np
import trimesh

from planning.grasp import Grasp
from planning.gripper import MAX_OPENING_M
from planning.kitting_area import KittingArea, box_corners
from planning.pedestal import (
    Pedestal,
    chocks_for,
    cradle_chocks,
    cut_back,
    pedestal_for,
    posts_under,
    standing_lean_m,
    top_box,
    top_boxes,
)
from planning.pick_clearance import grasp_key, pickable
from planning.pose import Pose
from planning.stability import SUPPORT_MARGIN_M, centre_of_mass, rests_stably

SETTLE_MAX_TILT_DEG = 20.0  # a part laid down that settles turned farther than this from its rest pose fell over ...
SETTLE_MAX_DROP_M = 0.02  # ... one whose centre of mass sank farther than this fell off (or through) its pedestal
SETTLE_MAX_COM_HEIGHT_RATIO = 1.0  # ... and it must lie low: its centre of mass at most this times its footprint's
# half width above the pedestal's top (it tips over only past 45 degrees)
FRAME_CUTS_M = (0.03, 0.045, 0.06, 0.08)  # a pedestal under every grasp's fingers (a frame of thin bars lying
# on it) is cut back by one of these from one side, where its bars then overhang for the fingers
LEAN_SHARES = (1.0, 0.5)  # a standing board's grasps open for these shares of its lean (widest first)
MAX_GROUND_POSES = 7  # rest poses tried on the ground per part (the best for picking from above), and laid down
# to settle where none rests as laid

_TABLE_SLAB = trimesh.creation.box((2.0, 2.0, 0.02))  # the table under the physics check of resting parts


class SupportChoice:
    """The pedestal each part rests on in each rest pose, found once and kept (``support_cache``), for parts
    ``meshes`` (name -> mesh, part frame) laid out in ``area``."""

    def __init__(self, meshes: dict[str, trimesh.Trimesh], area: KittingArea) -> None:
        self.meshes, self.area = meshes, area
        self.target_rotations: dict[str, np.ndarray] = {}  # part -> world_from_part rotation at its target
        self.usable_at_target: dict[tuple, bool] = {}
        self.support_cache: dict[tuple, Pedestal | None] = {}
        self.leaning_cache: dict[tuple, list[Grasp]] = {}  # (part, rest pose) -> grasps opened for its lean
        self.rests = None  # physics check (loose bodies, fixed bodies) -> bool, see plan_kitting
        self.settles = None  # physics (loose bodies, fixed bodies) -> where they come to rest, see plan_kitting
        self.unrested: set[str] = set()  # parts with no pose that rests on a pedestal
        # parts that rest on a pedestal only wedged into it or its chocks (cell.resting.WEDGED_FORCE_RATIO): the
        # physics checks of their places allow it, as the last resort
        self.wedge_allowed: set[str] = set()
        self.fingers_freed: set[tuple] = set()  # (part, rest pose) whose pedestal :meth:`_free_fingers` checked
        self.posts_tried: set[tuple] = set()  # (part, rest pose) that :meth:`_onto_posts` tried

    def _support(self, name: str, rest_from_part: np.ndarray) -> Pedestal | None:
        """The pedestal (rest frame, see :meth:`_pedestal_at_rest`) the part rests on in this pose, the same
        anywhere: alone, or with the chocks that cradle it; None when it does not rest there (computed once per
        part and pose; :meth:`_settled` adds the poses it finds)."""
        key = (name, np.round(rest_from_part, 9).tobytes())
        if key not in self.support_cache:
            mesh = self.meshes[name]
            pedestal = pedestal_for(rest_half(mesh, rest_from_part)[0], Pose([0, 0, 0], [1, 0, 0, 0]),
                                    self.area.pedestal_height_m)
            chocks = () if self._supported(name, rest_from_part, pedestal) else chocks_for(
                mesh, rest_from_part, self.area.pedestal_height_m, self._top(pedestal))
            pedestal = None if chocks is None else dataclasses.replace(pedestal, chocks=chocks)
            if pedestal is not None and self.rests is not None:  # and it stays there under physics
                if not self._rests(name, [(mesh, Pose.from_matrix(rest_from_part))], self._fixed(pedestal)):
                    pedestal = None
            self.support_cache[key] = pedestal
        return self.support_cache[key]

    def _supported(self, name: str, rest_from_part: np.ndarray, pedestal: Pedestal) -> bool:
        return rests_stably(self.meshes[name], rest_from_part, self._top(pedestal))

    @staticmethod
    def _top(pedestal: Pedestal) -> np.ndarray:
        """The pedestal's top outline (4, 2) in the rest frame (centred under the part, or cut back off centre; its
        main box only, for a pedestal of posts)."""
        return box_corners(*top_box(pedestal))

    @staticmethod
    def _table_slab(top_z_m: float) -> tuple[trimesh.Trimesh, Pose]:
        """A 2 m x 2 m table top at height ``top_z_m`` (world), for the physics check of resting parts (one shared
        mesh, so the check recognises it without hashing a new one each time)."""
        return _TABLE_SLAB, Pose([0.0, 0.0, top_z_m - 0.5 * _TABLE_SLAB.extents[2]], [1.0, 0.0, 0.0, 0.0])

    def _fixed(self, pedestal: Pedestal) -> list[tuple[trimesh.Trimesh, Pose]]:
        """A rest-frame pedestal and the table under it, for the physics checks."""
        return [(pedestal.mesh(), pedestal.world_from_pedestal), self._table_slab(-self.area.pedestal_height_m)]

    def _pedestal_at_rest(self, name: str, rest_from_part: np.ndarray, wide: bool = False) -> Pedestal:
        """The pedestal made for the part in this rest pose (rest frame: its top at z = 0 under the footprint's
        centre), with chocks if the part is elongated."""
        mesh = self.meshes[name]
        pedestal = pedestal_for(rest_half(mesh, rest_from_part)[0], Pose([0, 0, 0], [1, 0, 0, 0]),
                                self.area.pedestal_height_m, wide)
        return dataclasses.replace(pedestal, chocks=cradle_chocks(mesh, rest_from_part, self.area.pedestal_height_m)
                                   or ())

    def _ground_poses(self, name: str, poses: list[tuple[np.ndarray, float]]) -> list[tuple[np.ndarray, float]]:
        """The rest poses (rest_from_part, probability) in which the part rests on its pedestal as the geometry
        and the physics check judge them; and the poses it settles in under physics (:meth:`_settled`) when laid
        down as it sits in the assembly (the first of ``poses`` when it has a target rotation) and that does not
        rest as it is, or laid down in each of the first :data:`MAX_GROUND_POSES` when none rests."""
        ground = [pose for pose in poses if self._support(name, pose[0]) is not None]
        if self.settles is not None:
            upright = name in self.target_rotations and self._support(name, poses[0][0]) is None
            ground += self._settled_poses(name, poses if not ground else poses[:1] if upright else [])
        if not ground and self.rests is not None and name not in self.wedge_allowed:
            self.wedge_allowed.add(name)  # no pose rests unwedged: then wedged
            self.support_cache = {key: pedestal for key, pedestal in self.support_cache.items()
                                  if pedestal is not None or key[0] != name}
            return self._ground_poses(name, poses)
        if not ground:
            self.unrested.add(name)
        return ground

    def _settled_poses(self, name: str, poses: list[tuple[np.ndarray, float]]) -> list[tuple[np.ndarray, float]]:
        """Where the part lies once settled (:meth:`_settled`) when laid down in each of the first
        :data:`MAX_GROUND_POSES` of ``poses``, for those it settles in."""
        settled = ((self._settled(name, rest_from_part), p) for rest_from_part, p in poses[:MAX_GROUND_POSES])
        return [(rest_from_part, p) for rest_from_part, p in settled if rest_from_part is not None]

    def _rests(self, name: str, loose: list[tuple[trimesh.Trimesh, Pose]],
               fixed: list[tuple[trimesh.Trimesh, Pose]]) -> bool:
        """The physics check (:attr:`rests`) of part ``name``'s place, wedged allowed where it must be."""
        return bool(self.rests(loose, fixed, allow_wedged=name in self.wedge_allowed))

    def _settles(self, name: str, loose: list[tuple[trimesh.Trimesh, Pose]],
                 fixed: list[tuple[trimesh.Trimesh, Pose]]):
        """Where part ``name`` settles (:attr:`settles`), wedged allowed where it must be."""
        return self.settles(loose, fixed, allow_wedged=name in self.wedge_allowed)

    def _settled(self, name: str, rest_from_part: np.ndarray) -> np.ndarray | None:
        """``rest_from_part`` of the part laid down in this pose on its pedestal (cradled if elongated; else wide,
        when the part does not settle on the usual one) once it has settled there under physics
        (:attr:`settles`), centred over the same pedestal made for it as it lies, which it must rest on too;
        None when it does not settle, or tips beyond :data:`SETTLE_MAX_TILT_DEG` or its centre of mass sinks
        beyond :data:`SETTLE_MAX_DROP_M` on the way (it fell over, off or through), or it does not lie low
        (:data:`SETTLE_MAX_COM_HEIGHT_RATIO`)."""
        mesh = self.meshes[name]
        for wide in (False, True):
            pedestal = self._pedestal_at_rest(name, rest_from_part, wide)
            settled = self._settles(name, [(mesh, Pose.from_matrix(rest_from_part))], self._fixed(pedestal))
            if settled is None:
                continue
            lying = settled[0].matrix()
            if not settled_low(mesh, rest_from_part, lying):
                continue
            lying[:2, 3] -= footprint_centre(mesh, lying)  # centred in x-y, as rest poses are
            pedestal = self._pedestal_at_rest(name, lying, wide)
            if self.rests is not None and not self._rests(name, [(mesh, Pose.from_matrix(lying))],
                                                          self._fixed(pedestal)):
                continue
            self.support_cache[(name, np.round(lying, 9).tobytes())] = pedestal
            return lying
        return None

    def _usable_at_target(self, name: str, grasp: Grasp, grasp_ok_at_target) -> bool:
        key = (name, grasp_key(grasp))
        if key not in self.usable_at_target:
            self.usable_at_target[key] = bool(grasp_ok_at_target(name, grasp))
        return self.usable_at_target[key]

    def _clear_of(self, grasps: Sequence[Grasp], rest_from_part: np.ndarray, pedestal: Pedestal) -> list[Grasp]:
        """The ``grasps`` whose hand clears the pedestal (rest frame) and the table, the part lying on it."""
        return pickable(grasps, Pose.from_matrix(rest_from_part), self._fixed(pedestal)[:1],
                         -self.area.pedestal_height_m)

    def _leaning_grasps(self, name: str, rest_from_part: np.ndarray, grasps: Sequence[Grasp]) -> list[Grasp]:
        """For a board standing on its edge between chocks in this rest pose: ``grasps`` opened wider at the pick
        (``Grasp.pick_opening_m``; at the target as usual: a wide open hand releasing a cabinet's top there met a
        drawer front) by twice how far its top may move (:func:`planning.pedestal.standing_lean_m`), so that a
        finger coming down beside it clears it leaning either way, then by half that (leaning onto one chock, its
        foot where it stood, as cabinet_13's drawer side did by 6 mm at its top, where a finger with 5 mm to spare
        came down on it), for where the widest opening meets a neighbour; else none. The same copies each time (the
        checks cache them)."""
        key = (name, np.round(rest_from_part, 9).tobytes())
        if key not in self.leaning_cache:
            pedestal = self.support_cache.get(key)
            lean = (0.0 if pedestal is None else
                    standing_lean_m(self.meshes[name], rest_from_part, pedestal, self.area.pedestal_height_m))
            self.leaning_cache[key] = [] if lean <= 0.0 else [
                dataclasses.replace(g, pick_opening_m=min(g.opening_m + 2.0 * share * lean, MAX_OPENING_M))
                for share in LEAN_SHARES for g in grasps if g.opening_m < MAX_OPENING_M]
        return self.leaning_cache[key]

    def _free_fingers(self, name: str, rest_from_part: np.ndarray, grasps: Sequence[Grasp],
                      grasp_ok_at_target) -> np.ndarray:
        """The rest pose to try in place of ``rest_from_part``. Where none of the grasps that clear the part's
        pedestal in this pose works at the target (a frame of thin bars lying on it: the fingers closing on a bar
        reach down into the pedestal's top), the pedestal becomes one cut back from one side
        (:meth:`_cut_pedestals`), so that the bars there overhang: the same pose if the part rests on it as it
        is (the physics check, else the geometric one), or where it settles on it (as :meth:`_settled` accepts),
        re-centred with the pedestal; else the pose and pedestal stay."""
        key = (name, np.round(rest_from_part, 9).tobytes())
        pedestal = self.support_cache.get(key)
        if pedestal is None or pedestal.chocks or pedestal.posts or key in self.fingers_freed:
            return rest_from_part
        self.fingers_freed.add(key)
        if any(self._usable_at_target(name, g, grasp_ok_at_target)
               for g in self._clear_of(grasps, rest_from_part, pedestal)):
            return rest_from_part
        mesh, part = self.meshes[name], Pose.from_matrix(rest_from_part)
        usable = lambda grasp: self._usable_at_target(name, grasp, grasp_ok_at_target)  # noqa: E731
        for cut in self._cut_pedestals(name, rest_from_part, pedestal, grasps, usable):
            if (self._rests(name, [(mesh, part)], self._fixed(cut)) if self.rests is not None else
                    rests_stably(mesh, rest_from_part, self._top(cut))):
                self.support_cache[key] = cut
                return rest_from_part
            settled = None if self.settles is None else self._settles(name, [(mesh, part)], self._fixed(cut))
            if settled is None or not settled_low(mesh, rest_from_part, settled[0].matrix()):
                continue
            lying = settled[0].matrix()
            centre = footprint_centre(mesh, lying)
            lying[:2, 3] -= centre
            cut = dataclasses.replace(cut, world_from_pedestal=Pose([-centre[0], -centre[1], 0.0], [1, 0, 0, 0])
                                      @ cut.world_from_pedestal)
            if self.rests is not None and not self._rests(name, [(mesh, Pose.from_matrix(lying))],
                                                          self._fixed(cut)):
                continue
            settled_key = (name, np.round(lying, 9).tobytes())
            self.support_cache[settled_key] = cut
            self.fingers_freed.add(settled_key)
            return lying
        return rest_from_part

    def _cut_pedestals(self, name: str, rest_from_part: np.ndarray, pedestal: Pedestal, grasps: Sequence[Grasp],
                       usable: Callable[[Grasp], bool]) -> list[Pedestal]:
        """``pedestal`` (rest frame) cut back by :data:`FRAME_CUTS_M` from one side: per side the smallest cut that
        frees some of the ``grasps`` that are ``usable`` (at the target) and leaves the part's centre of mass over
        the top, the sides freeing the most grasps first."""
        com = (rest_from_part[:3, :3] @ centre_of_mass(self.meshes[name]) + rest_from_part[:3, 3])[:2]
        found = []
        for side in ((0, 1), (0, -1), (1, 1), (1, -1)):
            for cut_m in FRAME_CUTS_M:
                cut = cut_back(pedestal, side, cut_m)
                lo, hi = top_box(cut)
                if np.any(com < lo + SUPPORT_MARGIN_M) or np.any(com > hi - SUPPORT_MARGIN_M):
                    break  # cut back past its centre of mass
                freed = sum(map(usable, self._clear_of(grasps, rest_from_part, cut)))
                if freed:
                    found.append((freed, len(found), cut))
                    break
        return [cut for _, _, cut in sorted(found, key=lambda f: (-f[0], f[1]))]

    def _onto_posts(self, name: str, rest_from_part: np.ndarray, grasps: Sequence[Grasp],
                    grasp_ok_at_target) -> bool:
        """Whether the part, having found no place on its pedestals in any rest pose (the layout's ``place``),
        now lies on posts in this one (:func:`planning.pedestal.posts_under`; the pedestal for this pose replaced):
        a narrow part bent along its length, where some of ``grasps`` clear the posts but not the pedestal and work
        at the target, and which rests on the posts (the physics check, else the geometric one). Tried once per
        part and pose; the part keeps the posts in this pose in later tries of the layout. A part that finds a
        place on its pedestals never gets here: its layout is as without posts."""
        key = (name, np.round(rest_from_part, 9).tobytes())
        pedestal = self.support_cache.get(key)
        if pedestal is None or pedestal.posts or key in self.posts_tried:
            return False
        self.posts_tried.add(key)
        mesh = self.meshes[name]
        posts = posts_under(mesh, rest_from_part, self.area.pedestal_height_m)
        if posts is None:
            return False
        if pedestal.chocks:  # the same chocks cradle it (a round bar rolls on posts as on a box)
            posts_from_pedestal = posts.world_from_pedestal.inverse() @ pedestal.world_from_pedestal
            posts = dataclasses.replace(posts, chocks=tuple((size, posts_from_pedestal @ pose)
                                                            for size, pose in pedestal.chocks))
        on_pedestal = {grasp_key(g) for g in self._clear_of(grasps, rest_from_part, pedestal)}
        if not any(self._usable_at_target(name, g, grasp_ok_at_target)
                   for g in self._clear_of(grasps, rest_from_part, posts) if grasp_key(g) not in on_pedestal):
            return False  # (a straight bar's posts are as wide as its pedestal: they free no grasp)
        if not (self._rests(name, [(mesh, Pose.from_matrix(rest_from_part))], self._fixed(posts))
                if self.rests is not None else
                rests_stably(mesh, rest_from_part, [box_corners(lo, hi) for lo, hi in top_boxes(posts)])):
            return False
        self.support_cache[key] = posts
        return True


def settled_low(mesh: trimesh.Trimesh, rest_from_part: np.ndarray, lying: np.ndarray) -> bool:
    """Whether a part laid down in ``rest_from_part`` that settled in ``lying`` (both rest frames, 4x4) lies as
    :meth:`SupportChoice._settled` accepts: turned by at most :data:`SETTLE_MAX_TILT_DEG`, its centre of mass sunk
    by at most :data:`SETTLE_MAX_DROP_M`, and lying low (:data:`SETTLE_MAX_COM_HEIGHT_RATIO`)."""
    com = centre_of_mass(mesh)
    turned = lying[:3, :3] @ rest_from_part[:3, :3].T
    tilt = np.degrees(np.arccos(np.clip(turned[2, 2], -1.0, 1.0)))  # how far its up axis turned
    drop = float((rest_from_part[:3, :3] @ com)[2] + rest_from_part[2, 3] - (lying[:3, :3] @ com)[2] - lying[2, 3])
    moved = mesh.vertices @ lying[:3, :3].T + lying[:3, 3]
    half = 0.5 * np.ptp(moved[:, :2], axis=0)
    # lying low: untouched, a part standing on a narrow base balances, and tips over at the first nudge
    low = (lying[:3, :3] @ com)[2] + lying[2, 3] <= SETTLE_MAX_COM_HEIGHT_RATIO * half.min()
    return bool(tilt <= SETTLE_MAX_TILT_DEG and drop <= SETTLE_MAX_DROP_M and low)


def footprint_centre(mesh: trimesh.Trimesh, rest_from_part: np.ndarray) -> np.ndarray:
    """Centre (x, y) of the posed part's bounding box in the rest frame."""
    moved = mesh.vertices @ rest_from_part[:3, :3].T + rest_from_part[:3, 3]
    return 0.5 * (moved.min(axis=0) + moved.max(axis=0))[:2]


def rest_half(mesh: trimesh.Trimesh, rest_from_part: np.ndarray) -> tuple[np.ndarray, bool]:
    """Half extents (x, y) of the part's footprint in its rest frame, and whether x is the long side."""
    rested = mesh.vertices @ rest_from_part[:3, :3].T
    half = 0.5 * (rested.max(axis=0) - rested.min(axis=0))[:2]
    return half, bool(half[0] >= half[1])
