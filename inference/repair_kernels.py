"""Compiled kernels of ``inference.repair`` (numba, no Python objects, one thread); ``frame_knn``
also finds the arm lift's nearest torso points (``inference.motion.self_contact``).

Units: metres. Arrays: float32 vertices, int64 ids.
"""
from __future__ import annotations

import numba
import numpy as np

_JIT = {"nogil": True, "cache": True, "fastmath": False}
# ``frame_knn``'s bound is taken this much nearer than computed: a vertex's cell comes from a
# rounded division, so one a rounding away from a cell's side may be binned across it.
BOUND_SLACK_M = 1e-9
# Above this many neighbours ``frame_knn`` keeps every vertex it reads and sorts, once, those
# within the bound; up to it, it inserts each into the k best (the final stage asks 8, 32 and 512).
MANY_K = 64


@numba.njit(inline="always", **_JIT)
def _insert(best_d, best_i, d, i, k):
    """Put (d, i) into the ascending k-best lists, dropping the last. (``inference.guard.nearest``
    has the same helper: numba's on-disk cache does not see a change to a function of another
    module, so each kernel module keeps its own.)"""
    j = k - 1
    while j > 0 and best_d[j - 1] > d:
        best_d[j] = best_d[j - 1]
        best_i[j] = best_i[j - 1]
        j -= 1
    best_d[j] = d
    best_i[j] = i


@numba.njit(**_JIT)
def frame_knn(verts, frames, starts, q, ids, k, pad, h, radius=np.inf):
    """The k nearest of the vertices ``ids`` to each point, in the point's own frame, nearest
    first, where a grid of the frame's vertices near its points can tell them exactly.

    verts  : (B, V, 3) float32, metres; ids (S,) int64, the candidate vertices (the skin)
    frames : (nf,) int64, the frames that have points; starts (nf + 1,) int64: the points of
             frames[a] are q[starts[a]:starts[a + 1]]
    q      : (n, 3) float64, metres, the points, grouped by frame
    pad    : metres; per frame only the vertices within the box of its points widened by pad
             are binned, into cubic cells of side h (metres)
    radius : metres; a point whose cells read cover the ball of this radius without an answer
             stops there, not found (with pad > radius: none of its k nearest lies within radius)
    returns (nn (n, k) int64 vertex ids, found (n,) bool). A point's search reads shells of cells
             around its own until its k-th nearest is no farther than the nearest side of the
             cells read or of the box; a vertex not read then lies farther, so its k are those of
             all ``ids`` (exact; equal distances keep the order of the scan). found is False
             where the box holds fewer than k vertices or the whole box leaves the k-th nearest
             farther than the box's side: the caller asks a tree of all ``ids``.
    """
    n, S = q.shape[0], ids.shape[0]
    nn = np.full((n, k), -1, np.int64)
    found = np.zeros(n, np.bool_)
    pts = np.empty((S, 3))
    sel = np.empty(S, np.int64)
    best_d = np.empty(k)
    best_i = np.empty(k, np.int64)
    # many neighbours (the final stage's far look, k = 512): the vertices read are kept and those
    # within the bound sorted once, where inserting each into the k best shifts up to k of them
    many = k > MANY_K
    read_d = np.empty(S if many else 0)
    read_i = np.empty(S if many else 0, np.int64)
    near_d = np.empty(S if many else 0)
    near_i = np.empty(S if many else 0, np.int64)
    for a in range(frames.shape[0]):
        b, p0, p1 = frames[a], starts[a], starts[a + 1]
        lo = np.full(3, np.inf)
        hi = np.full(3, -np.inf)
        for p in range(p0, p1):
            for c in range(3):
                lo[c] = min(lo[c], q[p, c])
                hi[c] = max(hi[c], q[p, c])
        for c in range(3):
            lo[c] -= pad
            hi[c] += pad
        m = 0
        for s in range(S):
            v = ids[s]
            x, y, z = np.float64(verts[b, v, 0]), np.float64(verts[b, v, 1]), np.float64(verts[b, v, 2])
            if lo[0] <= x <= hi[0] and lo[1] <= y <= hi[1] and lo[2] <= z <= hi[2]:
                pts[m, 0], pts[m, 1], pts[m, 2] = x, y, z
                sel[m] = v
                m += 1
        if m < k:
            continue
        dims = np.empty(3, np.int64)
        for c in range(3):
            dims[c] = int((hi[c] - lo[c]) / h) + 1
        n1, n2 = dims[1], dims[2]
        cells = dims[0] * n1 * n2
        start = np.zeros(cells + 1, np.int64)
        cell_of = np.empty(m, np.int64)
        for r in range(m):
            ci = min(int((pts[r, 0] - lo[0]) / h), dims[0] - 1)
            cj = min(int((pts[r, 1] - lo[1]) / h), n1 - 1)
            ck = min(int((pts[r, 2] - lo[2]) / h), n2 - 1)
            cell_of[r] = (ci * n1 + cj) * n2 + ck
            start[cell_of[r] + 1] += 1
        for c in range(cells):
            start[c + 1] += start[c]
        fill = start[:-1].copy()
        members = np.empty(m, np.int64)
        for r in range(m):
            members[fill[cell_of[r]]] = r
            fill[cell_of[r]] += 1
        for p in range(p0, p1):
            x, y, z = q[p, 0], q[p, 1], q[p, 2]
            ci = min(int((x - lo[0]) / h), dims[0] - 1)
            cj = min(int((y - lo[1]) / h), n1 - 1)
            ck = min(int((z - lo[2]) / h), n2 - 1)
            # the box's nearest side: no vertex beyond it was binned
            box = min(x - lo[0], hi[0] - x, y - lo[1], hi[1] - y, z - lo[2], hi[2] - z)
            best_d[:] = np.inf
            best_i[:] = -1
            nread = 0
            r = 0
            while True:
                a0, a1 = max(ci - r, 0), min(ci + r, dims[0] - 1)
                b0, b1 = max(cj - r, 0), min(cj + r, n1 - 1)
                c0, c1 = max(ck - r, 0), min(ck + r, n2 - 1)
                for i in range(a0, a1 + 1):
                    for j in range(b0, b1 + 1):
                        edge = i == ci - r or i == ci + r or j == cj - r or j == cj + r
                        row = (i * n1 + j) * n2
                        for kk in range(c0, c1 + 1):
                            if not (edge or kk == ck - r or kk == ck + r):
                                continue  # read at a smaller r
                            for t in range(start[row + kk], start[row + kk + 1]):
                                s = members[t]
                                dx, dy, dz = pts[s, 0] - x, pts[s, 1] - y, pts[s, 2] - z
                                d = dx * dx + dy * dy + dz * dz
                                if many:
                                    read_d[nread] = d
                                    read_i[nread] = s
                                    nread += 1
                                elif d < best_d[k - 1]:
                                    _insert(best_d, best_i, d, s, k)
                # the cells read hold every vertex nearer than their cube's nearest side
                reach = min(x - (lo[0] + (ci - r) * h), lo[0] + (ci + r + 1) * h - x,
                            y - (lo[1] + (cj - r) * h), lo[1] + (cj + r + 1) * h - y,
                            z - (lo[2] + (ck - r) * h), lo[2] + (ck + r + 1) * h - z)
                bound = min(reach, box) - BOUND_SLACK_M
                if many:
                    # the k nearest are those read no farther than the bound once k of them are:
                    # sorted, nearest first, equal distances in the order read (the insertion's answer)
                    b2 = bound * bound
                    m2 = 0
                    if nread >= k:
                        for t2 in range(nread):
                            if read_d[t2] <= b2:
                                near_d[m2] = read_d[t2]
                                near_i[m2] = read_i[t2]
                                m2 += 1
                    if m2 >= k:
                        found[p] = True
                        by = np.argsort(near_d[:m2], kind="mergesort")
                        for j2 in range(k):
                            nn[p, j2] = sel[near_i[by[j2]]]
                        break
                elif best_d[k - 1] <= bound * bound:
                    found[p] = True
                    for j2 in range(k):
                        nn[p, j2] = sel[best_i[j2]]
                    break
                if a0 == 0 and b0 == 0 and c0 == 0 and a1 == dims[0] - 1 and b1 == n1 - 1 and c1 == n2 - 1:
                    break  # the whole box read: the k-th nearest may lie beyond it
                if reach - BOUND_SLACK_M >= radius:
                    break  # every vertex within radius read, and the k-th nearest lies beyond it
                r += 1
    return nn, found


@numba.njit(**_JIT)
def skin_targets(Bb, frame, ids, faces, indptr, face_of, margin_m, points, out):
    """The final stage's targets (``inference.repair._targets``) on the skin vertices ids (n, k) of
    points (n, 3) in frames frame (n,) of the block Bb (T, V, 3) (float32 in a request): out
    (n, 2k, 3) of Bb's type, the plane targets p + (max((c - p) . n_c, -margin) + margin) n_c, then the vertex
    targets c + margin n_c, with n_c the unit area-weighted normal of c over the faces (F, 3) int64
    (indptr, face_of: each vertex's faces, ascending, ``inference.mesh._vertex_faces``).

    The operations of the numpy form it replaced, in its order and precision, bitwise: each normal
    sums its faces' cross products in float64 in ascending face order and is normalised where
    longer than 1e-20 (``mesh_kernels.normals_at``); the depth and the targets in float64 from
    coordinates (their difference in their own type), rounded to out's type at the end."""
    n, k = ids.shape[0], ids.shape[1]
    for r in range(n):
        t = frame[r]
        p0, p1, p2 = np.float64(points[r, 0]), np.float64(points[r, 1]), np.float64(points[r, 2])
        for j in range(k):
            v = ids[r, j]
            s0, s1, s2 = 0.0, 0.0, 0.0
            for q in range(indptr[v], indptr[v + 1]):
                f = face_of[q]
                i0, i1, i2 = faces[f, 0], faces[f, 1], faces[f, 2]
                ax = np.float64(Bb[t, i1, 0]) - Bb[t, i0, 0]
                ay = np.float64(Bb[t, i1, 1]) - Bb[t, i0, 1]
                az = np.float64(Bb[t, i1, 2]) - Bb[t, i0, 2]
                bx = np.float64(Bb[t, i2, 0]) - Bb[t, i0, 0]
                by = np.float64(Bb[t, i2, 1]) - Bb[t, i0, 1]
                bz = np.float64(Bb[t, i2, 2]) - Bb[t, i0, 2]
                s0 += ay * bz - az * by
                s1 += az * bx - ax * bz
                s2 += ax * by - ay * bx
            length = (s0 ** 2 + s1 ** 2 + s2 ** 2) ** 0.5
            if length > 1e-20:
                s0, s1, s2 = s0 / length, s1 / length, s2 / length
            c0, c1, c2 = np.float64(Bb[t, v, 0]), np.float64(Bb[t, v, 1]), np.float64(Bb[t, v, 2])
            # c - p in the inputs' type, as numpy subtracts the arrays before the float64 product
            d0 = np.float64(Bb[t, v, 0] - points[r, 0])
            d1 = np.float64(Bb[t, v, 1] - points[r, 1])
            d2 = np.float64(Bb[t, v, 2] - points[r, 2])
            # never inward: a point already above c's plane moves out to the margin, no farther
            depth = max(d0 * s0 + d1 * s1 + d2 * s2, -margin_m)
            step = depth + margin_m
            out[r, j, 0] = p0 + step * s0
            out[r, j, 1] = p1 + step * s1
            out[r, j, 2] = p2 + step * s2
            out[r, k + j, 0] = c0 + margin_m * s0
            out[r, k + j, 1] = c1 + margin_m * s1
            out[r, k + j, 2] = c2 + margin_m * s2


@numba.njit(**_JIT)
def on_skin(P, B, anchors, eps2, tested):
    """tested[t, v] |= |P[t, v] - B[t, anchors[v]]|^2 < eps2, in place: a layer's points on their
    skin vertex (P (T, N, 3), B (T, Vb, 3) float; eps2 a scalar of their common type). The squared
    length in that type as numpy's einsum sums it ((x^2 + y^2) + z^2), without the (T, N, 3)
    difference (~0.3 ms a frame of an outfit's inner layer)."""
    T, N = P.shape[0], P.shape[1]
    for t in range(T):
        for v in range(N):
            a = anchors[v]
            d0, d1, d2 = P[t, v, 0] - B[t, a, 0], P[t, v, 1] - B[t, a, 1], P[t, v, 2] - B[t, a, 2]
            if d0 * d0 + d1 * d1 + d2 * d2 < eps2:
                tested[t, v] = True


@numba.njit(**_JIT)
def torn_ends(P, entering, row, frame, idx, inc_ptr, inc_edge, edges, stretch_m, mark):
    """The final stage's torn edges (``inference.repair._keep_together``): for each point (frame[r],
    idx[r]) of a block and each of its edges (inc_ptr, inc_edge: a vertex's rows of ``edges``
    (E, 2) int64), where the edge is longer than as the points came by more than stretch_m
    metres, mark[row[t, end]] = True at both ends that have a row (row (T, N) int64, -1 where none).
    P, entering: (T, N, 3) float32, the block now and as it came; mark (R,) bool, in place."""
    for r in range(frame.shape[0]):
        t, v = frame[r], idx[r]
        for q in range(inc_ptr[v], inc_ptr[v + 1]):
            e = inc_edge[q]
            a, b = edges[e, 0], edges[e, 1]
            now = 0.0
            was = 0.0
            for c in range(3):
                d = np.float64(P[t, a, c]) - np.float64(P[t, b, c])
                now += d * d
                d = np.float64(entering[t, a, c]) - np.float64(entering[t, b, c])
                was += d * d
            if np.sqrt(now) - np.sqrt(was) > stretch_m:
                if row[t, a] >= 0:
                    mark[row[t, a]] = True
                if row[t, b] >= 0:
                    mark[row[t, b]] = True


@numba.njit(**_JIT)
def carried_places(P, entering, frame, idx, adj_ptr, adj_idx, out):
    """Where each point's mesh neighbours would carry it (``inference.repair._keep_together``): out[r]
    = mean over the neighbours j of v = idx[r] (adj_ptr, adj_idx: CSR adjacency) of P[t, j] -
    entering[t, j] + entering[t, v], t = frame[r]; P, entering (T, N, 3) float32; out (R, 3) float64
    (a point with no neighbour: its own place as it came)."""
    for r in range(frame.shape[0]):
        t, v = frame[r], idx[r]
        s0, s1, s2 = 0.0, 0.0, 0.0
        n = adj_ptr[v + 1] - adj_ptr[v]
        for q in range(adj_ptr[v], adj_ptr[v + 1]):
            j = adj_idx[q]
            s0 += np.float64(P[t, j, 0]) - np.float64(entering[t, j, 0])
            s1 += np.float64(P[t, j, 1]) - np.float64(entering[t, j, 1])
            s2 += np.float64(P[t, j, 2]) - np.float64(entering[t, j, 2])
        m = max(n, 1)
        out[r, 0] = np.float64(entering[t, v, 0]) + s0 / m
        out[r, 1] = np.float64(entering[t, v, 1]) + s1 / m
        out[r, 2] = np.float64(entering[t, v, 2]) + s2 / m
