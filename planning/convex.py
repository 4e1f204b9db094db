"""Convex pieces of part meshes, for collision queries that must tell touching from penetrating.

FCL's mesh-mesh distance reads 0 whenever two meshes overlap, so contact and penetration are measured on convex
pieces, where FCL's GJK/EPA gives a signed distance. A mesh is split into connected components; a component that
is (nearly) convex is replaced by its convex hull, any other is decomposed with V-HACD (``vhacdx`` through
trimesh). Decompositions take seconds, so they are cached on disk per mesh, keyed by a hash of its vertices and
faces, under ``$IMAGE_ASSEMBLY_CACHE`` (default ``~/.cache/image-assembly/convex``).
"""

from __future__ import annotations

import hashlib
import os
from pathlib import Path

import numpy as np
import trimesh

# a component is taken as convex when its hull deviates from it by at most this fraction of its size
CONVEXITY_TOLERANCE = 0.02
_MAX_HULLS_PER_COMPONENT = 12
_MAX_COMPONENTS = 16
_memory_cache: dict[str, list[trimesh.Trimesh]] = {}


def cache_dir() -> Path:
    root = os.environ.get("IMAGE_ASSEMBLY_CACHE")
    return Path(root) if root else Path.home() / ".cache" / "image-assembly" / "convex"


def convex_hull(points: np.ndarray) -> trimesh.Trimesh:
    """The convex hull of ``points`` (N, 3). A flat piece's hull has no volume, and trimesh, orienting its faces,
    divides by that volume: the warning it raises (a divide by zero) is silenced here, the hull kept as it is."""
    with np.errstate(divide="ignore", invalid="ignore"):
        return trimesh.convex.convex_hull(points)


def mesh_key(mesh: trimesh.Trimesh) -> str:
    digest = hashlib.sha256()
    digest.update(np.ascontiguousarray(mesh.vertices, dtype=np.float64).tobytes())
    digest.update(np.ascontiguousarray(mesh.faces, dtype=np.int64).tobytes())
    return digest.hexdigest()[:32]


def is_nearly_convex(component: trimesh.Trimesh, tolerance: float = CONVEXITY_TOLERANCE) -> bool:
    """Whether the convex hull of ``component`` stays within ``tolerance`` x its bounding-box diagonal of it."""
    hull = component.convex_hull
    size = float(np.linalg.norm(component.extents))
    if component.is_watertight and component.volume > 0:
        # volume test first: cheap, and exact for closed meshes
        if component.volume >= (1.0 - tolerance) * hull.volume:
            return True
        if component.volume < 0.5 * hull.volume:
            return False
    probes = np.concatenate([hull.vertices, hull.triangles_center])
    _, distance, _ = trimesh.proximity.closest_point(component, probes)
    return float(distance.max()) <= tolerance * size


COVER_TOLERANCE_M = 0.005
"""Convex pieces may fall short of their mesh's bounds by at most this (or :data:`COVER_FRACTION` of the mesh's
extent along that axis, whichever is larger) before they are decomposed again; V-HACD's pieces of a well-formed
solid stay within 3 mm (all 267 parts of ``../shared/furniture``), those of a flat or open shell fall short by a
board's thickness or more, so that parts that touch would not be seen to touch."""
COVER_FRACTION = 0.05


def shortfall_m(pieces: list[trimesh.Trimesh], mesh: trimesh.Trimesh) -> np.ndarray:
    """(3,) how far the union of ``pieces``' bounds falls short of ``mesh``'s along each axis (the larger of the
    two ends; 0 where they cover it), in the mesh's unit."""
    low = np.min([p.bounds[0] for p in pieces], axis=0)
    high = np.max([p.bounds[1] for p in pieces], axis=0)
    return np.maximum(np.maximum(low - mesh.bounds[0], mesh.bounds[1] - high), 0.0)


def covers(pieces: list[trimesh.Trimesh], mesh: trimesh.Trimesh) -> bool:
    """Whether ``pieces`` reach ``mesh``'s bounds within :data:`COVER_TOLERANCE_M` or :data:`COVER_FRACTION`."""
    allowed = np.maximum(COVER_TOLERANCE_M, COVER_FRACTION * np.asarray(mesh.extents))
    return bool(pieces) and bool(np.all(shortfall_m(pieces, mesh) <= allowed))


def _vhacd_hulls(component: trimesh.Trimesh, **settings) -> list[trimesh.Trimesh]:
    pieces = trimesh.decomposition.convex_decomposition(component, maxConvexHulls=_MAX_HULLS_PER_COMPONENT,
                                                        **settings)
    if isinstance(pieces, dict):
        pieces = [pieces]
    hulls = []
    for piece in pieces:
        piece_mesh = piece if isinstance(piece, trimesh.Trimesh) else trimesh.Trimesh(**piece)
        if len(piece_mesh.vertices) >= 4:
            hulls.append(piece_mesh.convex_hull)
    return hulls


def _decompose(component: trimesh.Trimesh) -> list[trimesh.Trimesh]:
    """V-HACD's convex pieces of ``component``; where they fall short of its bounds (:func:`covers`), those of a
    decomposition that fills the solid by casting rays (open or inside-out shells defeat the flood fill), and
    where those fall short too, the component's hull, which covers it (and any opening it has)."""
    try:
        hulls = _vhacd_hulls(component)
        if not covers(hulls, component):
            hulls = _vhacd_hulls(component, fillMode="raycast")
    except ImportError as exc:  # not a property of the mesh: say so rather than cache a hull in its place
        raise ImportError("convex decomposition needs the vhacdx package, a dependency of image-assembly: "
                          "pip install vhacdx (or pip install -e . in the repository)") from exc
    except Exception:  # a decomposition failure must not stop planning: fall back to the hull
        return [component.convex_hull]
    return hulls if covers(hulls, component) else [component.convex_hull]


def _load_cached(path: Path) -> list[trimesh.Trimesh] | None:
    try:
        with np.load(path) as data:
            count = int(data["count"])
            return [trimesh.Trimesh(data[f"v{i}"], data[f"f{i}"], process=False) for i in range(count)]
    except (OSError, KeyError, ValueError):
        return None


def _store_cached(path: Path, pieces: list[trimesh.Trimesh]) -> None:
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        arrays = {"count": np.array(len(pieces))}
        for i, piece in enumerate(pieces):
            arrays[f"v{i}"], arrays[f"f{i}"] = piece.vertices, piece.faces
        tmp = path.with_suffix(f".{os.getpid()}.tmp.npz")
        np.savez(tmp, **arrays)
        os.replace(tmp, path)
    except OSError:
        pass  # a read-only home is no reason to fail; the pieces are simply recomputed next time


def convex_pieces(mesh: trimesh.Trimesh, use_cache: bool = True) -> list[trimesh.Trimesh]:
    """Convex meshes whose union approximates ``mesh`` (same frame and unit). ``use_cache=False``: computed afresh,
    neither read from nor written to the caches (in memory and on disk), as a first run would."""
    key = mesh_key(mesh)
    if use_cache and key in _memory_cache:
        return _memory_cache[key]
    components = mesh.split(only_watertight=False) if len(mesh.faces) > 0 else []
    components = [c for c in components if len(c.vertices) >= 4 and c.area > 0] or [mesh]
    pieces: list[trimesh.Trimesh] = []
    concave = []
    if len(components) > _MAX_COMPONENTS:
        concave = [mesh]  # many loose bits (screws, holes as separate shells): decompose the whole part
    else:
        with np.errstate(all="ignore"):  # volumes of open components are meaningless, and trimesh warns
            for component in components:
                if is_nearly_convex(component):
                    pieces.append(component.convex_hull)
                else:
                    concave.append(component)
    if concave:
        path = cache_dir() / f"{key}.npz"
        cached = _load_cached(path) if use_cache and path.exists() else None
        if cached is None:
            cached = [hull for component in concave for hull in _decompose(component)]
            if use_cache:
                _store_cached(path, cached)
        pieces.extend(cached)
    if use_cache:
        _memory_cache[key] = pieces
    return pieces
