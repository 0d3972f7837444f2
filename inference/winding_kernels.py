"""Compiled kernels of ``inference.winding``: the face bins of a batch of frames and the signed ray
crossings at points (numba, no Python objects, one thread).

The maths is the module doc of ``inference.winding``: a ray p + t e_y (t > 0) from each point, the
faces projected onto (u, v) = (x, z), a face f crossed where p's projection is inside f's (edge
functions of the canonical edges, lower vertex id first) and f's depth there is above p_y; each
crossing counts -sign(A2_f) (A2_f: twice f's signed projected area; n_y = -A2). A point on an
edge's line (E = 0) takes the side the point moved by (eps, eps^2) would have, eps -> 0: that of
-dv, else of du (E grows by du eps^2 - dv eps). The two faces of an edge see the same canonical
edge, so a ray through it counts once; the faces around a vertex see the one moved point, so a
ray through a vertex counts as a ray beside it does (a point 2 mm inside a slab, straight under
its middle vertex, counted 0 with ties always to the left).

Bitwise the same arithmetic as that doc's formulas in float64, without fast-math (no FMA
contraction): the two faces of an edge evaluate the same edge function from the same two
vertices, so a ray through an edge is counted once.

Cost per frame of the 27,420-face body (79k cell-face pairs), 5,148 garment points, one thread:
binning ~1.8 ms (two passes), counting ~0.7 ms (~17 candidate faces per point in its cell, ~1.2 of
them past the box pre-test).
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
# The count of a point outside a grid's region (``count_crossings``).
UNKNOWN = -(2**30)


@numba.njit(inline="always", **_JIT)
def _cells(u, v, u2, v2, a, c, d, lo_u, lo_v, inv_h, r0, r1, r2, r3, ni, nj):
    """(i0, i1, j0, j1): the cells covered by the projected box of the face with vertices a, c, d
    in both vertex sets (u, v) and (u2, v2) (the same arrays when a grid holds one mesh), clipped
    to the grid's ni x nj cells; i1 < i0 for a face of zero projected area in both (it never
    counts) or one whose box misses the frame's region (r0, r1, r2, r3) = (u min, u max, v min, v max)."""
    u0, u1, u2_ = u[a], u[c], u[d]
    v0, v1, v2_ = v[a], v[c], v[d]
    s0, s1, s2 = u2[a], u2[c], u2[d]
    t0, t1, t2 = v2[a], v2[c], v2[d]
    umin, umax = min(u0, u1, u2_, s0, s1, s2), max(u0, u1, u2_, s0, s1, s2)
    vmin, vmax = min(v0, v1, v2_, t0, t1, t2), max(v0, v1, v2_, t0, t1, t2)
    if umax < r0 or umin > r1 or vmax < r2 or vmin > r3:  # first: most faces a garment's region leaves out
        return 1, 0, 1, 0
    if (u1 - u0) * (v2_ - v0) - (v1 - v0) * (u2_ - u0) == 0.0 and (s1 - s0) * (t2 - t0) - (t1 - t0) * (s2 - s0) == 0.0:
        return 1, 0, 1, 0
    i0 = max(int(np.floor((umin - lo_u) * inv_h)), 0)
    i1 = min(int(np.floor((umax - lo_u) * inv_h)), ni - 1)
    j0 = max(int(np.floor((vmin - lo_v) * inv_h)), 0)
    j1 = min(int(np.floor((vmax - lo_v) * inv_h)), nj - 1)
    return i0, i1, j0, j1


@numba.njit(**_JIT)
def count_pairs(u, v, u2, v2, faces, B, V, inv_h, lo, ni, nj, region, start):
    """First pass of the binning: start[c + 1] = the number of faces of cell c, then its prefix
    sum (start: (B*ni*nj + 1,) int64, overwritten). Returns the number of (cell, face) pairs.

    u, v  : (B*V,) float64, every frame's projected vertex coordinates x, z (frame b at b*V)
    u2, v2: the same of a second vertex set of the same faces, binned with it (each face over
            the box of both of its projections), or u, v themselves
    faces : (F, 3) int64; inv_h: 1 / cell size, 1/metres; lo (B, 2): each frame's grid origin;
    region (B, 4): each frame's (u min, u max, v min, v max), the faces binned are those whose
    box meets it (a point outside it is answered by no cell: ``count_crossings``)
    (a cell index is floor((x - lo) inv_h), for faces and points alike: monotone in x, so a point
    inside a face's box lands in a cell the face covers)
    """
    F = faces.shape[0]
    cells = ni * nj
    start[:] = 0
    for b in range(B):
        base = b * V
        lo_u, lo_v, r0, r1, r2, r3 = lo[b, 0], lo[b, 1], region[b, 0], region[b, 1], region[b, 2], region[b, 3]
        for f in range(F):
            i0, i1, j0, j1 = _cells(u, v, u2, v2, base + faces[f, 0], base + faces[f, 1], base + faces[f, 2], lo_u, lo_v, inv_h,
                                    r0, r1, r2, r3, ni, nj)
            for i in range(i0, i1 + 1):
                for j in range(j0, j1 + 1):
                    start[b * cells + i * nj + j + 1] += 1
    for c in range(B * cells):
        start[c + 1] += start[c]
    return start[B * cells]


@numba.njit(**_JIT)
def fill_pairs(u, v, y, u2, v2, y2, faces, B, V, inv_h, lo, ni, nj, region, start, fill, cell_face, pair_box):
    """Second pass: the faces of cell c (face ids f of frame b, in increasing order) in
    cell_face[start[c]:start[c + 1]] (int32), each with its face's box (u min, u max, v min,
    v max, y max, y min; over both vertex sets, as ``count_pairs``) in pair_box (float32, widened by BOX_SLACK so that the pre-test of
    ``count_crossings`` stays conservative after the rounding), so that a point's pre-test
    reads memory in order. fill: (B*ni*nj,) int64 scratch."""
    F = faces.shape[0]
    cells = ni * nj
    fill[:] = start[:-1]
    for b in range(B):
        base = b * V
        lo_u, lo_v, r0, r1, r2, r3 = lo[b, 0], lo[b, 1], region[b, 0], region[b, 1], region[b, 2], region[b, 3]
        for f in range(F):
            a, c, d = base + faces[f, 0], base + faces[f, 1], base + faces[f, 2]
            i0, i1, j0, j1 = _cells(u, v, u2, v2, a, c, d, lo_u, lo_v, inv_h, r0, r1, r2, r3, ni, nj)
            if i1 < i0:
                continue
            umin, umax = min(u[a], u[c], u[d], u2[a], u2[c], u2[d]), max(u[a], u[c], u[d], u2[a], u2[c], u2[d])
            vmin, vmax = min(v[a], v[c], v[d], v2[a], v2[c], v2[d]), max(v[a], v[c], v[d], v2[a], v2[c], v2[d])
            ymax = max(y[a], y[c], y[d], y2[a], y2[c], y2[d])
            ymin = min(y[a], y[c], y[d], y2[a], y2[c], y2[d])
            box0 = np.float32(umin - BOX_SLACK * (1.0 + abs(umin)))
            box1 = np.float32(umax + BOX_SLACK * (1.0 + abs(umax)))
            box2 = np.float32(vmin - BOX_SLACK * (1.0 + abs(vmin)))
            box3 = np.float32(vmax + BOX_SLACK * (1.0 + abs(vmax)))
            box4 = np.float32(ymax + BOX_SLACK * (1.0 + abs(ymax)))
            box5 = np.float32(ymin - BOX_SLACK * (1.0 + abs(ymin)))
            for i in range(i0, i1 + 1):
                for j in range(j0, j1 + 1):
                    cell = b * cells + i * nj + j
                    s = fill[cell]
                    cell_face[s] = f
                    pair_box[s, 0], pair_box[s, 1], pair_box[s, 2], pair_box[s, 3], pair_box[s, 4] = box0, box1, box2, box3, box4
                    pair_box[s, 5] = box5
                    fill[cell] = s + 1


@numba.njit(inline="always", **_JIT)
def _crossing(pu, pv, pyy, up, f, base, u, v, y, faces, edge_lo, edge_hi, opposite, flip):
    """The signed crossing (-1, 0 or +1) of the ray from (pu, pyy, pv) along +y (``up``) or -y with
    face f of the frame at vertex offset ``base``: inside the face's projection by its canonical
    edge functions and the face above (below) the point (module doc; the -y ray is the mirror
    image: the face's side and the crossing's sign both flip)."""
    a, q, r = base + faces[f, 0], base + faces[f, 1], base + faces[f, 2]
    u0, v0 = u[a], v[a]
    A2 = (u[q] - u0) * (v[r] - v0) - (v[q] - v0) * (u[r] - u0)
    if A2 == 0.0:  # no area (binned for the other vertex set of the grid, if at all)
        return 0
    ccw = A2 > 0.0
    depth = 0.0
    for k in range(3):
        lo_k, hi_k = base + edge_lo[f, k], base + edge_hi[f, k]
        e0u, e0v = u[lo_k], v[lo_k]
        du, dv = u[hi_k] - e0u, v[hi_k] - e0v
        E = du * (pv - e0v) - dv * (pu - e0u)
        # the side of the point moved by (eps, eps^2) in (u, v), eps -> 0: E's own sign, else (on
        # the edge's line) that of -dv, else of du (module doc)
        left = (E > 0.0) | ((E == 0.0) & ((dv < 0.0) | ((dv == 0.0) & (du > 0.0))))  # no branch: | and &, not or and and
        if (left ^ flip[f, k]) != ccw:
            return 0
        Et = -E if flip[f, k] else E
        depth = depth + Et * (y[base + opposite[f, k]] - pyy)
    if up:
        if (depth > 0.0) == ccw:
            return -1 if ccw else 1
    elif (depth < 0.0) == ccw:
        return 1 if ccw else -1
    return 0


@numba.njit(**_JIT)
def count_crossings(points, frame, down, u, v, y, u2, v2, y2, faces, edge_lo, edge_hi, opposite, flip, V, inv_h, lo, ni, nj, region,
                    bounded, start, cell_face, pair_box, either):
    """Winding number at each point: the signed crossings of its ray with the faces of its cell.

    points     : (P, 3) float32 or float64, metres; frame (P,) int64: the frame each point is tested in
    down       : (P,) bool, the point's ray runs along -y (else +y): any ray gives the winding number
                 of a closed mesh; one leaving the body at once meets fewer faces
    u, v, y    : (B*V,) float64 vertex coordinates (x, z, y), one vertex set the grid was binned
                 with; faces (F, 3) int64
    u2, v2, y2 : the grid's other vertex set, read only if ``either``: then the larger of the two
                 winding numbers (a point inside either mesh counts as inside), in the same pass
    edge_lo, edge_hi, opposite : (F, 3) int64 canonical edge k of each face and the corner opposite
    flip       : (F, 3) bool, edge k runs against the face's own orientation
    inv_h, lo, ni, nj, region, start, cell_face, pair_box : the grid (``count_pairs``, ``fill_pairs``)
    bounded    : the region is smaller than the mesh: a point outside it gets UNKNOWN (else 0:
                 no face is there)
    returns    : (P,) int32
    """
    cells = ni * nj
    P = points.shape[0]
    w = np.zeros(P, np.int32)
    for p in range(P):
        b = frame[p]
        pu, pv, pyy = np.float64(points[p, 0]), np.float64(points[p, 2]), np.float64(points[p, 1])
        if not (region[b, 0] <= pu <= region[b, 1] and region[b, 2] <= pv <= region[b, 3]):
            w[p] = UNKNOWN if bounded else 0
            continue
        i = int(np.floor((pu - lo[b, 0]) * inv_h))
        j = int(np.floor((pv - lo[b, 1]) * inv_h))
        if i < 0 or i >= ni or j < 0 or j >= nj:
            continue
        c = b * cells + i * nj + j
        total, total2 = 0, 0
        base = b * V
        up = not down[p]
        for s in range(start[c], start[c + 1]):
            # cheap pre-test: the projected box holds p and the face reaches above (below) p; the
            # five comparisons joined by | (no short circuit), so that a face costs one branch,
            # not up to five hard-to-predict ones (0.79 against 1.38 ms a frame)
            miss = ((pu < pair_box[s, 0]) | (pu > pair_box[s, 1]) | (pv < pair_box[s, 2]) | (pv > pair_box[s, 3])
                    | ((pair_box[s, 4] <= pyy) if up else (pair_box[s, 5] >= pyy)))
            if miss:
                continue
            f = cell_face[s]
            total += _crossing(pu, pv, pyy, up, f, base, u, v, y, faces, edge_lo, edge_hi, opposite, flip)
            if either:
                total2 += _crossing(pu, pv, pyy, up, f, base, u2, v2, y2, faces, edge_lo, edge_hi, opposite, flip)
        w[p] = max(total, total2) if either else total
    return w


@numba.njit(**_JIT)
def inflate(x, faces, distance, out):
    """out[b, v] = x[b, v] + distance n_v: n_v the unit area-weighted vertex normal of frame b (the
    sum of its faces' (x1 - x0) x (x2 - x0)); a vertex without area keeps its place. x, out:
    (B, V, 3) float32; faces (F, 3) int64."""
    B, V = x.shape[0], x.shape[1]
    n = np.zeros((V, 3), np.float64)
    for b in range(B):
        n[:] = 0.0
        for f in range(faces.shape[0]):
            i, j, k = faces[f, 0], faces[f, 1], faces[f, 2]
            ax, ay, az = x[b, j, 0] - x[b, i, 0], x[b, j, 1] - x[b, i, 1], x[b, j, 2] - x[b, i, 2]
            bx, by, bz = x[b, k, 0] - x[b, i, 0], x[b, k, 1] - x[b, i, 1], x[b, k, 2] - x[b, i, 2]
            nx, ny, nz = ay * bz - az * by, az * bx - ax * bz, ax * by - ay * bx
            for c in (i, j, k):
                n[c, 0] += nx
                n[c, 1] += ny
                n[c, 2] += nz
        for v in range(V):
            length = (n[v, 0] ** 2 + n[v, 1] ** 2 + n[v, 2] ** 2) ** 0.5
            s = distance / length if length > 1e-24 else 0.0
            for c in range(3):
                out[b, v, c] = x[b, v, c] + s * n[v, c]
