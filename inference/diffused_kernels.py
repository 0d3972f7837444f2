"""Compiled trilinear interpolation of ``inference.diffused.BandGrid`` (numba, one thread).

The maths is ``inference.diffused``'s module doc: a point p reads the fine cell holding it,

    f(p) = sum over its 8 corners c of  prod_i w_i(c) f(c),   u = (p - origin) / h clamped to the box,
    i0 = min(floor(u), dims - 2), t = u - i0, w_i = 1 - t_i (lower corner) or t_i (upper),

where f(c) is the fine table's row for a corner on the band and, for a corner off the band, the
coarse grid's trilinear value at the corner's position (continuous across the band's edge).
float32 weights as the numpy version computes them; the sums accumulate in float32 too.

Cost (``python bench/bench_canonical.py``): W~ and the SDF (25 channels) and B~s (3 channels) at
5,148 points of 30 frames: see docs/benchmarks.md.

Units: metres. Arrays: float32 points and tables, int64 dims.
"""
from __future__ import annotations

import numba
import numpy as np

_JIT = {"nogil": True, "cache": True, "fastmath": False}


@numba.njit(**_JIT)
def _cell(p0, p1, p2, origin, inv_h, dims):
    """The lowest corner (i, j, k) of the cell holding a point and its fractions (t0, t1, t2)."""
    u0 = min(max((p0 - origin[0]) * inv_h, np.float32(0.0)), np.float32(dims[0] - 1))
    u1 = min(max((p1 - origin[1]) * inv_h, np.float32(0.0)), np.float32(dims[1] - 1))
    u2 = min(max((p2 - origin[2]) * inv_h, np.float32(0.0)), np.float32(dims[2] - 1))
    i = min(int(u0), dims[0] - 2)
    j = min(int(u1), dims[1] - 2)
    k = min(int(u2), dims[2] - 2)
    return i, j, k, u0 - np.float32(i), u1 - np.float32(j), u2 - np.float32(k)


@numba.njit(**_JIT)
def _coarse_add(out, n, scale, q0, q1, q2, origin, inv_h, dims, table):
    """out[n] += scale * (the coarse grid's trilinear value at q)."""
    i, j, k, t0, t1, t2 = _cell(q0, q1, q2, origin, inv_h, dims)
    C = table.shape[1]
    for c in range(8):
        a, b, d = c >> 2, (c >> 1) & 1, c & 1
        w = (t0 if a else np.float32(1.0) - t0) * (t1 if b else np.float32(1.0) - t1) * (t2 if d else np.float32(1.0) - t2)
        w = w * scale
        row = ((i + a) * dims[1] + (j + b)) * dims[2] + (k + d)
        for ch in range(C):
            out[n, ch] += w * table[row, ch]


@numba.njit(**_JIT)
def band_interpolate(points, origin, fine_h, fine_inv_h, fine_dims, band_row, fine, coarse_inv_h, coarse_dims, coarse):
    """The fields of ``fine`` (n_band, C) and ``coarse`` (n_coarse, C) at points (N, 3) -> (N, C).

    origin      : (3,) float32, both grids' corner; fine_h: the fine spacing, metres, fine_inv_h:
                  float32(1 / fine_h)
    fine_dims   : (3,) int64 fine nodes per axis; band_row: (nodes,) int32 fine flat id -> table
                  row, -1 off the band
    coarse_inv_h: 1 / the coarse spacing; coarse_dims (3,) int64
    """
    out = np.zeros((points.shape[0], fine.shape[1]), np.float32)
    _interpolate(points, origin, fine_h, fine_inv_h, fine_dims, band_row, fine, coarse_inv_h, coarse_dims, coarse, out,
                 fine[:, :0], coarse[:, :0], out[:, :0])
    return out


@numba.njit(**_JIT)
def band_interpolate_pair(points, origin, fine_h, fine_inv_h, fine_dims, band_row, fine, coarse_inv_h, coarse_dims, coarse,
                          fine2, coarse2):
    """``band_interpolate`` of two tables at the same points, (N, C) and (N, C2), each point's cell
    and corner weights found once; each table's values are bitwise those of its own call."""
    out = np.zeros((points.shape[0], fine.shape[1]), np.float32)
    out2 = np.zeros((points.shape[0], fine2.shape[1]), np.float32)
    _interpolate(points, origin, fine_h, fine_inv_h, fine_dims, band_row, fine, coarse_inv_h, coarse_dims, coarse, out,
                 fine2, coarse2, out2)
    return out, out2


@numba.njit(**_JIT)
def _interpolate(points, origin, fine_h, fine_inv_h, fine_dims, band_row, fine, coarse_inv_h, coarse_dims, coarse, out,
                 fine2, coarse2, out2):
    """out[n] (+)= the first table's field at point n, out2[n] the second's (zero channels: none)."""
    N = points.shape[0]
    C, C2 = fine.shape[1], fine2.shape[1]
    for n in range(N):
        i, j, k, t0, t1, t2 = _cell(points[n, 0], points[n, 1], points[n, 2], origin, fine_inv_h, fine_dims)
        for c in range(8):
            a, b, d = c >> 2, (c >> 1) & 1, c & 1
            w = (t0 if a else np.float32(1.0) - t0) * (t1 if b else np.float32(1.0) - t1) * (t2 if d else np.float32(1.0) - t2)
            r = band_row[((i + a) * fine_dims[1] + (j + b)) * fine_dims[2] + (k + d)]
            if r >= 0:
                for ch in range(C):
                    out[n, ch] += w * fine[r, ch]
                for ch in range(C2):
                    out2[n, ch] += w * fine2[r, ch]
            else:
                q0 = origin[0] + np.float32(fine_h) * np.float32(i + a)
                q1 = origin[1] + np.float32(fine_h) * np.float32(j + b)
                q2 = origin[2] + np.float32(fine_h) * np.float32(k + d)
                _coarse_add(out, n, w, q0, q1, q2, origin, coarse_inv_h, coarse_dims, coarse)
                if C2:
                    _coarse_add(out2, n, w, q0, q1, q2, origin, coarse_inv_h, coarse_dims, coarse2)


@numba.njit(**_JIT)
def blend_pose(weights, shaped, transforms, out):
    """Eq. 6.7's blend at every point of every frame: w = max(W~, 0) / sum (the weights over the
    kept bones, clamped and normalised), then

        out[t, v] = sum_k w_k A_tk[:, :3] shaped[t, v] + sum_k w_k A_tk[:, 3],

    the bones with no weight at the point skipped (~5 of ~23 carry one). The sums run in float64
    and are rounded once.

    weights    : (T, V, C) float32, W~ over the kept bones in the first K = transforms.shape[1]
                 channels (later channels, the SDF, are not read)
    shaped     : (T, V, 3) float32, X + B~s(X, beta), metres
    transforms : (T, K, 12) float32, the kept bones' skinning transforms, rows of 3 x 4
    out        : (T, V, 3) float32, metres
    """
    T, V, K = weights.shape[0], weights.shape[1], transforms.shape[1]
    A = np.empty(12)
    for t in range(T):
        for v in range(V):
            s = 0.0
            for k in range(K):
                s += max(np.float64(weights[t, v, k]), 0.0)
            inv = 1.0 / max(s, 1e-12)
            for c in range(12):
                A[c] = 0.0
            for k in range(K):
                w = np.float64(weights[t, v, k])
                if w > 0.0:
                    for c in range(12):
                        A[c] += w * transforms[t, k, c]
            x, y, z = np.float64(shaped[t, v, 0]), np.float64(shaped[t, v, 1]), np.float64(shaped[t, v, 2])
            for r in range(3):
                out[t, v, r] = np.float32((A[4 * r] * x + A[4 * r + 1] * y + A[4 * r + 2] * z + A[4 * r + 3]) * inv)
