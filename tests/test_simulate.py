"""Physics reference (training.simulate): closed-form free fall, cloth on a sphere, convergence log."""
import numpy as np
import pytest
import torch
import trimesh

from training.physics import GRAVITY_M_S2, ClothGeometry, ClothMaterial
from training.simulate import (
    HessianAssembly,
    RestPoseContacts,
    SimulationLog,
    SolverSettings,
    minimize_energy,
    settle,
    simulate,
    simulate_sequence,
)

FPS = 30.0
RADIUS = 0.1  # sphere body, metres
TIGHT = SolverSettings(force_tolerance=1e-4)  # residual 0.01 % of a vertex's weight


def _cloth_grid(n=7, size=0.16, z=0.0):
    """A flat n x n square cloth centred over the origin at height z (metres)."""
    g = np.linspace(-size / 2, size / 2, n)
    u, v = np.meshgrid(g, g, indexing="ij")
    verts = np.stack([u.ravel(), v.ravel(), np.full(n * n, z)], -1)
    idx = np.arange(n * n).reshape(n, n)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel(), idx[:-1, 1:].ravel()
    faces = np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)])
    return verts, faces


def _sphere(subdivisions=3):
    s = trimesh.creation.icosphere(subdivisions=subdivisions, radius=RADIUS)
    return s.vertices.astype(np.float64), s.faces.astype(np.int64)


def _radii(x):
    return np.linalg.norm(x, axis=-1)


def test_minimize_energy_reaches_the_minimiser_of_a_quadratic():
    rng = np.random.default_rng(0)
    target = torch.as_tensor(rng.normal(size=(1, 10, 3)))
    w = torch.as_tensor(rng.uniform(0.5, 5.0, size=(1, 10, 1)))

    def energy(x):
        return (w * (x - target) ** 2).sum(dim=(1, 2))

    x, rep = minimize_energy(energy, torch.zeros(1, 10, 3, dtype=torch.float64), 1e-7)
    torch.testing.assert_close(x, target, atol=1e-6, rtol=0)
    assert rep["converged"] and rep["energy_end_j"] < rep["energy_start_j"] and rep["iterations"] > 0


def test_free_fall_follows_backward_euler_in_closed_form():
    """No collider, no deformation: x_n = x_0 + n dt v0 - g dt^2 n (n + 1) / 2 (backward Euler)."""
    verts, faces = _cloth_grid()
    cloth = ClothGeometry.from_mesh(verts, faces, ClothMaterial())
    v0 = np.tile([0.3, -0.1, 0.5], (len(verts), 1))  # m/s, carried by inertia
    T, substeps = 6, 2
    frames, sim_log = simulate(cloth, verts, None, None, FPS, substeps, TIGHT, v0=v0, num_frames=T)
    dt = 1.0 / (FPS * substeps)
    for t in range(T):
        n = t * substeps
        expected = verts + n * dt * v0 - np.array([0, 0, GRAVITY_M_S2]) * dt * dt * n * (n + 1) / 2
        np.testing.assert_allclose(frames[t], expected, atol=2e-6)
    assert len(sim_log.solves) == (T - 1) * substeps
    assert all(s.kind == "dynamic" for s in sim_log.solves)


def test_cloth_dropped_on_a_sphere_comes_to_rest_above_it():
    verts, faces = _cloth_grid(z=RADIUS + 0.01)
    body, body_faces = _sphere()
    cloth = ClothGeometry.from_mesh(verts, faces, ClothMaterial())
    T = 24
    frames, sim_log = simulate(cloth, verts, np.repeat(body[None], T, 0), body_faces, FPS, 1, SolverSettings())
    assert np.isfinite(frames).all()
    # No penetration beyond 1.5 mm. The penalty is soft (eq. 5.12, k = 250 J/m^3): a vertex
    # pressed with force f sits (f / 3k)^(1/2) inside the 2 mm margin; here ~9 vertices carry the
    # cloth's 0.05 N, 2.7 mm inside the margin, 0.7 mm into the sphere (the same on impact).
    assert _radii(frames).min() > RADIUS - 1.5e-3
    # it fell: the centre vertex lies on the sphere's top, the corners drape below it
    centre = len(verts) // 2
    assert frames[-1, centre, 2] == pytest.approx(RADIUS, abs=1.5e-3)
    assert frames[-1, 0, 2] < frames[-1, centre, 2] - 0.01
    # and comes to rest: the last frame moves < 1 mm
    assert np.abs(frames[-1] - frames[-2]).max() < 1e-3
    # convergence log: every solve logged, energy decreased by every L-BFGS solve
    dyn = [s for s in sim_log.solves if s.kind == "dynamic"]
    assert len(dyn) == T - 1
    for s in dyn:
        assert s.energy_end_j <= s.energy_start_j + 1e-12
        assert np.isfinite(s.grad_norm_end_n) and s.grad_norm_end_n <= s.grad_norm_start_n
        assert s.iterations >= 0 and s.evaluations >= s.iterations + 1 and s.seconds > 0
    assert np.mean([s.converged for s in dyn]) >= 0.9 and max(s.iterations for s in dyn) >= 3
    assert set(sim_log.frame_energies) == {"strain", "bending", "gravity", "collision", "inertia"}
    assert all(v.shape == (T,) for v in sim_log.frame_energies.values())
    arrays = sim_log.arrays()
    assert arrays["log_grad_norm_end_n"].shape == (T - 1,) and arrays["frame_seconds"].shape == (T,)
    assert sim_log.summary()["energy_decreased_fraction"] == 1.0


def test_rigidly_translated_body_carries_the_cloth_along():
    """A sphere rising 6 cm in 0.4 s (smooth start and stop) lifts the cloth resting on it."""
    verts, faces = _cloth_grid(z=RADIUS + 0.0015)
    body, body_faces = _sphere()
    cloth = ClothGeometry.from_mesh(verts, faces, ClothMaterial())
    T, height = 13, 0.06
    rise = height * (1 - np.cos(np.pi * np.arange(T) / (T - 1))) / 2  # peak 0.24 m/s, 0.19 g
    centres = rise[:, None, None] * np.array([0.0, 0.0, 1.0])
    frames, _ = simulate(cloth, verts, body[None] + centres, body_faces, FPS, 1, SolverSettings())
    centre = len(verts) // 2
    lift = frames[-1, centre, 2] - frames[0, centre, 2]
    assert lift == pytest.approx(height - 0.0022, abs=1e-3)  # carried up, less its settling into the margin
    assert _radii(frames - centres).min() > RADIUS - 1.5e-3  # never pushed through
    # the rim drapes below the centre throughout
    assert np.all(frames[1:, 0, 2] < frames[1:, centre, 2])


def test_settle_reaches_static_equilibrium_on_a_sphere():
    verts, faces = _cloth_grid(n=6, size=0.12, z=RADIUS + 0.004)
    body, body_faces = _sphere()
    cloth = ClothGeometry.from_mesh(verts, faces, ClothMaterial())
    x, logs = settle(cloth, verts, body, body_faces, SolverSettings(settle_dt_s=0.1, settle_steps=60))
    assert logs and logs[-1].kind == "settle" and logs[-1].converged
    assert logs[-1].max_force_n < logs[0].grad_norm_start_n
    assert _radii(x).min() > RADIUS - 1.5e-3
    assert x[:, 2].min() < verts[:, 2].min() - 0.005  # the borders sag over the sphere


class _TubeAsset:
    """A tiny skirt-like tube around the anny body's hips (duck-typed GarmentAsset)."""

    def __init__(self, body, shape, n_around=16, n_down=4):
        rest = shape.rest_vertices[0]
        hips = rest[np.abs(rest[:, 2] - 0.0) < 0.02]
        centre = hips.mean(0)
        r = np.abs(hips[:, :2] - centre[:2]).max() + 0.03
        ang = np.linspace(0, 2 * np.pi, n_around, endpoint=False)
        rings = [np.stack([centre[0] + r * np.cos(ang), centre[1] + r * np.sin(ang), np.full(n_around, centre[2] - 0.05 * k)], -1) for k in range(n_down)]
        self.rest_vertices = np.concatenate(rings).astype(np.float32)
        faces = []
        for k in range(n_down - 1):
            for i in range(n_around):
                a, b = k * n_around + i, k * n_around + (i + 1) % n_around
                faces += [[a, b, b + n_around], [a, b + n_around, a + n_around]]
        self.faces = np.array(faces)
        self.material = {"collision_margin_m": 0.003}
        # rigidly attached to the hips bone (index 0)
        self.skin_weights = np.zeros((len(self.rest_vertices), body.num_bones), np.float32)
        self.skin_weights[:, 0] = 1.0

    def retarget_fit(self, hm08_vertices):
        return self.rest_vertices[None]


def test_simulate_sequence_on_the_body_model_smoke():
    from inference.body import NEUTRAL_PHENOTYPES, BodyModel

    body = BodyModel.load()
    shape = body.shape(NEUTRAL_PHENOTYPES[None])
    asset = _TubeAsset(body, shape)
    T = 3
    rotations = np.zeros((T, body.num_bones, 3), np.float32)
    rotations[:, 0, 2] = np.linspace(0, 0.2, T)  # turning about the vertical
    translation = np.zeros((T, 3), np.float32)
    translation[:, 0] = np.linspace(0, 0.04, T)
    settings = SolverSettings(settle_steps=3, max_iterations=50)
    frames, sim_log = simulate_sequence(asset, body, NEUTRAL_PHENOTYPES, rotations, translation, FPS, substeps=1, settings=settings, lead_in_frames=2)
    assert frames.shape == (T, len(asset.rest_vertices), 3) and frames.dtype == np.float32
    assert np.isfinite(frames).all()
    kinds = [s.kind for s in sim_log.solves]
    assert kinds.count("dynamic") == T - 1 and kinds.count("lead_in") == 2 and "settle" in kinds
    assert [s.frame for s in sim_log.solves if s.kind != "settle"] == [-1, 0, 1, 2]
    assert isinstance(sim_log, SimulationLog) and sim_log.frame_energies["gravity"].shape == (T,)
    # the tube does not touch the body: it falls freely from rest at the start of the lead-in,
    # backward Euler z_n = z_0 - g dt^2 n (n + 1) / 2; clip frames 0 and 2 are steps n = 2 and 4
    dt = 1.0 / FPS
    drop = frames[0, :, 2].mean() - frames[-1, :, 2].mean()
    assert drop == pytest.approx(GRAVITY_M_S2 * dt * dt * (10 - 3), rel=0.02)  # solver tolerance 0.1 m g per step
    with pytest.raises(ValueError):
        simulate_sequence(asset, body, NEUTRAL_PHENOTYPES, rotations[:, :5], translation, FPS)


def test_hessian_assembly_matches_dense_sum_of_blocks():
    verts, faces = _cloth_grid(n=4)
    cloth = ClothGeometry.from_mesh(verts, faces, ClothMaterial())
    V = len(verts)
    rng = np.random.default_rng(1)
    tri = rng.normal(size=(len(faces), 9, 9))
    hinge = rng.normal(size=(len(cloth.hinges), 12, 12))
    vert = rng.normal(size=(V, 3, 3))
    dense = np.zeros((3 * V, 3 * V))
    for blocks, elements in ((tri, cloth.faces.numpy()), (hinge, cloth.hinges.numpy()), (vert, np.arange(V)[:, None])):
        for b, e in zip(blocks, elements):
            dofs = (3 * e[:, None] + np.arange(3)).ravel()
            dense[np.ix_(dofs, dofs)] += b
    np.testing.assert_allclose(HessianAssembly(cloth).matrix(tri, hinge, vert).toarray(), dense, atol=1e-12)


def test_rest_pose_contacts_keep_to_body_parts_that_move_alike():
    """Two body 'parts' side by side: the garment vertex over the seam only gets candidates on
    the part whose skinning weights match its own."""
    g = np.linspace(-0.05, 0.05, 11)
    u, v = np.meshgrid(g, g, indexing="ij")
    body = np.stack([u.ravel(), v.ravel(), np.zeros(u.size)], -1)
    body_w = np.zeros((len(body), 2))
    body_w[body[:, 0] < 0, 0] = 1.0  # left part: bone 0
    body_w[body[:, 0] >= 0, 1] = 1.0  # right part: bone 1
    garment = np.array([[0.0, 0.0, 0.01], [0.0, 0.02, 0.01]])
    garment_w = np.array([[1.0, 0.0], [0.5, 0.5]])
    rc = RestPoseContacts(garment, body, garment_w, body_w, k=6)
    assert (body[rc.candidates[0], 0] < 0).all()  # bone-0 vertex: left part only
    assert (body[rc.candidates[1], 0] < 0).any() and (body[rc.candidates[1], 0] >= 0).any()  # mixed: both
    plain = RestPoseContacts(garment, body, k=6)
    assert (body[plain.candidates[0], 0] >= 0).any()  # without weights: the nearest, both parts
