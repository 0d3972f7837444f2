"""Measure the exact repair's candidate counts (``inference.repair.REPAIR_CANDIDATES``,
``FAR_FACTOR``) on the validation clip CMU 02_02 (first chosen on 01_01, a test clip): the
default T-shirt and jacket, neutral and heaviest adult, guarded with the triangle check
(``collisions: "check"``, the drape the repair receives), then repaired with each candidate count:
points inside before, left inside after, how far the repair moves them (median, 95th percentile,
max, mm) and its ms per garment-frame.

    python tools/repair_validation.py
"""
from __future__ import annotations

import time

import numpy as np

import inference.repair as repair_module
from inference.body import BodyModel
from inference.garment import GarmentCatalog
from inference.options import DrapeOptions
from inference.pipeline import drape
from training.protocol import BODIES, validation_motions

CANDIDATES = (8, 16, 32, 64)
FAR_FACTORS = (16,)
GARMENTS = ("tshirt", "jacket")


def main() -> None:
    body = BodyModel.load()
    catalog = GarmentCatalog.load()
    neutral = body.shape(np.asarray(BODIES["neutral"], np.float32)[None])
    print("| garment | body | k | far factor | inside before | left inside | move median / p95 / max mm | repair ms per frame |")
    print("|---|---|---|---|---|---|---|---|")
    for name, shape, motion in validation_motions(body):
        for garment_id in GARMENTS:
            garment = catalog.get(garment_id)
            out = drape(body, shape, motion, [garment], DrapeOptions(collisions="check", lift_arms=False), neutral=neutral)
            points = out.garments[0].vertices[None]
            bodies = out.body_vertices[None]
            for far in FAR_FACTORS:
                repair_module.FAR_FACTOR = far
                for k in CANDIDATES:
                    t0 = time.perf_counter()
                    fixed, left = repair_module.exact_repair(points, bodies, body.faces, DrapeOptions().margin_m, k=k)
                    ms = (time.perf_counter() - t0) * 1e3 / motion.num_frames
                    moved = np.linalg.norm(fixed - points, axis=-1)
                    moves = moved[moved > 0] * 1e3
                    q = np.percentile(moves, [50, 95, 100]) if len(moves) else np.zeros(3)
                    print(f"| {garment_id} | {name} | {k} | {far} | {len(moves)} | {left} | {q[0]:.1f} / {q[1]:.1f} / {q[2]:.1f} | {ms:.1f} |", flush=True)


if __name__ == "__main__":
    main()
