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

Layout: a vertex is one row (u, v, y) of 24 bytes, and a face's corners and canonical edges come
from its three vertex ids alone, so a crossing test reads four rows, not four index arrays and
nine coordinate planes. The binning's first pass keeps each binned face's cells and box as a
record, so the second only scatters them; a face whose corners all lie beyond one side of the
region (a vertex's side bits, ``_outside_codes``) costs three byte reads.

Cost per frame (session 42, a 2-core AMD EPYC; the body and its inflated copy, 27,420 faces, over
the region of 5,148 T-shirt points on ``dance``, 16-frame blocks, one thread): binning 1.72 ->
1.42 ms (two passes, ~49k cell-face pairs; 1.08 over a 3 cm region), counting 1.39 -> 1.14 ms
(~23 faces in a point's cell, ~1.8 past the box pre-test, each tested against both copies).
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


@numba.njit(**_JIT)
def median_edge(verts, faces, step):
    """The median length of the first edge of every ``step``-th face, metres: numpy's
    ``np.median(np.linalg.norm(verts[faces[::step, 1]] - verts[faces[::step, 0]], axis=1))`` in
    float64, bitwise (the grid's cell; ~0.3 ms of fancy indexing in numpy for the body's 3,428).
    verts (V, 3) float32 or float64; faces (F, 3) int64."""
    n = (faces.shape[0] + step - 1) // step
    e = np.empty(max(n, 1))
    e[0] = 0.0
    for r in range(n):
        a, b = faces[r * step, 0], faces[r * step, 1]
        d0 = np.float64(verts[b, 0]) - np.float64(verts[a, 0])
        d1 = np.float64(verts[b, 1]) - np.float64(verts[a, 1])
        d2 = np.float64(verts[b, 2]) - np.float64(verts[a, 2])
        e[r] = np.sqrt(d0 * d0 + d1 * d1 + d2 * d2)
    return np.median(e)


@numba.njit(**_JIT)
def uv_bounds(X, X2, used, B, V, lo, hi):
    """Per frame b, the (u, v) box of the vertices ``used`` (int64 ids) over both vertex sets X,
    X2 ((B*V, 3) rows (u, v, y)): lo (B, 2), hi (B, 2), written."""
    for b in range(B):
        u0, u1, v0, v1 = np.inf, -np.inf, np.inf, -np.inf
        for k in range(used.shape[0]):
            a = b * V + used[k]
            u0, u1 = min(u0, X[a, 0], X2[a, 0]), max(u1, X[a, 0], X2[a, 0])
            v0, v1 = min(v0, X[a, 1], X2[a, 1]), max(v1, X[a, 1], X2[a, 1])
        lo[b, 0], lo[b, 1], hi[b, 0], hi[b, 1] = u0, v0, u1, v1


@numba.njit(**_JIT)
def _outside_codes(X, X2, base, V, r0, r1, r2, r3, code):
    """code[v] (V,) uint8 of frame vertex base + v: bit 1 where its u is below r0 in both vertex
    sets, 2 above r1, 4 its v below r2, 8 above r3. A face's box (over both sets) misses the
    region exactly where the AND of its corners' codes is not 0 (each bit: all six coordinates
    beyond that side), so the faces a region leaves out cost three byte reads, not 18 coordinates."""
    for k in range(V):
        a = base + k
        u, v, s, t = X[a, 0], X[a, 1], X2[a, 0], X2[a, 1]
        code[k] = (((u < r0) & (s < r0)) * 1 | ((u > r1) & (s > r1)) * 2 | ((v < r2) & (t < r2)) * 4
                   | ((v > r3) & (t > r3)) * 8)


@numba.njit(**_JIT)
def bin_boxes(X, X2, faces, B, V, inv_h, lo, ni, nj, region, start, code, rec_face, rec_cells, rec_box):
    """First pass of the binning: per frame, each face whose projected box (over both vertex sets)
    meets the frame's region, as a record in (frame, face) order: its id (rec_face, int32), its
    cells (rec_cells (m, 4) int32: frame * ni + i0, i1 - i0, j0, j1) and its box (rec_box (m, 6)
    float32: u min, u max, v min, v max, y max, y min, widened by BOX_SLACK so that the pre-test of
    ``count_crossings`` stays conservative after the rounding); start[c + 1] = the number of faces
    of cell c, then its prefix sum (start (B*ni*nj + 1,) int64, overwritten). Returns (m, pairs).

    X, X2 : (B*V, 3) float64, every frame's vertices as (u, v, y) = (x, z, y) (frame b at b*V); X2
            a second vertex set of the same faces, binned with it (each face over the box of
            both of its projections), or X itself
    faces : (F, 3) int64; inv_h: 1 / cell size, 1/metres; lo (B, 2): each frame's grid origin;
    region (B, 4): each frame's (u min, u max, v min, v max), the faces binned are those whose
    box meets it (a point outside it is answered by no cell: ``count_crossings``); code: (V,)
    uint8 scratch (``_outside_codes``)
    (a cell index is floor((x - lo) inv_h), for faces and points alike: monotone in x, so a point
    inside a face's box lands in a cell the face covers; a face of zero projected area in both
    sets never counts and is left out)
    """
    F = faces.shape[0]
    cells = ni * nj
    start[:] = 0
    m = 0
    for b in range(B):
        base = b * V
        lo_u, lo_v = lo[b, 0], lo[b, 1]
        _outside_codes(X, X2, base, V, region[b, 0], region[b, 1], region[b, 2], region[b, 3], code)
        for f in range(F):
            fa, fc, fd = faces[f, 0], faces[f, 1], faces[f, 2]
            if code[fa] & code[fc] & code[fd]:  # first: most faces a garment's region leaves out
                continue
            a, c, d = base + fa, base + fc, base + fd
            u0, v0, y0 = X[a, 0], X[a, 1], X[a, 2]
            u1, v1, y1 = X[c, 0], X[c, 1], X[c, 2]
            u2, v2, y2 = X[d, 0], X[d, 1], X[d, 2]
            s0, t0, z0 = X2[a, 0], X2[a, 1], X2[a, 2]
            s1, t1, z1 = X2[c, 0], X2[c, 1], X2[c, 2]
            s2, t2, z2 = X2[d, 0], X2[d, 1], X2[d, 2]
            if (u1 - u0) * (v2 - v0) - (v1 - v0) * (u2 - u0) == 0.0 and (s1 - s0) * (t2 - t0) - (t1 - t0) * (s2 - s0) == 0.0:
                continue
            umin, umax = min(u0, u1, u2, s0, s1, s2), max(u0, u1, u2, s0, s1, s2)
            vmin, vmax = min(v0, v1, v2, t0, t1, t2), max(v0, v1, v2, t0, t1, t2)
            i0 = max(int(np.floor((umin - lo_u) * inv_h)), 0)
            i1 = min(int(np.floor((umax - lo_u) * inv_h)), ni - 1)
            j0 = max(int(np.floor((vmin - lo_v) * inv_h)), 0)
            j1 = min(int(np.floor((vmax - lo_v) * inv_h)), nj - 1)
            if i1 < i0 or j1 < j0:
                continue
            ymax, ymin = max(y0, y1, y2, z0, z1, z2), min(y0, y1, y2, z0, z1, z2)
            rec_face[m] = f
            rec_cells[m, 0], rec_cells[m, 1], rec_cells[m, 2], rec_cells[m, 3] = b * ni + i0, i1 - i0, j0, j1
            rec_box[m, 0] = np.float32(umin - BOX_SLACK * (1.0 + abs(umin)))
            rec_box[m, 1] = np.float32(umax + BOX_SLACK * (1.0 + abs(umax)))
            rec_box[m, 2] = np.float32(vmin - BOX_SLACK * (1.0 + abs(vmin)))
            rec_box[m, 3] = np.float32(vmax + BOX_SLACK * (1.0 + abs(vmax)))
            rec_box[m, 4] = np.float32(ymax + BOX_SLACK * (1.0 + abs(ymax)))
            rec_box[m, 5] = np.float32(ymin - BOX_SLACK * (1.0 + abs(ymin)))
            m += 1
            for i in range(i0, i1 + 1):
                row = b * cells + i * nj + 1
                for j in range(j0, j1 + 1):
                    start[row + j] += 1
    for c in range(B * cells):
        start[c + 1] += start[c]
    return m, start[B * cells]


@numba.njit(**_JIT)
def fill_pairs(m, nj, start, fill, rec_face, rec_cells, rec_box, cell_face, pair_box):
    """Second pass: the faces of cell c (face ids f of frame b, in increasing order) in
    cell_face[start[c]:start[c + 1]] (int32), each with its record's box in pair_box (pairs, 6)
    float32, so that a point's pre-test reads memory in order. fill: (B*ni*nj,) int64 scratch;
    the records are ``bin_boxes``'s first m."""
    fill[:] = start[:-1]
    for r in range(m):
        row0, di, j0, j1 = rec_cells[r, 0], rec_cells[r, 1], rec_cells[r, 2], rec_cells[r, 3]
        f = rec_face[r]
        for i in range(di + 1):
            row = (row0 + i) * nj
            for j in range(j0, j1 + 1):
                s = fill[row + j]
                cell_face[s] = f
                for q in range(6):
                    pair_box[s, q] = rec_box[r, q]
                fill[row + j] = s + 1


@numba.njit(inline="always", **_JIT)
def _crossing(pu, pv, pyy, up, f, base, X, faces):
    """The signed crossing (-1, 0 or +1) of the ray from (pu, pyy, pv) along +y (``up``) or -y with
    face f of the frame at vertex offset ``base`` (X: (B*V, 3) (u, v, y)): inside the face's
    projection by its canonical edge functions and the face above (below) the point (module doc;
    the -y ray is the mirror image: the face's side and the crossing's sign both flip). Edge k
    runs from corner k to corner k + 1, evaluated from its lower vertex id (flipped where the
    face's order is reversed); its opposite corner is k + 2."""
    i0, i1, i2 = base + faces[f, 0], base + faces[f, 1], base + faces[f, 2]
    u0, v0, y0 = X[i0, 0], X[i0, 1], X[i0, 2]
    u1, v1, y1 = X[i1, 0], X[i1, 1], X[i1, 2]
    u2, v2, y2 = X[i2, 0], X[i2, 1], X[i2, 2]
    A2 = (u1 - u0) * (v2 - v0) - (v1 - v0) * (u2 - u0)
    if A2 == 0.0:  # no area (binned for the other vertex set of the grid, if at all)
        return 0
    ccw = A2 > 0.0
    depth = 0.0
    for k in range(3):
        if k == 0:
            ia, ib, ua, va, ub, vb, yo = i0, i1, u0, v0, u1, v1, y2
        elif k == 1:
            ia, ib, ua, va, ub, vb, yo = i1, i2, u1, v1, u2, v2, y0
        else:
            ia, ib, ua, va, ub, vb, yo = i2, i0, u2, v2, u0, v0, y1
        flip = ia > ib
        if flip:
            e0u, e0v, du, dv = ub, vb, ua - ub, va - vb
        else:
            e0u, e0v, du, dv = ua, va, ub - ua, vb - va
        E = du * (pv - e0v) - dv * (pu - e0u)
        # the side of the point moved by (eps, eps^2) in (u, v), eps -> 0: E's own sign, else (on
        # the edge's line) that of -dv, else of du (module doc)
        left = (E > 0.0) | ((E == 0.0) & ((dv < 0.0) | ((dv == 0.0) & (du > 0.0))))  # no branch: | and &, not or and and
        if (left ^ flip) != ccw:
            return 0
        Et = -E if flip else E
        depth = depth + Et * (yo - pyy)
    if up:
        if (depth > 0.0) == ccw:
            return -1 if ccw else 1
    elif (depth < 0.0) == ccw:
        return 1 if ccw else -1
    return 0


@numba.njit(inline="always", **_JIT)
def _fullest(start):
    """The most faces any cell of a grid holds (start: its cells' offsets)."""
    most = 0
    for c in range(start.shape[0] - 1):
        most = max(most, start[c + 1] - start[c])
    return most


@numba.njit(inline="always", **_JIT)
def _count_point(pu, pv, pyy, b, up, X, X2, faces, V, inv_h, lo, ni, nj, region, bounded, start, cell_face, pair_box, either, hits):
    """The winding number at the point (pu, pyy, pv) of frame b, its ray along +y (``up``) or -y
    (``count_crossings``); hits: scratch for a cell's candidates, at least as long as the fullest cell."""
    if not (region[b, 0] <= pu <= region[b, 1] and region[b, 2] <= pv <= region[b, 3]):
        return UNKNOWN if bounded else 0
    i = int(np.floor((pu - lo[b, 0]) * inv_h))
    j = int(np.floor((pv - lo[b, 1]) * inv_h))
    if i < 0 or i >= ni or j < 0 or j >= nj:
        return 0
    c = b * ni * nj + i * nj + j
    base = b * V
    s0, s1 = start[c], start[c + 1]
    # cheap pre-test, without a branch: the projected box holds p and the face reaches above
    # (below) p; the pairs that pass are written to ``hits`` as the loop goes (~2 of ~23)
    n = 0
    if up:
        for s in range(s0, s1):
            hits[n] = s
            n += ((pu >= pair_box[s, 0]) & (pu <= pair_box[s, 1]) & (pv >= pair_box[s, 2]) & (pv <= pair_box[s, 3])
                  & (pair_box[s, 4] > pyy))
    else:
        for s in range(s0, s1):
            hits[n] = s
            n += ((pu >= pair_box[s, 0]) & (pu <= pair_box[s, 1]) & (pv >= pair_box[s, 2]) & (pv <= pair_box[s, 3])
                  & (pair_box[s, 5] < pyy))
    total, total2 = 0, 0
    for h in range(n):
        f = cell_face[hits[h]]
        total += _crossing(pu, pv, pyy, up, f, base, X, faces)
        if either:
            total2 += _crossing(pu, pv, pyy, up, f, base, X2, faces)
    return max(total, total2) if either else total


@numba.njit(**_JIT)
def count_crossings(points, frame, down, X, X2, faces, V, inv_h, lo, ni, nj, region, bounded, start, cell_face, pair_box, either):
    """Winding number at each point: the signed crossings of its ray with the faces of its cell.

    points     : (P, 3) float32 or float64, metres; frame (P,) int64: the frame each point is tested in
    down       : (P,) bool, the point's ray runs along -y (else +y): any ray gives the winding number
                 of a closed mesh; one leaving the body at once meets fewer faces
    X          : (B*V, 3) float64 vertex coordinates (x, z, y), one vertex set the grid was binned
                 with; faces (F, 3) int64
    X2         : the grid's other vertex set, read only if ``either``: then the larger of the two
                 winding numbers (a point inside either mesh counts as inside), in the same pass
    inv_h, lo, ni, nj, region, start, cell_face, pair_box : the grid (``bin_boxes``, ``fill_pairs``)
    bounded    : the region is smaller than the mesh: a point outside it gets UNKNOWN (else 0:
                 no face is there)
    returns    : (P,) int32
    """
    cells = ni * nj
    P = points.shape[0]
    w = np.zeros(P, np.int32)
    hits = np.empty(_fullest(start), np.int64)
    # the loop of ``_count_point`` written out: as a call, inlined or not, it cost 1.30-1.47 against
    # 1.14 ms a frame (5,148 points, 16-frame blocks)
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
        base = b * V
        up = not down[p]
        s0, s1 = start[c], start[c + 1]
        n = 0
        if up:
            for s in range(s0, s1):
                hits[n] = s
                n += ((pu >= pair_box[s, 0]) & (pu <= pair_box[s, 1]) & (pv >= pair_box[s, 2]) & (pv <= pair_box[s, 3])
                      & (pair_box[s, 4] > pyy))
        else:
            for s in range(s0, s1):
                hits[n] = s
                n += ((pu >= pair_box[s, 0]) & (pu <= pair_box[s, 1]) & (pv >= pair_box[s, 2]) & (pv <= pair_box[s, 3])
                      & (pair_box[s, 5] < pyy))
        total, total2 = 0, 0
        for h in range(n):
            f = cell_face[hits[h]]
            total += _crossing(pu, pv, pyy, up, f, base, X, faces)
            if either:
                total2 += _crossing(pu, pv, pyy, up, f, base, X2, faces)
        w[p] = max(total, total2) if either else total
    return w


@numba.njit(**_JIT)
def first_outside(points, targets, frame, X, X2, faces, V, inv_h, lo, ni, nj, region, bounded, start, cell_face, pair_box, either,
                  known):
    """Per point, its nearest target with winding number 0: the targets taken by their float32
    distance to the point, nearest first (equal distances in their own order, as numpy's argsort
    of rows of up to 16), each target's ray along its move's side of y (down where it lies below
    the point), stopping at the first outside one.

    points  : (n, 3) float32, metres; targets (n, m, 3) float32; frame (n,) int64
    the grid: as ``count_crossings``
    known   : (n, mk) int8, mk <= m (0: none), the verdicts of the first mk targets already
              counted: 0 outside, 1 inside (taken or passed over without a count), -1 not known
              (counted here, and its verdict written in). A closed mesh's winding number is the
              same along any ray, so a verdict holds whichever side of y it was counted along.
    returns : (n,) int64, the column of the first outside target, -1 where none is, -2 where a
              target tested lies beyond the grid's region (its count is the caller's to finish)
    """
    mk = known.shape[1]
    n, m = targets.shape[0], targets.shape[1]
    best = np.full(n, -1, np.int64)
    hits = np.empty(_fullest(start), np.int64)
    dist = np.empty(m, np.float32)
    order = np.empty(m, np.int64)
    for p in range(n):
        px, py, pz = points[p, 0], points[p, 1], points[p, 2]
        for t in range(m):  # numpy's float32 norm: sqrt((dx^2 + dy^2) + dz^2)
            dx, dy, dz = targets[p, t, 0] - px, targets[p, t, 1] - py, targets[p, t, 2] - pz
            dist[t] = np.sqrt(dx * dx + dy * dy + dz * dz)
            k = t  # insertion sort: equal distances keep their order
            while k > 0 and dist[order[k - 1]] > dist[t]:
                order[k] = order[k - 1]
                k -= 1
            order[k] = t
        for r in range(m):
            t = order[r]
            if t < mk and known[p, t] >= 0:
                if known[p, t] == 0:
                    best[p] = t
                    break
                continue
            ty = targets[p, t, 1]
            w = _count_point(np.float64(targets[p, t, 0]), np.float64(targets[p, t, 2]), np.float64(ty), frame[p], not (ty < py),
                                   X, X2, faces, V, inv_h, lo, ni, nj, region, bounded, start, cell_face, pair_box, either, hits)
            if w == UNKNOWN:
                best[p] = -2
                break
            if t < mk:
                known[p, t] = 0 if w == 0 else 1
            if w == 0:
                best[p] = t
                break
    return best


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
