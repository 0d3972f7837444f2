"""Tears and jumps that the final stage (``inference.repair.repair_layers``) makes: each garment's
default drape (``inference.pipeline.drape``, default options) of a clip window on some bodies,
its layers compared as they enter the stage and as they leave it.

- torn edge-frames: mesh edges whose two ends the stage moved, ending more than 1 cm and 3x
  longer than they came (neighbours sent to opposite sides of a body part);
- longest growth: the most any edge grew in the stage, cm;
- pops: vertex-frames whose step from the frame before grows by more than 2 cm in the stage;
- moves: p99 and largest move of the points the stage moved, cm.

One line per garment. The protocol's validation clip is 02_02; a test clip (01_01, 02_07) reports
only: nothing is chosen on it.

    python tools/final_stage_tears.py --clip 02_02 --start 0 --frames 75 --body neutral --body heavy \
        --outfit tshirt --outfit tshirt,jacket
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import inference.pipeline as pipeline  # noqa: E402
from inference.body import BodyModel  # noqa: E402
from inference.garment import GarmentCatalog  # noqa: E402
from inference.mesh import mesh_edges  # noqa: E402
from inference.options import DrapeOptions  # noqa: E402
from training.protocol import BODIES, clip_motion, load_clip  # noqa: E402

TORN_GROWTH_M = 0.01
TORN_RATIO = 3.0
POP_M = 0.02


def stage_io(body, shape, motion, garments) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """Each layer's (T, N, 3) as it enters the final stage and as it leaves it."""
    seen = {}
    repair = pipeline.repair_layers

    def spy(posed, body_vertices, *args, **kwargs):
        out = repair(posed, body_vertices, *args, **kwargs)
        seen["in"], seen["out"] = [p[0].copy() for p in posed], [o[0].copy() for o in out[0]]
        return out

    pipeline.repair_layers = spy
    try:
        pipeline.drape(body, shape, motion, garments, DrapeOptions())
    finally:
        pipeline.repair_layers = repair
    if "in" not in seen:
        raise SystemExit("the drape ran no final stage")
    return seen["in"], seen["out"]


def tears(faces: np.ndarray, came: np.ndarray, left: np.ndarray) -> dict:
    """The module doc's numbers for one layer: came, left (T, N, 3) metres."""
    E = mesh_edges(faces)
    move = left - came
    moved = np.abs(move).sum(-1) > 0
    both = moved[:, E[:, 0]] & moved[:, E[:, 1]]
    before = np.linalg.norm(came[:, E[:, 0]] - came[:, E[:, 1]], axis=-1)
    after = np.linalg.norm(left[:, E[:, 0]] - left[:, E[:, 1]], axis=-1)
    torn = both & (after - before > TORN_GROWTH_M) & (after > TORN_RATIO * before)
    step_in = np.linalg.norm(np.diff(came, axis=0), axis=-1)
    step_out = np.linalg.norm(np.diff(left, axis=0), axis=-1)
    lengths = np.linalg.norm(move, axis=-1)[moved]
    return {"torn": int(torn.sum()), "frames_torn": int(torn.any(1).sum()), "frames": len(came),
            "longest_cm": float((after - before).max(initial=0.0) * 100),
            "pops": int((step_out - step_in > POP_M).sum()),
            "move_p99_cm": float(np.percentile(lengths, 99) * 100) if len(lengths) else 0.0,
            "move_max_cm": float(lengths.max(initial=0.0) * 100)}


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--clip", default="02_02", help="protocol clip id (02_02: validation)")
    ap.add_argument("--start", type=int, default=0, help="first frame")
    ap.add_argument("--frames", type=int, default=75)
    ap.add_argument("--body", action="append", help=f"a BODIES name (repeatable; default neutral, heavy): {sorted(BODIES)}")
    ap.add_argument("--outfit", action="append", help="garment ids, innermost first (repeatable; default tshirt)")
    a = ap.parse_args(argv)
    body, catalog = BodyModel.load(), GarmentCatalog.load()
    for name in a.body or ["neutral", "heavy"]:
        shape = body.shape(BODIES[name][None])
        m = clip_motion(body, shape, load_clip(a.clip, body), a.start + a.frames)
        motion = pipeline.PoseSequence(m.rotations[a.start:], m.translation[a.start:], m.fps)
        for outfit in a.outfit or ["tshirt"]:
            garments = [catalog.get(g) for g in outfit.split(",")]
            came, left = stage_io(body, shape, motion, garments)
            for g, c, l in zip(garments, came, left):
                r = tears(g.faces, c, l)
                print(f"{name:10s} {outfit:22s} {g.id:10s} torn edge-frames {r['torn']:5d}  frames with a tear "
                      f"{r['frames_torn']:3d}/{r['frames']}  longest growth {r['longest_cm']:5.1f} cm  pops {r['pops']:4d}  "
                      f"moves p99/max cm {r['move_p99_cm']:4.1f}/{r['move_max_cm']:4.1f}", flush=True)


if __name__ == "__main__":
    main()
