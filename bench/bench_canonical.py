"""Per-stage cost of fit 'canonical' (thesis ch. 6, ``inference.canonical``) on one request.

    python bench/bench_canonical.py [--garment tshirt] [--frames 30] [--repeats 5] [--model-dir DIR]

One thread (BLAS 1, onnxruntime intra-op 1), the 02_02 walk (validation clip) on the heavy body,
``--frames`` frames as one request. Stages: the body's offsets contracted from the diffused
kernels (once per body), W~ and B~s at the garment's canonical points (once per request for a
static X), the skinning per frame, and the final exact stage; then eq. 6.7 with the fields read
at every frame's own points (``DiffusedBody.pose``: what a per-frame canonical X costs, here X
plus a 1 cm ripple per frame). With ``--model-dir`` (``training.train_canonical``'s output:
canonical_regressor.onnx, canonical_decoder.onnx) also the regressor and the decoder.
Prints a markdown table: best-of-``--repeats`` ms per request and per garment-frame.
"""
from __future__ import annotations

import os

for _v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_v, "1")

import argparse  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from inference.body import BodyModel, linear_blend_skinning  # noqa: E402
from inference.canonical import CanonicalModels, push_out  # noqa: E402
from inference.garment import GarmentCatalog  # noqa: E402
from inference.repair import exact_repair  # noqa: E402


def best(fn, repeats: int) -> tuple[float, object]:
    out = fn()
    times = []
    for _ in range(repeats):
        t = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - t)
    return min(times) * 1e3, out


def main() -> None:
    from training.protocol import BODIES, clip_motion, load_clip

    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--garment", default="tshirt")
    p.add_argument("--frames", type=int, default=30)
    p.add_argument("--repeats", type=int, default=5)
    p.add_argument("--model-dir", type=Path, default=None)
    args = p.parse_args()
    body, catalog, canonical = BodyModel.load(), GarmentCatalog.load(), CanonicalModels()
    d, asset = canonical.diffused, catalog.get(args.garment)
    shape = body.shape(BODIES["heavy"][None])
    motion = clip_motion(body, shape, load_clip("02_02", body), 30 + args.frames)
    T = args.frames
    _, transforms = body.pose(shape.rest_bone_poses, motion.rotations[None, 30:], motion.translation[None, 30:])
    body_frames = body.skin(shape.rest_vertices, transforms)
    rest = shape.rest_vertices[0]
    X = canonical.template(asset)
    rows = []

    def contract():
        d._offsets.clear()  # the per-body cache: measure the contraction itself
        return d.offsets(rest)

    ms, off = best(contract, args.repeats)
    rows.append(("B~s(., beta) contracted at the nodes (once per body)", ms))
    ms, w = best(lambda: d.weights(X), args.repeats)
    rows.append(("W~(X) (once per request, static X)", ms))
    ms, shaped = best(lambda: d.deshaped_to_shaped(X, off), args.repeats)
    rows.append(("X + B~s(X, beta) (once per request, static X)", ms))
    ms, posed = best(lambda: linear_blend_skinning(shaped[None, None].repeat(T, 1), w, transforms), args.repeats)
    rows.append(("skinning, every frame", ms))
    ms, _ = best(lambda: exact_repair(posed, body_frames, body.faces, float(asset.material["collision_margin_m"])), args.repeats)
    rows.append(("final exact stage (winding number + moves), every frame", ms))
    static = [r[1] for r in rows]
    ripple = (0.01 * np.sin(np.arange(T)[:, None, None] * 0.3 + 8.0 * X[None, :, 2:3])).astype(np.float32)
    Xt = (X[None] + ripple * np.array([1.0, 0.0, 0.0], np.float32)).astype(np.float32)
    ms, Xt = best(lambda: push_out(d, Xt, 0.003)[0], args.repeats)
    rows.append(("per-frame X: canonical push to the margin (SDF lookup)", ms))
    ms, _ = best(lambda: d.pose(Xt, off, transforms[0]), args.repeats)
    rows.append(("per-frame X: eq. 6.7 with W~, B~s at each frame's points", ms))
    if args.model_dir is not None:
        import onnxruntime as ort

        from training.train_canonical import case_inputs
        from training.protocol import Case

        so = ort.SessionOptions()
        so.intra_op_num_threads = so.inter_op_num_threads = 1
        reg = ort.InferenceSession(str(args.model_dir / "canonical_regressor.onnx"), so, providers=["CPUExecutionProvider"])
        dec = ort.InferenceSession(str(args.model_dir / "canonical_decoder.onnx"), so, providers=["CPUExecutionProvider"])
        inp = case_inputs(body, Case("02_02", "heavy", 30, T))
        h0 = np.zeros([dim if isinstance(dim, int) else 1 for dim in reg.get_inputs()[2].shape], np.float32)
        feeds = {"phenotypes": inp["phenotypes"][None], "gamma": inp["gamma"][None].astype(np.float32), "h0": h0}
        ms, (z, _) = best(lambda: reg.run(None, feeds), args.repeats)
        rows.append(("regressor R (one ORT call, whole sequence)", ms))
        ms, _ = best(lambda: dec.run(None, {"z": z[0]}), args.repeats)
        rows.append(("decoder D (one ORT call, all frames)", ms))
    print(f"{args.garment}, {T} frames, {len(X)} vertices, heavy body, one thread\n")
    print("| stage | ms per request | ms per garment-frame |\n|---|---|---|")
    for name, ms in rows:
        print(f"| {name} | {ms:.2f} | {ms / T:.3f} |")
    total = sum(static)
    print(f"| **total, static canonical X** (the five stages above) | {total:.2f} | {total / T:.3f} |")


if __name__ == "__main__":
    main()
