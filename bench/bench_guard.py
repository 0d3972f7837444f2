"""Benchmark: collision guard and inside test on the anny body (script, not a test).

    .venv/bin/python bench/bench_guard.py [--points 5000] [--frames 32] [--repeats 20]

Garment-like points: area-uniform samples on the skin of the torso, hips and upper arms
(a T-shirt and trousers region), offset along the normal by U(-3 mm, +15 mm), skinned with the
body's weights interpolated at the sample; poses: rest + Gaussian bone rotations (0.2 rad).
Reports ms per frame (best of ``repeats`` and median) for:
- guard, B=1 T=1 and B=1 T=frames (one call for all frames), plan built once outside the timing
- exact_repair after the guard (winding grid, inside test, moves), B=1 T=1 and T=frames
- inside_mask (exact winding numbers) for the same points, T=1 and T=8
- collision_rates (inside + distance + self-intersection), T=8
and the machine (CPU count) they ran on.
"""
from __future__ import annotations

import argparse
import os
import platform
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from inference.body import NEUTRAL_PHENOTYPES, BodyModel, linear_blend_skinning  # noqa: E402
from inference.guard import GuardPlan, guard  # noqa: E402
from inference.mesh import vertex_normals  # noqa: E402
from inference.metrics import collision_rates, inside_mask  # noqa: E402
from inference.repair import exact_repair  # noqa: E402

GARMENT_BONES = ("Hips", "LowerBack", "Spine", "Spine1", "LeftShoulder", "RightShoulder", "LeftArm", "RightArm", "LeftUpLeg", "RightUpLeg")


def garment_like(body: BodyModel, rest: np.ndarray, n: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """n rest points near the skin of GARMENT_BONES and their (n, J) skinning weights."""
    F = body.faces
    bones = [body.bone_names.index(b) for b in GARMENT_BONES]
    region = np.isin(body.dense_weights.argmax(1), bones)[F].all(1)
    faces = F[region]
    tri = rest[faces]
    area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    f = rng.choice(len(faces), n, p=area / area.sum())
    w = rng.dirichlet([1.0, 1.0, 1.0], n).astype(np.float32)
    normals = vertex_normals(rest[None], F)[0]
    pos = np.einsum("nk,nkc->nc", w, rest[faces[f]])
    nrm = np.einsum("nk,nkc->nc", w, normals[faces[f]])
    nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
    pos += rng.uniform(-0.003, 0.015, (n, 1)) * nrm
    weights = np.einsum("nk,nkj->nj", w, body.dense_weights[faces[f]])
    return pos.astype(np.float32), weights.astype(np.float32)


def timed(fn, repeats: int) -> tuple[float, float]:
    fn()
    t = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        t.append(time.perf_counter() - t0)
    return 1e3 * min(t), 1e3 * float(np.median(t))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--points", type=int, default=5000)
    ap.add_argument("--frames", type=int, default=32)
    ap.add_argument("--repeats", type=int, default=20)
    args = ap.parse_args()

    rng = np.random.default_rng(0)
    body = BodyModel.load()
    shape = body.shape(NEUTRAL_PHENOTYPES[None])
    T, J = args.frames, body.num_bones
    rot = rng.normal(0.0, 0.2, (1, T, J, 3)).astype(np.float32)
    rot[0, 0] = 0.0
    _, transforms = body.pose(shape.rest_bone_poses, rot, np.zeros((1, T, 3), np.float32))
    posed = body.skin(shape.rest_vertices, transforms)
    rest_pts, weights = garment_like(body, shape.rest_vertices[0], args.points, rng)
    pts = linear_blend_skinning(rest_pts[None], weights, transforms)

    t0 = time.perf_counter()
    plan = GuardPlan.build(rest_pts[None], shape.rest_vertices, body.faces)
    build_ms = 1e3 * (time.perf_counter() - t0)
    out = guard(pts, posed, plan)
    moved = float((np.abs(out - pts).max(-1) > 0).mean())

    rows = [("GuardPlan.build (once per request)", 1, build_ms, build_ms)]
    for frames in (1, T):
        best, med = timed(lambda: guard(pts[:, :frames], posed[:, :frames], plan), args.repeats)
        rows.append((f"guard, {args.points} points", frames, best / frames, med / frames))
    repaired, left = exact_repair(out, posed, body.faces, 0.002)
    repair_moved = int((np.abs(repaired - out).max(-1) > 0).sum())
    for frames in (1, T):
        best, med = timed(lambda: exact_repair(out[:, :frames], posed[:, :frames], body.faces, 0.002), max(args.repeats // 4, 3))
        rows.append((f"exact_repair, {args.points} points", frames, best / frames, med / frames))
    for frames in (1, 8):
        best, med = timed(lambda: inside_mask(pts[0, :frames], posed[0, :frames], body.faces), max(args.repeats // 4, 3))
        rows.append((f"inside_mask, {args.points} points", frames, best / frames, med / frames))
    best, med = timed(lambda: collision_rates(pts[:, :8], posed[:, :8], body.faces), 3)
    rows.append((f"collision_rates, {args.points} points", 8, best / 8, med / 8))

    print(f"machine: {platform.processor() or platform.machine()}, {os.cpu_count()} CPUs, numpy {np.__version__}")
    print(f"plan: {len(plan.collider_ids)} body vertices, {len(plan.face_ids)} faces, k={plan.candidates.shape[2]}; "
          f"guard moved {100 * moved:.1f} % of the points; the repair then moved {repair_moved} point-frames ({left} left inside)")
    print(f"{'stage':42s} {'frames':>6s} {'best ms/frame':>14s} {'median ms/frame':>16s}")
    for name, frames, best, med in rows:
        print(f"{name:42s} {frames:6d} {best:14.3f} {med:16.3f}")


if __name__ == "__main__":
    main()
