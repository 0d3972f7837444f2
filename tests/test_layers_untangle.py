"""inference.layers: the body-anchor crossing test and the untangling of layered garments, on
concentric spheres (a "body" of radius 0.5, an outer layer of radius 1, an inner one of 0.95
with a patch bulged out through the outer), and the crossing kernel against brute force."""
from __future__ import annotations

import numpy as np
import pytest
import scipy.sparse as sp
import trimesh

from inference.intersections import first_crossings
from inference.layers import SPREAD_RINGS, LayerContacts, anchor_crossings, body_anchors, untangle_layers
from inference.metrics import layer_beyond_pct

GAP, FLOOR = 0.003, 0.002


def _orient(a, b, c, d):
    return np.einsum("...i,...i->...", np.cross(b - a, c - a), d - a)


def test_first_crossings_match_brute_force():
    rng = np.random.default_rng(0)
    mesh = trimesh.creation.icosphere(2)
    V, F = np.asarray(mesh.vertices, np.float64) + rng.normal(0, 0.02, mesh.vertices.shape), np.asarray(mesh.faces, np.int64)
    P = rng.normal(0, 0.6, (400, 3))
    Q = P + rng.normal(0, 0.8, (400, 3))
    a, b, c = (V[F[:, k]][None] for k in range(3))
    p, q = P[:, None], Q[:, None]
    sp_, sq = _orient(a, b, c, p), _orient(a, b, c, q)
    e = [_orient(p, q, a, b), _orient(p, q, b, c), _orient(p, q, c, a)]
    cross = (sp_ * sq < 0) & (((e[0] > 0) & (e[1] > 0) & (e[2] > 0)) | ((e[0] < 0) & (e[1] < 0) & (e[2] < 0)))
    for exiting in (False, True):
        want = cross & (sp_ < 0) if exiting else cross  # exiting: P behind the face's plane
        count, first, face = first_crossings(P, Q, V, F, 0.3, exiting)
        assert (count == want.sum(1)).all()
        t = np.where(want, sp_ / (sp_ - sq), 2.0)
        np.testing.assert_allclose(first, t.min(1), atol=1e-12)
        hit = count > 0
        np.testing.assert_array_equal(face[hit], t.argmin(1)[hit])
        assert (face[~hit] == -1).all()
        assert hit.sum() > 50 and (~hit).sum() > 20  # both cases are exercised


@pytest.fixture()
def spheres():
    s = trimesh.creation.icosphere(3)
    unit, F = np.asarray(s.vertices, np.float32), np.asarray(s.faces, np.int64)
    body = 0.5 * unit
    outer = 1.0 * unit
    inner = 0.95 * unit.copy()
    bulge = unit[:, 2] > 0.8  # a cap of the inner layer through the outer, up to 5 cm beyond
    inner[bulge] = unit[bulge] * (0.95 + 0.1 * (unit[bulge, 2:3] - 0.8) / 0.2)
    return body, inner, outer, F, bulge


def _rings(faces: np.ndarray, seeds: np.ndarray, k: int) -> np.ndarray:
    """The vertices within k edges of the seeds."""
    n = int(faces.max()) + 1
    e = faces[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2)
    A = sp.coo_matrix((np.ones(len(e)), (e[:, 0], e[:, 1])), shape=(n, n)).tocsr()
    A = A + A.T + sp.identity(n)
    reach = seeds.astype(float)
    for _ in range(k):
        reach = A @ reach
    return reach > 0


def test_untangle_sinks_the_bulge_under_the_outer_layer_and_nothing_far_from_it(spheres):
    body, inner, outer, F, bulge = spheres
    anchors = body_anchors(inner, body)
    np.testing.assert_array_equal(anchors, np.arange(len(body)))  # same directions: each vertex over its own
    beyond = anchor_crossings(inner[None], body[anchors][None], outer[None], F)[0][0] > 0
    assert beyond.sum() > 20 and not beyond[~bulge].any()
    assert layer_beyond_pct(inner[None], anchors, body[None], outer[None], F) > 1.0
    (u, o), report = untangle_layers([inner[None], outer[None]], [F, F], [anchors, anchors], body[None], F, GAP, [FLOOR, FLOOR + GAP])
    np.testing.assert_array_equal(o[0], outer)  # the outermost layer never moves
    assert layer_beyond_pct(u, anchors, body[None], o, F) == 0.0
    moved = np.linalg.norm(u[0] - inner, axis=1) > 0
    assert moved[beyond].all() and not moved[~_rings(F, beyond, SPREAD_RINGS + 1)].any()
    assert report.moved == [int(moved.sum()), 0] and report.held == [0, 0]
    r = np.linalg.norm(u[0][beyond], axis=1)
    # on the faceted outer sphere (radius 1 at its vertices, a little less inside its faces), at least the gap below it
    assert (r <= 1.0 - GAP + 1e-5).all() and (r >= 0.98 - GAP).all()
    assert (np.linalg.norm(u[0], axis=1) <= np.linalg.norm(inner, axis=1) + 1e-6).all()  # sinks, never rises
    assert report.max_move_m == pytest.approx(np.linalg.norm(u[0] - inner, axis=1).max(), rel=1e-5)


def test_an_opening_in_the_outer_layer_lets_the_inner_one_through(spheres):
    body, inner, outer, F, bulge = spheres
    open_faces = F[~(outer[F][:, :, 2] > 0.75).any(1)]  # a hole over the whole bulge
    anchors = body_anchors(inner, body)
    assert layer_beyond_pct(inner[None], anchors, body[None], outer[None], open_faces) == 0.0  # nothing to cross
    (u, _), report = untangle_layers([inner[None], outer[None]], [F, open_faces], [anchors, anchors], body[None], F, GAP, [FLOOR, FLOOR])
    # the hole's rim lies under the bulge's flanks (step (a) sinks those a little); its middle stays
    middle = inner[:, 2] > 0.9
    assert middle.sum() > 10
    np.testing.assert_array_equal(u[0][middle], inner[middle])
    assert report.moved[0] < bulge.sum()


def test_an_outer_layer_at_the_skin_holds_the_inner_one_half_way(spheres):
    body, inner, _, F, _ = spheres
    fine = trimesh.creation.icosphere(5)  # finer, and turned, so that no anchor segment meets one of its vertices or edges
    turn = trimesh.transformations.rotation_matrix(0.01, [1.0, 2.0, 3.0])[:3, :3]
    outer, Fo = (0.5015 * np.asarray(fine.vertices) @ turn.T).astype(np.float32), np.asarray(fine.faces, np.int64)  # 1.5 mm off the skin
    anchors = body_anchors(inner, body)
    (u, _), report = untangle_layers([inner[None], outer[None]], [F, Fo], [anchors, body_anchors(outer, body)], body[None], F, GAP, [FLOOR, FLOOR])
    d = np.linalg.norm(u[0], axis=1) - 0.5
    # sunk to the floor (2 mm), still beyond the outer layer: then half-way to it (~0.75 mm)
    assert report.held[0] == len(inner) and (np.abs(d - 0.00075) < 1e-4).all()


def test_untangle_checks_its_inputs(spheres):
    body, inner, outer, F, _ = spheres
    with pytest.raises(ValueError):
        untangle_layers([inner[None], outer[None]], [F], [np.arange(len(body))] * 2, body[None], F, GAP, [FLOOR, FLOOR])
    with pytest.raises(ValueError):
        anchor_crossings(inner[None], body[None, :10], outer[None], F)


def test_contacts_leave_out_only_parts_that_cannot_meet():
    # the fixture's spheres, finer (edges ~3 cm: contacts are judged at vertices, so the radius
    # must exceed an edge)
    s = trimesh.creation.icosphere(5)
    unit, F = np.asarray(s.vertices, np.float32), np.asarray(s.faces, np.int64)
    body, outer, inner = 0.5 * unit, 1.0 * unit, 0.9 * unit
    bulge = unit[:, 2] > 0.8  # up to 3 cm through the outer layer
    inner[bulge] = unit[bulge] * (0.9 + 0.13 * (unit[bulge, 2:3] - 0.8) / 0.2)
    anchors = body_anchors(inner, body)
    # 5 cm: of the inner sphere (10 cm under the outer one) only the bulge is near it
    contacts = LayerContacts.build([inner, outer], [F, F], radius_m=0.05)
    near = np.unique(F[contacts.inner_faces[0, 1]])
    assert 0 < len(near) < len(inner) / 4 and bulge[near].mean() > 0.5
    assert 0 < len(contacts.outer_vertices[0, 1]) < len(outer) / 4
    args = ([inner[None], outer[None]], [F, F], [anchors, anchors], body[None], F, GAP, [FLOOR, FLOOR + GAP])
    (u_near, _), _ = untangle_layers(*args, contacts)
    (u_all, _), _ = untangle_layers(*args)
    np.testing.assert_array_equal(u_near, u_all)
    assert not np.array_equal(u_all, inner[None])


def test_the_body_tree_is_kept_for_the_same_rest_body_only():
    from scipy.spatial import cKDTree

    from inference import layers as layers_module

    rng = np.random.default_rng(4)
    body = rng.normal(size=(500, 3)).astype(np.float32)
    garment = rng.normal(size=(200, 3)).astype(np.float32)
    tree = layers_module.body_tree(body)
    assert layers_module.body_tree(body.copy()) is tree  # same contents
    assert layers_module.body_tree(body * 1.01) is not tree  # another body
    np.testing.assert_array_equal(layers_module.body_anchors(garment, body, tree),
                                  cKDTree(body.astype(np.float64)).query(garment.astype(np.float64))[1])
    for i in range(layers_module.BODY_TREE_ENTRIES + 2):
        layers_module.body_tree(body * (1.1 + i))
    assert len(layers_module._BODY_TREES) == layers_module.BODY_TREE_ENTRIES


def test_anchors_and_contacts_are_kept_for_the_same_rest_forms_only():
    from inference import layers as layers_module

    s = trimesh.creation.icosphere(4)
    unit, F = np.asarray(s.vertices, np.float32), np.asarray(s.faces, np.int64)
    body, inner, outer = 0.5 * unit, 0.9 * unit, 1.0 * unit
    a = layers_module.kept_anchors(inner, body)
    np.testing.assert_array_equal(a, body_anchors(inner, body))
    assert layers_module.kept_anchors(inner.copy(), body.copy()) is a  # same contents: kept
    assert not a.flags.writeable  # a shared entry cannot be changed by one request
    moved = inner * np.float32(1.02)
    np.testing.assert_array_equal(layers_module.kept_anchors(moved, body), body_anchors(moved, body))
    c = LayerContacts.kept([inner, outer], [F, F])
    fresh = LayerContacts.build([inner, outer], [F, F])
    for got, want in ((c.outer_vertices, fresh.outer_vertices), (c.inner_faces, fresh.inner_faces)):
        assert got.keys() == want.keys() and all(np.array_equal(got[k], want[k]) for k in want)
    assert LayerContacts.kept([inner.copy(), outer.copy()], [F, F]) is c
    assert LayerContacts.kept([inner, outer * np.float32(0.95)], [F, F]) is not c  # another outer form
    assert LayerContacts.kept([inner, outer], [F.copy(), F]) is not c  # other faces arrays
    for i in range(layers_module.REST_ENTRIES + 2):
        layers_module.kept_anchors(inner * np.float32(1.1 + i), body)
    assert len(layers_module._RESTS) == layers_module.REST_ENTRIES


def test_kept_contacts_are_read_only():
    s = trimesh.creation.icosphere(3)
    unit, F = np.asarray(s.vertices, np.float32), np.asarray(s.faces, np.int64)
    c = LayerContacts.kept([0.9 * unit, unit], [F, F])
    assert not c.outer_vertices[0, 1].flags.writeable and not c.inner_faces[0, 1].flags.writeable


def _turned_fine_sphere(radius: float) -> tuple[np.ndarray, np.ndarray]:
    """An icosphere finer than the inner layer's and turned, so that no anchor segment meets one of
    its vertices or edges."""
    fine = trimesh.creation.icosphere(5)
    turn = trimesh.transformations.rotation_matrix(0.01, [1.0, 2.0, 3.0])[:3, :3]
    return (radius * np.asarray(fine.vertices) @ turn.T).astype(np.float32), np.asarray(fine.faces, np.int64)


def test_an_inner_layer_closer_than_the_gap_under_the_outer_one_sinks_to_the_gap(spheres):
    body, _, _, F, _ = spheres
    unit = body / 0.5
    inner = (0.999 * unit).astype(np.float32)  # under the outer layer everywhere, by ~1 mm: not beyond it
    outer, Fo = _turned_fine_sphere(1.0)
    anchors = body_anchors(inner, body)
    assert layer_beyond_pct(inner[None], anchors, body[None], outer[None], Fo) == 0.0
    (u, _), report = untangle_layers([inner[None], outer[None]], [F, Fo], [anchors, body_anchors(outer, body)], body[None], F, GAP,
                                     [FLOOR, FLOOR + GAP])
    r = np.linalg.norm(u[0], axis=1)
    # the gap under the faceted outer sphere (its faces dip ~0.3 mm inside radius 1), no deeper
    assert report.moved[0] == len(inner) and (r <= 1.0 - GAP + 1e-4).all() and (r >= 1.0 - GAP - 1e-3).all()



def test_the_rim_is_the_border_and_rings_in_from_it(spheres):
    from inference.layers import RIM_RINGS, _rim

    _, _, outer, F, _ = spheres
    Fo = F[~(outer[F][:, :, 2] > 0.75).any(1)]  # a hole: its border is the rim
    e = np.sort(Fo[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1)
    keys, count = np.unique(e, axis=0, return_counts=True)
    border = np.zeros(len(outer), bool)
    border[keys[count == 1].ravel()] = True
    rim = _rim(Fo, len(outer))
    rings = np.zeros(len(outer), bool)
    grown = _rings(Fo, border[: int(Fo.max()) + 1], RIM_RINGS)
    rings[: len(grown)] = grown
    np.testing.assert_array_equal(rim, rings)
    assert border.sum() > 10 and not rim.flags.writeable


def _sheet(n: int, spacing: float, z: float, shift=(0.0, 0.0), turn: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """A flat n x n grid of squares (two triangles each, facing +z) at height z, metres."""
    i, j = np.meshgrid(np.arange(n), np.arange(n), indexing="ij")
    xy = np.stack([i.ravel(), j.ravel()], 1) * spacing - 0.5 * (n - 1) * spacing
    c, s = np.cos(turn), np.sin(turn)
    xy = xy @ np.array([[c, s], [-s, c]]) + np.asarray(shift)
    v = np.concatenate([xy, np.full((n * n, 1), z)], 1).astype(np.float32)
    q = (i[:-1, :-1] * n + j[:-1, :-1]).ravel()
    faces = np.concatenate([np.stack([q, q + n, q + n + 1], 1), np.stack([q, q + n + 1, q + 1], 1)])
    return v, faces.astype(np.int64)


def test_the_gap_is_a_height_over_the_skin_along_an_oblique_anchor_segment():
    """Inner vertices 1 mm under a flat outer layer, each anchored 1 cm to the side (segments at
    ~22 degrees to the skin): they sink until they lie the gap under it in height over the skin,
    not the gap along their segment (which would leave them ~1.1 mm under it)."""
    body, body_faces = _sheet(21, 0.01, 0.0)
    inner, inner_faces = _sheet(21, 0.01, 0.004)
    outer, outer_faces = _sheet(40, 0.007, 0.005, shift=(0.0013, 0.0007), turn=0.01)
    n = 21
    anchors = np.arange(n * n) - n  # the body vertex one row back: 1 cm along x
    keep = anchors >= 0
    anchors[~keep] += n  # the first row: its own (vertical)
    (u, _), report = untangle_layers([inner[None], outer[None]], [inner_faces, outer_faces], [anchors, body_anchors(outer, body)],
                                     body[None], body_faces, GAP, [0.001, 0.004])
    inside = keep & (np.abs(inner[:, :2]) < 0.07).all(1)  # away from the sheets' borders
    z = u[0][inside, 2]
    assert report.moved[0] >= inside.sum()
    np.testing.assert_allclose(z, 0.005 - GAP, atol=2e-4)
