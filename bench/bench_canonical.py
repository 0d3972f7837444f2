"""Per-stage cost of fit 'canonical' (thesis ch. 6, ``inference.canonical``) on one request.

    python bench/bench_canonical.py [--garment tshirt] [--frames 30] [--repeats 5] [--model-dir DIR]

One thread (BLAS 1, onnxruntime intra-op 1), the 02_02 walk (validation clip) on the heavy body,
``--frames`` frames as one request. Stages: the body's offsets contracted from the diffused
kernels (once per body), W~ and B~s at the garment's canonical points (once per request for a
static X), the skinning per frame, the compression limit (``inference.strain``) and the final
exact stage; then eq. 6.7 with the fields read
at every frame's own points (``DiffusedBody.pose``: what a per-frame canonical X costs, here X
plus a 1 cm ripple per frame). With ``--model-dir`` (``training.train_canonical``'s output:
canonical_regressor.onnx, canonical_decoder.onnx) also the regressor, the decoder, the
canonical push, eq. 6.7 at each frame's points, the limit and the final stage.
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
    margin_m = float(asset.material["collision_margin_m"])
    rows = []
    canonical.rest_fit(asset, rest)  # the garment's W~(X) and shape operator, once per garment (start-up)
    ms, (shaped, w) = best(lambda: canonical.rest_fit(asset, rest), args.repeats)
    rows.append(("static X: X + B~s(X, beta), one sparse product per body (W~(X) cached)", ms))
    ms, posed = best(lambda: linear_blend_skinning(shaped[None, None].repeat(T, 1), w, transforms), args.repeats)
    rows.append(("static X: skinning, every frame", ms))
    limit = canonical.strain_limit(asset)
    ms, posed = best(lambda: limit(posed[0])[None], args.repeats)
    rows.append(("static X: compression limit (inference.strain, 5 Jacobi passes, compiled)", ms))
    ms, _ = best(lambda: exact_repair(posed, body_frames, body.faces, margin_m), args.repeats)
    rows.append(("final exact stage (winding number + moves), every frame", ms))
    static = sum(r[1] for r in rows)
    model_dir = args.model_dir
    if model_dir is not None:
        import onnxruntime as ort

        from inference.motion.descriptor import motion_descriptor

        so = ort.SessionOptions()
        so.intra_op_num_threads = so.inter_op_num_threads = 1
        reg = ort.InferenceSession(str(model_dir / "canonical_regressor.onnx"), so, providers=["CPUExecutionProvider"])
        dec = ort.InferenceSession(str(model_dir / "canonical_decoder.onnx"), so, providers=["CPUExecutionProvider"])
        gamma = motion_descriptor(motion.rotations[None], motion.translation[None], motion.fps)[:, 30:].astype(np.float32)
        h0 = np.zeros([dim if isinstance(dim, int) else 1 for dim in reg.get_inputs()[2].shape], np.float32)
        feeds = {"phenotypes": shape.phenotypes.astype(np.float32), "gamma": gamma, "h0": h0}
        ms, (z, _) = best(lambda: reg.run(None, feeds), args.repeats)
        rows.append(("learned X_t: regressor R (one ORT call, whole sequence)", ms))
        ms, (Xt,) = best(lambda: dec.run(None, {"z": z[0]}), args.repeats)
        rows.append(("learned X_t: decoder D (one ORT call, all frames)", ms))
        ms, Xt = best(lambda: push_out(d, Xt, margin_m)[0], args.repeats)
        rows.append(("learned X_t: canonical push to the margin (SDF lookup)", ms))

        def contract():
            d._offsets.clear()  # the per-body cache: measure the contraction itself
            return d.offsets(rest)

        ms, off = best(contract, args.repeats)
        rows.append(("learned X_t: B~s(., beta) contracted at the nodes (once per body)", ms))
        ms, posed_t = best(lambda: d.pose(Xt, off, transforms[0]), args.repeats)
        rows.append(("learned X_t: eq. 6.7, W~ and B~s at each frame's points", ms))
        ms, posed_t = best(lambda: limit(posed_t), args.repeats)
        rows.append(("learned X_t: compression limit (inference.strain)", ms))
        ms, _ = best(lambda: exact_repair(posed_t[None], body_frames, body.faces, margin_m), args.repeats)
        rows.append(("learned X_t: final exact stage", ms))
    print(f"{args.garment}, {T} frames, {asset.num_vertices} vertices, heavy body, one thread\n")
    print("| stage | ms per request | ms per garment-frame |\n|---|---|---|")
    for name, ms in rows:
        print(f"| {name} | {ms:.2f} | {ms / T:.3f} |")
    print(f"| **total, static X** (its four rows) | {static:.2f} | {static / T:.3f} |")
    if model_dir is not None:
        learned = sum(r[1] for r in rows[4:])
        print(f"| **total, learned X_t** (its seven rows) | {learned:.2f} | {learned / T:.3f} |")


if __name__ == "__main__":
    main()
