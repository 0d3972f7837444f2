"""The guard's compiled plane push and closest-triangle check (``inference.guard.push_kernels``)
against the numpy versions they replaced, kept here as the reference: bitwise the same points."""
import sys

import numpy as np
import pytest

from inference.guard.constants import _FARTHER_M, _OPPOSING_COS, _SQUEEZE_RADIUS_M, _TANGENT_M, REFINE_CANDIDATES
from inference.guard.push import _push_block, _screen_tolerance
from inference.triangles import closest_barycentrics


def _numpy_push_block(P, C, Nrm, flat, across, M, margin_m, max_push_m, boundary, reach_m, iterations):
    """Screened points: P (3, L), flat (k, L) candidate indices into C, Nrm (3, .), across (k, L).

    Each pass after the first revisits only the points the previous one moved (the others are
    where they were, so a pass would decide the same for them again). Returns (3, L) float32.
    """
    P = P.astype(np.float32, copy=True)
    live = np.arange(P.shape[1])
    for _ in range(max(int(iterations), 1)):
        if len(live) == 0:
            break
        delta, na, moved = _numpy_push_pass(P[:, live], C, Nrm, flat[:, live], None if across is None else across[:, live],
                                      M, margin_m, max_push_m, boundary, reach_m)
        live = live[moved]
        for c in range(3):
            P[c, live] += delta * na[c]  # p' = p + delta n*
    return P


def _numpy_push_pass(P, C, Nrm, flat, across, M, margin_m, max_push_m, boundary, reach_m):
    """One pass over points P (3, L): returns the push lengths delta (A,) != 0 and directions
    n* (3 x (A,)) of the A points it moves, and their positions ``moved`` (A,) in L."""
    L = P.shape[1]
    G = [np.take(C[c], flat) for c in range(3)]  # (k, L) candidate coordinates
    rows = np.arange(L, dtype=np.intp)
    Gn = [np.take(Nrm[c], flat) for c in range(3)]  # (k, L) candidate normals n_j
    D = [P[c] - G[c] for c in range(3)]  # p - c_j
    d2 = D[0] * D[0] + D[1] * D[1] + D[2] * D[2]
    s_all = D[0] * Gn[0] + D[1] * Gn[1] + D[2] * Gn[2]  # s_j = (p - c_j) . n_j
    j = np.argmin(d2, axis=0)  # closest candidate c*
    # ... unless p lies behind the plane of a candidate it projects onto (tangential offset <
    # _TANGENT_M) that is not much farther (< _FARTHER_M more): then p is inside that part,
    # and the nearest vertex (outside an arm, say) misjudges it; take the deepest such plane.
    s_near = np.take_along_axis(s_all, j[None], 0)[0]
    dmin = np.sqrt(np.take_along_axis(d2, j[None], 0)[0])
    behind = (s_all < 0) & (d2 - s_all * s_all < _TANGENT_M**2) & (np.sqrt(d2) <= dmin + _FARTHER_M)
    deep = np.argmin(np.where(behind, s_all, np.inf), axis=0)
    j = np.where(behind.any(axis=0) & (np.take_along_axis(s_all, deep[None], 0)[0] < s_near), deep, j)
    pick = j * L + rows
    sel = np.take(flat, pick)
    ns = [np.take(Gn[c], pick) for c in range(3)]  # n*
    s = np.take(s_all, pick)  # s = (p - c*) . n*
    delta = margin_m - s
    act = np.flatnonzero(delta > 0)  # only these need a push
    delta, s_a = delta[act], s[act]
    na = [ns[c][act] for c in range(3)]
    Gna = [Gn[c][:, act] for c in range(3)]
    a = na[0] * Gna[0] + na[1] * Gna[1] + na[2] * Gna[2]  # n* . n_j
    s_j = s_all[:, act]
    # a surface ahead of p (in the push direction), facing it and close in this frame squeezes:
    # balanced push delta_j = (s_j - s*) / (1 - n*.n_j) (the module docstring)
    ahead = -(D[0][:, act] * na[0] + D[1][:, act] * na[1] + D[2][:, act] * na[2]) > 0
    if across is not None:
        ahead = ahead | across[:, act]
    opposing = ahead & (a < _OPPOSING_COS) & (d2[:, act] < _SQUEEZE_RADIUS_M**2)
    bal = np.where(opposing, (s_j - s_a) / np.maximum(1.0 - a, 1.0), np.inf).min(axis=0)
    delta = np.minimum(delta, np.maximum(bal, 0.0))
    if max_push_m is not None:
        delta = np.minimum(delta, max_push_m)
    if boundary is not None:
        tangential2 = d2[j[act], act] - s_a * s_a
        delta = np.where(boundary[sel[act] % M] & (tangential2 > reach_m**2), 0.0, delta)
    moved = delta != 0
    return delta[moved], [n[moved] for n in na], act[moved]


def _screen_planes(P: np.ndarray, Nrm: np.ndarray, offset: np.ndarray, flat: np.ndarray) -> np.ndarray:
    """min_j s_j = min_j (p . n_j - o_j) per point: P (3, L), flat (k, L) into Nrm (3, .) and
    offset (.,) = c . n; returns (L,) float32. In-place arithmetic: no (k, L) temporaries."""
    s = np.take(offset, flat)
    np.negative(s, out=s)
    t = np.empty_like(s)
    for c in range(3):
        np.take(Nrm[c], flat, out=t)
        t *= P[c]
        s += t
    return s.min(axis=0)


def _ring_closest(ap, centre, C, other):
    """Closest points on ring triangles (centre, b, c): ap = p - centre and centre (3 x arrays
    broadcasting against other[..., 0]), other (..., 2) flat ids of b and c into C (3, .).
    Returns barycentrics v, w and p - q (3 x arrays) of other[..., 0]'s shape."""
    corner = [np.take(C[c], other) for c in range(3)]
    ab = [corner[c][..., 0] - centre[c] for c in range(3)]
    ac = [corner[c][..., 1] - centre[c] for c in range(3)]
    v, w = closest_barycentrics(ap, ab, ac)
    return v, w, [ap[c] - v * ab[c] - w * ac[c] for c in range(3)]


# Ring slots computed for every selected vertex; rings with more triangles get the rest computed
# for them alone.
_RING_SLOTS = 6


def _numpy_refine_block(P: np.ndarray, C: np.ndarray, Nrm: np.ndarray, flat: np.ndarray, ring: np.ndarray, valence: np.ndarray,
                        M: int, margin_m: float) -> np.ndarray:
    """``push._refine_block`` as numpy over (candidates, ring slots, points) arrays, the form the
    compiled ``push_kernels.refine_points`` replaced (its arguments and answer).
    """
    k = flat.shape[0]
    kr = int(min(REFINE_CANDIDATES, k))
    G = [np.take(C[c], flat) for c in range(3)]
    d2 = (P[0] - G[0]) ** 2 + (P[1] - G[1]) ** 2 + (P[2] - G[2]) ** 2
    L = flat.shape[1]
    near = np.argpartition(d2, kr - 1, axis=0)[:kr] if kr < k else np.arange(k)[:, None].repeat(L, 1)
    sel = np.take_along_axis(flat, near, 0)  # (kr, L) flat ids f * M + s
    # the ring triangles (centre, b, c) of each selected vertex, laid out (kr, R, L)
    other = np.moveaxis(ring[sel % M], 2, 1) + (sel - sel % M)[:, None, :, None]  # (kr, R, L, 2) flat ids
    centre = [np.take(C[c], sel)[:, None] for c in range(3)]  # (kr, 1, L)
    ap = [P[c] - centre[c] for c in range(3)]
    R = other.shape[1]
    R0 = min(R, _RING_SLOTS)
    v, w, r = _ring_closest(ap, centre, C, other[:, :R0])  # the first R0 triangles of every ring
    if R > R0:
        # slots past a ring's valence repeat its first triangle (``_one_rings``): their results are
        # slot 0's, so only the rings with more than R0 triangles are computed there
        v, w = (np.concatenate([a, np.repeat(a[:, :1], R - R0, axis=1)], axis=1) for a in (v, w))
        r = [np.concatenate([a, np.repeat(a[:, :1], R - R0, axis=1)], axis=1) for a in r]
        j, col = np.nonzero(valence[sel % M] > R0)
        if len(j):
            sub = other[j, R0:, col]  # (E, R - R0, 2)
            cj = [np.take(C[c], sel[j, col])[:, None] for c in range(3)]
            vx, wx, rx = _ring_closest([P[c][col][:, None] - cj[c] for c in range(3)], cj, C, sub)
            v[j, R0:, col], w[j, R0:, col] = vx, wx
            for c in range(3):
                r[c][j, R0:, col] = rx[c]
    best = np.argmin((r[0] * r[0] + r[1] * r[1] + r[2] * r[2]).reshape(-1, L), axis=0)[None]
    pick = lambda a: np.take_along_axis(np.broadcast_to(a, v.shape).reshape(-1, L), best, 0)[0]  # noqa: E731
    vb, wb = pick(v), pick(w)
    ub = 1 - vb - wb
    rb = [pick(r[c]) for c in range(3)]  # p - q
    ids = [pick(sel[:, None]), pick(other[..., 0]), pick(other[..., 1])]
    n = [ub * np.take(Nrm[c], ids[0]) + vb * np.take(Nrm[c], ids[1]) + wb * np.take(Nrm[c], ids[2]) for c in range(3)]
    norm = np.sqrt(n[0] * n[0] + n[1] * n[1] + n[2] * n[2])
    inside = (rb[0] * n[0] + rb[1] * n[1] + rb[2] * n[2] < 0) & (norm > 0)
    out = P.copy()
    if inside.any():
        scale = margin_m / norm[inside]
        for c in range(3):  # q + margin n_q, q = p - (p - q)
            out[c, inside] = P[c, inside] - rb[c][inside] + scale * n[c][inside]
    return out


def _case(rng, L=3000, M=600, k=7):
    # two wavy sheets of collider vertices 12 mm apart facing each other (a gap between an arm and
    # the torso), noisy normals, points around them within a few cm, each with its k - 2 nearest
    # vertices and two random ones as candidates: pushes, points behind another candidate's
    # plane, squeezes between the sheets, border vertices, points already outside
    from scipy.spatial import cKDTree

    C = np.zeros((3, M), np.float32)
    C[0], C[1] = rng.uniform(-0.1, 0.1, M), rng.uniform(-0.1, 0.1, M)
    top = np.arange(M) < M // 2
    C[2] = 0.01 * np.sin(40 * C[0]) + np.where(top, 0.012, 0.0)
    n = rng.normal(0, 0.3, (3, M)) + np.where(top, -1.0, 1.0) * np.array([[0.0], [0.0], [1.0]])
    Nrm = (n / np.linalg.norm(n, axis=0)).astype(np.float32)
    P = np.zeros((3, L), np.float32)
    P[:2] = rng.uniform(-0.1, 0.1, (2, L))
    P[2] = rng.uniform(-0.02, 0.03, L)
    near = cKDTree(C.T).query(P.T, k=k - 2)[1].T
    flat = np.concatenate([near, rng.integers(0, M, (2, L))]).astype(np.intp)
    return P, C, Nrm, flat


@pytest.mark.parametrize("seed", range(4))
@pytest.mark.parametrize("variant", ["plain", "across", "border", "capped"])
def test_the_compiled_push_moves_every_point_as_the_numpy_one(seed, variant):
    rng = np.random.default_rng(seed)
    P, C, Nrm, flat = _case(rng)
    M = C.shape[1]
    across = rng.random(flat.shape) < 0.3 if variant == "across" else None
    boundary = rng.random(M) < 0.3 if variant == "border" else None
    max_push = 0.004 if variant == "capped" else None
    for margin, iterations in ((0.004, 2), (0.01, 1), (0.0, 3)):
        ref = _numpy_push_block(P, C, Nrm, flat, across, M, margin, max_push, boundary, 0.005, iterations)
        got = _push_block(P, C, Nrm, flat, across, M, margin, max_push, boundary, 0.005, iterations)[0]
        assert (ref != P).any()  # the case pushes points
        np.testing.assert_array_equal(got, ref)


def test_the_warm_up_compiles_the_type_every_push_passes():
    # a worker warms the kernel at start-up (service.runtime); a type it missed would compile
    # inside the first request that guards a garment
    from inference.guard import push_kernels

    push_kernels.warm_up()
    P, C, Nrm, flat = _case(np.random.default_rng(0), L=10, M=20)
    before = len(push_kernels.push_points.signatures)
    _push_block(P, C, Nrm, flat, None, 20, 0.004, None, None, 0.005, 2)
    _push_block(P, C, Nrm, flat[:4], np.zeros(flat[:4].shape, bool), 20, 0.004, 0.01, np.zeros(20, bool), 0.005, 2, extra=flat[4:],
                offset=np.ones(20, np.float32), keep=0.01)
    assert len(push_kernels.push_points.signatures) == before


@pytest.mark.parametrize("seed", range(3))
def test_the_compiled_screen_keeps_the_points_numpy_kept_and_pushes_them_alike(seed):
    # the guard's block: rest-pose candidates (across some) and per-frame extra ones, screened
    # by s_j = p . n_j - c_j . n_j against margin + tolerance in numpy's float32 order
    rng = np.random.default_rng(seed)
    P, C, Nrm, flat = _case(rng)
    M = C.shape[1]
    static, extra = flat[:4], flat[4:]
    across = rng.random(static.shape) < 0.2
    offset = C[0] * Nrm[0] + C[1] * Nrm[1] + C[2] * Nrm[2]
    for margin in (0.002, 0.005):
        keep = margin + _screen_tolerance(P, C)
        s_min = np.minimum(_screen_planes(P, Nrm, offset, static), _screen_planes(P, Nrm, offset, extra))
        live = np.flatnonzero(s_min < keep)
        ref = P.copy()
        ref[:, live] = _numpy_push_block(P[:, live], C, Nrm, flat[:, live], np.concatenate([across, np.zeros(extra.shape, bool)])[:, live],
                                         M, margin, None, None, 0.005, 2)
        got, kept = _push_block(P, C, Nrm, static, across, M, margin, None, None, 0.005, 2, extra=extra, offset=offset, keep=keep)
        assert 0 < len(live) < P.shape[1]  # the screen drops some points, keeps others
        np.testing.assert_array_equal(kept, live)
        np.testing.assert_array_equal(got, ref)


def _numpy_collider_planes(plan, collider):
    """``GuardPlan.collider_planes`` as numpy computed it (the reference of the compiled pass)."""
    from inference.guard.push import _planes

    B, T, M, _ = collider.shape
    BT = B * T
    C = _planes(collider)
    frame = (np.arange(BT, dtype=np.intp) * M)[None, :]
    f = plan.faces[plan.face_ids]
    corner = [[np.take(C[c], f[:, i, None] + frame) for c in range(3)] for i in range(3)]
    e1 = [corner[1][c] - corner[0][c] for c in range(3)]
    e2 = [corner[2][c] - corner[0][c] for c in range(3)]
    fn = np.stack([e1[1] * e2[2] - e1[2] * e2[1], e1[2] * e2[0] - e1[0] * e2[2], e1[0] * e2[1] - e1[1] * e2[0]], axis=1)
    vn = (plan.incidence @ fn.reshape(len(f), 3 * BT)).reshape(-1, 3, BT)
    vn *= plan.orientation / np.maximum(np.sqrt(np.einsum("scb,scb->sb", vn, vn)), 1e-20)[:, None]
    normals = np.ascontiguousarray(vn.transpose(1, 2, 0)).reshape(3, BT * len(plan.collider_ids))
    points = np.take(C, (frame.T + plan.collider_ids[None]).reshape(-1), axis=1)
    return points, normals


@pytest.mark.parametrize("flip", [False, True])
def test_the_collider_planes_are_numpys(flip):
    # a closed collider (a sphere, normals outward) and the same faces wound inward (orientation
    # -1), moving over three frames: the compiled planes are the numpy form's, bit for bit
    import trimesh

    from inference.guard.plan import GuardPlan

    s = trimesh.creation.icosphere(subdivisions=3, radius=0.2)
    faces = s.faces[:, ::-1] if flip else s.faces
    rng = np.random.default_rng(5)
    body = (s.vertices[None] + rng.normal(0, 0.003, (3, len(s.vertices), 3))).astype(np.float32)
    points = (s.vertices[::7] * 1.05).astype(np.float32)
    plan = GuardPlan.build(points[None], body[:1], faces)
    assert plan.orientation == (-1.0 if flip else 1.0)
    got = plan.collider_planes(body[None])
    want = _numpy_collider_planes(plan, body[None])
    assert got[0].dtype == got[1].dtype == np.float32
    assert np.array_equal(got[0], want[0]) and np.array_equal(got[1], want[1])


def _refine_case(rng, L=4000, k=7):
    # an icosphere's vertices in two frames (the second moved and squashed), with its one-rings;
    # points within 2 cm of its surface, inside and out; each with its k - 2 nearest vertices of
    # its frame and two random ones as candidates (frame-major flat ids)
    import trimesh
    from scipy.spatial import cKDTree

    from inference.guard.plan import _one_rings

    sphere = trimesh.creation.icosphere(subdivisions=3, radius=0.1)
    V, F = np.asarray(sphere.vertices), np.asarray(sphere.faces)
    M = len(V)
    frames = [V, V * [1.2, 1.0, 0.7] + [0.0, 0.05, 0.0]]
    C = np.concatenate([f.T for f in frames], 1).astype(np.float32)
    Nrm = np.concatenate([trimesh.Trimesh(f, F, process=False).vertex_normals.T for f in frames], 1).astype(np.float32)
    ring, valence = _one_rings(F, M)
    frame = rng.integers(0, 2, L)
    P = np.empty((3, L), np.float32)
    flat = np.empty((k, L), np.int64)
    for b in range(2):
        rows = np.flatnonzero(frame == b)
        u = rng.normal(size=(len(rows), 3))
        u /= np.linalg.norm(u, axis=1, keepdims=True)
        pts = frames[b][rng.integers(0, M, len(rows))] + u * rng.uniform(0.0, 0.02, (len(rows), 1))
        P[:, rows] = pts.T
        near = cKDTree(frames[b]).query(pts, k=k - 2)[1].T
        flat[:, rows] = np.concatenate([near, rng.integers(0, M, (2, len(rows)))]) + b * M
    return P, C, Nrm, flat, ring, valence, M


@pytest.mark.parametrize("seed", range(3))
@pytest.mark.parametrize("slots", [6, 3])
def test_the_compiled_closest_triangle_check_moves_points_as_the_numpy_one(seed, slots, monkeypatch):
    """``push._refine_block`` (compiled) against its numpy form: the same points moved, to the same
    places bitwise wherever both took the same candidates (numpy's partial sort orders equal
    distances its own way; then within a micrometre). With 3 ring slots every ring of the
    icosphere (valence 5-6) takes the numpy form's overflow path."""
    from inference.guard.push import _refine_block

    monkeypatch.setattr(sys.modules[__name__], "_RING_SLOTS", slots)
    rng = np.random.default_rng(seed)
    P, C, Nrm, flat, ring, valence, M = _refine_case(rng)
    for margin in (0.004, 0.0):
        ref = _numpy_refine_block(P, C, Nrm, flat, ring, valence, M, margin)
        got = _refine_block(P, C, Nrm, flat, ring, valence, M, margin)
        moved = (ref != P).any(0)
        assert moved.sum() > 200 and (moved == (got != P).any(0)).all()
        same = (got == ref).all(0)
        assert same.mean() > 0.99
        np.testing.assert_allclose(got, ref, atol=1e-6, rtol=0)
