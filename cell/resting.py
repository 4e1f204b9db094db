"""Whether parts rest where the kitting layout puts them, checked with the simulation's own physics.

The kitting planner (:mod:`planning.kitting`) decides from geometry whether a part rests on its pedestal (its
contact with the support surrounds its centre of mass, with a margin for a tilt) or on the board under it. That
is a judgement about ideal shapes; the simulation sees the parts as compounds of inset convex pieces with
friction, and a real mesh (open, a frame of round tubes, a board with a bevelled underside) can rest in the first
and slide or tip over in the second: a chair's side frame of tubes standing on two narrow feet between 1 cm
chocks falls over within a second, a board stacked on a bevelled one slides off it, and later the fingers close
on air. :class:`PhysicsRestCheck` drops the bodies where the layout puts them in a headless PyBullet client built
as :mod:`cell.simulate` builds its cell (same bodies, friction, density and physics settings) and says whether every
loose one stays put, and whether it is wedged into what it lies on. :meth:`PhysicsRestCheck.settle` lets them come to
rest first and says where they lie (for a part that rests on its pedestal only once it has tipped onto it: a
dished board on a pedestal inset from its rim, a tapered leg).

Units: metres, seconds; poses ``world_from_*`` (world +z up) as :class:`planning.pose.Pose`.
"""

from __future__ import annotations

import tempfile
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import trimesh

from cell.bodies import add_convex_body
from cell.bullet import BulletClient
from cell.simulate import SimSettings, configure_physics
from planning.convex import mesh_key
from planning.payload import GRAVITY_M_S2, MassProperties, mass_properties
from planning.pose import Pose

REST_CHECK_S = 4.0
"""Simulated seconds the bodies are left alone. A part balanced at the edge of tipping moves slowly at first and
then faster and faster: cabinet_akurum_0014's part_03 on its pedestal moved 0.3 mm in 1.5 s, which a check that
short passed, and had tipped by 1 degree (2.3 mm) at 4 s; in the program it was woken 5.6 s in, kept tipping and
was picked 30 mm off."""
REST_MOTION_M = 0.002
"""A corner of a loose body's bounding box moving farther than this (metres) in that time: it does not rest."""
REST_SPEED_M_S = 0.004
"""... nor one whose centre still moves faster than this at the end (a slow creep off its support)."""
WEDGED_FORCE_RATIO = 3.0
"""A loose body pressed by contacts whose normal forces sum to more than this times the weight of all the loose
bodies is wedged. Resting, a body's contacts carry its weight and that of any body on it (0.2 to 2.2 measured,
under 1 while still moving); one jammed into its support is pressed far harder (12 to 55 measured) and is held
there by friction when lifted. A chair's frame of tubes lying between chocks (chair_bertil_0148's part_00,
0.83 kg) was jammed across them at both ends, 1.2 mm into them, with 258 N of contact, 30 times its weight. It
stayed put, so it passed as resting. In the program, an arm whose shoulder had less torque to spare (another IK
solution) stalled lifting it and tore it out with a jerk that broke joint 7's velocity limit. A wedged body counts
as resting only where the caller allows it (``allow_wedged``): the kit takes such a place only for a part that
rests unwedged in none of its poses."""
SETTLE_S = 1.5
"""Simulated seconds :meth:`PhysicsRestCheck.settle` lets the bodies move before it reads where they lie."""

Body = tuple[trimesh.Trimesh, Pose]


class PhysicsRestCheck:
    """``check(loose, fixed)``: whether every ``loose`` (mesh, world_from_part) stays where it is, within
    :data:`REST_MOTION_M` over :data:`REST_CHECK_S`, among the ``fixed`` (mesh, world_from_body) bodies (pedestals,
    the table) under gravity, and is not wedged there (pressed with over ``wedged_force_ratio`` times the loose
    bodies' weight, :data:`WEDGED_FORCE_RATIO`) unless ``allow_wedged``. One headless client is reused for every
    check; close it (or use ``with``)."""

    def __init__(self, settings: SimSettings | None = None, duration_s: float = REST_CHECK_S,
                 tolerance_m: float = REST_MOTION_M, speed_m_s: float = REST_SPEED_M_S,
                 wedged_force_ratio: float = WEDGED_FORCE_RATIO) -> None:
        self.settings = settings or SimSettings()
        self.duration_s, self.tolerance_m, self.speed_m_s = duration_s, tolerance_m, speed_m_s
        self.wedged_force_ratio = wedged_force_ratio
        self._client: BulletClient | None = None
        self._folder = tempfile.TemporaryDirectory(prefix="image-assembly-rest-")
        self._props: dict[str, MassProperties] = {}
        self.checks = 0  # how many simulations ran (for profiling and tests)
        self._answers: dict[tuple, tuple[bool, bool]] = {}  # the same bodies at the same poses: (still, wedged)
        self._settled: dict[tuple, list[Pose]] = {}  # the same bodies at the same poses: where they settle
        self._keys: dict[int, tuple[trimesh.Trimesh, str]] = {}  # id(mesh) -> (mesh, mesh_key): hashing is slow

    def __call__(self, loose: Sequence[Body], fixed: Sequence[Body], allow_wedged: bool = False) -> bool:
        return self.check(loose, fixed, allow_wedged)

    def check(self, loose: Sequence[Body], fixed: Sequence[Body], allow_wedged: bool = False) -> bool:
        key = self._key(loose, fixed)
        if key not in self._answers:
            self._answers[key] = self._simulate(loose, fixed, self.duration_s)[:2]
        still, wedged = self._answers[key]
        return still and (allow_wedged or not wedged)

    def settle(self, loose: Sequence[Body], fixed: Sequence[Body], allow_wedged: bool = False) -> list[Pose] | None:
        """Where the ``loose`` bodies lie (world_from_part, in their order) after :data:`SETTLE_S` under gravity
        among the ``fixed`` ones, provided they then rest there (:meth:`check` from those poses); else None.
        Where they went (fell off, tipped over) is the caller's to judge."""
        key = self._key(loose, fixed)
        if key not in self._settled:  # where they lie does not depend on allow_wedged, only whether that counts
            self._settled[key] = self._simulate(loose, fixed, SETTLE_S)[2]
        poses = self._settled[key]
        rested = self.check([(mesh, pose) for (mesh, _), pose in zip(loose, poses)], fixed, allow_wedged)
        return poses if rested else None

    def _key(self, loose: Sequence[Body], fixed: Sequence[Body]) -> tuple:
        key = tuple((self._mesh_key(mesh), np.round(pose.matrix(), 6).tobytes()) for mesh, pose in (*loose, *fixed))
        return (len(loose), key)

    def _mesh_key(self, mesh: trimesh.Trimesh) -> str:
        cached = self._keys.get(id(mesh))
        if cached is None or cached[0] is not mesh:
            cached = self._keys[id(mesh)] = (mesh, mesh_key(mesh))
        return cached[1]

    def _simulate(self, loose: Sequence[Body], fixed: Sequence[Body],
                  duration_s: float) -> tuple[bool, bool, list[Pose]]:
        """(whether every loose body stayed put for ``duration_s``, whether some loose body is wedged at the end
        (``wedged_force_ratio``), their world_from_part poses at the end)."""
        if self._client is None:
            self._client = BulletClient()
        pb, cid, settings = self._client.pb, self._client.client_id, self.settings
        self.checks += 1
        pb.resetSimulation(physicsClientId=cid)
        configure_physics(pb, cid, settings)
        folder = Path(self._folder.name)
        for mesh, world_from_body in fixed:
            add_convex_body(pb, cid, folder, mesh, world_from_body, None, settings.friction,
                            key=self._mesh_key(mesh))
        bodies, corners = [], []
        for mesh, world_from_part in loose:
            key = self._mesh_key(mesh)
            if key not in self._props:
                self._props[key] = mass_properties(mesh, settings.density_kg_m3)
            props = self._props[key]
            body = add_convex_body(pb, cid, folder, mesh, world_from_part, props, settings.friction,
                                   inset_m=0.5 * settings.joint_clearance_m, key=key)
            # the box's corners in the centre-of-mass frame PyBullet reports
            box = trimesh.bounds.corners(mesh.bounds)
            bodies.append(body)
            corners.append(props.part_from_com.inverse().apply(box))
        start = [self._corners_now(body, local) for body, local in zip(bodies, corners)]
        for _ in range(int(round(duration_s * settings.rate_hz))):
            pb.stepSimulation(physicsClientId=cid)
        still, wedged = True, False
        weight_n = GRAVITY_M_S2 * sum(self._props[self._mesh_key(mesh)].mass_kg for mesh, _ in loose)
        for body, local, before in zip(bodies, corners, start):
            moved = np.linalg.norm(self._corners_now(body, local) - before, axis=1).max()
            speed = np.linalg.norm(pb.getBaseVelocity(body, physicsClientId=cid)[0])
            pressed_n = sum(point[9] for point in pb.getContactPoints(bodyA=body, physicsClientId=cid))
            still &= bool(moved <= self.tolerance_m and speed <= self.speed_m_s)
            wedged |= bool(pressed_n > self.wedged_force_ratio * weight_n)
        poses = [self._world_from_com(body) @ self._props[self._mesh_key(mesh)].part_from_com.inverse()
                 for body, (mesh, _) in zip(bodies, loose)]
        return still, wedged, poses

    def _world_from_com(self, body: int) -> Pose:
        position, orientation = self._client.pb.getBasePositionAndOrientation(body,
                                                                              physicsClientId=self._client.client_id)
        return Pose.from_pybullet(position, orientation)

    def _corners_now(self, body: int, com_corners: np.ndarray) -> np.ndarray:
        return self._world_from_com(body).apply(com_corners)

    def close(self) -> None:
        if self._client is not None:
            self._client.close()
            self._client = None
        self._folder.cleanup()

    def __enter__(self) -> PhysicsRestCheck:
        return self

    def __exit__(self, *exc) -> None:
        self.close()
