"""The "mixed" granularity: merge random connected sub-assemblies of a level-3 object into single parts.

Groups are chosen in the designed joint graph, so every merged part is physically connected. A target part
count is drawn uniformly between 2 and one less than the level-3 count. Whole modules (a chair's back, a
leg-and-stretcher frame, a drawer box, a trestle) are merged first, each with a probability drawn per object
and only while the target is not overshot; then random joints are contracted (for example a table leg with
its adjacent apron) until the target is reached. A merged part's mesh is the concatenation
(``trimesh.util.concatenate``) of its members' meshes in the assembly frame, re-expressed in a frame
centred at its bounding-box centre with the assembly's axes.

Merges must keep the object assemblable by a robot, one part after the other:

- where the generator recorded a designed assembly order (``metadata["stages"]``: chairs, cabinets), a group
  never straddles another part's stage (that part would have to go in after one member and before another: a
  cabinet side merged with the bottom would have to go in before the drawers, whose sides are held from above,
  over the cabinet side's place; a chair's top rail merged with its posts leaves no way in for the slats
  between them) and, with ``metadata["max_stage_span"]``, spans at most that many stages (cabinets: no closed
  box without a free edge to hold it by);
- every merge is checked with the sequence planner without grasps (:func:`assemblable`: straight-line
  insertions, every part kept in contact with the floor), which rejects merges that lock a part in (a carcass
  merged with its door around a shelf, a seat frame around its slats). A rejected merge is redrawn from the same
  generator, with fewer merges after :data:`ATTEMPTS` tries, so the result stays a function of its state. The
  check costs about 0.1-0.4 s per object (blocking sweeps in :mod:`planning.sweep`).
"""

from __future__ import annotations

import fcl
import numpy as np
import trimesh

from perception.synth.sampling import chance, integer, uniform
from planning.assembly import Assembly, AssemblyPart
from planning.collision import ConvexPart
from planning.disassembly import plan_sequence
from planning.pose import Pose

__all__ = ["merge_parts", "assemblable"]

ATTEMPTS = 6  # random merges tried before drawing fewer merges
FEWER_ATTEMPTS = 6  # then tries with fewer and fewer merges


class _Groups:
    """Union-find over part indices that never merges down to fewer than two groups and, given the parts'
    designed assembly stages, only merges groups whose stages no other part's stage lies strictly between (such
    a part would have to go in after one member of the group and before another)."""

    def __init__(self, n: int, stages: list[float] | None = None, max_span: float | None = None) -> None:
        self.parent = list(range(n))
        self.count = n
        self.stages = stages
        self.max_span = max_span

    def find(self, i: int) -> int:
        while self.parent[i] != i:
            self.parent[i] = self.parent[self.parent[i]]
            i = self.parent[i]
        return i

    def allowed(self, members: list[int]) -> bool:
        """Whether merging the groups of ``members`` keeps every group's stages contiguous."""
        if self.stages is None:
            return True
        roots = {self.find(i) for i in members}
        inside = [j for j in range(len(self.parent)) if self.find(j) in roots]
        lo = min(self.stages[j] for j in inside)
        hi = max(self.stages[j] for j in inside)
        if self.max_span is not None and hi - lo > self.max_span:
            return False
        outside = set(range(len(self.parent))) - set(inside)
        return not any(lo < self.stages[j] < hi for j in outside)

    def merge(self, members: list[int]) -> bool:
        roots = sorted({self.find(i) for i in members})
        if len(roots) < 2 or self.count - (len(roots) - 1) < 2 or not self.allowed(members):
            return False
        for r in roots[1:]:
            self.parent[r] = roots[0]
        self.count -= len(roots) - 1
        return True


def _components(nodes: list[int], edges: list[tuple[int, int]]) -> list[list[int]]:
    """Connected components of the subgraph induced by ``nodes`` (each sorted, in order of first node)."""
    inside = set(nodes)
    adjacency: dict[int, list[int]] = {i: [] for i in nodes}
    for a, b in edges:
        if a in inside and b in inside:
            adjacency[a].append(b)
            adjacency[b].append(a)
    seen: set[int] = set()
    out = []
    for start in nodes:
        if start in seen:
            continue
        stack, comp = [start], []
        seen.add(start)
        while stack:
            i = stack.pop()
            comp.append(i)
            for j in adjacency[i]:
                if j not in seen:
                    seen.add(j)
                    stack.append(j)
        out.append(sorted(comp))
    return out


def _draw_groups(
    n: int,
    edges: list[tuple[int, int]],
    modules: list[str],
    rng: np.random.Generator,
    fewer: int = 0,
    stages: list[float] | None = None,
    max_span: float | None = None,
) -> list[list[int]]:
    """Members of each part of one random merge (lists of level-3 indices, in order of their first member).

    A target part count is drawn uniformly from [2, n - 1] (from [n - m, n - 1] with m = (n - 2) >> ``fewer``
    when ``fewer`` > 0, i.e. fewer merges); whole modules are merged first (each with a probability drawn per
    object, in random order, skipped when it would overshoot the target), then random joints, only as far as
    the parts' ``stages`` allow (see :class:`_Groups`)."""
    lo = 2 if fewer <= 0 else max(2, n - max(1, (n - 2) >> fewer))
    target = integer(rng, lo, n - 1)
    groups = _Groups(n, stages, max_span)
    p_module = uniform(rng, 0.2, 1.0)
    module_components = [
        comp
        for module in dict.fromkeys(modules)
        for comp in _components([i for i in range(n) if modules[i] == module], edges)
        if len(comp) >= 2
    ]
    for k in rng.permutation(len(module_components)):
        comp = module_components[int(k)]
        after = groups.count - (len({groups.find(i) for i in comp}) - 1)
        if after >= target and chance(rng, p_module):
            groups.merge(comp)
    while groups.count > target:
        candidates = [(a, b) for a, b in edges if groups.find(a) != groups.find(b) and groups.allowed([a, b])]
        if not candidates:
            break
        a, b = candidates[int(rng.integers(len(candidates)))]
        groups.merge([a, b])
    members_of: dict[int, list[int]] = {}
    for i in range(n):
        members_of.setdefault(groups.find(i), []).append(i)
    return sorted(members_of.values(), key=lambda m: m[0])


def _world_vertices(part: AssemblyPart) -> np.ndarray:
    pose = part.assembly_from_part
    return np.asarray(part.mesh.vertices) @ pose.rotation.T + pose.position


def _convex_part(name: str, pieces: list[trimesh.Trimesh]) -> ConvexPart:
    """A planner part whose convex pieces are given (level-3 parts are convex: no decomposition, no caches)."""
    geometries, piece_vertices, piece_normals = [], [], []
    for piece in pieces:
        vertices = np.asarray(piece.vertices, dtype=np.float64)
        faces = np.asarray(piece.faces, dtype=np.int64)
        flat = np.hstack([np.full((len(faces), 1), 3, dtype=np.int64), faces]).ravel()
        geometries.append(fcl.Convex(vertices, len(faces), flat))
        normals = np.asarray(piece.face_normals)
        signed = normals * np.where(normals[:, [0]] < 0, -1.0, 1.0)
        _, keep = np.unique(np.round(signed, 6), axis=0, return_index=True)
        piece_vertices.append(vertices)
        piece_normals.append(normals[np.sort(keep)])
    return ConvexPart(name, geometries, piece_vertices, piece_normals, np.concatenate(piece_vertices))


def _build(level3: Assembly, ordered: list[list[int]], name: str) -> tuple[Assembly, list[ConvexPart]]:
    """The merged assembly for groups ``ordered``, and its parts as planner parts (for :func:`assemblable`)."""
    names = level3.part_names
    modules = [level3.metadata["modules"][nm] for nm in names]
    index = {nm: i for i, nm in enumerate(names)}
    edges = [(index[a], index[b]) for a, b in level3.metadata["joints"]]
    parts: list[AssemblyPart] = []
    convex: list[ConvexPart] = []
    new_name_of: dict[int, str] = {}
    group_members: dict[str, list[str]] = {}
    group_modules: dict[str, str] = {}
    merged_count = 0
    for members in ordered:
        if len(members) == 1:
            part = level3.parts[members[0]]
            parts.append(AssemblyPart(part.name, part.mesh, part.assembly_from_part, part.mesh_file))
            new_name = part.name
            label = modules[members[0]]
            convex.append(_convex_part(new_name, [part.mesh]))
        else:
            distinct = list(dict.fromkeys(modules[i] for i in members))
            label = "_".join(distinct[:2]) + ("_etc" if len(distinct) > 2 else "")
            new_name = f"group_{merged_count:02d}_{label}"
            merged_count += 1
            meshes = [
                trimesh.Trimesh(vertices=_world_vertices(level3.parts[i]), faces=level3.parts[i].mesh.faces,
                                process=False)
                for i in members
            ]
            combined = trimesh.util.concatenate(meshes)
            lo, hi = combined.vertices.min(axis=0), combined.vertices.max(axis=0)
            centre = 0.5 * (lo + hi)
            mesh = trimesh.Trimesh(vertices=combined.vertices - centre, faces=combined.faces, process=False)
            parts.append(AssemblyPart(new_name, mesh, Pose(centre, np.array([1.0, 0.0, 0.0, 0.0])), ""))
            for m in meshes:
                m.vertices = m.vertices - centre
            convex.append(_convex_part(new_name, meshes))
        parts[-1].mesh_file = f"parts/{new_name}.obj"
        for i in members:
            new_name_of[i] = new_name
        group_members[new_name] = [names[i] for i in members]
        group_modules[new_name] = label

    joints: list[list[str]] = []
    seen: set[tuple[str, str]] = set()
    for a, b in edges:
        na, nb = new_name_of[a], new_name_of[b]
        if na != nb and (na, nb) not in seen and (nb, na) not in seen:
            seen.add((na, nb))
            joints.append([na, nb])

    meta = {k: v for k, v in level3.metadata.items() if k not in ("joints", "modules", "stages", "max_stage_span")}
    meta["level"] = "mixed"
    meta["joints"] = joints
    meta["modules"] = group_modules
    meta["groups"] = group_members
    meta["level3_part_count"] = len(names)
    return Assembly(name=name, parts=parts, metadata=meta), convex


def assemblable(assembly: Assembly, convex: list[ConvexPart] | None = None, time_budget_s: float = 2.0) -> bool:
    """Whether the sequence planner finds an assembly order for ``assembly`` without checking grasps (straight-line
    insertions free of the parts placed before, every part kept in contact with the floor)."""
    if convex is None:
        convex = [ConvexPart.from_mesh(p.name, p.mesh) for p in assembly.parts]
    poses = [p.assembly_from_part for p in assembly.parts]
    return plan_sequence(convex, poses, None, time_budget_s=time_budget_s).success


def merge_parts(level3: Assembly, rng: np.random.Generator, name: str, check: bool = True) -> Assembly:
    """Merge connected groups of ``level3``'s parts (which must carry ``metadata['joints']`` and
    ``metadata['modules']``, as :class:`~perception.synth.builder.Builder` writes them).

    With ``check``, a merge is kept only when the merged object can still be assembled (:func:`assemblable`):
    a merge can lock a part in (a carcass merged with its door around a shelf). Rejected merges are redrawn from
    ``rng``, with fewer merges after :data:`ATTEMPTS` tries; the result stays a function of the generator state.
    """
    names = level3.part_names
    n = len(names)
    if n < 3:
        raise ValueError(f"{level3.name}: {n} parts, too few to merge while keeping two")
    index = {nm: i for i, nm in enumerate(names)}
    edges = [(index[a], index[b]) for a, b in level3.metadata["joints"]]
    modules = [level3.metadata["modules"][nm] for nm in names]
    stage_of = level3.metadata.get("stages")
    stages = None if stage_of is None else [float(stage_of[nm]) for nm in names]
    max_span = level3.metadata.get("max_stage_span")
    for attempt in range(ATTEMPTS + FEWER_ATTEMPTS):
        fewer = max(0, attempt - ATTEMPTS + 1)
        ordered = _draw_groups(n, edges, modules, rng, fewer=fewer, stages=stages, max_span=max_span)
        if len(ordered) >= n:  # no merge the stages allow (not seen with the generators here): draw again
            continue
        assembly, convex = _build(level3, ordered, name)
        if not check or assemblable(assembly, convex):
            return assembly
    # last resort (not reached over thousands of objects): one joint, each in turn, in random order
    fallback = None
    for k in rng.permutation(len(edges)):
        groups = _Groups(n, stages, max_span)
        if not groups.merge(list(edges[int(k)])):
            continue
        ordered = sorted(
            ([i for i in range(n) if groups.find(i) == r] for r in {groups.find(i) for i in range(n)}),
            key=lambda m: m[0],
        )
        assembly, convex = _build(level3, ordered, name)
        if assemblable(assembly, convex):
            return assembly
        if fallback is None:
            fallback = assembly
    if fallback is None:
        raise RuntimeError(f"{level3.name}: no merge was possible")
    return fallback
