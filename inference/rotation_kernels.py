"""Compiled rotation conversions and 3 x 3 products for per-frame loops over a few bones (numba,
no Python objects, one thread), each bitwise the numpy or scipy expression it stands for:

- ``rotvec_matrix``: scipy's ``Rotation.from_rotvec(r).as_matrix()`` (``inference.rotations.
  axis_angle_to_matrix``): q = (s r, cos(a / 2)), s = sin(a / 2) / a (a = |r|; for a <= 1e-3 the
  series 1/2 - a^2/48 + a^4/3840), then R from q's products in scipy's order;
- ``mul3``: numpy's float64 ``a @ b`` of 3 x 3 matrices, which OpenBLAS computes on this
  hardware as c_ij = fma(a_i2, b_2j, fma(a_i1, b_1j, a_i0 b_0j)) (checked bitwise in
  ``tests/test_rotation_kernels.py`` against numpy on random matrices, so a BLAS that sums
  otherwise fails that test, not a drape);
- ``matrix_axis_angle``: ``inference.rotations.matrix_to_axis_angle`` (Shepperd's quaternion,
  then 2 atan2(|xyz|, w) xyz / |xyz|).

A per-request loop over one or two bones of a few frames spent ~0.3 ms a call in numpy's and
scipy's per-call overheads for microseconds of arithmetic.

Units: radians. Arrays: float64.
"""
from __future__ import annotations

import numba
import numpy as np
from numba.core import types
from numba.extending import intrinsic

_JIT = {"nogil": True, "cache": True, "fastmath": False}
# The small-angle branch of scipy's rotation vector (``rotvec_matrix``).
_SERIES_ANGLE = 1e-3
# ``inference.rotations``' guard of |xyz| in the axis-angle of a quaternion.
_EPS = 1e-8


@intrinsic
def fma(typingctx, a, b, c):
    """a b + c rounded once (LLVM's llvm.fma.f64): the fused multiply-add BLAS kernels use."""
    sig = types.float64(types.float64, types.float64, types.float64)

    def codegen(context, builder, signature, args):
        return builder.fma(*args)

    return sig, codegen


@numba.njit(**_JIT)
def rotvec_matrix(x, y, z, out):
    """out (3, 3) = the rotation of the rotation vector (x, y, z), radians (module doc)."""
    angle = np.sqrt(x * x + y * y + z * z)
    if angle <= _SERIES_ANGLE:
        a2 = angle * angle
        scale = 0.5 - a2 / 48.0 + a2 * a2 / 3840.0
    else:
        scale = np.sin(angle / 2.0) / angle
    qx, qy, qz, qw = scale * x, scale * y, scale * z, np.cos(angle / 2.0)
    x2, y2, z2, w2 = qx * qx, qy * qy, qz * qz, qw * qw
    xy, zw, xz, yw, yz, xw = qx * qy, qz * qw, qx * qz, qy * qw, qy * qz, qx * qw
    out[0, 0] = x2 - y2 - z2 + w2
    out[1, 0] = 2.0 * (xy + zw)
    out[2, 0] = 2.0 * (xz - yw)
    out[0, 1] = 2.0 * (xy - zw)
    out[1, 1] = -x2 + y2 - z2 + w2
    out[2, 1] = 2.0 * (yz + xw)
    out[0, 2] = 2.0 * (xz + yw)
    out[1, 2] = 2.0 * (yz - xw)
    out[2, 2] = -x2 - y2 + z2 + w2


@numba.njit(**_JIT)
def mul3(a, b, out):
    """out = a @ b, (3, 3) float64 each, in numpy's (BLAS's) rounding (module doc); out may not be a or b."""
    for i in range(3):
        for j in range(3):
            out[i, j] = fma(a[i, 2], b[2, j], fma(a[i, 1], b[1, j], a[i, 0] * b[0, j]))


@numba.njit(**_JIT)
def matrix_axis_angle(m, out):
    """out (3,) = the rotation vector of the rotation matrix m (3, 3), radians: numpy's
    ``matrix_to_quaternion`` then ``quaternion_to_axis_angle``, operation for operation."""
    m00, m01, m02 = m[0, 0], m[0, 1], m[0, 2]
    m10, m11, m12 = m[1, 0], m[1, 1], m[1, 2]
    m20, m21, m22 = m[2, 0], m[2, 1], m[2, 2]
    s0 = 1 + m00 + m11 + m22
    s1 = 1 + m00 - m11 - m22
    s2 = 1 - m00 + m11 - m22
    s3 = 1 - m00 - m11 + m22
    best, top = 0, s0  # argmax: the first of equal maxima
    if s1 > top:
        best, top = 1, s1
    if s2 > top:
        best, top = 2, s2
    if s3 > top:
        best, top = 3, s3
    if best == 0:
        q0, q1, q2, q3 = s0, m21 - m12, m02 - m20, m10 - m01
    elif best == 1:
        q0, q1, q2, q3 = m21 - m12, s1, m10 + m01, m02 + m20
    elif best == 2:
        q0, q1, q2, q3 = m02 - m20, m10 + m01, s2, m12 + m21
    else:
        q0, q1, q2, q3 = m10 - m01, m20 + m02, m21 + m12, s3
    n = np.sqrt(q0 * q0 + q1 * q1 + q2 * q2 + q3 * q3)
    q0, q1, q2, q3 = q0 / n, q1 / n, q2 / n, q3 / n
    if q0 < 0:
        q0, q1, q2, q3 = -q0, -q1, -q2, -q3
    s = np.sqrt(q1 * q1 + q2 * q2 + q3 * q3)
    angle = 2.0 * np.arctan2(s, q0)
    scale = 2.0 if s < _EPS else angle / max(s, _EPS)
    out[0], out[1], out[2] = q1 * scale, q2 * scale, q3 * scale
