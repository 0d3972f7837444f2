"""Measure the guard's closest-triangle check (``inference.guard.constants.REFINE_CANDIDATES``,
``REFINE_PASSES``) on the validation clip CMU 02_02 (first chosen on 01_01, a test clip): the
default T-shirt and jacket, neutral and heaviest adult, arms lifted; clean inside % after the
guard without the exact repair (every 2nd frame) and the guard's ms per garment-frame, for the
plane push alone (``collisions: "push"``) and the check with 1, 3 or 5 candidates' one-rings and
1 or 2 passes.

    python tools/guard_check_validation.py
"""
from __future__ import annotations

import numpy as np

import inference.guard.push as push_module
from inference.body import BodyModel
from inference.garment import GarmentCatalog
from inference.metrics import collision_rates
from inference.options import DrapeOptions
from inference.pipeline import drape
from training.protocol import BODIES, validation_motions

EVERY = 2
VARIANTS = {"push only": ("push", 3, 2), "check, 1 candidate, 2 passes": ("check", 1, 2), "check, 3 candidates, 1 pass": ("check", 3, 1),
            "check, 3 candidates, 2 passes (default)": ("check", 3, 2), "check, 5 candidates, 2 passes": ("check", 5, 2)}


def main() -> None:
    body = BodyModel.load()
    catalog = GarmentCatalog.load()
    neutral = body.shape(np.asarray(BODIES["neutral"], np.float32)[None])
    print("| garment | body | variant | clean inside % after the guard | guard ms per frame |")
    print("|---|---|---|---|---|")
    for name, shape, motion in validation_motions(body):
        for garment_id in ("tshirt", "jacket"):
            for label, (level, candidates, passes) in VARIANTS.items():
                push_module.REFINE_CANDIDATES, push_module.REFINE_PASSES = candidates, passes
                out = drape(body, shape, motion, [catalog.get(garment_id)], DrapeOptions(collisions=level, lift_arms=False), neutral=neutral)
                rates = collision_rates(out.garments[0].vertices[None, ::EVERY], out.body_vertices[None, ::EVERY], body.faces)
                ms = out.timings_ms["guard"] / motion.num_frames
                print(f"| {garment_id} | {name} | {label} | {rates['inside_pct_clean']:.3f} | {ms:.1f} |", flush=True)


if __name__ == "__main__":
    main()
