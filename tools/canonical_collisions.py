"""Garment vertices inside the posed body before any collision stage: fit 'canonical' (the
canonical template through the diffused body, thesis eq. 6.7-6.8) against the retarget baseline
(the .mhclo retarget, plain LBS with the garment's own weights), every garment, on a protocol
split's cases plus the other extreme bodies, with and without the arm lift.

    python tools/canonical_collisions.py --split validation    # 02_02 on neutral, heavy, light-tall
    python tools/canonical_collisions.py --split test          # 01_01 and 02_07 on the three bodies (reported only)

Prints one line per (case, arm lift, garment): % of vertex-frames inside (exact winding number)
and the same away from body self-intersections ("clean", ``inference.metrics.collision_rates``).
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from inference.body import BodyModel, linear_blend_skinning  # noqa: E402
from inference.canonical import CanonicalModels  # noqa: E402
from inference.garment import GarmentCatalog  # noqa: E402
from inference.metrics import collision_rates  # noqa: E402
from training.protocol import BODIES, SPLITS, Case, clip_motion, load_clip  # noqa: E402

EXTRA = {"validation": (Case("02_02", "light-tall", 30, 20),),
         "test": (Case("01_01", "light-tall", 120, 20), Case("02_07", "heavy", 60, 20))}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--split", choices=sorted(EXTRA), required=True)
    p.add_argument("--garment", action="append")
    args = p.parse_args()
    body, catalog, canonical = BodyModel.load(), GarmentCatalog.load(), CanonicalModels()
    for case in (*SPLITS[args.split], *EXTRA[args.split]):
        clip = load_clip(case.clip, body)
        shape = body.shape(BODIES[case.body][None])
        w = slice(case.start, case.start + case.frames)
        for lift in (True, False):
            motion = clip_motion(body, shape, clip, case.start + case.frames, lift=lift)
            _, T = body.pose(shape.rest_bone_poses, motion.rotations[None, w], motion.translation[None, w])
            body_frames = body.skin(shape.rest_vertices, T)
            for g in args.garment or catalog.ids():
                asset = catalog.get(g)
                fit, weights = canonical.rest_fit(asset, shape.rest_vertices[0])
                can = linear_blend_skinning(np.repeat(fit[None, None], case.frames, 1), weights, T)
                ret = asset.retarget_fit(body.hm08_vertices(shape))
                base = linear_blend_skinning(np.repeat(ret[:, None], case.frames, 1), asset.skin_weights, T)
                rc, rr = collision_rates(can, body_frames, body.faces), collision_rates(base, body_frames, body.faces)
                print(f"{case.name:28s} lift={lift!s:5s} {g:10s} canonical {rc['inside_pct']:.3f} % (clean {rc['inside_pct_clean']:.3f} %) | "
                      f"retarget {rr['inside_pct']:.3f} % (clean {rr['inside_pct_clean']:.3f} %)", flush=True)


if __name__ == "__main__":
    main()
