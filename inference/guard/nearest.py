"""The guard's per-frame nearest body vertices (``push._dynamic_candidates``), compiled.

Every garment point that another body part can reach asks, in every posed frame, for its k
nearest vertices of a body region (a few thousand vertices; k = DYNAMIC_K). A KD-tree per frame
(scipy's ``cKDTree``) took ~4 ms a frame for a T-shirt's 5,148 points against 3,099 region
vertices, ~0.7 us a query. Here the region's vertices of each frame are sorted into cubic cells
of side CELL_M (counting sort), and a point's answer in the previous frame bounds its answer in
this one: with those k vertices at their new places, the k nearest lie within

    rho = max_j |q_t - c_j(t)|,   j over the previous frame's k nearest,

so only the cells meeting the ball of radius rho around q_t are read. A point with no previous
answer (a block's first frame with no state, or a rho beyond COLD_RHO_M) searches shells of cells
around its own until it holds k vertices no farther than the unread cells can be. Both are exact:
the same k vertices as a KD-tree, nearest first (equal distances may come in another order).

Units: metres. Arrays: float64 coordinates, int64 indices.
"""
from __future__ import annotations

import numba
import numpy as np

_JIT = {"nogil": True, "cache": True, "fastmath": False}

# Cell side of the per-frame grid, metres. A point's warm ball (rho ~2 cm: its third-nearest body
# vertex, a garment 1-3 cm off the skin) meets one to eight cells of this side; smaller cells
# read fewer vertices but walk more cell rows: 2.2 ms a frame at 2.5 cm, 2.0 at 3.5-6 cm (T-shirt +
# jacket, 11,481 points, 02_02, the validation clip).
CELL_M = 0.045
# A warm bound wider than this searches by shells instead (the ball's box grows as rho^3).
COLD_RHO_M = 0.1


@numba.njit(**_JIT)
def _insert(best_d, best_i, d, i, k):
    j = k - 1
    while j > 0 and best_d[j - 1] > d:
        best_d[j] = best_d[j - 1]
        best_i[j] = best_i[j - 1]
        j -= 1
    best_d[j] = d
    best_i[j] = i


@numba.njit(inline="always", **_JIT)
def _gather(pts, start, n1, n2, a0, a1, b0, b1, c0, c1, x, y, z, bound, hit_s, hit_d):
    """The vertices of the cells [a0, a1] x [b0, b1] x [c0, c1] nearer than ``bound`` (squared
    distance), in cell order (pts in cell order: a cell's vertices are the rows
    start[cell]:start[cell + 1]): their rows into hit_s, their squared distances into hit_d;
    returns how many. Without a branch per vertex: each is written and the count moves past it
    only if it is nearer (~4 of a warm ball's ~40 vertices; the branch of a test per vertex,
    taken at random, cost more than the distances)."""
    n = 0
    for a in range(a0, a1 + 1):
        for b in range(b0, b1 + 1):
            row = (a * n1 + b) * n2
            for s in range(start[row + c0], start[row + c1 + 1]):
                dx, dy, dz = pts[s, 0] - x, pts[s, 1] - y, pts[s, 2] - z
                d = dx * dx + dy * dy + dz * dz
                hit_s[n] = s
                hit_d[n] = d
                n += d < bound
    return n


@numba.njit(**_JIT)
def _scan(pts, start, n1, n2, a0, a1, b0, b1, c0, c1, x, y, z, best_d, best_i, k, hit_s, hit_d):
    """Every vertex of the cells [a0, a1] x [b0, b1] x [c0, c1] into the k-best lists: the ones
    nearer than the k-th best when the scan starts (``_gather``; the k-th best only shrinks, so
    no other could enter), then inserted in scan order, as a scan that tested each in turn would."""
    n = _gather(pts, start, n1, n2, a0, a1, b0, b1, c0, c1, x, y, z, best_d[k - 1], hit_s, hit_d)
    for h in range(n):
        if hit_d[h] < best_d[k - 1]:
            _insert(best_d, best_i, hit_d[h], hit_s[h], k)


@numba.njit(**_JIT)
def _scan3(pts, start, n1, n2, a0, a1, b0, b1, c0, c1, x, y, z, best_d, best_i, hit_s, hit_d):
    """``_scan`` for k = 3 (the guard's DYNAMIC_K), the three best held in locals rather than
    arrays: the same lists, ~10 % less time per query."""
    d0, d1, d2 = best_d[0], best_d[1], best_d[2]
    i0, i1, i2 = best_i[0], best_i[1], best_i[2]
    n = _gather(pts, start, n1, n2, a0, a1, b0, b1, c0, c1, x, y, z, d2, hit_s, hit_d)
    for h in range(n):
        d, s = hit_d[h], hit_s[h]
        if d < d2:  # the insertion of ``_insert``: strictly nearer moves ahead
            if d < d1:
                d2, i2 = d1, i1
                if d < d0:
                    d1, i1 = d0, i0
                    d0, i0 = d, s
                else:
                    d1, i1 = d, s
            else:
                d2, i2 = d, s
    best_d[0], best_d[1], best_d[2] = d0, d1, d2
    best_i[0], best_i[1], best_i[2] = i0, i1, i2


@numba.njit(**_JIT)
def _scan_any(pts, start, n1, n2, a0, a1, b0, b1, c0, c1, x, y, z, best_d, best_i, k, hit_s, hit_d):
    if k == 3:
        _scan3(pts, start, n1, n2, a0, a1, b0, b1, c0, c1, x, y, z, best_d, best_i, hit_s, hit_d)
    else:
        _scan(pts, start, n1, n2, a0, a1, b0, b1, c0, c1, x, y, z, best_d, best_i, k, hit_s, hit_d)


@numba.njit(**_JIT)
def frames_knn(C3, region, P, dyn, N, f0, f1, k, h, cold_rho, prev):
    """The k nearest region vertices of the dynamic points in frames f0..f1 (module doc).

    C3 (3, frames, S) body vertex coordinates ; region (R,) int64 indices into S
    P (3, (f1 - f0) * N) the block's points, frame-major ; dyn (Nd,) int64 point indices
    prev (Nd, k) int64: positions in ``region`` of each point's answer in the frame before f0,
         -1 where none; updated in place to the last frame's answer
    returns (f1 - f0, Nd, k) int64 positions in ``region``, nearest first
    """
    R, Nd = region.shape[0], dyn.shape[0]
    out = np.empty((f1 - f0, Nd, k), np.int64)
    pts = np.empty((R, 3))
    spts = np.empty((R, 3))
    lo = np.empty(3)
    dims = np.empty(3, np.int64)
    best_d = np.empty(k)
    best_i = np.empty(k, np.int64)
    hit_s = np.empty(R, np.int64)  # ``_gather``'s scratch: a scan reads at most the R vertices
    hit_d = np.empty(R)
    for f in range(f0, f1):
        for r in range(R):
            for a in range(3):
                pts[r, a] = C3[a, f, region[r]]
        for a in range(3):
            lo[a] = pts[:, a].min()
            dims[a] = int((pts[:, a].max() - lo[a]) / h) + 1
        n0, n1, n2 = dims[0], dims[1], dims[2]
        # counting sort of the region's vertices into the cells (c fastest)
        cell = np.empty(R, np.int64)
        start = np.zeros(n0 * n1 * n2 + 1, np.int64)
        for r in range(R):
            ia = min(int((pts[r, 0] - lo[0]) / h), n0 - 1)
            ib = min(int((pts[r, 1] - lo[1]) / h), n1 - 1)
            ic = min(int((pts[r, 2] - lo[2]) / h), n2 - 1)
            cell[r] = (ia * n1 + ib) * n2 + ic
            start[cell[r] + 1] += 1
        for c in range(n0 * n1 * n2):
            start[c + 1] += start[c]
        fill = start[:-1].copy()
        members = np.empty(R, np.int64)
        for r in range(R):
            members[fill[cell[r]]] = r
            fill[cell[r]] += 1
        for s in range(R):  # the vertices in cell order: a cell's scan reads consecutive rows
            for a in range(3):
                spts[s, a] = pts[members[s], a]
        for q in range(Nd):
            col = (f - f0) * N + dyn[q]
            x, y, z = P[0, col], P[1, col], P[2, col]
            for j in range(k):
                best_d[j] = np.inf
                best_i[j] = -1
            rho2 = -1.0
            if prev[q, 0] >= 0:
                for j in range(k):
                    i = prev[q, j]
                    dx, dy, dz = pts[i, 0] - x, pts[i, 1] - y, pts[i, 2] - z
                    rho2 = max(rho2, dx * dx + dy * dy + dz * dz)
            if 0.0 <= rho2 <= cold_rho * cold_rho:
                # warm: the cells meeting the ball's box; its k vertices are among them, at <= rho
                rho = np.sqrt(rho2)
                for j in range(k):
                    best_d[j] = rho2 * (1.0 + 1e-12) + 1e-300
                a0 = min(max(int(np.floor((x - rho - lo[0]) / h)), 0), n0 - 1)
                a1 = min(max(int(np.floor((x + rho - lo[0]) / h)), 0), n0 - 1)
                b0 = min(max(int(np.floor((y - rho - lo[1]) / h)), 0), n1 - 1)
                b1 = min(max(int(np.floor((y + rho - lo[1]) / h)), 0), n1 - 1)
                c0 = min(max(int(np.floor((z - rho - lo[2]) / h)), 0), n2 - 1)
                c1 = min(max(int(np.floor((z + rho - lo[2]) / h)), 0), n2 - 1)
                _scan_any(spts, start, n1, n2, a0, a1, b0, b1, c0, c1, x, y, z, best_d, best_i, k, hit_s, hit_d)
            if best_i[k - 1] < 0:
                # cold: shells of cells around the point's own until no unread cell can be nearer
                for j in range(k):
                    best_d[j] = np.inf
                    best_i[j] = -1
                ca = min(max(int(np.floor((x - lo[0]) / h)), 0), n0 - 1)
                cb = min(max(int(np.floor((y - lo[1]) / h)), 0), n1 - 1)
                cc = min(max(int(np.floor((z - lo[2]) / h)), 0), n2 - 1)
                r = 0
                while True:
                    a0, a1 = max(ca - r, 0), min(ca + r, n0 - 1)
                    b0, b1 = max(cb - r, 0), min(cb + r, n1 - 1)
                    c0, c1 = max(cc - r, 0), min(cc + r, n2 - 1)
                    for a in range(a0, a1 + 1):
                        for b in range(b0, b1 + 1):
                            if a == ca - r or a == ca + r or b == cb - r or b == cb + r:
                                _scan_any(spts, start, n1, n2, a, a, b, b, c0, c1, x, y, z, best_d, best_i, k, hit_s, hit_d)
                            else:  # the shell's two c ends of this column
                                if cc - r >= 0:
                                    _scan_any(spts, start, n1, n2, a, a, b, b, cc - r, cc - r, x, y, z, best_d, best_i, k, hit_s, hit_d)
                                if cc + r <= n2 - 1 and r > 0:
                                    _scan_any(spts, start, n1, n2, a, a, b, b, cc + r, cc + r, x, y, z, best_d, best_i, k, hit_s, hit_d)
                    # the distance from the point to the cells not read yet (inf: none left)
                    reach = np.inf
                    if a0 > 0:
                        reach = min(reach, x - (lo[0] + a0 * h))
                    if a1 < n0 - 1:
                        reach = min(reach, lo[0] + (a1 + 1) * h - x)
                    if b0 > 0:
                        reach = min(reach, y - (lo[1] + b0 * h))
                    if b1 < n1 - 1:
                        reach = min(reach, lo[1] + (b1 + 1) * h - y)
                    if c0 > 0:
                        reach = min(reach, z - (lo[2] + c0 * h))
                    if c1 < n2 - 1:
                        reach = min(reach, lo[2] + (c1 + 1) * h - z)
                    if reach == np.inf or (best_i[k - 1] >= 0 and best_d[k - 1] <= reach * reach):
                        break
                    r += 1
            for j in range(k):  # rows of spts -> positions in ``region``
                m = members[best_i[j]] if best_i[j] >= 0 else -1
                out[f - f0, q, j] = m
                prev[q, j] = m
    return out


@numba.njit(**_JIT)
def flat_candidates(found, region, dyn, N, f0, S, extra):
    """``frames_knn``'s answers as flat candidate ids, in place: extra[j, i N + dyn[q]] =
    (f0 + i) S + region[found[i, q, j]] (frame-major planes of S vertices a frame; every other
    column of ``extra`` is left as it is). Compiled: numpy's transposed gather and column scatter
    took ~0.27 ms a frame for the T-shirt's 5,148 points."""
    F, Nd, k = found.shape
    for i in range(F):
        base = (f0 + i) * S
        for q in range(Nd):
            col = i * N + dyn[q]
            for j in range(k):
                extra[j, col] = base + region[found[i, q, j]]


def warm_up() -> None:
    """Compile the kernel (or load numba's cache) on three vertices, cold and warm, for the guard's
    float32 body coordinates (``GuardPlan.collider_planes``) and float64 ones."""
    for dtype in (np.float32, np.float64):
        C3 = np.ascontiguousarray(np.eye(3, dtype=dtype)[:, None, :].repeat(2, 1))  # (3, 2 frames, 3 vertices)
        prev = np.full((1, 2), -1, np.int64)
        found = frames_knn(C3, np.arange(3), np.zeros((3, 2)), np.zeros(1, np.int64), 1, 0, 2, 2, CELL_M, COLD_RHO_M, prev)
    flat_candidates(found, np.arange(3), np.zeros(1, np.int64), 1, 0, 3, np.zeros((2, 2), np.intp))
