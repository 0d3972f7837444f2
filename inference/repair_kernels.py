"""Compiled kernels of ``inference.repair`` (numba, no Python objects, one thread).

Units: metres. Arrays: float32 vertices, int64 ids.
"""
from __future__ import annotations

import numba
import numpy as np

_JIT = {"nogil": True, "cache": True, "fastmath": False}


@numba.njit(**_JIT)
def vertices_in_boxes(verts, frames, ids, lo, hi):
    """The vertices ``ids`` of frames ``frames`` inside each frame's box: verts (B, V, 3) float32;
    frames (nf,) int64; ids (S,) int64; lo, hi (nf, 3) float, the boxes. Returns (fi, si): the
    position in ``frames`` and in ``ids`` of each vertex inside, frame by frame, int64."""
    nf, S = frames.shape[0], ids.shape[0]
    fi = np.empty(nf * S, np.int64)
    si = np.empty(nf * S, np.int64)
    n = 0
    for a in range(nf):
        b = frames[a]
        l0, l1, l2, h0, h1, h2 = lo[a, 0], lo[a, 1], lo[a, 2], hi[a, 0], hi[a, 1], hi[a, 2]
        for s in range(S):
            v = ids[s]
            x, y, z = verts[b, v, 0], verts[b, v, 1], verts[b, v, 2]
            if l0 <= x <= h0 and l1 <= y <= h1 and l2 <= z <= h2:
                fi[n] = a
                si[n] = s
                n += 1
    return fi[:n].copy(), si[:n].copy()
