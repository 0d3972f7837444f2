"""Realism metrics (inference.metrics, DESIGN.md §5): hand-computed cases, and that a crumpled
surface, a spike and a pop fail what a smooth moving sheet passes."""
import numpy as np
import pytest

from inference.metrics import edge_length_ratios, folded_face_share, hinge_angles, interior_hinges, realism, vertex_jumps


def _grid(n: int = 6, size_m: float = 0.5):
    """A flat n x n vertex sheet in the XY plane: vertices (n*n, 3), faces, edges."""
    u = np.linspace(0.0, size_m, n)
    x, y = np.meshgrid(u, u, indexing="ij")
    verts = np.stack([x.ravel(), y.ravel(), np.zeros(n * n)], 1).astype(np.float32)
    idx = np.arange(n * n).reshape(n, n)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel(), idx[:-1, 1:].ravel()
    faces = np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)]).astype(np.int64)
    edges = np.unique(np.sort(faces[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1), axis=0)
    return verts, faces, edges


def test_edge_ratios_of_a_scaled_mesh():
    verts, faces, edges = _grid()
    r = edge_length_ratios(np.stack([verts, 2.0 * verts]), verts, edges)
    np.testing.assert_allclose(r[0], 1.0, rtol=1e-6)
    np.testing.assert_allclose(r[1], 2.0, rtol=1e-6)


def test_hinge_angle_and_fold_of_two_triangles():
    # two triangles sharing the edge (0, 1); vertex 3 swings about it
    base = np.array([[0, 0, 0], [1, 0, 0], [0.5, 1, 0]], np.float32)
    faces = np.array([[0, 1, 2], [1, 0, 3]])
    flat = np.vstack([base, [[0.5, -1, 0]]])
    right = np.vstack([base, [[0.5, 0, 1]]])  # 90 degrees
    over = np.vstack([base, [[0.5, 1, 0.01]]])  # folded back onto the first face
    hinges = interior_hinges(faces)
    assert hinges.shape == (1, 2)
    ang = hinge_angles(np.stack([flat, right, over]), faces, hinges)[:, 0]
    np.testing.assert_allclose(ang[:2], [0.0, np.pi / 2], atol=1e-5)
    assert ang[2] > 0.9 * np.pi
    np.testing.assert_allclose(folded_face_share(ang[:, None], hinges, 2), [0.0, 0.0, 1.0])


def test_vertex_jumps_hand_computed():
    frames = np.zeros((3, 4, 3), np.float32)
    frames[1, 2] = [0.03, 0.04, 0.0]  # 5 cm
    frames[2, 2] = [0.03, 0.04, 0.0]
    np.testing.assert_allclose(vertex_jumps(frames), [0.05, 0.0], atol=1e-7)
    with pytest.raises(ValueError):
        vertex_jumps(frames[0])


def test_crumple_spike_and_pop_fail_what_a_smooth_motion_passes():
    verts, faces, edges = _grid(12)
    t = np.linspace(0, 1, 8, dtype=np.float32)
    smooth = verts[None] + (0.02 * t)[:, None, None] * np.array([0, 0, 1], np.float32)  # the sheet rises 2 cm
    good = realism(smooth, faces, verts, edges)
    assert good["folded_pct"] == 0.0 and good["edge_p1"] == pytest.approx(1.0, abs=1e-5) and good["edge_max"] == pytest.approx(1.0, abs=1e-5)
    assert good["jump_max_m"] == pytest.approx(0.02 / 7, rel=1e-4)

    rng = np.random.default_rng(0)
    crumpled = smooth.copy()
    crumpled[:, :, 2] += rng.normal(0.0, 0.03, crumpled.shape[1])  # 3 cm noise on 4.5 cm edges: knots
    crumpled[:, :, :2] *= 0.5  # squashed to half its size: compressed
    bad = realism(crumpled, faces, verts, edges)
    assert bad["folded_pct"] > 10.0 and bad["edge_p1"] < 0.6 and bad["roughness_deg"] > 10 * max(good["roughness_deg"], 1.0)

    spiky = smooth.copy()
    spiky[4:, 40, 2] += 0.2  # one vertex shoots 20 cm out from frame 4 on
    spike = realism(spiky, faces, verts, edges)
    assert spike["edge_max"] > 3.0 and spike["jump_max_m"] > 0.19
