"""Headless rendering of an assembly: RGB image, per-part instance masks, camera and part poses.

Camera convention (OpenCV): the camera frame ``camera`` has x to the right of the image, y down, z forward
along the optical axis, metres. ``intrinsics`` is the usual 3x3 K with pixel (u, v) = (column, row) and pixel
i covering [i, i + 1): a point projects to ``u = fx * x / z + cx``, ``v = fy * y / z + cy``.

Cameras are sampled as in the perception paper's renders: azimuth all around, elevation 10-50 degrees, no roll,
a fixed field of view and a distance fitted so that the object's bounding sphere fills the view.

PyBullet DIRECT with TinyRenderer by default; ``renderer="egl"`` (or ``"auto"`` on a machine with an NVIDIA
device) loads PyBullet's EGL plugin for hardware rendering.
"""

from __future__ import annotations

import colorsys
import os
from dataclasses import dataclass

import numpy as np
import trimesh

from cell.bullet import BulletClient
from planning.assembly import Assembly
from planning.pose import Pose

IMAGE_SIZE = 224
FIELD_OF_VIEW_DEG = 35.0
ELEVATION_RANGE_DEG = (10.0, 50.0)
BACKGROUND_LABEL = -1


@dataclass(frozen=True)
class CameraSpec:
    """Where the camera looks from, in the assembly frame (metres, +z up)."""

    azimuth_deg: float  # around +z, 0 = camera on the +x side looking towards -x
    elevation_deg: float  # above the horizontal plane through the target
    distance_m: float  # from the target to the camera centre
    target_m: tuple[float, float, float]  # point the optical axis passes through, assembly frame
    fov_deg: float = FIELD_OF_VIEW_DEG  # vertical field of view
    width_px: int = IMAGE_SIZE
    height_px: int = IMAGE_SIZE

    def eye_m(self) -> np.ndarray:
        az, el = np.radians(self.azimuth_deg), np.radians(self.elevation_deg)
        direction = np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])
        return np.asarray(self.target_m) + self.distance_m * direction

    def camera_from_assembly(self) -> Pose:
        """OpenCV camera frame (x right, y down, z forward) from the assembly frame; no roll."""
        eye = self.eye_m()
        forward = np.asarray(self.target_m) - eye
        forward /= np.linalg.norm(forward)
        right = np.cross(forward, [0.0, 0.0, 1.0])
        right /= np.linalg.norm(right)
        down = np.cross(forward, right)
        assembly_from_camera_rot = np.stack([right, down, forward], axis=1)
        return Pose.from_rotation(assembly_from_camera_rot, eye).inverse()

    def intrinsics(self) -> np.ndarray:
        """(3, 3) pinhole matrix K in pixels."""
        fy = 0.5 * self.height_px / np.tan(np.radians(self.fov_deg) / 2.0)
        return np.array([[fy, 0.0, 0.5 * self.width_px], [0.0, fy, 0.5 * self.height_px], [0.0, 0.0, 1.0]])


def fitted_distance_m(bounds_m: np.ndarray, fov_deg: float = FIELD_OF_VIEW_DEG) -> float:
    """Distance at which the bounding sphere of ``bounds_m`` ((2, 3), metres) just fits the field of view."""
    radius = 0.5 * float(np.linalg.norm(bounds_m[1] - bounds_m[0]))
    return radius / np.sin(np.radians(fov_deg) / 2.0)


def sample_camera(rng: np.random.Generator, bounds_m: np.ndarray, fov_deg: float = FIELD_OF_VIEW_DEG) -> CameraSpec:
    """A random camera around an object with assembly-frame bounds ``bounds_m`` ((2, 3), metres)."""
    target = 0.5 * (bounds_m[0] + bounds_m[1])
    return CameraSpec(
        azimuth_deg=float(rng.uniform(0.0, 360.0)),
        elevation_deg=float(rng.uniform(*ELEVATION_RANGE_DEG)),
        distance_m=fitted_distance_m(bounds_m, fov_deg),
        target_m=tuple(float(v) for v in target),
        fov_deg=fov_deg,
    )


MATERIALS = ("parts", "one", "few")  # Appearance.sample: a colour per part, one material, two or three


@dataclass(frozen=True)
class Appearance:
    """Colours and lighting of one rendering (all colours RGB in [0, 1])."""

    part_rgb: np.ndarray  # (N, 3)
    background_rgb: np.ndarray  # (2, 3): top and bottom of a vertical gradient
    light_direction: np.ndarray  # (3,) towards the light, assembly frame
    light_rgb: np.ndarray  # (3,)
    ambient: float
    diffuse: float
    specular: float
    shadow: bool

    @staticmethod
    def sample(rng: np.random.Generator, num_parts: int, materials: str = "parts") -> Appearance:
        """Random colours, backdrop and lighting. ``materials`` (:data:`MATERIALS`): ``parts``, every part its own
        colour; ``one``, every part the same material, as a photo of a wooden chair shows it (only shading tells
        its parts apart); ``few``, two or three materials shared among the parts (a frame and its panels). The
        random numbers drawn are the same in every mode, so a view differs between modes in its parts' colours
        only."""
        if materials not in MATERIALS:
            raise ValueError(f"materials must be one of {MATERIALS}, got {materials!r}")
        hues = rng.uniform(0.0, 1.0, num_parts)
        sat = rng.uniform(0.25, 0.9, num_parts)
        val = rng.uniform(0.45, 1.0, num_parts)
        parts = np.array([colorsys.hsv_to_rgb(h, s, v) for h, s, v in zip(hues, sat, val)]).reshape(num_parts, 3)
        if materials == "one" and num_parts:
            parts = np.repeat(parts[:1], num_parts, axis=0)
        elif materials == "few" and num_parts:
            palette = parts[: 2 if hues[0] < 0.5 else 3]  # two or three materials, as the first hue falls
            parts = palette[np.arange(num_parts) % len(palette)]
        background = np.clip(rng.uniform(0.0, 1.0, 3) + rng.uniform(-0.15, 0.15, (2, 3)), 0.0, 1.0)
        az, el = rng.uniform(0, 2 * np.pi), rng.uniform(np.radians(25), np.radians(85))
        return Appearance(
            part_rgb=parts,
            background_rgb=background,
            light_direction=np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)]),
            light_rgb=rng.uniform(0.85, 1.0, 3),
            ambient=float(rng.uniform(0.35, 0.6)),
            diffuse=float(rng.uniform(0.4, 0.7)),
            specular=float(rng.uniform(0.0, 0.3)),
            shadow=bool(rng.uniform() < 0.5),
        )


@dataclass
class Rendering:
    """One rendered view of an assembly.

    rgb: (H, W, 3) uint8.
    part_labels: (H, W) int16; the index of the part seen at each pixel (order of ``assembly.parts``), or -1.
    visible_pixels: (N,) int64, pixels of each part in ``part_labels``; a part with 0 is invisible.
    intrinsics: (3, 3) float64, pixels.
    camera_from_assembly: OpenCV camera frame from the assembly frame (metres).
    camera_from_part: list of N poses, each part's mesh frame in the camera frame (metres).
    """

    rgb: np.ndarray
    part_labels: np.ndarray
    visible_pixels: np.ndarray
    intrinsics: np.ndarray
    camera_from_assembly: Pose
    camera_from_part: list[Pose]
    camera: CameraSpec

    @property
    def visible(self) -> np.ndarray:
        return self.visible_pixels > 0

    def part_masks(self) -> np.ndarray:
        """(N, H, W) bool instance masks."""
        n = len(self.camera_from_part)
        return self.part_labels[None] == np.arange(n)[:, None, None]


def _nvidia_present() -> bool:
    return os.path.exists("/dev/nvidia0")


# PyBullet refuses a visual mesh of more than 2^17 vertices, and the renderer gives every face its own three
MAX_RENDER_FACES = 40_000


def simplified_for_rendering(mesh: trimesh.Trimesh, max_faces: int = MAX_RENDER_FACES) -> trimesh.Trimesh:
    """``mesh`` itself when it has at most ``max_faces`` faces, else a copy decimated by vertex clustering on a
    grid made coarser until it fits (same frame and unit; for pictures only, never for geometry)."""
    if len(mesh.faces) <= max_faces:
        return mesh
    cell = float(np.linalg.norm(mesh.extents)) / 2000.0
    while True:
        keys = np.floor(mesh.vertices / cell).astype(np.int64)
        _, first, inverse = np.unique(keys, axis=0, return_index=True, return_inverse=True)
        faces = inverse.reshape(-1)[mesh.faces]
        faces = faces[(faces[:, 0] != faces[:, 1]) & (faces[:, 1] != faces[:, 2]) & (faces[:, 0] != faces[:, 2])]
        simplified = trimesh.Trimesh(mesh.vertices[first], faces, process=True)
        if len(simplified.faces) <= max_faces:
            return simplified
        cell *= 1.5


def visual_shape(pb, client_id: int, mesh: trimesh.Trimesh, rgba=None) -> int:
    """A flat-shaded PyBullet visual shape of ``mesh`` (its own frame), decimated for the picture when it has more
    faces than PyBullet takes (:func:`simplified_for_rendering`); raises RuntimeError when PyBullet refuses it."""
    mesh = simplified_for_rendering(mesh).copy()
    mesh.unmerge_vertices()  # one vertex per face corner: flat shading with face normals
    options = {} if rgba is None else {"rgbaColor": list(rgba)}
    shape = pb.createVisualShape(pb.GEOM_MESH, vertices=mesh.vertices.tolist(), indices=mesh.faces.ravel().tolist(),
                                 normals=np.repeat(mesh.face_normals, 3, axis=0).tolist(), physicsClientId=client_id,
                                 **options)
    if shape < 0:
        raise RuntimeError(f"PyBullet refused a visual mesh of {len(mesh.faces)} faces")
    return shape


class AssemblyRenderer:
    """Holds one headless PyBullet client with an assembly's parts loaded as visual bodies.

    Load once, render many views (colours and lighting change per view)::

        with AssemblyRenderer(assembly) as renderer:
            view = renderer.render(sample_camera(rng, assembly.bounds()), Appearance.sample(rng, n))
    """

    def __init__(self, assembly: Assembly, renderer: str = "tiny") -> None:
        if renderer not in ("tiny", "egl", "auto"):
            raise ValueError(f"renderer must be 'tiny', 'egl' or 'auto', got {renderer!r}")
        self.assembly = assembly
        self._client = BulletClient()
        pb, cid = self._client.pb, self._client.client_id
        self._renderer_flag = pb.ER_TINY_RENDERER
        if renderer == "egl" or (renderer == "auto" and _nvidia_present()):
            self._load_egl(pb, cid, required=renderer == "egl")
        self._body_ids: list[int] = []
        for part in assembly.parts:
            try:
                shape = visual_shape(pb, cid, part.mesh)
            except RuntimeError as exc:
                raise RuntimeError(f"part {part.name!r}: {exc}") from exc
            position, quat_xyzw = part.assembly_from_part.to_pybullet()
            body = pb.createMultiBody(
                baseVisualShapeIndex=shape,
                basePosition=position,
                baseOrientation=quat_xyzw,
                physicsClientId=cid,
            )
            self._body_ids.append(body)
        self._label_of_body = {body: index for index, body in enumerate(self._body_ids)}

    def _load_egl(self, pb, cid: int, required: bool) -> None:
        import pkgutil

        loader = pkgutil.get_loader("eglRenderer")
        plugin = pb.loadPlugin(loader.get_filename(), "_eglRendererPlugin", physicsClientId=cid) if loader else -1
        if plugin >= 0:
            self._renderer_flag = pb.ER_BULLET_HARDWARE_OPENGL
        elif required:
            raise RuntimeError("PyBullet's EGL renderer plugin could not be loaded")

    def render(self, camera: CameraSpec, appearance: Appearance) -> Rendering:
        pb, cid = self._client.pb, self._client.client_id
        n = len(self._body_ids)
        if appearance.part_rgb.shape != (n, 3):
            raise ValueError(f"appearance has {len(appearance.part_rgb)} part colours for {n} parts")
        for body, rgb in zip(self._body_ids, appearance.part_rgb):
            pb.changeVisualShape(body, -1, rgbaColor=[*rgb.tolist(), 1.0], physicsClientId=cid)
        view = pb.computeViewMatrix(camera.eye_m().tolist(), list(camera.target_m), [0, 0, 1])
        near = max(1e-3, camera.distance_m * 0.05)
        projection = pb.computeProjectionMatrixFOV(camera.fov_deg, camera.width_px / camera.height_px, near,
                                                   camera.distance_m * 4.0)
        _, _, rgba, depth, seg = pb.getCameraImage(
            camera.width_px,
            camera.height_px,
            viewMatrix=view,
            projectionMatrix=projection,
            lightDirection=appearance.light_direction.tolist(),
            lightColor=appearance.light_rgb.tolist(),
            lightDistance=camera.distance_m * 3.0,
            shadow=int(appearance.shadow),
            lightAmbientCoeff=appearance.ambient,
            lightDiffuseCoeff=appearance.diffuse,
            lightSpecularCoeff=appearance.specular,
            renderer=self._renderer_flag,
            physicsClientId=cid,
        )
        rgb = np.asarray(rgba, dtype=np.uint8).reshape(camera.height_px, camera.width_px, 4)[..., :3].copy()
        seg = np.asarray(seg, dtype=np.int64).reshape(camera.height_px, camera.width_px)
        labels = np.full(seg.shape, BACKGROUND_LABEL, dtype=np.int16)
        for body, index in self._label_of_body.items():
            labels[seg == body] = index
        background = labels == BACKGROUND_LABEL
        ramp = np.linspace(0.0, 1.0, camera.height_px)[:, None, None]
        gradient = (1 - ramp) * appearance.background_rgb[0] + ramp * appearance.background_rgb[1]
        gradient = np.broadcast_to(gradient, (camera.height_px, camera.width_px, 3))
        rgb[background] = np.round(gradient[background] * 255).astype(np.uint8)
        camera_from_assembly = camera.camera_from_assembly()
        return Rendering(
            rgb=rgb,
            part_labels=labels,
            visible_pixels=np.bincount(labels[~background].astype(np.int64), minlength=n)[:n],
            intrinsics=camera.intrinsics(),
            camera_from_assembly=camera_from_assembly,
            camera_from_part=[camera_from_assembly @ p.assembly_from_part for p in self.assembly.parts],
            camera=camera,
        )

    def close(self) -> None:
        self._client.close()

    def __enter__(self) -> AssemblyRenderer:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def render_assembly(assembly: Assembly, rng: np.random.Generator, renderer: str = "tiny") -> Rendering:
    """Render one random view of ``assembly`` (random camera, colours, lighting and background)."""
    with AssemblyRenderer(assembly, renderer=renderer) as r:
        return r.render(sample_camera(rng, assembly.bounds()), Appearance.sample(rng, len(assembly.parts)))


def project_points(points_camera_m: np.ndarray, intrinsics: np.ndarray) -> np.ndarray:
    """(N, 3) camera-frame points (metres) to (N, 2) pixel coordinates (u, v)."""
    uvw = points_camera_m @ intrinsics.T
    return uvw[:, :2] / uvw[:, 2:3]


def overlay_labels(rendering: Rendering) -> np.ndarray:
    """(H, W, 3) uint8 picture of the instance masks: one flat colour per part, black background."""
    n = len(rendering.camera_from_part)
    palette = (np.array([colorsys.hsv_to_rgb((0.61803 * i) % 1.0, 0.75, 0.95) for i in range(max(n, 1))]) * 255)
    out = np.zeros((*rendering.part_labels.shape, 3), dtype=np.uint8)
    visible = rendering.part_labels >= 0
    out[visible] = palette[rendering.part_labels[visible]].astype(np.uint8)
    return out


def main(argv: list[str] | None = None) -> int:
    """``python -m cell.render ASSEMBLY_DIR --out IMAGE.png``: render one random view (image | masks)."""
    import argparse
    import sys
    from pathlib import Path

    from PIL import Image

    from planning.assembly import AssemblyError, read_assembly

    parser = argparse.ArgumentParser(prog="python -m cell.render", description=main.__doc__)
    parser.add_argument("assembly", type=Path, help="assembly folder (assembly.json + parts/)")
    parser.add_argument("--out", type=Path, required=True, help="PNG to write")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--masks", action="store_true", help="put the instance masks beside the image")
    parser.add_argument("--renderer", choices=["tiny", "egl", "auto"], default="tiny")
    args = parser.parse_args(argv)
    if args.out.suffix.lower() != ".png":
        parser.error(f"--out must name a .png file, got {args.out}")
    try:
        assembly = read_assembly(args.assembly)
    except AssemblyError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    view = render_assembly(assembly, np.random.default_rng(args.seed), renderer=args.renderer)
    picture = np.concatenate([view.rgb, overlay_labels(view)], axis=1) if args.masks else view.rgb
    args.out.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(picture).save(args.out)
    camera = view.camera
    print(f"{assembly.name}: {len(assembly.parts)} parts, {int(view.visible.sum())} visible; camera azimuth "
          f"{camera.azimuth_deg:.0f} deg, elevation {camera.elevation_deg:.0f} deg, {camera.distance_m:.2f} m "
          f"-> {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
