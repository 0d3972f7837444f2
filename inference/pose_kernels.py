"""Compiled forward kinematics of ``inference.body.BodyModel.pose`` (numba, no Python objects, one
thread): the same float64 arithmetic as its numpy form, product for product, rounded to float32
at the end.

Per bone c with parent p, rest frame P_c = [R_c | h_c] and local rotation D_c = R(theta_c)
(``inference.rotation_kernels.rotvec_matrix``):

    K_c = [R_p^T R_c D_c | R_p^T (h_c - h_p)],   W_0 = [R_0 D_0 | h_0 + trans],   W_c = W_p K_c,
    T_c = W_c P_c^-1 = [W_R R_c^T | w - W_R R_c^T h_c].

numpy evaluates the 3 x 3 and 4 x 4 products with BLAS (``rotation_kernels.mul3``: fused
multiply-adds in the order of the inner index) and the matrix-vector products with ``einsum``,
which sums (a_0 b_0 + a_2 b_2) + a_1 b_1 on this hardware; both forms are kept, so the poses
match numpy's bit for bit here (and to rounding where a BLAS or einsum sums in another order:
``tests/test_pose_kernels.py``). A request's pose of one frame took ~0.4 ms in numpy's per-call
overheads (31 bones, 5 depth levels, scipy's rotations); compiled, ~0.01 ms.

Units: metres, radians. Arrays: float32 in and out, float64 inside.
"""
from __future__ import annotations

import numba
import numpy as np

from inference.rotation_kernels import fma, mul3, rotvec_matrix

_JIT = {"nogil": True, "cache": True, "fastmath": False}


@numba.njit(inline="always", **_JIT)
def _mat_vec(M, v, out):
    """out = M v, (3, 3) and (3,) float64, in ``einsum``'s order: (m0 v0 + m2 v2) + m1 v1."""
    for i in range(3):
        out[i] = (M[i, 0] * v[0] + M[i, 2] * v[2]) + M[i, 1] * v[1]


@numba.njit(**_JIT)
def forward_kinematics(rest, rotations, translation, parents, order, W, T):
    """Bone poses W and skinning transforms T of every frame (module doc).

    rest        : (B, J, 4, 4) float32 rigid rest frames P
    rotations   : (B, F, J, 3) float32 axis-angle, radians; translation (B, F, 3) float32, metres
    parents     : (J,) int64 (the root's is ignored); order: (J,) int64, the bones root first,
                  every parent before its children
    W, T        : (B, F, J, 4, 4) float32, written
    """
    B, F, J = rotations.shape[0], rotations.shape[1], rotations.shape[2]
    R = np.empty((J, 3, 3))
    h = np.empty((J, 3))
    C = np.empty((J, 3, 3))  # R_p^T R_c
    k = np.empty((J, 3))  # R_p^T (h_c - h_p)
    Wd = np.empty((J, 4, 4))
    Kc = np.zeros((4, 4))
    Kc[3, 3] = 1.0
    Rpt = np.empty((3, 3))
    Rt = np.empty((3, 3))
    D = np.empty((3, 3))
    TR = np.empty((3, 3))
    Wr = np.empty((3, 3))
    d = np.empty(3)
    w = np.empty(3)
    for b in range(B):
        for j in range(J):
            for r in range(3):
                h[j, r] = np.float64(rest[b, j, r, 3])
                for c in range(3):
                    R[j, r, c] = np.float64(rest[b, j, r, c])
        for j in range(J):
            p = parents[j] if j > 0 else 0
            for r in range(3):
                for c in range(3):
                    Rpt[r, c] = R[p, c, r]
                d[r] = h[j, r] - h[p, r]
            mul3(Rpt, R[j], C[j])
            _mat_vec(Rpt, d, k[j])
        for f in range(F):
            for q in range(J):
                j = order[q]
                rotvec_matrix(np.float64(rotations[b, f, j, 0]), np.float64(rotations[b, f, j, 1]),
                              np.float64(rotations[b, f, j, 2]), D)
                if q == 0:  # the root: [R_0 D_0 | h_0 + trans]
                    mul3(R[j], D, TR)
                    Wd[j, :, :] = 0.0
                    for r in range(3):
                        for c in range(3):
                            Wd[j, r, c] = TR[r, c]
                        Wd[j, r, 3] = h[j, r] + np.float64(translation[b, f, r])
                    Wd[j, 3, 3] = 1.0
                else:
                    mul3(C[j], D, TR)
                    for r in range(3):
                        for c in range(3):
                            Kc[r, c] = TR[r, c]
                        Kc[r, 3] = k[j, r]
                    p = parents[j]
                    for r in range(4):
                        for c in range(4):
                            Wd[j, r, c] = fma(Wd[p, r, 3], Kc[3, c], fma(Wd[p, r, 2], Kc[2, c],
                                              fma(Wd[p, r, 1], Kc[1, c], Wd[p, r, 0] * Kc[0, c])))
                # T = [W_R R^T | w - W_R R^T h]
                for r in range(3):
                    for c in range(3):
                        Wr[r, c] = Wd[j, r, c]
                        Rt[r, c] = R[j, c, r]
                mul3(Wr, Rt, TR)
                _mat_vec(TR, h[j], w)
                for r in range(4):
                    for c in range(4):
                        W[b, f, j, r, c] = np.float32(Wd[j, r, c])
                for r in range(3):
                    for c in range(3):
                        T[b, f, j, r, c] = np.float32(TR[r, c])
                    T[b, f, j, r, 3] = np.float32(Wd[j, r, 3] - w[r])
                    T[b, f, j, 3, r] = np.float32(0.0)
                T[b, f, j, 3, 3] = np.float32(1.0)
