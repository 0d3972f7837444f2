"""Collision guard: hand-made pushes, squeeze limit, batch consistency, end-to-end on the posed body."""
import numpy as np
import pytest
import trimesh
from scipy.spatial import cKDTree

from inference.body import NEUTRAL_PHENOTYPES, BodyModel, linear_blend_skinning
from inference.errors import InputShapeError, InputValueError
from inference.guard import GuardPlan, LayerPlans, guard, guard_layers, push_outside
from inference.mesh import major_components, vertex_normals
from inference.metrics import inside_mask, near_self_intersection, signed_distance

MARGIN = 0.002


def _sphere(subdivisions=3):
    s = trimesh.creation.icosphere(subdivisions=subdivisions, radius=1.0)
    return s.vertices.astype(np.float32), s.faces.astype(np.int64)


def _knn(points, collider, k=8):
    return cKDTree(collider).query(points, k=k)[1]


def test_inside_point_pushed_to_exactly_margin_along_normal():
    verts, _ = _sphere()
    normals = verts / np.linalg.norm(verts, axis=1, keepdims=True)  # analytic normals
    idx = np.arange(0, len(verts), 7)
    radii = np.array([0.9, 0.999, 1.0 + MARGIN / 2, 1.0 + 2 * MARGIN, 1.1], np.float32)
    pts = (radii[:, None, None] * normals[idx][None]).reshape(-1, 3)
    cand = _knn(pts, verts)
    out = push_outside(pts[None, None], verts[None, None], normals[None, None], cand, MARGIN)[0, 0]
    r_in = np.linalg.norm(out, axis=1).reshape(len(radii), -1)
    # inside and within the margin: exactly margin outside, along the normal (direction kept)
    np.testing.assert_allclose(r_in[:3], 1.0 + MARGIN, atol=1e-6)
    np.testing.assert_allclose(out.reshape(len(radii), -1, 3)[:3] / r_in[:3, :, None], np.broadcast_to(normals[idx], (3, len(idx), 3)), atol=1e-6)
    # beyond the margin: bit-identical
    np.testing.assert_array_equal(out.reshape(len(radii), -1, 3)[3:], pts.reshape(len(radii), -1, 3)[3:])


def test_plane_push_keeps_tangential_coordinates():
    g = np.stack(np.meshgrid(np.linspace(-1, 1, 21), np.linspace(-1, 1, 21)), -1).reshape(-1, 2)
    plane = np.concatenate([g, np.zeros((len(g), 1))], 1).astype(np.float32)
    normals = np.tile(np.float32([0, 0, 1]), (len(plane), 1))
    rng = np.random.default_rng(0)
    pts = np.concatenate([rng.uniform(-0.9, 0.9, (200, 2)), rng.uniform(-0.05, 0.01, (200, 1))], 1).astype(np.float32)
    out = push_outside(pts[None, None], plane[None, None], normals[None, None], _knn(pts, plane), MARGIN)[0, 0]
    np.testing.assert_array_equal(out[:, :2], pts[:, :2])
    np.testing.assert_allclose(out[:, 2], np.maximum(pts[:, 2], MARGIN), atol=1e-7)


def test_squeezed_point_is_balanced_not_pushed_through():
    """Two facing plates 3 mm apart (gap < 2 margins) and two plates overlapping by 2 mm."""
    g = np.stack(np.meshgrid(np.linspace(-0.05, 0.05, 11), np.linspace(-0.05, 0.05, 11)), -1).reshape(-1, 2)
    for top, p_z, expected in [(0.003, 0.0005, 0.0015), (-0.002, -0.001, -0.001)]:
        lower = np.concatenate([g, np.zeros((len(g), 1))], 1)
        upper = np.concatenate([g, np.full((len(g), 1), top)], 1)
        coll = np.concatenate([lower, upper]).astype(np.float32)
        nrm = np.concatenate([np.tile([0, 0, 1.0], (len(g), 1)), np.tile([0, 0, -1.0], (len(g), 1))]).astype(np.float32)
        p = np.float32([[0.001, 0.002, p_z]])
        cand = np.concatenate([_knn(p, lower, 4), len(g) + _knn(p, upper, 4)], 1)
        across = np.array([[False] * 4 + [True] * 4])  # the upper plate is another part
        out = push_outside(p[None, None], coll[None, None], nrm[None, None], cand, MARGIN, across=across)[0, 0, 0]
        # gap: the point stops half-way (1.5 mm from both); overlap: inside both, it stays
        assert out[2] == pytest.approx(expected, abs=1e-7)
        np.testing.assert_array_equal(out[:2], p[0, :2])


def test_open_collider_border_is_not_extrapolated():
    """An inner garment patch that ends at x = 0: points beyond its border are left alone."""
    g = np.stack(np.meshgrid(np.linspace(-0.1, 0.0, 11), np.linspace(-0.05, 0.05, 11)), -1).reshape(-1, 2)
    patch = trimesh.Trimesh(np.concatenate([g, np.zeros((len(g), 1))], 1), _grid_faces(11, 11), process=False)
    verts = patch.vertices.astype(np.float32)[None]
    pts = np.float32([[[-0.05, 0.0, 0.001], [0.05, 0.0, 0.001]]])  # above the patch; 5 cm beyond its border
    plan = GuardPlan.build(pts + np.float32([0, 0, 0.01]), verts, patch.faces)
    out = guard(pts[:, None], verts[:, None], plan, MARGIN)[0, 0]
    assert out[0, 2] == pytest.approx(MARGIN, abs=1e-6)
    np.testing.assert_array_equal(out[1], pts[0, 1])


def _grid_faces(nx, ny):
    i = np.arange(nx - 1)[:, None] * ny + np.arange(ny - 1)[None]
    i = i.ravel()
    return np.concatenate([np.stack([i, i + ny, i + 1], 1), np.stack([i + 1, i + ny, i + ny + 1], 1)])


def test_batch_consistency_and_plan_on_mesh():
    verts, faces = _sphere(2)
    rng = np.random.default_rng(1)
    R = np.stack([np.linalg.qr(rng.normal(size=(3, 3)))[0] for _ in range(4)]).astype(np.float32)
    coll = np.einsum("bij,vj->bvi", R, verts)[:, None]  # (4, 1, V, 3): rotated spheres
    n = 200
    dirs = rng.normal(size=(n, 3))
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    rest = (dirs * rng.uniform(0.95, 1.01, (n, 1))).astype(np.float32)
    pts = np.einsum("bij,nj->bni", R, rest)[:, None]
    plan = GuardPlan.build(rest[None], verts[None], faces)
    all4 = guard(pts, coll, plan, MARGIN)
    one = np.concatenate([guard(pts[b : b + 1], coll[b : b + 1], plan, MARGIN) for b in range(4)])
    np.testing.assert_allclose(all4, one, atol=1e-7)
    assert not inside_mask(all4[:, 0], coll[:, 0], faces).any()
    # frames on the time axis give the same result as frames on the batch axis
    along_t = guard(pts.transpose(1, 0, 2, 3), coll.transpose(1, 0, 2, 3), plan, MARGIN)
    np.testing.assert_allclose(along_t[0], all4[:, 0], atol=1e-7)


def test_layers_outer_pushed_out_of_inner():
    verts, faces = _sphere(2)
    inner = (1.02 * verts)[None]  # a closed "garment" 2 cm outside a unit-sphere body
    rng = np.random.default_rng(2)
    d = rng.normal(size=(300, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    outer = (1.01 * d).astype(np.float32)[None]  # an outer layer sunk below the inner one
    plans = LayerPlans.build([inner, (1.04 * d).astype(np.float32)[None]], [faces, np.zeros((0, 3), np.int64)], verts[None], faces)
    g_inner, g_outer = guard_layers([inner[:, None], outer[:, None]], verts[None, None], plans, MARGIN, MARGIN)
    # out of the convex inner layer by at least the layer margin
    assert signed_distance(g_outer[:, 0], inner, faces).min() >= MARGIN - 1e-5
    np.testing.assert_allclose(g_inner, inner[:, None], atol=1e-7)  # inner already clear of the body


def test_input_validation():
    verts, faces = _sphere(1)
    with pytest.raises(InputShapeError):
        push_outside(np.zeros((1, 5, 3), np.float32), verts[None, None], verts[None, None], np.zeros((5, 2), int))
    with pytest.raises(InputValueError):
        push_outside(np.zeros((1, 1, 5, 3), np.float32), verts[None, None], verts[None, None], np.full((5, 2), len(verts)))
    with pytest.raises(InputValueError):
        push_outside(np.zeros((1, 1, 5, 3), np.float32), verts[None, None], verts[None, None], np.zeros((5, 2), int), -1.0)


# ------------------------------------------------------------------------------ real body
@pytest.fixture(scope="module")
def posed_body():
    body = BodyModel.load()
    shape = body.shape(NEUTRAL_PHENOTYPES[None])
    J = body.num_bones
    rng = np.random.default_rng(3)
    rot = np.zeros((1, 3, J, 3), np.float32)
    rot[0, 1, body.bone_names.index("LeftArm"), 2] = -1.2  # upper arm into the torso
    upper = [body.bone_names.index(n) for n in ("Spine", "Spine1", "Neck", "LeftArm", "RightArm", "LeftForeArm", "RightForeArm")]
    rot[0, 2, upper] = rng.normal(0.0, 0.25, (len(upper), 3))  # upper-body motion, no leg contact
    _, transforms = body.pose(shape.rest_bone_poses, rot, np.zeros((1, 3, 3), np.float32))
    return body, shape, transforms, body.skin(shape.rest_vertices, transforms)


def test_end_to_end_on_posed_body(posed_body):
    """Points 5 mm inside/outside the skin of garment-covered parts, skinned with the body."""
    body, shape, transforms, posed = posed_body
    F, V = body.faces, body.num_vertices
    covered = ~np.isin(body.dense_weights.argmax(1), [body.bone_names.index(n) for n in body.bone_names if n.endswith(("Foot", "ToeBase", "Hand", "Thumb", "FingerBase", "Finger1")) or n == "Head"])
    ids = np.random.default_rng(4).choice(np.flatnonzero(covered & major_components(F, V)), 3000, replace=False)
    n_rest = vertex_normals(shape.rest_vertices, F)
    offset = np.where(np.arange(len(ids)) % 2 == 0, -0.005, 0.005).astype(np.float32)[:, None]
    rest = shape.rest_vertices[:, ids] + offset * n_rest[:, ids]
    pts = linear_blend_skinning(rest, body.dense_weights[ids], transforms)  # (1, 3, N, 3)
    plan = GuardPlan.build(rest, shape.rest_vertices, F)
    out = guard(pts, posed, plan, MARGIN)
    for t in range(posed.shape[1]):
        before = inside_mask(pts[:, t], posed[:, t], F)[0]
        after = inside_mask(out[:, t], posed[:, t], F)[0]
        excluded = near_self_intersection(out[:, t], posed[:, t], F, 0.02)[0]
        assert before.sum() > 1000
        assert not (after & ~excluded).any(), f"frame {t}: {np.flatnonzero(after & ~excluded)} still inside"
        sd0 = signed_distance(pts[:, t], posed[:, t], F)[0]
        far = sd0 > MARGIN + 0.001
        np.testing.assert_array_equal(out[0, t, far], pts[0, t, far])  # outside beyond the margin: untouched
    assert (near_self_intersection(out[:, 1], posed[:, 1], F, 0.02)).sum() > 0  # the arm frame has a region


def _l_prism():
    """Closed L-shaped prism [0,2]x[0,1] u [0,1]x[0,2] x [0,1] (metres), coarse: 12 vertices. Its
    inner corner edge (x = y = 1) is concave."""
    ring = np.array([(0, 0), (2, 0), (2, 1), (1, 1), (1, 2), (0, 2)], np.float32)
    verts = np.concatenate([np.c_[ring, np.zeros(6)], np.c_[ring, np.ones(6)]]).astype(np.float32)
    fan = [(0, 1, 2), (0, 2, 3), (0, 3, 4), (0, 4, 5)]
    sides = [f for i in range(6) for f in ((i, (i + 1) % 6, 6 + (i + 1) % 6), (i, 6 + (i + 1) % 6, 6 + i))]
    faces = np.array([f[::-1] for f in fan] + [tuple(6 + j for j in f) for f in fan] + sides, np.int64)
    mesh = trimesh.Trimesh(verts, faces, process=False)
    trimesh.repair.fix_normals(mesh)
    assert mesh.is_volume
    return verts, np.asarray(mesh.faces, np.int64)


def test_closest_triangle_check_catches_a_point_the_vertex_plane_misjudges(monkeypatch):
    """Just inside the face x = 1 next to the concave corner edge, the nearest vertex is on that
    edge, whose tangent plane (normal along the notch's bisector) misjudges the point; the
    closest triangle (the face x = 1) shows it is inside, and the check moves it out."""
    import inference.guard.push as G  # the kernels read these constants

    verts, faces = _l_prism()
    rng = np.random.default_rng(0)  # up to 10 cm inside the face x = 1 of the upper bar
    pts = np.c_[rng.uniform(0.9, 1.0, 400), rng.uniform(1.05, 1.95, 400), rng.uniform(0.05, 0.95, 400)].astype(np.float32)
    assert inside_mask(pts[None], verts[None], faces).all()
    plan = GuardPlan.build(pts[None], verts[None], faces, k=4)
    assert plan.ring is not None

    plane_only = guard(pts[None, None], verts[None, None], plan, MARGIN, check=False)[0, 0]
    assert inside_mask(plane_only[None], verts[None], faces).mean() > 0.1  # the tangent planes miss them (117 of 400)
    monkeypatch.setattr(G, "REFINE_CANDIDATES", 0)  # the module switch gives the same
    np.testing.assert_array_equal(guard(pts[None, None], verts[None, None], plan, MARGIN)[0, 0], plane_only)
    monkeypatch.undo()

    out = guard(pts[None, None], verts[None, None], plan, MARGIN)[0, 0]
    assert not inside_mask(out[None], verts[None], faces).any()
    # outside: at the margin along the interpolated normal, which this coarse corner tilts far
    # from the face normal (0.8 mm of the 2 mm clearance is left at worst)
    d = signed_distance(out[None], verts[None], faces)[0]
    assert (d > 0.3 * MARGIN).all()


def test_closest_triangle_check_leaves_outside_points_alone():
    verts, faces = _sphere(2)
    rng = np.random.default_rng(4)
    dirs = rng.normal(size=(300, 3)).astype(np.float32)
    pts = (dirs / np.linalg.norm(dirs, axis=1, keepdims=True) * rng.uniform(1.003, 1.05, (300, 1))).astype(np.float32)
    plan = GuardPlan.build(pts[None], verts[None], faces)
    out = guard(pts[None, None], verts[None, None], plan, MARGIN)[0, 0]
    moved = np.linalg.norm(out - pts, axis=1) > 0
    # a point can only move when the surface is within the margin (vertex planes over-push on a
    # convex mesh); every point ends outside
    assert not inside_mask(out[None], verts[None], faces).any()
    assert (signed_distance(pts[None], verts[None], faces)[0][moved] < MARGIN + 0.05).all()


def test_a_reused_body_plan_comes_back_only_for_the_same_rest_form_and_body():
    from inference.guard import layers as guard_layers_module

    s = trimesh.creation.icosphere(subdivisions=2, radius=1.0)
    body = s.vertices.astype(np.float32)[None]
    shirt = (s.vertices * 1.01).astype(np.float32)[None]
    first = LayerPlans.build([shirt], [s.faces], body, s.faces, reuse=[True]).body[0]
    assert LayerPlans.build([shirt.copy()], [s.faces], body.copy(), s.faces, reuse=[True]).body[0] is first  # same contents
    fresh = LayerPlans.build([shirt], [s.faces], body, s.faces).body[0]  # not reused: built again, equal
    assert fresh is not first
    np.testing.assert_array_equal(fresh.candidates, first.candidates)
    moved = shirt.copy()
    moved[0, 0, 0] += 1e-3
    assert LayerPlans.build([moved], [s.faces], body, s.faces, reuse=[True]).body[0] is not first  # another rest form
    assert LayerPlans.build([shirt], [s.faces], body * 1.01, s.faces, reuse=[True]).body[0] is not first  # another body
    assert len(guard_layers_module._PLANS) <= guard_layers_module.PLAN_CACHE_ENTRIES


def test_a_plan_built_on_a_kept_body_equals_one_built_from_scratch():
    """What a plan derives from the body at rest alone is kept per body (``plan._collider_rest``):
    a plan on a kept body, with skin-aware candidates, equals one built with nothing kept, and
    another body's contents miss."""
    from inference.guard import plan as plan_module

    s = trimesh.creation.icosphere(subdivisions=3, radius=1.0)
    body = s.vertices.astype(np.float32)[None]
    rng = np.random.default_rng(2)
    shirt = (s.vertices * 1.02 + rng.normal(size=s.vertices.shape) * 1e-3).astype(np.float32)[None]
    # two "bones": the upper and the lower half, blended across the equator
    t = np.clip(s.vertices[:, 1] * 2 + 0.5, 0, 1)
    weights = np.stack([t, 1 - t], 1).astype(np.float32)
    plan_module._RESTS.clear()
    cold = GuardPlan.build(shirt, body, s.faces, skin=(weights, weights), k_skin=2)
    assert len(plan_module._RESTS) == 1
    warm = GuardPlan.build(shirt, body.copy(), s.faces, skin=(weights, weights), k_skin=2)  # same contents: kept
    assert len(plan_module._RESTS) == 1
    for name in ("collider_ids", "candidates", "across", "face_ids", "dynamic_points", "dynamic_region", "ring", "ring_valence"):
        np.testing.assert_array_equal(getattr(warm, name), getattr(cold, name))
    assert (warm.reach_m, warm.orientation) == (cold.reach_m, cold.orientation)
    GuardPlan.build(shirt, body * 1.01, s.faces, skin=(weights, weights), k_skin=2)  # another body
    assert len(plan_module._RESTS) == 2
    for i in range(plan_module.REST_CACHE_ENTRIES + 2):
        GuardPlan.build(shirt, body * (1.02 + 0.01 * i), s.faces)
    assert len(plan_module._RESTS) == plan_module.REST_CACHE_ENTRIES


def test_dynamic_region_is_the_near_vertices_and_one_far_vertex_per_cell():
    """``dynamic_region`` against its definition from the full distance matrix: every collider
    vertex within region_m of a point, and of those within reach_m the lowest index per voxel."""
    from inference.guard.plan import dynamic_region

    rng = np.random.default_rng(3)
    points = rng.uniform(-0.2, 0.2, (300, 3)).astype(np.float32)
    collider = rng.uniform(-0.6, 0.6, (4000, 3)).astype(np.float32)
    d = np.sqrt(((collider[:, None, :].astype(np.float64) - points[None]) ** 2).sum(-1)).min(1)
    near = set(np.flatnonzero(d <= 0.05).tolist())
    far = np.flatnonzero((d > 0.05) & (d <= 0.3))
    first = {}
    for i in far:  # ascending: the first vertex seen in a cell is its lowest index
        first.setdefault(tuple(np.floor(collider[i] / 0.02).astype(np.int64)), i)
    expected = np.array(sorted(near | set(first.values())))
    got = dynamic_region(points, collider, 0.05, 0.3, 0.02)
    assert np.array_equal(got, expected)
    assert len(near) > 10 and len(first) < len(far)  # the case tests both parts and the thinning
    assert np.array_equal(dynamic_region(points, collider, 0.05, 0.3, 0.0), np.flatnonzero(d <= 0.3))
