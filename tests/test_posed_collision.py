"""The posed-space collision term of the canonical regressor (training/posed_collision.py)."""
import numpy as np
import pytest

torch = pytest.importorskip("torch")
trimesh = pytest.importorskip("trimesh")

from training.posed_collision import PosedFrames, collision_energy, pose_frames, posed_distance  # noqa: E402


class RigidBody:
    """A diffused body of one bone with no shape offsets: eq. 6.7 is the bone's transform."""

    bone_index = torch.as_tensor([0])

    def fields(self, X):
        return torch.ones(len(X), 1), torch.zeros(len(X)), torch.zeros_like(X)


def sphere_frames(T=3, radius=0.1):
    s = trimesh.creation.icosphere(subdivisions=4, radius=radius)
    shifts = np.array([[0.0, 0.0, 0.0], [0.05, 0.0, 0.0], [0.0, 0.1, 0.0]])[:T]
    verts = (np.asarray(s.vertices)[None] + shifts[:, None]).astype(np.float32)
    transforms = np.tile(np.eye(4, dtype=np.float32), (T, 1, 1, 1))
    transforms[:, 0, :3, 3] = shifts  # the bone carries the garment with the sphere
    return PosedFrames.build(verts, np.asarray(s.faces), transforms, RigidBody()), shifts


def test_signed_distance_is_the_depth_along_the_body_normal():
    frames, shifts = sphere_frames()
    rng = np.random.default_rng(0)
    u = rng.normal(size=(3, 200, 3))
    u /= np.linalg.norm(u, axis=-1, keepdims=True)
    depth = rng.uniform(-0.01, 0.01, (3, 200, 1))  # within 1 cm of the skin, both sides
    x = torch.as_tensor((shifts[:, None] + u * (0.1 + depth)).astype(np.float32))
    d = posed_distance(x, frames, np.arange(3)).numpy()
    np.testing.assert_allclose(d, depth[..., 0], atol=1.5e-3)  # a 4-times subdivided sphere's vertex spacing
    assert collision_energy(torch.as_tensor(d), 0.003) > 0
    assert float(collision_energy(torch.as_tensor(d + 0.02), 0.003)) == 0.0


def test_pose_frames_is_eq_6_7_per_frame():
    from training.projection import CanonicalBody

    frames, shifts = sphere_frames()
    X = torch.as_tensor(np.random.default_rng(1).normal(size=(3, 50, 3)).astype(np.float32))
    posed = pose_frames(frames.body, X, frames.transforms)
    np.testing.assert_allclose(posed.numpy(), (X + torch.as_tensor(shifts[:, None], dtype=torch.float32)).numpy(), atol=1e-6)
    one = CanonicalBody.pose(frames.body, X[1], frames.transforms[1])[0]
    np.testing.assert_allclose(posed[1].numpy(), one.numpy(), atol=1e-6)


def test_the_regressor_learns_to_keep_the_posed_garment_out_with_the_term():
    """Targets whose decoded garment sits 5 mm inside the sphere: eq. 6.18 alone reproduces them;
    with the posed term the regressor's latents keep the garment near or beyond the skin."""
    from training.canonical_regressor import RegressorConfig, train_regressor

    frames, _ = sphere_frames(T=1)
    rng = np.random.default_rng(2)
    u = rng.normal(size=(60, 3))
    u /= np.linalg.norm(u, axis=-1, keepdims=True)
    decoder = SphereDecoder(u)
    T = 12
    seqs = []
    for k in range(4):
        posed = PosedFrames.build(np.repeat(frames.vertices, T, 0), np.asarray(trimesh.creation.icosphere(subdivisions=4).faces),
                                  np.repeat(frames.transforms.numpy(), T, 0), RigidBody())
        seqs.append({"phenotypes": np.full(6, 0.5, np.float32), "gamma": rng.normal(size=(T, 4)).astype(np.float32),
                     "z": np.full((T, 1), 0.95, np.float32), "posed": posed})  # radius 0.095: 5 mm inside
    base = RegressorConfig(hidden=16, layers=1, steps=300, window=T, batch=2, posed_frames=3)
    results = {}
    for w in (0.0, 300.0):
        model, record = train_regressor(seqs, 1, RegressorConfig(**{**base.__dict__, "posed_weight": w}), decoder=decoder)
        with torch.no_grad():
            z, _ = model(torch.as_tensor(seqs[0]["phenotypes"][None]), torch.as_tensor(seqs[0]["gamma"][None]), model.initial_state(1))
        results[w] = float(z.mean())
    assert results[0.0] == pytest.approx(0.95, abs=0.02)
    assert results[300.0] > 0.98, results


class SphereDecoder(torch.nn.Module):
    """z (n, 1) -> (n, V, 3): fixed directions u (V, 3) at radius 0.1 z (m)."""

    def __init__(self, u):
        super().__init__()
        self.u = torch.nn.Parameter(torch.as_tensor(u, dtype=torch.float32))

    def forward(self, z):
        return 0.1 * z[:, :, None] * self.u[None]
