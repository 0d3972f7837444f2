"""Per-stage cost of the canonical-space garment model (thesis ch. 6) on one request.

    python bench/bench_canonical.py --model-dir build/canonical_model/tshirt [--frames 30] [--repeats 5]

Needs what ``python -m training.train_canonical --garment G`` writes (regressor.onnx,
decoder.onnx) and the diffused body it used (``--diffused``). One thread (onnxruntime intra-op 1,
BLAS 1), the 02_02 walk (validation clip) on the heavy body, ``--frames`` frames as one request.
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
import onnxruntime as ort  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from inference.body import BodyModel  # noqa: E402
from inference.diffused import DiffusedBody  # noqa: E402


def best(fn, repeats: int) -> tuple[float, object]:
    out = fn()
    times = []
    for _ in range(repeats):
        t = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - t)
    return min(times) * 1e3, out


def main() -> None:
    from training.protocol import Case
    from training.train_canonical import case_inputs

    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--model-dir", type=Path, required=True)
    p.add_argument("--diffused", type=Path, default=Path("build/diffused/diffused.npz"))
    p.add_argument("--frames", type=int, default=30)
    p.add_argument("--repeats", type=int, default=5)
    args = p.parse_args()
    so = ort.SessionOptions()
    so.intra_op_num_threads = so.inter_op_num_threads = 1
    reg = ort.InferenceSession(str(args.model_dir / "regressor.onnx"), so, providers=["CPUExecutionProvider"])
    dec = ort.InferenceSession(str(args.model_dir / "decoder.onnx"), so, providers=["CPUExecutionProvider"])
    body = BodyModel.load()
    diffused = DiffusedBody.load(args.diffused)
    inp = case_inputs(body, Case("02_02", "heavy", 30, args.frames))
    T = args.frames
    h0 = np.zeros([d if isinstance(d, int) else 1 for d in reg.get_inputs()[2].shape], np.float32)
    rows = []
    ms, grid = best(lambda: diffused.offset_grid(inp["coeffs"]), args.repeats)
    rows.append(("B~s contracted with a(beta) (once per body)", ms))
    feeds = {"phenotypes": inp["phenotypes"][None], "gamma": inp["gamma"][None].astype(np.float32), "h0": h0}
    ms, (z, _) = best(lambda: reg.run(None, feeds), args.repeats)
    rows.append(("regressor R (one ORT call, whole sequence)", ms))
    ms, (X,) = best(lambda: dec.run(None, {"z": z[0]}), args.repeats)
    rows.append(("decoder D (one ORT call, all frames)", ms))
    ms, _ = best(lambda: diffused.skin_grid.interpolate(X, slice(0, -1)), args.repeats)
    rows.append(("W~(X) lookup (23 bones, per frame's points)", ms))
    ms, _ = best(lambda: grid.interpolate(X), args.repeats)
    rows.append(("B~s(X, beta) lookup (3 channels)", ms))
    ms, _ = best(lambda: diffused.pose(X, grid, inp["transforms"]), args.repeats)
    rows.append(("M_G: W~, B~s and skinning (eq. 6.7, all of it)", ms))
    posed = diffused.pose(X, grid, inp["transforms"])
    ms, (w_bar, off_bar) = best(lambda: diffused.fields_at(X.mean(0), inp["coeffs"]), args.repeats)
    rows.append(("W~, B~s at the request's mean X (frozen, once per request)", ms))
    ms, frozen = best(lambda: diffused.pose_frozen(X, w_bar, off_bar, inp["transforms"]), args.repeats)
    rows.append(("M_G with the frozen fields: skinning only", ms))
    ms, _ = best(lambda: diffused.sdf(X), args.repeats)
    rows.append(("SDF(X) of the canonical body (check)", ms))
    print(f"{T} frames, {X.shape[1]} vertices, one thread\n")
    print("| stage | ms per request | ms per garment-frame |\n|---|---|---|")
    for name, ms in rows:
        print(f"| {name} | {ms:.2f} | {ms / T:.3f} |")
    ms = dict(rows)
    exact = ms[rows[0][0]] + ms[rows[1][0]] + ms[rows[2][0]] + ms[rows[5][0]]
    fast = ms[rows[1][0]] + ms[rows[2][0]] + ms[rows[6][0]] + ms[rows[7][0]]
    print(f"| **total, fields per frame** (contraction + R + D + M_G) | {exact:.2f} | {exact / T:.3f} |")
    print(f"| **total, frozen fields** (R + D + fields at mean X + skinning) | {fast:.2f} | {fast / T:.3f} |")
    d = np.linalg.norm(frozen - posed, axis=-1) * 1e3
    print(f"\nfrozen against per-frame fields: mean {d.mean():.2f} mm, p99 {np.percentile(d, 99):.2f} mm, max {d.max():.2f} mm")


if __name__ == "__main__":
    main()
