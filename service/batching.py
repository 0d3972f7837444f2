"""Cross-request batching: which requests can share one pipeline call, and how their frames are
merged and split again.

The pipeline (inference/pipeline.py) dresses one body per call, and every stage after the body
shape is per frame (pose, skinning, guard) except the learned dynamics, whose motion descriptor
and wrinkle GRU restart at each request's first frame (``drape(..., segments=...)``). Requests for
the same body, garments and options therefore run as one call on their motions concatenated
along the frame axis: the per-request work (body shape, garment fit, the guard's candidate plan,
~0.3 s for a T-shirt on this CPU) is done once per batch instead of once per request.

Float32 rounding differs with the frame count (BLAS blocking in the skinning einsum, ~1e-7 m);
the collision guard's discrete candidate choice can turn that into a different push at a few
vertices, so a merged result equals the solo one up to that guard tolerance (tests/test_pool.py).
"""
from __future__ import annotations

import numpy as np

from inference.pipeline import DrapedGarment, DrapeResult, PoseSequence
from service.schemas import DrapeRequest

# dynamics modes whose stages are all per frame (a job may run them in chunks of frames)
PER_FRAME_DYNAMICS = frozenset({"none"})
# dynamics modes that can run on concatenated motions (the GRU restarts per segment)
MERGEABLE_DYNAMICS = frozenset({"none", "learned"})


def merge_key(request: DrapeRequest) -> tuple | None:
    """Requests with equal keys may share one pipeline call; None: run alone."""
    o = request.options
    if o.dynamics not in MERGEABLE_DYNAMICS:
        return None
    p = request.body.phenotypes
    return (
        (p.gender, p.age, p.muscle, p.weight, p.height, p.proportions),
        tuple(g.id for g in request.garments),
        o.fit, o.dynamics, o.guard, o.margin_m, o.layer_gap_m, o.lift_arms, o.guard_check, o.guard_exact,
    )


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
            garments=[DrapedGarment(asset=g.asset, vertices=g.vertices[start:stop]) for g in result.garments],
            shape=result.shape,
            bone_poses=result.bone_poses[start:stop],
            body_vertices=None if result.body_vertices is None else result.body_vertices[start:stop],
            fps=m.fps,
            # each member is charged its share of the batch's time
            timings_ms={k: v * m.num_frames / len(result.bone_poses) for k, v in result.timings_ms.items()},
        ))
        start = stop
    return out


def concatenate_results(results: list[DrapeResult], fps: float) -> DrapeResult:
    """Consecutive chunks of one motion (a job) joined into one result."""
    if len(results) == 1:
        return results[0]
    timings: dict[str, float] = {}
    for r in results:
        for k, v in r.timings_ms.items():
            timings[k] = timings.get(k, 0.0) + v
    first = results[0]
    return DrapeResult(
        garments=[DrapedGarment(asset=g.asset, vertices=np.concatenate([r.garments[i].vertices for r in results]))
                  for i, g in enumerate(first.garments)],
        shape=first.shape,
        bone_poses=np.concatenate([r.bone_poses for r in results]),
        body_vertices=None if first.body_vertices is None else np.concatenate([r.body_vertices for r in results]),
        fps=fps,
        timings_ms=timings,
    )
