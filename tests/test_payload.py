"""Payload limits: a part's mass properties from its mesh, and how much a heavy carry is slowed."""

import numpy as np
import pytest
import trimesh

from cell.task import PANDA_LIMITS
from planning.payload import MIN_SCALE, carry_limits, carry_scale, mass_properties
from planning.pose import Pose

GRASP_AT_CENTRE = Pose(np.zeros(3), np.array([1.0, 0.0, 0.0, 0.0]))


def edge_grasp(distance_m):
    return Pose(np.array([distance_m, 0.0, 0.0]), np.array([1.0, 0.0, 0.0, 0.0]))


def test_mass_properties_of_a_box():
    box = trimesh.creation.box(extents=(0.5, 0.3, 0.03))
    box.apply_translation((0.1, 0.0, 0.0))
    props = mass_properties(box, 600.0)
    assert props.mass_kg == pytest.approx(600.0 * 0.5 * 0.3 * 0.03)
    np.testing.assert_allclose(props.part_from_com.position, (0.1, 0.0, 0.0), atol=1e-9)
    largest = props.mass_kg * (0.5 ** 2 + 0.3 ** 2) / 12.0  # about the plate's normal
    assert max(props.inertia_kg_m2) == pytest.approx(largest)


def test_light_parts_keep_the_full_limits():
    stick = mass_properties(trimesh.creation.box(extents=(0.2, 0.02, 0.02)))  # 48 g
    assert carry_scale(stick, edge_grasp(0.08), 18.0) == 1.0
    assert carry_limits(PANDA_LIMITS, stick, edge_grasp(0.08)) is PANDA_LIMITS


def test_a_heavy_top_held_by_its_edge_is_carried_slower_the_farther_it_is_held():
    top = mass_properties(trimesh.creation.box(extents=(0.52, 0.32, 0.034)))  # 3.4 kg of wood
    near, far = carry_scale(top, edge_grasp(0.05), 18.0), carry_scale(top, edge_grasp(0.14), 18.0)
    assert MIN_SCALE <= far < near < 1.0
    slowed = carry_limits(PANDA_LIMITS, top, edge_grasp(0.14))
    np.testing.assert_allclose(slowed.acceleration, PANDA_LIMITS.acceleration * far)
    np.testing.assert_allclose(slowed.velocity, PANDA_LIMITS.velocity * np.sqrt(far))
    np.testing.assert_allclose(slowed.jerk, PANDA_LIMITS.jerk * far ** 1.5)
    # too heavy for the wrist even at rest: the slowest carry, not a negative limit
    anvil = mass_properties(trimesh.creation.box(extents=(0.3, 0.3, 0.3)), 2000.0)
    assert carry_scale(anvil, edge_grasp(0.15), 18.0) == MIN_SCALE
