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


@numba.njit(inline="always", **_JIT)
def _ratio(num, den):
    """num / den, 0 where den == 0 (``inference.triangles._ratio``)."""
    return num / den if den != 0 else np.float32(0.0)


@numba.njit(inline="always", **_JIT)
def _select(mask, new, old):
    """old + mask (new - old) (``inference.triangles._select``, the same rounding)."""
    return old + np.float32(mask) * (new - old)


@numba.njit(**_JIT)
def refine_points(P, C, Nrm, flat, ring, valence, M, kr, margin, out):
    """``push._refine_block``, point by point: P (3, L) float32 pushed points, C and Nrm (3, BT*M)
    float32 the frames' collider planes, flat (k, L) int64 candidate ids, ring (M, R, 2) int32 and
    valence (M,) int32 the one-rings (``GuardPlan.ring``), kr the candidates checked, margin float32;
    out (3, L) float32.

    Per point, its kr nearest candidates (by float32 squared distance, equal ones in candidate
    order), the closest point q on each one's ring triangles (Ericson §5.1.5 as
    ``inference.triangles.closest_barycentrics``, its operations in its order), the nearest q over
    them (the first of equal ones) and the normal n_q interpolated from the corners' vertex
    normals: a point with (p - q) . n_q < 0 goes to q + margin n_q / |n_q|. Every quantity in float32
    in numpy's order of operations, so that a point's answer is bitwise the numpy form's wherever
    both pick the same candidates (numpy's partial sort orders equal distances its own way)."""
    k, L = flat.shape
    zero, one = np.float32(0.0), np.float32(1.0)
    d2 = np.empty(k, np.float32)
    pick = np.empty(kr, np.int64)
    for q in range(L):
        x, y, z = P[0, q], P[1, q], P[2, q]
        for j in range(k):
            g = flat[j, q]
            dx, dy, dz = x - C[0, g], y - C[1, g], z - C[2, g]
            d2[j] = dx * dx + dy * dy + dz * dz
        for a in range(kr):  # the kr nearest, nearest first
            best = -1
            for j in range(k):
                taken = False
                for b in range(a):
                    if pick[b] == j:
                        taken = True
                if not taken and (best < 0 or d2[j] < d2[best]):
                    best = j
            pick[a] = best
        found = False
        best_r = np.float32(np.inf)
        bv, bw, r0, r1, r2 = zero, zero, zero, zero, zero
        ia, ib, ic = 0, 0, 0
        for a in range(kr):
            f = flat[pick[a], q]
            s = f % M
            base = f - s
            cx, cy, cz = C[0, f], C[1, f], C[2, f]
            apx, apy, apz = x - cx, y - cy, z - cz
            for t in range(max(valence[s], 1)):
                gb, gc = base + ring[s, t, 0], base + ring[s, t, 1]
                abx, aby, abz = C[0, gb] - cx, C[1, gb] - cy, C[2, gb] - cz
                acx, acy, acz = C[0, gc] - cx, C[1, gc] - cy, C[2, gc] - cz
                d1 = abx * apx + aby * apy + abz * apz
                dd2 = acx * apx + acy * apy + acz * apz
                bb = abx * abx + aby * aby + abz * abz
                bc = abx * acx + aby * acy + abz * acz
                cc = acx * acx + acy * acy + acz * acz
                d3, d4, d5, d6 = d1 - bb, dd2 - bc, d1 - bc, dd2 - cc
                va, vb, vc = d3 * d6 - d5 * d4, d5 * dd2 - d1 * d6, d1 * d4 - d3 * dd2
                total = va + vb + vc
                v, w = _ratio(vb, total), _ratio(vc, total)
                on_bc = (va <= zero) and (d4 >= d3) and (d5 >= d6)
                t_bc = _ratio(d4 - d3, (d4 - d3) + (d5 - d6))
                v, w = _select(on_bc, one - t_bc, v), _select(on_bc, t_bc, w)
                on_ac = (vb <= zero) and (dd2 >= zero) and (d6 <= zero)
                v, w = v * np.float32(not on_ac), _select(on_ac, _ratio(dd2, dd2 - d6), w)
                on_ab = (vc <= zero) and (d1 >= zero) and (d3 <= zero)
                v, w = _select(on_ab, _ratio(d1, d1 - d3), v), w * np.float32(not on_ab)
                at_c = (d6 >= zero) and (d5 <= d6)
                v, w = v * np.float32(not at_c), _select(at_c, one, w)
                at_b = (d3 >= zero) and (d4 <= d3)
                v, w = _select(at_b, one, v), w * np.float32(not at_b)
                at_a = (d1 <= zero) and (dd2 <= zero)
                v, w = v * np.float32(not at_a), w * np.float32(not at_a)
                rx = apx - v * abx - w * acx
                ry = apy - v * aby - w * acy
                rz = apz - v * abz - w * acz
                dist = rx * rx + ry * ry + rz * rz
                if not found or dist < best_r:
                    found = True
                    best_r, bv, bw, r0, r1, r2 = dist, v, w, rx, ry, rz
                    ia, ib, ic = f, gb, gc
        ub = one - bv - bw
        nx = ub * Nrm[0, ia] + bv * Nrm[0, ib] + bw * Nrm[0, ic]
        ny = ub * Nrm[1, ia] + bv * Nrm[1, ib] + bw * Nrm[1, ic]
        nz = ub * Nrm[2, ia] + bv * Nrm[2, ib] + bw * Nrm[2, ic]
        norm = np.float32(np.sqrt(nx * nx + ny * ny + nz * nz))
        if r0 * nx + r1 * ny + r2 * nz < zero and norm > zero:
            scale = margin / norm
            out[0, q], out[1, q], out[2, q] = x - r0 + scale * nx, y - r1 + scale * ny, z - r2 + scale * nz
        else:
            out[0, q], out[1, q], out[2, q] = x, y, z


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
    # the closest-triangle check (``push._refine_block``): a plan's rings and valences are int32
    ring = np.zeros((1, 1, 2), np.int32)
    refine_points(P, C, Nrm, np.zeros((1, 1), np.int64), ring, np.ones(1, np.int32), 1, 1, f32(0.004), np.empty((3, 1), np.float32))
    # and the collider's planes: a plan's faces are read-only int64 (``collider_topology``), the
    # incidence scipy's int32 CSR of float32 ones
    faces = np.array([[0, 1, 2]], np.int64)
    faces.flags.writeable = False
    out = np.empty((3, 3), np.float32)
    collider_planes(np.zeros((1, 3, 3), np.float32), faces, np.zeros(1, np.int64), np.array([0, 1, 1, 1], np.int32), np.zeros(1, np.int32),
                    np.ones(1, np.float32), np.arange(3, dtype=np.int64), 1.0, out, out.copy(), np.empty((1, 3), np.float32))
