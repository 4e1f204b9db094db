"""Kitting: stable rest poses, a ring layout on the table, and a pick grasp that also serves at the target."""

import numpy as np
import pytest
import trimesh
from scipy.spatial.transform import Rotation

from planning.assembly import read_assembly
from planning.grasp import APPROACH_M, Grasp, feasible_grasps
from planning.kitting import NO_GRASP_AT_TARGET, TOO_LARGE, KittingError, Reach, plan_kitting
from planning.kitting_area import KittingArea, polygons_overlap
from planning.pick_clearance import (
    HAND,
    HAND_CLEARANCE_M,
    NEIGHBOUR_CLEARANCE_M,
    clear_at_pick,
    pickable,
    tips_under,
)
from planning.pose import Pose
from planning.sequence import GraspChecker
from planning.stability import stable_rest_poses
from scenes import sample_folder

AREA = KittingArea(centre_xy=(0.0, 0.0), inner_radius_m=0.32, outer_radius_m=0.72, table_min_xy=(-0.55, -0.8),
                   table_max_xy=(0.95, 0.8), table_z_m=0.0, pedestal_height_m=0.12,
                   keep_out=(((0.25, -0.25), (0.75, 0.25)),), gap_m=0.06)


def test_a_board_rests_flat_most_often():
    board = trimesh.creation.box([0.3, 0.1, 0.02])
    poses = stable_rest_poses(board)
    rest_from_part, probability = poses[0]
    rested = board.vertices @ rest_from_part[:3, :3].T + rest_from_part[:3, 3]
    assert rested[:, 2].min() == pytest.approx(0.0, abs=1e-9)
    assert np.ptp(rested[:, 2]) == pytest.approx(0.02)  # lying on its face
    assert probability == max(p for _, p in poses)


def test_chair_parts_lie_apart_in_the_ring_with_grasps_valid_at_pick():
    assembly = read_assembly(sample_folder("chair"))
    checker = GraspChecker(assembly)
    names = assembly.part_names  # taken as the assembly order
    slots = plan_kitting(names, [p.mesh for p in assembly.parts], checker.candidates,
                         lambda name, grasp: True, AREA, prefer_near_xy=(0.5, 0.0))
    assert [s.part for s in slots] == names
    by_name = {s.part: s for s in slots}
    for k, slot in enumerate(slots):
        mesh = assembly.part(slot.part).mesh
        world = slot.world_from_part.apply(mesh.vertices)
        if slot.rests_on is None:
            assert world[:, 2].min() == pytest.approx(0.12, abs=1e-6)  # resting on its pedestal
        else:  # on a board assembled after it
            base = by_name[slot.rests_on]
            assert names.index(slot.rests_on) > k
            top = base.world_from_part.apply(assembly.part(base.part).mesh.vertices)[:, 2].max()
            assert world[:, 2].min() == pytest.approx(top, abs=1e-6)
        centre = slot.footprint_world.mean(axis=0)
        assert 0.32 <= np.linalg.norm(centre) <= 0.72 + 1e-9
        # the footprint holds the part's own x-y extent and lies on the table, outside the jig's keep-out
        assert np.all(world[:, :2].min(axis=0) >= slot.footprint_world.min(axis=0) - 1e-6)
        assert np.all(world[:, :2].max(axis=0) <= slot.footprint_world.max(axis=0) + 1e-6)
        assert np.all(slot.footprint_world >= [-0.55, -0.8]) and np.all(slot.footprint_world <= [0.95, 0.8])
        assert not np.any(np.all((world[:, :2] > [0.25, -0.25]) & (world[:, :2] < [0.75, 0.25]), axis=1))
        for other in slots[:k]:
            stacked = slot.part in (other.rests_on, other.part) or other.part == slot.rests_on
            assert stacked or not polygons_overlap(slot.footprint_world, other.footprint_world)
        # when it is picked: the pedestals and the parts assembled after it are there, its support aside
        present = [(assembly.part(o.part).mesh, o.world_from_part) for o in slots[k + 1:]
                   if o.part != slot.rests_on]
        present += [(o.pedestal.mesh(), o.pedestal.world_from_pedestal) for o in slots if o.pedestal is not None]
        if slot.rests_on is not None:
            present.append((assembly.part(slot.rests_on).mesh, by_name[slot.rests_on].world_from_part))
        again = feasible_grasps([slot.grasp], slot.world_from_part, present, None, floor_z=0.0)
        assert len(again) == 1


def test_no_grasp_at_target_is_named():
    assembly = read_assembly(sample_folder("table"))
    checker = GraspChecker(assembly)
    with pytest.raises(KittingError, match="part 'top': no grasp works at its target") as caught:
        plan_kitting(assembly.part_names[::-1], [p.mesh for p in assembly.parts][::-1], checker.candidates,
                     lambda name, grasp: name != "top", AREA)
    assert caught.value.kind == NO_GRASP_AT_TARGET and caught.value.part == "top"  # what cell.plan acts on


def test_a_ring_too_small_says_so():
    board = trimesh.creation.box([0.3, 0.1, 0.02])
    small = KittingArea(centre_xy=(0.0, 0.0), inner_radius_m=0.32, outer_radius_m=0.72, table_min_xy=(-0.2, -0.2),
                        table_max_xy=(0.2, 0.2), table_z_m=0.0, pedestal_height_m=0.04)  # the ring leaves the table
    from planning.grasp import antipodal_grasps

    grasps = antipodal_grasps(board, np.random.default_rng(0))
    with pytest.raises(KittingError, match="too large for this cell") as caught:
        plan_kitting(["board"], [board], {"board": grasps}, lambda n, g: True, small)
    assert caught.value.kind == TOO_LARGE


@pytest.mark.parametrize("diameter_m, laid_out", [(0.012, False), (0.016, True)])
def test_a_part_too_low_for_the_fingers_is_named_as_such(diameter_m, laid_out):
    """A dowel 60 mm long lying on its support: at 12 mm across, every grasp's fingers reach below it into what it
    lies on, at every place, and the failure says the part is too small for the hand; at 16 mm it is laid out."""
    from planning.grasp import antipodal_grasps

    dowel = trimesh.creation.cylinder(diameter_m / 2, 0.06, sections=24)
    grasps = antipodal_grasps(dowel, np.random.default_rng(0))
    if laid_out:
        assert plan_kitting(["dowel"], [dowel], {"dowel": grasps}, lambda n, g: True, AREA)
        return
    with pytest.raises(KittingError, match="part 'dowel': at no place in the kitting ring does any of its grasps "
                                           "keep the hand clear of what the part lies on .it is 12 mm across"):
        plan_kitting(["dowel"], [dowel], {"dowel": grasps}, lambda n, g: True, AREA)


@pytest.mark.parametrize("dowel_first", [False, True])
def test_a_part_laid_out_first_that_finds_no_place_fails_the_layout_at_once(dowel_first):
    """A dowel too low for the fingers (12 mm across) beside three boards: by size the boards are laid out before
    it, each grasp checked at its target, and then the dowel fails. Named in ``lay_out_first`` (cell.plan names a
    part that failed with the jig placed otherwise), the dowel is laid out first and fails before any board is
    tried; the failure is the same."""
    from planning.grasp import antipodal_grasps

    dowel = trimesh.creation.cylinder(0.006, 0.06, sections=24)
    boards = {f"board_{k}": trimesh.creation.box((0.3, 0.2, 0.02)) for k in range(3)}
    names, meshes = list(boards) + ["dowel"], list(boards.values()) + [dowel]
    grasps = {n: antipodal_grasps(m, np.random.default_rng(0))[:20] for n, m in zip(names, meshes)}
    asked = []

    def ok_at_target(name, grasp):
        asked.append(name)
        return True

    with pytest.raises(KittingError, match="part 'dowel': at no place in the kitting ring") as caught:
        plan_kitting(names, meshes, grasps, ok_at_target, AREA, lay_out_first=["dowel"] if dowel_first else [])
    assert caught.value.part == "dowel"
    boards_tried = [name for name in asked if name.startswith("board")]
    assert (not boards_tried) if dowel_first else boards_tried


def test_a_part_laid_out_first_takes_the_place_nearest_the_jig():
    """Four crates alike are laid out in order, the first nearest the jig; with the last named in
    ``lay_out_first``, the last takes that place."""
    from planning.grasp import antipodal_grasps

    names = [f"crate_{k}" for k in range(4)]
    meshes = [trimesh.creation.box((0.2, 0.15, 0.06)) for _ in names]
    grasps = {n: antipodal_grasps(m, np.random.default_rng(0))[:20] for n, m in zip(names, meshes)}
    jig = np.array([0.5, 0.0])

    def places(slots):
        return {s.part: s.footprint_world.mean(axis=0) for s in slots}

    in_order = places(plan_kitting(names, meshes, grasps, lambda n, g: True, AREA, prefer_near_xy=jig))
    last_first = places(plan_kitting(names, meshes, grasps, lambda n, g: True, AREA, prefer_near_xy=jig,
                                     lay_out_first=["crate_3"]))
    gaps = {name: np.linalg.norm(xy - jig) for name, xy in in_order.items()}
    assert gaps["crate_0"] == pytest.approx(min(gaps.values())) and gaps["crate_3"] > gaps["crate_0"] + 0.05
    assert np.allclose(last_first["crate_3"], in_order["crate_0"])
    assert not np.allclose(last_first["crate_0"], in_order["crate_0"])


def _plain_pedestal_top(mesh, rest_from_part):
    from planning.kitting_support import rest_half
    from planning.pedestal import pedestal_for
    from planning.pose import Pose

    half, _ = rest_half(mesh, rest_from_part)
    pedestal = pedestal_for(half, Pose([0, 0, 0], [1, 0, 0, 0]), 0.12)
    return pedestal, np.array([[-1, -1], [1, -1], [1, 1], [-1, 1]]) * 0.5 * np.array(pedestal.size_m[:2])


def test_a_round_leg_would_roll_off_a_pedestal_and_is_cradled_by_chocks():
    from planning.pedestal import Pedestal, chocks_for
    from planning.stability import rests_stably

    leg = trimesh.creation.cylinder(radius=0.009, height=0.227, sections=24)
    rest_from_part, _ = stable_rest_poses(leg)[0]
    pedestal, top = _plain_pedestal_top(leg, rest_from_part)
    assert not rests_stably(leg, rest_from_part, top)  # on one 2.4 mm facet it rolls at a 7.5 degree tilt
    chocks = chocks_for(leg, rest_from_part, 0.12, top)
    assert chocks is not None and len(chocks) == 4
    cradle = Pedestal(pedestal.size_m, pedestal.world_from_pedestal, chocks).mesh()
    assert len(cradle.split(only_watertight=False)) == 5  # the pedestal and four separate posts
    # the posts stand beside the leg, clear of it by the chock clearance, and hold it across
    rested = trimesh.Trimesh(leg.vertices @ rest_from_part[:3, :3].T + rest_from_part[:3, 3], leg.faces)
    rested.apply_translation([0, 0, 0.06])  # the rest frame's origin sits 6 cm above the pedestal's centre
    gaps = [trimesh.proximity.signed_distance(rested, trimesh.creation.box(size, transform=pose.matrix()).vertices)
            for size, pose in chocks]
    for gap in gaps:
        assert np.all(gap < 0)  # no post corner inside the leg
        assert -np.max(gap) < 0.003  # the nearest corner of each post is within a few mm of the leg
    across = np.argmin(np.ptp(rested.vertices[:, :2], axis=0))
    sides = {np.sign(pose.position[across]) for _, pose in chocks}
    assert sides == {-1.0, 1.0}


def _bent_bar(radius_m: float = 0.4, half_angle_rad: float = np.radians(20.0), half_width_m: float = 0.006,
              rings: int = 25, sides: int = 4) -> trimesh.Trimesh:
    """A bar bent along an arc in the x-y plane (28 cm long, bowed 2.4 cm) of square section 12 mm wide, or with
    more ``sides`` a round one 12 mm across."""
    vertices = []
    radius = half_width_m * (np.sqrt(2.0) if sides == 4 else 1.0)
    for angle in np.linspace(-half_angle_rad, half_angle_rad, rings):
        centre = np.array([radius_m * np.sin(angle), radius_m * (np.cos(angle) - 1.0), 0.0])
        outwards = np.array([np.sin(angle), np.cos(angle), 0.0])
        for k in range(sides):  # from below and inside the arc, as (-1, -1), (1, -1), (1, 1), (-1, 1) for a square
            phi = np.pi * (1.25 + 2.0 * k / sides)
            vertices.append(centre + radius * (np.cos(phi) * outwards + np.sin(phi) * np.array([0.0, 0.0, 1.0])))
    n = sides
    faces = [[n * i + k, n * i + (k + 1) % n, n * (i + 1) + (k + 1) % n] for i in range(rings - 1) for k in range(n)]
    faces += [[n * i + k, n * (i + 1) + (k + 1) % n, n * (i + 1) + k] for i in range(rings - 1) for k in range(n)]
    last = n * (rings - 1)
    faces += [[0, k + 1, k] for k in range(1, n - 1)] + [[last, last + k, last + k + 1] for k in range(1, n - 1)]
    bar = trimesh.Trimesh(np.array(vertices), faces)
    trimesh.repair.fix_normals(bar)
    return bar


def test_chocks_clear_a_bent_bar_and_its_convex_pieces_all_along_them():
    # a chock is 2 cm long; at the ends of a bent bar the bar runs across it, and the convex pieces the simulation
    # gives the bar bulge beyond its mesh. Chocks set from the bar's section at their middle went 4 mm into it
    # (a real chair's frame of tubes lay 1.3 mm into its chocks from the start, jammed there)
    from planning.convex import convex_pieces
    from planning.pedestal import CHOCK_CLEARANCE_M, cradle_chocks

    bar = _bent_bar()
    assert bar.is_watertight
    rest_from_part, _ = stable_rest_poses(bar)[0]
    chocks = cradle_chocks(bar, rest_from_part, 0.12, inwards=False)
    assert chocks is not None and len(chocks) == 4
    pedestal_from_part = trimesh.transformations.translation_matrix([0.0, 0.0, 0.06]) @ rest_from_part
    shapes = {"mesh": bar.copy().apply_transform(pedestal_from_part)}
    shapes.update({f"piece {i}": piece.copy().apply_transform(pedestal_from_part)
                   for i, piece in enumerate(convex_pieces(bar))})
    for name, shape in shapes.items():
        manager = trimesh.collision.CollisionManager()
        manager.add_object(name, shape)
        for size, pose in chocks:
            post = trimesh.creation.box(size, transform=pose.matrix())
            assert not manager.in_collision_single(post), (name, pose.position)
        gaps = [manager.min_distance_single(trimesh.creation.box(size, transform=pose.matrix()))
                for size, pose in chocks]
        assert min(gaps) > 0.8 * CHOCK_CLEARANCE_M, name
    # and the posts still cradle the bar: each within a few millimetres of it
    manager = trimesh.collision.CollisionManager()
    manager.add_object("mesh", shapes["mesh"])
    for size, pose in chocks:
        assert manager.min_distance_single(trimesh.creation.box(size, transform=pose.matrix())) < 0.003


def test_a_square_beam_rests_without_chocks():
    from planning.stability import rests_stably

    beam = trimesh.creation.box([0.227, 0.018, 0.018])
    rest_from_part, _ = stable_rest_poses(beam)[0]
    _, top = _plain_pedestal_top(beam, rest_from_part)
    assert rests_stably(beam, rest_from_part, top)


def test_closing_fingertips_are_checked_against_the_pedestal():
    """A top-down grasp whose fingertips reach 2 mm below a bar: the open hand clears a pedestal as wide as the
    bar, the closed fingers would press on it. The check at the pick rejects it there and keeps it on a narrower
    pedestal."""
    # a 0.2 x 0.02 x 0.02 m bar (only its pose matters: the grasp is given)
    world_from_bar = Pose(np.array([0.5, 0.0, 0.13]), np.array([1.0, 0.0, 0.0, 0.0]))  # lying on z = 0.12
    # approach straight down (TCP z = world -z), fingers closing along y; TCP 9 mm below the bar's centre: the
    # fingertips (7.2 mm beyond the TCP) reach 6.2 mm below the bar's bottom face
    down = Pose.from_rotation(np.array([[-1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, -1.0]]), np.array([0.0, 0.0,
                                                                                                         -0.009]))
    grasp = Grasp(down, width_m=0.02, opening_m=0.03, score=1.0, centroid_score=1.0, contact_score=1.0)

    def pedestal(width_y):
        box = trimesh.creation.box(extents=(0.1, width_y, 0.12))
        return [(box, Pose(np.array([0.5, 0.0, 0.06]), np.array([1.0, 0.0, 0.0, 0.0])))]

    assert clear_at_pick([grasp], world_from_bar, pedestal(0.02), 0.0, HAND) == []
    open_only = feasible_grasps([grasp], world_from_bar, pedestal(0.02), None, floor_z=0.0, gripper=HAND)
    assert len(open_only) == 1  # the opened hand alone does not show it
    assert len(clear_at_pick([grasp], world_from_bar, pedestal(0.008), 0.0, HAND)) == 1


def test_the_approach_to_the_pick_clears_the_support():
    """The arm's motion does not check the hand against the part's own support: the check at the pick covers the
    whole straight approach. A plate 4 cm above the hand of a top-down grasp, clear of it at the grasp, is met on
    the way down; the check at the pose alone keeps the grasp."""
    world_from_bar = Pose(np.array([0.5, 0.0, 0.13]), np.array([1.0, 0.0, 0.0, 0.0]))
    down = Pose.from_rotation(np.array([[-1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, -1.0]]), np.array([0.0, 0.0,
                                                                                                         0.005]))
    grasp = Grasp(down, width_m=0.02, opening_m=0.03, score=1.0, centroid_score=1.0, contact_score=1.0)
    hand_top_z = HAND.vertices(world_from_bar @ grasp.part_from_tcp, grasp.opening_m)[:, 2].max()
    plate = [(trimesh.creation.box(extents=(0.3, 0.3, 0.005)),
              Pose(np.array([0.5, 0.0, hand_top_z + 0.04 + 0.0025]), np.array([1.0, 0.0, 0.0, 0.0])))]
    assert len(clear_at_pick([grasp], world_from_bar, plate, 0.0, HAND)) == 1
    assert clear_at_pick([grasp], world_from_bar, plate, 0.0, HAND, approach_m=APPROACH_M) == []


def test_a_grasp_keeps_more_clearance_from_other_slots_than_from_its_own_pedestal():
    """A block as tall as a bar's underside beside the fingers of the bar's top-down grasp, its face ``offset``
    from the TCP across the fingers: as the bar's own support the hand must clear it by HAND_CLEARANCE_M, as
    another slot's body by NEIGHBOUR_CLEARANCE_M (the arm's approach keeps the transit clearance from those, and
    the simulator's hand is larger than the model), so it may stand that much closer as a support."""
    world_from_bar = Pose(np.array([0.5, 0.0, 0.13]), np.array([1.0, 0.0, 0.0, 0.0]))  # a bar lying on z = 0.12
    down = Pose.from_rotation(np.array([[-1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, -1.0]]), np.zeros(3))
    grasp = Grasp(down, width_m=0.02, opening_m=0.03, score=1.0, centroid_score=1.0, contact_score=1.0)

    def block(offset):
        return [(trimesh.creation.box(extents=(0.04, 0.04, 0.135)),
                 Pose(np.array([0.5 + offset + 0.02, 0.0, 0.0675]), np.array([1.0, 0.0, 0.0, 0.0])))]

    def closest(clear):  # the smallest offset (to 0.1 mm) at which the grasp is clear
        low, high = 0.0, 0.05
        while high - low > 1e-4:
            middle = 0.5 * (low + high)
            low, high = (low, middle) if clear(middle) else (middle, high)
        return high

    as_support = closest(lambda offset: bool(pickable([grasp], world_from_bar, block(offset), 0.0)))
    as_neighbour = closest(lambda offset: bool(pickable([grasp], world_from_bar, [], 0.0, block(offset))))
    assert 0.005 < as_support < 0.03  # the fingers' half depth and the clearance
    # the hand models are grown about each piece's centre, by about the clearance
    assert as_neighbour - as_support == pytest.approx(NEIGHBOUR_CLEARANCE_M - HAND_CLEARANCE_M, abs=4e-4)


class _ArmSweepsTheRight:
    """A robot whose arm, placing any part at its target, sweeps the ring's right-hand side (y < -0.3): whatever
    lies there in the kitting area then (other parts, pedestals, the part's own support) is hit."""

    def __init__(self):
        self.calls = 0

    @staticmethod
    def _behind(bodies):
        return any(pose.apply(mesh.vertices)[:, 1].min() < -0.3 for mesh, pose in bodies)

    def at_pick(self, part, grasp, world_from_part, obstacles, support=()):
        self.calls += 1
        return None if self._behind(list(obstacles) + list(support)) else (part,)

    def still_clear(self, reach, obstacles):
        return not self._behind(obstacles)


def test_the_arm_at_the_target_is_checked_against_the_parts_own_support():
    assembly = read_assembly(sample_folder("chair"))
    checker = GraspChecker(assembly)
    reach = _ArmSweepsTheRight()
    slots = plan_kitting(assembly.part_names, [p.mesh for p in assembly.parts], checker.candidates,
                         lambda name, grasp: True, AREA, reach=reach)
    assert reach.calls >= len(slots)
    for slot in slots:  # pedestals included: the part's own is still there when the arm places the part
        if slot.pedestal is not None:
            assert slot.pedestal.world_from_pedestal.apply(slot.pedestal.mesh().vertices)[:, 1].min() >= -0.3
        mesh = assembly.part(slot.part).mesh
        assert slot.world_from_part.apply(mesh.vertices)[:, 1].min() >= -0.3


def test_nothing_is_stacked_on_a_board_standing_on_its_edge():
    """A board kitted standing (as it sits in its assembly) has a flat top only 14 mm wide: a board laid on it
    would fall as soon as anything nudges it. Lying on its face, its top takes a board."""
    from planning.kitting import _flat_top

    board = trimesh.creation.box([0.4, 0.3, 0.014])
    lying = Pose([0.4, 0.0, 0.127], [1.0, 0.0, 0.0, 0.0])
    standing = Pose([0.4, 0.0, 0.27], [np.cos(np.pi / 4), np.sin(np.pi / 4), 0.0, 0.0])  # on its 0.4 m edge
    top = _flat_top(board, lying)
    assert top is not None and abs(top[0] - 0.134) < 1e-9 and np.allclose(sorted(2 * top[3]), [0.3, 0.4])
    assert _flat_top(board, standing) is None


class _ArmPlacingOnePartSweepsTheRight(_ArmSweepsTheRight):
    """A robot whose arm sweeps the ring's right-hand side (y < -0.3) only when it places ``part`` at its target."""

    def __init__(self, part: str):
        super().__init__()
        self.part = part

    def at_pick(self, part, grasp, world_from_part, obstacles, support=()):
        return super().at_pick(part, grasp, world_from_part, obstacles, support) if part == self.part else (part,)

    def still_clear(self, reach, obstacles):
        return reach != (self.part,) or super().still_clear(reach, obstacles)


def test_a_part_whose_arm_sweeps_the_places_larger_parts_took_is_laid_out_first():
    """Three boards take the places nearest the jig first, one on the right; the arm placing the small block
    sweeps the right, so no place works for the block. Laid out again with the block first, the boards keep clear
    of its arm and every part finds a place."""
    from planning.grasp import antipodal_grasps

    boards = {f"board_{k}": trimesh.creation.box((0.3, 0.2, 0.02)) for k in range(3)}
    names = ["block"] + list(boards)
    meshes = [trimesh.creation.box((0.06, 0.04, 0.04))] + list(boards.values())
    grasps = {n: antipodal_grasps(m, np.random.default_rng(0))[:20] for n, m in zip(names, meshes)}
    plain = plan_kitting(names, meshes, grasps, lambda name, grasp: True, AREA)
    assert any(slot.footprint_world[:, 1].min() < -0.3 for slot in plain if slot.part != "block")
    reach = _ArmPlacingOnePartSweepsTheRight("block")
    slots = plan_kitting(names, meshes, grasps, lambda name, grasp: True, AREA, reach=reach)
    assert [s.part for s in slots] == names
    for slot in slots:
        assert slot.world_from_part.apply(meshes[names.index(slot.part)].vertices)[:, 1].min() >= -0.3
        if slot.pedestal is not None:
            assert slot.pedestal.world_from_pedestal.apply(slot.pedestal.mesh().vertices)[:, 1].min() >= -0.3



def test_an_asymmetric_board_is_also_tried_turned_half_a_turn_on_each_place():
    """Each place in the ring is offered with the board as laid and turned half a turn on the same footprint
    (another edge faces the arm: chair_ivar_0668's side is held at its target by an edge that faced away from the
    arm in every place); a board that looks the same turned is offered once."""
    from planning.kitting import _Layout

    tab = trimesh.util.concatenate([trimesh.creation.box((0.30, 0.16, 0.02)), trimesh.creation.box(
        (0.08, 0.04, 0.02), transform=trimesh.transformations.translation_matrix((0.08, 0.10, 0.0)))])
    plain = trimesh.creation.box((0.30, 0.16, 0.02))
    layout = _Layout(["tab", "plain"], {"tab": tab, "plain": plain}, AREA, np.array([0.5, 0.0]), Reach())
    for name, mesh, turns in (("tab", tab, 2), ("plain", plain, 1)):
        rest_from_part = stable_rest_poses(mesh)[0][0]
        places = list(layout._ground_places(name, rest_from_part))
        assert len(places) % turns == 0 and len(places) >= 10 * turns
        for k in range(0, 10 * turns, turns):  # consecutive offers share the place, headings opposite
            group = places[k:k + turns]
            assert all(np.allclose(p[0].position, group[0][0].position) for p in group)
            assert all(np.allclose(p[1], group[0][1]) for p in group)  # the same footprint
            if turns == 2:
                np.testing.assert_allclose(group[1][0].rotation[:, 0], -group[0][0].rotation[:, 0], atol=1e-9)
                np.testing.assert_allclose(group[1][2].world_from_pedestal.position,
                                           group[0][2].world_from_pedestal.position, atol=1e-9)


def test_a_board_standing_between_chocks_is_picked_with_the_hand_opened_for_its_lean():
    """A drawer side kitted standing on its 11 mm edge, as it sits in its drawer, between chocks: its grasp opens
    wider at the pick by the lean kitting allows on each side (:func:`standing_lean_m`), so that a finger coming
    down beside its top clears it leaning onto either chock, and as usual at its target; a block 4 cm thick stands
    without chocks and gets the usual opening at both."""
    from planning.grasp import GRASP_CLEARANCE_M, antipodal_grasps
    from planning.pedestal import standing_lean_m
    from planning.stability import upright_rest_pose

    board = trimesh.creation.box((0.18, 0.011, 0.128))
    grasps = antipodal_grasps(board, np.random.default_rng(0))
    standing = plan_kitting(["side"], [board], {"side": grasps}, lambda name, grasp: True, AREA,
                            target_rotations={"side": np.eye(3)})[0]
    assert standing.pedestal.chocks and standing.world_from_part.rotation[2, 2] > 0.999
    lean = standing_lean_m(board, upright_rest_pose(board, np.eye(3)), standing.pedestal, AREA.pedestal_height_m)
    assert lean > 0.005
    usual = standing.grasp.width_m + GRASP_CLEARANCE_M
    assert standing.grasp.opening_m == pytest.approx(usual)
    assert standing.grasp.opening_at_pick_m == pytest.approx(usual + 2 * lean)
    block = trimesh.creation.box((0.18, 0.04, 0.128))
    firm = plan_kitting(["block"], [block], {"block": antipodal_grasps(block, np.random.default_rng(0))},
                        lambda name, grasp: True, AREA, target_rotations={"block": np.eye(3)})[0]
    assert not firm.pedestal.chocks and firm.world_from_part.rotation[2, 2] > 0.999
    assert firm.grasp.opening_m == firm.grasp.opening_at_pick_m == pytest.approx(firm.grasp.width_m + GRASP_CLEARANCE_M)


def test_a_part_standing_on_a_narrow_foot_is_not_picked_by_a_hand_coming_on_a_slant():
    """A slat standing on its end (24 cm tall on a 25 x 7 mm foot) tips over its foot when fingers coming 30 degrees
    off vertical close across its thickness (chair_5's back slat, carried 4.9 degrees off): that grasp is refused,
    the same grasp from straight above is not, and neither is a slanted one on a board standing on its long edge
    (its foot reaches far along the direction it could tip in)."""
    slat = trimesh.creation.box((0.24, 0.025, 0.0074))  # long x, wide y, thin z
    standing = Pose([0.5, 0.3, 0.24], Rotation.from_euler("y", -90, degrees=True).as_quat(scalar_first=True))
    assert np.allclose(standing.rotation @ [1.0, 0.0, 0.0], [0.0, 0.0, 1.0], atol=1e-9)  # on its end
    tips = tips_under(slat, standing)

    def grasp_with(approach_world: np.ndarray) -> Grasp:
        closing = standing.rotation @ [0.0, 0.0, 1.0]  # across the thickness
        approach = approach_world / np.linalg.norm(approach_world)
        world_tcp = np.column_stack([np.cross(closing, approach), closing, approach])
        part_tcp = standing.rotation.T @ world_tcp
        return Grasp(Pose([0.0, 0.0, 0.05], Rotation.from_matrix(part_tcp).as_quat(scalar_first=True)),
                     width_m=0.0074, opening_m=0.0174, score=1.0, centroid_score=1.0, contact_score=1.0)

    width_axis = standing.rotation @ [0.0, 1.0, 0.0]
    assert tips(grasp_with(np.array([0.0, 0.0, -1.0]) + np.tan(np.radians(30.0)) * width_axis))
    assert not tips(grasp_with(np.array([0.0, 0.0, -1.0])))
    on_edge = Pose([0.5, 0.3, 0.0125], Rotation.from_euler("x", 90, degrees=True).as_quat(scalar_first=True))
    length_axis = on_edge.rotation @ [1.0, 0.0, 0.0]
    closing = on_edge.rotation @ [0.0, 0.0, 1.0]
    approach = np.array([0.0, 0.0, -1.0]) + np.tan(np.radians(30.0)) * length_axis
    approach /= np.linalg.norm(approach)
    world_tcp = np.column_stack([np.cross(closing, approach), closing, approach])
    lying = Grasp(Pose([0.0, 0.0, 0.0], Rotation.from_matrix(on_edge.rotation.T @ world_tcp).as_quat(
        scalar_first=True)), width_m=0.0074, opening_m=0.0174, score=1.0, centroid_score=1.0, contact_score=1.0)
    assert not tips_under(slat, on_edge)(lying)


def test_a_bent_bar_lies_on_posts_that_leave_its_sides_free():
    """A round rod bent along its length (28 cm, bowed 2.4 cm, 17 mm across, a chair's curved rail) lying flat:
    the one box under its 41 mm wide footprint stands out beside the rod nearly all along it, so the fingers of few
    grasps from above clear it. Where none of those works at the target, the rod lies on posts under its ends and
    its middle instead, each under the rod, rests there (physics), and is picked by a grasp that the box kept
    out."""
    from cell.resting import PhysicsRestCheck
    from planning.grasp import antipodal_grasps
    from planning.kitting_support import rest_half
    from planning.pedestal import pedestal_for, posts_under, top_boxes
    from planning.pick_clearance import grasp_key
    from planning.stability import upright_rest_pose

    bar, height = _bent_bar(half_width_m=0.0085, sides=16), AREA.pedestal_height_m
    flat = upright_rest_pose(bar, np.eye(3))
    posts = posts_under(bar, flat, height)
    assert posts is not None and len(posts.posts) == 2
    rested = bar.vertices @ flat[:3, :3].T + flat[:3, 3]
    for lo, hi in top_boxes(posts):  # each post's top lies within the bar's cross-section above it
        above = rested[(rested[:, 0] > lo[0] - 0.01) & (rested[:, 0] < hi[0] + 0.01), 1]
        assert above.min() <= lo[1] and hi[1] <= above.max()
    box = pedestal_for(rest_half(bar, flat)[0], Pose([0, 0, 0], [1, 0, 0, 0]), height)
    grasps = [g for g in antipodal_grasps(bar, np.random.default_rng(0)) if g.part_from_tcp.rotation[2, 2] < -0.9]
    floor = (trimesh.creation.box((4.0, 4.0, 0.02)), Pose([0, 0, -height - 0.01], [1, 0, 0, 0]))
    clear = {name: {grasp_key(g) for g in clear_at_pick(grasps, Pose.from_matrix(flat), [
        (support.mesh(), support.world_from_pedestal), floor], -height, HAND, approach_m=APPROACH_M)}
        for name, support in (("box", box), ("posts", posts))}
    assert len(clear["posts"]) >= 3 * max(len(clear["box"]), 1)
    table = (trimesh.creation.box((4.0, 4.0, 0.02)), Pose([0, 0, -0.01], [1, 0, 0, 0]))
    with PhysicsRestCheck() as check:
        slot = plan_kitting(["bar"], [bar], {"bar": grasps}, lambda name, g: grasp_key(g) not in clear["box"],
                            AREA, rests=check, settles=check.settle, target_rotations={"bar": np.eye(3)})[0]
        assert slot.pedestal.posts and slot.world_from_part.rotation[2, 2] > 0.999  # flat, on posts
        assert check([(bar, slot.world_from_part)], [(slot.pedestal.mesh(), slot.pedestal.world_from_pedestal),
                                                     table])
        assert grasp_key(slot.grasp) not in clear["box"]
        # the chocks that cradled it on the box cradle it on the posts: beside it, within 3 mm, at most touching it
        # (it settled against them)
        assert slot.pedestal.chocks
        manager = trimesh.collision.CollisionManager()
        manager.add_object("bar", bar, transform=slot.world_from_part.matrix())
        for size, pose in slot.pedestal.chocks:
            chock = trimesh.creation.box(size, transform=(slot.pedestal.world_from_pedestal @ pose).matrix())
            touching, contacts = manager.in_collision_single(chock, return_data=True)
            assert max((c.depth for c in contacts), default=0.0) < 0.0005
            assert touching or manager.min_distance_single(chock) < 0.003


def test_posts_are_only_for_narrow_elongated_parts_and_where_they_touch():
    from planning.pedestal import posts_under, top_boxes
    from planning.stability import upright_rest_pose

    board = trimesh.creation.box((0.3, 0.2, 0.016))  # wide: its box pedestal serves
    assert posts_under(board, upright_rest_pose(board, np.eye(3)), 0.12) is None
    stub = trimesh.creation.box((0.05, 0.03, 0.03))  # not elongated
    assert posts_under(stub, upright_rest_pose(stub, np.eye(3)), 0.12) is None
    dowel = trimesh.creation.box((0.05, 0.008, 0.008))  # too short for two posts
    assert posts_under(dowel, upright_rest_pose(dowel, np.eye(3)), 0.12) is None
    for rise, rises in ((0.002, True), (0.008, False)):  # held above the pedestal's top (settled on its chocks)
        raised = upright_rest_pose(_bent_bar(), np.eye(3))
        raised[2, 3] += rise
        posts = posts_under(_bent_bar(), raised, 0.12)
        if rises:  # the posts rise to it
            assert posts is not None and posts.size_m[2] == pytest.approx(0.12 + rise)
        else:
            assert posts is None
    # a bar bent in its upright plane: as an arch it comes down at its ends only, and stands on two posts near them
    # that rise to it; as a rocker, it comes down near its middle only
    for turn, arch in ((np.pi / 2, True), (-np.pi / 2, False)):
        bar = _bent_bar(half_width_m=0.0085, sides=16)
        bar.apply_transform(trimesh.transformations.rotation_matrix(turn, [1.0, 0.0, 0.0]))
        posts = posts_under(bar, upright_rest_pose(bar, np.eye(3)), 0.12)
        assert posts is not None
        centres = [lo[0] + 0.01 for lo, _ in top_boxes(posts)]
        if arch:
            assert len(centres) == 2 and min(centres) < -0.11 and max(centres) > 0.11
            assert posts.size_m[2] > 0.12 + 0.001  # rising to the arch's underside, which leaves the floor at its ends
        else:
            assert max(np.abs(centres)) < 0.03
        assert min(np.diff(sorted(centres))) >= 0.02  # none overlaps another
