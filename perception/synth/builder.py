"""Collects the parts and designed joints of one procedurally built object and turns them into an Assembly.

Generators place parts in a working frame (metres, +z up, anything for x and y); :meth:`Builder.finish`
moves the whole object so that its lowest point is at z = 0 and its x-y bounding box is centred at the
origin, as the assembly-folder format requires.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass, field

import numpy as np
import trimesh

from perception.synth.legs import PlacedLeg
from perception.synth.primitives import box, canonical_frame
from planning.assembly import MAX_PARTS, Assembly, AssemblyPart
from planning.pose import Pose

__all__ = ["SynthPart", "Builder", "GENERATOR"]

GENERATOR = "perception.synth"


@dataclass
class SynthPart:
    """One part under construction: canonical-frame mesh arrays and its placement in the working frame."""

    name: str
    vertices: np.ndarray  # (V, 3) canonical frame (bbox centre at origin, extents decreasing along x, y, z)
    faces: np.ndarray  # (F, 3)
    rotation: np.ndarray  # (3, 3) working_from_part
    centre: np.ndarray  # (3,) working-frame position of the part's bbox centre
    module: str  # sub-assembly the part belongs to ("back", "base", "drawer_1", ...), used by the mixed level

    def world_vertices(self) -> np.ndarray:
        return self.vertices @ self.rotation.T + self.centre


@dataclass
class Builder:
    """Accumulates parts and designed joints (pairs of part names meant to touch)."""

    parts: list[SynthPart] = field(default_factory=list)
    joints: list[tuple[str, str]] = field(default_factory=list)
    stages: dict[str, float] = field(default_factory=dict)
    max_stage_span: float | None = None
    _index: dict[str, int] = field(default_factory=dict)

    # --- adding parts -------------------------------------------------------------------------------------
    def add_mesh(
        self,
        name: str,
        vertices: np.ndarray,
        faces: np.ndarray,
        extents,
        centre,
        module: str,
        rotation: np.ndarray | None = None,
    ) -> str:
        """Add an as-built mesh (bbox-centred, box axes along x, y, z, full ``extents``) placed with its bbox
        centre at ``centre``, optionally turned by ``rotation`` (working frame) about that centre."""
        if name in self._index:
            raise ValueError(f"duplicate part name {name!r}")
        canonical, built_from_canonical = canonical_frame(vertices, extents)
        rot = (
            built_from_canonical
            if rotation is None
            else np.asarray(rotation, dtype=np.float64) @ built_from_canonical
        )
        self._index[name] = len(self.parts)
        self.parts.append(
            SynthPart(name, canonical, faces, rot, np.asarray(centre, dtype=np.float64), module)
        )
        return name

    def add_box(self, name: str, size, centre, module: str) -> str:
        """Add an axis-aligned box of full ``size`` (x, y, z) centred at ``centre``. Pass the same ``size``
        values to interchangeable parts so that their meshes are identical."""
        size = np.asarray(size, dtype=np.float64)
        if np.any(size < 0.004):
            raise ValueError(f"part {name!r} is degenerate: size {size.tolist()}")
        vertices, faces = box(size)
        return self.add_mesh(name, vertices, faces, size, centre, module)

    def add_leg(self, name: str, placed: PlacedLeg, module: str) -> str:
        """Add a vertical leg, post or column."""
        vertices, faces, extents = placed.leg.mesh()
        return self.add_mesh(name, vertices, faces, extents, placed.centre, module)

    def join(self, a: str, b: str) -> None:
        """Record that parts ``a`` and ``b`` are designed to touch."""
        for n in (a, b):
            if n not in self._index:
                raise KeyError(f"joint names unknown part {n!r}")
        if a != b and (a, b) not in self.joints and (b, a) not in self.joints:
            self.joints.append((a, b))

    def set_stages(self, order: list[list[str]], max_span: int | None = None) -> None:
        """Record a designed assembly order: ``order`` lists groups of part names (empty ones skipped), first
        placed first, the parts of one group in any order among themselves. The mixed level merges only parts
        whose stages no other part's stage lies strictly between, and (with ``max_span``) whose stages differ by
        at most ``max_span`` (see :mod:`perception.synth.merge`)."""
        self.max_stage_span = None if max_span is None else float(max_span)
        for rank, names in enumerate(n for n in order if n):
            for n in names:
                if n not in self._index:
                    raise KeyError(f"stage names unknown part {n!r}")
                self.stages[n] = float(rank)
        missing = sorted(set(self._index) - set(self.stages))
        if missing:
            raise RuntimeError(f"parts without a stage: {missing}")

    def has(self, name: str) -> bool:
        return name in self._index

    def __len__(self) -> int:
        return len(self.parts)

    # --- finishing ----------------------------------------------------------------------------------------
    def check_connected(self) -> None:
        """Raise if the designed joint graph does not connect every part (a generator bug)."""
        adjacency: dict[str, list[str]] = {p.name: [] for p in self.parts}
        for a, b in self.joints:
            adjacency[a].append(b)
            adjacency[b].append(a)
        start = self.parts[0].name
        seen, queue = {start}, deque([start])
        while queue:
            for nxt in adjacency[queue.popleft()]:
                if nxt not in seen:
                    seen.add(nxt)
                    queue.append(nxt)
        if len(seen) != len(self.parts):
            missing = sorted(set(adjacency) - seen)
            raise RuntimeError(f"designed joint graph is not connected; unreachable parts: {missing}")

    def recentre(self) -> None:
        """Shift every part so the object stands on z = 0 with its x-y bounding box centred at the origin."""
        poses = [Pose.from_rotation(p.rotation, p.centre) for p in self.parts]
        lo = np.full(3, np.inf)
        hi = np.full(3, -np.inf)
        for part, pose in zip(self.parts, poses):
            world = part.vertices @ pose.rotation.T + pose.position
            lo = np.minimum(lo, world.min(axis=0))
            hi = np.maximum(hi, world.max(axis=0))
        shift = np.array([-0.5 * (lo[0] + hi[0]), -0.5 * (lo[1] + hi[1]), -lo[2]])
        for part in self.parts:
            part.centre = part.centre + shift

    def finish(self, name: str, metadata: dict) -> Assembly:
        """Recentre, check, and build the Assembly (level-3 parts, one per primitive)."""
        if not 2 <= len(self.parts) <= MAX_PARTS:
            raise RuntimeError(f"{name}: generator produced {len(self.parts)} parts (allowed 2..{MAX_PARTS})")
        self.check_connected()
        self.recentre()
        parts = [
            AssemblyPart(
                p.name,
                trimesh.Trimesh(vertices=p.vertices, faces=p.faces, process=False),
                Pose.from_rotation(p.rotation, p.centre),
                f"parts/{p.name}.obj",
            )
            for p in self.parts
        ]
        meta = dict(metadata)
        meta["joints"] = [[a, b] for a, b in self.joints]
        meta["modules"] = {p.name: p.module for p in self.parts}
        if self.stages:
            meta["stages"] = {p.name: self.stages[p.name] for p in self.parts}
            if self.max_stage_span is not None:
                meta["max_stage_span"] = self.max_stage_span
        return Assembly(name=name, parts=parts, metadata=meta)
