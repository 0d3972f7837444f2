"""Runtime of the learned garment models: ONNX fit + wrinkle GRU + LBS, ms per frame per garment.

Three ways to run a clip of T frames (walk, 30 fps) on this CPU, onnxruntime with 1 thread:
- stream   : batch 1, one frame per call (GRU state carried), + skinning of that frame
- sequence : batch 1, the whole clip in one ORT call, + skinning of all frames
- batched  : B bodies x T frames in one ORT call, + skinning; ms per body-frame
The fit (once per body) is included, amortised over the frames. Median of ``--repeats`` runs.

Run: ``.venv/bin/python bench/bench_learned.py [--frames 120] [--batch 8] [--repeats 5]``
"""
from __future__ import annotations

import argparse
import json
import logging
import time

import numpy as np

from inference.body import NEUTRAL_PHENOTYPES, BodyModel, linear_blend_skinning
from inference.garment import GarmentCatalog
from inference.learned import LearnedModels
from inference.motion.clips import ClipLibrary, adapt_clip
from inference.motion.descriptor import motion_descriptor

log = logging.getLogger("bench_learned")


def median_ms(fn, repeats: int) -> float:
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append((time.perf_counter() - t0) * 1e3)
    return float(np.median(times))


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--frames", type=int, default=80)
    p.add_argument("--batch", type=int, default=8)
    p.add_argument("--repeats", type=int, default=5)
    p.add_argument("--threads", type=int, default=1)
    args = p.parse_args()
    logging.basicConfig(level=logging.INFO, format="%(message)s")

    body = BodyModel.load()
    catalog = GarmentCatalog.load()
    models = LearnedModels(threads=args.threads)
    rng = np.random.default_rng(0)
    phen = NEUTRAL_PHENOTYPES[None].repeat(args.batch, 0).copy()
    phen[1:] = np.clip(phen[1:] + rng.uniform(-0.3, 0.3, (args.batch - 1, 6)), [0, 0.77, 0, 0, 0, 0], 1).astype(np.float32)
    shape = body.shape(phen)
    clip = ClipLibrary().load("walk")
    rot, trans = adapt_clip(clip, body, shape)
    T = min(args.frames, rot.shape[1])
    rot, trans = rot[:, :T], trans[:, :T]
    _, transforms = body.pose(shape.rest_bone_poses, rot, trans)
    gamma = motion_descriptor(rot, trans, clip.fps)
    hm08 = body.hm08_vertices(shape)

    results = {}
    for gid in catalog.ids():
        if not models.available(gid):
            log.info("%-10s no learned models: skipped", gid)
            continue
        asset = catalog.get(gid)
        lg = models.get(gid)
        if not lg.has_wrinkles:
            log.info("%-10s a fit regressor alone (no wrinkle GRU): skipped", gid)
            continue
        retarget = asset.retarget_fit(hm08)
        lg.wrinkles(phen[:1], gamma[:1, :2])  # warm-up

        def stream():
            fit = retarget[:1] + lg.fit(phen[:1])
            h = None
            for t in range(T):
                d, h = lg.wrinkles(phen[:1], gamma[:1, t : t + 1], h)
                linear_blend_skinning(fit[:, None] + d, asset.skin_weights, transforms[:1, t : t + 1])

        def sequence():
            fit = retarget[:1] + lg.fit(phen[:1])
            d, _ = lg.wrinkles(phen[:1], gamma[:1])
            linear_blend_skinning(fit[:, None] + d, asset.skin_weights, transforms[:1])

        def batched():
            fit = retarget + lg.fit(phen)
            d, _ = lg.wrinkles(phen, gamma)
            linear_blend_skinning(fit[:, None] + d, asset.skin_weights, transforms)

        def models_only():
            lg.fit(phen[:1])
            lg.wrinkles(phen[:1], gamma[:1])

        r = {
            "vertices": asset.num_vertices,
            "stream_ms_per_frame": median_ms(stream, args.repeats) / T,
            "sequence_ms_per_frame": median_ms(sequence, args.repeats) / T,
            "batched_ms_per_frame": median_ms(batched, args.repeats) / (T * args.batch),
            "models_only_sequence_ms_per_frame": median_ms(models_only, args.repeats) / T,
        }
        results[gid] = r
        log.info("%-10s V=%5d  stream %.2f  sequence %.2f  batched(B=%d) %.3f  [models only %.2f] ms/frame", gid, r["vertices"],
                 r["stream_ms_per_frame"], r["sequence_ms_per_frame"], args.batch, r["batched_ms_per_frame"], r["models_only_sequence_ms_per_frame"])
    log.info(json.dumps({"frames": T, "batch": args.batch, "threads": args.threads, "results": results}, indent=1))


if __name__ == "__main__":
    main()
