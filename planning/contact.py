"""Contact and support graphs of an assembly (+z up, metres).

Two parts are in contact when the signed distance between their convex pieces is at most a tolerance relative
to their size (:func:`contact_tolerance_m`): real furniture meets within millimetres, and its connectors (dowels,
cam bolts) make parts overlap. Each contact keeps its witness points and a normal.

The support graph says which part rests on which under gravity: ``b`` rests on ``a`` when they touch and the
contact normal from ``a`` to ``b`` points up (within 45 degrees of +z), with the floor (the fixture) as the node
:data:`FLOOR`.
"""

from __future__ import annotations

from dataclasses import dataclass

import networkx as nx
import numpy as np

from planning.collision import ConvexPart, signed_distance
from planning.pose import Pose

FLOOR = "floor"
MIN_CONTACT_TOLERANCE_M = 0.002
MAX_CONTACT_TOLERANCE_M = 0.012
RELATIVE_CONTACT_TOLERANCE = 0.025
SUPPORT_NORMAL_MIN_Z = np.cos(np.radians(45.0))


def tolerance_for_size_m(size_m: float) -> float:
    """Gap under which a part of this size (its box diagonal, metres) touches something: 2.5%, within 2-12 mm."""
    return float(np.clip(RELATIVE_CONTACT_TOLERANCE * size_m, MIN_CONTACT_TOLERANCE_M, MAX_CONTACT_TOLERANCE_M))


def contact_tolerance_m(part_a: ConvexPart, part_b: ConvexPart) -> float:
    """Gap under which two parts count as touching: 2.5% of the smaller part's size, within 2-12 mm."""
    return tolerance_for_size_m(min(float(np.linalg.norm(np.ptp(p.vertices, axis=0))) for p in (part_a, part_b)))


@dataclass(frozen=True)
class Contact:
    """A contact between parts ``a`` and ``b`` (world frame, metres). ``normal_ab`` points from a into b."""

    a: str
    b: str
    distance_m: float  # signed: < 0 overlapping
    point_m: np.ndarray  # midpoint of the witness points
    normal_ab: np.ndarray


def contact_graph(parts: list[ConvexPart], poses: list[Pose], floor_z_m: float = 0.0) -> nx.Graph:
    """Undirected graph over part names plus :data:`FLOOR`; each edge holds a :class:`Contact` as ``contact``.

    A part touches the floor when its lowest point is within its contact tolerance of ``floor_z_m``.
    """
    graph = nx.Graph()
    graph.add_node(FLOOR)
    bounds = [p.bounds(pose) for p, pose in zip(parts, poses)]
    for part in parts:
        graph.add_node(part.name)
    for i, (part_a, pose_a) in enumerate(zip(parts, poses)):
        floor_tolerance = tolerance_for_size_m(float(np.linalg.norm(np.ptp(part_a.vertices, axis=0))))
        lowest = bounds[i][0, 2]
        if lowest - floor_z_m <= floor_tolerance:
            point = pose_a.apply(part_a.vertices[np.argmin(pose_a.apply(part_a.vertices)[:, 2])])
            graph.add_edge(FLOOR, part_a.name, contact=Contact(FLOOR, part_a.name, float(lowest - floor_z_m),
                                                               point, np.array([0.0, 0.0, 1.0])))
        for j in range(i + 1, len(parts)):
            part_b, pose_b = parts[j], poses[j]
            tolerance = contact_tolerance_m(part_a, part_b)
            result = signed_distance(part_a, pose_a, part_b, pose_b, cutoff_m=tolerance)
            if not result.measured or result.distance_m > tolerance:
                continue
            if result.point_a is not None:
                point = 0.5 * (result.point_a + result.point_b)
            else:  # overlapping: the middle of the overlap of the two parts' boxes
                point = 0.5 * (np.maximum(bounds[i][0], bounds[j][0]) + np.minimum(bounds[i][1], bounds[j][1]))
            graph.add_edge(part_a.name, part_b.name, contact=Contact(
                part_a.name, part_b.name, result.distance_m, point, result.normal_ab))
    return graph


def normal_from(contact: Contact, name: str) -> np.ndarray:
    """The contact normal pointing away from part ``name`` (into the other part)."""
    return contact.normal_ab if contact.a == name else -contact.normal_ab


def support_graph(contacts: nx.Graph) -> nx.DiGraph:
    """Directed graph with an edge ``a -> b`` when ``b`` rests on ``a`` (``a`` may be :data:`FLOOR`)."""
    support = nx.DiGraph()
    support.add_nodes_from(contacts.nodes)
    for _, _, data in contacts.edges(data=True):
        contact: Contact = data["contact"]
        upward_ab = float(contact.normal_ab[2])
        if contact.a == FLOOR or upward_ab >= SUPPORT_NORMAL_MIN_Z:
            support.add_edge(contact.a, contact.b)
        elif -upward_ab >= SUPPORT_NORMAL_MIN_Z:
            support.add_edge(contact.b, contact.a)
    return support


def pieces(contacts: nx.Graph) -> list[set[str]]:
    """The pieces of a :func:`contact_graph`: the sets of parts joined by contacts, the floor not counted (two
    parts that only stand on the floor are two pieces), largest first, then by name."""
    parts = contacts.subgraph(node for node in contacts if node != FLOOR)
    return sorted((set(c) for c in nx.connected_components(parts)), key=lambda c: (-len(c), sorted(c)))


def ungrounded(contacts: nx.Graph, present: set[str]) -> set[str]:
    """The parts of ``present`` without a path of contacts to the floor through parts in ``present``: with parts
    fastened where they touch, these would fall."""
    if not present:
        return set()
    sub = contacts.subgraph(set(present) | {FLOOR})
    return set(present) - nx.node_connected_component(sub, FLOOR)


def all_grounded(contacts: nx.Graph, present: set[str]) -> bool:
    """Whether every part in ``present`` has a path of contacts to the floor through parts in ``present``
    (touching parts are fastened once placed, standing for the connectors)."""
    return not ungrounded(contacts, present)
