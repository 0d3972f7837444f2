"""Collision rates of the drape pipeline on a clip, for several bodies and garments (DESIGN.md §5).

Run: ``python -m training.evaluate_collisions [--clip 01_01] [--fit retarget] [--every 1]``

For each body (neutral and the two extreme adult corners) and each catalog garment, drapes the
clip (arms lifted out of the torso, as the service does by default) through
``inference.pipeline.drape`` and measures with the exact inside test of ``inference.metrics``
(ray-crossing winding number), before and after the collision guard:
``inside_pct`` (all vertices) and ``inside_pct_clean`` (vertices farther than 2 cm from a skin
vertex that is itself inside another body part: LBS self-intersection, which no garment vertex
can escape). Prints a Markdown table.
"""
from __future__ import annotations

import argparse
import logging
import time
from dataclasses import dataclass

import numpy as np

from inference.body import NEUTRAL_PHENOTYPES, BodyModel, BodyShape
from inference.garment import GarmentCatalog
from inference.metrics import collision_rates
from inference.motion.clips import Clip, ClipLibrary
from inference.pipeline import DrapeOptions, PoseSequence, drape
from training.protocol import clip_motion

log = logging.getLogger(__name__)

BODIES = {
    "neutral": NEUTRAL_PHENOTYPES,
    "min corner [0,.77,0,0,0,0]": np.array([0.0, 0.77, 0.0, 0.0, 0.0, 0.0], np.float32),
    "max corner [1,1,1,1,1,1]": np.array([1.0, 1.0, 1.0, 1.0, 1.0, 1.0], np.float32),
}


@dataclass
class Row:
    body: str
    garment: str
    frames: int
    before: dict
    after: dict
    seconds: float


def shaped_motion(body: BodyModel, clip, phenotypes: np.ndarray, lift: bool = True):
    """The body shape of ``phenotypes`` (6,) and ``clip`` retargeted to it: (BodyShape, PoseSequence).

    lift: with the arms lifted out of the torso over the whole clip, as the service runs it
    (``inference.motion.self_contact``); drape it with ``lift_arms=False`` (already applied)."""
    shape = body.shape(np.asarray(phenotypes, np.float32)[None])
    return shape, clip_motion(body, shape, clip, lift=lift)


@dataclass
class Inputs:
    """What every evaluation loads: the body model, the catalog, the clip and the neutral shape."""

    body: BodyModel
    catalog: GarmentCatalog
    clip: Clip
    neutral: BodyShape

    @classmethod
    def load(cls, clip_id: str) -> "Inputs":
        body = BodyModel.load()
        return cls(body, GarmentCatalog.load(), ClipLibrary().load(clip_id), body.shape(NEUTRAL_PHENOTYPES[None]))


def evaluate(clip_id: str = "01_01", fit: str = "retarget", every: int = 1, garments: list[str] | None = None,
             bodies: dict[str, np.ndarray] = BODIES, repair: bool = True) -> list[Row]:
    """Collision rates before/after the guard for every (body, garment) on ``clip_id``.

    repair: the guard's exact repair (``DrapeOptions.guard_exact``, the default) included

    every : evaluate every n-th frame of the 30 fps clip (fit baselines without dynamics: frames
            are independent, so only those frames are draped)
    """
    inputs = Inputs.load(clip_id)
    body, catalog, clip, neutral = inputs.body, inputs.catalog, inputs.clip, inputs.neutral
    rows = []
    for body_name, phenotypes in bodies.items():
        shape, full = shaped_motion(body, clip, phenotypes)
        # no dynamics: each frame is independent, so drape only the evaluated frames
        motion = PoseSequence(full.rotations[::every], full.translation[::every], clip.fps / every)
        for gid in garments or catalog.ids():
            g = catalog.get(gid)
            t0 = time.perf_counter()
            raw = drape(body, shape, motion, [g], DrapeOptions(fit=fit, dynamics="none", guard=False, lift_arms=False), neutral=neutral)
            guarded = drape(body, shape, motion, [g], DrapeOptions(fit=fit, dynamics="none", guard=True, lift_arms=False, guard_exact=repair),
                            neutral=neutral)
            _, transforms = body.pose(shape.rest_bone_poses, motion.rotations[None], motion.translation[None])
            body_verts = body.skin(shape.rest_vertices, transforms)
            before = collision_rates(raw.garments[0].vertices[None], body_verts, body.faces)
            after = collision_rates(guarded.garments[0].vertices[None], body_verts, body.faces)
            rows.append(Row(body_name, gid, body_verts.shape[1], before, after, time.perf_counter() - t0))
            log.info("%s %s: inside %.3f%% -> %.3f%% (clean %.3f%% -> %.3f%%; %d -> %d vertex-frames)", body_name, gid, before["inside_pct"],
                     after["inside_pct"], before["inside_pct_clean"], after["inside_pct_clean"], before["inside"], after["inside"])
    return rows


def markdown(rows: list[Row]) -> str:
    lines = [
        "| body | garment | frames | inside before guard (all / clean) % | inside after guard (all / clean) % | within 2 mm after % | s |",
        "|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        lines.append(
            f"| {r.body} | {r.garment} | {r.frames} | {r.before['inside_pct']:.3f} / {r.before['inside_pct_clean']:.3f} | "
            f"{r.after['inside_pct']:.3f} / {r.after['inside_pct_clean']:.4f} | {r.after['within_margin_pct']:.2f} | {r.seconds:.0f} |"
        )
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--clip", default="01_01")
    parser.add_argument("--fit", default="retarget", choices=["retarget", "none"])
    parser.add_argument("--every", type=int, default=1, help="evaluate every n-th frame")
    parser.add_argument("--garments", nargs="*")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    rows = evaluate(args.clip, args.fit, args.every, args.garments)
    print(markdown(rows))  # the report itself goes to stdout


if __name__ == "__main__":
    main()
