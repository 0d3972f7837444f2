"""Export benchmark: time and size of glb/npz for a 5k-vertex garment (+ a 13,718-vertex body).

Run: .venv/bin/python bench/bench_export.py
Synthetic data with the product's sizes: a 100 x 50 tube garment (5,000 vertices, one UV seam)
moving smoothly, and a 13,718-vertex tube body skinned to a 31-bone tree with 8 influences.
"""
from __future__ import annotations

import gzip
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from inference.export.glb import write_glb  # noqa: E402
from inference.export.npz import write_npz  # noqa: E402
from inference.export.tracks import BodyTrack, GarmentTrack  # noqa: E402
from inference.rotations import axis_angle_to_matrix  # noqa: E402


def tube(n_around: int, n_rows: int, radius: float, z0: float, height: float):
    """Open cylinder about Z with a UV seam: vertices (V, 3), faces, uvs, face_uvs."""
    a = np.arange(n_around) * 2 * np.pi / n_around
    z = np.linspace(z0, z0 + height, n_rows)
    v = np.stack([np.broadcast_to(radius * np.cos(a), (n_rows, n_around)),
                  np.broadcast_to(radius * np.sin(a), (n_rows, n_around)),
                  np.broadcast_to(z[:, None], (n_rows, n_around))], -1).reshape(-1, 3)
    uvs = np.stack(np.broadcast_arrays(np.arange(n_around + 1)[None] / n_around,
                                       np.linspace(0, 1, n_rows)[:, None]), -1).reshape(-1, 2)
    r, c = (x.ravel() for x in np.meshgrid(np.arange(n_rows - 1), np.arange(n_around), indexing="ij"))
    p = lambda rr, cc: rr * n_around + cc % n_around  # noqa: E731
    t = lambda rr, cc: rr * (n_around + 1) + cc  # noqa: E731
    faces = np.concatenate([np.stack([p(r, c), p(r, c + 1), p(r + 1, c + 1)], -1),
                            np.stack([p(r, c), p(r + 1, c + 1), p(r + 1, c)], -1)])
    face_uvs = np.concatenate([np.stack([t(r, c), t(r, c + 1), t(r + 1, c + 1)], -1),
                               np.stack([t(r, c), t(r + 1, c + 1), t(r + 1, c)], -1)])
    return v.astype(np.float32), faces, uvs.astype(np.float32), face_uvs


def garment(T: int) -> GarmentTrack:
    v, f, uv, fuv = tube(100, 50, 0.18, 0.9, 0.6)  # 5,000 vertices
    s = np.arange(T)[:, None, None] / 30.0
    R = axis_angle_to_matrix(np.stack([np.zeros(T), np.zeros(T), 0.6 * np.arange(T) / 30.0], -1))
    ripple = 1.0 + 0.04 * np.sin(10 * v[None, :, 2:3] + 4 * s + 3 * np.arctan2(v[None, :, 1:2], v[None, :, :1]))
    frames = np.einsum("tij,tvj->tvi", R, v[None] * np.concatenate([ripple, ripple, np.ones_like(ripple)], -1))
    frames[..., 0] += 1.3 * s[..., 0]
    return GarmentTrack("shirt", frames.astype(np.float32), f, uv, fuv, {"id": "shirt_01", "size": "M"})


def body(T: int, J: int = 31, K: int = 8) -> BodyTrack:
    rng = np.random.default_rng(0)
    v, f, uv, fuv = tube(361, 38, 0.2, 0.0, 1.7)  # 13,718 vertices
    parents = np.concatenate([[-1], rng.integers(0, np.arange(1, J))])  # a random tree, parents first
    heads = np.stack([0.1 * rng.normal(size=J), 0.1 * rng.normal(size=J), np.linspace(0.0, 1.6, J)], -1)
    rest = np.tile(np.eye(4), (J, 1, 1))
    rest[:, :3, :3] = axis_angle_to_matrix(rng.normal(scale=0.4, size=(J, 3)))
    rest[:, :3, 3] = heads
    local = np.tile(np.eye(4), (T, J, 1, 1))
    angles = 0.3 * np.sin(np.arange(T)[:, None, None] / 9.0) * rng.normal(size=(1, J, 3))
    local[..., :3, :3] = axis_angle_to_matrix(angles)
    world = np.zeros((T, J, 4, 4))
    for j in range(J):  # bench data only: tiny reference FK
        rel = rest[j] if parents[j] < 0 else np.linalg.inv(rest[parents[j]]) @ rest[j]
        world[:, j] = (rel @ local[:, j]) if parents[j] < 0 else world[:, parents[j]] @ rel @ local[:, j]
    d = np.linalg.norm(v[:, None] - heads[None], axis=-1)
    idx = np.argsort(d, axis=1)[:, :K]
    w = np.exp(-np.take_along_axis(d, idx, 1) / 0.1)
    w /= w.sum(1, keepdims=True)
    return BodyTrack(v, f, idx, w.astype(np.float32), parents, [f"bone{j}" for j in range(J)],
                     rest.astype(np.float32), world.astype(np.float32), uv, fuv)


def timed(fn, repeats: int = 3):
    best, out = float("inf"), None
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = fn()
        best = min(best, time.perf_counter() - t0)
    return best * 1e3, out


def main() -> None:
    print(f"{'case':46s} {'ms':>8s} {'bytes':>12s} {'gzip -6':>12s}")
    for T in (1, 300):
        g, b = garment(T), body(T)
        cases = [  # (name, writer, garments, body, options)
            ("glb garment", write_glb, [g], None, {}),
            ("glb garment quantize=False", write_glb, [g], None, {"quantize": False}),
            ("glb garment normals=False", write_glb, [g], None, {"normals": False}),
            ("glb garment compression=meshopt", write_glb, [g], None, {"compression": "meshopt"}),
            ("glb garment + body", write_glb, [g], b, {}),
            ("glb garment + body max_influences=4", write_glb, [g], b, {"max_influences": 4}),
            ("npz garment", write_npz, [g], None, {}),
            ("npz garment compress=True", write_npz, [g], None, {"compress": True}),
            ("npz garment + body", write_npz, [g], b, {}),
            ("npz garment + body compress=True", write_npz, [g], b, {"compress": True}),
        ]
        for name, writer, garments, body_track, options in cases:
            ms, data = timed(lambda: writer(garments, body_track, **options))  # noqa: B023 (called at once)
            print(f"{f'T={T:<3d} {name}':46s} {ms:8.1f} {len(data):12,d} {len(gzip.compress(data, 6)):12,d}")


if __name__ == "__main__":
    main()
