"""What the final collision stage does to the cloth's motion and shape, per garment, on a split of
the protocol (``training.protocol.SPLITS``): each drape with the default options (the arm lift
off, as the protocol's tools) against the same drape with collisions 'off' (what came to the
collision stages).

    python tools/final_stage_motion.py [--split validation] [--garments tshirt --garments tshirt,jacket ...]

Per garment of each case, one line:
- pops: vertex-steps between consecutive frames more than 3 cm longer than the same vertex's step
  before the collision stages, and the largest such excess (cm): the cloth jumping where a point
  inside the body changes its way out (``inference.repair._hold_sides``);
- edges lengthened by more than 2 cm and 3 cm over their length before the collision stages, and
  the largest lengthening (cm): the cloth torn where neighbours leave the body on different sides;
- the largest move of a vertex (mm) and the visible skin crossings per frame
  (``inference.metrics.skin_crossings``).
The last line sums the counts over every case.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from inference.body import BodyModel  # noqa: E402
from inference.garment import GarmentCatalog  # noqa: E402
from inference.mesh import mesh_edges  # noqa: E402
from inference.metrics import skin_crossings  # noqa: E402
from inference.options import DrapeOptions  # noqa: E402
from inference.pipeline import PoseSequence, drape  # noqa: E402
from training.protocol import BODIES, SPLITS, clip_motion, load_clip  # noqa: E402

DEFAULT_SETS = ("tshirt", "longsleeve", "trousers", "dress", "leggings", "shirt", "crewtee", "jacket", "croptop", "shorts",
                "suittrousers", "tshirt,jacket", "croptop,shirt,jacket")
POP_M = 0.03


def edges(faces: np.ndarray) -> np.ndarray:
    return mesh_edges(np.asarray(faces))


def row(after: np.ndarray, before: np.ndarray, faces: np.ndarray, body: np.ndarray, body_faces: np.ndarray) -> dict[str, float]:
    """The line's numbers for one garment: after / before (T, V, 3) the collision stages."""
    excess = np.linalg.norm(np.diff(after, axis=0), axis=-1) - np.linalg.norm(np.diff(before, axis=0), axis=-1)
    e = edges(faces)
    longer = (np.linalg.norm(after[:, e[:, 0]] - after[:, e[:, 1]], axis=-1)
              - np.linalg.norm(before[:, e[:, 0]] - before[:, e[:, 1]], axis=-1))
    return {"pops": int((excess > POP_M).sum()), "pop_max_cm": 100 * float(excess.max(initial=0.0)),
            "edges_2cm": int((longer > 0.02).sum()), "edges_3cm": int((longer > 0.03).sum()), "longer_max_cm": 100 * float(longer.max()),
            "move_max_mm": 1e3 * float(np.linalg.norm(after - before, axis=-1).max()),
            "skin": skin_crossings(after, faces, body, body_faces)}


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--split", default="validation", choices=sorted(SPLITS))
    ap.add_argument("--garments", action="append", help="garment ids, innermost first, comma-separated (repeatable)")
    args = ap.parse_args(argv)
    body, catalog = BodyModel.load(), GarmentCatalog.load()
    total = {"pops": 0, "edges_2cm": 0, "edges_3cm": 0, "skin": 0.0}
    for case in SPLITS[args.split]:
        shape = body.shape(BODIES[case.body][None])
        m = clip_motion(body, shape, load_clip(case.clip, body), case.start + case.frames)
        motion = PoseSequence(m.rotations[case.start:], m.translation[case.start:], m.fps)
        for outfit in args.garments or DEFAULT_SETS:
            assets = [catalog.get(g) for g in outfit.split(",")]
            after = drape(body, shape, motion, assets, DrapeOptions(lift_arms=False))
            before = drape(body, shape, motion, assets, DrapeOptions(lift_arms=False, collisions="off"))
            for g, a, b in zip(assets, after.garments, before.garments):
                r = row(a.vertices, b.vertices, g.faces, after.body_vertices, body.faces)
                for k in total:
                    total[k] += r[k]
                print(f"{case.name:22s} {outfit:22s} {g.id:12s} pops {r['pops']:4d} (max {r['pop_max_cm']:4.1f} cm) | edges +2 cm "
                      f"{r['edges_2cm']:4d}, +3 cm {r['edges_3cm']:4d} (max +{r['longer_max_cm']:.1f} cm) | move max "
                      f"{r['move_max_mm']:5.1f} mm | skin crossings {r['skin']:6.1f}/frame", flush=True)
    print(f"total: pops {total['pops']}, edges +2 cm {total['edges_2cm']}, +3 cm {total['edges_3cm']}, skin crossings {total['skin']:.1f}")


if __name__ == "__main__":
    main()
