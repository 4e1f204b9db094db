"""The physics check of resting parts (cell.resting) and its use by the kitting layout."""

import dataclasses
import tempfile
import warnings
from pathlib import Path

import numpy as np
import pybullet as pb
import pytest
import trimesh

from cell.bodies import add_convex_body
from cell.bullet import BulletClient
from cell.resting import PhysicsRestCheck
from cell.simulate import SimSettings, configure_physics
from planning.kitting_support import rest_half
from planning.payload import mass_properties
from planning.pedestal import chocks_for, pedestal_for
from planning.pose import Pose
from planning.stability import rests_stably, upright_rest_pose

PEDESTAL_HEIGHT_M = 0.12
IDENTITY = Pose([0.0, 0.0, 0.0], [1.0, 0.0, 0.0, 0.0])


def _frame(height_m: float) -> trimesh.Trimesh:
    """A flat frame in the x-z plane, 1 cm thick: two posts (3 cm along x) 20 cm apart and a bar across their tops."""
    posts = [trimesh.creation.box((0.03, 0.01, height_m), transform=trimesh.transformations.translation_matrix(
        (x, 0.0, height_m / 2))) for x in (-0.1, 0.1)]
    bar = trimesh.creation.box((0.21, 0.01, 0.01), transform=trimesh.transformations.translation_matrix(
        (0.0, 0.0, height_m - 0.005)))
    return trimesh.util.concatenate(posts + [bar])


def _on_pedestal(mesh: trimesh.Trimesh):
    """The part standing as modelled (upright), its pedestal as kitting makes it (with chocks where it would
    roll), and what the geometric checks say: (loose, fixed, rests geometrically, chocks)."""
    rest = upright_rest_pose(mesh, np.eye(3))
    pedestal = pedestal_for(rest_half(mesh, rest)[0], IDENTITY, PEDESTAL_HEIGHT_M)
    top = np.array([[-1, -1], [1, -1], [1, 1], [-1, 1]]) * 0.5 * np.array(pedestal.size_m[:2])
    stable = rests_stably(mesh, rest, top)
    chocks = () if stable else chocks_for(mesh, rest, PEDESTAL_HEIGHT_M, top)
    pedestal = dataclasses.replace(pedestal, chocks=chocks or ())
    table = (trimesh.creation.box((2.0, 2.0, 0.02)), Pose([0.0, 0.0, -PEDESTAL_HEIGHT_M - 0.01], [1, 0, 0, 0]))
    return [(mesh, Pose.from_matrix(rest))], [(pedestal.mesh(), pedestal.world_from_pedestal), table], stable, chocks


def test_a_flat_piece_is_made_a_body_without_warnings():
    # a part whose mesh holds a flat patch (a label): its convex piece has no volume, and trimesh warned ("divide by
    # zero") in the middle of a run's output as it oriented that hull's faces, for the simulator and the planner
    from cell.bodies import inset
    from planning.collision import ConvexPart, shrunk
    from planning.convex import convex_hull

    label = np.array([[0.0, 0.0, 0.0], [0.05, 0.0, 0.0], [0.05, 0.05, 0.0], [0.0, 0.05, 0.0]])
    patch = trimesh.Trimesh(label, [[0, 1, 2], [0, 2, 3]], process=False)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        hull = convex_hull(label)
        assert inset(patch, 0.00025).vertices.shape == hull.vertices.shape  # too thin to inset: kept as it is
        assert len(shrunk(ConvexPart.from_mesh("label", patch), -0.003).piece_vertices) == 1
    assert hull.volume == 0.0 and np.allclose(hull.bounds, [[0.0, 0.0, 0.0], [0.05, 0.05, 0.0]])


def test_a_box_rests_on_its_pedestal_and_the_answer_is_remembered():
    loose, fixed, stable, _ = _on_pedestal(trimesh.creation.box((0.2, 0.1, 0.03)))
    assert stable
    with PhysicsRestCheck() as check:
        assert check(loose, fixed)
        assert check(loose, fixed)
        assert check.checks == 1  # the same bodies at the same poses: simulated once


@pytest.mark.parametrize("gap_m, rests", [(-0.001, False), (0.001, True)])
def test_a_bar_jammed_between_two_posts_does_not_count_as_resting(gap_m, rests):
    # a 20 cm bar lying on a slab between two posts: 1 mm narrower than the bar, the posts squeeze it, it stays put
    # but pressed with many times its weight (it would not come out when lifted); 1 mm wider, it rests
    bar = trimesh.creation.box((0.2, 0.02, 0.02))
    slab = (trimesh.creation.box((0.4, 0.2, 0.02)), Pose([0.0, 0.0, -0.01], [1, 0, 0, 0]))
    posts = [(trimesh.creation.box((0.03, 0.01, 0.03)), Pose([x, side * (0.015 + gap_m / 2), 0.015], [1, 0, 0, 0]))
             for x in (-0.08, 0.08) for side in (-1.0, 1.0)]
    loose = [(bar, Pose([0.0, 0.0, 0.01], [1, 0, 0, 0]))]
    with PhysicsRestCheck() as check:
        assert check(loose, [slab] + posts) is rests
        assert check(loose, [slab] + posts, allow_wedged=True)  # it does stay put (from the same simulation)
        assert check(loose, [slab]) is True  # without the posts it rests either way
        assert check.checks == 2


def test_a_tall_frame_between_chocks_falls_over():
    # the geometry says chocks hold it (a chair's side frame of tubes standing on two feet); physics says no
    loose, fixed, stable, chocks = _on_pedestal(_frame(0.25))
    assert not stable and chocks
    with PhysicsRestCheck() as check:
        assert not check(loose, fixed)


def test_a_frame_whose_feet_miss_the_pedestal_does_not_rest():
    # the pedestal is inset from the footprint's ends for the fingers; the feet lie beyond it and only touch its
    # edge, which the geometric check counts as support
    loose, fixed, stable, _ = _on_pedestal(_frame(0.03))
    assert stable
    with PhysicsRestCheck() as check:
        assert not check(loose, fixed)


def test_a_stacked_board_rests_when_centred_and_slides_off_when_overhanging():
    lower, upper = trimesh.creation.box((0.3, 0.2, 0.018)), trimesh.creation.box((0.25, 0.15, 0.018))
    pedestal = (trimesh.creation.box((0.24, 0.14, PEDESTAL_HEIGHT_M)),
                Pose([0.0, 0.0, -PEDESTAL_HEIGHT_M / 2], [1.0, 0.0, 0.0, 0.0]))
    on_pedestal = (lower, Pose([0.0, 0.0, 0.009], [1.0, 0.0, 0.0, 0.0]))
    with PhysicsRestCheck() as check:
        assert check([(upper, Pose([0.0, 0.0, 0.027], [1, 0, 0, 0])), on_pedestal], [pedestal])
        # its centre 2 cm beyond the lower board's edge: it tips off
        assert not check([(upper, Pose([0.17, 0.0, 0.027], [1, 0, 0, 0])), on_pedestal], [pedestal])


def test_kitting_never_stands_a_frame_where_physics_says_it_falls():
    from planning.grasp import antipodal_grasps
    from planning.kitting import plan_kitting
    from planning.kitting_area import KittingArea

    frame = _frame(0.25)
    area = KittingArea(centre_xy=(0.0, 0.0), inner_radius_m=0.32, outer_radius_m=0.72, table_min_xy=(-0.55, -0.8),
                       table_max_xy=(0.95, 0.8), table_z_m=0.0, pedestal_height_m=PEDESTAL_HEIGHT_M,
                       keep_out=(((0.25, -0.25), (0.75, 0.25)),), gap_m=0.06)
    # grasps approaching along the frame's -z (from above where it stands upright): kitting tries the upright pose
    # first, where they all pick from above
    grasps = [g for g in antipodal_grasps(frame, np.random.default_rng(0)) if g.part_from_tcp.rotation[2, 2] < -0.9]
    assert grasps

    def from_above_at_target(name, grasp):  # the target takes grasps approaching straight down (the part upright)
        return grasp.part_from_tcp.rotation[2, 2] < -0.9

    kwargs = dict(target_rotations={"frame": np.eye(3)})  # first tried standing as it sits in its assembly
    standing = plan_kitting(["frame"], [frame], {"frame": grasps}, from_above_at_target, area, **kwargs)[0]
    assert standing.world_from_part.rotation[2, 2] > 0.99 and standing.pedestal.chocks  # upright between chocks
    with PhysicsRestCheck() as check:
        slot = plan_kitting(["frame"], [frame], {"frame": grasps}, from_above_at_target, area, rests=check,
                            **kwargs)[0]
        assert slot.world_from_part.rotation[2, 2] < 0.99  # not upright: in another pose where it rests
        table = (trimesh.creation.box((4.0, 4.0, 0.02)), Pose([0, 0, -0.01], [1, 0, 0, 0]))
        assert check([(frame, slot.world_from_part)], [(slot.pedestal.mesh(), slot.pedestal.world_from_pedestal),
                                                       table])


def test_kitting_lays_a_part_wedged_only_where_it_rests_in_no_pose_unwedged():
    # a checker that finds every resting body wedged (its contacts carry its weight: a ratio of 1 > 0.5): kitting
    # still places the frame, allowing it wedged as the last resort; with the usual ratio, in the same place
    from planning.grasp import antipodal_grasps
    from planning.kitting import plan_kitting
    from planning.kitting_area import KittingArea

    frame = _frame(0.25)
    area = KittingArea(centre_xy=(0.0, 0.0), inner_radius_m=0.32, outer_radius_m=0.72, table_min_xy=(-0.55, -0.8),
                       table_max_xy=(0.95, 0.8), table_z_m=0.0, pedestal_height_m=PEDESTAL_HEIGHT_M,
                       keep_out=(((0.25, -0.25), (0.75, 0.25)),), gap_m=0.06)
    grasps = antipodal_grasps(frame, np.random.default_rng(0))
    slots = []
    for ratio in (0.5, 3.0):
        with PhysicsRestCheck(wedged_force_ratio=ratio) as check:
            slots.append(plan_kitting(["frame"], [frame], {"frame": grasps}, lambda name, grasp: True, area,
                                      rests=check, settles=check.settle)[0])
            table = (trimesh.creation.box((4.0, 4.0, 0.02)), Pose([0, 0, -0.01], [1, 0, 0, 0]))
            fixed = [(slots[-1].pedestal.mesh(), slots[-1].pedestal.world_from_pedestal), table]
            assert check([(frame, slots[-1].world_from_part)], fixed) is (ratio > 1.0)
            assert check([(frame, slots[-1].world_from_part)], fixed, allow_wedged=True)
    assert np.allclose(slots[0].world_from_part.matrix(), slots[1].world_from_part.matrix())
    assert slots[0].wedged and not slots[1].wedged  # the slot says so (report.json: kitting_wedged)


def _sway_of_top_mm(mesh: trimesh.Trimesh, chocks, nudge_rad_s: float = 0.2) -> float:
    """A board standing on its edge on a pedestal between ``chocks``, nudged about its long axis (x): how far its
    top edge ends from where it stood, after 1.5 s (millimetres), with the simulation's bodies."""
    settings = SimSettings()
    rest = upright_rest_pose(mesh, np.eye(3))
    pedestal = dataclasses.replace(pedestal_for(rest_half(mesh, rest)[0], IDENTITY, PEDESTAL_HEIGHT_M),
                                   chocks=chocks)
    with BulletClient() as client, tempfile.TemporaryDirectory() as folder:
        cid = client.client_id
        configure_physics(pb, cid, settings)
        add_convex_body(pb, cid, Path(folder), pedestal.mesh(), pedestal.world_from_pedestal,
                        None, settings.friction)
        props = mass_properties(mesh, settings.density_kg_m3)
        world_from_part = Pose.from_matrix(rest)
        body = add_convex_body(pb, cid, Path(folder), mesh, world_from_part, props,
                               settings.friction, inset_m=0.5 * settings.joint_clearance_m)
        pb.resetBaseVelocity(body, [0, 0, 0], [nudge_rad_s, 0, 0], physicsClientId=cid)
        for _ in range(int(1.5 * settings.rate_hz)):
            pb.stepSimulation(physicsClientId=cid)
        position, orientation = pb.getBasePositionAndOrientation(body, physicsClientId=cid)
        now = Pose.from_pybullet(position, orientation) @ props.part_from_com.inverse()
        top = np.array([[0.0, 0.0, mesh.bounds[1][2]]])
        return float(np.linalg.norm(now.apply(top) - world_from_part.apply(top)) * 1000)


def test_a_thin_panel_standing_on_its_edge_gets_chocks_tall_enough_to_keep_it_upright():
    """A 3 mm hardboard panel 25 cm tall standing on its edge (as a cabinet's back stands in its assembly): its
    chocks rise far enough that, nudged, it leans on them by millimetres at the top, where the fingers take it
    (they open 5 mm beyond each face); on 1 cm chocks (those that cradle a round leg) it leaned by centimetres."""
    panel = trimesh.creation.box((0.55, 0.003, 0.254))
    _, _, stable, chocks = _on_pedestal(panel)
    assert not stable and chocks
    rise = max(size[2] for size, _ in chocks) - PEDESTAL_HEIGHT_M
    assert rise >= 0.03
    low = tuple((size[:2] + (PEDESTAL_HEIGHT_M + 0.01,), Pose(pose.position * [1, 1, 0] + [0, 0, 0.005],
                                                            pose.quat_wxyz)) for size, pose in chocks)
    assert _sway_of_top_mm(panel, chocks) < 10.0
    assert _sway_of_top_mm(panel, low) > 20.0


@pytest.mark.parametrize("thickness_m, height_m", [(0.003, 0.254), (0.011, 0.128)])
def test_a_panel_nudged_onto_its_chocks_moves_its_top_no_farther_than_kitting_allows(thickness_m, height_m):
    """Nudged harder and harder, a panel standing between its chocks leans onto them (its foot sliding the other
    way) and its top ends up to about a centimetre from where it stood: within :func:`standing_lean_m`, which
    kitting opens the hand by on each side at its pick, and beyond what the chocks' clearance alone gives
    (the simulated part is inset; cabinet_13's drawer side leaned onto a finger planned with 5 mm to spare)."""
    from planning.pedestal import CHOCK_CLEARANCE_M, standing_lean_m

    panel = trimesh.creation.box((0.3, thickness_m, height_m))
    _, _, _, chocks = _on_pedestal(panel)
    assert chocks
    rise = max(size[2] for size, _ in chocks) - PEDESTAL_HEIGHT_M
    pedestal = dataclasses.replace(pedestal_for((0.15, 0.05), IDENTITY, PEDESTAL_HEIGHT_M), chocks=chocks)
    allowed_mm = 1000 * standing_lean_m(panel, upright_rest_pose(panel, np.eye(3)), pedestal, PEDESTAL_HEIGHT_M)
    sways = [_sway_of_top_mm(panel, chocks, nudge) for nudge in (0.2, 0.5, 1.0, 2.0)]
    assert max(sways) <= allowed_mm
    assert max(sways) > 1000 * CHOCK_CLEARANCE_M * height_m / rise  # leaning on the chocks' clearance alone


def _square_frame(outer_m: float, bar_m: float, thickness_m: float) -> trimesh.Trimesh:
    """A flat square frame of four bars (a seat frame or a picture frame) in the x-y plane, its opening
    ``outer_m - 2 bar_m`` wide."""
    bars = []
    for side in (-1.0, 1.0):
        offset = side * (outer_m - bar_m) / 2
        bars.append(trimesh.creation.box((outer_m, bar_m, thickness_m),
                                         transform=trimesh.transformations.translation_matrix((0.0, offset, 0.0))))
        bars.append(trimesh.creation.box((bar_m, outer_m - 2 * bar_m, thickness_m),
                                         transform=trimesh.transformations.translation_matrix((offset, 0.0, 0.0))))
    return trimesh.util.concatenate(bars)


def test_a_frame_lying_flat_falls_through_its_usual_pedestal_and_settles_on_a_wide_one():
    """A 24 cm square frame of 2 cm bars lying flat: the usual pedestal, inset 3 cm for the fingers, fits its 20 cm
    opening. Its underside stands on nothing there, and physics drops it through to the table. Given the physics'
    settling, kitting lays it flat as it sits in its assembly on a pedestal inset 5 mm, where it rests;
    without it, it stands the frame on an edge."""
    from planning.grasp import antipodal_grasps
    from planning.kitting import plan_kitting
    from planning.kitting_area import KittingArea
    from planning.pedestal import NARROW_INSET_M

    frame = _square_frame(0.24, 0.02, 0.03)
    flat = upright_rest_pose(frame, np.eye(3))
    usual = pedestal_for(rest_half(frame, flat)[0], IDENTITY, PEDESTAL_HEIGHT_M)
    assert max(usual.size_m[:2]) < 0.24 - 2 * 0.02  # it fits the opening
    top = np.array([[-1, -1], [1, -1], [1, 1], [-1, 1]]) * 0.5 * np.array(usual.size_m[:2])
    assert not rests_stably(frame, flat, top)
    area = KittingArea(centre_xy=(0.0, 0.0), inner_radius_m=0.32, outer_radius_m=0.72, table_min_xy=(-0.55, -0.8),
                       table_max_xy=(0.95, 0.8), table_z_m=0.0, pedestal_height_m=PEDESTAL_HEIGHT_M,
                       keep_out=(((0.25, -0.25), (0.75, 0.25)),), gap_m=0.06)
    grasps = [g for g in antipodal_grasps(frame, np.random.default_rng(0)) if g.part_from_tcp.rotation[2, 2] < -0.9]
    assert grasps
    kwargs = dict(target_rotations={"frame": np.eye(3)})
    table = trimesh.creation.box((4.0, 4.0, 0.02))
    with PhysicsRestCheck() as check:  # the pedestal's top at z = 0 (rest frame), the table under it
        fixed = [(usual.mesh(), usual.world_from_pedestal), (table, Pose([0, 0, -PEDESTAL_HEIGHT_M - 0.01],
                                                                         [1, 0, 0, 0]))]
        assert check.settle([(frame, Pose.from_matrix(flat))], fixed)[0].position[2] < -0.1  # on the table
        edge = plan_kitting(["frame"], [frame], {"frame": grasps}, lambda name, grasp: True, area, rests=check,
                            **kwargs)[0]
        assert abs(edge.world_from_part.rotation[2, 2]) < 0.01  # standing on an edge
        slot = plan_kitting(["frame"], [frame], {"frame": grasps}, lambda name, grasp: True, area, rests=check,
                            settles=check.settle, **kwargs)[0]
        assert slot.world_from_part.rotation[2, 2] > 0.999  # flat, as in its assembly
        assert slot.pedestal.size_m[:2] == pytest.approx((0.24 - 2 * NARROW_INSET_M,) * 2)
        pedestal_top = slot.pedestal.world_from_pedestal.position[2] + PEDESTAL_HEIGHT_M / 2
        lowest = slot.world_from_part.apply(frame.vertices)[:, 2].min()
        assert abs(lowest - pedestal_top) < 0.001  # lying on it (the simulated body is inset 0.25 mm)
        assert check([(frame, slot.world_from_part)], [(slot.pedestal.mesh(), slot.pedestal.world_from_pedestal),
                                                       (table, Pose([0, 0, -0.01], [1, 0, 0, 0]))])


def test_a_frame_of_thin_bars_lies_on_a_pedestal_cut_back_from_one_side():
    """A 24 cm square frame of 12 mm bars lying flat settles on the wide pedestal (inset 5 mm), where the fingers
    closing on any bar reach down into the pedestal's top: no grasp clears it. Kitting cuts the pedestal back
    from one side, so that the bar there overhangs it, and the frame rests on what is left; the grasp it picks
    closes on that bar, beyond the pedestal's edge."""
    from planning.grasp import antipodal_grasps
    from planning.kitting import plan_kitting
    from planning.kitting_area import KittingArea
    from planning.pedestal import NARROW_INSET_M
    from planning.pick_clearance import HAND, clear_at_pick

    frame = _square_frame(0.24, 0.012, 0.012)
    flat = upright_rest_pose(frame, np.eye(3))
    wide = pedestal_for(rest_half(frame, flat)[0], IDENTITY, PEDESTAL_HEIGHT_M, wide=True)
    grasps = [g for g in antipodal_grasps(frame, np.random.default_rng(0)) if g.part_from_tcp.rotation[2, 2] < -0.9]
    assert grasps
    floor = (trimesh.creation.box((4.0, 4.0, 0.02)), Pose([0, 0, -PEDESTAL_HEIGHT_M - 0.01], [1, 0, 0, 0]))
    assert not clear_at_pick(grasps, Pose.from_matrix(flat), [(wide.mesh(), wide.world_from_pedestal), floor],
                             -PEDESTAL_HEIGHT_M, HAND)  # every grasp's fingers meet the wide pedestal
    area = KittingArea(centre_xy=(0.0, 0.0), inner_radius_m=0.32, outer_radius_m=0.72, table_min_xy=(-0.55, -0.8),
                       table_max_xy=(0.95, 0.8), table_z_m=0.0, pedestal_height_m=PEDESTAL_HEIGHT_M,
                       keep_out=(((0.25, -0.25), (0.75, 0.25)),), gap_m=0.06)
    table = trimesh.creation.box((4.0, 4.0, 0.02))
    with PhysicsRestCheck() as check:
        slot = plan_kitting(["frame"], [frame], {"frame": grasps}, lambda name, grasp: True, area, rests=check,
                            settles=check.settle, target_rotations={"frame": np.eye(3)})[0]
        assert slot.world_from_part.rotation[2, 2] > 0.999  # flat, as in its assembly
        full = 0.24 - 2 * NARROW_INSET_M
        sizes = sorted(slot.pedestal.size_m[:2])
        assert sizes[1] == pytest.approx(full) and sizes[0] < full - 0.02  # cut back along one axis only
        assert check([(frame, slot.world_from_part)], [(slot.pedestal.mesh(), slot.pedestal.world_from_pedestal),
                                                       (table, Pose([0, 0, -0.01], [1, 0, 0, 0]))])
        tcp = (slot.world_from_part @ slot.grasp.part_from_tcp).position
        pedestal_from_tcp = slot.pedestal.world_from_pedestal.inverse().apply(tcp)
        assert np.any(np.abs(pedestal_from_tcp[:2]) > 0.5 * np.array(slot.pedestal.size_m[:2]))  # beyond its edge
