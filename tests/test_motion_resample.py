"""Resampling: duration kept, slerp midpoint, linear translation, identity at the same rate."""
from __future__ import annotations

import numpy as np
import pytest

from inference import rotations as rot
from inference.motion.resample import resample_motion, resample_times


def test_times_keep_duration():
    t = resample_times(343, 120.0, 30.0)  # 2.85 s
    assert len(t) == 86 and t[-1] == pytest.approx(85 / 30)
    assert resample_times(1, 120.0, 30.0).tolist() == [0.0]
    up = resample_times(31, 30.0, 120.0)
    assert len(up) == 121 and up[-1] == pytest.approx(1.0)
    with pytest.raises(ValueError):
        resample_times(10, 0.0, 30.0)


def test_same_rate_is_identity():
    rng = np.random.default_rng(0)
    rv = rng.normal(size=(7, 31, 3)).astype(np.float32) * 0.5
    tr = rng.normal(size=(7, 3)).astype(np.float32)
    r2, t2 = resample_motion(rv, tr, 30.0, 30.0)
    np.testing.assert_allclose(rot.axis_angle_to_matrix(r2), rot.axis_angle_to_matrix(rv), atol=1e-5)
    np.testing.assert_allclose(t2, tr, atol=1e-6)
    assert r2.dtype == np.float32 and t2.dtype == np.float32


def test_slerp_midpoint_and_lerp():
    # 2 frames at 1 fps: 0 and 90 deg about Z; at 2 fps the middle frame is 45 deg.
    rv = np.zeros((2, 31, 3), np.float32)
    rv[1, :, 2] = np.pi / 2
    tr = np.array([[0, 0, 0], [1, 2, 4]], np.float32)
    r2, t2 = resample_motion(rv, tr, 1.0, 2.0)
    assert r2.shape == (3, 31, 3) and t2.shape == (3, 3)
    np.testing.assert_allclose(r2[1], np.tile([0, 0, np.pi / 4], (31, 1)), atol=1e-6)
    np.testing.assert_allclose(t2[1], [0.5, 1.0, 2.0], atol=1e-6)
    np.testing.assert_allclose(r2[2], rv[1], atol=1e-6)


def test_slerp_takes_the_short_way_and_batches():
    # 170 deg -> -170 deg about X: the midpoint is 180 deg, not 0.
    rv = np.zeros((2, 2, 31, 3), np.float32)
    rv[:, 0, :, 0] = np.radians(170)
    rv[:, 1, :, 0] = np.radians(-170)
    r2, _ = resample_motion(rv, np.zeros((2, 2, 3), np.float32), 1.0, 2.0)
    assert r2.shape == (2, 3, 31, 3)
    R = rot.axis_angle_to_matrix(r2[:, 1].astype(np.float64))
    np.testing.assert_allclose(R, np.broadcast_to(np.diag([1.0, -1.0, -1.0]), R.shape), atol=1e-5)


def test_downsample_picks_source_frames():
    rng = np.random.default_rng(1)
    rv = (rng.normal(size=(121, 31, 3)) * 0.3).astype(np.float32)
    tr = rng.normal(size=(121, 3)).astype(np.float32)
    r2, t2 = resample_motion(rv, tr, 120.0, 30.0)
    assert len(r2) == 31
    np.testing.assert_allclose(rot.axis_angle_to_matrix(r2), rot.axis_angle_to_matrix(rv[::4]), atol=1e-5)
    np.testing.assert_allclose(t2, tr[::4], atol=1e-6)
