"""The "mixed" granularity: merge random connected sub-assemblies of a level-3 object into single parts.

Groups are chosen in the designed joint graph, so every merged part is physically connected. A target part
count is drawn uniformly between 2 and one less than the level-3 count. Whole modules (a chair's back, a
leg-and-stretcher frame, a drawer box, a trestle) are merged first, each with a probability drawn per object
and only while the target is not overshot; then random joints are contracted (for example a table leg with
its adjacent apron) until the target is reached. A merged part's mesh is the concatenation
(``trimesh.util.concatenate``) of its members' meshes in the assembly frame, re-expressed in a frame
centred at its bounding-box centre with the assembly's axes.
"""

from __future__ import annotations

import numpy as np
import trimesh

from perception.synth.sampling import chance, integer, uniform
from planning.assembly import Assembly, AssemblyPart
from planning.pose import Pose

__all__ = ["merge_parts"]


class _Groups:
    """Union-find over part indices that never merges down to fewer than two groups."""

    def __init__(self, n: int) -> None:
        self.parent = list(range(n))
        self.count = n

    def find(self, i: int) -> int:
        while self.parent[i] != i:
            self.parent[i] = self.parent[self.parent[i]]
            i = self.parent[i]
        return i

    def merge(self, members: list[int]) -> bool:
        roots = sorted({self.find(i) for i in members})
        if len(roots) < 2 or self.count - (len(roots) - 1) < 2:
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


def merge_parts(level3: Assembly, rng: np.random.Generator, name: str) -> Assembly:
    """Merge connected groups of ``level3``'s parts (which must carry ``metadata['joints']`` and
    ``metadata['modules']``, as :class:`~perception.synth.builder.Builder` writes them)."""
    names = level3.part_names
    n = len(names)
    if n < 3:
        raise ValueError(f"{level3.name}: {n} parts, too few to merge while keeping two")
    index = {nm: i for i, nm in enumerate(names)}
    edges = [(index[a], index[b]) for a, b in level3.metadata["joints"]]
    modules = [level3.metadata["modules"][nm] for nm in names]

    # a target part count drawn uniformly from [2, n - 1]; whole modules first (each tried with a probability
    # drawn per object, in random order, skipped when it would overshoot the target), then random joints
    target = integer(rng, 2, n - 1)
    groups = _Groups(n)
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
        candidates = [(a, b) for a, b in edges if groups.find(a) != groups.find(b)]
        a, b = candidates[int(rng.integers(len(candidates)))]
        groups.merge([a, b])
    if groups.count >= n:  # cannot happen: target <= n - 1 and the joint graph is connected
        raise RuntimeError(f"{level3.name}: no merge was possible")

    # build the merged parts in order of their first member
    members_of: dict[int, list[int]] = {}
    for i in range(n):
        members_of.setdefault(groups.find(i), []).append(i)
    ordered = sorted(members_of.values(), key=lambda m: m[0])
    parts: list[AssemblyPart] = []
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
        else:
            distinct = list(dict.fromkeys(modules[i] for i in members))
            label = "_".join(distinct[:2]) + ("_etc" if len(distinct) > 2 else "")
            new_name = f"group_{merged_count:02d}_{label}"
            merged_count += 1
            meshes = []
            for i in members:
                src = level3.parts[i]
                pose = src.assembly_from_part
                world = np.asarray(src.mesh.vertices) @ pose.rotation.T + pose.position
                meshes.append(trimesh.Trimesh(vertices=world, faces=src.mesh.faces, process=False))
            combined = trimesh.util.concatenate(meshes)
            lo, hi = combined.vertices.min(axis=0), combined.vertices.max(axis=0)
            centre = 0.5 * (lo + hi)
            mesh = trimesh.Trimesh(vertices=combined.vertices - centre, faces=combined.faces, process=False)
            parts.append(AssemblyPart(new_name, mesh, Pose(centre, np.array([1.0, 0.0, 0.0, 0.0])), ""))
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

    meta = {k: v for k, v in level3.metadata.items() if k not in ("joints", "modules")}
    meta["level"] = "mixed"
    meta["joints"] = joints
    meta["modules"] = group_modules
    meta["groups"] = group_members
    meta["level3_part_count"] = n
    return Assembly(name=name, parts=parts, metadata=meta)
