"""``inference.nearness``: the exact "some point nearer than r" test and the k nearest."""
from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from inference.nearness import first_per_cell, within


def test_within_equals_the_distance_matrix_whatever_the_cell():
    rng = np.random.default_rng(7)
    points = rng.uniform(-0.3, 0.3, (500, 3)).astype(np.float32)
    queries = rng.uniform(-0.8, 0.8, (3000, 3)).astype(np.float32)
    d = np.sqrt(((queries[:, None].astype(np.float64) - points[None]) ** 2).sum(-1)).min(1)
    for cell in (0.01, 0.05, 0.2):
        got = within(points, queries, 0.15, cell)
        np.testing.assert_array_equal(got, d < 0.15)
    assert 0.1 < (d < 0.15).mean() < 0.9  # both answers are exercised
    assert not within(points[:0], queries, 0.15, 0.05).any() and within(points, queries[:0], 0.15, 0.05).shape == (0,)


def test_first_per_cell_keeps_the_lowest_index_of_each_cell():
    x = np.array([[0.01, 0, 0], [0.5, 0, 0], [0.02, 0.01, 0], [0.51, 0.02, 0.03], [-0.01, 0, 0]], np.float32)
    assert sorted(first_per_cell(x, 0.1).tolist()) == [0, 1, 4]


def test_nearest_equals_the_kd_trees_near_and_far():
    # the grid search where a query's k nearest lie within its radius, the tree for the others (far
    # queries, and float64 vertices, go to the tree alone)
    import trimesh

    from inference.nearness import GRID_RADIUS_M, nearest

    s = trimesh.creation.icosphere(subdivisions=4, radius=0.15)
    verts = s.vertices.astype(np.float32)
    rng = np.random.default_rng(4)
    ids = np.sort(rng.choice(len(verts), len(verts) - 50, replace=False))
    tree = cKDTree(verts[ids])
    d = rng.normal(size=(600, 3))
    r = rng.uniform(0.15, 0.15 + 3 * GRID_RADIUS_M, (600, 1))
    q = (d / np.linalg.norm(d, axis=1, keepdims=True) * r).astype(np.float32)
    for k in (1, 2, 4):
        want = ids[tree.query(q, k=k)[1].reshape(len(q), k)]
        np.testing.assert_array_equal(nearest(tree, verts, ids, q, k), want)
        np.testing.assert_array_equal(nearest(tree, verts.astype(np.float64), ids, q, k), want)
    ro = ids.copy()
    ro.flags.writeable = False  # a kept topology's ids
    np.testing.assert_array_equal(nearest(tree, verts, ro, q, 2), ids[tree.query(q, k=2)[1]])
    wide = q * np.float32(40.0)  # a box of ~12 m: more cells than the grid may have, the tree answers
    np.testing.assert_array_equal(nearest(tree, verts, ids, wide, 1), ids[tree.query(wide, k=1)[1]][:, None])


def test_near_equals_within_and_the_distance_matrix():
    from inference.nearness import near

    rng = np.random.default_rng(9)
    points = rng.uniform(-0.3, 0.3, (800, 3)).astype(np.float32)

    def nearest_distance(q):
        return np.sqrt(((q[:, None].astype(np.float64) - points[None].astype(np.float64)) ** 2).sum(-1)).min(1)

    queries = rng.uniform(-0.5, 0.5, (2500, 3)).astype(np.float32)
    wide = queries * np.float32(60.0)  # a box of ~60 m: more cells than the grid may have, the tree answers
    d, d_wide = nearest_distance(queries), nearest_distance(wide)
    for r in (0.01, 0.06, 0.2):
        assert 0 < (d < r).sum() < len(d)
        np.testing.assert_array_equal(near(points, queries, r), d < r)
        np.testing.assert_array_equal(near(points.astype(np.float64), queries, r), d < r)  # the tree
        np.testing.assert_array_equal(near(points, wide, r), d_wide < r)
    assert near(points[:0], queries, 0.1).shape == (len(queries),) and not near(points[:0], queries, 0.1).any()


def test_read_only_inputs_reach_the_kernel_as_the_warmed_types():
    # kept rest forms and topologies are read-only; numba would compile them as other types
    from inference.nearness import near, nearest
    from inference.repair_kernels import frame_knn

    rng = np.random.default_rng(5)
    verts = rng.uniform(-0.2, 0.2, (300, 3)).astype(np.float32)
    q = (verts[:50] + np.float32(0.01)).astype(np.float32)
    ids = np.arange(300)
    tree = cKDTree(verts)
    nearest(tree, verts, ids, q, 2)
    near(verts, q, 0.05)
    before = len(frame_knn.signatures)
    for a in (verts, q, ids):
        a.flags.writeable = False
    nearest(tree, verts, ids, q, 2)
    near(verts, q, 0.05)
    assert len(frame_knn.signatures) == before
