"""Layer order of the T-shirt under the jacket on the validation clip (02_02 frames 30-50) for
each pair of fit methods: % of T-shirt vertex-frames beyond the jacket
(``inference.metrics.layer_violation_pct``, tolerance 0 and 3 mm), intersecting (T-shirt, jacket)
triangle pairs per frame (``inference.intersections``, exact) and inside the body, after the
whole pipeline (the guard's layer pushes and the final exact stage).

    python tools/outfit_layers.py
"""
from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from inference.body import BodyModel  # noqa: E402
from inference.defaults import DefaultMethod, DefaultMethods  # noqa: E402
from inference.garment import GarmentCatalog  # noqa: E402
from inference.intersections import layer_intersections  # noqa: E402
from inference.metrics import inside_mask, layer_violation_pct  # noqa: E402
from inference.options import DrapeOptions  # noqa: E402
from inference.pipeline import PoseSequence, drape  # noqa: E402
from training.protocol import BODIES, clip_motion, load_clip  # noqa: E402

PAIRS = (("retarget", "retarget"), ("retarget", "canonical"), ("canonical", "canonical"))


def main() -> None:
    body, catalog = BodyModel.load(), GarmentCatalog.load()
    garments = [catalog.get("tshirt"), catalog.get("jacket")]
    clip = load_clip("02_02", body)
    for name in ("neutral", "heavy", "light-tall"):
        shape = body.shape(BODIES[name][None])
        m = clip_motion(body, shape, clip, 50)
        motion = PoseSequence(m.rotations[30:], m.translation[30:], m.fps)
        for inner, outer in PAIRS:
            entry = dict(dynamics="none", reason="measurement", evidence="tools/outfit_layers.py")
            table = DefaultMethods({"tshirt": DefaultMethod(fit=inner, **entry), "jacket": DefaultMethod(fit=outer, **entry)})
            r = drape(body, shape, motion, garments, DrapeOptions(lift_arms=False), defaults=table)
            t, j = r.garments[0].vertices, r.garments[1].vertices
            pairs = layer_intersections(t, garments[0].faces, j, garments[1].faces)
            print(f"{name:10s} tshirt {inner:9s} jacket {outer:9s}: beyond the jacket {layer_violation_pct(t[None], j[None], garments[1].faces):.2f} % "
                  f"(> 3 mm {layer_violation_pct(t[None], j[None], garments[1].faces, 0.003):.2f} %), intersecting triangle pairs per frame "
                  f"mean {pairs.mean():.0f}, max {pairs.max()}, inside the body "
                  f"{100 * np.mean([inside_mask(g.vertices, r.body_vertices, body.faces).mean() for g in r.garments]):.3f} %", flush=True)


if __name__ == "__main__":
    main()
