"""``inference.mesh.per_array``: values derived once per array object, never for another array."""
import gc

import numpy as np

from inference.layers import anchor_normals
from inference.mesh import per_array, vertex_normals


def test_a_value_is_kept_per_array_object_and_not_reused_for_another():
    calls = []

    @per_array
    def total(a, scale):
        calls.append(1)
        return float(np.sum(a)) * scale

    a = np.arange(4.0)
    assert total(a, 2) == 12.0 and total(a, 2) == 12.0 and len(calls) == 1
    assert total(a, 3) == 18.0 and len(calls) == 2  # other arguments: another entry
    b = np.arange(4.0) + 1  # equal shape, another object
    assert total(b, 2) == 20.0 and len(calls) == 3
    del a
    gc.collect()
    c = np.zeros(4)  # may take the freed array's id: the weak reference tells them apart
    assert total(c, 2) == 0.0 and len(calls) == 4
    assert total([1.0, 2.0], 1) == 3.0 and total([1.0, 2.0], 1) == 3.0 and len(calls) == 6  # no weak reference: no cache


def test_compiled_anchor_normals_equal_the_numpy_vertex_normals():
    rng = np.random.default_rng(0)
    import trimesh

    s = trimesh.creation.icosphere(subdivisions=2)
    v = (s.vertices[None] * rng.uniform(0.8, 1.2, (3, 1, 3))).astype(np.float32)
    ids = rng.choice(len(s.vertices), 20, replace=False)
    got = anchor_normals(v, s.faces.astype(np.int32), ids)
    np.testing.assert_allclose(got, vertex_normals(v, s.faces)[:, ids], atol=1e-6)


def test_faces_touching_equals_the_row_test():
    from inference.mesh import faces_touching

    rng = np.random.default_rng(2)
    faces = rng.integers(0, 1000, (5000, 3))
    slot = np.full(1000, -1, np.int64)
    slot[rng.choice(1000, 40, replace=False)] = np.arange(40)
    got = faces_touching(faces, slot)
    np.testing.assert_array_equal(got, np.flatnonzero((slot[faces] >= 0).any(1)))
    assert 0 < len(got) < len(faces)


def test_faces_around_equals_faces_touching():
    from inference.mesh import faces_around, faces_touching

    rng = np.random.default_rng(2)
    faces = rng.integers(0, 300, (900, 3))
    for n in (0, 1, 7, 120, 300):
        ids = rng.choice(300, n, replace=False)
        slot = np.full(300, -1, np.int64)
        slot[ids] = np.arange(n)
        got = faces_around(faces, np.concatenate([ids, ids[: n // 2]]), 300)  # repeats allowed
        np.testing.assert_array_equal(got, faces_touching(faces, slot))
        assert got.dtype == np.int64
