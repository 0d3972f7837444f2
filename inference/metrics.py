"""Evaluation metrics (DESIGN.md §5): one implementation for tests, training and bench.

Inside test. The posed body is a closed, outward-oriented triangle mesh that intersects itself
under LBS, so "inside" means a winding number >= 1 (generalised winding number > 0.5), not
the parity of ray crossings and not a closest-face sign (``trimesh.contains`` misjudges points
inside two overlapping parts). For a closed mesh the winding number is an integer and equals the
signed number of crossings of any ray from the point:

    w(p) = sum over faces f hit by the ray p + t e_y (t > 0) of sign(n_f . e_y)

(an outward face is left through, +1, or entered, -1). ``winding_numbers`` counts these exactly
in float64, vectorised over a 2-D grid of the faces projected along the ray (x, z): a point only
tests the faces binned in its grid cell. Point-in-projected-triangle uses edge functions that
are evaluated from the edge's two vertices in canonical (lower index first) order, so the two
faces sharing an edge compute the bitwise same value and a ray through the edge is counted
once (ties go to the left of the canonical edge). Only rays through a projected vertex, or
points on the surface, are ambiguous (measure zero). Cost per frame for 5k points on
the 13,718-vertex body (~20 ms measured, bench/bench_guard.py); exact, unlike a fast-multipole
approximation (libigl's fast winding number took 65-100 ms on the same points).

Distances (``unsigned_distance``) use libigl's AABB point-mesh distance (exact).
Self-intersections: a skin vertex is in self-intersection when the point 1 mm inside it along
its normal has winding number >= 2 with respect to the body's major components (it is inside
its own part and inside another one); small components (the eyes and teeth, < 10 % of the
vertices) are ignored. Garment vertices closer than ``exclusion_radius_m`` to such a vertex are
reported separately ("clean" rates), as the thesis does (ch. 6.6.1).

Units: metres. Shapes: batch axis first; a frame is one (points, mesh) pair.
"""
from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from inference.errors import InputShapeError
from inference.guard import major_components, vertex_normals

# Offset of the self-intersection probe inside a skin vertex, metres (thinner than any limb,
# thicker than float32 noise).
SELF_INTERSECTION_PROBE_M = 0.001
# HOOD-style collision threshold: a garment vertex closer than this to the body (or inside).
HOOD_THRESHOLD_M = 0.001
# Grid cell of the ray-crossing count, in multiples of the median edge length.
_CELL_EDGES = 1.5
# Candidate (point, face) pairs evaluated at once; bounds memory (~130 bytes per pair).
_PAIR_BLOCK = 2_000_000


# ------------------------------------------------------------------------------ checks
def _frames(name: str, a: np.ndarray, ndim: int) -> np.ndarray:
    a = np.asarray(a)
    if a.ndim != ndim or a.shape[-1] != 3:
        raise InputShapeError(name, "(B, N, 3)" if ndim == 3 else "(B, T, N, 3)", a.shape)
    return a


def _faces(faces: np.ndarray, num_vertices: int) -> np.ndarray:
    faces = np.asarray(faces)
    if faces.ndim != 2 or faces.shape[1] != 3 or faces.min() < 0 or faces.max() >= num_vertices:
        raise InputShapeError("faces", f"(F, 3) indices < {num_vertices}", faces.shape)
    return faces.astype(np.int64)


# ------------------------------------------------------------------------------ inside
def winding_numbers(points: np.ndarray, verts: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Winding number of a closed mesh at each point, by signed ray crossings (see module doc).

    points : (B, N, 3) float, metres
    verts  : (B, V, 3) float, metres, closed mesh with outward (counter-clockwise) faces
    faces  : (F, 3) int
    returns: (B, N) int32 (0 outside, 1 inside, 2 inside two overlapping parts, ...)
    """
    points = _frames("points", points, 3)
    verts = _frames("verts", verts, 3)
    B, N = points.shape[:2]
    if verts.shape[0] != B:
        raise InputShapeError("verts", f"({B}, V, 3)", verts.shape)
    faces = _faces(faces, verts.shape[1])
    out = np.empty((B, N), np.int32)
    for b0 in range(0, B, _FRAME_BLOCK):  # blocks of frames bound the memory of the face bins
        out[b0 : b0 + _FRAME_BLOCK] = _winding_block(points[b0 : b0 + _FRAME_BLOCK], verts[b0 : b0 + _FRAME_BLOCK], faces)
    return out


# Frames per block in ``winding_numbers``.
_FRAME_BLOCK = 16


def _winding_block(points: np.ndarray, verts: np.ndarray, faces: np.ndarray) -> np.ndarray:
    B, N = points.shape[:2]
    F = len(faces)
    p = points.astype(np.float64).reshape(B * N, 3)
    tri = verts.astype(np.float64)[:, faces]  # (B, F, 3 corners, 3)
    u, v, y = tri[..., 0], tri[..., 2], tri[..., 1]  # project along +y onto (u, v) = (x, z)
    # A2 = twice the signed projected area; n_y = -A2, so a crossing counts -sign(A2)
    A2 = (u[..., 1] - u[..., 0]) * (v[..., 2] - v[..., 0]) - (v[..., 1] - v[..., 0]) * (u[..., 2] - u[..., 0])

    # grid over the projected mesh: each face binned into the cells its bounding box covers
    h = _CELL_EDGES * float(np.median(np.linalg.norm(tri[0, :, 1] - tri[0, :, 0], axis=-1)))
    umin, umax, vmin, vmax = u.min(-1), u.max(-1), v.min(-1), v.max(-1)  # (B, F)
    lo = np.stack([umin.min(1), vmin.min(1)], -1)  # (B, 2): each frame's own grid origin
    extent = np.stack([umax.max(1), vmax.max(1)], -1) - lo
    ncell = np.floor(extent.max(0) / h).astype(np.int64) + 1
    i0 = np.floor((umin - lo[:, :1]) / h).astype(np.int64)
    i1 = np.floor((umax - lo[:, :1]) / h).astype(np.int64)
    j0 = np.floor((vmin - lo[:, 1:]) / h).astype(np.int64)
    j1 = np.floor((vmax - lo[:, 1:]) / h).astype(np.int64)
    wj = (j1 - j0 + 1).ravel()
    count = np.where(A2.ravel() != 0, (i1 - i0 + 1).ravel() * wj, 0)  # zero-area faces never count
    face = np.repeat(np.arange(B * F), count)  # (pairs,) frame-major face id b*F + f
    r = np.arange(len(face)) - np.repeat(np.cumsum(count) - count, count)
    cell_of = (np.repeat(i0.ravel(), count) + r // np.repeat(wj, count)) * ncell[1] + np.repeat(j0.ravel(), count) + r % np.repeat(wj, count)
    cells = ncell[0] * ncell[1]
    key = face // F * cells + cell_of
    order = np.argsort(key, kind="stable")
    cell_face = face[order]
    start = np.concatenate([[0], np.cumsum(np.bincount(key, minlength=B * cells))])

    # each point against the faces of its cell
    plo = np.repeat(lo, N, axis=0)
    pi = np.floor((p[:, 0] - plo[:, 0]) / h).astype(np.int64)
    pj = np.floor((p[:, 2] - plo[:, 1]) / h).astype(np.int64)
    inside_grid = (pi >= 0) & (pi < ncell[0]) & (pj >= 0) & (pj < ncell[1])
    pkey = np.repeat(np.arange(B), N) * cells + np.clip(pi, 0, ncell[0] - 1) * ncell[1] + np.clip(pj, 0, ncell[1] - 1)
    pcount = np.where(inside_grid, start[pkey + 1] - start[pkey], 0)

    # per-face data: canonical edges k (corner k -> k+1), flipped where the index order is reversed
    nxt = [1, 2, 0]
    flip = faces > faces[:, nxt]  # (F, 3)
    lo_c = np.where(flip, np.array(nxt), np.arange(3))  # corner of the canonical edge start
    hi_c = np.where(flip, np.arange(3), np.array(nxt))
    ar = np.arange(F)[:, None]
    data = np.concatenate(
        [
            u[:, ar, lo_c], v[:, ar, lo_c],  # canonical edge start (B, F, 3) each
            u[:, ar, hi_c] - u[:, ar, lo_c], v[:, ar, hi_c] - v[:, ar, lo_c],  # canonical edge vectors
            y[..., [2, 0, 1]],  # depth of the corner opposite edge k
            A2[..., None],
        ],
        axis=-1,
    ).reshape(B * F, 16)
    flip_f = np.broadcast_to(flip, (B, F, 3)).reshape(B * F, 3)
    # cheap pre-test: the projected bounding box holds p and the face reaches above p
    umin, umax, vmin, vmax, ymax = (a.ravel() for a in (umin, umax, vmin, vmax, y.max(-1)))
    p_u, p_v, p_y = (np.ascontiguousarray(p[:, c]) for c in (0, 2, 1))

    w = np.zeros(B * N, np.int64)
    pts_idx = np.flatnonzero(pcount)
    csum = np.cumsum(pcount[pts_idx])
    # blocks of points with at most _PAIR_BLOCK candidate pairs
    bounds = np.searchsorted(csum, np.arange(0, csum[-1] if len(csum) else 0, _PAIR_BLOCK), side="right")
    bounds = np.unique(np.concatenate([[0], bounds, [len(pts_idx)]]))
    for a, b in zip(bounds[:-1], bounds[1:]):
        idx = pts_idx[a:b]
        pc = pcount[idx]
        pt = np.repeat(idx, pc)
        # fid = cell_face[start[cell of p] + 0 .. pc-1] for each point (ragged arange)
        fid = np.take(cell_face, np.repeat(start[pkey[idx]] - (np.cumsum(pc) - pc), pc) + np.arange(len(pt)))
        pu, pv, py = (np.repeat(a[idx], pc) for a in (p_u, p_v, p_y))
        keep = np.flatnonzero(
            (np.take(umin, fid) <= pu) & (pu <= np.take(umax, fid)) & (np.take(vmin, fid) <= pv) & (pv <= np.take(vmax, fid)) & (np.take(ymax, fid) > py)
        )
        pt, fid, pu, pv, py = pt[keep], fid[keep], pu[keep], pv[keep], py[keep]
        d = data[fid]
        # E_k: canonical edge function (du (pv - v0) - dv (pu - u0)); same bits for both faces of an edge
        E = d[:, 6:9] * (pv[:, None] - d[:, 3:6]) - d[:, 9:12] * (pu[:, None] - d[:, 0:3])
        fl = flip_f[fid]
        ccw = d[:, 15] > 0
        # interior side of every edge: (left of canonical, ties left) xor flipped == counter-clockwise
        hit = np.all(((E >= 0) ^ fl) == ccw[:, None], axis=1)
        Et = np.where(fl, -E, E)  # edge functions in the face's own orientation
        # crossing above p: sum_k Et_k (y_opp_k - p_y) / A2 > 0  (barycentric depth minus p_y)
        above = (np.sum(Et * (d[:, 12:15] - py[:, None]), axis=1) > 0) == ccw
        contrib = np.where(hit & above, np.where(ccw, -1, 1), 0)
        w += np.bincount(pt, weights=contrib, minlength=B * N).astype(np.int64)
    return w.reshape(B, N).astype(np.int32)


def inside_mask(points: np.ndarray, verts: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Points inside a closed mesh: winding number >= 1 (generalised winding number > 0.5).

    points : (B, N, 3) ; verts : (B, V, 3) ; faces : (F, 3) ; returns (B, N) bool
    """
    return winding_numbers(points, verts, faces) > 0


# ------------------------------------------------------------------------------ distance
def unsigned_distance(points: np.ndarray, verts: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Exact distance from each point to the closest point of the mesh (libigl AABB tree).

    points : (B, N, 3) ; verts : (B, V, 3) ; faces : (F, 3)
    returns: distance (B, N) float32 metres, closest face (B, N) int64, closest point (B, N, 3) float64
    """
    import igl  # libigl: only the metrics need it

    points = _frames("points", points, 3)
    verts = _frames("verts", verts, 3)
    faces = _faces(faces, verts.shape[1])
    B, N = points.shape[:2]
    if verts.shape[0] != B:
        raise InputShapeError("verts", f"({B}, V, 3)", verts.shape)
    d = np.empty((B, N), np.float32)
    fi = np.empty((B, N), np.int64)
    cp = np.empty((B, N, 3), np.float64)
    for b in range(B):  # one C++ call per frame (libigl has no batch axis)
        d2, fi[b], cp[b] = igl.point_mesh_squared_distance(
            np.ascontiguousarray(points[b], np.float64), np.ascontiguousarray(verts[b], np.float64), faces
        )
        d[b] = np.sqrt(d2)
    return d, fi, cp


def signed_distance(points: np.ndarray, verts: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Signed distance to a closed mesh: |closest point| distance, negative inside (winding >= 1).

    points : (B, N, 3) ; verts : (B, V, 3) ; faces : (F, 3) ; returns (B, N) float32, metres
    """
    d = unsigned_distance(points, verts, faces)[0]
    return np.where(inside_mask(points, verts, faces), -d, d).astype(np.float32)


# ------------------------------------------------------------------------------ self-intersection
def self_intersecting_vertices(verts: np.ndarray, faces: np.ndarray, probe_m: float = SELF_INTERSECTION_PROBE_M) -> np.ndarray:
    """Skin vertices inside another part of the body: w(v - probe n_v) >= 2 on the major components.

    verts : (B, V, 3) float32, metres, posed body ; faces : (F, 3)
    returns (B, V) bool (False on small components: eyes, teeth)
    """
    verts = _frames("verts", verts, 3)
    faces = _faces(faces, verts.shape[1])
    keep = major_components(faces, verts.shape[1])
    mfaces = faces[keep[faces].all(1)]
    ids = np.flatnonzero(keep)
    n = vertex_normals(verts, mfaces)
    probe = verts[:, ids] - probe_m * n[:, ids]
    out = np.zeros(verts.shape[:2], bool)
    out[:, ids] = winding_numbers(probe, verts, mfaces) >= 2
    return out


def _near(points: np.ndarray, centres: np.ndarray, mask: np.ndarray, radius_m: float) -> np.ndarray:
    """(B, N) bool: points within radius_m of a masked centre of the same frame."""
    out = np.zeros(points.shape[:2], bool)
    for b in range(len(points)):  # cKDTree has no batch axis; one tree per frame
        c = centres[b][mask[b]]
        if len(c):
            d, _ = cKDTree(c).query(points[b], k=1, distance_upper_bound=radius_m)
            out[b] = d <= radius_m
    return out


def self_intersection_exclusion(verts: np.ndarray, faces: np.ndarray, radius_m: float = 0.02) -> np.ndarray:
    """Body region in self-intersection: skin vertices within radius_m of a self-intersecting one.

    verts : (B, V, 3) float32, metres ; faces : (F, 3) ; returns (B, V) bool
    """
    verts = _frames("verts", verts, 3)
    return _near(verts, verts, self_intersecting_vertices(verts, faces), radius_m)


def near_self_intersection(points: np.ndarray, verts: np.ndarray, faces: np.ndarray, radius_m: float = 0.02) -> np.ndarray:
    """Points within radius_m of a self-intersecting skin vertex of the same frame.

    points : (B, N, 3) ; verts : (B, V, 3) ; faces : (F, 3) ; returns (B, N) bool
    """
    points = _frames("points", points, 3)
    verts = _frames("verts", verts, 3)
    return _near(points, verts, self_intersecting_vertices(verts, faces), radius_m)


# ------------------------------------------------------------------------------ rates
def collision_rates(
    garment_points: np.ndarray,
    body_verts: np.ndarray,
    body_faces: np.ndarray,
    margin_m: float = 0.002,
    exclusion_radius_m: float = 0.02,
) -> dict[str, float | int]:
    """Garment-body collision rates over all frames (DESIGN.md §5), signed distance sd:

    inside_pct        : 100 * #(sd < 0) / #points                     (winding number >= 1)
    inside_pct_clean  : the same over points farther than exclusion_radius_m from every
                        self-intersecting skin vertex of their frame (zero-collision goals)
    within_margin_pct : 100 * #(sd < margin_m) / #points                (inside or too close)
    within_1mm_pct    : 100 * #(sd < 1 mm) / #points                    (HOOD-style)
    counts            : points, inside, clean_points, inside_clean, within_margin, within_1mm,
                        self_intersecting_vertices (summed over frames)

    garment_points : (B, T, N, 3) float32, metres ; body_verts : (B, T, Vb, 3) float32, metres
    """
    gp = _frames("garment_points", garment_points, 4)
    bv = _frames("body_verts", body_verts, 4)
    if gp.shape[:2] != bv.shape[:2]:
        raise InputShapeError("body_verts", f"({gp.shape[0]}, {gp.shape[1]}, Vb, 3)", bv.shape)
    B, T, N, _ = gp.shape
    pts = gp.reshape(B * T, N, 3)
    body = bv.reshape(B * T, -1, 3)
    inside = inside_mask(pts, body, body_faces)
    dist = unsigned_distance(pts, body, body_faces)[0]
    sd = np.where(inside, -dist, dist)
    selfx = self_intersecting_vertices(body, body_faces)
    excluded = _near(pts, body, selfx, exclusion_radius_m)
    clean = ~excluded
    n_points, n_clean = int(inside.size), int(clean.sum())
    counts = {
        "points": n_points,
        "inside": int(inside.sum()),
        "clean_points": n_clean,
        "inside_clean": int((inside & clean).sum()),
        "within_margin": int((sd < margin_m).sum()),
        "within_1mm": int((sd < HOOD_THRESHOLD_M).sum()),
        "self_intersecting_vertices": int(selfx.sum()),
    }
    pct = lambda a, n: 100.0 * a / n if n else 0.0  # noqa: E731
    return {
        "inside_pct": pct(counts["inside"], n_points),
        "inside_pct_clean": pct(counts["inside_clean"], n_clean),
        "within_margin_pct": pct(counts["within_margin"], n_points),
        "within_1mm_pct": pct(counts["within_1mm"], n_points),
        **counts,
    }


# ------------------------------------------------------------------------------ layers
def layer_violations(
    inner_points: np.ndarray,
    outer_verts: np.ndarray,
    outer_faces: np.ndarray,
    tolerance_m: float = 0.0,
) -> tuple[np.ndarray, np.ndarray]:
    """Inner-garment vertices on the wrong (outer) side of the next outer layer.

    For an inner point p, c is its closest point on the (open) outer mesh, on face f with unit
    normal n_f (outward: the outer garment's faces wind counter-clockwise seen from outside).
    p is covered when c is not on the outer mesh's border (p projects onto the surface), and
    violates the layer order when covered and (p - c) . n_f > tolerance_m.

    inner_points : (B, N, 3) ; outer_verts : (B, Vo, 3) ; outer_faces : (Fo, 3)
    returns      : violation (B, N) bool, covered (B, N) bool
    """
    inner_points = _frames("inner_points", inner_points, 3)
    outer_verts = _frames("outer_verts", outer_verts, 3)
    faces = _faces(outer_faces, outer_verts.shape[1])
    _, fi, c = unsigned_distance(inner_points, outer_verts, faces)
    tri = np.take_along_axis(outer_verts.astype(np.float64)[:, faces], fi[..., None, None], 1)  # (B, N, 3, 3)
    e1, e2 = tri[..., 1, :] - tri[..., 0, :], tri[..., 2, :] - tri[..., 0, :]
    n = np.cross(e1, e2)
    area2 = np.linalg.norm(n, axis=-1)
    n = n / np.maximum(area2, 1e-30)[..., None]
    # barycentric weight of corner k = area of the sub-triangle opposite k; 0 <=> c on edge (k+1, k+2)
    bary = np.stack([np.linalg.norm(np.cross(tri[..., (k + 1) % 3, :] - c, tri[..., (k + 2) % 3, :] - c), axis=-1) for k in range(3)], -1)
    bary = bary / np.maximum(area2, 1e-30)[..., None]
    on_edge = bary < 1e-6
    f = faces[fi]  # (B, N, 3) corners
    V1 = outer_verts.shape[1] + 1
    border = _border_edge_keys(faces, V1)
    edge_is_border = np.stack(
        [np.isin(np.minimum(f[..., (k + 1) % 3], f[..., (k + 2) % 3]) * V1 + np.maximum(f[..., (k + 1) % 3], f[..., (k + 2) % 3]), border) for k in range(3)],
        -1,
    )
    covered = ~(on_edge & edge_is_border).any(-1)
    side = np.einsum("bnc,bnc->bn", inner_points.astype(np.float64) - c, n)
    return covered & (side > tolerance_m), covered


def _border_edge_keys(faces: np.ndarray, V1: int) -> np.ndarray:
    """Keys min * V1 + max of the edges used by a single face (the border of an open mesh)."""
    e = np.sort(faces[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1)
    uniq, count = np.unique(e[:, 0] * V1 + e[:, 1], return_counts=True)
    return uniq[count == 1]


def layer_violation_pct(inner_points: np.ndarray, outer_verts: np.ndarray, outer_faces: np.ndarray, tolerance_m: float = 0.0) -> float:
    """100 * #(covered inner vertices outside the outer layer) / #inner vertices, all frames.

    inner_points : (B, N, 3) or (B, T, N, 3) ; outer_verts : (B, Vo, 3) or (B, T, Vo, 3)
    """
    ip, ov = np.asarray(inner_points), np.asarray(outer_verts)
    if ip.ndim == 4:
        ip, ov = ip.reshape((-1,) + ip.shape[2:]), ov.reshape((-1,) + ov.shape[2:])
    bad, _ = layer_violations(ip, ov, outer_faces, tolerance_m)
    return 100.0 * float(bad.mean()) if bad.size else 0.0
