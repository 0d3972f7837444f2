"""Compiled kernels of ``inference.layers`` (numba, no Python objects, one thread): an inner
layer's anchor segments, the spread of its sink depths over the mesh and its moves along the
smoothed anchor rays (the module doc of ``inference.layers``, steps (a)-(b) after the crossings).

Each is the numpy form it replaced, operation for operation in float64 without fast-math (no FMA
contraction): sums of three products in numpy's order ((x0 + x1) + x2), the ring sums in the
stored order of the CSR matrix (scipy's ``csr_matvecs``: y += a x from zero), so that the layers
come out bitwise the same. They save numpy's (T, N, 3) temporaries: ~1.7 ms a frame of T-shirt
under jacket went to them.

Units: metres. Arrays: float64, frames first (T, N, 3).
"""
from __future__ import annotations

import numba
import numpy as np

_JIT = {"nogil": True, "cache": True, "fastmath": False}


@numba.njit(**_JIT)
def anchor_segments(p, body, anchors, a, seg, length):
    """The posed anchors a = body[:, anchors] in float64, seg = p - a and its length |seg|
    (numpy's ``linalg.norm(seg, axis=-1)``), in place: p, a, seg (T, N, 3) float64; body (T, Vb, 3)
    float32 or float64; anchors (N,) int64; length (T, N) float64."""
    T, N = p.shape[0], p.shape[1]
    for t in range(T):
        for v in range(N):
            b = anchors[v]
            a0, a1, a2 = np.float64(body[t, b, 0]), np.float64(body[t, b, 1]), np.float64(body[t, b, 2])
            a[t, v, 0], a[t, v, 1], a[t, v, 2] = a0, a1, a2
            s0, s1, s2 = p[t, v, 0] - a0, p[t, v, 1] - a1, p[t, v, 2] - a2
            seg[t, v, 0], seg[t, v, 1], seg[t, v, 2] = s0, s1, s2
            length[t, v] = np.sqrt(s0 * s0 + s1 * s1 + s2 * s2)


@numba.njit(**_JIT)
def moves(after, before):
    """How many vertex-frames moved (a move of nonzero length) and the longest move, metres: after,
    before (T, N, 3); the length in their common precision as numpy's ``linalg.norm`` of the
    difference (without the (T, N, 3) difference: ~4 ms of a 30-frame outfit request)."""
    moved, longest = 0, 0.0
    for t in range(after.shape[0]):
        for v in range(after.shape[1]):
            d0, d1, d2 = after[t, v, 0] - before[t, v, 0], after[t, v, 1] - before[t, v, 1], after[t, v, 2] - before[t, v, 2]
            step = np.sqrt(d0 * d0 + d1 * d1 + d2 * d2)
            if step > 0:
                moved += 1
                longest = max(longest, step)
    return moved, longest


@numba.njit(**_JIT)
def ray_starts(o, a, reach, out):
    """out = o + reach (o - a) / max(|o - a|, 1e-12), in place: each outer vertex o pushed ``reach``
    metres on along its anchor ray (step (a)'s segments start there); o (T, n, 3) float64, a (T, n, 3)
    its posed anchors (float32 or float64), out (T, n, 3) float64."""
    T, n = o.shape[0], o.shape[1]
    for t in range(T):
        for v in range(n):
            r0 = o[t, v, 0] - np.float64(a[t, v, 0])
            r1 = o[t, v, 1] - np.float64(a[t, v, 1])
            r2 = o[t, v, 2] - np.float64(a[t, v, 2])
            scale = max(np.sqrt(r0 * r0 + r1 * r1 + r2 * r2), 1e-12)
            out[t, v, 0] = o[t, v, 0] + r0 / scale * reach
            out[t, v, 1] = o[t, v, 1] + r1 / scale * reach
            out[t, v, 2] = o[t, v, 2] + r2 / scale * reach


@numba.njit(**_JIT)
def spread(flat, N, start, dst, decay, rings):
    """Each nonzero sink of flat (T * N,) spread over the mesh, in place: for ``rings`` rings, every
    neighbour dst[start[v]:start[v + 1]] of a vertex v that rose in the ring before (at first: every
    nonzero one) takes at least ``decay`` times v's value as that ring began. The vertices that rise
    are the next ring's; the order they are visited in does not change the maxima."""
    M = flat.shape[0]
    front = np.empty(M, np.int64)
    nf = 0
    for e in range(M):
        if flat[e] != 0.0:
            front[nf] = e
            nf += 1
    values = np.empty(M)
    rose = np.zeros(M, np.bool_)
    nxt = np.empty(M, np.int64)
    for _ in range(rings):
        for q in range(nf):  # the values as the ring begins: a front vertex may rise during it
            values[q] = decay * flat[front[q]]
        nn = 0
        for q in range(nf):
            e = front[q]
            frame, v = e // N, e % N
            value = values[q]
            for s in range(start[v], start[v + 1]):
                target = frame * N + dst[s]
                if value > flat[target]:
                    flat[target] = value
                    if not rose[target]:
                        rose[target] = True
                        nxt[nn] = target
                        nn += 1
        for q in range(nn):
            rose[nxt[q]] = False
            front[q] = nxt[q]
        nf = nn


@numba.njit(**_JIT)
def sink_along_rays(p, seg, length, sink, normals, indptr, indices, data, rounds, floor, min_cos):
    """Move every vertex-frame with sink > 0 down its smoothed anchor ray, no deeper than its floor,
    in place on p (T, N, 3) float64:

        r = normalise(A^rounds (seg / max(|seg|, 1e-12))),   A: the one-ring matrix with the diagonal
        depth = min(sink, max(seg . n - floor, 0) / max(r . n, min_cos)),   p <- p - depth r

    seg (T, N, 3), length (T, N) = |seg|, sink (T, N), normals (T, N, 3) the skin's at the anchors;
    A as CSR (indptr, indices, data). A frame without a sink is skipped."""
    T, N = p.shape[0], p.shape[1]
    r = np.empty((N, 3))
    y = np.empty((N, 3))
    for t in range(T):
        any_sink = False
        for v in range(N):
            if sink[t, v] > 0.0:
                any_sink = True
                break
        if not any_sink:
            continue
        for v in range(N):
            scale = max(length[t, v], 1e-12)
            for c in range(3):
                r[v, c] = seg[t, v, c] / scale
        for _ in range(rounds):
            for i in range(N):
                y0, y1, y2 = 0.0, 0.0, 0.0
                for jj in range(indptr[i], indptr[i + 1]):
                    j, d = indices[jj], data[jj]
                    y0 += d * r[j, 0]
                    y1 += d * r[j, 1]
                    y2 += d * r[j, 2]
                y[i, 0], y[i, 1], y[i, 2] = y0, y1, y2
            r, y = y, r
        for v in range(N):
            s = sink[t, v]
            if not s > 0.0:
                continue
            norm = max(np.sqrt(r[v, 0] * r[v, 0] + r[v, 1] * r[v, 1] + r[v, 2] * r[v, 2]), 1e-12)
            u0, u1, u2 = r[v, 0] / norm, r[v, 1] / norm, r[v, 2] / norm
            n0, n1, n2 = normals[t, v, 0], normals[t, v, 1], normals[t, v, 2]
            height = seg[t, v, 0] * n0 + seg[t, v, 1] * n1 + seg[t, v, 2] * n2
            cos = max(u0 * n0 + u1 * n1 + u2 * n2, min_cos)
            depth = min(s, max(height - floor, 0.0) / cos)
            p[t, v, 0] -= u0 * depth
            p[t, v, 1] -= u1 * depth
            p[t, v, 2] -= u2 * depth
