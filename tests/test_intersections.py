"""Intersecting triangle pairs between two layers (inference/intersections.py)."""
import numpy as np
import pytest
import trimesh

from inference.errors import InputShapeError
from inference.intersections import layer_intersection_faces, layer_intersections, self_intersecting_faces


def _sphere(radius=1.0, centre=(0.0, 0.0, 0.0), subdivisions=2):
    s = trimesh.creation.icosphere(subdivisions=subdivisions, radius=radius)
    return (s.vertices + centre).astype(np.float32), s.faces


def _brute_force(A, Fa, B, Fb) -> int:
    """Every pair, numpy, the same predicate (an edge of one crosses the other; zeros do not count)."""
    A, B = A.astype(np.float64), B.astype(np.float64)

    def orient(a, b, c, d):
        return np.einsum("...i,...i->...", np.cross(b - a, c - a), d - a)

    def crosses(P, Fp, T, Ft):  # (Fp, 3 edges) x Ft
        hit = np.zeros((len(Fp), len(Ft)), bool)
        a, b, c = (T[Ft[:, k]][None] for k in range(3))
        for k in range(3):
            p, q = P[Fp[:, k]][:, None], P[Fp[:, (k + 1) % 3]][:, None]
            sp, sq = orient(a, b, c, p), orient(a, b, c, q)
            e = np.stack([orient(p, q, a, b), orient(p, q, b, c), orient(p, q, c, a)])
            hit |= (sp * sq < 0) & ((e > 0).all(0) | (e < 0).all(0))
        return hit

    return int((crosses(A, Fa, B, Fb) | crosses(B, Fb, A, Fa).T).sum())


def test_crossing_spheres_match_the_brute_force_count():
    a, fa = _sphere(1.0)
    b, fb = _sphere(0.9, (0.7, 0.1, -0.05))
    n = layer_intersections(a[None], fa, b[None], fb)
    assert n.shape == (1,) and n[0] > 0
    assert n[0] == _brute_force(a, fa, b, fb)
    # per inner face: the faces along the intersection curve, nowhere else
    per_face = layer_intersection_faces(a[None], fa, b[None], fb)[0]
    assert per_face.sum() == n[0] and 0 < (per_face > 0).sum() < len(fa) // 2


def test_nested_layers_do_not_intersect_and_frames_are_independent():
    inner, fi = _sphere(1.0)
    outer, fo = _sphere(1.02)  # a layer 2 cm outside
    shifted = outer + np.float32([0.3, 0.0, 0.0])  # frame 1: the outer layer slid through the inner
    n = layer_intersections(np.stack([inner, inner]), fi, np.stack([outer, shifted]), fo)
    assert n[0] == 0 and n[1] == _brute_force(inner, fi, shifted, fo) > 0


def test_shapes_are_checked():
    a, fa = _sphere()
    with pytest.raises(InputShapeError):
        layer_intersections(a, fa, a[None], fa)
    with pytest.raises(InputShapeError):
        layer_intersections(a[None], fa, np.stack([a, a]), fa)
    with pytest.raises(InputShapeError):
        layer_intersections(a[None], fa + len(a), a[None], fa)


def test_self_intersecting_faces_are_where_a_mesh_passes_through_itself():
    V, F = _sphere(subdivisions=2)
    assert not self_intersecting_faces(V[None], F).any()  # a closed sphere: neighbours only touch
    # two spheres in one mesh, overlapping (not mirror images: those meet in exactly coplanar spots)
    W, G = _sphere(radius=0.9, centre=(0.3, 0.1, 0.05), subdivisions=2)
    both = np.concatenate([V, W])[None]
    faces = np.concatenate([F, G + len(V)])
    hit = self_intersecting_faces(both, faces)[0]
    assert hit[:len(F)].any() and hit[len(F):].any()
    centres = both[0][faces[hit]].mean(1)
    # along the circle where the two surfaces meet: near both (an edge is ~0.3 long here)
    assert np.abs(np.linalg.norm(centres, axis=1) - 1.0).max() < 0.2
    assert np.abs(np.linalg.norm(centres - (0.3, 0.1, 0.05), axis=1) - 0.9).max() < 0.2


def test_the_box_pre_test_is_the_six_comparisons():
    """``_apart`` (one max of six differences, no branch) says what the short-circuit comparisons
    lo_b > hi or hi_b < lo on each axis say, touching boxes (a shared coordinate) included."""
    from inference.intersections import _apart

    rng = np.random.default_rng(3)
    grid = np.round(rng.uniform(-1, 1, (4000, 12)), 1)  # coarse values: many equal coordinates
    lo_b, hi_b = np.minimum(grid[:, :3], grid[:, 3:6]), np.maximum(grid[:, :3], grid[:, 3:6])
    lo, hi = np.minimum(grid[:, 6:9], grid[:, 9:]), np.maximum(grid[:, 6:9], grid[:, 9:])
    lo[::7] = np.nextafter(hi_b[::7], np.inf)  # just past: apart by one ulp on every axis
    boxes = np.concatenate([lo_b, hi_b], 1)
    got = np.array([_apart(boxes, f, *lo[f], *hi[f]) for f in range(len(boxes))])
    want = ((lo_b > hi) | (hi_b < lo)).any(1)
    assert want.any() and (~want).any() and ((lo == hi_b) & ~want[:, None]).any()
    assert np.array_equal(got, want)


def test_a_walk_that_stops_at_the_first_crossing_tells_the_same_segments_apart():
    """``binned_crossings(any_only=True)``: the segments that cross a folded surface are the full
    walk's, each counted once, its crossing one of the segment's; the others are untouched."""
    from inference.intersections import _bin_faces, binned_crossings

    s = trimesh.creation.icosphere(3)
    B = np.concatenate([s.vertices, 0.6 * s.vertices])  # two nested spheres: a segment may cross 0-4 times
    F = np.concatenate([s.faces, s.faces + len(s.vertices)]).astype(np.int64)
    rng = np.random.default_rng(5)
    P, Q = rng.uniform(-1.3, 1.3, (2, 4000, 3))
    h = 0.2
    grid = _bin_faces(B, F, h)
    count, first, face = binned_crossings(P, Q, B, F, h, grid, False)
    c1, f1, face1 = binned_crossings(P, Q, B, F, h, grid, False, True)
    assert (count >= 2).sum() > 100 and (count == 0).sum() > 100
    np.testing.assert_array_equal(c1, np.minimum(count, 1))
    hit = count > 0
    assert (f1[hit] >= first[hit]).all() and (f1[hit] <= 1.0).all() and (face1[hit] >= 0).all()
    assert (f1[~hit] == 2.0).all() and (face1[~hit] == -1).all()
    assert (f1[hit] > first[hit]).any()  # some walks stopped at a crossing other than the nearest
