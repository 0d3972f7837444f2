"""Garment catalog build (training.assets.garments_mesh / garments_fit / build_garments)."""
from __future__ import annotations

import numpy as np
import pytest
import scipy.sparse as sp
import trimesh

from inference.body import ASSETS_DIR, BodyModel
from inference.garment import HM08_VERTEX_COUNT, bind_garment
from training.assets import build_garments as bg
from training.assets import garments_fit as fit
from training.assets import garments_mesh as gm


def grid_mesh(n: int = 3) -> tuple[gm.GarmentMesh, np.ndarray]:
    """An n x n quad grid (z = 0, unit spacing) as a triangle GarmentMesh and its positions."""
    ij = np.stack(np.meshgrid(np.arange(n + 1), np.arange(n + 1), indexing="ij"), -1).reshape(-1, 2)
    pos = np.concatenate([ij.astype(float), np.zeros((len(ij), 1))], 1)
    vid = np.arange(len(ij)).reshape(n + 1, n + 1)
    quads = np.stack([vid[:-1, :-1], vid[1:, :-1], vid[1:, 1:], vid[:-1, 1:]], -1).reshape(-1, 4)
    faces, face_uvs = gm.triangulate_quads(quads, quads, pos)
    V = len(pos)
    mesh = gm.GarmentMesh(faces, pos[:, :2].copy(), face_uvs, sp.identity(V, format="csr"), np.zeros(V, np.int64))
    return mesh, pos


def test_subdivide_midpoints_and_sources():
    mesh, pos = grid_mesh(2)
    sub = gm.subdivide(mesh)
    V, E = mesh.n_vertices, len(gm.unique_edges(mesh.faces))
    assert sub.n_vertices == V + E and len(sub.faces) == 4 * len(mesh.faces)
    np.testing.assert_allclose(np.asarray(sub.source.sum(1)).ravel(), 1.0)
    p = sub.positions(pos)
    # every new vertex is the midpoint of an old edge; the grid becomes the 4 x 4 half-unit grid
    assert set(map(tuple, np.round(p * 2).astype(int))) == {(i, j, 0) for i in range(5) for j in range(5)}
    # UVs follow (here uv = xy)
    np.testing.assert_allclose(sub.uvs[sub.face_uvs], p[sub.faces][..., :2])
    assert trimesh.Trimesh(p, sub.faces, process=False).is_winding_consistent


def test_subdivide_rejects_t_junctions():
    mesh, _ = grid_mesh(2)
    mask = np.zeros(len(mesh.faces), bool)
    mask[0] = True
    with pytest.raises(ValueError, match="T-junctions"):
        gm.subdivide(mesh, mask)


def test_boundary_loops_and_orientation():
    mesh, pos = grid_mesh(3)
    (loop,) = gm.boundary_loops(mesh.faces)
    assert len(loop) == 12
    flipped = mesh.faces.copy()
    flipped[4] = flipped[4, ::-1]  # a triangle of the centre quad
    bad = gm.GarmentMesh(flipped, mesh.uvs, flipped.copy(), mesh.source, mesh.piece)
    patches = gm.orientation_patches(bad.faces)
    assert np.bincount(patches).tolist() == [17, 1]  # the reversed face is a patch of its own
    fixed = gm.orient_consistently(bad)
    assert trimesh.Trimesh(pos, fixed.faces, process=False).is_winding_consistent
    # face_uvs are permuted with their faces (uv index == vertex index here)
    np.testing.assert_array_equal(fixed.face_uvs, fixed.faces)
    up = gm.orient_outward(fixed, pos, np.tile([0.0, 0.0, -1.0], (len(pos), 1)))
    assert np.all(trimesh.Trimesh(pos, up.faces, process=False).face_normals[:, 2] < 0)


def test_merge_and_collapse_short_edges():
    mesh, pos = grid_mesh(3)
    pos = pos.copy()
    pos[5] = pos[6] + [0.0, 0.001, 0.0]  # vertex 5 almost on vertex 6
    out = gm.collapse_short_edges(mesh, pos, 0.01)
    assert out.n_vertices == mesh.n_vertices - 1
    p = out.positions(pos)
    np.testing.assert_allclose(p[5], 0.5 * (pos[5] + pos[6]))  # the average
    assert len(out.faces) == len(mesh.faces) - 2  # the two faces on the collapsed edge
    assert trimesh.Trimesh(p, out.faces, process=False).is_winding_consistent


def test_bridge_loops_closes_a_band():
    """Two rings around the z axis (different vertex counts) become one closed band."""
    def ring(n, z, r):
        t = np.linspace(0, 2 * np.pi, n, endpoint=False)
        return np.stack([r * np.cos(t), r * np.sin(t), np.full(n, z)], 1)

    # ring a (12, z=1), ring b (7, z=0), and a strip of faces above ring a (to orient the bridge by)
    pos = np.concatenate([ring(12, 1.0, 1.0), ring(7, 0.0, 1.2), ring(12, 1.5, 1.0)])
    a = np.arange(12)
    faces = np.concatenate([np.stack([a, (a + 1) % 12, 19 + a], 1), np.stack([(a + 1) % 12, 19 + (a + 1) % 12, 19 + a], 1)])
    V = len(pos)
    mesh = gm.GarmentMesh(faces, pos[:, :2], faces.copy(), sp.identity(V, format="csr"), np.zeros(V, np.int64))
    mesh = gm.bridge_loops(mesh, np.arange(12), 12 + np.arange(7), pos, np.zeros(2))
    assert len(mesh.faces) == 24 + 12 + 7
    m = trimesh.Trimesh(pos, mesh.faces, process=False)
    assert m.is_winding_consistent
    loops = gm.boundary_loops(mesh.faces)
    assert sorted(len(l) for l in loops) == [7, 12]


def test_binding_survives_mesh_surgery_exactly():
    """bind(subdivided garment) == subdivision of bind(garment) on any body: the binding is linear."""
    outfit = gm.load_outfit(bg.SOURCES / "male_casualsuit02")
    mesh = gm.select_components(outfit, (0,), (886,))
    mesh = gm.subdivide(gm.orient_consistently(mesh))
    idx, w, off = gm.binding_arrays(mesh, outfit)
    assert idx.shape[1] <= 6 and np.allclose(w.sum(1), 1.0, atol=1e-6)
    src_idx, src_w, src_off = gm.binding_arrays(
        gm.GarmentMesh(np.zeros((0, 3), np.int64), np.zeros((0, 2)), np.zeros((0, 3), np.int64),
                       sp.identity(len(outfit.vertices), format="csr"), np.zeros(len(outfit.vertices), np.int64)),
        outfit,
    )
    rng = np.random.default_rng(1)
    body = BodyModel.load()
    H = body.hm08_vertices(body.shape(rng.uniform([0, 0.77, 0, 0, 0, 0], 1, size=(2, 6)).astype(np.float32)))
    refs = outfit.scale_refs.astype(np.float32)
    direct = bind_garment(H, idx, w, off, refs)
    via_source = np.stack([mesh.positions(x) for x in bind_garment(H, src_idx, src_w, src_off, refs).astype(np.float64)])
    np.testing.assert_allclose(direct, via_source, atol=2e-6)


def test_push_out_and_relax_on_a_sphere():
    """A patch dipping into a unit sphere is pushed out to the margin and stays smooth."""
    sphere = trimesh.creation.icosphere(subdivisions=4, radius=1.0)
    mesh, pos = grid_mesh(10)
    pts = (pos - [5.0, 5.0, 0.0]) * 0.05 + [0.0, 0.0, 1.0]
    pts = 0.98 * pts / np.linalg.norm(pts, axis=1, keepdims=True)  # a spherical cap 2 cm inside
    margin = 0.01
    out, moved = fit.push_out(pts, sphere.vertices, sphere.faces, margin)
    assert moved.all()
    np.testing.assert_allclose(np.linalg.norm(out, axis=1), 1.0 + margin, atol=2e-3)  # flat facets: ~mm
    template, report = fit.relax_template(pts, mesh.faces, sphere.vertices, sphere.faces, margin)
    assert report["inside_before"] == 1.0 and report["inside_after"] == 0.0
    assert report["min_clearance_m"] >= margin - 1e-9
    assert not fit.body_inside_mask(template, sphere.vertices, sphere.faces).any()


def test_skirt_weight_diffusion_blends_and_sums_to_one():
    mesh, pos = grid_mesh(8)
    w = np.zeros((mesh.n_vertices, 2))
    w[:, 0] = pos[:, 0] < 4  # a hard left/right split
    w[:, 1] = 1.0 - w[:, 0]
    heights = pos[:, 1] - 8.0  # y plays the height: 0 at the top row, -8 at the bottom
    out = fit.smooth_skirt_weights(w, mesh.faces, heights, np.ones(mesh.n_vertices, bool), 0.0, 2.0, 40)
    np.testing.assert_allclose(out.sum(1), 1.0)
    e = gm.unique_edges(mesh.faces)
    low = heights[e].max(1) <= -2.0
    assert np.abs(out[e[:, 0]] - out[e[:, 1]]).sum(1)[low].max() < 0.5 * np.abs(w[e[:, 0]] - w[e[:, 1]]).sum(1)[low].max()
    np.testing.assert_allclose(out[heights == 0], w[heights == 0])  # the top is untouched


def test_fold_into_parents():
    w = np.array([[0.2, 0.3, 0.5], [0.0, 0.0, 1.0]])
    parents = np.array([-1, 0, 1])
    out = fit.fold_into_parents(w, parents, np.array([1, 2]))
    np.testing.assert_allclose(out, [[1.0, 0.0, 0.0], [1.0, 0.0, 0.0]])


def test_build_is_deterministic_and_assets_are_current(tmp_path):
    """Building trousers twice gives identical bytes, equal to the committed asset."""
    body = BodyModel.load()
    nb = bg.neutral_body(body)
    spec = next(s for s in bg.GARMENTS if s.id == "trousers")
    bg.build_garment(spec, body, nb, tmp_path / "a")
    bg.build_garment(spec, body, nb, tmp_path / "b")
    for name in ("garment.npz", "garment.json", "template.glb"):
        assert (tmp_path / "a/trousers" / name).read_bytes() == (tmp_path / "b/trousers" / name).read_bytes()
    with np.load(tmp_path / "a/trousers/garment.npz") as fresh, np.load(ASSETS_DIR / "garments/trousers/garment.npz") as shipped:
        assert sorted(fresh.files) == sorted(shipped.files)
        for key in fresh.files:
            np.testing.assert_allclose(fresh[key], shipped[key], atol=1e-5, err_msg=key)
    assert HM08_VERTEX_COUNT == gm.HM08_VERTEX_COUNT
