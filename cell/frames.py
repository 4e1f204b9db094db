"""Pictures of the cell: stills and the animation frames of a simulated run, rendered with TinyRenderer.

A picture is rendered from a :class:`CellSnapshot` (where every part and the robot's joints are) in a picture-only
copy of the cell: the robot, the static bodies and the parts as visual bodies without collision shapes or physics.
During a simulation, :class:`FrameRecorder` takes snapshots at the frame times and renders them in a second process
(forked, Linux), so that the pictures (about 50 ms each at 480x360, mostly the Panda's 100k visual triangles) cost
the simulation no time on a machine with a spare core; elsewhere, or when the second process fails, it renders them
in this process. Frames: world (+z up, metres); poses ``world_from_*`` use :class:`planning.pose.Pose`.
"""

from __future__ import annotations

import colorsys
import multiprocessing
import os
import queue
import sys
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from cell.bullet import BulletClient
from cell.render import visual_shape
from cell.robot import Panda
from cell.scene import CameraConfig
from planning.pose import Pose

RESULT_TIMEOUT_S = 600.0  # how long the parent waits for the frames once it has sent the last snapshot


@dataclass(frozen=True)
class CellSnapshot:
    """The cell's state at one moment: ``world_from_part`` (mesh frames; parts not named stay where they start),
    ``arm_q`` (7,) radians, ``finger_positions_m`` (left, right) metres from closed."""

    world_from_part: Mapping[str, Pose]
    arm_q: tuple[float, ...]
    finger_positions_m: tuple[float, float]


def part_colours(count: int) -> list[tuple[float, float, float, float]]:
    """RGBA of the parts in the order given: golden-ratio hues, the same in every picture of the cell."""
    return [(*colorsys.hsv_to_rgb((0.08 + 0.61803 * k) % 1.0, 0.6, 0.9), 1.0) for k in range(count)]


def static_colour(name: str) -> tuple[float, float, float, float]:
    """RGBA of a static body: wood for the table, grey for jig pads and pedestals."""
    return (0.78, 0.68, 0.55, 1.0) if name == "table" else (0.55, 0.57, 0.62, 1.0)


def render_camera(pb, client_id: int, camera: CameraConfig) -> np.ndarray:
    """(H, W, 3) uint8 RGB of what client ``client_id`` holds now, seen from ``camera`` (TinyRenderer)."""
    view = pb.computeViewMatrix(list(camera.eye), list(camera.target), [0.0, 0.0, 1.0])
    projection = pb.computeProjectionMatrixFOV(camera.fov_deg, camera.width_px / camera.height_px, 0.02, 10.0)
    _, _, rgba, _, _ = pb.getCameraImage(camera.width_px, camera.height_px, viewMatrix=view,
                                         projectionMatrix=projection, renderer=pb.ER_TINY_RENDERER,
                                         flags=pb.ER_NO_SEGMENTATION_MASK, physicsClientId=client_id)
    return np.asarray(rgba, dtype=np.uint8).reshape(camera.height_px, camera.width_px, 4)[..., :3].copy()


class CellPictures:
    """A picture-only copy of the cell in its own headless client. ``parts`` and ``static_bodies``: objects with
    ``name``, ``mesh`` (own frame, metres) and ``world_from_start`` / ``world_from_body`` (:class:`Pose`), e.g.
    :class:`cell.simulate.SimPart` and :class:`cell.simulate.StaticBody`. Use as a context manager, or
    :meth:`close` it."""

    def __init__(self, parts: Sequence, static_bodies: Sequence, world_from_robot_base: Pose,
                 urdf: str = "franka_panda/panda.urdf") -> None:
        self._client = BulletClient()
        pb, cid = self._client.pb, self._client.client_id
        self.pb, self.cid = pb, cid
        try:
            self.panda = Panda(self._client, world_from_robot_base, urdf)
            for body in static_bodies:
                self._add(body.mesh, body.world_from_body, static_colour(body.name))
            self.parts = {part.name: self._add(part.mesh, part.world_from_start, rgba)
                          for part, rgba in zip(parts, part_colours(len(parts)))}
        except Exception:
            self._client.close()
            raise

    def _add(self, mesh, world_from_body: Pose, rgba) -> int:
        position, orientation = world_from_body.to_pybullet()
        return self.pb.createMultiBody(0.0, -1, visual_shape(self.pb, self.cid, mesh, rgba), position, orientation,
                                       physicsClientId=self.cid)

    def render(self, snapshot: CellSnapshot, camera: CameraConfig) -> np.ndarray:
        """(H, W, 3) uint8 RGB of the cell at ``snapshot`` from ``camera``."""
        pb, cid = self.pb, self.cid
        for name, pose in snapshot.world_from_part.items():
            position, orientation = pose.to_pybullet()
            pb.resetBasePositionAndOrientation(self.parts[name], position, orientation, physicsClientId=cid)
        self.panda.set_arm(np.asarray(snapshot.arm_q, dtype=np.float64))
        for joint, value in zip(self.panda.fingers, snapshot.finger_positions_m):
            pb.resetJointState(self.panda.body, joint, float(value), physicsClientId=cid)
        return render_camera(pb, cid, camera)

    def close(self) -> None:
        self._client.close()

    def __enter__(self) -> CellPictures:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def _render_worker(snapshots, results, parts, static_bodies, world_from_robot_base, urdf, camera) -> None:
    """The second process: render every snapshot that arrives until None, then send the frames back (or the
    error's words)."""
    try:
        frames = []
        with CellPictures(parts, static_bodies, world_from_robot_base, urdf) as pictures:
            while (snapshot := snapshots.get()) is not None:
                frames.append(pictures.render(snapshot, camera))
        results.put(np.stack(frames) if frames else np.zeros((0, camera.height_px, camera.width_px, 3), np.uint8))
    except BaseException as exc:  # reported to the parent, which renders the frames itself
        results.put(f"{type(exc).__name__}: {exc}")


def _second_process_useful() -> bool:
    return sys.platform.startswith("linux") and (os.cpu_count() or 1) > 1


class FrameRecorder:
    """Collects :class:`CellSnapshot` during a simulation and turns them into frames.

    ``background``: render in a forked second process (default: on Linux with more than one core). The frames are
    the same either way; :meth:`frames` returns them in the order the snapshots were added and ends the second
    process. Use as a context manager, so that the second process is ended on errors too.
    """

    def __init__(self, parts: Sequence, static_bodies: Sequence, world_from_robot_base: Pose,
                 camera: CameraConfig, urdf: str = "franka_panda/panda.urdf", background: bool | None = None) -> None:
        self._scene = (list(parts), list(static_bodies), world_from_robot_base, urdf)
        self.camera = camera
        self.snapshots: list[CellSnapshot] = []
        self._process = None
        if background if background is not None else _second_process_useful():
            context = multiprocessing.get_context("fork")
            self._to_worker, self._from_worker = context.Queue(), context.Queue()
            self._process = context.Process(target=_render_worker, daemon=True,
                                            args=(self._to_worker, self._from_worker, *self._scene, camera))
            self._process.start()

    @property
    def in_background(self) -> bool:
        return self._process is not None

    def add(self, snapshot: CellSnapshot) -> None:
        self.snapshots.append(snapshot)
        if self._process is not None:
            self._to_worker.put(snapshot)

    def frames(self) -> list[np.ndarray]:
        """(H, W, 3) uint8 RGB per snapshot."""
        if self._process is not None:
            self._to_worker.put(None)
            answer = self._answer()
            self._stop()
            if isinstance(answer, np.ndarray) and len(answer) == len(self.snapshots):
                return list(answer)
        with CellPictures(*self._scene) as pictures:  # in this process
            return [pictures.render(s, self.camera) for s in self.snapshots]

    def _answer(self):
        """The second process's frames (or its error's words); "no answer" when it died without one or took
        longer than :data:`RESULT_TIMEOUT_S`."""
        waited = 0.0
        while waited < RESULT_TIMEOUT_S:
            try:
                return self._from_worker.get(timeout=1.0)
            except queue.Empty:
                waited += 1.0
                if not self._process.is_alive() and self._from_worker.empty():
                    break
        return "no answer"

    def _stop(self) -> None:
        if self._process is not None:
            self._process.join(timeout=5.0)
            if self._process.is_alive():
                self._process.kill()
                self._process.join()
            self._to_worker.close()
            self._from_worker.close()
            self._process = None

    def close(self) -> None:
        if self._process is not None:
            self._process.kill()
        self._stop()

    def __enter__(self) -> FrameRecorder:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


__all__ = ["CellPictures", "CellSnapshot", "FrameRecorder", "part_colours", "render_camera", "static_colour"]
