"""The renderer: masks agree with the projected geometry, camera conventions, determinism."""

import numpy as np
import pytest
import trimesh
from scipy.spatial import ConvexHull, Delaunay

from cell.render import (
    Appearance,
    AssemblyRenderer,
    CameraSpec,
    project_points,
    render_assembly,
    sample_camera,
)
from planning.assembly import Assembly, AssemblyPart
from planning.pose import Pose


def table_like() -> Assembly:
    """A box slab on a smaller block, both convex: each projects to the convex hull of its vertices."""
    slab = trimesh.creation.box([0.3, 0.2, 0.03])
    block = trimesh.creation.box([0.08, 0.08, 0.2])
    return Assembly("slab_on_block", [
        AssemblyPart("block", block, Pose([0, 0, 0.1], [1, 0, 0, 0])),
        AssemblyPart("slab", slab, Pose([0.02, 0, 0.215], [np.cos(0.2), 0, 0, np.sin(0.2)])),
    ])


def pixel_centres(mask: np.ndarray) -> np.ndarray:
    rows, cols = np.nonzero(mask)
    return np.stack([cols + 0.5, rows + 0.5], axis=1)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_masks_agree_with_projected_geometry(seed):
    assembly = table_like()
    rng = np.random.default_rng(seed)
    view = render_assembly(assembly, rng)
    assert view.rgb.shape == (224, 224, 3) and view.rgb.dtype == np.uint8
    masks = view.part_masks()
    for index, part in enumerate(assembly.parts):
        uv = project_points(view.camera_from_part[index].apply(part.mesh.vertices), view.intrinsics)
        hull = Delaunay(uv)
        inside = hull.find_simplex(pixel_centres(masks[index])) >= 0
        # every mask pixel lies in the projected hull, up to anti-aliasing at its border
        assert inside.mean() > 0.97, (part.name, inside.mean())
    # the slab is on top: seen from above nothing hides it, so its mask fills its projected hull
    slab_uv = project_points(view.camera_from_part[1].apply(assembly.parts[1].mesh.vertices), view.intrinsics)
    hull_area = ConvexHull(slab_uv).volume  # in 2-D, "volume" is the area
    assert masks[1].sum() == pytest.approx(hull_area, rel=0.06)
    assert view.visible_pixels.tolist() == masks.sum(axis=(1, 2)).tolist()


def test_camera_conventions():
    camera = CameraSpec(azimuth_deg=0.0, elevation_deg=0.0, distance_m=1.0, target_m=(0.0, 0.0, 0.0))
    camera_from_assembly = camera.camera_from_assembly()
    # camera on +x looking at the origin: optical axis (+z camera) is -x, image down (+y camera) is -z
    np.testing.assert_allclose(camera.eye_m(), [1, 0, 0], atol=1e-12)
    np.testing.assert_allclose(camera_from_assembly.apply([0, 0, 0]), [0, 0, 1], atol=1e-12)
    np.testing.assert_allclose(camera_from_assembly.rotation @ [0, 0, 1], [0, -1, 0], atol=1e-12)
    np.testing.assert_allclose(camera_from_assembly.rotation @ [0, 1, 0], [1, 0, 0], atol=1e-12)
    # the target projects to the image centre
    uv = project_points(camera_from_assembly.apply(np.zeros((1, 3))), camera.intrinsics())
    np.testing.assert_allclose(uv, [[112, 112]])


def test_sampled_cameras_stay_in_range_and_see_everything():
    assembly = table_like()
    rng = np.random.default_rng(7)
    with AssemblyRenderer(assembly) as renderer:
        for _ in range(8):
            camera = sample_camera(rng, assembly.bounds())
            assert 10.0 <= camera.elevation_deg <= 50.0 and 0.0 <= camera.azimuth_deg < 360.0
            view = renderer.render(camera, Appearance.sample(rng, 2))
            labels = view.part_labels
            # the object fits: no part touches the image border
            border = np.concatenate([labels[0], labels[-1], labels[:, 0], labels[:, -1]])
            assert np.all(border == -1)
            assert view.visible_pixels[1] > 500


def test_same_seed_same_image():
    a = render_assembly(table_like(), np.random.default_rng(3))
    b = render_assembly(table_like(), np.random.default_rng(3))
    c = render_assembly(table_like(), np.random.default_rng(4))
    assert np.array_equal(a.rgb, b.rgb) and np.array_equal(a.part_labels, b.part_labels)
    assert not np.array_equal(a.rgb, c.rgb)
