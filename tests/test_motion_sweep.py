"""tools/motion_sweep.py's windows of a mocap file: the frames asked for, the file's header kept."""
from __future__ import annotations

import importlib.util

import numpy as np

from inference.motion.bvh import parse_bvh
from tests.conftest import REPO_ROOT
from tests.test_motion_bvh import make_bvh

_spec = importlib.util.spec_from_file_location("motion_sweep", REPO_ROOT / "tools" / "motion_sweep.py")
sweep = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(sweep)


def _bvh(frames: int) -> tuple[str, np.ndarray]:
    joints = [("Hips", -1, (0.0, 0.0, 0.0), ["Xposition", "Yposition", "Zposition", "Zrotation", "Xrotation", "Yrotation"], None),
              ("Spine", 0, (0.0, 10.0, 0.0), ["Zrotation", "Xrotation", "Yrotation"], (0.0, 10.0, 0.0))]
    values = np.zeros((frames, 9))
    values[:, 0] = np.arange(frames)  # the root's x: the frame's index
    values[:, 4] = np.linspace(0.0, 45.0, frames)
    return make_bvh(joints, values, frame_time=1 / 30), values


def test_bvh_window_keeps_the_frames_asked_for_and_the_hierarchy():
    text, values = _bvh(10)
    window = sweep.bvh_window(text, 0.1, 0.2)  # frames 3..8 at 30 fps
    motion, whole = parse_bvh(window, unit_scale=1.0), parse_bvh(text, unit_scale=1.0)
    assert motion.names == whole.names and motion.fps == whole.fps
    np.testing.assert_array_equal(motion.root_positions[:, 0], values[3:9, 0])
    np.testing.assert_allclose(motion.world_rotations, whole.world_rotations[3:9])


def test_bvh_window_past_the_end_keeps_what_there_is():
    text, values = _bvh(10)
    motion = parse_bvh(sweep.bvh_window(text, 0.2, 5.0), unit_scale=1.0)
    np.testing.assert_array_equal(motion.root_positions[:, 0], values[6:, 0])


def test_amc_window_renumbers_the_frames_it_keeps():
    head = ":FULLY-SPECIFIED\n:DEGREES"
    frames = "\n".join(f"{i + 1}\nroot {i} 0 0 0 0 0" for i in range(240))
    window = sweep.amc_window(f"{head}\n{frames}\n", 0.5, 0.25)  # CMU's 120 fps: frames 60..89
    lines = window.splitlines()
    assert lines[:2] == head.splitlines()
    assert lines[2::2] == [str(i + 1) for i in range(30)]
    assert lines[3] == "root 60 0 0 0 0 0" and lines[-1] == "root 89 0 0 0 0 0"
