"""Cloth energies (training.physics): hand-computed cases, rest, rigid invariance, batch, gradients, Hessians."""
import math

import numpy as np
import pytest
import torch

from training.candidates import body_candidates
from training.physics import (
    GRAVITY_M_S2,
    ClothGeometry,
    ClothMaterial,
    bending_energy,
    bending_hessian,
    body_signed_distances,
    collision_energy,
    collision_hessian,
    dihedral_angles,
    energy_terms,
    gravity_energy,
    inertia_energy,
    interior_hinges,
    static_energy,
    strain_energy,
    strain_hessian,
    total_energy,
)

MAT = ClothMaterial()  # SNUG values (thesis ch. 5.3.1), margin 2 mm
F64 = torch.float64


def _t(a, dtype=F64):
    return torch.as_tensor(np.asarray(a), dtype=dtype)


def _square():
    """Unit square in z = 0 split along the diagonal 0-2: two right triangles, one hinge."""
    verts = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], np.float64)
    faces = np.array([[0, 1, 2], [0, 2, 3]])
    return verts, faces


def _grid(n=5, size=0.1, seed=0, curved=True):
    """An n x n vertex grid, triangulated, optionally bent (a curved rest shape)."""
    u, v = np.meshgrid(np.linspace(0, size, n), np.linspace(0, size, n), indexing="ij")
    z = 0.3 * (u - size / 2) ** 2 / size if curved else 0 * u
    verts = np.stack([u, v, z], -1).reshape(-1, 3)
    idx = np.arange(n * n).reshape(n, n)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel(), idx[:-1, 1:].ravel()
    faces = np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)])
    return verts, faces


def _random_rigid(seed):
    rng = np.random.default_rng(seed)
    q, r = np.linalg.qr(rng.normal(size=(3, 3)))
    q = q * np.sign(np.diag(r))
    if np.linalg.det(q) < 0:
        q[:, 0] *= -1
    return q, rng.normal(size=3)


# --------------------------------------------------------------------------- precompute
def test_geometry_precompute_masses_hinges_kscale():
    verts, faces = _square()
    cloth = ClothGeometry.from_mesh(verts, faces, MAT)
    # lumped masses: each triangle (area 1/2) gives rho h / 6 to each corner
    per = MAT.density_kg_m3 * MAT.thickness_m * 0.5 / 3
    np.testing.assert_allclose(cloth.vertex_mass_kg.numpy(), [2 * per, per, 2 * per, per])
    assert cloth.total_mass_kg == pytest.approx(MAT.density_kg_m3 * MAT.thickness_m * 1.0)
    np.testing.assert_allclose(cloth.rest_area_m2.numpy(), [0.5, 0.5])
    assert cloth.hinges.tolist() == [[0, 2, 1, 3]]
    np.testing.assert_allclose(cloth.k_scale.numpy(), [2.0 / (4 * 1.0)])  # l^2 / (4 (a1 + a2))
    np.testing.assert_allclose(cloth.rest_dihedral_rad.numpy(), [0.0], atol=1e-15)


def test_interior_hinges_of_a_grid():
    _, faces = _grid(4)
    hinges, hinge_faces = interior_hinges(faces)
    # 3x3 quads: 9 diagonals + 2 * 3 * 2 interior grid lines = 21 interior edges
    assert len(hinges) == 21
    for (i, j, k, l), (f1, f2) in zip(hinges, hinge_faces):
        assert {i, j, k} == set(faces[f1]) and {i, j, l} == set(faces[f2])


def test_material_from_asset_dict_and_bad_values():
    m = ClothMaterial.from_dict({"density_kg_m3": 426.0, "collision_margin_m": 0.003})
    assert m.collision_margin_m == 0.003 and m.lame_mu_pa == 2.36e4
    with pytest.raises(ValueError, match="unknown keys"):
        ClothMaterial.from_dict({"stiffness": 1.0})
    with pytest.raises(ValueError):
        ClothMaterial(thickness_m=-1.0)


def test_degenerate_rest_triangle_rejected():
    verts = np.array([[0, 0, 0], [1, 0, 0], [2, 0, 0]], np.float64)
    with pytest.raises(ValueError, match="degenerate"):
        ClothGeometry.from_mesh(verts, np.array([[0, 1, 2]]), MAT)


# --------------------------------------------------------------------------- strain
def test_zero_at_rest_strain_bending():
    verts, faces = _grid(curved=True)
    cloth = ClothGeometry.from_mesh(verts, faces, MAT)
    x = _t(verts[None])
    assert strain_energy(cloth, x).item() == pytest.approx(0.0, abs=1e-20)
    assert bending_energy(cloth, x).item() == pytest.approx(0.0, abs=1e-20)
    assert cloth.rest_dihedral_rad.abs().max() > 0.01  # the rest shape is really curved


def test_strain_uniaxial_stretch_of_a_right_triangle_hand_computed():
    verts = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]], np.float64)
    cloth = ClothGeometry.from_mesh(verts, [[0, 1, 2]], MAT)
    s = 1.1
    x = _t((verts * [s, 1, 1])[None])
    # F = diag(s, 1): G = diag((s^2 - 1)/2, 0); tr G = (s^2-1)/2, tr G^2 = (s^2-1)^2/4
    # Psi = lambda/2 * 0.21^2/4 + mu * 0.21^2/4 = (22200 + 23600) * 0.011025 = 504.945 J/m^3
    # E = area 0.5 m^2 * thickness 0.47e-3 m * Psi = 0.118662... J
    assert strain_energy(cloth, x).item() == pytest.approx(0.5 * 0.47e-3 * 504.945, rel=1e-12)


def test_strain_shear_hand_computed():
    verts = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]], np.float64)
    cloth = ClothGeometry.from_mesh(verts, [[0, 1, 2]], MAT)
    gamma = 0.2  # simple shear x += gamma y: F = [[1, gamma], [0, 1]]
    x = _t(np.array([[0, 0, 0], [1, 0, 0], [gamma, 1, 0]])[None])
    # F^T F = [[1, g], [g, 1 + g^2]]: G = [[0, g/2], [g/2, g^2/2]]
    tr_g, tr_g2 = gamma**2 / 2, 2 * (gamma / 2) ** 2 + (gamma**2 / 2) ** 2
    psi = MAT.lame_lambda_pa / 2 * tr_g**2 + MAT.lame_mu_pa * tr_g2
    assert strain_energy(cloth, x).item() == pytest.approx(0.5 * MAT.thickness_m * psi, rel=1e-12)


def test_strain_does_not_depend_on_the_rest_triangle_orientation():
    """Flattening each rest triangle into its own plane: the same triangle tilted in 3D."""
    verts = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]], np.float64)
    R, t = _random_rigid(3)
    a = ClothGeometry.from_mesh(verts, [[0, 1, 2]], MAT)
    b = ClothGeometry.from_mesh(verts @ R.T + t, [[0, 1, 2]], MAT)
    x = np.array([[0, 0, 0], [1.2, 0.1, 0.0], [0.1, 0.9, 0.2]])
    ea = strain_energy(a, _t(x[None])).item()
    eb = strain_energy(b, _t((x @ R.T)[None])).item()
    assert ea > 0 and eb == pytest.approx(ea, rel=1e-10)


# --------------------------------------------------------------------------- bending
@pytest.mark.parametrize("fold_deg", [10.0, 60.0, 135.0])
def test_bending_known_fold_angle_hand_computed(fold_deg):
    verts, faces = _square()
    cloth = ClothGeometry.from_mesh(verts, faces, MAT)
    phi = math.radians(fold_deg)
    # rotate vertex 3 about the hinge 0-2 (the diagonal) by phi
    axis = np.array([1.0, 1.0, 0.0]) / math.sqrt(2)
    p = verts[3]
    p_rot = p * math.cos(phi) + np.cross(axis, p) * math.sin(phi) + axis * (axis @ p) * (1 - math.cos(phi))
    x = verts.copy()
    x[3] = p_rot
    theta = dihedral_angles(_t(x[None]), cloth.hinges)[0, 0].item()
    assert abs(theta) == pytest.approx(phi, rel=1e-12)
    # E = k_bend * k_scale * phi^2 / 2, k_scale = l^2 / (4 (a1 + a2)) = 2 / 4
    assert bending_energy(cloth, _t(x[None])).item() == pytest.approx(MAT.k_bend * 0.5 * phi**2 / 2, rel=1e-12)


def test_bending_sign_distinguishes_fold_directions_and_rest_is_relative():
    verts, faces = _square()
    up, down = verts.copy(), verts.copy()
    up[3, 2], down[3, 2] = 0.3, -0.3
    th_up = dihedral_angles(_t(up[None]), _t(interior_hinges(faces)[0], torch.int64))[0, 0]
    th_down = dihedral_angles(_t(down[None]), _t(interior_hinges(faces)[0], torch.int64))[0, 0]
    assert th_up.item() == pytest.approx(-th_down.item()) and abs(th_up.item()) > 0.1
    cloth_folded = ClothGeometry.from_mesh(up, faces, MAT)  # rest = folded up
    assert bending_energy(cloth_folded, _t(up[None])).item() == pytest.approx(0.0, abs=1e-20)
    flat = bending_energy(cloth_folded, _t(verts[None])).item()
    down_e = bending_energy(cloth_folded, _t(down[None])).item()
    assert down_e == pytest.approx(4 * flat, rel=1e-9)  # (2 theta)^2 vs theta^2


def test_bending_degenerate_configurations_are_finite():
    verts, faces = _square()
    cloth = ClothGeometry.from_mesh(verts, faces, MAT)
    for x in (
        np.zeros((4, 3)),  # everything collapsed onto one point
        np.array([[0, 0, 0], [0.5, 0.5, 0], [1, 1, 0], [0, 1, 0]], np.float64),  # one triangle collinear
        np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [1, 0, 0]], np.float64),  # folded fully onto itself
    ):
        xt = _t(x[None]).requires_grad_(True)
        e = bending_energy(cloth, xt) + strain_energy(cloth, xt)
        (g,) = torch.autograd.grad(e.sum(), xt)
        assert torch.isfinite(e).all() and torch.isfinite(g).all()


# --------------------------------------------------------------------------- invariance, batch
def test_rigid_motion_invariance_strain_bending():
    verts, faces = _grid(curved=True)
    cloth = ClothGeometry.from_mesh(verts, faces, MAT)
    rng = np.random.default_rng(1)
    x = verts + 0.004 * rng.normal(size=verts.shape)  # a deformed state
    e0 = (strain_energy(cloth, _t(x[None])).item(), bending_energy(cloth, _t(x[None])).item())
    assert min(e0) > 0
    for seed in range(3):
        R, t = _random_rigid(seed)
        xr = _t((x @ R.T + t)[None])
        assert strain_energy(cloth, xr).item() == pytest.approx(e0[0], rel=1e-9)
        assert bending_energy(cloth, xr).item() == pytest.approx(e0[1], rel=1e-9)


def test_batch_consistency_and_float32():
    verts, faces = _grid(curved=True)
    cloth64 = ClothGeometry.from_mesh(verts, faces, MAT)
    cloth32 = ClothGeometry.from_mesh(verts, faces, MAT, dtype=torch.float32)
    rng = np.random.default_rng(2)
    xs = verts[None] + 0.003 * rng.normal(size=(4,) + verts.shape)
    body = np.stack([np.array([[0.05, 0.05, -0.001 * b]]) for b in range(4)])
    normals = np.tile([0.0, 0.0, 1.0], (4, 1, 1))
    batched = energy_terms(cloth64, _t(xs), _t(body), _t(normals))
    for b in range(4):
        one = energy_terms(cloth64, _t(xs[b : b + 1]), _t(body[b : b + 1]), _t(normals[b : b + 1]))
        for k in batched:
            assert batched[k][b].item() == pytest.approx(one[k][0].item(), rel=1e-12, abs=1e-300)
    e32 = energy_terms(cloth32, _t(xs, torch.float32), _t(body, torch.float32), _t(normals, torch.float32))
    for k in batched:
        assert e32[k].dtype == torch.float32
        np.testing.assert_allclose(e32[k].numpy(), batched[k].numpy(), rtol=2e-3, atol=1e-9)
    with pytest.raises(ValueError, match="dtype"):
        strain_energy(cloth64, _t(xs, torch.float32))
    with pytest.raises(ValueError, match="shape"):
        strain_energy(cloth64, _t(xs[:, :-1]))


# --------------------------------------------------------------------------- gravity, collision, inertia
def test_gravity_hand_case():
    verts, faces = _square()
    cloth = ClothGeometry.from_mesh(verts, faces, MAT)
    m = cloth.vertex_mass_kg.numpy()
    x = verts + [0.3, -0.2, 2.0]  # lifted by 2 m (x, y do not matter)
    assert gravity_energy(cloth, _t(x[None])).item() == pytest.approx(m.sum() * GRAVITY_M_S2 * 2.0, rel=1e-12)
    x[0, 2] -= 1.0
    assert gravity_energy(cloth, _t(x[None])).item() == pytest.approx(m.sum() * GRAVITY_M_S2 * 2.0 - m[0] * GRAVITY_M_S2, rel=1e-12)


def _plane_body(n=5, spacing=0.05):
    g = (np.arange(n) - n // 2) * spacing
    u, v = np.meshgrid(g, g, indexing="ij")
    pts = np.stack([u.ravel(), v.ravel(), np.zeros(n * n)], -1)
    return pts[None], np.tile([0.0, 0.0, 1.0], (1, n * n, 1))


def test_collision_zero_beyond_margin_and_cube_at_depth():
    verts = np.array([[0, 0, 0], [0.01, 0, 0], [0, 0.01, 0]], np.float64)
    cloth = ClothGeometry.from_mesh(verts, [[0, 1, 2]], MAT)
    pts, nrm = _plane_body()
    eps = MAT.collision_margin_m
    # above the margin everywhere: zero
    x = verts + [0.0, 0.0, eps + 1e-4]
    assert collision_energy(cloth, _t(x[None]), _t(pts), _t(nrm)).item() == 0.0
    # one vertex 1 cm deep, two outside the margin: k (eps + 0.01)^3 = 250 * 0.012^3 = 4.32e-4 J
    x = verts + [0.0, 0.0, 0.05]
    x[1, 2] = -0.01
    e = collision_energy(cloth, _t(x[None]), _t(pts), _t(nrm)).item()
    assert e == pytest.approx(MAT.k_collision * (eps + 0.01) ** 3, rel=1e-12)
    assert e == pytest.approx(4.32e-4, rel=1e-12)
    # inside the margin but outside the body: still penalised, (eps - d)^3
    x[1, 2] = 0.001
    assert collision_energy(cloth, _t(x[None]), _t(pts), _t(nrm)).item() == pytest.approx(MAT.k_collision * 0.001**3, rel=1e-9)


def test_training_margin_and_stiffness_override():
    verts = np.array([[0, 0, 0], [0.01, 0, 0], [0, 0.01, 0]], np.float64)
    cloth = ClothGeometry.from_mesh(verts, [[0, 1, 2]], MAT)
    pts, nrm = _plane_body()
    x = _t((verts + [0.0, 0.0, 0.003])[None])  # 3 mm above the plane: outside the 2 mm margin
    assert collision_energy(cloth, x, _t(pts), _t(nrm)).item() == 0.0
    wide = cloth.with_collision_stiffness(1e5, margin_m=0.005)
    assert wide.material.collision_margin_m == 0.005 and cloth.material.collision_margin_m == MAT.collision_margin_m
    # three vertices 2 mm inside the 5 mm margin: 3 k (0.002)^3
    assert collision_energy(wide, x, _t(pts), _t(nrm)).item() == pytest.approx(3 * 1e5 * 0.002**3, rel=1e-9)
    assert cloth.with_collision_stiffness(None) is cloth


def test_exact_inside_mask_overrides_the_tangent_plane():
    """A vertex the exact test finds inside (e.g. pushed into an arm while its closest skin is the
    torso beside it) is penalised by its distance to the closest skin vertex, pulled toward it;
    vertices the mask leaves outside keep the tangent-plane penalty; no mask = eq. 5.12 as before."""
    verts = np.array([[0, 0, 0], [0.01, 0, 0], [0, 0.01, 0]], np.float64)
    cloth = ClothGeometry.from_mesh(verts, [[0, 1, 2]], MAT)
    pts, nrm = _plane_body()  # closest skin vertex of every point below: the origin
    x = verts * 0.1 + [0.0, 0.0, 0.05]  # 5 cm above the plane: no tangent-plane penalty
    x[0] = [0.003, 0.0, 0.004]  # 4 mm above the plane, 5 mm from the skin vertex at the origin
    inside = torch.tensor([[True, False, False]])
    xt = _t(x[None]).requires_grad_(True)
    assert collision_energy(cloth, xt, _t(pts), _t(nrm)).item() == 0.0
    e = collision_energy(cloth, xt, _t(pts), _t(nrm), inside=inside)
    assert e.item() == pytest.approx(MAT.k_collision * (MAT.collision_margin_m + 0.005) ** 3, rel=1e-9)
    e.backward()
    g = xt.grad[0, 0].numpy()
    # descent (-g) points from x toward the skin vertex at the origin
    np.testing.assert_allclose(-g / np.linalg.norm(g), -x[0] / np.linalg.norm(x[0]), atol=1e-9)
    assert np.all(xt.grad[0, 1:].numpy() == 0.0)
    # a deeper tangent-plane penalty is kept (min of the two distances)
    y = x.copy()
    y[0] = [0.0, 0.0, -0.01]
    assert collision_energy(cloth, _t(y[None]), _t(pts), _t(nrm), inside=inside).item() == pytest.approx(MAT.k_collision * (MAT.collision_margin_m + 0.01) ** 3, rel=1e-9)
    with pytest.raises(ValueError, match="inside"):
        collision_energy(cloth, xt, _t(pts), _t(nrm), inside=inside[:, :2])


def test_geometry_to_device_keeps_values():
    verts, faces = _grid()
    cloth = ClothGeometry.from_mesh(verts, faces, MAT, torch.float32)
    moved = cloth.to("cpu")
    for name in ("faces", "dm_inv", "rest_area_m2", "vertex_mass_kg", "hinges", "k_scale", "rest_dihedral_rad"):
        assert torch.equal(getattr(moved, name), getattr(cloth, name))
    assert moved.material == cloth.material


def test_signed_distance_candidates_match_full_search():
    rng = np.random.default_rng(4)
    body = rng.normal(size=(2, 300, 3))
    normals = rng.normal(size=(2, 300, 3))
    normals /= np.linalg.norm(normals, axis=-1, keepdims=True)
    x = rng.normal(size=(2, 50, 3))
    cand = torch.as_tensor(body_candidates(x, body, k=4))
    full = body_signed_distances(_t(x), _t(body), _t(normals))
    knn = body_signed_distances(_t(x), _t(body), _t(normals), cand)
    np.testing.assert_allclose(knn.numpy(), full.numpy(), rtol=1e-12)
    # (V, k) candidates shared by the batch give the same as (B, V, k) when they are the same
    shared = body_signed_distances(_t(x[:1]), _t(body[:1]), _t(normals[:1]), cand[0])
    np.testing.assert_allclose(shared.numpy(), knn[:1].numpy())


def test_inertia_hand_case():
    verts = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]], np.float64)
    cloth = ClothGeometry.from_mesh(verts, [[0, 1, 2]], MAT)
    m = cloth.vertex_mass_kg.numpy()
    dt = 1.0 / 30.0
    x_prev2, x_prev = verts, verts + [0.1, 0.0, 0.0]  # moving 0.1 m per step along x
    # x_hat = x_prev + dt v = verts + 0.2 x; x = verts + 0.25 x: |x - x_hat| = 0.05 m for all
    x = verts + [0.25, 0.0, 0.0]
    e = inertia_energy(cloth, _t(x[None]), _t(x_prev[None]), _t(x_prev2[None]), dt).item()
    assert e == pytest.approx(m.sum() * 0.05**2 / (2 * dt**2), rel=1e-12)
    # following the constant velocity costs nothing
    assert inertia_energy(cloth, _t((verts + [0.2, 0, 0])[None]), _t(x_prev[None]), _t(x_prev2[None]), dt).item() == pytest.approx(0.0, abs=1e-20)
    with pytest.raises(ValueError, match="dt_s"):
        inertia_energy(cloth, _t(x[None]), _t(x_prev[None]), _t(x_prev2[None]), 0.0)


def test_static_and_total_are_sums_of_terms():
    verts, faces = _grid(curved=True)
    cloth = ClothGeometry.from_mesh(verts, faces, MAT)
    rng = np.random.default_rng(5)
    x, xp, xpp = (_t((verts + 0.002 * rng.normal(size=verts.shape))[None]) for _ in range(3))
    pts, nrm = _t(_plane_body()[0] + [0.05, 0.05, 0.005]), _t(_plane_body()[1])
    terms = energy_terms(cloth, x, pts, nrm, x_prev=xp, x_prev2=xpp, dt_s=0.01)
    assert terms["collision"].item() > 0
    static = terms["strain"] + terms["bending"] + terms["gravity"] + terms["collision"]
    assert static_energy(cloth, x, pts, nrm).item() == pytest.approx(static.item(), rel=1e-12)
    assert total_energy(cloth, x, xp, xpp, 0.01, pts, nrm).item() == pytest.approx((static + terms["inertia"]).item(), rel=1e-12)


# --------------------------------------------------------------------------- gradients
def test_gradients_match_finite_differences():
    verts, faces = _grid(n=3, size=0.05, curved=True)
    cloth = ClothGeometry.from_mesh(verts, faces, MAT)
    rng = np.random.default_rng(6)
    x = _t((verts + 0.003 * rng.normal(size=verts.shape))[None]).requires_grad_(True)
    xp = _t((verts + 0.002 * rng.normal(size=verts.shape))[None])
    xpp = _t((verts + 0.002 * rng.normal(size=verts.shape))[None])
    pts, nrm = _plane_body(n=7, spacing=0.01)
    pts = _t(pts + [0.025, 0.025, 0.001])  # close under the cloth: some vertices in the margin
    nrm = _t(nrm)
    assert collision_energy(cloth, x, pts, nrm).item() > 0
    checks = {
        "strain": lambda y: strain_energy(cloth, y),
        "bending": lambda y: bending_energy(cloth, y),
        "gravity": lambda y: gravity_energy(cloth, y),
        "collision": lambda y: collision_energy(cloth, y, pts, nrm),
        "collision_smoothed": lambda y: collision_energy(cloth, y, pts, nrm, smoothing_m=0.004),
        "inertia": lambda y: inertia_energy(cloth, y, xp, xpp, 1.0 / 30.0),
    }
    for name, fn in checks.items():
        # scaled so that the largest gradient entry is 1: atol is relative to the term's forces
        (g,) = torch.autograd.grad(fn(x).sum(), x)
        scale = g.abs().max().item()
        assert scale > 0, name
        assert torch.autograd.gradcheck(lambda y: fn(y) / scale, (x,), eps=1e-7, atol=1e-6, rtol=1e-5), name


def test_collision_active_mask_and_smoothing():
    verts = np.array([[0, 0, 0], [0.01, 0, 0], [0, 0.01, 0]], np.float64)
    cloth = ClothGeometry.from_mesh(verts, [[0, 1, 2]], MAT)
    pts, nrm = _plane_body()
    x = _t((verts + [0.0, 0.0, -0.005])[None])  # all three 5 mm deep
    full = collision_energy(cloth, x, _t(pts), _t(nrm)).item()
    assert full == pytest.approx(3 * MAT.k_collision * 0.007**3, rel=1e-12)
    active = torch.tensor([[True, False, True]])
    assert collision_energy(cloth, x, _t(pts), _t(nrm), active=active).item() == pytest.approx(full * 2 / 3, rel=1e-12)
    # blending coplanar tangent planes changes nothing; a tiny smoothing is the closest-vertex d
    assert collision_energy(cloth, x, _t(pts), _t(nrm), smoothing_m=0.01).item() == pytest.approx(full, rel=1e-12)
    rng = np.random.default_rng(7)
    body = rng.normal(size=(1, 200, 3))
    normals = body / np.linalg.norm(body, axis=-1, keepdims=True)
    pts3 = _t(rng.normal(size=(1, 30, 3)))
    sharp = body_signed_distances(pts3, _t(body), _t(normals))
    soft = body_signed_distances(pts3, _t(body), _t(normals), smoothing_m=1e-3)
    np.testing.assert_allclose(soft.numpy(), sharp.numpy(), atol=1e-9)


def _dense(blocks, elements, V):
    H = torch.zeros(3 * V, 3 * V, dtype=F64)
    dofs = (3 * elements[:, :, None] + torch.arange(3)).reshape(len(elements), -1)
    for e in range(len(elements)):
        H[dofs[e][:, None], dofs[e][None, :]] += blocks[e]
    return H


def test_hessians_match_autograd_where_exact_and_are_psd():
    from torch.autograd.functional import hessian

    verts, faces = _grid(n=4, size=0.05, curved=True)
    cloth = ClothGeometry.from_mesh(verts, faces, MAT)
    V = len(verts)

    def exact(fn, x):
        return hessian(lambda y: fn(y.reshape(1, V, 3)).sum(), x.reshape(-1))

    rng = np.random.default_rng(8)
    x = _t((verts + 0.003 * rng.normal(size=verts.shape))[None])  # mixed tension / compression
    H = exact(lambda y: strain_energy(cloth, y), x)
    torch.testing.assert_close(_dense(strain_hessian(cloth, x, project=False)[0], cloth.faces, V), H, rtol=1e-9, atol=1e-9 * H.abs().max().item())
    assert torch.linalg.eigvalsh(H).min() < 0  # compression: indefinite
    Hp = _dense(strain_hessian(cloth, x)[0], cloth.faces, V)
    assert torch.linalg.eigvalsh(Hp).min() > -1e-9 * Hp.abs().max()  # the projection is PSD
    stretched = _t((verts * [1.05, 1.02, 1.0])[None])  # pure tension: the projection is exact
    torch.testing.assert_close(_dense(strain_hessian(cloth, stretched)[0], cloth.faces, V), exact(lambda y: strain_energy(cloth, y), stretched))
    rest = _t(verts[None])  # bending Gauss-Newton is exact at the rest angle
    torch.testing.assert_close(_dense(bending_hessian(cloth, rest)[0], cloth.hinges, V), exact(lambda y: bending_energy(cloth, y), rest))
    pts, nrm = _plane_body(n=7, spacing=0.01)
    pts, nrm = _t(pts + [0.025, 0.025, 0.001]), _t(nrm)
    Hc = torch.block_diag(*collision_hessian(cloth, x, pts, nrm)[0])
    torch.testing.assert_close(Hc, exact(lambda y: collision_energy(cloth, y, pts, nrm), x))
    assert Hc.abs().max() > 0
