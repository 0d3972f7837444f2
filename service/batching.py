"""Which queued requests the worker pool may put in one batch: requests for the same body,
garments, per-garment methods (the request's fit and dynamics, else each garment's default:
``inference.defaults``) and other options. The batch runs as one pipeline call on the requests'
motions concatenated along the frame axis (``inference.batch.drape_many``, which keys the
prepared drapes the same way).
"""
from __future__ import annotations

from inference.batch import MERGEABLE_DYNAMICS
from inference.defaults import DefaultMethods, Method, resolve_methods
from service.schemas import DrapeRequest


def request_methods(request: DrapeRequest, defaults: DefaultMethods) -> list[Method] | None:
    """The method each of the request's garments runs (request order: its options, else each
    garment's default); None when a garment is not in ``defaults`` (an unknown id: the request
    fails its validation later, with its own 422)."""
    o = request.options
    ids = [g.id for g in request.garments]
    if (o.fit is None or o.dynamics is None) and not all(i in defaults for i in ids):
        return None
    return resolve_methods(ids, o.fit, o.dynamics, defaults, outfit=len(ids) > 1)


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
        o.pipeline_key(),
    )
