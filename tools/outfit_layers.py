"""Layer order of outfits after the whole pipeline (each garment's default method, the service's
options), on the protocol's cases (``training.protocol.SPLITS``): per pair of layers (inner <
outer), the % of inner vertex-frames beyond the outer layer by the body-anchor crossing test
(``inference.metrics.layer_beyond_pct``) and by the closest outer point's side
(``layer_violation_pct``, tolerance 0), the intersecting triangle pairs per frame (exact,
``inference.intersections``); per garment, the % of vertex-frames inside the body; and the layer
stage's cost per frame (``timings_ms['layers']``).

    python tools/outfit_layers.py --split validation
    python tools/outfit_layers.py --split test --outfit tshirt,jacket --outfit tanktop,shirt,jacket
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from inference.body import BodyModel  # noqa: E402
from inference.garment import GarmentCatalog  # noqa: E402
from inference.intersections import layer_intersection_faces, self_intersecting_faces  # noqa: E402
from inference.metrics import inside_mask, layer_beyond_pct, layer_violation_pct  # noqa: E402
from inference.options import DrapeOptions  # noqa: E402
from inference.pipeline import PoseSequence, drape  # noqa: E402
from training.protocol import BODIES, SPLITS, clip_motion, load_clip  # noqa: E402

DEFAULT_OUTFITS = ("tshirt,jacket",)
# Intersecting pairs of inner faces within this of a face where the outer layer crosses itself
# (a sleeve's wall through the torso's under the arm) are reported apart: no layer order exists there.
SELF_RADIUS_M = 0.03


def away_from_self_intersections(per_face: np.ndarray, inner: np.ndarray, inner_faces: np.ndarray, outer: np.ndarray,
                                 outer_faces: np.ndarray) -> np.ndarray:
    """per_face (T, Fi) pair counts, zeroed for the inner faces within SELF_RADIUS_M of a
    self-intersecting outer face."""
    out = per_face.copy()
    own = self_intersecting_faces(outer, outer_faces)
    for t in np.flatnonzero((per_face > 0).any(1) & own.any(1)):
        near = cKDTree(outer[t][outer_faces[own[t]]].mean(1)).query(inner[t][inner_faces].mean(1), distance_upper_bound=SELF_RADIUS_M)[0]
        out[t, np.isfinite(near)] = 0
    return out


def report(outfit: list[str], case, body: BodyModel, catalog: GarmentCatalog, collisions: str = "exact") -> str:
    garments = [catalog.get(g) for g in outfit]
    shape = body.shape(BODIES[case.body][None])
    m = clip_motion(body, shape, load_clip(case.clip, body), case.start + case.frames)
    motion = PoseSequence(m.rotations[case.start:], m.translation[case.start:], m.fps)
    r = drape(body, shape, motion, garments, DrapeOptions(lift_arms=False, collisions=collisions))
    V = [g.vertices for g in r.garments]
    lines = [f"{case.name:28s} {'+'.join(outfit)} ({', '.join(g.method.fit for g in r.garments)}): "
             f"layers {r.timings_ms.get('layers', 0.0) / motion.num_frames:.1f} ms/frame, inside the body "
             + " ".join(f"{100 * inside_mask(v, r.body_vertices, body.faces).mean():.3f} %" for v in V)]
    for i in range(len(V) - 1):
        for j in range(i + 1, len(V)):
            per_face = layer_intersection_faces(V[i], garments[i].faces, V[j], garments[j].faces)
            pairs = per_face.sum(1)
            clean = away_from_self_intersections(per_face, V[i], garments[i].faces, V[j], garments[j].faces).sum(1)
            lines.append(f"    {outfit[i]} under {outfit[j]}: beyond (anchor crossing) "
                         f"{layer_beyond_pct(V[i], r.anchors[i], r.body_vertices, V[j], garments[j].faces):.2f} %, "
                         f"beyond (closest side) {layer_violation_pct(V[i][None], V[j][None], garments[j].faces):.2f} %, "
                         f"intersecting triangle pairs per frame mean {pairs.mean():.0f}, max {pairs.max()} "
                         f"({clean.mean():.1f}, max {clean.max()} farther than {SELF_RADIUS_M * 100:.0f} cm from the outer layer's own intersections)")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--split", default="validation", choices=sorted(SPLITS))
    ap.add_argument("--outfit", action="append", help="garment ids, innermost first, comma-separated (repeatable)")
    ap.add_argument("--collisions", default="exact", help="the request's collision level (DrapeOptions.collisions)")
    args = ap.parse_args(argv)
    body, catalog = BodyModel.load(), GarmentCatalog.load()
    for outfit in args.outfit or DEFAULT_OUTFITS:
        for case in SPLITS[args.split]:
            print(report(outfit.split(","), case, body, catalog, args.collisions), flush=True)


if __name__ == "__main__":
    main()
