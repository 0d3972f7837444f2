"""The guard's compiled plane push (``inference.guard.push_kernels``) against the numpy version it
replaced, kept here as the reference: bitwise the same points."""
import numpy as np
import pytest

from inference.guard.constants import _FARTHER_M, _OPPOSING_COS, _SQUEEZE_RADIUS_M, _TANGENT_M
from inference.guard.push import _push_block, _screen_tolerance


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
