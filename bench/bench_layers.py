"""Cost of the layer stage (``inference.layers.untangle_layers``) on top of the single garments.

    python bench/bench_layers.py [--outfit tshirt,jacket] [--frames 30] [--repeats 5]

One thread (BLAS 1), the 02_02 walk (validation clip) on the neutral body, ``--frames`` frames as
one request, each garment's default method. The stage's inputs are captured from a whole drape
(the layers after the guard's push out of the body), then the stage alone is timed, best of
``--repeats``, with cProfile's split of one run by function. Prints a markdown table: ms per
frame (an outfit-frame: all its layers) for the stage and its parts.
"""
from __future__ import annotations

import os

for _v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMBA_NUM_THREADS"):
    os.environ.setdefault(_v, "1")

import argparse  # noqa: E402
import cProfile  # noqa: E402
import pstats  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import inference.pipeline as pipeline  # noqa: E402
from inference.body import BodyModel  # noqa: E402
from inference.garment import GarmentCatalog  # noqa: E402
from inference.options import DrapeOptions  # noqa: E402
from inference.pipeline import PoseSequence, drape  # noqa: E402
from training.protocol import BODIES, clip_motion, load_clip  # noqa: E402

# What cProfile's functions are reported as.
PARTS = {"_bin_faces": "binning a layer's faces (per frame and layer)", "binned_crossings": "crossing queries",
         "spread": "spreading the sinks", "sink_along_rays": "smoothing the directions and sinking", "anchor_normals": "body normals at the anchors"}


def capture(outfit: list[str], frames: int) -> tuple[tuple, dict]:
    """The arguments ``drape`` passes to the layer stage for this outfit on 02_02 (neutral)."""
    body, catalog = BodyModel.load(), GarmentCatalog.load()
    shape = body.shape(BODIES["neutral"][None])
    m = clip_motion(body, shape, load_clip("02_02", body), 30 + frames)
    motion = PoseSequence(m.rotations[30:], m.translation[30:], m.fps)
    seen: dict = {}
    real = pipeline.untangle_layers

    def spy(*args, **kwargs):
        seen["call"] = (args, kwargs)
        return real(*args, **kwargs)

    pipeline.untangle_layers = spy
    try:
        drape(body, shape, motion, [catalog.get(g) for g in outfit], DrapeOptions(lift_arms=False))
    finally:
        pipeline.untangle_layers = real
    return seen["call"]


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--outfit", default="tshirt,jacket")
    ap.add_argument("--frames", type=int, default=30)
    ap.add_argument("--repeats", type=int, default=5)
    args = ap.parse_args(argv)
    call_args, call_kwargs = capture(args.outfit.split(","), args.frames)
    stage = pipeline.untangle_layers
    stage(*call_args, **call_kwargs)  # compiled kernels warm
    times = []
    for _ in range(args.repeats):
        t = time.perf_counter()
        _, report = stage(*call_args, **call_kwargs)
        times.append(time.perf_counter() - t)
    prof = cProfile.Profile()
    prof.enable()
    stage(*call_args, **call_kwargs)
    prof.disable()
    stats = pstats.Stats(prof).stats
    per = {name: sum(v[3] for (_, _, fn), v in stats.items() if fn == name) for name in PARTS}
    T = call_args[0][0].shape[0]
    print(f"{args.outfit}, {T} frames of 02_02 (neutral); moved {report.moved}, held {report.held}, largest move {report.max_move_m * 100:.1f} cm\n")
    print("| ms per frame | |\n|---|---|")
    print(f"| **layer stage, best of {args.repeats}** | **{min(times) / T * 1e3:.2f}** |")
    for name, label in PARTS.items():
        print(f"| {label} (cProfile, cumulative) | {per[name] / T * 1e3:.2f} |")


if __name__ == "__main__":
    main()
