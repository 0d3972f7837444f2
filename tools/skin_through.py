"""Skin through the cloth: body and garment triangles that cross each other, per frame, after the
final collision stage (what the service returns), for several methods of one garment.

    python tools/skin_through.py --garment longsleeve [--split validation] [--method canonical-learned ...]

The final stage guarantees that no garment *vertex* is inside the body; the body can still cross
a garment triangle between its vertices where the cloth lies tight on a bulge (under the chest,
on the upper arm), and the renders then show the skin through the cloth. Counted with the exact
triangle-pair test of the layer metrics (``inference.intersections.layer_intersection_faces``,
the body as the inner layer): pairs per frame, and the body faces involved; and the judge's
realism metric (``inference.metrics.skin_crossings``): the pairs on visible body faces, not inside
the body's own self-intersections (the armpit). Cases: the split's (``training.protocol.SPLITS``),
plus the light-tall body on the validation clip.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from inference.body import BodyModel  # noqa: E402
from inference.garment import GarmentCatalog  # noqa: E402
from inference.intersections import layer_intersection_faces  # noqa: E402
from inference.learned import MissingModelError  # noqa: E402
from inference.metrics import skin_crossings  # noqa: E402
from inference.pipeline import DrapeOptions, drape  # noqa: E402
from training.protocol import SPLITS, Case, case_motion  # noqa: E402

METHODS = {"canonical-learned": ("canonical", "learned"), "canonical": ("canonical", "none"), "learned-fit": ("learned", "none"),
           "retarget": ("retarget", "none")}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--garment", required=True)
    p.add_argument("--split", default="validation", choices=sorted(SPLITS))
    p.add_argument("--method", action="append", choices=sorted(METHODS))
    args = p.parse_args()
    body, catalog = BodyModel.load(), GarmentCatalog.load()
    g = catalog.get(args.garment)
    extra = (Case("02_02", "light-tall", 30, 20),) if args.split == "validation" else ()
    for case in (*SPLITS[args.split], *extra):
        shape, motion, start = case_motion(body, case)
        out = []
        for name in args.method or list(METHODS):
            fit, dynamics = METHODS[name]
            try:
                r = drape(body, shape, motion, [g], DrapeOptions(fit=fit, dynamics=dynamics, lift_arms=False))
            except MissingModelError:
                continue
            window = slice(start, start + case.frames)
            bv, gv = r.body_vertices[window], r.garments[0].vertices[window]
            crossed = layer_intersection_faces(bv, body.faces, gv, g.faces)
            seen = skin_crossings(gv, g.faces, bv, body.faces)
            out.append(f"{name} {crossed.sum(1).mean():.0f} pairs ({(crossed > 0).sum(1).mean():.0f} body faces; {seen:.0f} visible)")
        print(f"{case.name:28s}", " | ".join(out), flush=True)


if __name__ == "__main__":
    main()
