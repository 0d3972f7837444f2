"""Training and evaluation import motions through the service's importer (``MotionImporter``):
``training.protocol.clip_motion`` and its clip library of bundled and CMU source clips."""
from __future__ import annotations

import numpy as np
import pytest

from inference.body import BodyModel
from inference.motion.clips import ClipLibrary
from inference.motion.importer import ClipSpec, MotionImporter, MotionLimits
from inference.motion.self_contact import lift_arms
from training.protocol import SMOKE, SourceClips, case_motion, clip_motion


@pytest.fixture(scope="module")
def body():
    return BodyModel.load()


def test_a_bundled_clip_is_imported_as_the_service_imports_it(body):
    shape = body.shape(np.array([[1.0, 1.0, 1.0, 1.0, 1.0, 1.0]], np.float32))
    fps = ClipLibrary().load("walk").fps
    service = MotionImporter(body, ClipLibrary()).import_motion(ClipSpec("walk", 0.0, 11 / fps), shape, fps, MotionLimits(300, 300, 1))
    plain = clip_motion(body, shape, "walk", 12, lift=False)
    assert plain.rotations.shape == (12, 31, 3) and plain.fps == fps
    np.testing.assert_array_equal(plain.rotations, service.rotations)
    np.testing.assert_array_equal(plain.translation, service.translation)
    lifted = clip_motion(body, shape, "walk", 12)
    np.testing.assert_array_equal(lifted.rotations, lift_arms(body, shape, service.rotations, service.translation)[0])
    assert np.abs(lifted.rotations - plain.rotations).max() > 1e-3  # the heaviest body's arms are lifted


def test_the_source_clips_hold_the_cmu_validation_clip(body):
    clips = SourceClips(body)
    assert {"walk", "02_02", "01_01"} <= set(clips.ids())
    shape, motion, start = case_motion(body, SMOKE)
    assert motion.rotations.shape[0] == SMOKE.start + SMOKE.frames and start == SMOKE.start and motion.fps == 30.0
    with pytest.raises(ValueError, match="frames asked"):
        clip_motion(body, shape, "02_02", clips.load("02_02").num_frames + 1)
