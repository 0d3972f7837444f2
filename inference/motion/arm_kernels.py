"""Compiled kernels of the arm lift (``inference.motion.self_contact``): one abduction step per
frame from the arm points' nearest torso points, the window maximum of the steps, and the arm's
new local rotation (numba, no Python objects, one thread).

Units: metres, radians. Arrays: float32 points and normals, int64 ids.
"""
from __future__ import annotations

import numba
import numpy as np

from inference.rotation_kernels import matrix_axis_angle, mul3, rotvec_matrix

_JIT = {"nogil": True, "cache": True, "fastmath": False}


@numba.njit(**_JIT)
def arm_steps(tp, tn, ap, shoulder, active, near, found, margin_m, reach_m, tangent_m, cap, step, axes):
    """The step of ``self_contact._steps`` (module doc there) for the active frames, written into
    step (T,) float64 and axes (T, 3) float64 (left as they are where the arm is clear).

    tp, tn   : (T, m, 3) float32, the torso points and their unit normals
    ap       : (A, n, 3) float32, the arm points of the active frames (A,) int64
    shoulder : (A, 3) float32, the shoulder joint of each active frame
    near     : (A * n,) int64, each arm point's nearest torso point (its row in tp), where found
               (A * n,) bool (``repair_kernels.frame_knn`` within the reach)

    In the order and precision of the numpy expressions it replaces: the distance in float64 from
    the float32 coordinates, the depth, the direction, the lever and the step in float32.
    """
    A, n = ap.shape[0], ap.shape[1]
    zero = np.float32(0.0)
    tiny = np.float32(1e-12)
    margin = np.float32(margin_m)
    for r in range(A):
        t = active[r]
        d0 = d1 = d2 = zero  # the depth-weighted sum of the normals (the direction)
        best = zero  # the largest depth, at the arm point ``deepest`` (the first of equal ones)
        deepest = 0
        for i in range(n):
            s = r * n + i
            depth = zero
            if found[s]:
                c = near[s]
                e0 = np.float64(ap[r, i, 0]) - np.float64(tp[t, c, 0])
                e1 = np.float64(ap[r, i, 1]) - np.float64(tp[t, c, 1])
                e2 = np.float64(ap[r, i, 2]) - np.float64(tp[t, c, 2])
                dist = np.sqrt(e0 * e0 + e1 * e1 + e2 * e2)
                if dist < reach_m:
                    a0, a1, a2 = ap[r, i, 0] - tp[t, c, 0], ap[r, i, 1] - tp[t, c, 1], ap[r, i, 2] - tp[t, c, 2]
                    h = -(a0 * tn[t, c, 0] + a1 * tn[t, c, 1] + a2 * tn[t, c, 2])
                    # the tangent plane judges only points that project near c (not across a crease)
                    if dist * dist - np.float64(h * h) < tangent_m * tangent_m:
                        depth = h
            if depth > zero:
                d0 += depth * tn[t, near[s], 0]
                d1 += depth * tn[t, near[s], 1]
                d2 += depth * tn[t, near[s], 2]
            if i == 0 or depth > best:
                best = depth
                deepest = i
        if not best > zero:
            continue
        length = np.sqrt(d0 * d0 + d1 * d1 + d2 * d2)
        length = max(length, tiny)
        d0, d1, d2 = d0 / length, d1 / length, d2 / length
        l0 = ap[r, deepest, 0] - shoulder[r, 0]
        l1 = ap[r, deepest, 1] - shoulder[r, 1]
        l2 = ap[r, deepest, 2] - shoulder[r, 2]
        k0, k1, k2 = l1 * d2 - l2 * d1, l2 * d0 - l0 * d2, l0 * d1 - l1 * d0
        lever = np.sqrt(k0 * k0 + k1 * k1 + k2 * k2)
        if not lever > np.float32(1e-3):
            continue
        step[t] = min((best + margin) / lever, np.float32(cap))
        axes[t, 0], axes[t, 1], axes[t, 2] = k0 / lever, k1 / lever, k2 / lever


@numba.njit(**_JIT)
def window_argmax(x, seg, smooth, best):
    """best[i] = the index of the largest x[j], |j - i| <= smooth, j clipped to [0, T) and in i's
    segment (seg (T,) int64 ids), written into best (T,) int64: the offsets -smooth..smooth in
    turn from best[i] = i, an offset taking over only where x is strictly larger (numpy's loop of
    shifted comparisons, the same ties)."""
    T = x.shape[0]
    for i in range(T):
        b = i
        for off in range(-smooth, smooth + 1):
            j = min(max(i + off, 0), T - 1)
            if seg[j] == seg[i] and x[j] > x[b]:
                b = j
        best[i] = b


@numba.njit(**_JIT)
def rotate_bone(parent, C, axes, theta, rot, out):
    """The bone's local rotation vector after the world rotation R(axes, theta) about its head,
    per frame: D' = A^T Q A D with A = W_parent C, Q = R(axes theta), D = R(rot), bitwise numpy's
    ``(A^T @ Q @ A @ D)`` and ``matrix_to_axis_angle`` (``inference.rotation_kernels``).

    parent : (n, 3, 3) float32, the parent bone's world rotation W_parent per frame
    C      : (3, 3) float64, R_parent^T R_bone (the rest frames)
    axes   : (n, 3) float64 unit axes; theta (n,) float64 radians; rot (n, 3) float32 the bone's
             local rotation vectors
    out    : (n, 3) float32
    """
    m = np.empty((7, 3, 3))  # Wp, A, A^T, Q, D and two products
    Wp, A, At, Q, D, M, M2 = m[0], m[1], m[2], m[3], m[4], m[5], m[6]
    r = np.empty(3)
    for t in range(parent.shape[0]):
        for i in range(3):
            for j in range(3):
                Wp[i, j] = np.float64(parent[t, i, j])
        mul3(Wp, C, A)
        for i in range(3):
            for j in range(3):
                At[i, j] = A[j, i]
        rotvec_matrix(axes[t, 0] * theta[t], axes[t, 1] * theta[t], axes[t, 2] * theta[t], Q)
        rotvec_matrix(np.float64(rot[t, 0]), np.float64(rot[t, 1]), np.float64(rot[t, 2]), D)
        mul3(At, Q, M)
        mul3(M, A, M2)
        mul3(M2, D, M)
        matrix_axis_angle(M, r)
        for c in range(3):
            out[t, c] = np.float32(r[c])
