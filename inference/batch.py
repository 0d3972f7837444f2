"""Several drapes in few pipeline calls: the cross-request batching behind the service's worker
pool, and the joining of a job's chunks.

The pipeline (``inference.pipeline.drape``) dresses one body per call, and every stage after the
body shape is per frame (pose, skinning, guard) except the learned dynamics, whose motion
descriptor and wrinkle GRU restart at each motion's first frame (``drape(..., segments=...)``).
Drapes of the same body, garments, per-garment methods and options therefore run as one call on
their motions concatenated along the frame axis: the per-drape work (body shape, garment fit, the
guard's candidate plan, ~0.3 s for a T-shirt on a 2-core CPU) is done once per batch.

Float32 rounding differs with the frame count (BLAS blocking in the skinning einsum, ~1e-7 m);
the collision guard's discrete candidate choice can turn that into a different push at a few
vertices, so a merged result equals the solo one up to that guard tolerance (tests/test_pool.py).
"""
from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from inference.body import BodyModel, BodyShape
from inference.canonical import CanonicalModels
from inference.defaults import DefaultMethods, Method
from inference.garment import GarmentAsset
from inference.learned import LearnedModels
from inference.options import DrapeOptions
from inference.pipeline import DrapedGarment, DrapeResult, PoseSequence, drape

# dynamics modes that can run on concatenated motions (the GRU restarts per segment)
MERGEABLE_DYNAMICS = frozenset({"none", "learned"})


@dataclass(frozen=True)
class DrapeJob:
    """One drape: a shaped body, its motion, its garments (layer order), the options and each
    garment's resolved method."""

    shape: BodyShape
    motion: PoseSequence
    assets: list[GarmentAsset]
    options: DrapeOptions
    methods: list[Method]

    def batch_key(self) -> tuple | None:
        """Jobs with equal keys may share one pipeline call; None: run alone."""
        if any(m.dynamics not in MERGEABLE_DYNAMICS for m in self.methods):
            return None
        return (self.shape.phenotypes.tobytes(), tuple((a.id, m) for a, m in zip(self.assets, self.methods)),
                self.options.pipeline_key())


def drape_many(body: BodyModel, jobs: Sequence[DrapeJob], neutral: BodyShape | None = None, models: LearnedModels | None = None,
               defaults: DefaultMethods | None = None, canonical: CanonicalModels | None = None) -> list[DrapeResult]:
    """Every job's result, in order; jobs with the same ``batch_key`` go through one ``drape``
    call on their concatenated motions."""
    groups: dict[object, list[int]] = {}
    for i, job in enumerate(jobs):
        key = job.batch_key()
        groups.setdefault(key if key is not None else ("solo", i), []).append(i)
    results: list[DrapeResult | None] = [None] * len(jobs)
    for members in groups.values():
        first = jobs[members[0]]
        motions = [jobs[i].motion for i in members]
        merged = drape(body, first.shape, merge_motions(motions), first.assets, first.options, neutral=neutral,
                       segments=[m.num_frames for m in motions], defaults=defaults, models=models, canonical=canonical)
        for i, r in zip(members, split_result(merged, motions)):
            results[i] = r
    return results  # type: ignore[return-value]


def merge_motions(motions: list[PoseSequence]) -> PoseSequence:
    """Motions (T_i, J, 3) concatenated along the frame axis: (sum T_i, J, 3); the fps is the
    first one's (per-frame stages do not use it)."""
    if len(motions) == 1:
        return motions[0]
    return PoseSequence(
        np.concatenate([m.rotations for m in motions]), np.concatenate([m.translation for m in motions]), motions[0].fps
    )


def split_result(result: DrapeResult, motions: list[PoseSequence]) -> list[DrapeResult]:
    """The inverse of ``merge_motions`` on the pipeline's result: one result per motion."""
    if len(motions) == 1:
        return [result]
    out, start = [], 0
    for m in motions:
        stop = start + m.num_frames
        out.append(DrapeResult(
            garments=[DrapedGarment(asset=g.asset, vertices=g.vertices[start:stop], method=g.method) for g in result.garments],
            shape=result.shape,
            bone_poses=result.bone_poses[start:stop],
            body_vertices=None if result.body_vertices is None else result.body_vertices[start:stop],
            fps=m.fps,
            # each member is charged its share of the batch's time
            timings_ms={k: v * m.num_frames / len(result.bone_poses) for k, v in result.timings_ms.items()},
            anchors=result.anchors,
        ))
        start = stop
    return out


def concatenate_results(results: list[DrapeResult], fps: float) -> DrapeResult:
    """Consecutive chunks of one motion (``inference.pipeline.drape_chunks``) joined into one result."""
    if len(results) == 1:
        return results[0]
    timings: dict[str, float] = {}
    for r in results:
        for k, v in r.timings_ms.items():
            timings[k] = timings.get(k, 0.0) + v
    first = results[0]
    return DrapeResult(
        garments=[DrapedGarment(asset=g.asset, vertices=np.concatenate([r.garments[i].vertices for r in results]), method=g.method)
                  for i, g in enumerate(first.garments)],
        shape=first.shape,
        bone_poses=np.concatenate([r.bone_poses for r in results]),
        body_vertices=None if first.body_vertices is None else np.concatenate([r.body_vertices for r in results]),
        fps=fps,
        timings_ms=timings,
        wrinkle_state=results[-1].wrinkle_state,
        anchors=first.anchors,
        repair_state=results[-1].repair_state,
    )
