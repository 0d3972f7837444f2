"""Exact repair after the guard (inference/repair.py) and the reusable winding grid."""
import numpy as np
import pytest
import trimesh

from inference.errors import InputShapeError
from inference.repair import exact_repair
from inference.winding import WindingGrid, inflated, ray_down, winding_numbers


def _two_spheres():
    """Two unit spheres at x = -+0.9 overlapping in a lens around x = 0 (|x| < 0.1): one closed,
    self-intersecting mesh, like an LBS arm sunk into the torso."""
    s = trimesh.creation.icosphere(subdivisions=4, radius=1.0)
    v = np.concatenate([s.vertices + [-0.9, 0, 0], s.vertices + [0.9, 0, 0]]).astype(np.float32)
    return v, np.concatenate([s.faces, s.faces + len(s.vertices)])


def test_grid_answers_several_point_sets_per_frame():
    v, f = _two_spheres()
    frames = np.stack([v, v + [0.0, 0.0, 3.0]]).astype(np.float32)  # frame 1: the mesh moved up 3 m
    grid = WindingGrid(frames, f)
    p = np.array([[0.0, 0.0, 0.0], [-1.0, 0.0, 0.0], [0.0, 0.0, 1.5]], np.float32)  # lens, one part, outside
    np.testing.assert_array_equal(grid.count(np.stack([p, p])), [[2, 1, 0], [0, 0, 0]])
    np.testing.assert_array_equal(grid.count(np.stack([p + [0, 0, 3.0]] * 2)), [[0, 0, 0], [2, 1, 0]])
    rng = np.random.default_rng(0)
    q = rng.uniform(-2, 2, (2, 500, 3)).astype(np.float32)
    np.testing.assert_array_equal(grid.count(q), winding_numbers(q, frames, f))
    with pytest.raises(InputShapeError):
        grid.count(q[:1])


def test_grids_alive_together_keep_their_own_bins():
    """Each grid holds its own buffers of the per-thread pool until it is collected."""
    v, f = _two_spheres()
    p = np.array([[[0.0, 0.0, 0.0], [-1.0, 0.0, 0.0], [0.0, 0.0, 1.5], [0.0, 0.0, 1.0]]], np.float32)
    a = WindingGrid(v[None], f)
    b = WindingGrid((v * 3.0)[None], f)  # bigger: the buffers a took are not enough
    np.testing.assert_array_equal(a.count(p), [[2, 1, 0, 0]])
    np.testing.assert_array_equal(b.count(p), [[2, 1, 0, 2]])
    del a
    c = WindingGrid(v[None] + [0.0, 0.0, 3.0], f)  # reuses a's buffers
    np.testing.assert_array_equal(b.count(p), [[2, 1, 0, 2]])
    np.testing.assert_array_equal(c.count(p + [0.0, 0.0, 3.0]), [[2, 1, 0, 0]])


def test_far_from_the_origin_the_compiled_pre_test_stays_exact():
    """float64 input 10 km from the origin: the float32 face boxes of the pre-test are widened,
    so the counts equal libigl's exact winding numbers."""
    import igl

    v, f = _two_spheres()
    off = np.array([1.0e4, -2.0e3, 7.5e3])
    v64 = v.astype(np.float64) + off
    q = np.random.default_rng(1).uniform(-2, 2, (3000, 3)) + off
    q[:50] = v64[:50] + 1e-7  # within a micrometre of the surface, beyond float32's resolution here
    exact = np.round(igl.winding_number(v64, f.astype(np.int64), q)).astype(np.int32)
    np.testing.assert_array_equal(WindingGrid(v64[None], f).count(q[None])[0], exact)


def _bellows(sections=32, rings=300, height=3.0):
    """A closed, outward tube along y whose radius waves between 4 and 6 cm every 4 cm of height:
    every ring's band of faces projects onto the same annulus in (x, z)."""
    y = np.linspace(-height / 2, height / 2, rings)
    r = 0.05 + 0.01 * np.sin(2 * np.pi * y / 0.04)
    a = 2 * np.pi * np.arange(sections) / sections
    v = np.stack([r[:, None] * np.cos(a)[None], np.repeat(y[:, None], sections, 1), r[:, None] * np.sin(a)[None]], -1).reshape(-1, 3)
    v = np.concatenate([v, [[0.0, y[0], 0.0], [0.0, y[-1], 0.0]]])
    i, j = np.meshgrid(np.arange(rings - 1), np.arange(sections), indexing="ij")
    a0, a1 = (i * sections + j).ravel(), (i * sections + (j + 1) % sections).ravel()
    bot, top, k = len(v) - 2, len(v) - 1, np.arange(sections)
    last = (rings - 1) * sections
    f = np.concatenate([np.stack([a0, a0 + sections, a1], 1), np.stack([a1, a0 + sections, a1 + sections], 1),
                        np.stack([np.full(sections, bot), k, (k + 1) % sections], 1),
                        np.stack([np.full(sections, top), last + (k + 1) % sections, last + k], 1)])
    return v, f.astype(np.int64)


def test_a_cell_holding_thousands_of_faces_counts_them_all():
    """Every ring of a tall waved tube along the ray's axis (y) projects onto the same annulus,
    so a cell there holds faces of all 300 rings (far more than the count kernel's first list of
    candidates), and the counts still equal libigl's, rays up and down."""
    import igl

    v, f = _bellows()
    grid = WindingGrid(v[None], f)
    assert np.diff(grid.start).max() > 1000
    q = np.random.default_rng(4).uniform([-0.07, -1.6, -0.07], [0.07, 1.6, 0.07], (3000, 3))
    exact = np.round(igl.winding_number(v, f, q)).astype(np.int32)
    assert 500 < exact.sum() < 2500 and set(np.unique(exact)) == {0, 1}
    for down in (False, True):
        np.testing.assert_array_equal(grid.count(q[None], down=np.full((1, len(q)), down))[0], exact)


def test_the_first_outside_target_is_the_nearest_outside_one():
    """WindingGrid.first_outside equals testing every target with count_at, nearest first (a
    stable order), for either mesh of a grid over a region, targets beyond it included."""
    v, f = _two_spheres()
    frames = np.stack([v, v + [0.0, 0.0, 3.0]]).astype(np.float32)
    big = inflated(frames, f, 0.05)
    region = np.array([[-1.2, 1.2, -1.0, 1.0], [-1.2, 1.2, 2.0, 4.0]])
    grid = WindingGrid(big, f, second=frames, region=region)
    rng = np.random.default_rng(8)
    frame = rng.integers(0, 2, 400)
    points = (rng.uniform(-1.0, 1.0, (400, 3)) + [0.0, 0.0, 3.0] * frame[:, None]).astype(np.float32)
    targets = (points[:, None] + rng.normal(0.0, 0.6, (400, 16, 3))).astype(np.float32)  # some beyond the region
    targets[:20, 5] = targets[:20, 2]  # equal distances: the first column wins
    points[20:40] = [-0.9, 0.0, 0.0] + np.float32(3.0) * frame[20:40, None] * [0, 0, 1]  # deep in a part: no free target
    targets[20:40] = points[20:40, None] + rng.normal(0.0, 0.05, (20, 16, 3)).astype(np.float32)
    for mesh in ("first", "second", "either"):
        got = grid.first_outside(points, targets, frame, mesh)
        order = np.argsort(np.linalg.norm(targets - points[:, None], axis=-1), axis=1, kind="stable")
        tried = np.take_along_axis(targets, order[..., None], 1)
        free = grid.count_at(tried.reshape(-1, 3), np.repeat(frame, 16), mesh,
                             (tried[..., 1] < points[:, None, 1]).ravel()).reshape(400, 16) == 0
        want = np.where(free.any(1), order[np.arange(400), free.argmax(1)], -1)
        np.testing.assert_array_equal(got, want)
        assert (got == -1).any() and (got >= 0).any() and (got[:20] != 5).all()
    assert grid._whole  # some targets lay beyond the region


def test_first_outside_counts_a_known_target_once():
    """``known``: the verdicts the first call writes give the same answers without a count; a
    target marked inside is passed over and one marked outside taken, untested."""
    v, f = _two_spheres()
    grid = WindingGrid(v[None].astype(np.float32), f)
    rng = np.random.default_rng(3)
    points = rng.uniform(-1.0, 1.0, (300, 3)).astype(np.float32)
    targets = (points[:, None] + rng.normal(0.0, 0.6, (300, 12, 3))).astype(np.float32)
    frame = np.zeros(300, np.int64)
    plain = grid.first_outside(points, targets, frame)
    known = np.full((300, 8), -1, np.int8)  # the first 8 columns kept, the last 4 asked afresh
    np.testing.assert_array_equal(grid.first_outside(points, targets, frame, known=known), plain)
    counted = known >= 0
    assert counted.any() and (known[np.arange(300)[plain >= 0][plain[plain >= 0] < 8], plain[(plain >= 0) & (plain < 8)]] == 0).all()
    free = grid.count_at(targets[:, :8].reshape(-1, 3), np.zeros(300 * 8, np.int64)).reshape(300, 8) == 0
    np.testing.assert_array_equal(known[counted] == 0, free[counted])  # each verdict the count's
    again = known.copy()
    np.testing.assert_array_equal(grid.first_outside(points, targets, frame, known=again), plain)
    np.testing.assert_array_equal(again, known)  # nothing new to count
    # the verdicts are read, not counted again: a free target marked inside is passed over, and an
    # inside one marked outside is taken
    rows = np.flatnonzero((plain >= 0) & (plain < 8))
    lied = known.copy()
    lied[rows, plain[rows]] = 1
    moved = grid.first_outside(points, targets, frame, known=lied)
    assert (moved[rows] != plain[rows]).all()
    lied = np.where(known == 1, np.int8(0), known)
    order = np.argsort(np.linalg.norm(targets - points[:, None], axis=-1), axis=1, kind="stable")
    rank = np.argsort(order, axis=1)  # each column's place in its row's order
    first_lie = np.where(lied == 0, rank[:, :8], 99).min(1)  # the nearest target now called outside
    want = np.where(first_lie < np.where(plain >= 0, rank[np.arange(300), np.maximum(plain, 0)], 99),
                    order[np.arange(300), np.minimum(first_lie, 11)], plain)
    assert (want != plain).any()
    np.testing.assert_array_equal(grid.first_outside(points, targets, frame, known=lied), want)
    with pytest.raises(InputShapeError):
        grid.first_outside(points, targets, frame, known=np.full((300, 13), -1, np.int8))


def test_an_accepted_target_deep_in_the_list_is_the_nearest_accepted_outside_one():
    """With an outer layer to respect (``accept``), the final stage takes each point's nearest
    target that is outside and accepted, however far down its list (rounds growing from ROUND)."""
    from inference.repair import _move_outside

    v, f = _two_spheres()
    frames = np.stack([v, v + [0.0, 0.0, 3.0]]).astype(np.float32)
    grid = WindingGrid(frames, f)
    rng = np.random.default_rng(21)
    n, k = 300, 200
    frame = rng.integers(0, 2, n)
    Pb = (rng.uniform(-1.0, 1.0, (2, n, 3))).astype(np.float32)
    Pb[1] += np.float32([0.0, 0.0, 3.0])
    idx = np.arange(n)
    points = Pb[frame, idx]
    targets = (points[:, None] + rng.normal(0.0, 0.8, (n, k, 3))).astype(np.float32)
    rank = np.argsort(np.argsort(np.linalg.norm(targets - points[:, None], axis=-1), axis=1, kind="stable"), axis=1)
    deep = rng.integers(0, k, n)  # per point, only its targets from this rank on are accepted
    deep[:10] = k  # none accepted

    def accept(fr, ix, t):
        j = np.argmax(np.all(targets[ix] == t[:, None], axis=-1), axis=1)  # the column of each tried target
        return rank[ix, j] >= deep[ix]

    free = grid.count_at(targets.reshape(-1, 3), np.repeat(frame, k), "first",
                         (targets[..., 1] < points[:, None, 1]).ravel()).reshape(n, k) == 0
    ok_cols = free & (rank >= deep[:, None])
    want = np.where(ok_cols.any(1), np.argmin(np.where(ok_cols, rank, k), axis=1), -1)
    got = _move_outside(Pb, grid, "first", frame, idx, targets, accept)
    np.testing.assert_array_equal(got, want >= 0)
    moved = np.flatnonzero(want >= 0)
    np.testing.assert_array_equal(Pb[frame[moved], idx[moved]], targets[moved, want[moved]])
    np.testing.assert_array_equal(Pb[frame[:10], idx[:10]], points[:10])  # no accepted target: left where it was
    assert (deep[moved] > 100).sum() > 50  # many found theirs past the first 100 candidates
    # within a reach: the nearest accepted outside target no farther than it, or none
    reach = 0.9
    Pb[frame, idx] = points
    near = ok_cols & (np.linalg.norm(targets - points[:, None], axis=-1) <= reach)
    want_near = np.where(near.any(1), np.argmin(np.where(near, rank, k), axis=1), -1)
    got = _move_outside(Pb, grid, "first", frame, idx, targets, accept, reach_m=reach)
    np.testing.assert_array_equal(got, want_near >= 0)
    moved = np.flatnonzero(want_near >= 0)
    np.testing.assert_array_equal(Pb[frame[moved], idx[moved]], targets[moved, want_near[moved]])
    assert ((want >= 0) & (want_near < 0)).sum() > 20 and (want_near != want)[want_near >= 0].sum() == 0
    # the verdicts an accepting call counts (before accept's say) let a plain call on the same
    # targets find the same nearest outside ones
    Pb[frame, idx] = points
    known = np.full((n, k), -1, np.int8)
    _move_outside(Pb, grid, "first", frame, idx, targets, accept, reach_m=reach, known=known)
    counted = known >= 0
    assert counted.any() and np.array_equal(known[counted] == 0, free[counted])
    Pb[frame, idx] = points
    plain = _move_outside(Pb, grid, "first", frame, idx, targets)
    alone = Pb[frame, idx].copy()
    Pb[frame, idx] = points
    np.testing.assert_array_equal(_move_outside(Pb, grid, "first", frame, idx, targets, known=known), plain)
    np.testing.assert_array_equal(Pb[frame, idx], alone)


def test_the_compiled_targets_are_the_numpy_ones():
    """The final stage's plane and vertex targets (compiled) equal the numpy form of the module
    doc bitwise for float32 input (every request's): unit area-weighted normals of the skin
    vertices over their faces, depth clamped at -margin."""
    from inference import mesh_kernels
    from inference.mesh import faces_around
    from inference.repair import _targets

    v, f = _two_spheres()
    rng = np.random.default_rng(4)
    Bb = (np.stack([v, v * 1.1]) + rng.normal(0.0, 0.005, (2,) + v.shape)).astype(np.float32)
    n, k = 500, 8
    frame = rng.integers(0, 2, n)
    ids = rng.integers(0, len(v), (n, k))
    points = (Bb[frame, ids[:, 0]] + rng.normal(0.0, 0.05, (n, 3))).astype(np.float32)
    faces = f.astype(np.int32)  # the body model's
    frames, fpos = np.unique(frame, return_inverse=True)
    verts, vpos = np.unique(ids, return_inverse=True)
    slot = np.full(len(v), -1, np.int64)
    slot[verts] = np.arange(len(verts))
    normals = np.empty((len(frames), len(verts), 3))
    mesh_kernels.normals_at(Bb[frames], faces, faces_around(faces, verts, len(v)), slot, normals)
    c, nc = Bb[frame[:, None], ids], normals[fpos[:, None], vpos.reshape(ids.shape)]
    p = points[:, None, :]
    depth = np.maximum(np.einsum("nkc,nkc->nk", c - p, nc), -0.004)
    want = np.concatenate([p + (depth + 0.004)[..., None] * nc, c + 0.004 * nc], axis=1).astype(np.float32)
    got = _targets(Bb, frame, ids, faces, 0.004, points)
    assert got.dtype == np.float32 and got.shape == (n, 2 * k, 3)
    np.testing.assert_array_equal(got, want)
    assert (depth == -0.004).any() and (depth > 0).any()  # both sides of the tangent planes


def test_points_inside_the_overlap_or_a_part_end_outside_and_others_stay():
    v, f = _two_spheres()
    # inside both parts (the lens: no target among the nearest 32 is outside), inside one part
    # just beyond the other's surface, inside one part near its top; and outside
    inside = np.array([[0.0, 0.0, 0.0], [0.05, 0.2, 0.1], [0.15, 0.0, 0.0], [0.9, 0.0, 0.95]], np.float32)
    outside = np.array([[0.0, 0.0, 0.6], [2.0, 0.0, 0.0], [-0.9, 1.1, 0.0]], np.float32)
    p = np.concatenate([inside, outside])[None, None]  # (B=1, T=1, N, 3)
    body = v[None, None]
    out, left = exact_repair(p, body, f, margin_m=0.01)
    assert left == 0
    assert not winding_numbers(out[0], body[0], f).any()
    np.testing.assert_array_equal(out[0, 0, len(inside):], outside)  # untouched
    # each moved point is on the union's outer surface, ~margin outside it
    c = out[0, 0, : len(inside)]
    r = np.minimum(np.linalg.norm(c - [-0.9, 0, 0], axis=1), np.linalg.norm(c - [0.9, 0, 0], axis=1))
    assert np.all((r > 1.0) & (r < 1.03)), r
    # to the nearest outside target: the point near the top goes up, not across the sphere
    assert c[3, 2] > 0.95 and np.linalg.norm(c[3] - inside[3]) < 0.1


def test_batch_and_frames_are_independent():
    v, f = _two_spheres()
    body = np.stack([np.stack([v, v + [0, 0, 5.0]])] * 2).astype(np.float32)  # (2, 2, V, 3)
    p = np.zeros((2, 2, 1, 3), np.float32)  # the origin: inside in frame 0 only
    out, left = exact_repair(p, body, f, margin_m=0.005)
    assert left == 0
    assert np.linalg.norm(out[:, 0, 0], axis=-1).min() > 0.4  # moved out of the lens, to its rim
    np.testing.assert_array_equal(out[:, 1], p[:, 1])  # frame 1: outside already


def test_input_shapes_are_checked():
    v, f = _two_spheres()
    with pytest.raises(InputShapeError):
        exact_repair(np.zeros((1, 4, 3), np.float32), v[None, None], f, 0.002)
    with pytest.raises(InputShapeError):
        exact_repair(np.zeros((1, 2, 4, 3), np.float32), v[None, None], f, 0.002)


def test_layers_share_the_body_and_keep_their_margins():
    from inference.repair import repair_layers

    v, f = _two_spheres()
    body = v[None, None]
    inner = np.array([[[[0.0, 0.0, 0.0], [0.0, 0.0, 1.3]]]], np.float32)  # the lens; outside
    outer = np.array([[[[0.9, 0.0, 0.95], [0.9, 0.0, 1.2]]]], np.float32)  # inside the top of a part; outside
    (a, b), left = repair_layers([inner, outer], body, f, [0.005, 0.02])
    assert left == 0
    assert not winding_numbers(np.concatenate([a, b], axis=2)[0], body[0], f).any()
    np.testing.assert_array_equal(a[0, 0, 1], inner[0, 0, 1])
    np.testing.assert_array_equal(b[0, 0, 1], outer[0, 0, 1])
    assert 1.015 < np.linalg.norm(b[0, 0, 0] - [0.9, 0, 0]) < 1.03  # its own margin: 2 cm
    with pytest.raises(InputShapeError):
        repair_layers([inner, outer], body, f, [0.005])


def test_a_grid_over_a_region_bins_fewer_faces_and_answers_every_point():
    """Only the faces over each frame's region are binned; points inside it are answered by them,
    points beyond it by a grid of the whole mesh, so every count equals the whole grid's."""
    v, f = _two_spheres()
    frames = np.stack([v, v + [0.0, 0.0, 3.0]]).astype(np.float32)
    big = inflated(frames, f, 0.05)
    region = np.array([[-0.3, 0.3, -0.5, 0.2], [0.5, 1.2, 2.0, 3.5]])  # (x min, x max, z min, z max)
    grid = WindingGrid(big, f, second=frames, region=region)
    whole = WindingGrid(big, f, second=frames)
    assert len(grid.cell_face) < len(whole.cell_face) / 2
    rng = np.random.default_rng(3)
    inner = np.stack([rng.uniform(region[b, [0, 0, 2]], region[b, [1, 1, 3]], (1500, 3)) for b in range(2)])
    inner[..., 1] = rng.uniform(-1.2, 1.2, inner.shape[:2])
    for mesh in ("first", "second", "either"):
        np.testing.assert_array_equal(grid.count(inner, mesh), whole.count(inner, mesh))
    assert not grid._whole  # nothing beyond the region was asked
    q = rng.uniform(-2.2, 2.2, (2, 2000, 3)).astype(np.float32)
    q[1] += [0.0, 0.0, 3.0]
    for mesh in ("first", "second", "either"):
        np.testing.assert_array_equal(grid.count(q, mesh), whole.count(q, mesh))
    assert sorted(grid._whole) == [0, 1]  # a grid of the whole mesh per frame asked beyond it
    # a point beyond the region of one frame only: only that frame's whole mesh is binned
    grid = WindingGrid(big, f, second=frames, region=region)
    far = np.array([[[0.0, 0.0, 0.0]], [[1.8, 0.0, 3.0]]], np.float32)
    for mesh in ("first", "second", "either"):
        np.testing.assert_array_equal(grid.count(far, mesh), whole.count(far, mesh))
    assert list(grid._whole) == [1]
    with pytest.raises(InputShapeError):
        WindingGrid(big, f, region=region[:1])


def test_the_grids_cell_and_box_are_numpys():
    """The compiled median edge and (u, v) box equal the numpy expressions they replace, bitwise
    (the grid's bins depend on both), on odd and even sample counts and with unused vertices."""
    from inference import winding_kernels as kernels
    from inference.winding import CELL_EDGES, EDGE_SAMPLE

    v, f = _two_spheres()
    rng = np.random.default_rng(11)
    frames = (np.stack([v, v * 1.3 + 0.2]) + rng.normal(0.0, 0.01, (2,) + v.shape)).astype(np.float32)
    frames = np.concatenate([frames, np.full((2, 1, 3), 50.0, np.float32)], 1)  # a vertex no face uses
    for step in (1, 7, EDGE_SAMPLE):
        edge = frames[0, f[::step, 1]].astype(np.float64) - frames[0, f[::step, 0]]
        assert kernels.median_edge(frames[0], f.astype(np.int64), step) == np.median(np.linalg.norm(edge, axis=1))
    grid = WindingGrid(frames, f, second=frames - np.float32(0.05))
    edge = frames[0, f[::EDGE_SAMPLE, 1]].astype(np.float64) - frames[0, f[::EDGE_SAMPLE, 0]]
    assert grid.h == CELL_EDGES * np.median(np.linalg.norm(edge, axis=1))
    used = np.unique(f)
    both = np.concatenate([frames[:, used], frames[:, used] - np.float32(0.05)], 1).astype(np.float64)
    np.testing.assert_array_equal(grid.lo, both[..., [0, 2]].min(1))  # (u, v) = (x, z); not the far vertex


def test_rays_down_y_count_the_same_winding_numbers():
    """A closed mesh's winding number is the signed crossings of any ray: -y rays (per point)
    give the +y rays' numbers, in the overlap of the two parts too; ``ray_down`` picks -y where
    a vertex's outward normal points down y."""
    v, f = _two_spheres()
    frames = np.stack([v, v + [0.0, 0.0, 3.0]]).astype(np.float32)
    grid = WindingGrid(inflated(frames, f, 0.05), f, second=frames)
    rng = np.random.default_rng(4)
    q = rng.uniform(-2.2, 2.2, (2, 3000, 3)).astype(np.float32)
    q[1] += [0.0, 0.0, 3.0]
    down = rng.random(q.shape[:2]) < 0.5
    for mesh in ("first", "second", "either"):
        np.testing.assert_array_equal(grid.count(q, mesh, down), grid.count(q, mesh))
        np.testing.assert_array_equal(grid.count(q, mesh, np.ones_like(down)), grid.count(q, mesh))
    assert (grid.count(q) == 2).sum() > 5  # the lens is sampled
    picked = ray_down(frames, f)
    np.testing.assert_array_equal(picked[0, : len(v) // 2], v[: len(v) // 2, 1] < -1e-6)  # a sphere's normals are radial
    with pytest.raises(InputShapeError):
        grid.count(q, "first", down[:1])


def test_one_grid_answers_for_the_body_its_inflated_copy_or_either():
    v, f = _two_spheres()
    frames = np.stack([v, v + [0.0, 0.0, 3.0]]).astype(np.float32)
    big = inflated(frames, f, 0.05)
    # every vertex 5 cm out along its normal: the spheres' radius grows by ~5 cm (the normals of an
    # icosphere are radial; those on the lens' seam are not, so only the outer vertices are checked)
    r = np.linalg.norm(big[0, : len(v) // 2] - [-0.9, 0, 0], axis=1)
    outer = np.linalg.norm(v[: len(v) // 2] - [0.9, 0, 0], axis=1) > 1.0
    np.testing.assert_allclose(r[outer], 1.05, atol=2e-3)
    grid = WindingGrid(big, f, second=frames)
    q = np.random.default_rng(2).uniform(-2.2, 2.2, (2, 2000, 3)).astype(np.float32)
    q[1] += [0.0, 0.0, 3.0]
    first, second = winding_numbers(q, big, f), winding_numbers(q, frames, f)
    assert (first > second).sum() > 50  # the shell between the two is sampled
    np.testing.assert_array_equal(grid.count(q), first)
    np.testing.assert_array_equal(grid.count(q, "second"), second)
    np.testing.assert_array_equal(grid.count(q, "either"), np.maximum(first, second))
    with pytest.raises(ValueError):
        WindingGrid(frames, f).count(q, "second")


def test_points_within_the_clearance_move_out_unless_only_a_far_target_is_free():
    """The body inflated by the clearance is the test (inference.repair.CLEARANCE_M): a point 1 mm
    off the skin moves out to the margin, one 5 mm off stays; one in a 3 mm gap between two parts
    (within the clearance of both, outside the body) has no target near enough and stays."""
    from inference.repair import CLEARANCE_M, CLEARANCE_SLACK_M

    s = trimesh.creation.icosphere(subdivisions=5, radius=1.0)
    gap = 0.003
    v = np.concatenate([s.vertices - [1.0 + gap / 2, 0, 0], s.vertices + [1.0 + gap / 2, 0, 0]]).astype(np.float32)
    f = np.concatenate([s.faces, s.faces + len(s.vertices)])
    centre = np.array([1.0 + gap / 2, 0, 0])
    d = np.array([0.0, 0.0, 1.0])
    p = np.array([centre + 1.001 * d, centre + 1.005 * d, [0.0, 0.0, 0.0]], np.float32)[None, None]
    out, left = exact_repair(p, v[None, None], f, margin_m=0.002)
    assert left == 0
    r = np.linalg.norm(out[0, 0, 0] - centre)
    assert CLEARANCE_M < r - 1.0 < CLEARANCE_M + 2 * CLEARANCE_SLACK_M, r  # just beyond the clearance, along the normal
    np.testing.assert_allclose(out[0, 0, 0, :2], p[0, 0, 0, :2], atol=5e-4)
    np.testing.assert_array_equal(out[0, 0, 1:], p[0, 0, 1:])
    # with no clearance, only points inside the body move
    out0, _ = exact_repair(p, v[None, None], f, margin_m=0.002, clearance_m=0.0)
    np.testing.assert_array_equal(out0, p)


def _sphere_and_cover(patch: bool):
    """A unit sphere (the body), a point of an inner layer 2 cm inside it under its top vertex (the
    point's anchor), and an outer layer 4 mm over the skin: a 4 cm square patch over that vertex
    (room beside it), or a whole shell (no room under it at a 1 cm margin)."""
    s = trimesh.creation.icosphere(subdivisions=4, radius=1.0)
    body = s.vertices.astype(np.float32)
    top = int(np.argmax(body[:, 2]))
    inner = (0.98 * body[top])[None]
    if patch:
        w, (x, y) = 0.02, body[top, :2] + [0.003, 0.007]  # off the diagonal: no ray through an edge
        outer = np.array([[x - w, y - w, 1.004], [x + w, y - w, 1.004], [x + w, y + w, 1.004], [x - w, y + w, 1.004]], np.float32)
        outer_faces = np.array([[0, 1, 2], [0, 2, 3]])
    else:
        from scipy.spatial.transform import Rotation

        turn = Rotation.from_rotvec([0.011, 0.017, 0.0]).as_matrix()  # its vertices off the anchor's ray
        outer, outer_faces = (1.004 * body @ turn.T).astype(np.float32), s.faces
    return body, s.faces, inner, outer, outer_faces, [np.array([top]), np.zeros(len(outer), np.int64)]


def test_an_inner_point_leaves_the_body_under_the_outer_layer_where_a_target_allows():
    from inference.layers import anchor_crossings
    from inference.repair import LayerOrder, repair_layers

    for under in (True, False):
        body, faces, inner, patch, patch_faces, anchors = _sphere_and_cover(patch=under)
        layers = [inner[None, None], patch[None, None]]
        plain, _ = repair_layers(layers, body[None, None], faces, [0.01, 0.01], clearance_m=0.0)
        ordered, left = repair_layers(layers, body[None, None], faces, [0.01, 0.01], clearance_m=0.0,
                                      order=LayerOrder(anchors, [np.zeros((0, 3), np.int64), patch_faces]))
        assert left == 0
        np.testing.assert_array_equal(ordered[1], layers[1])  # the outermost layer is not moved for the order
        for out in (plain, ordered):  # out of the body either way: the body comes first
            assert not winding_numbers(out[0][0], body[None], faces).any()

        def beyond(out):
            return anchor_crossings(out[0][0], body[None, anchors[0]], patch[None], patch_faces)[0][0, 0] % 2 == 1

        assert beyond(plain)  # straight out, through the patch
        assert beyond(ordered) != under


def test_nearest_skin_vertices_of_the_grid_equal_a_kd_trees():
    """``frame_knn`` (the repair's nearest skin vertices per frame) gives a KD-tree's k nearest,
    nearest first, for points inside, on and off a mesh, and leaves to the caller the points whose
    k nearest may lie beyond their frame's box."""
    from scipy.spatial import cKDTree

    from inference.repair_kernels import MANY_K, frame_knn

    rng = np.random.default_rng(3)
    v, _ = _two_spheres()
    verts = np.stack([v, v * 1.1 + [0.0, 0.3, 0.0]]).astype(np.float32)
    ids = np.flatnonzero(rng.random(len(v)) < 0.8)
    q = np.concatenate([rng.normal(size=(40, 3)) * 0.9, v[rng.choice(len(v), 20)] + rng.normal(size=(20, 3)) * 0.01])
    frame = rng.integers(0, 2, len(q))
    order = np.argsort(frame, kind="stable")
    frames, counts = np.unique(frame[order], return_counts=True)
    starts = np.concatenate([[0], np.cumsum(counts)])
    trees = [cKDTree(verts[f, ids].astype(np.float64)) for f in range(2)]
    for k in (8, MANY_K + 36):  # an insertion into the k best, and above MANY_K one sort of all read
        for pad in (0.05, 0.3, 5.0):
            nn, found = frame_knn(verts, frames, starts, q[order], ids, k, pad, 0.1)
            for p, f in enumerate(frame[order]):
                dist, want = trees[f].query(q[order][p], k=k)
                if found[p]:
                    assert np.array_equal(nn[p], ids[want])
                else:
                    assert dist[-1] > pad  # only a point whose k-th nearest lies beyond the box is left
            assert found.all() == (pad == 5.0)
        # a search stopped at a radius leaves the points whose k-th nearest lies beyond it; the
        # others have the same answer
        wide = frame_knn(verts, frames, starts, q[order], ids, k, 5.0, 0.1)[0]
        nn, found = frame_knn(verts, frames, starts, q[order], ids, k, 5.0, 0.1, 0.4)
        kth = np.array([trees[f].query(q[order][p], k=k)[0][-1] for p, f in enumerate(frame[order])])
        assert found.any() and not found.all()
        assert (kth[~found] > 0.4 - 1e-6).all() and np.array_equal(nn[found], wide[found])
    # equal distances keep the order read in both paths: the first 8 of the many are the 8
    grid = np.stack(np.meshgrid(*[np.arange(6.0)] * 3, indexing="ij"), -1).reshape(-1, 3).astype(np.float32) * 0.05
    pts = np.array([[0.125, 0.125, 0.125], [0.1, 0.1, 0.1]])
    args = (grid[None], np.zeros(1, np.int64), np.array([0, 2], np.int64), pts, np.arange(len(grid), dtype=np.int64))
    few, many = frame_knn(*args, 8, 1.0, 0.05), frame_knn(*args, MANY_K + 1, 1.0, 0.05)
    assert few[1].all() and many[1].all() and np.array_equal(many[0][:, :8], few[0])


def test_a_skin_mask_gives_the_same_skin_faces_array_each_request():
    # the target normals' vertex-to-faces table is kept per faces array: equal masks from two
    # requests (two objects) must reach it as one array, with the faces whose corners are all skin
    from inference.repair import _masked_skin

    faces = np.array([[0, 1, 2], [1, 2, 3], [2, 3, 4], [4, 5, 6]])
    mask = np.array([1, 1, 1, 1, 0, 1, 1], bool)
    ids, a = _masked_skin(faces, mask.copy().tobytes())
    _, b = _masked_skin(faces, mask.copy().tobytes())
    assert a is b
    np.testing.assert_array_equal(ids, [0, 1, 2, 3, 5, 6])
    np.testing.assert_array_equal(a, faces[:2])
    other = _masked_skin(faces, np.ones(7, bool).tobytes())[1]
    assert other is not a and len(other) == 4


def test_inner_points_sink_under_the_faces_the_final_stage_moved_across_them():
    # a unit sphere (the body); inner points 6 mm over the skin at two anchors; an outer patch that
    # this stage moved from 2 cm over the skin down to 4 mm over it at the first anchor (across
    # that inner point's anchor segment) and left alone elsewhere: that point goes back along its
    # segment to the gap under the patch, the other one (no face moved near it) and the frame
    # where nothing moved keep theirs
    from inference.layers import anchor_crossings
    from inference.repair import LayerOrder, _sink_under_moved

    s = trimesh.creation.icosphere(subdivisions=4, radius=1.0)
    body = s.vertices.astype(np.float32)
    top = int(np.argmax(body[:, 2]))
    side = int(np.argmax(body[:, 0]))
    anchors = np.array([top, side])
    inner = (body[anchors] * 1.006)[None].repeat(2, 0)  # (2 frames, 2, 3)
    w, (x, y) = 0.02, body[top, :2] + [0.003, 0.007]
    square = np.array([[x - w, y - w], [x + w, y - w], [x + w, y + w], [x - w, y + w]])
    before = np.concatenate([square, np.full((4, 1), 1.02)], 1).astype(np.float32)[None].repeat(2, 0)
    after = before.copy()
    after[0, :, 2] = 1.004  # frame 0: moved across the first point's segment; frame 1: not moved
    faces = np.array([[0, 1, 2], [0, 2, 3]])
    order = LayerOrder([anchors, np.zeros(4, np.int64)], [np.zeros((0, 3), np.int64), faces], gap_m=0.001)
    body_frames = body[None].repeat(2, 0)
    P = inner.copy()
    assert anchor_crossings(P, body_frames[:, anchors], after, faces)[0][0, 0] == 1  # beyond the moved patch
    assert _sink_under_moved(P, body_frames, s.faces, order, 0, 1, before, after, floor_m=0.0) == 1
    assert anchor_crossings(P, body_frames[:, anchors], after, faces)[0][0, 0] == 0  # under it now
    height = np.linalg.norm(P[0, 0]) - 1.0
    assert 0.002 < height < 0.0035, height  # the gap (1 mm) under the patch at 4 mm, along its segment
    np.testing.assert_array_equal(P[0, 1], inner[0, 1])
    np.testing.assert_array_equal(P[1], inner[1])


def _slab_and_flips():
    """A slab 6 cm thick (an ellipsoid 1 m x 6 cm x 1 m, still in 4 frames) and one point inside
    it, 2 mm on one side of its middle and then the other: its nearest way out, 3 cm off, is
    up (+y) in frames 0 and 3 and down in frames 1 and 2."""
    s = trimesh.creation.icosphere(subdivisions=4, radius=1.0)
    body = (s.vertices * [0.5, 0.03, 0.5]).astype(np.float32)
    y = np.array([0.002, -0.002, -0.002, 0.002], np.float32)
    points = np.zeros((1, 4, 1, 3), np.float32)
    points[0, :, 0] = [0.0123, 0.0, 0.0071]  # off the vertical through the slab's middle vertex
    points[0, :, 0, 1] = y
    return np.repeat(body[None, None], 4, axis=1), np.asarray(s.faces), points


def test_a_point_keeps_its_side_of_a_limb_from_frame_to_frame_within_a_motion():
    """The final stage's hold (``repair._hold_sides``): a point whose nearest way out flips to the
    other side of a thin part keeps the side it had (3.2 against 2.8 cm: within HOLD_M), so it does
    not jump 6 cm from frame to frame; a new motion (``segments``) chooses afresh; a chunk that
    goes on from another (``moves_before``) holds as the whole motion does."""
    from inference import repair
    from inference.repair import repair_layers

    body, faces, points = _slab_and_flips()
    side = lambda out: np.sign(out[0][0, :, 0, 1])  # noqa: E731 - the side each frame went out on

    hold = repair.HOLD_M
    try:
        repair.HOLD_M = 0.0  # no hold: each frame alone, its nearest way out
        np.testing.assert_array_equal(side(repair_layers([points], body, faces, [0.002])[0]), [1, -1, -1, 1])
    finally:
        repair.HOLD_M = hold
    whole, left = repair_layers([points], body, faces, [0.002])
    assert left == 0 and not winding_numbers(whole[0][0], body[0], faces).any()
    np.testing.assert_array_equal(side(whole), [1, 1, 1, 1])
    # two motions of two frames each: the second chooses its first frame afresh, then holds it
    np.testing.assert_array_equal(side(repair_layers([points], body, faces, [0.002], segments=[2, 2])[0]), [1, 1, -1, -1])
    # frames 2-3 as a chunk that goes on from frame 1's move: as in the whole motion
    moved = whole[0][0, 1, 0] - points[0, 1, 0]
    chunk = repair_layers([points[:, 2:]], body[:, 2:], faces, [0.002], moves_before=[moved[None]])[0]
    np.testing.assert_array_equal(chunk[0], whole[0][:, 2:])
    with pytest.raises(InputShapeError):
        repair_layers([points], body, faces, [0.002], segments=[3, 2])


def test_neighbours_leave_a_thin_part_on_one_side():
    """The final stage keeps neighbours together (``repair._keep_together``): a strip of cloth (2 x 6
    vertices, 1 cm apart) inside a slab 6 cm thick, 2 mm above its middle but for its last column,
    2 mm below. Each point alone takes its nearest way out and the strip tears 6 cm across the
    slab; kept together, the last column goes out on its neighbours' side, 4 mm farther (within
    KEEP_M), and no edge stretches."""
    from inference import repair
    from inference.repair import repair_layers

    s = trimesh.creation.icosphere(subdivisions=4, radius=1.0)
    body, body_faces = (s.vertices * [0.5, 0.03, 0.5]).astype(np.float32)[None, None], np.asarray(s.faces)
    cols = 6
    grid = np.zeros((2, cols, 3), np.float32)
    grid[..., 0] = 0.0123 + 0.01 * np.arange(cols)  # off the verticals through the slab's vertices
    grid[..., 2] = [[0.0071], [0.0171]]
    grid[..., 1] = 0.002
    grid[:, -1, 1] = -0.002
    points = grid.reshape(1, 1, -1, 3)
    quads = [(r * cols + c, r * cols + c + 1, (r + 1) * cols + c + 1, (r + 1) * cols + c) for r in range(1) for c in range(cols - 1)]
    faces = np.array([f for a, b, c, d in quads for f in ((a, b, c), (a, c, d))])
    edges = np.unique(np.sort(np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]]), axis=1), axis=0)
    growth = lambda x: (np.linalg.norm(x[edges[:, 0]] - x[edges[:, 1]], axis=1)  # noqa: E731
                        - np.linalg.norm(points[0, 0, edges[:, 0]] - points[0, 0, edges[:, 1]], axis=1)).max()
    passes = repair.KEEP_PASSES
    try:
        repair.KEEP_PASSES = 0  # each point alone
        alone = repair_layers([points], body, body_faces, [0.002], faces=[faces])[0][0][0, 0]
    finally:
        repair.KEEP_PASSES = passes
    np.testing.assert_array_equal(np.sign(alone[:, 1]).reshape(2, cols), [[1] * (cols - 1) + [-1]] * 2)
    assert growth(alone) > 0.05
    kept, left = repair_layers([points], body, body_faces, [0.002], faces=[faces])
    kept = kept[0][0, 0]
    assert left == 0 and not winding_numbers(kept[None], body[0], body_faces).any()
    assert (kept[:, 1] > 0.03).all()  # every point out on the upper side
    assert growth(kept) < 0.002


def test_an_inner_point_left_on_its_skin_vertex_moves_off_it():
    """The layer stage can put an inner point on its anchor (half-way under an outer layer that
    crosses at the skin); on the surface a ray's inside test is a tie, so the final stage moves it
    out as if it were inside."""
    from inference.repair import LayerOrder, repair_layers

    s = trimesh.creation.icosphere(subdivisions=4, radius=1.0)
    body = s.vertices.astype(np.float32)
    top = int(np.argmax(body[:, 2]))
    inner = body[[top]][None, None].copy()  # (1, 1, 1, 3): exactly on the skin vertex
    outer = (body * 1.02)[None, None]  # a sphere 2 cm over the skin
    order = LayerOrder([np.array([top]), np.arange(len(body))], [np.zeros((0, 3), np.int64), np.asarray(s.faces)])
    out, left = repair_layers([inner, outer], body[None, None], s.faces, [0.002, 0.005], order=order)
    height = np.linalg.norm(out[0][0, 0, 0]) - 1.0
    assert left == 0 and 0.001 < height < 0.003, height  # out to the inner layer's margin, under the outer one


def test_rays_through_a_projected_vertex_count_as_rays_beside_it():
    """A point straight above or below a mesh vertex casts its ray through that vertex: the faces
    around it must count it once in all (the point on an edge's line takes the side of an
    infinitesimally moved point). Same numbers as libigl's exact winding numbers, off the surface."""
    import igl

    v, f = _two_spheres()
    rng = np.random.default_rng(2)
    q = v[rng.integers(0, len(v), 3000)].copy()
    q[:, 1] = rng.uniform(-1.5, 1.5, len(q))  # the x and z of a vertex: the vertical ray meets it
    exact = igl.winding_number(v.astype(np.float64), f.astype(np.int64), q.astype(np.float64))
    off = np.abs(exact - np.round(exact)) < 1e-3  # not on the surface (ambiguous there)
    counted = WindingGrid(v[None], f).count(q[None])[0]
    np.testing.assert_array_equal(counted[off], np.round(exact[off]).astype(np.int32))
    assert off.sum() > 2900 and (counted[off] > 0).sum() > 500  # inside both parts, one, or none


def test_ray_down_is_the_sign_of_the_normals_y():
    # ``ray_down`` sums the faces' y components alone: the same answers as the full area-weighted
    # normals' (``mesh_kernels.normals_at``, which the normalisation leaves the sign of), a
    # crumpled sphere with flat (zero) and degenerate faces included
    import trimesh

    from inference import mesh_kernels

    s = trimesh.creation.icosphere(subdivisions=3)
    rng = np.random.default_rng(9)
    frames = (s.vertices[None] + rng.normal(0, 0.05, (3, len(s.vertices), 3))).astype(np.float32)
    frames[1, :, 0] = 0.25  # a frame flattened onto a plane of x: every normal along x, its y component 0
    faces = np.asarray(s.faces, np.int64).copy()
    faces[::50, 1] = faces[::50, 0]  # degenerate faces
    n = np.empty(frames.shape, np.float64)
    mesh_kernels.normals_at(np.ascontiguousarray(frames), faces, np.arange(len(faces)), np.arange(frames.shape[1]), n)
    got = ray_down(frames, faces)
    assert np.array_equal(got, n[..., 1] < 0.0)
    assert got[0].any() and not got[0].all() and not got[1].any()


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_points_on_their_skin_vertex_are_numpys(dtype):
    # ``repair_kernels.on_skin``: |p - b_anchor|^2 < eps^2 in the frames' precision, as numpy's
    # einsum sums the squares; points on, near and off their anchors
    from inference import repair_kernels
    from inference.repair import ON_SKIN_M

    rng = np.random.default_rng(6)
    B = rng.normal(0, 0.3, (3, 50, 3)).astype(dtype)
    anchors = rng.integers(0, 50, 40)
    P = (B[:, anchors] + rng.normal(0, 1, (3, 40, 1)) * 10.0 ** rng.integers(-8, -2, (3, 40, 1)) * rng.normal(0, 1, (3, 40, 3))).astype(dtype)
    P[1, :5] = B[1, anchors[:5]]  # exactly on
    off = P - B[:, anchors]
    want = np.einsum("tnc,tnc->tn", off, off) < ON_SKIN_M ** 2
    got = np.zeros(want.shape, bool)
    repair_kernels.on_skin(P, B, anchors.astype(np.int64), np.dtype(dtype).type(ON_SKIN_M ** 2), got)
    assert np.array_equal(got, want) and want.any() and not want.all()
