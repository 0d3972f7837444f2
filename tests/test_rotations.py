"""Rotation conversions: round trips, a hand-computed case, and parity with scipy."""
import numpy as np
from scipy.spatial.transform import Rotation

from inference import rotations as rot


def test_quarter_turn_about_z():
    R = rot.axis_angle_to_matrix(np.array([0.0, 0.0, np.pi / 2], np.float32))
    np.testing.assert_allclose(R @ np.array([1.0, 0.0, 0.0]), [0.0, 1.0, 0.0], atol=1e-6)


def test_round_trips_match_scipy():
    rng = np.random.default_rng(0)
    rv = rng.normal(size=(4, 50, 3)) * 1.2
    R = rot.axis_angle_to_matrix(rv)
    np.testing.assert_allclose(R, Rotation.from_rotvec(rv.reshape(-1, 3)).as_matrix().reshape(R.shape), atol=1e-9)
    back = rot.axis_angle_to_matrix(rot.matrix_to_axis_angle(R))
    np.testing.assert_allclose(back, R, atol=1e-9)
    q = rot.axis_angle_to_quaternion(rv)
    np.testing.assert_allclose(rot.quaternion_to_matrix(q), R, atol=1e-9)


def test_small_and_pi_angles():
    rv = np.array([[1e-9, 0, 0], [0, np.pi, 0], [0, 0, 0]])
    R = rot.axis_angle_to_matrix(rv)
    np.testing.assert_allclose(R[1], np.diag([-1.0, 1.0, -1.0]), atol=1e-12)
    np.testing.assert_allclose(rot.axis_angle_to_matrix(rot.matrix_to_axis_angle(R)), R, atol=1e-9)


def test_slerp_midpoint_and_ends():
    q0 = rot.axis_angle_to_quaternion(np.array([0.0, 0.0, 0.0]))
    q1 = rot.axis_angle_to_quaternion(np.array([0.0, 0.0, 1.0]))
    mid = rot.quaternion_slerp(q0, q1, 0.5)
    np.testing.assert_allclose(rot.quaternion_to_axis_angle(mid), [0, 0, 0.5], atol=1e-9)
    np.testing.assert_allclose(rot.quaternion_slerp(q0, q1, 1.0), q1, atol=1e-9)
    # shorter arc: -q1 is the same rotation
    np.testing.assert_allclose(rot.quaternion_to_axis_angle(rot.quaternion_slerp(q0, -q1, 0.5)), [0, 0, 0.5], atol=1e-9)


def test_rotation_between():
    rng = np.random.default_rng(1)
    a, b = rng.normal(size=(10, 3)), rng.normal(size=(10, 3))
    R = rot.rotation_between(a, b)
    got = np.einsum("nij,nj->ni", R, a / np.linalg.norm(a, axis=1, keepdims=True))
    np.testing.assert_allclose(got, b / np.linalg.norm(b, axis=1, keepdims=True), atol=1e-9)
    R = rot.rotation_between(np.array([1.0, 0, 0]), np.array([-1.0, 0, 0]))
    np.testing.assert_allclose(R @ np.array([1.0, 0, 0]), [-1, 0, 0], atol=1e-9)
