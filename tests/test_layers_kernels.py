"""inference.layers_kernels against the numpy forms they replaced, bit for bit: the anchor
segments, the spread of the sinks and the moves along the smoothed rays."""
from __future__ import annotations

import numpy as np
import trimesh

from inference import layers_kernels
from inference.layers import MIN_SINK_COS, RAY_SMOOTHING, SPREAD_DECAY, SPREAD_RINGS, _neighbours, _ring_matrix


def _mesh_and_frames(T=4, seed=0):
    rng = np.random.default_rng(seed)
    s = trimesh.creation.icosphere(3)
    faces = np.asarray(s.faces, np.int64)
    layer = np.asarray(s.vertices)[None] * 0.3 + rng.normal(0, 0.01, (T, len(s.vertices), 3))
    anchors = layer * rng.uniform(0.8, 0.97, (T, len(s.vertices), 1))
    return faces, layer, anchors, rng


def _spread_numpy(sink, faces):
    T, N = sink.shape
    src, dst = _neighbours(faces, N)
    start = np.searchsorted(src, np.arange(N + 1))
    flat = sink.ravel().copy()
    front = np.flatnonzero(flat)
    for _ in range(SPREAD_RINGS):
        frame, v = np.divmod(front, N)
        deg = start[v + 1] - start[v]
        rows = np.repeat(np.arange(len(v)), deg)
        nb = dst[np.repeat(start[v], deg) + (np.arange(deg.sum()) - np.repeat(np.cumsum(deg) - deg, deg))]
        target = frame[rows] * N + nb
        value = SPREAD_DECAY * flat[front][rows]
        grow = value > flat[target]
        target, value = target[grow], value[grow]
        np.maximum.at(flat, target, value)
        front = np.unique(target)
    return flat.reshape(T, N)


def _sink_numpy(p, seg, L, sink, n, faces, floor):
    A = _ring_matrix(faces, p.shape[1])
    rays = seg / np.maximum(L, 1e-12)[..., None]
    r = np.moveaxis(rays, 1, 0).reshape(p.shape[1], -1)
    for _ in range(RAY_SMOOTHING):
        r = A @ r
    r = np.moveaxis(r.reshape(p.shape[1], p.shape[0], 3), 0, 1)
    hit = sink > 0
    ray = (r / np.maximum(np.linalg.norm(r, axis=-1), 1e-12)[..., None])[hit]
    height = (seg[hit] * n[hit]).sum(-1)
    cos = np.maximum((ray * n[hit]).sum(-1), MIN_SINK_COS)
    depth = np.minimum(sink[hit], np.maximum(height - floor, 0.0) / cos)
    out = p.copy()
    out[hit] -= ray * depth[:, None]
    return out


def test_anchor_segments_are_the_differences_and_numpys_norms():
    _, p, _, rng = _mesh_and_frames()
    body = rng.normal(0, 0.3, (p.shape[0], 300, 3)).astype(np.float32)  # posed bodies come float32
    anchors = rng.integers(0, 300, p.shape[1])
    a_want = body[:, anchors].astype(np.float64)
    a, seg, L = np.empty_like(p), np.empty_like(p), np.empty(p.shape[:2])
    layers_kernels.anchor_segments(p, body, anchors.astype(np.int64), a, seg, L)
    assert np.array_equal(a, a_want) and np.array_equal(seg, p - a_want)
    assert np.array_equal(L, np.linalg.norm(p - a_want, axis=-1))


def test_the_moves_counted_are_numpys():
    # the layer stage's report: vertex-frames moved and the longest move, float32 and mixed inputs
    _, p, _, rng = _mesh_and_frames()
    before = p.astype(np.float32)
    after = before.copy()
    pick = rng.random(after.shape[:2]) < 0.1
    after[pick] += rng.normal(0, 0.01, (pick.sum(), 3)).astype(np.float32)
    for b in (before, p):  # float32, and a float64 input (the rounding moves every vertex)
        step = np.linalg.norm(after - b, axis=-1)
        count, longest = layers_kernels.moves(after, b)
        assert count == (step > 0).sum() and longest == step.max()


def test_the_spread_is_the_numpy_rings():
    faces, p, _, rng = _mesh_and_frames()
    sink = np.where(rng.random(p.shape[:2]) < 0.03, rng.uniform(0.001, 0.02, p.shape[:2]), 0.0)
    sink[1] = 0.0  # a frame without a sink
    want = _spread_numpy(sink, faces)
    flat = sink.ravel().copy()
    src, dst = _neighbours(faces, p.shape[1])
    layers_kernels.spread(flat, p.shape[1], np.searchsorted(src, np.arange(p.shape[1] + 1)), dst, SPREAD_DECAY, SPREAD_RINGS)
    assert np.array_equal(flat.reshape(sink.shape), want)
    assert (want > 0).sum() > 3 * (sink > 0).sum()  # it spread


def test_the_moves_are_the_numpy_smoothing_and_floor():
    faces, p, a, rng = _mesh_and_frames(seed=2)
    seg, L = p - a, np.linalg.norm(p - a, axis=-1)
    sink = np.where(rng.random(L.shape) < 0.3, rng.uniform(0.0, 0.02, L.shape), 0.0)
    sink[2] = 0.0
    n = seg / L[..., None] + rng.normal(0, 0.6, seg.shape)  # normals off the rays: the cosine's floor is hit too
    n /= np.linalg.norm(n, axis=-1, keepdims=True)
    floor = 0.004
    want = _sink_numpy(p, seg, L, sink, n, faces, floor)
    got = p.copy()
    A = _ring_matrix(faces, p.shape[1])
    layers_kernels.sink_along_rays(got, seg, L, sink, n, A.indptr, A.indices, A.data, RAY_SMOOTHING, floor, MIN_SINK_COS)
    assert np.array_equal(got, want)
    moved = (got != p).any(-1)
    assert moved.sum() > 100 and not moved[2].any() and not moved[sink == 0].any()


def test_the_rays_starts_are_numpys():
    # step (a)'s segment starts: each outer vertex pushed reach_m on along its unit anchor ray
    _, o, _, rng = _mesh_and_frames(seed=3)
    a = (o * rng.uniform(0.8, 0.97, (*o.shape[:2], 1))).astype(np.float32)  # posed anchors come float32
    a[0, 0] = o[0, 0]  # a zero ray: the 1e-12 floor
    ray = o - a
    ray /= np.maximum(np.linalg.norm(ray, axis=-1), 1e-12)[..., None]
    got = np.empty_like(o)
    layers_kernels.ray_starts(o, a, 0.02, got)
    assert np.array_equal(got, o + ray * 0.02)
