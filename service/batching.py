"""Cross-request batching: which requests can share one pipeline call, and how their frames are
merged and split again.

The pipeline (inference/pipeline.py) dresses one body per call, and every stage after the body
shape is per frame (pose, skinning, guard) except the learned dynamics, whose motion descriptor
and wrinkle GRU restart at each request's first frame (``drape(..., segments=...)``). Requests for
the same body, garments, per-garment methods (the request's fit and dynamics, else each garment's
default: ``inference.defaults``) and other options therefore run as one call on their motions
concatenated along the frame axis: the per-request work (body shape, garment fit, the guard's
candidate plan, ~0.3 s for a T-shirt on this CPU) is done once per batch instead of once per request.

Float32 rounding differs with the frame count (BLAS blocking in the skinning einsum, ~1e-7 m);
the collision guard's discrete candidate choice can turn that into a different push at a few
vertices, so a merged result equals the solo one up to that guard tolerance (tests/test_pool.py).
"""
from __future__ import annotations

import numpy as np

from inference.defaults import DefaultMethods, Method, resolve_methods
from inference.pipeline import DrapedGarment, DrapeResult, PoseSequence
from service.schemas import DrapeRequest

# dynamics modes that can run on concatenated motions (the GRU restarts per segment)
MERGEABLE_DYNAMICS = frozenset({"none", "learned"})


def request_methods(request: DrapeRequest, defaults: DefaultMethods) -> list[Method] | None:
    """The method each of the request's garments runs (request order: its options, else each
    garment's default); None when a garment is not in ``defaults`` (an unknown id: the request
    fails its validation later, with its own 422)."""
    o = request.options
    ids = [g.id for g in request.garments]
    if (o.fit is None or o.dynamics is None) and not all(i in defaults for i in ids):
        return None
    return resolve_methods(ids, o.fit, o.dynamics, defaults)


def merge_key(request: DrapeRequest, defaults: DefaultMethods) -> tuple | None:
    """Requests with equal keys may share one pipeline call (``defaults``: each garment's default
    method, for the options left None); None: run alone."""
    methods = request_methods(request, defaults)
    if methods is None or any(m.dynamics not in MERGEABLE_DYNAMICS for m in methods):
        return None
    o, p = request.options, request.body.phenotypes
    return (
        (p.gender, p.age, p.muscle, p.weight, p.height, p.proportions),
        tuple((g.id, m.fit, m.dynamics) for g, m in zip(request.garments, methods)),
        o.guard, o.margin_m, o.layer_gap_m, o.lift_arms, o.guard_check, o.guard_exact,
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
            garments=[DrapedGarment(asset=g.asset, vertices=g.vertices[start:stop], method=g.method) for g in result.garments],
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
        garments=[DrapedGarment(asset=g.asset, vertices=np.concatenate([r.garments[i].vertices for r in results]), method=g.method)
                  for i, g in enumerate(first.garments)],
        shape=first.shape,
        bone_poses=np.concatenate([r.bone_poses for r in results]),
        body_vertices=None if first.body_vertices is None else np.concatenate([r.body_vertices for r in results]),
        fps=fps,
        timings_ms=timings,
    )
