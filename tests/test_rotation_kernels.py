"""The compiled rotation conversions and 3 x 3 products (inference.rotation_kernels) against the
numpy and scipy forms they stand for: equal to rounding (bitwise on the development machine,
docs/benchmarks.md; another BLAS or SIMD libm may round its own side differently)."""
import numba
import numpy as np

from inference import rotation_kernels as rk
from inference.rotations import axis_angle_to_matrix, matrix_to_axis_angle


@numba.njit(cache=False)
def _all_matrices(r, out):
    for i in range(r.shape[0]):
        rk.rotvec_matrix(r[i, 0], r[i, 1], r[i, 2], out[i])


@numba.njit(cache=False)
def _all_axis_angles(m, out):
    for i in range(m.shape[0]):
        rk.matrix_axis_angle(m[i], out[i])


@numba.njit(cache=False)
def _all_products(a, b, out):
    for i in range(a.shape[0]):
        rk.mul3(a[i], b[i], out[i])


@numba.njit(cache=False)
def _fma(a, b, c):
    return rk.fma(a, b, c)


def _rotvecs(rng, n):
    r = rng.normal(size=(n, 3)) * rng.uniform(0.0, 3.1, (n, 1))
    r[: n // 10] *= 1e-4  # the small-angle series
    r[n // 10: n // 10 + 5] = 0.0
    return r


def test_fma_rounds_once():
    a, b = 1.0 + 2.0**-30, 1.0 - 2.0**-30  # a b = 1 - 2^-60, which a product alone rounds to 1
    assert a * b - 1.0 == 0.0
    assert _fma(a, b, -1.0) == -(2.0**-60)


def test_rotation_vector_to_matrix_is_scipys():
    r = _rotvecs(np.random.default_rng(0), 20000)
    out = np.empty((len(r), 3, 3))
    _all_matrices(r, out)
    np.testing.assert_allclose(out, axis_angle_to_matrix(r), rtol=0, atol=1e-15)
    np.testing.assert_allclose(out @ np.swapaxes(out, 1, 2), np.broadcast_to(np.eye(3), out.shape), atol=1e-14)


def test_products_are_numpys():
    rng = np.random.default_rng(1)
    a, b = rng.normal(size=(20000, 3, 3)), rng.normal(size=(20000, 3, 3))
    out = np.empty_like(a)
    _all_products(a, b, out)
    np.testing.assert_allclose(out, a @ b, rtol=1e-14, atol=1e-14)


def test_matrix_to_rotation_vector_is_numpys():
    rng = np.random.default_rng(2)
    m = axis_angle_to_matrix(_rotvecs(rng, 20000)) @ axis_angle_to_matrix(_rotvecs(rng, 20000))  # not exactly orthonormal
    axis = rng.normal(size=(50, 3))
    axis /= np.linalg.norm(axis, axis=1, keepdims=True)
    m[:50] = axis_angle_to_matrix(axis * (np.pi - rng.uniform(0.0, 1e-6, (50, 1))))  # near pi: another pivot
    m[50:55] = np.eye(3)
    out = np.empty((len(m), 3))
    _all_axis_angles(m, out)
    np.testing.assert_allclose(out, matrix_to_axis_angle(m), rtol=0, atol=1e-12)
    np.testing.assert_allclose(axis_angle_to_matrix(out), m, atol=1e-12)
