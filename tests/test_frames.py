"""Pictures of the cell: frames rendered in a second process are the frames rendered here."""

import numpy as np
import trimesh

from cell.frames import CellSnapshot, FrameRecorder
from cell.scene import load_scene
from cell.simulate import DEFAULT_CAMERA, SimPart, StaticBody
from planning.pose import Pose

UPRIGHT = [1.0, 0.0, 0.0, 0.0]


def _cell():
    start = Pose([0.5, 0.25, 0.05], UPRIGHT)
    parts = [SimPart("box", trimesh.creation.box([0.1, 0.1, 0.1]), start, start, ())]
    table = StaticBody("table", trimesh.creation.box([1.2, 1.2, 0.05]), Pose([0.4, 0.0, -0.025], UPRIGHT))
    return parts, [table], Pose([0.0, 0.0, 0.0], UPRIGHT)


def test_frames_from_a_second_process_match_those_rendered_here():
    parts, static, base = _cell()
    home = tuple(load_scene().robot.home_q)
    snapshots = [CellSnapshot({"box": Pose([0.5, 0.25 - 0.2 * k, 0.05], UPRIGHT)}, home, (0.02, 0.02))
                 for k in range(3)]
    frames = {}
    for background in (True, False):
        with FrameRecorder(parts, static, base, DEFAULT_CAMERA, background=background) as recorder:
            assert recorder.in_background == background
            for snapshot in snapshots:
                recorder.add(snapshot)
            frames[background] = recorder.frames()
    assert len(frames[True]) == len(frames[False]) == 3
    assert frames[True][0].shape == (DEFAULT_CAMERA.height_px, DEFAULT_CAMERA.width_px, 3)
    for there, here in zip(frames[True], frames[False]):
        np.testing.assert_array_equal(there, here)
    assert np.abs(frames[True][0].astype(int) - frames[True][2].astype(int)).sum() > 0  # the box moved


def test_a_recorder_without_snapshots_gives_no_frames_and_ends_its_process():
    parts, static, base = _cell()
    recorder = FrameRecorder(parts, static, base, DEFAULT_CAMERA, background=True)
    process = recorder._process
    assert recorder.frames() == []
    assert not process.is_alive() and not recorder.in_background


def test_frames_are_rendered_here_when_the_second_process_dies():
    parts, static, base = _cell()
    home = tuple(load_scene().robot.home_q)
    with FrameRecorder(parts, static, base, DEFAULT_CAMERA, background=True) as recorder:
        recorder._process.kill()  # as if it crashed
        recorder._process.join()
        recorder.add(CellSnapshot({}, home, (0.04, 0.04)))
        frames = recorder.frames()
    assert len(frames) == 1 and frames[0].shape == (DEFAULT_CAMERA.height_px, DEFAULT_CAMERA.width_px, 3)
