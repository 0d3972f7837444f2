"""Compiled kernels of ``inference.winding``: the face bins of a batch of frames and the signed ray
crossings at points (numba, no Python objects, one thread).

The maths is the module doc of ``inference.winding``: a ray p + t e_y (t > 0) from each point, the
faces projected onto (u, v) = (x, z), a face f crossed where p's projection is inside f's (edge
functions of the canonical edges, lower vertex id first, ties to the left) and f's depth there is
above p_y; each crossing counts -sign(A2_f) (A2_f: twice f's signed projected area; n_y = -A2).

Bitwise the same arithmetic as that doc's formulas in float64, without fast-math (no FMA
contraction): the two faces of an edge evaluate the same edge function from the same two
vertices, so a ray through an edge is counted once.

Cost per frame of the 27,420-face body (79k cell-face pairs), 5,148 garment points, one thread:
binning ~1.9 ms (two passes), counting ~1.6 ms (~17 candidate faces per point in its cell).
The first call of a process compiles (~5 s) or loads numba's cache (~0.3 s):
``inference.winding.warm_up``.

Units: metres. Arrays: float64 coordinates, int64 vertex ids; the bins: int32 face ids, float32 boxes.
"""
from __future__ import annotations

import numba
import numpy as np

_JIT = {"nogil": True, "cache": True, "fastmath": False}
# Relative widening of the float32 face boxes: float32 rounds a coordinate x by at most
# |x| 2^-24 (6e-8 |x|), so a box widened by 1e-6 (1 + |x|) before the rounding still holds
# every point the float64 box holds; the pre-test only skips faces, the exact test follows.
BOX_SLACK = 1e-6


@numba.njit(**_JIT)
def _cells(u, v, a, c, d, lo_u, lo_v, inv_h):
    """(i0, i1, j0, j1): the cells covered by the projected box of the face with vertices a, c, d;
    i1 < i0 for a face of zero projected area (it never counts)."""
    u0, u1, u2 = u[a], u[c], u[d]
    v0, v1, v2 = v[a], v[c], v[d]
    if (u1 - u0) * (v2 - v0) - (v1 - v0) * (u2 - u0) == 0.0:
        return 1, 0, 1, 0
    i0 = int(np.floor((min(u0, u1, u2) - lo_u) * inv_h))
    i1 = int(np.floor((max(u0, u1, u2) - lo_u) * inv_h))
    j0 = int(np.floor((min(v0, v1, v2) - lo_v) * inv_h))
    j1 = int(np.floor((max(v0, v1, v2) - lo_v) * inv_h))
    return i0, i1, j0, j1


@numba.njit(**_JIT)
def count_pairs(u, v, faces, B, V, inv_h, lo, ni, nj, start):
    """First pass of the binning: start[c + 1] = the number of faces of cell c, then its prefix
    sum (start: (B*ni*nj + 1,) int64, overwritten). Returns the number of (cell, face) pairs.

    u, v  : (B*V,) float64, every frame's projected vertex coordinates x, z (frame b at b*V)
    faces : (F, 3) int64; inv_h: 1 / cell size, 1/metres; lo (B, 2): each frame's grid origin
    (a cell index is floor((x - lo) inv_h), for faces and points alike: monotone in x, so a point
    inside a face's box lands in a cell the face covers)
    """
    F = faces.shape[0]
    cells = ni * nj
    start[:] = 0
    for b in range(B):
        base = b * V
        for f in range(F):
            i0, i1, j0, j1 = _cells(u, v, base + faces[f, 0], base + faces[f, 1], base + faces[f, 2], lo[b, 0], lo[b, 1], inv_h)
            for i in range(i0, i1 + 1):
                for j in range(j0, j1 + 1):
                    start[b * cells + i * nj + j + 1] += 1
    for c in range(B * cells):
        start[c + 1] += start[c]
    return start[B * cells]


@numba.njit(**_JIT)
def fill_pairs(u, v, y, faces, B, V, inv_h, lo, ni, nj, start, fill, cell_face, pair_box):
    """Second pass: the faces of cell c (face ids f of frame b, in increasing order) in
    cell_face[start[c]:start[c + 1]] (int32), each with its face's box (u min, u max, v min,
    v max, y max) in pair_box (float32, widened by BOX_SLACK so that the pre-test of
    ``count_crossings`` stays conservative after the rounding), so that a point's pre-test
    reads memory in order. fill: (B*ni*nj,) int64 scratch."""
    F = faces.shape[0]
    cells = ni * nj
    fill[:] = start[:-1]
    for b in range(B):
        base = b * V
        for f in range(F):
            a, c, d = base + faces[f, 0], base + faces[f, 1], base + faces[f, 2]
            i0, i1, j0, j1 = _cells(u, v, a, c, d, lo[b, 0], lo[b, 1], inv_h)
            if i1 < i0:
                continue
            umin, umax = min(u[a], u[c], u[d]), max(u[a], u[c], u[d])
            vmin, vmax = min(v[a], v[c], v[d]), max(v[a], v[c], v[d])
            ymax = max(y[a], y[c], y[d])
            box0 = np.float32(umin - BOX_SLACK * (1.0 + abs(umin)))
            box1 = np.float32(umax + BOX_SLACK * (1.0 + abs(umax)))
            box2 = np.float32(vmin - BOX_SLACK * (1.0 + abs(vmin)))
            box3 = np.float32(vmax + BOX_SLACK * (1.0 + abs(vmax)))
            box4 = np.float32(ymax + BOX_SLACK * (1.0 + abs(ymax)))
            for i in range(i0, i1 + 1):
                for j in range(j0, j1 + 1):
                    cell = b * cells + i * nj + j
                    s = fill[cell]
                    cell_face[s] = f
                    pair_box[s, 0], pair_box[s, 1], pair_box[s, 2], pair_box[s, 3], pair_box[s, 4] = box0, box1, box2, box3, box4
                    fill[cell] = s + 1


@numba.njit(**_JIT)
def count_crossings(points, frame, u, v, y, faces, edge_lo, edge_hi, opposite, flip, V, inv_h, lo, ni, nj, start, cell_face,
                    pair_box):
    """Winding number at each point: the signed crossings of its ray with the faces of its cell.

    points     : (P, 3) float32 or float64, metres; frame (P,) int64: the frame each point is tested in
    u, v, y    : (B*V,) float64 vertex coordinates (x, z, y); faces (F, 3) int64
    edge_lo, edge_hi, opposite : (F, 3) int64 canonical edge k of each face and the corner opposite
    flip       : (F, 3) bool, edge k runs against the face's own orientation
    inv_h, lo, ni, nj, start, cell_face, pair_box : the grid (``count_pairs``, ``fill_pairs``)
    returns    : (P,) int32
    """
    cells = ni * nj
    P = points.shape[0]
    w = np.zeros(P, np.int32)
    for p in range(P):
        b = frame[p]
        pu, pv, pyy = np.float64(points[p, 0]), np.float64(points[p, 2]), np.float64(points[p, 1])
        i = int(np.floor((pu - lo[b, 0]) * inv_h))
        j = int(np.floor((pv - lo[b, 1]) * inv_h))
        if i < 0 or i >= ni or j < 0 or j >= nj:
            continue
        c = b * cells + i * nj + j
        total = 0
        base = b * V
        for s in range(start[c], start[c + 1]):
            # cheap pre-test: the projected box holds p and the face reaches above p
            if pu < pair_box[s, 0] or pu > pair_box[s, 1] or pv < pair_box[s, 2] or pv > pair_box[s, 3] or pair_box[s, 4] <= pyy:
                continue
            f = cell_face[s]
            a, q, r = base + faces[f, 0], base + faces[f, 1], base + faces[f, 2]
            u0, v0 = u[a], v[a]
            A2 = (u[q] - u0) * (v[r] - v0) - (v[q] - v0) * (u[r] - u0)
            ccw = A2 > 0.0
            hit = True
            depth = 0.0
            for k in range(3):
                lo_k, hi_k = base + edge_lo[f, k], base + edge_hi[f, k]
                e0u, e0v = u[lo_k], v[lo_k]
                du, dv = u[hi_k] - e0u, v[hi_k] - e0v
                E = du * (pv - e0v) - dv * (pu - e0u)
                if ((E >= 0.0) ^ flip[f, k]) != ccw:
                    hit = False
                    break
                Et = -E if flip[f, k] else E
                depth = depth + Et * (y[base + opposite[f, k]] - pyy)
            if hit and ((depth > 0.0) == ccw):
                total += -1 if ccw else 1
        w[p] = total
    return w
