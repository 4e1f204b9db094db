"""Vertical members (legs, posts, columns) of box, round or tapered section, and where a flat face meets them.

A tapered leg is widest at its top. A horizontal member (stretcher, apron, shelf edge) that ends against a
leg is placed at the leg's widest point over the member's height span, so it touches the leg along one
edge and never overlaps it. Against a round leg the flat end sits tangent to the polygon, on the vertex
that points at it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from perception.synth.primitives import box as box_mesh
from perception.synth.primitives import prism, square_frustum

__all__ = ["SECTIONS", "Leg", "PlacedLeg"]

SECTIONS = ("box", "round", "tapered", "tapered_round")


@dataclass(frozen=True)
class Leg:
    """A vertical member: ``section`` in :data:`SECTIONS`, full width (or diameter) at top and bottom,
    length."""

    section: str
    top: float
    bottom: float
    length: float

    def __post_init__(self) -> None:
        if self.section not in SECTIONS:
            raise ValueError(f"unknown leg section {self.section!r}")
        if self.section in ("box", "round") and self.top != self.bottom:
            raise ValueError(
                f"a {self.section} leg has one width, got top {self.top} and bottom {self.bottom}"
            )

    @property
    def round(self) -> bool:
        return self.section in ("round", "tapered_round")

    @property
    def max_half_width(self) -> float:
        return 0.5 * max(self.top, self.bottom)

    @property
    def min_width(self) -> float:
        return min(self.top, self.bottom)

    def half_width_at(self, z_rel: float) -> float:
        """Half width (or radius) at height ``z_rel`` above the leg's bottom."""
        t = min(max(z_rel / self.length, 0.0), 1.0)
        return 0.5 * (self.bottom + (self.top - self.bottom) * t)

    def mesh(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """As-built mesh along z (vertices, faces, extents)."""
        w = max(self.top, self.bottom)
        extents = np.array([w, w, self.length])
        if self.section == "box":
            v, f = box_mesh(extents)
        elif self.section == "tapered":
            v, f = square_frustum(self.bottom, self.top, self.length)
        else:
            rb, rt = 0.5 * self.bottom, 0.5 * self.top
            v, f = prism(rb, rb, rt, rt, self.length)
        return v, f, extents


@dataclass(frozen=True)
class PlacedLeg:
    """A leg standing with its bottom at ``z0`` and its axis through (x, y)."""

    leg: Leg
    x: float
    y: float
    z0: float

    @property
    def z1(self) -> float:
        return self.z0 + self.leg.length

    @property
    def centre(self) -> np.ndarray:
        return np.array([self.x, self.y, self.z0 + 0.5 * self.leg.length])

    def reach(self, z_lo: float, z_hi: float) -> float:
        """Largest half width of the leg over the height span [z_lo, z_hi] (working-frame z): the distance
        from the axis at which a flat face spanning those heights touches the leg without overlapping it."""
        return max(self.leg.half_width_at(z_lo - self.z0), self.leg.half_width_at(z_hi - self.z0))
