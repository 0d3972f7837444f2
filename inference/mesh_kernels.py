"""Compiled mesh kernels (numba, no Python objects, one thread): vertex normals at a few vertices
of many frames.

Units: metres. Arrays: float32 or float64 vertices, int64 ids.
"""
from __future__ import annotations

import numba
import numpy as np

_JIT = {"nogil": True, "cache": True, "fastmath": False}


@numba.njit(**_JIT)
def normals_at(x, faces, face_ids, slot, out):
    """Unit area-weighted vertex normals n_v = normalise(sum_{f ∋ v} (x1 - x0) x (x2 - x0)) of the
    vertices with slot[v] >= 0, every frame: x (T, V, 3) float; faces (F, 3) int64; face_ids: the
    faces touching those vertices (the others add nothing); slot (V,) int64, the row of each vertex
    in out (T, S, 3) float64 (overwritten; a vertex without area gets zeros)."""
    T, S = x.shape[0], out.shape[1]
    for t in range(T):
        out[t] = 0.0
        for q in range(face_ids.shape[0]):
            f = face_ids[q]
            i, j, k = faces[f, 0], faces[f, 1], faces[f, 2]
            ax, ay, az = np.float64(x[t, j, 0]) - x[t, i, 0], np.float64(x[t, j, 1]) - x[t, i, 1], np.float64(x[t, j, 2]) - x[t, i, 2]
            bx, by, bz = np.float64(x[t, k, 0]) - x[t, i, 0], np.float64(x[t, k, 1]) - x[t, i, 1], np.float64(x[t, k, 2]) - x[t, i, 2]
            nx, ny, nz = ay * bz - az * by, az * bx - ax * bz, ax * by - ay * bx
            for c in (i, j, k):
                s = slot[c]
                if s >= 0:
                    out[t, s, 0] += nx
                    out[t, s, 1] += ny
                    out[t, s, 2] += nz
        for s in range(S):
            length = (out[t, s, 0] ** 2 + out[t, s, 1] ** 2 + out[t, s, 2] ** 2) ** 0.5
            if length > 1e-20:
                for c in range(3):
                    out[t, s, c] /= length


@numba.njit(**_JIT)
def normal_points_down(x, faces, out):
    """out[t, v] = the area-weighted normal of vertex v points down y in frame t: the sign of
    sum_{f ∋ v} ((x1 - x0) x (x2 - x0))_y, the faces in ascending order as ``normals_at`` sums them
    (its normalisation keeps the sign), so the same answer as ``normals_at(...)[..., 1] < 0`` over
    every face and vertex, from the y component alone. x (T, V, 3) float; faces (F, 3) int64; out
    (T, V) bool (overwritten)."""
    T, V = x.shape[0], x.shape[1]
    ny = np.empty(V)
    for t in range(T):
        ny[:] = 0.0
        for f in range(faces.shape[0]):
            i, j, k = faces[f, 0], faces[f, 1], faces[f, 2]
            ax, az = np.float64(x[t, j, 0]) - x[t, i, 0], np.float64(x[t, j, 2]) - x[t, i, 2]
            bx, bz = np.float64(x[t, k, 0]) - x[t, i, 0], np.float64(x[t, k, 2]) - x[t, i, 2]
            n = az * bx - ax * bz
            ny[i] += n
            ny[j] += n
            ny[k] += n
        for v in range(V):
            out[t, v] = ny[v] < 0.0
