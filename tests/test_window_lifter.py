"""Training windows get the runtime's arm correction (training.datasets.WindowLifter)."""
from types import SimpleNamespace

import numpy as np
import pytest

from inference.body import NEUTRAL_PHENOTYPES, BodyModel
from inference.motion.clips import ClipLibrary, adapt_clip
from inference.motion.descriptor import motion_descriptor
from inference.motion.self_contact import lift_arms

pytest.importorskip("torch")  # training.datasets imports training.physics (torch)

HEAVY = np.ones(6, np.float32)
LIGHT = np.array([0.0, 0.77, 0.0, 0.0, 0.0, 0.0], np.float32)


def test_windows_are_lifted_as_at_runtime():
    from training.datasets import LIFT_CONTEXT, MotionBank, WindowLifter

    body = BodyModel.load()
    neutral = body.shape(NEUTRAL_PHENOTYPES[None])
    rot, trans = adapt_clip(ClipLibrary().load("walk"), body, neutral)
    T = 40
    rot, trans = rot[0, :T], trans[0, :T]
    gamma = motion_descriptor(rot[None], trans[None], 30.0)[0]
    motions = MotionBank(clip_ids=["walk"], clip_start=np.array([0, T]), rotations=rot, translation=trans, gamma=gamma,
                         leg_length_m=1.0, windows=np.arange(T - 2))
    lifter = WindowLifter(body, SimpleNamespace(phenotypes=np.stack([HEAVY, LIGHT])), motions)
    frames = np.array([[10, 11, 12], [10, 11, 12], [0, 1, 2]])
    r, g = lifter(np.array([0, 1, 0]), frames)

    heavy = body.shape(HEAVY[None])
    a, e = 10 - LIFT_CONTEXT, 13 + LIFT_CONTEXT
    lifted, angles = lift_arms(body, heavy, rot[a:e], trans[a:e])
    assert angles.max() > 0  # the heavy body's arms do need the correction on this window
    np.testing.assert_allclose(r[0], lifted[LIFT_CONTEXT:LIFT_CONTEXT + 3], atol=1e-6)
    delta = motion_descriptor(lifted[None], trans[None, a:e], 30.0)[0] - motion_descriptor(rot[None, a:e], trans[None, a:e], 30.0)[0]
    np.testing.assert_allclose(g[0], gamma[10:13] + delta[LIFT_CONTEXT:LIFT_CONTEXT + 3], atol=1e-5)
    assert np.abs(g[0] - gamma[10:13]).max() > 1e-3

    # the slim body needs none: the clip's own poses and descriptor
    np.testing.assert_array_equal(r[1], rot[10:13])
    np.testing.assert_array_equal(g[1], gamma[10:13])

    # at the clip's start the context is cut at the clip boundary
    first, _ = lift_arms(body, heavy, rot[0:3 + LIFT_CONTEXT], trans[0:3 + LIFT_CONTEXT])
    np.testing.assert_allclose(r[2], first[:3], atol=1e-6)


def test_longer_windows_stay_within_their_clip():
    from training.datasets import MotionBank

    lengths = [10, 6, 12]  # three clips, their 3-frame window starts as MotionBank.build makes them
    start = np.concatenate([[0], np.cumsum(lengths)])
    windows = np.concatenate([s + np.arange(n - 2) for s, n in zip(start, lengths)])
    z = np.zeros((start[-1], 3), np.float32)
    motions = MotionBank(clip_ids=["a", "b", "c"], clip_start=start, rotations=z, translation=z, gamma=z, leg_length_m=1.0, windows=windows)
    np.testing.assert_array_equal(motions.windows_of(3), windows)
    w8 = motions.windows_of(8)
    np.testing.assert_array_equal(w8, [0, 1, 2, 16, 17, 18, 19, 20])  # clip b (6 frames) has none
    frames = motions.window_frames(w8, 8)
    clip = np.searchsorted(start, frames, side="right") - 1
    assert (clip == clip[:, :1]).all()
    with pytest.raises(ValueError):
        motions.windows_of(2)
