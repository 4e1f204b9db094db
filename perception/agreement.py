"""Does a predicted assembly agree with the picture it came from? Outlines and edges compared in its pixels.

The predicted (repaired) assembly is drawn with the picture's camera (the camera frame the prediction gives every
part: OpenCV, x right, y down, z forward, metres; the pinhole of :func:`picture_intrinsics`) and compared with the
object's silhouette in the picture (what differs from a plain backdrop, or else the segmentation network's
foreground: :func:`object_mask`):

- ``silhouette_iou``: intersection over union of the two silhouettes, after the drawn one is scaled about its
  centre and shifted to fit the object's (:func:`fit_silhouette`): the network's estimate of the object's distance
  is off by 0.1-0.2 m, which changes its size in the picture, not its layout; only the layout is judged;
- ``edge_recall``: the share of the picture's edges inside the object that the drawing explains with an edge of
  its own between parts or between the sides of a part (:func:`edge_recall`): the outline alone does not show
  where a cabinet's shelves are, its edges do;
- per part, ``on_object``: the fraction of its drawn pixels that lie on the object (a leg floating beside the
  chair scores near 0).

Drawing is by hand, with Pillow's polygon fill of every projected triangle, so that no simulator client is needed:
the result is the same on any machine, and the whole check takes about 50 ms for a 20-part object.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import trimesh
from PIL import Image, ImageDraw

from cell.render import FIELD_OF_VIEW_DEG, IMAGE_SIZE
from planning.pose import Pose

FOREGROUND_PROBABILITY = 0.5  # a pixel whose foreground probability is at least this is on the object
MIN_OBJECT_FRACTION = 0.01  # a picture whose object covers less than this fraction of it holds no object
MAX_OBJECT_FRACTION = 0.9  # nor one whose "object" covers almost all of it (a uniform or noisy picture)
SCALE_RANGE = (0.75, 1.33)  # how much the fit may scale the drawn silhouette (the object's distance, +-25-33%)
NEAR_PLANE_M = 0.01  # triangles with a vertex nearer the camera than this are not drawn
MAX_PIXEL_NOISE = 30.0  # a picture whose neighbouring pixels differ more than this (median) is noise, no object
EDGE_CONTRAST = 24  # a colour step over this (RGB, 0-255) between neighbouring pixels is an edge in the picture
SIDE_COMPONENT = 0.38  # a normal's component over this (cos 67.5 degrees) counts in the side it faces
EDGE_TOLERANCE_PX = 2  # an edge drawn this close to one in the picture (and back) agrees with it
BORDER_PX = 3  # the picture's left and right strips this wide show the backdrop
BACKDROP_SPREAD = 6.0  # a plain backdrop's border pixels lie this close (median, RGB 0-255) to their row's colour
BACKDROP_DISTANCE = 24.0  # ... 90% of them within this; and a pixel this close to its row's colour is backdrop


def picture_intrinsics(size_px: int = IMAGE_SIZE, fov_deg: float = FIELD_OF_VIEW_DEG) -> np.ndarray:
    """(3, 3) pinhole matrix in pixels of a square picture of ``size_px`` with vertical field of view ``fov_deg``:
    the camera model the network is trained with (:class:`cell.render.CameraSpec`)."""
    f = 0.5 * size_px / np.tan(np.radians(fov_deg) / 2.0)
    return np.array([[f, 0.0, 0.5 * size_px], [0.0, f, 0.5 * size_px], [0.0, 0.0, 1.0]])


def plain_background(image: np.ndarray) -> np.ndarray | None:
    """(H, W) bool background of a picture taken against a plain backdrop (a studio or product photo, and every
    training render: one colour, possibly graded from top to bottom), or None where the picture's left and right
    borders do not look like one (a cluttered room). The backdrop's colour per row is the mean of its border
    pixels; a pixel within :data:`BACKDROP_DISTANCE` of it (RGB, 0-255) is background."""
    rgb = np.asarray(image, dtype=np.float64)
    border = np.concatenate([rgb[:, :BORDER_PX], rgb[:, -BORDER_PX:]], axis=1)  # (H, 2B, 3)
    row_colour = border.mean(axis=1)  # (H, 3)
    spread = np.linalg.norm(border - row_colour[:, None], axis=2)
    if np.median(spread) > BACKDROP_SPREAD or np.percentile(spread, 90) > BACKDROP_DISTANCE:
        return None
    return np.linalg.norm(rgb - row_colour[:, None], axis=2) <= BACKDROP_DISTANCE


def object_mask(image: np.ndarray, foreground_probability: np.ndarray | None) -> tuple[np.ndarray, str]:
    """(H, W) bool pixels on the object, and where they come from: ``plain background`` (everything that differs
    from a plain backdrop, :func:`plain_background`) or else ``segmentation`` (the network's foreground probability
    of at least :data:`FOREGROUND_PROBABILITY`). The backdrop, where there is one, is the sharper of the two: the
    segmentation blurs thin legs and rails. Without either, an empty mask (``none``)."""
    background = plain_background(image)
    if background is not None:
        return ~background, "plain background"
    if foreground_probability is not None:
        return np.asarray(foreground_probability) >= FOREGROUND_PROBABILITY, "segmentation"
    return np.zeros(np.asarray(image).shape[:2], dtype=bool), "none"


def object_fraction(mask: np.ndarray) -> float:
    return float(np.mean(mask))


def pixel_noise(image: np.ndarray) -> float:
    """The median difference between horizontally neighbouring pixels (RGB, 0-255): a few units for a photo or a
    render, whose neighbouring pixels mostly show the same surface; about 85 for a picture of random pixels."""
    rgb = np.asarray(image, dtype=np.int16)
    return float(np.median(np.abs(np.diff(rgb, axis=1))))


def holds_an_object(mask: np.ndarray) -> bool:
    """Whether the object mask looks like an object in the picture: it covers between
    :data:`MIN_OBJECT_FRACTION` and :data:`MAX_OBJECT_FRACTION` of it."""
    return MIN_OBJECT_FRACTION <= object_fraction(mask) <= MAX_OBJECT_FRACTION


def projected_triangles(mesh: trimesh.Trimesh, camera_from_part: Pose,
                        intrinsics: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The mesh's triangles in front of the camera: (T, 3, 2) pixel coordinates (u, v), (T,) mean depth (metres,
    camera frame) and (T,) the side of the part each faces (:func:`facing_side`)."""
    camera = camera_from_part.apply(np.asarray(mesh.vertices, dtype=np.float64))
    triangles = camera[np.asarray(mesh.faces)]
    in_front = np.all(triangles[:, :, 2] > NEAR_PLANE_M, axis=1)
    triangles = triangles[in_front]
    uvw = triangles @ intrinsics.T
    sides = facing_side(np.asarray(mesh.face_normals)[in_front])
    return uvw[:, :, :2] / uvw[:, :, 2:3], triangles[:, :, 2].mean(axis=1), sides


def facing_side(normals: np.ndarray) -> np.ndarray:
    """(T,) int in 0..26: each (T, 3) unit normal (part frame) snapped to the nearest of the 26 directions of a cube's
    faces, edges and corners. Two faces of a board that meet at an edge face different sides, so the edge between
    them is drawn, as the picture shows it by their shading; the facets of a round leg change side every 45
    degrees or so."""
    snapped = np.where(np.abs(normals) > SIDE_COMPONENT, np.sign(normals), 0.0).astype(np.int64) + 1
    return snapped[:, 0] * 9 + snapped[:, 1] * 3 + snapped[:, 2]


def draw_labels(per_part: Sequence[tuple[np.ndarray, np.ndarray, np.ndarray]], size_px: int, centre_px: np.ndarray,
                scale: float, shift_px: np.ndarray) -> np.ndarray:
    """(size, size) int32: 0 background, else ``27 k + side + 1`` where side ``side`` of part k is the nearest
    surface (:func:`projected_triangles`), by drawing every triangle far to near (the painter's order by mean depth:
    exact for the separate boxes and boards furniture is made of, close enough elsewhere for an edge check),
    placed as :func:`draw_silhouette` places them."""
    image = Image.new("I", (size_px, size_px), 0)
    draw = ImageDraw.Draw(image)
    triangles = [(depth, 27 * k + side + 1, triangle) for k, (tris, depths, sides) in enumerate(per_part)
                 for triangle, depth, side in zip(tris, depths, sides)]
    for _, label, triangle in sorted(triangles, key=lambda item: -item[0]):
        points = centre_px + scale * (triangle - centre_px) + shift_px
        draw.polygon([tuple(p) for p in points], fill=int(label), outline=int(label))
    return np.asarray(image)


def picture_edges(image: np.ndarray) -> np.ndarray:
    """(H, W) bool: where the picture's colour changes sharply (the largest RGB difference to the right or below
    neighbour over :data:`EDGE_CONTRAST`, 0-255)."""
    rgb = np.asarray(image, dtype=np.int16)
    right = np.abs(np.diff(rgb, axis=1)).max(axis=2)
    down = np.abs(np.diff(rgb, axis=0)).max(axis=2)
    edges = np.zeros(rgb.shape[:2], dtype=bool)
    edges[:, :-1] |= right > EDGE_CONTRAST
    edges[:-1, :] |= down > EDGE_CONTRAST
    return edges


def label_edges(labels: np.ndarray) -> np.ndarray:
    """(H, W) bool: pixels whose right or lower neighbour shows another part or another side of the same part, inside
    the drawn object (not its outline, which the silhouette IoU judges)."""
    edges = np.zeros(labels.shape, dtype=bool)
    right = (labels[:, :-1] != labels[:, 1:]) & (labels[:, :-1] > 0) & (labels[:, 1:] > 0)
    down = (labels[:-1, :] != labels[1:, :]) & (labels[:-1, :] > 0) & (labels[1:, :] > 0)
    edges[:, :-1] |= right
    edges[:-1, :] |= down
    return edges


def edge_recall(predicted_edges: np.ndarray, image_edges: np.ndarray, object_px: np.ndarray) -> float:
    """The share of the picture's edges inside the object (colour steps, :func:`picture_edges`) that lie within
    :data:`EDGE_TOLERANCE_PX` of an edge the prediction draws there (between parts, or between the sides of a part,
    :func:`label_edges`): near 1 for the true assembly, whose drawing explains every edge the picture shows, and low
    where the parts inside the outline sit elsewhere than the picture shows them (a cabinet's shelf at the wrong
    height). The converse share is not used: the picture hides many drawn edges (two sides in the same light)."""
    from scipy.ndimage import binary_dilation, binary_erosion

    inside = binary_erosion(object_px, iterations=EDGE_TOLERANCE_PX + 1)
    seen = image_edges & inside
    if not seen.any():
        return 1.0
    near_drawn = binary_dilation(predicted_edges & inside, iterations=EDGE_TOLERANCE_PX)
    return float(np.count_nonzero(seen & near_drawn) / np.count_nonzero(seen))


def draw_silhouette(triangles_px: np.ndarray, size_px: int, centre_px: np.ndarray | None = None,
                    scale: float = 1.0, shift_px: np.ndarray | None = None) -> np.ndarray:
    """(size, size) bool: the filled triangles (T, 3, 2), scaled by ``scale`` about ``centre_px`` then shifted by
    ``shift_px`` (pixels)."""
    image = Image.new("1", (size_px, size_px), 0)
    if len(triangles_px):
        points = np.asarray(triangles_px, dtype=np.float64)
        if centre_px is not None:
            points = centre_px + scale * (points - centre_px)
        if shift_px is not None:
            points = points + shift_px
        draw = ImageDraw.Draw(image)
        for triangle in points:
            draw.polygon([tuple(p) for p in triangle], fill=1, outline=1)
    return np.asarray(image, dtype=bool)


def iou(a: np.ndarray, b: np.ndarray) -> float:
    union = np.count_nonzero(a | b)
    return float(np.count_nonzero(a & b) / union) if union else 0.0


def _centroid(mask: np.ndarray) -> np.ndarray:
    v, u = np.nonzero(mask)
    return np.array([u.mean(), v.mean()]) if len(u) else np.array([mask.shape[1] / 2.0, mask.shape[0] / 2.0])


def fit_silhouette(triangles_px: np.ndarray, target: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    """The scale (within :data:`SCALE_RANGE`) about the drawn silhouette's centroid, and the shift (pixels), that
    bring the drawn triangles onto ``target`` best: first centroid onto centroid and area onto area, then a few
    rounds of local search on IoU. Returns (scale, shift_px, centre_px)."""
    size = target.shape[0]
    drawn = draw_silhouette(triangles_px, size)
    if not drawn.any() or not target.any():
        return 1.0, np.zeros(2), _centroid(drawn)
    centre = _centroid(drawn)
    scale = float(np.clip(np.sqrt(np.count_nonzero(target) / np.count_nonzero(drawn)), *SCALE_RANGE))
    shift = _centroid(target) - centre

    def score(s: float, t: np.ndarray) -> float:
        return iou(draw_silhouette(triangles_px, size, centre, s, t), target)

    best = score(scale, shift)
    for step_px, step_scale in ((4.0, 0.06), (2.0, 0.03), (1.0, 0.015)):
        improved = True
        while improved:
            improved = False
            for ds, dt in ((step_scale, (0, 0)), (-step_scale, (0, 0)), (0, (step_px, 0)), (0, (-step_px, 0)),
                           (0, (0, step_px)), (0, (0, -step_px))):
                s = float(np.clip(scale + ds, *SCALE_RANGE))
                t = shift + np.asarray(dt, dtype=np.float64)
                value = score(s, t)
                if value > best + 1e-9:
                    best, scale, shift, improved = value, s, t, True
    return scale, shift, centre


@dataclass(frozen=True)
class PictureAgreement:
    """How a predicted assembly agrees with the picture. ``silhouette_iou`` in [0, 1] (after :func:`fit_silhouette`);
    ``on_object``: part name -> fraction of its drawn pixels on the object; ``scale`` and ``shift_px``: the fit;
    ``object_fraction``: the share of the picture the object covers."""

    silhouette_iou: float
    on_object: dict
    scale: float
    shift_px: tuple[float, float]
    object_fraction: float
    object_px: np.ndarray | None = None  # (H, W) bool: the object in the picture
    drawn_px: np.ndarray | None = None  # (H, W) bool: the assembly drawn and fitted
    edge_recall: float | None = None  # the picture's edges the drawing explains (edge_recall), given the picture

    def overlay(self, image: np.ndarray) -> np.ndarray:
        """(H, W, 3) uint8: the picture dimmed, with the drawn assembly's pixels off the object in red, the object's
        pixels it misses in blue, and the two where they agree in green."""
        out = 0.4 * np.asarray(image, dtype=np.float64)
        both, drawn_only, object_only = (self.drawn_px & self.object_px, self.drawn_px & ~self.object_px,
                                         self.object_px & ~self.drawn_px)
        for pixels, rgb in ((both, (60, 200, 90)), (drawn_only, (235, 60, 50)), (object_only, (70, 120, 255))):
            out[pixels] = 0.35 * out[pixels] + 0.65 * np.array(rgb)
        return np.clip(np.round(out), 0, 255).astype(np.uint8)

    def worst_part(self) -> tuple[str, float] | None:
        if not self.on_object:
            return None
        name = min(self.on_object, key=self.on_object.get)
        return name, self.on_object[name]

    def to_dict(self) -> dict:
        return {"silhouette_iou": round(self.silhouette_iou, 4),
                "on_object": {str(k): round(v, 4) for k, v in self.on_object.items()},
                "fit_scale": round(self.scale, 4), "fit_shift_px": [round(v, 2) for v in self.shift_px],
                "object_fraction": round(self.object_fraction, 4),
                "edge_recall": None if self.edge_recall is None else round(self.edge_recall, 4)}


def picture_agreement(mask: np.ndarray, names: Sequence, meshes: Sequence[trimesh.Trimesh],
                      camera_from_parts: Sequence[Pose], intrinsics: np.ndarray | None = None,
                      image: np.ndarray | None = None) -> PictureAgreement:
    """Compare the parts (``meshes`` in their own frames, metres, at ``camera_from_parts``) drawn with
    ``intrinsics`` (default :func:`picture_intrinsics` of the mask's size) with the object ``mask`` (H, W) bool;
    with the picture ``image`` (H, W, 3) also the picture's edges it explains (:func:`edge_recall`)."""
    mask = np.asarray(mask, dtype=bool)
    size = mask.shape[0]
    intrinsics = picture_intrinsics(size) if intrinsics is None else intrinsics
    projected = [projected_triangles(m, pose, intrinsics) for m, pose in zip(meshes, camera_from_parts)]
    per_part = [triangles for triangles, _, _ in projected]
    everything = np.concatenate([t for t in per_part if len(t)] or [np.zeros((0, 3, 2))])
    scale, shift, centre = fit_silhouette(everything, mask)
    drawn = draw_silhouette(everything, size, centre, scale, shift)
    on_object = {}
    for name, triangles in zip(names, per_part):
        part = draw_silhouette(triangles, size, centre, scale, shift)
        pixels = np.count_nonzero(part)
        on_object[name] = float(np.count_nonzero(part & mask) / pixels) if pixels else 0.0
    edges = None
    if image is not None:
        labels = draw_labels(projected, size, centre, scale, shift)
        edges = edge_recall(label_edges(labels), picture_edges(image), mask)
    return PictureAgreement(iou(drawn, mask), on_object, scale, (float(shift[0]), float(shift[1])),
                            object_fraction(mask), mask, drawn, edges)


__all__ = ["MAX_PIXEL_NOISE", "PictureAgreement", "draw_labels", "draw_silhouette", "edge_recall", "facing_side",
           "fit_silhouette", "holds_an_object", "iou", "label_edges", "object_mask", "picture_agreement",
           "picture_edges", "picture_intrinsics", "pixel_noise", "plain_background", "projected_triangles"]
