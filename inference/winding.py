"""Exact winding numbers of a closed triangle mesh by signed ray crossings (DESIGN.md §5).

The posed body is a closed, outward-oriented triangle mesh that intersects itself under LBS, so
"inside" means a winding number >= 1 (generalised winding number > 0.5), not the parity of ray
crossings and not a closest-face sign. For a closed mesh the winding number is an integer and
equals the signed number of crossings of any ray from the point:

    w(p) = sum over faces f hit by the ray p + t e_y (t > 0) of sign(n_f . e_y)

(an outward face is left through, +1, or entered, -1). ``WindingGrid`` bins the faces of a batch
of frames once, projected along the ray onto (x, z), into a 2-D grid; a point then tests only the
faces of its cell, so one grid answers many point sets (a garment's vertices, then the targets of
``inference.repair``). Point-in-projected-triangle uses edge functions evaluated from the edge's
two vertices in canonical (lower index first) order, so the two faces sharing an edge compute the
bitwise same value and a ray through the edge is counted once (ties go to the left of the
canonical edge). Only rays through a projected vertex, or points on the surface, are ambiguous
(measure zero). The crossing test runs in float64 on the candidate (point, face) pairs only.

Cost (13,718-vertex body, one thread, bench/bench_guard.py): building the grid is most of it;
testing 5k points adds a few ms per frame.

Units: metres. Shapes: batch axis first; a frame is one (points, mesh) pair.
"""
from __future__ import annotations

import numpy as np

from inference.errors import InputShapeError

# Grid cell, in multiples of the median edge length.
CELL_EDGES = 2.0
# Candidate (point, face) pairs evaluated at once; bounds memory (~150 bytes per pair).
PAIR_BLOCK = 2_000_000
# Frames binned at once by ``winding_numbers`` (bounds the memory of the face bins).
FRAME_BLOCK = 16


def _frames(name: str, a: np.ndarray) -> np.ndarray:
    a = np.asarray(a)
    if a.ndim != 3 or a.shape[-1] != 3:
        raise InputShapeError(name, "(B, N, 3)", a.shape)
    return a


def check_faces(faces: np.ndarray, num_vertices: int) -> np.ndarray:
    """(F, 3) int64 triangle indices into num_vertices vertices (InputShapeError otherwise)."""
    faces = np.asarray(faces)
    if faces.ndim != 2 or faces.shape[1] != 3 or faces.min() < 0 or faces.max() >= num_vertices:
        raise InputShapeError("faces", f"(F, 3) indices < {num_vertices}", faces.shape)
    return faces.astype(np.int64)


class WindingGrid:
    """The faces of B frames of one closed mesh, binned for ray-crossing winding numbers.

    verts : (B, V, 3) float, metres, closed mesh with outward (counter-clockwise) faces
    faces : (F, 3) int
    """

    def __init__(self, verts: np.ndarray, faces: np.ndarray):
        verts = _frames("verts", verts)
        faces = check_faces(faces, verts.shape[1])
        B, V = verts.shape[:2]
        F = len(faces)
        self.B, self.V, self.F = B, V, F
        # coordinate planes, float64 (exact copies of float32 input): u = x, v = z, depth y
        self.u = np.ascontiguousarray(verts[..., 0], np.float64).ravel()  # (B*V,)
        self.v = np.ascontiguousarray(verts[..., 2], np.float64).ravel()
        self.y = np.ascontiguousarray(verts[..., 1], np.float64).ravel()
        base = (np.arange(B) * V)[:, None]
        c = [base + faces[:, k] for k in range(3)]  # (B, F) flat vertex ids of corner k
        u0, u1, u2 = (self.u[i] for i in c)
        v0, v1, v2 = (self.v[i] for i in c)
        # A2 = twice the signed projected area; n_y = -A2, so a crossing counts -sign(A2)
        self.A2 = ((u1 - u0) * (v2 - v0) - (v1 - v0) * (u2 - u0)).ravel()
        umin, umax = np.minimum(np.minimum(u0, u1), u2), np.maximum(np.maximum(u0, u1), u2)
        vmin, vmax = np.minimum(np.minimum(v0, v1), v2), np.maximum(np.maximum(v0, v1), v2)
        y0, y1, y2 = (self.y[i] for i in c)
        self.box = np.stack([umin.ravel(), umax.ravel(), vmin.ravel(), vmax.ravel(), np.maximum(np.maximum(y0, y1), y2).ravel()])

        # canonical edges k (corner k -> k+1, flipped where the index order is reversed) and the
        # corner opposite each edge, as vertex ids (static over frames)
        nxt = [1, 2, 0]
        flip = faces > faces[:, nxt]
        self.edge_lo = np.where(flip, faces[:, nxt], faces)
        self.edge_hi = np.where(flip, faces, faces[:, nxt])
        self.opposite = faces[:, [2, 0, 1]]
        self.flip = flip

        # grid over each frame's projected mesh: each face binned into the cells its box covers
        med = float(np.median(np.sqrt((u1[0] - u0[0]) ** 2 + (v1[0] - v0[0]) ** 2 + (y1[0] - y0[0]) ** 2)))
        self.h = h = CELL_EDGES * max(med, 1e-6)
        self.lo = np.stack([umin.min(1), vmin.min(1)], -1)  # (B, 2): each frame's own origin
        extent = np.stack([umax.max(1), vmax.max(1)], -1) - self.lo
        self.ncell = ncell = np.floor(extent.max(0) / h).astype(np.int64) + 1
        i0 = np.floor((umin - self.lo[:, :1]) / h).astype(np.int64)
        i1 = np.floor((umax - self.lo[:, :1]) / h).astype(np.int64)
        j0 = np.floor((vmin - self.lo[:, 1:]) / h).astype(np.int64)
        j1 = np.floor((vmax - self.lo[:, 1:]) / h).astype(np.int64)
        ni = np.where(self.A2 != 0, (i1 - i0 + 1).ravel(), 0)  # zero-area faces never count
        nj = (j1 - j0 + 1).ravel()
        self.cells = int(ncell[0] * ncell[1])
        first = (np.arange(B)[:, None] * self.cells + i0 * ncell[1] + j0).ravel()  # key of (i0, j0)
        # (face, cell) pairs, one pass per cell offset (di, dj) of the face's box (most span 1-2)
        bits = int(B * F).bit_length()
        keys = []
        rows = np.flatnonzero(ni)
        for di in range(int(ni.max(initial=0))):
            rows = rows[ni[rows] > di]
            cols = rows
            for dj in range(int(nj[rows].max(initial=0))):
                cols = cols[nj[cols] > dj]
                keys.append(((first[cols] + (di * ncell[1] + dj)) << bits) | cols)
        # sort by cell (then face): one SIMD sort of the packed int64 keys
        key = np.sort(np.concatenate(keys)) if keys else np.zeros(0, np.int64)
        self.cell_face = key & ((1 << bits) - 1)
        self.start = np.concatenate([[0], np.cumsum(np.bincount(key >> bits, minlength=B * self.cells))])

    def count(self, points: np.ndarray) -> np.ndarray:
        """Winding number at each point of each frame.

        points : (B, N, 3) float, metres (frame b against frame b of the mesh)
        returns: (B, N) int32 (0 outside, 1 inside, 2 inside two overlapping parts, ...)
        """
        points = _frames("points", points)
        if points.shape[0] != self.B:
            raise InputShapeError("points", f"({self.B}, N, 3)", points.shape)
        B, N = points.shape[:2]
        return self.count_at(points.reshape(B * N, 3), np.repeat(np.arange(B), N)).reshape(B, N)

    def count_at(self, points: np.ndarray, frame: np.ndarray) -> np.ndarray:
        """Winding number at points of any frames: points (P, 3) float, metres, point i against
        frame ``frame[i]`` (P,) int of the mesh; returns (P,) int32."""
        points = np.asarray(points)
        frame = np.asarray(frame, np.int64)
        if points.ndim != 2 or points.shape[1] != 3 or frame.shape != points.shape[:1]:
            raise InputShapeError("points", "(P, 3) with frame (P,)", points.shape)
        if len(frame) and (frame.min() < 0 or frame.max() >= self.B):
            raise InputShapeError("frame", f"indices < {self.B}", frame.shape)
        p_u = np.ascontiguousarray(points[:, 0], np.float64)
        p_v = np.ascontiguousarray(points[:, 2], np.float64)
        p_y = np.ascontiguousarray(points[:, 1], np.float64)
        h, ncell = self.h, self.ncell
        pi = np.floor((p_u - self.lo[frame, 0]) / h).astype(np.int64)
        pj = np.floor((p_v - self.lo[frame, 1]) / h).astype(np.int64)
        in_grid = (pi >= 0) & (pi < ncell[0]) & (pj >= 0) & (pj < ncell[1])
        pkey = frame * self.cells + np.clip(pi, 0, ncell[0] - 1) * ncell[1] + np.clip(pj, 0, ncell[1] - 1)
        pcount = np.where(in_grid, self.start[pkey + 1] - self.start[pkey], 0)

        P = len(points)
        w = np.zeros(P, np.int64)
        pts_idx = np.flatnonzero(pcount)
        csum = np.cumsum(pcount[pts_idx])
        # blocks of points with at most PAIR_BLOCK candidate pairs
        bounds = np.searchsorted(csum, np.arange(0, csum[-1] if len(csum) else 0, PAIR_BLOCK), side="right")
        bounds = np.unique(np.concatenate([[0], bounds, [len(pts_idx)]]))
        umin, umax, vmin, vmax, ymax = self.box
        for a, b in zip(bounds[:-1], bounds[1:]):
            idx = pts_idx[a:b]
            pc = pcount[idx]
            pt = np.repeat(idx, pc)
            # fid = cell_face[start[cell of p] + 0 .. pc-1] for each point (ragged arange)
            fid = np.take(self.cell_face, np.repeat(self.start[pkey[idx]] - (np.cumsum(pc) - pc), pc) + np.arange(len(pt)))
            pu, pv, py = (np.take(c, pt) for c in (p_u, p_v, p_y))
            # cheap pre-test: the projected bounding box holds p and the face reaches above p
            keep = np.flatnonzero(
                (np.take(umin, fid) <= pu) & (pu <= np.take(umax, fid)) & (np.take(vmin, fid) <= pv)
                & (pv <= np.take(vmax, fid)) & (np.take(ymax, fid) > py)
            )
            pt, fid, pu, pv, py = pt[keep], fid[keep], pu[keep], pv[keep], py[keep]
            w += np.bincount(pt, weights=self._crossings(fid, pu, pv, py), minlength=P).astype(np.int64)
        return w.astype(np.int32)

    def _crossings(self, fid: np.ndarray, pu: np.ndarray, pv: np.ndarray, py: np.ndarray) -> np.ndarray:
        """Signed crossing (-1, 0, +1) of the ray from each point with its candidate face fid."""
        f = fid % self.F
        base = (fid // self.F * self.V)[:, None]
        lo, hi, opp = base + self.edge_lo[f], base + self.edge_hi[f], base + self.opposite[f]  # (P, 3)
        u0, v0 = self.u[lo], self.v[lo]
        du, dv = self.u[hi] - u0, self.v[hi] - v0
        # E_k: canonical edge function (du (pv - v0) - dv (pu - u0)); same bits for both faces of an edge
        E = du * (pv[:, None] - v0) - dv * (pu[:, None] - u0)
        fl = self.flip[f]
        A2 = self.A2[fid]
        ccw = A2 > 0
        # interior side of every edge: (left of canonical, ties left) xor flipped == counter-clockwise
        hit = np.all(((E >= 0) ^ fl) == ccw[:, None], axis=1)
        Et = np.where(fl, -E, E)  # edge functions in the face's own orientation
        # crossing above p: sum_k Et_k (y_opp_k - p_y) / A2 > 0  (barycentric depth minus p_y)
        above = (np.sum(Et * (self.y[opp] - py[:, None]), axis=1) > 0) == ccw
        return np.where(hit & above, np.where(ccw, -1, 1), 0)


def winding_numbers(points: np.ndarray, verts: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Winding number of a closed mesh at each point, by signed ray crossings (module doc).

    points : (B, N, 3) float, metres
    verts  : (B, V, 3) float, metres, closed mesh with outward (counter-clockwise) faces
    faces  : (F, 3) int
    returns: (B, N) int32 (0 outside, 1 inside, 2 inside two overlapping parts, ...)
    """
    points = _frames("points", points)
    verts = _frames("verts", verts)
    B, N = points.shape[:2]
    if verts.shape[0] != B:
        raise InputShapeError("verts", f"({B}, V, 3)", verts.shape)
    check_faces(faces, verts.shape[1])
    out = np.empty((B, N), np.int32)
    for b0 in range(0, B, FRAME_BLOCK):
        sl = slice(b0, b0 + FRAME_BLOCK)
        out[sl] = WindingGrid(verts[sl], faces).count(points[sl])
    return out
