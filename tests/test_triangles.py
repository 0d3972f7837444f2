"""Closest point on triangles (inference.triangles) against trimesh's, degenerate triangles included."""
import numpy as np
import trimesh

from inference.triangles import closest_barycentrics


def _planes(a):
    return [a[..., i] for i in range(3)]


def test_closest_point_matches_trimesh_on_random_triangles():
    rng = np.random.default_rng(3)
    tri = rng.normal(size=(5000, 3, 3)).astype(np.float32)
    tri[:40, 2] = tri[:40, 1]  # degenerate: two corners coincide
    tri[40:80, 1:] = tri[40:80, :1]  # degenerate: a point
    p = (2.0 * rng.normal(size=(5000, 3))).astype(np.float32)
    a, ab, ac = tri[:, 0], tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]
    v, w = closest_barycentrics(_planes(p - a), _planes(ab), _planes(ac))
    assert v.dtype == np.float32 and np.isfinite(v).all() and np.isfinite(w).all()
    assert (v >= 0).all() and (w >= 0).all() and (v + w <= 1 + 1e-6).all()
    q = a + v[:, None] * ab + w[:, None] * ac
    ref = trimesh.triangles.closest_point(tri.astype(np.float64), p.astype(np.float64))
    np.testing.assert_allclose(np.linalg.norm(q - p, axis=1), np.linalg.norm(ref - p, axis=1), atol=2e-6)


def test_each_voronoi_region_of_one_triangle():
    a, b, c = np.array([0, 0, 0.0]), np.array([1, 0, 0.0]), np.array([0, 1, 0.0])
    cases = {  # point -> expected closest point
        (0.2, 0.2, 0.5): (0.2, 0.2, 0),  # interior
        (-1, -1, 0): (0, 0, 0),  # vertex a
        (2, -0.5, 0): (1, 0, 0),  # vertex b
        (-0.5, 2, 1): (0, 1, 0),  # vertex c
        (0.5, -1, 0): (0.5, 0, 0),  # edge ab
        (-1, 0.5, 0): (0, 0.5, 0),  # edge ac
        (1, 1, 0): (0.5, 0.5, 0),  # edge bc
    }
    p = np.array(list(cases), np.float32)
    n = len(p)
    v, w = closest_barycentrics(_planes(p - a), _planes(np.tile(b - a, (n, 1))), _planes(np.tile(c - a, (n, 1))))
    q = a + v[:, None] * (b - a) + w[:, None] * (c - a)
    np.testing.assert_allclose(q, np.array(list(cases.values())), atol=1e-6)
