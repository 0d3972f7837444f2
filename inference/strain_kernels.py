"""Compiled Jacobi iteration of the strain limit (``inference.strain``; numba, one thread).

The maths is ``inference.strain``'s module doc. Per frame and iteration, one pass over the edges
sums each active edge's correction into its two ends (float64 sums), one pass over the vertices
moves each by the mean of its corrections; a frame stops early once every edge is within
[min_ratio, max_ratio] of its rest length.

Units: metres. Arrays: float32 vertices and rest lengths, int64 edges.
"""
from __future__ import annotations

import numba
import numpy as np

_JIT = {"nogil": True, "cache": True, "fastmath": False}


@numba.njit(**_JIT)
def limit_in_place(X, edges, rest, min_ratio, max_ratio, iterations):
    """X (B, V, 3) float32, moved in place; edges (E, 2) int64; rest (E,) float32; a ratio of
    0 (min) or inf (max) leaves that side free."""
    B, V = X.shape[0], X.shape[1]
    E = edges.shape[0]
    move = np.zeros((V, 3), np.float64)
    count = np.zeros(V, np.int64)
    for b in range(B):
        for it in range(iterations):
            move[:] = 0.0
            count[:] = 0
            active = 0
            for e in range(E):
                i, j = edges[e, 0], edges[e, 1]
                d0 = np.float64(X[b, j, 0]) - X[b, i, 0]
                d1 = np.float64(X[b, j, 1]) - X[b, i, 1]
                d2 = np.float64(X[b, j, 2]) - X[b, i, 2]
                length = np.sqrt(d0 * d0 + d1 * d1 + d2 * d2)
                deficit = min_ratio * rest[e] - length
                if deficit <= 0.0:
                    deficit = min(max_ratio * rest[e] - length, 0.0)  # negative: an edge pulled in
                if deficit != 0.0 and length > 1e-9:
                    s = 0.5 * deficit / length
                    move[j, 0] += s * d0
                    move[j, 1] += s * d1
                    move[j, 2] += s * d2
                    move[i, 0] -= s * d0
                    move[i, 1] -= s * d1
                    move[i, 2] -= s * d2
                    count[i] += 1
                    count[j] += 1
                    active += 1
            if active == 0:
                break
            for v in range(V):
                if count[v] > 0:
                    for k in range(3):
                        X[b, v, k] = np.float32(X[b, v, k] + move[v, k] / count[v])
