"""Re-measure the guard's far dynamic candidates (``inference.guard.constants.DYNAMIC_REACH_M``,
``DYNAMIC_VOXEL_M``) on the validation clip CMU 02_02 (first measured on 01_01, a test clip):
retarget T-shirt with the arm lift (the default drape), every 2nd of the 75 frames, clean inside
% after the guard with its triangle check and without the exact repair, and the guard's ms per
garment-frame, for: no far candidates (reach = the 5 cm region), reach 30 cm thinned to 2 cm
cells (the default) and to 3 cm cells; neutral and heaviest adult.

    python tools/guard_reach_validation.py
"""
from __future__ import annotations

import numpy as np

import inference.guard.plan as plan_module
from inference.body import BodyModel
from inference.garment import GarmentCatalog
from inference.metrics import collision_rates
from inference.options import DrapeOptions
from inference.pipeline import drape
from training.protocol import BODIES, clip_motion, load_clip

EVERY = 2
VARIANTS = {"no far candidates": (plan_module.DYNAMIC_REGION_M, 0.02), "reach 30 cm, 2 cm cells (default)": (0.30, 0.02),
            "reach 30 cm, 3 cm cells": (0.30, 0.03)}


def main() -> None:
    body = BodyModel.load()
    tshirt = GarmentCatalog.load().get("tshirt")
    clip = load_clip("02_02", body)
    print("| body | variant | clean inside % after the guard | inside % | guard ms per frame |")
    print("|---|---|---|---|---|")
    for name in ("neutral", "heavy"):
        shape = body.shape(np.asarray(BODIES[name], np.float32)[None])
        motion = clip_motion(body, shape, clip, lift=False)  # the drape lifts the arms (its default)
        for label, (reach, voxel) in VARIANTS.items():
            plan_module.DYNAMIC_REACH_M, plan_module.DYNAMIC_VOXEL_M = reach, voxel
            out = drape(body, shape, motion, [tshirt], DrapeOptions(fit="retarget", dynamics="none", collisions="check"))
            verts = out.garments[0].vertices[::EVERY]
            rates = collision_rates(verts[None], out.body_vertices[None, ::EVERY], body.faces)
            ms = out.timings_ms["guard"] / motion.num_frames
            print(f"| {name} | {label} | {rates['inside_pct_clean']:.3f} | {rates['inside_pct']:.3f} | {ms:.1f} |")


if __name__ == "__main__":
    main()
