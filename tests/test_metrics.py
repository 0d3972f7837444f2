"""Metrics: exact inside test (winding numbers by ray crossings), distances, self-intersection, rates."""
import numpy as np
import pytest
import trimesh

from inference.body import NEUTRAL_PHENOTYPES, BodyModel
from inference.errors import InputShapeError
from inference.metrics import (
    collision_rates,
    inside_mask,
    layer_violation_pct,
    layer_violations,
    near_self_intersection,
    self_intersecting_vertices,
    self_intersection_exclusion,
    signed_distance,
    winding_numbers,
)


def _sphere(centre=(0.0, 0.0, 0.0), radius=1.0, subdivisions=3):
    s = trimesh.creation.icosphere(subdivisions=subdivisions, radius=radius)
    return s.vertices + np.asarray(centre), s.faces


def _two_spheres():
    """Two unit spheres overlapping in a lens around x = 0 (one closed mesh, two parts)."""
    va, fa = _sphere((-0.5, 0, 0))
    vb, fb = _sphere((0.5, 0, 0))
    return np.concatenate([va, vb]), np.concatenate([fa, fb + len(va)])


def test_sphere_inside_outside_analytic():
    v, f = _sphere()
    rng = np.random.default_rng(0)
    p = rng.uniform(-1.3, 1.3, (20000, 3))
    r = np.linalg.norm(p, axis=1)
    p, r = p[(r < 0.98) | (r > 1.0)], r[(r < 0.98) | (r > 1.0)]  # skip the faceting band
    w = winding_numbers(p[None], v[None], f)[0]
    np.testing.assert_array_equal(w, (r < 1.0).astype(np.int32))
    # faces wound inwards: the count flips sign
    np.testing.assert_array_equal(winding_numbers(p[None], v[None], f[:, ::-1])[0], -w)


def test_overlapping_parts_where_trimesh_contains_fails():
    v, f = _two_spheres()
    lens = np.array([[0.0, 0.0, 0.0], [0.1, 0.2, -0.1], [-0.2, -0.1, 0.3]])
    single = np.array([[-1.0, 0.0, 0.0], [1.0, 0.1, 0.0]])
    outside = np.array([[0.0, 0.0, 1.0], [2.0, 0.0, 0.0]])
    p = np.concatenate([lens, single, outside])
    w = winding_numbers(p[None], v[None], f)[0]
    np.testing.assert_array_equal(w, [2, 2, 2, 1, 1, 0, 0])
    np.testing.assert_array_equal(inside_mask(p[None], v[None], f)[0], [True] * 5 + [False] * 2)
    # a parity count of ray crossings (what trimesh.contains does) reads the lens as outside
    assert not (w[:3] % 2).any()


def test_trimesh_contains_misjudges_overlap():
    pytest.importorskip("rtree")  # trimesh's ray queries need it
    v, f = _two_spheres()
    lens = np.array([[0.0, 0.0, 0.0], [0.1, 0.2, -0.1]])
    assert not trimesh.Trimesh(v, f, process=False).contains(lens).any()
    assert inside_mask(lens[None], v[None], f).all()


def test_box_signed_distance():
    box = trimesh.creation.box(extents=(1.0, 1.0, 1.0))
    p = np.array([[0.0, 0.0, 0.0], [0.4, 0.0, 0.0], [0.0, 0.0, 0.51], [0.7, 0.0, 0.0], [0.0, -0.45, 0.1]])
    sd = signed_distance(p[None], box.vertices[None], box.faces)[0]
    np.testing.assert_allclose(sd, [-0.5, -0.1, 0.01, 0.2, -0.05], atol=1e-6)


@pytest.fixture(scope="module")
def body_frames():
    body = BodyModel.load()
    shape = body.shape(NEUTRAL_PHENOTYPES[None])
    J = body.num_bones
    rot = np.zeros((1, 2, J, 3), np.float32)
    rot[0, 1, body.bone_names.index("LeftArm"), 2] = -1.2  # upper arm rotated into the torso
    _, transforms = body.pose(shape.rest_bone_poses, rot, np.zeros((1, 2, 3), np.float32))
    return body, body.skin(shape.rest_vertices, transforms)[0]  # (2, V, 3): rest, arm down


def test_posed_body_against_exact_winding_numbers(body_frames):
    igl = pytest.importorskip("igl")
    body, posed = body_frames
    rng = np.random.default_rng(1)
    v = posed[1].astype(np.float64)
    fi = rng.integers(0, len(body.faces), 3000)
    near = (v[body.faces[fi]] * rng.dirichlet([1, 1, 1], 3000)[..., None]).sum(1) + rng.normal(0, 0.01, (3000, 3))
    box = rng.uniform(v.min(0), v.max(0), (3000, 3))
    p = np.concatenate([near, box])
    exact = np.round(igl.winding_number(v, body.faces.astype(np.int64), p)).astype(np.int32)
    np.testing.assert_array_equal(winding_numbers(p[None], posed[1:2], body.faces)[0], exact)
    assert (exact == 2).any()  # points inside both the arm and the torso


def test_batch_consistency(body_frames):
    body, posed = body_frames
    rng = np.random.default_rng(2)
    p = rng.uniform(posed.min((0, 1)), posed.max((0, 1)), (2, 2000, 3)).astype(np.float32)
    both = winding_numbers(p, posed, body.faces)
    one = np.concatenate([winding_numbers(p[b : b + 1], posed[b : b + 1], body.faces) for b in range(2)])
    np.testing.assert_array_equal(both, one)


def test_self_intersection_arm_into_torso(body_frames):
    body, posed = body_frames
    sx = self_intersecting_vertices(posed, body.faces)
    assert sx[0].sum() == 0  # the rest pose does not intersect itself (eyes and teeth ignored)
    assert sx[1].sum() > 100
    bones = {body.bone_names[j] for j in body.dense_weights[np.flatnonzero(sx[1])].argmax(1)}
    assert "LeftArm" in bones and bones & {"Spine", "Spine1", "LowerBack"}
    assert not bones & {"RightArm", "RightForeArm", "LeftUpLeg", "RightUpLeg", "Head"}
    region = self_intersection_exclusion(posed, body.faces, 0.02)
    assert region[0].sum() == 0 and region[1].sum() > sx[1].sum()
    assert region[1][sx[1]].all()


def test_collision_rates_hand_made():
    v, f = _sphere()
    # along vertex directions the icosphere's closest point is the vertex: sd = r - 1 outside
    d = v[np.random.default_rng(3).choice(len(v), 100, replace=False)]
    # 10 inside (0.9), 20 within 1 mm (1.0005), 30 within 2 mm (1.0015), 40 far (1.1)
    r = np.repeat([0.9, 1.0005, 1.0015, 1.1], [10, 20, 30, 40])
    g = (d * r[:, None])[None, None].repeat(2, 1)  # (1, T=2, 100, 3)
    out = collision_rates(g, v[None, None].repeat(2, 1), f, margin_m=0.002)
    assert out["inside_pct"] == pytest.approx(10.0)
    assert out["inside_pct_clean"] == pytest.approx(10.0)
    assert out["within_1mm_pct"] == pytest.approx(30.0)
    assert out["within_margin_pct"] == pytest.approx(60.0)
    assert out["points"] == 200 and out["clean_points"] == 200 and out["self_intersecting_vertices"] == 0
    np.testing.assert_allclose(signed_distance(g[0], v[None].repeat(2, 0), f)[:, 10:], np.broadcast_to(r[10:] - 1.0, (2, 90)), atol=1e-6)


def test_collision_rates_exclude_self_intersection():
    v, f = _two_spheres()
    sx = self_intersecting_vertices(v[None], f)[0]
    assert sx.sum() > 0
    centre = np.where(v[:, :1] < 0, -0.5, 0.5) * [1, 0, 0]
    a, b = np.flatnonzero(sx)[:2]
    lens = [v[i] - 0.01 * (v[i] - centre[i]) for i in (a, b)]  # 1 cm inside a vertex inside the other part
    g = np.array([[lens + [[-1.2, 0.0, 0.0], [1.2, 0.0, 0.0]]]])  # + two points inside one sphere only
    out = collision_rates(g, v[None, None], f, exclusion_radius_m=0.05)
    assert out["inside"] == 4 and out["inside_pct"] == pytest.approx(100.0)
    assert out["clean_points"] == 2 and out["inside_clean"] == 2
    np.testing.assert_array_equal(near_self_intersection(g[0], v[None], f, 0.05)[0], [True, True, False, False])
    np.testing.assert_array_equal(winding_numbers(g[0], v[None], f)[0], [2, 2, 1, 1])


def test_layer_violation_open_cylinder():
    cyl = trimesh.creation.cylinder(radius=1.0, height=1.0, sections=64)
    keep = np.abs(cyl.face_normals[:, 2]) < 0.5  # drop the caps: an open tube, normals outward
    outer = trimesh.Trimesh(cyl.vertices, cyl.faces[keep], process=True)
    ang = np.linspace(0, 2 * np.pi, 40, endpoint=False)
    ring = np.stack([np.cos(ang), np.sin(ang), np.zeros_like(ang)], 1)
    inner = np.concatenate([0.95 * ring, 1.05 * ring, 0.95 * ring + [0, 0, 0.8]])  # ok, outside, beyond the hem
    bad, covered = layer_violations(inner[None], outer.vertices[None], outer.faces)
    np.testing.assert_array_equal(covered[0], [True] * 80 + [False] * 40)
    np.testing.assert_array_equal(bad[0], [False] * 40 + [True] * 40 + [False] * 40)
    assert layer_violation_pct(inner[None, None], outer.vertices[None, None], outer.faces) == pytest.approx(100 * 40 / 120)


def test_input_validation():
    v, f = _sphere(subdivisions=1)
    with pytest.raises(InputShapeError):
        winding_numbers(np.zeros((5, 3)), v[None], f)
    with pytest.raises(InputShapeError):
        winding_numbers(np.zeros((2, 5, 3)), v[None], f)
    with pytest.raises(InputShapeError):
        winding_numbers(np.zeros((1, 5, 3)), v[None], f + len(v))


def test_skin_crossings_count_the_visible_body_faces_a_garment_crosses():
    """A small triangle through a sphere's surface crosses it; moved 1 cm out it does not; through
    the part of one sphere's surface that is inside the other (an arm in the torso) it is not seen."""
    import trimesh

    from inference.metrics import skin_crossings

    s = trimesh.creation.icosphere(subdivisions=3, radius=1.0)
    body = np.concatenate([s.vertices - [0.9, 0, 0], s.vertices + [0.9, 0, 0]]).astype(np.float32)[None]
    faces = np.concatenate([s.faces, s.faces + len(s.vertices)])
    plate = np.array([[[-0.2, -0.2, 0.0], [0.2, -0.2, 0.0], [0.0, 0.2, 0.0]]], np.float32)  # normal z
    top = np.array([-0.9, 0.0, 0.98], np.float32)  # 2 cm below the top of the left sphere, far from the other
    assert skin_crossings(plate + top, [[0, 1, 2]], body, faces) > 0
    assert skin_crossings(plate + top + [0, 0, 0.03], [[0, 1, 2]], body, faces) == 0
    # upright across the left sphere's tip at x = 0.1, which is inside the right sphere
    upright = np.array([[[0.05, 0.013, -0.05], [0.15, 0.013, -0.05], [0.1, 0.013, 0.05]]], np.float32)
    assert skin_crossings(upright, [[0, 1, 2]], body, faces) == 0
    # the same plate across the right sphere's outer tip (x = 1.9) is seen
    assert skin_crossings(upright + [1.8, 0.0, 0.0], [[0, 1, 2]], body, faces) > 0
