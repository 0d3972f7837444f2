"""Collision guard shortcuts against the naive versions: the screen, the plan's searches."""
import numpy as np
import pytest
import trimesh
from scipy.spatial import cKDTree

from inference.guard import DEFAULT_MARGIN_M, GuardPlan, boundary_vertices, push_outside
from inference.guard.push import _planes, _push_block
from inference.mesh import vertex_normals


def test_screened_push_equals_pushing_every_point():
    s = trimesh.creation.icosphere(subdivisions=3, radius=1.0)
    verts, faces = s.vertices.astype(np.float32), s.faces
    rng = np.random.default_rng(0)
    d = rng.normal(size=(2000, 3))
    pts = (d / np.linalg.norm(d, axis=1, keepdims=True) * rng.uniform(0.97, 1.03, (2000, 1))).astype(np.float32)
    cand = cKDTree(verts).query(pts, k=6)[1]
    nrm = vertex_normals(verts[None], faces)
    out = push_outside(pts[None, None], verts[None, None], nrm[None], cand, DEFAULT_MARGIN_M, iterations=2)[0, 0]
    # naive: every point through every pass (no screen), flat indices of frame 0
    naive = _push_block(_planes(pts[None, None]), _planes(verts[None, None]), _planes(nrm[None]), cand.T.astype(np.intp),
                        None, len(verts), DEFAULT_MARGIN_M, None, None, 0.0, 2)[0]
    np.testing.assert_array_equal(out, naive.T)
    assert 0 < (out != pts).any(1).sum() < len(pts)


def test_boundary_vertices_match_naive_edge_count():
    g = trimesh.creation.icosphere(subdivisions=2)
    faces = g.faces[g.vertices[g.faces].mean(1)[:, 2] < 0.3]  # an open cap
    edges = np.sort(faces[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1)
    uniq, count = np.unique(edges, axis=0, return_counts=True)
    naive = np.zeros(len(g.vertices), bool)
    naive[uniq[count == 1].ravel()] = True
    np.testing.assert_array_equal(boundary_vertices(faces, len(g.vertices)), naive)
    assert naive.any()


def test_skin_candidates_are_the_nearest_of_another_bone():
    s = trimesh.creation.icosphere(subdivisions=3, radius=1.0)
    verts, faces = s.vertices.astype(np.float32), s.faces
    bone = (verts[:, 2] > 0.2).astype(int) + (verts[:, 0] > 0.5).astype(int)  # three "bones"
    cw = np.eye(3, dtype=np.float32)[bone]
    rng = np.random.default_rng(1)
    d = rng.normal(size=(300, 3))
    pts = (d / np.linalg.norm(d, axis=1, keepdims=True) * 1.01).astype(np.float32)
    pw = np.eye(3, dtype=np.float32)[rng.integers(0, 3, 300)]
    plan = GuardPlan.build(pts[None], verts[None], faces, 4, skin=(pw, cw), k_skin=2)
    skin = plan.collider_ids[plan.candidates[0, :, 6:8]]  # after 4 nearest and 2 ahead
    pb = pw.argmax(1)
    for b in range(3):  # naive: a KD-tree over the vertices of the other bones
        rows = pb == b
        others = np.flatnonzero(bone != b)
        want = others[cKDTree(verts[others]).query(pts[rows], k=2)[1]]
        np.testing.assert_array_equal(np.sort(skin[rows], 1), np.sort(want, 1))


@pytest.mark.parametrize("k", [3, 1, 5])
def test_per_frame_nearest_equal_a_kd_tree_warm_and_cold(k):
    # a moving sphere's vertices as the region, points around it: every frame's k nearest equal
    # the KD-tree's (by distance), from a cold start, from the last frame's answers (warm), from
    # answers of another region (a bound wider than COLD_RHO_M: cold again), and for points far
    # outside the region's box; k = 3 (the guard's) runs its own scan, other k the general one
    from inference.guard import nearest

    s = trimesh.creation.icosphere(subdivisions=3, radius=0.12)
    rng = np.random.default_rng(1)
    F, S, N = 5, len(s.vertices), 400
    shift = np.cumsum(rng.normal(0, 0.01, (F, 3)), 0)
    C3 = np.ascontiguousarray(np.moveaxis(s.vertices[None] + shift[:, None], 2, 0))  # (3, F, S)
    region = np.flatnonzero(s.vertices[:, 2] > -0.05)
    d = rng.normal(size=(N, 3))
    base = d / np.linalg.norm(d, axis=1, keepdims=True) * rng.uniform(0.1, 0.2, (N, 1))
    base[:20] *= 10.0  # ~1-2 m away
    P = np.ascontiguousarray(np.moveaxis(base[None] + shift[:, None], 2, 0).reshape(3, -1))
    dyn = np.arange(0, N, 2)
    for start in ("cold", "warm", "stale"):
        prev = np.full((len(dyn), k), -1, np.int64)
        if start != "cold":
            prev[:] = rng.integers(0, len(region), prev.shape) if start == "stale" else 0
        found = nearest.frames_knn(C3, region, P, dyn, N, 0, F, k, nearest.CELL_M, nearest.COLD_RHO_M, prev)
        for f in range(F):
            pts, q = C3[:, f, region].T, P[:, f * N + dyn].T
            ref = cKDTree(pts).query(q, k=k)[0].reshape(len(q), k)
            np.testing.assert_allclose(np.linalg.norm(pts[found[f]] - q[:, None], axis=-1), ref, rtol=0, atol=1e-12)
        np.testing.assert_array_equal(prev, found[-1])  # the state carried to the next block


def test_per_frame_nearest_of_a_region_smaller_than_k_marks_the_missing():
    # two region vertices, k = 3: each point gets both, nearest first, then -1 (not another row)
    from inference.guard import nearest

    C3 = np.ascontiguousarray(np.array([[0.0, 0.0, 0.0], [0.1, 0.0, 0.0], [5.0, 5.0, 5.0]]).T[:, None, :])  # (3, 1 frame, 3)
    P = np.ascontiguousarray(np.array([[0.09, 0.0, 0.0], [-0.02, 0.01, 0.0]]).T)
    prev = np.full((2, 3), -1, np.int64)
    found = nearest.frames_knn(C3, np.array([0, 1]), P, np.arange(2), 2, 0, 1, 3, nearest.CELL_M, nearest.COLD_RHO_M, prev)
    np.testing.assert_array_equal(found[0], [[1, 0, -1], [0, 1, -1]])


def test_the_answers_become_flat_candidate_ids_as_numpy_writes_them():
    # ``flat_candidates`` against the numpy form it replaces: the dynamic points' columns of
    # frame-major flat ids, a missing answer (-1) included, every other column left alone
    from inference.guard import nearest

    rng = np.random.default_rng(4)
    F, Nd, k, N, S, f0 = 3, 40, 3, 70, 500, 5
    region = rng.choice(S, 120, replace=False)
    found = rng.integers(0, len(region), (F, Nd, k))
    found[0, 3, 2] = -1
    dyn = np.sort(rng.choice(N, Nd, replace=False))
    want = rng.integers(0, 10**6, (k, F * N))
    got = want.copy()
    for i in range(F):
        want[:, i * N + dyn] = (f0 + i) * S + region[found[i]].T
    nearest.flat_candidates(found, region, dyn, N, f0, S, got)
    np.testing.assert_array_equal(got, want)


def test_the_warm_up_compiles_the_per_frame_search_for_the_guards_coordinates():
    # a worker warms the kernel at start-up (service.runtime); a signature it missed would compile
    # (~1 s) inside the first outfit's request: the guard's planes are float32
    import numba

    from inference.guard import nearest

    s = trimesh.creation.icosphere(subdivisions=1)
    plan = GuardPlan.build(s.vertices[None].astype(np.float32), s.vertices[None].astype(np.float32), s.faces)
    C, _ = plan.collider_planes(s.vertices[None, None].astype(np.float32))
    nearest.warm_up()
    assert numba.typeof(np.ascontiguousarray(C.reshape(3, 1, -1))) in [sig[0] for sig in nearest.frames_knn.signatures]


def test_the_first_frame_starts_from_the_rest_nearest_in_the_region():
    # ``_warm_start``: each dynamic point's first k plan candidates as positions in its region (a
    # bound the search is exact from, whatever the vertices: the test above), -1 for a whole row
    # where one of them lies outside the region
    from inference.guard.push import _warm_start

    s = trimesh.creation.icosphere(subdivisions=3, radius=0.2)
    verts, faces = s.vertices.astype(np.float32), s.faces
    bone = (verts[:, 2] > 0.0).astype(int)
    cw = np.eye(2, dtype=np.float32)[bone]
    rng = np.random.default_rng(3)
    d = rng.normal(size=(300, 3))
    pts = (d / np.linalg.norm(d, axis=1, keepdims=True) * 0.205).astype(np.float32)
    pw = np.eye(2, dtype=np.float32)[(pts[:, 2] > 0.0).astype(int)]
    plan = GuardPlan.build(pts[None], verts[None], faces, 4, skin=(pw, cw), k_skin=2)
    assert plan.dynamic_points is not None and len(plan.dynamic_points) > 0
    prev = _warm_start(plan, 3)
    assert prev.shape == (len(plan.dynamic_points), 3) and prev.dtype == np.int64
    warm = prev[:, 0] >= 0
    assert warm.any() and np.array_equal(warm, (prev >= 0).all(1))
    np.testing.assert_array_equal(plan.dynamic_region[prev[warm]], plan.candidates[0][plan.dynamic_points[warm], :3])

