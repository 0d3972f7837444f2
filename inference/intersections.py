"""Intersecting triangle pairs between two meshes, exactly (no sampling): the layers of an outfit.

Two triangles in general position intersect iff an edge of one crosses the other. A segment pq
crosses the triangle abc iff p and q lie on opposite sides of abc's plane and the line pq passes
inside abc's three edges:

    o(a, b, c, p) o(a, b, c, q) < 0   and   o(p, q, a, b), o(p, q, b, c), o(p, q, c, a) all of one sign,

with o(a, b, c, d) = (b - a) x (c - a) . (d - a), six times the signed volume of abcd, evaluated in
float64. Coplanar or touching pairs (a zero among the signs) do not count: they have measure zero,
and a garment layer lying exactly on another is not an intersection a viewer sees.

The outer mesh's triangles are binned once per frame into a uniform grid (cell CELL_EDGES median
edge lengths) by their bounding boxes; each inner triangle tests the outer ones of the cells its
box covers whose boxes overlap its own, each pair once (in the lowest cell both boxes cover).
Compiled with numba (one thread): ~5 ms per frame for the T-shirt (10,096 faces) inside the
jacket (12,440); a box pre-test without a branch (``_apart``) took it from ~7.5. Measured with it (``python tools/outfit_layers.py``, 02_02 frames 30-50, the
whole pipeline): T-shirt under jacket, both fit 'canonical', 442-821 intersecting pairs per
frame (max 1,458); both retargeted 1,277-1,568 (max 2,001); in the rest pose, 0.

Units: metres. Shapes: batch first, (T, V, 3) frames.
"""
from __future__ import annotations

import numba
import numpy as np

from inference.errors import InputShapeError
from inference.winding import check_faces

# Grid cell, in multiples of the outer mesh's median edge length.
CELL_EDGES = 2.0

_JIT = {"nogil": True, "cache": True, "fastmath": False}


@numba.njit(**_JIT)
def _orient(a0, a1, a2, b0, b1, b2, c0, c1, c2, d0, d1, d2):
    """(b - a) x (c - a) . (d - a)."""
    u0, u1, u2 = b0 - a0, b1 - a1, b2 - a2
    v0, v1, v2 = c0 - a0, c1 - a1, c2 - a2
    w0, w1, w2 = d0 - a0, d1 - a1, d2 - a2
    return (u1 * v2 - u2 * v1) * w0 + (u2 * v0 - u0 * v2) * w1 + (u0 * v1 - u1 * v0) * w2


@numba.njit(**_JIT)
def _segment_crosses(P, p, q, T, a, b, c):
    """Segment P[p] P[q] crosses triangle T[a] T[b] T[c] (module doc; zeros do not count)."""
    sp = _orient(T[a, 0], T[a, 1], T[a, 2], T[b, 0], T[b, 1], T[b, 2], T[c, 0], T[c, 1], T[c, 2], P[p, 0], P[p, 1], P[p, 2])
    sq = _orient(T[a, 0], T[a, 1], T[a, 2], T[b, 0], T[b, 1], T[b, 2], T[c, 0], T[c, 1], T[c, 2], P[q, 0], P[q, 1], P[q, 2])
    if not ((sp > 0.0 and sq < 0.0) or (sp < 0.0 and sq > 0.0)):
        return False
    e0 = _orient(P[p, 0], P[p, 1], P[p, 2], P[q, 0], P[q, 1], P[q, 2], T[a, 0], T[a, 1], T[a, 2], T[b, 0], T[b, 1], T[b, 2])
    e1 = _orient(P[p, 0], P[p, 1], P[p, 2], P[q, 0], P[q, 1], P[q, 2], T[b, 0], T[b, 1], T[b, 2], T[c, 0], T[c, 1], T[c, 2])
    e2 = _orient(P[p, 0], P[p, 1], P[p, 2], P[q, 0], P[q, 1], P[q, 2], T[c, 0], T[c, 1], T[c, 2], T[a, 0], T[a, 1], T[a, 2])
    return (e0 > 0.0 and e1 > 0.0 and e2 > 0.0) or (e0 < 0.0 and e1 < 0.0 and e2 < 0.0)


@numba.njit(**_JIT)
def _triangles_intersect(A, fa, B, fb):
    """Triangle fa (3 vertex ids into A) and triangle fb (into B) intersect."""
    for k in range(3):
        if _segment_crosses(A, fa[k], fa[(k + 1) % 3], B, fb[0], fb[1], fb[2]):
            return True
        if _segment_crosses(B, fb[k], fb[(k + 1) % 3], A, fa[0], fa[1], fa[2]):
            return True
    return False


@numba.njit(**_JIT)
def _box(V, f):
    lo0, lo1, lo2 = V[f[0], 0], V[f[0], 1], V[f[0], 2]
    hi0, hi1, hi2 = lo0, lo1, lo2
    for k in range(1, 3):
        lo0, lo1, lo2 = min(lo0, V[f[k], 0]), min(lo1, V[f[k], 1]), min(lo2, V[f[k], 2])
        hi0, hi1, hi2 = max(hi0, V[f[k], 0]), max(hi1, V[f[k], 1]), max(hi2, V[f[k], 2])
    return lo0, lo1, lo2, hi0, hi1, hi2


@numba.njit(inline="always", **_JIT)
def _apart(boxes, f, lo0, lo1, lo2, hi0, hi1, hi2):
    """Face f's box (boxes[f]: lo, hi) and the box lo-hi are disjoint: some gap lo_b - hi or
    lo - hi_b is positive (the sign of a float difference is exact, so this is the six comparisons
    boxes[f, 0] > hi0, ... exactly). One max of the six, without a branch: the short-circuit
    comparisons' unpredictable exits cost ~7 ns a face (a segment's ~25 faces, 5,148 T-shirt
    segments against the jacket: 1.2 -> 0.5 ms of box tests a frame)."""
    return max(max(max(boxes[f, 0] - hi0, lo0 - boxes[f, 3]), max(boxes[f, 1] - hi1, lo1 - boxes[f, 4])),
               max(boxes[f, 2] - hi2, lo2 - boxes[f, 5])) > 0.0


@numba.njit(**_JIT)
def _cell_range(lo, hi, origin, inv_h, n):
    i0 = min(max(int(np.floor((lo - origin) * inv_h)), 0), n - 1)
    i1 = min(max(int(np.floor((hi - origin) * inv_h)), 0), n - 1)
    return i0, i1


@numba.njit(inline="always", **_JIT)
def _next_cell(i, j, k, b0, b1, c0, c1):
    """The cell after (i, j, k) in a box of cells [., .] x [b0, b1] x [c0, c1], k fastest."""
    k += 1
    if k > c1:
        k = c0
        j += 1
        if j > b1:
            j = b0
            i += 1
    return i, j, k


@numba.njit(**_JIT)
def _bin_faces(B, Fb, h):
    """Bin the faces Fb of B into a uniform grid of cell h by their boxes: returns origin (3,),
    top (3,), dims (3,), boxes (Fb, 6) lo/hi, cells (Fb, 6) i0, i1, j0, j1, k0, k1, and the CSR
    start (cells + 1,) / members of each cell's faces."""
    nB = Fb.shape[0]
    origin = np.empty(3)
    top = np.empty(3)
    for d in range(3):
        origin[d] = B[:, d].min()
        top[d] = B[:, d].max()
    inv_h = 1.0 / h
    dims = np.empty(3, np.int64)
    for d in range(3):
        dims[d] = int(np.floor((top[d] - origin[d]) * inv_h)) + 1
    n0, n1, n2 = dims[0], dims[1], dims[2]
    boxes = np.empty((nB, 6), np.float64)
    cells = np.empty((nB, 6), np.int64)
    start = np.zeros(n0 * n1 * n2 + 1, np.int64)
    for f in range(nB):
        lo0, lo1, lo2, hi0, hi1, hi2 = _box(B, Fb[f])
        boxes[f, 0], boxes[f, 1], boxes[f, 2], boxes[f, 3], boxes[f, 4], boxes[f, 5] = lo0, lo1, lo2, hi0, hi1, hi2
        cells[f, 0], cells[f, 1] = _cell_range(lo0, hi0, origin[0], inv_h, n0)
        cells[f, 2], cells[f, 3] = _cell_range(lo1, hi1, origin[1], inv_h, n1)
        cells[f, 4], cells[f, 5] = _cell_range(lo2, hi2, origin[2], inv_h, n2)
        # the box's cells walked as one loop, k fastest, not three nested loops of one or two
        # steps each, whose exits the CPU cannot predict (the jacket's 12,440 faces: 0.65 -> 0.55 ms)
        a0, a1, b0, b1, c0, c1 = cells[f, 0], cells[f, 1], cells[f, 2], cells[f, 3], cells[f, 4], cells[f, 5]
        i, j, k = a0, b0, c0
        for _ in range((a1 - a0 + 1) * (b1 - b0 + 1) * (c1 - c0 + 1)):
            start[(i * n1 + j) * n2 + k + 1] += 1
            i, j, k = _next_cell(i, j, k, b0, b1, c0, c1)
    for c in range(n0 * n1 * n2):
        start[c + 1] += start[c]
    members = np.empty(start[-1], np.int64)
    fill = start[:-1].copy()
    for f in range(nB):
        a0, a1, b0, b1, c0, c1 = cells[f, 0], cells[f, 1], cells[f, 2], cells[f, 3], cells[f, 4], cells[f, 5]
        i, j, k = a0, b0, c0
        for _ in range((a1 - a0 + 1) * (b1 - b0 + 1) * (c1 - c0 + 1)):
            c = (i * n1 + j) * n2 + k
            members[fill[c]] = f
            fill[c] += 1
            i, j, k = _next_cell(i, j, k, b0, b1, c0, c1)
    return origin, top, dims, boxes, cells, start, members


@numba.njit(**_JIT)
def intersecting_faces(A, Fa, B, Fb, h):
    """Per inner face (Fa rows) the number of outer faces (Fb rows) it intersects, (Fa,) int32.

    A (Va, 3), B (Vb, 3) float64 vertices; Fa, Fb int64 faces; h: cell size, metres.
    """
    nA, nB = Fa.shape[0], Fb.shape[0]
    out = np.zeros(nA, np.int32)
    if nA == 0 or nB == 0:
        return out
    origin, top, dims, boxes, cells, start, members = _bin_faces(B, Fb, h)
    n0, n1, n2 = dims[0], dims[1], dims[2]
    inv_h = 1.0 / h
    for g in range(nA):
        lo0, lo1, lo2, hi0, hi1, hi2 = _box(A, Fa[g])
        if hi0 < origin[0] or lo0 > top[0] or hi1 < origin[1] or lo1 > top[1] or hi2 < origin[2] or lo2 > top[2]:
            continue
        i0, i1 = _cell_range(lo0, hi0, origin[0], inv_h, n0)
        j0, j1 = _cell_range(lo1, hi1, origin[1], inv_h, n1)
        k0, k1 = _cell_range(lo2, hi2, origin[2], inv_h, n2)
        total = 0
        for i in range(i0, i1 + 1):
            for j in range(j0, j1 + 1):
                for k in range(k0, k1 + 1):
                    c = (i * n1 + j) * n2 + k
                    for s in range(start[c], start[c + 1]):
                        f = members[s]
                        if _apart(boxes, f, lo0, lo1, lo2, hi0, hi1, hi2):
                            continue
                        # each pair once: in the lowest cell both boxes cover
                        if i != max(i0, cells[f, 0]) or j != max(j0, cells[f, 2]) or k != max(k0, cells[f, 4]):
                            continue
                        if _triangles_intersect(A, Fa[g], B, Fb[f]):
                            total += 1
        out[g] = total
    return out


@numba.njit(**_JIT)
def first_crossings(P, Q, B, Fb, h, exiting):
    """Segments P[n] -> Q[n] against the triangles Fb of B (module doc's crossing test): the
    number of triangles each crosses, (N,) int32, the segment parameter in [0, 1] of its crossing
    nearest P, (N,) float64 (2.0 where none), and that triangle's row in Fb, (N,) int64 (-1).
    P, Q (N, 3), B (Vb, 3) float64; h: cell; exiting: only the crossings from a triangle's back
    to its front (P behind its plane: the normal (b - a) x (c - a) points toward Q, out of a
    layer whose faces wind outward)."""
    if P.shape[0] == 0 or Fb.shape[0] == 0:
        return np.zeros(P.shape[0], np.int32), np.full(P.shape[0], 2.0), np.full(P.shape[0], -1, np.int64)
    return binned_crossings(P, Q, B, Fb, h, _bin_faces(B, Fb, h), exiting)


@numba.njit(**_JIT)
def binned_crossings(P, Q, B, Fb, h, grid, exiting, any_only=False):
    """``first_crossings`` with the faces already binned: grid = _bin_faces(B, Fb, h) (so that
    several queries against one frame of a layer share it). The cell walk is written out as in
    ``intersecting_faces`` rather than shared: a shared candidate list (a helper filling a buffer)
    made this query 1.6-2x slower (0.83 -> 1.3-1.8 ms for 5,148 segments against the jacket).
    any_only: a segment's walk stops at its first crossing found (count 1; first and face that
    crossing's, not the nearest): whether it crosses at all, for less."""
    origin, top, dims, boxes, cells, start, members = grid
    N = P.shape[0]
    count = np.zeros(N, np.int32)
    first = np.full(N, 2.0)
    face = np.full(N, -1, np.int64)
    if N == 0 or Fb.shape[0] == 0:
        return count, first, face
    n0, n1, n2 = dims[0], dims[1], dims[2]
    inv_h = 1.0 / h
    S = np.empty((2, 3))
    for g in range(N):
        done = False
        for d in range(3):
            S[0, d] = P[g, d]
            S[1, d] = Q[g, d]
        lo0, hi0 = min(S[0, 0], S[1, 0]), max(S[0, 0], S[1, 0])
        lo1, hi1 = min(S[0, 1], S[1, 1]), max(S[0, 1], S[1, 1])
        lo2, hi2 = min(S[0, 2], S[1, 2]), max(S[0, 2], S[1, 2])
        if hi0 < origin[0] or lo0 > top[0] or hi1 < origin[1] or lo1 > top[1] or hi2 < origin[2] or lo2 > top[2]:
            continue
        i0, i1 = _cell_range(lo0, hi0, origin[0], inv_h, n0)
        j0, j1 = _cell_range(lo1, hi1, origin[1], inv_h, n1)
        k0, k1 = _cell_range(lo2, hi2, origin[2], inv_h, n2)
        for i in range(i0, i1 + 1):
            for j in range(j0, j1 + 1):
                for k in range(k0, k1 + 1):
                    c = (i * n1 + j) * n2 + k
                    for s in range(start[c], start[c + 1]):
                        f = members[s]
                        if _apart(boxes, f, lo0, lo1, lo2, hi0, hi1, hi2):
                            continue
                        if i != max(i0, cells[f, 0]) or j != max(j0, cells[f, 2]) or k != max(k0, cells[f, 4]):
                            continue
                        a, b, cc = Fb[f, 0], Fb[f, 1], Fb[f, 2]
                        if _segment_crosses(S, 0, 1, B, a, b, cc):
                            sp = _orient(B[a, 0], B[a, 1], B[a, 2], B[b, 0], B[b, 1], B[b, 2], B[cc, 0], B[cc, 1], B[cc, 2], S[0, 0], S[0, 1], S[0, 2])
                            if exiting and sp > 0.0:
                                continue
                            count[g] += 1
                            sq = _orient(B[a, 0], B[a, 1], B[a, 2], B[b, 0], B[b, 1], B[b, 2], B[cc, 0], B[cc, 1], B[cc, 2], S[1, 0], S[1, 1], S[1, 2])
                            t = sp / (sp - sq)
                            if t < first[g]:
                                first[g] = t
                                face[g] = f
                            if any_only:
                                done = True
                                break
                    if done:
                        break
                if done:
                    break
            if done:
                break
    return count, first, face


def layer_intersections(inner: np.ndarray, inner_faces: np.ndarray, outer: np.ndarray, outer_faces: np.ndarray) -> np.ndarray:
    """Intersecting (inner, outer) triangle pairs per frame (module doc).

    inner : (T, Vi, 3) metres, inner_faces (Fi, 3); outer : (T, Vo, 3), outer_faces (Fo, 3)
    returns (T,) int64 pair counts (0: the layers do not cross anywhere)
    """
    counts = layer_intersection_faces(inner, inner_faces, outer, outer_faces).sum(1)
    return counts.astype(np.int64)


def self_intersecting_faces(verts: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Faces of one mesh that cross another face of it (the test above; faces that share a vertex
    or an edge touch there, which does not count): (T, F) bool for verts (T, V, 3)."""
    return layer_intersection_faces(verts, faces, verts, faces) > 0


def layer_intersection_faces(inner: np.ndarray, inner_faces: np.ndarray, outer: np.ndarray, outer_faces: np.ndarray) -> np.ndarray:
    """Per frame and inner face, the number of outer faces it intersects: (T, Fi) int32."""
    inner, outer = np.asarray(inner), np.asarray(outer)
    if inner.ndim != 3 or inner.shape[-1] != 3:
        raise InputShapeError("inner", "(T, Vi, 3)", inner.shape)
    if outer.ndim != 3 or outer.shape[-1] != 3 or outer.shape[0] != inner.shape[0]:
        raise InputShapeError("outer", f"({inner.shape[0]}, Vo, 3)", outer.shape)
    fi = np.ascontiguousarray(check_faces(inner_faces, inner.shape[1]))
    fo = np.ascontiguousarray(check_faces(outer_faces, outer.shape[1]))
    out = np.zeros((inner.shape[0], len(fi)), np.int32)
    if not len(fo):
        return out
    for t in range(inner.shape[0]):  # frames: a few per request; each kernel call is one frame's work
        B = np.ascontiguousarray(outer[t], np.float64)
        edge = np.linalg.norm(B[fo[:, 1]] - B[fo[:, 0]], axis=1)
        h = CELL_EDGES * max(float(np.median(edge)), 1e-6)
        out[t] = intersecting_faces(np.ascontiguousarray(inner[t], np.float64), fi, B, fo, h)
    return out
