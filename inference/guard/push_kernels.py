"""The guard's screen and plane push, compiled (numba, one thread): ``push._push_block`` point by point.

The maths is ``inference.guard``'s: a point whose s_j = p . n_j - c_j . n_j is at least the
margin (plus a rounding tolerance) for every candidate is never pushed and is skipped (the
screen); for the others, with candidates c_j and normals n_j (j < k),

    d2_j = |p - c_j|^2,  s_j = (p - c_j) . n_j,  j* = argmin d2_j (the first of equal ones),

unless p lies behind the plane of a candidate it projects onto (d2_j - s_j^2 < _TANGENT_M^2, s_j <
0) no more than _FARTHER_M farther than c_j*: then the deepest such plane (least s_j) where it is
deeper than j*'s. The push delta = margin - s_j* (> 0), shortened by the squeeze of the candidates
ahead of p that face it (min (s_j - s*) / max(1 - n*.n_j, 1), not below 0), by ``max_push`` and
by the open collider's border; p <- p + delta n*, ``iterations`` times while it moves.

Every quantity in float32 in numpy's order of operations (no fast-math: no fused multiply-adds),
the constants rounded to float32 as numpy rounds a Python float against a float32 array, so that
the result is bitwise the numpy version's (``tests/test_guard_push_kernel.py`` keeps it as the
reference). The numpy screen and push made ~20 (k, L) temporaries per pass: ~1.7 ms an
outfit-frame of T-shirt + jacket (02_02, 30 frames), ~0.3 compiled.

Units: metres. Arrays: float32 coordinate planes (3, n), int64 flat candidate ids, bool masks.
"""
from __future__ import annotations

import numba
import numpy as np

_JIT = {"nogil": True, "cache": True, "fastmath": False}


@numba.njit(**_JIT)
def push_points(P, C, Nrm, offset, flat, extra, across, keep, live, M, margin, max_push, boundary, reach2, iterations, tangent2,
                farther, opposing_cos, squeeze2):
    """Screen, then push the points P (3, L) float32 (in place) out of their candidates' planes.

    C, Nrm    : (3, .) float32 candidate positions and unit normals; offset (.,) float32 their
                c . n (``push._push_planes``)
    flat      : (k, L) int64 candidate ids into them, extra (k2, L) more (the per-frame nearest;
                k2 may be 0), in that order
    across    : (k, L) bool, candidates of ``flat`` across a gap (they limit the push), or (0, 0): none
    keep      : float32; the screen: a point whose s_j = p . n_j - o_j, summed in numpy's order
                (-o_j + n_x x + n_y y + n_z z), is >= keep for every candidate is never pushed (the
                push is at most margin - s*); live (L,) bool out: the points it kept
    M         : the collider's vertex count (a flat id mod M is the vertex); boundary (M,) bool its
                border vertices, or (0,): none; reach2 float32, the squared border reach
    margin, max_push, tangent2, farther, opposing_cos, squeeze2 : float32 (max_push inf: none)
    """
    k = flat.shape[0]
    K = k + extra.shape[0]
    L = flat.shape[1]
    has_across = across.shape[0] > 0
    has_boundary = boundary.shape[0] > 0
    zero = np.float32(0.0)
    one = np.float32(1.0)
    d2 = np.empty(K, np.float32)
    s = np.empty(K, np.float32)
    ids = np.empty(K, np.int64)
    for q in range(L):
        x, y, z = P[0, q], P[1, q], P[2, q]
        for c in range(K):
            ids[c] = flat[c, q] if c < k else extra[c - k, q]  # written inline: through a helper the kernel ran 3x slower
        # the screen: the least s_j over flat, and over extra, as two numpy minima (a NaN: not kept)
        lo = np.float32(np.inf)
        nan = False
        for c in range(K):
            f = ids[c]
            sj = -offset[f]
            sj += Nrm[0, f] * x
            sj += Nrm[1, f] * y
            sj += Nrm[2, f] * z
            nan |= sj != sj  # no branch: one cost ~30 % here
            if sj < lo:
                lo = sj
        live[q] = (not nan) and lo < keep
        if not live[q]:
            continue
        for _ in range(iterations):
            j = 0
            for c in range(K):
                f = ids[c]
                dx, dy, dz = x - C[0, f], y - C[1, f], z - C[2, f]
                d2[c] = dx * dx + dy * dy + dz * dz
                s[c] = dx * Nrm[0, f] + dy * Nrm[1, f] + dz * Nrm[2, f]
                if d2[c] < d2[j]:
                    j = c
            s_near = s[j]
            reach = np.sqrt(d2[j]) + farther
            deep = -1
            for c in range(K):
                if s[c] < zero and d2[c] - s[c] * s[c] < tangent2 and np.sqrt(d2[c]) <= reach:
                    if deep < 0 or s[c] < s[deep]:
                        deep = c
            if deep >= 0 and s[deep] < s_near:
                j = deep
            f = ids[j]
            nx, ny, nz = Nrm[0, f], Nrm[1, f], Nrm[2, f]
            s_star = s[j]
            delta = margin - s_star
            if not delta > zero:
                break
            bal = np.float32(np.inf)
            for c in range(K):
                g = ids[c]
                dx, dy, dz = x - C[0, g], y - C[1, g], z - C[2, g]
                ahead = dx * nx + dy * ny + dz * nz < zero
                if has_across and c < k:
                    ahead = ahead or across[c, q]
                a = nx * Nrm[0, g] + ny * Nrm[1, g] + nz * Nrm[2, g]
                if ahead and a < opposing_cos and d2[c] < squeeze2:
                    bal = min(bal, (s[c] - s_star) / max(one - a, one))
            delta = min(delta, max(bal, zero))
            delta = min(delta, max_push)
            if has_boundary and boundary[f % M] and d2[j] - s_star * s_star > reach2:
                delta = zero
            if delta == zero:
                break
            x += delta * nx
            y += delta * ny
            z += delta * nz
        P[0, q], P[1, q], P[2, q] = x, y, z

@numba.njit(**_JIT)
def collider_planes(X, faces, face_ids, indptr, indices, data, collider_ids, orientation, points, normals, fn):
    """``GuardPlan.collider_planes`` in one pass per frame: the plan's collider vertices and their
    unit outward normals as frame-major coordinate planes, written into points, normals (3, BT*S).

    X (BT, M, 3) float32 the posed collider; faces (F, 3) int64 and face_ids (Fs,) the plan's faces;
    the (S, Fs) incidence as CSR (indptr, indices, data); collider_ids (S,); orientation +-1;
    fn (Fs, 3) float32 scratch. Per frame, every face's (v1 - v0) x (v2 - v0) in float32, each
    vertex's sum over its incident faces in the CSR's order from zero (scipy's y += a x), the norm
    sqrt((x^2 + y^2) + z^2) in float32 (numpy's einsum over the three) and the normal times
    orientation / max(norm, 1e-20): bitwise numpy's float32 arithmetic, without the (Fs, T)
    temporaries (~0.7 ms a frame of T-shirt + jacket went to them)."""
    BT = X.shape[0]
    S, Fs = collider_ids.shape[0], face_ids.shape[0]
    o = np.float32(orientation)
    tiny = np.float32(1e-20)
    for b in range(BT):
        for q in range(Fs):
            f = face_ids[q]
            i0, i1, i2 = faces[f, 0], faces[f, 1], faces[f, 2]
            ax, ay, az = X[b, i1, 0] - X[b, i0, 0], X[b, i1, 1] - X[b, i0, 1], X[b, i1, 2] - X[b, i0, 2]
            bx, by, bz = X[b, i2, 0] - X[b, i0, 0], X[b, i2, 1] - X[b, i0, 1], X[b, i2, 2] - X[b, i0, 2]
            fn[q, 0] = ay * bz - az * by
            fn[q, 1] = az * bx - ax * bz
            fn[q, 2] = ax * by - ay * bx
        for s in range(S):
            y0, y1, y2 = np.float32(0.0), np.float32(0.0), np.float32(0.0)
            for jj in range(indptr[s], indptr[s + 1]):
                q, a = indices[jj], data[jj]
                y0 += a * fn[q, 0]
                y1 += a * fn[q, 1]
                y2 += a * fn[q, 2]
            scale = o / max(np.sqrt(y0 * y0 + y1 * y1 + y2 * y2), tiny)
            col = b * S + s
            normals[0, col], normals[1, col], normals[2, col] = y0 * scale, y1 * scale, y2 * scale
            v = collider_ids[s]
            points[0, col], points[1, col], points[2, col] = X[b, v, 0], X[b, v, 1], X[b, v, 2]


def warm_up() -> None:
    """Compile the kernel (or load numba's cache) on one point and one candidate, with the types
    every call passes (``push._push_block``), so that no request pays the compilation (~1 s)."""
    P = np.zeros((3, 1), np.float32)
    C = np.ascontiguousarray(np.array([[0.0], [0.0], [0.01]], np.float32))
    Nrm = np.ascontiguousarray(np.array([[0.0], [0.0], [1.0]], np.float32))
    f32 = np.float32
    push_points(P, C, Nrm, np.zeros(1, np.float32), np.zeros((1, 1), np.int64), np.zeros((0, 1), np.int64), np.zeros((0, 0), bool),
                f32(np.inf), np.zeros(1, bool), 1, f32(0.004), f32(np.inf), np.zeros(0, bool), f32(0.0), 2, f32(1e-4), f32(0.02), f32(-0.5),
                f32(4e-4))
    # and the collider's planes: a plan's faces are read-only int64 (``collider_topology``), the
    # incidence scipy's int32 CSR of float32 ones
    faces = np.array([[0, 1, 2]], np.int64)
    faces.flags.writeable = False
    out = np.empty((3, 3), np.float32)
    collider_planes(np.zeros((1, 3, 3), np.float32), faces, np.zeros(1, np.int64), np.array([0, 1, 1, 1], np.int32), np.zeros(1, np.int32),
                    np.ones(1, np.float32), np.arange(3, dtype=np.int64), 1.0, out, out.copy(), np.empty((1, 3), np.float32))
