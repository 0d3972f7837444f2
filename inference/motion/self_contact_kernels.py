"""Compiled kernel of ``inference.motion.self_contact``: each arm point's nearest torso point
within a reach, per frame (numba, no Python objects, one thread).

Units: metres. Arrays: float32 points, float64 distances.
"""
from __future__ import annotations

import numba
import numpy as np

_JIT = {"nogil": True, "cache": True, "fastmath": False}


@numba.njit(**_JIT)
def nearest_within(torso, frames, arm, reach):
    """The nearest torso point of each arm point in its own frame, nearer than ``reach``.

    torso  : (T, m, 3) float32, the torso points of every frame
    frames : (A,) int64, the frame of each row of ``arm``
    arm    : (A, n, 3) float32, arm points
    returns (dist (A, n) float64: sqrt of the float64 sum of squared differences, inf where no
             torso point is nearer than reach; near (A, n) int64: its index, 0 where none)

    Per row, the frame's torso points within the box of its arm points widened by reach are binned
    into cubic cells of side reach (1 + 1e-6): a point nearer than reach lies in the 27 cells around
    an arm point's own (a coordinate apart by less than a cell's side, its cell index by at most
    one). Equal distances keep the lowest index.
    """
    A, n = arm.shape[0], arm.shape[1]
    m = torso.shape[1]
    dist = np.full((A, n), np.inf)
    near = np.zeros((A, n), np.int64)
    h = reach * (1.0 + 1e-6)
    r2 = reach * reach
    pts = np.empty((m, 3))
    sel = np.empty(m, np.int64)
    for a in range(A):
        b = frames[a]
        lo = np.full(3, np.inf)
        hi = np.full(3, -np.inf)
        for p in range(n):
            for c in range(3):
                x = np.float64(arm[a, p, c])
                lo[c] = min(lo[c], x)
                hi[c] = max(hi[c], x)
        for c in range(3):
            lo[c] -= h
            hi[c] += h
        k = 0
        for s in range(m):
            x, y, z = np.float64(torso[b, s, 0]), np.float64(torso[b, s, 1]), np.float64(torso[b, s, 2])
            if lo[0] <= x <= hi[0] and lo[1] <= y <= hi[1] and lo[2] <= z <= hi[2]:
                pts[k, 0], pts[k, 1], pts[k, 2] = x, y, z
                sel[k] = s
                k += 1
        if k == 0:
            continue
        d0 = int((hi[0] - lo[0]) / h) + 1
        d1 = int((hi[1] - lo[1]) / h) + 1
        d2 = int((hi[2] - lo[2]) / h) + 1
        start = np.zeros(d0 * d1 * d2 + 1, np.int64)
        cell_of = np.empty(k, np.int64)
        for r in range(k):
            ci = min(int((pts[r, 0] - lo[0]) / h), d0 - 1)
            cj = min(int((pts[r, 1] - lo[1]) / h), d1 - 1)
            ck = min(int((pts[r, 2] - lo[2]) / h), d2 - 1)
            cell_of[r] = (ci * d1 + cj) * d2 + ck
            start[cell_of[r] + 1] += 1
        for c in range(d0 * d1 * d2):
            start[c + 1] += start[c]
        fill = start[:-1].copy()
        members = np.empty(k, np.int64)
        for r in range(k):  # ascending r: each cell lists its points by increasing index
            members[fill[cell_of[r]]] = r
            fill[cell_of[r]] += 1
        for p in range(n):
            x, y, z = np.float64(arm[a, p, 0]), np.float64(arm[a, p, 1]), np.float64(arm[a, p, 2])
            ci = min(int((x - lo[0]) / h), d0 - 1)
            cj = min(int((y - lo[1]) / h), d1 - 1)
            ck = min(int((z - lo[2]) / h), d2 - 1)
            best, best_s = np.inf, -1
            for i in range(max(ci - 1, 0), min(ci + 1, d0 - 1) + 1):
                for j in range(max(cj - 1, 0), min(cj + 1, d1 - 1) + 1):
                    row = (i * d1 + j) * d2
                    for kk in range(max(ck - 1, 0), min(ck + 1, d2 - 1) + 1):
                        for t in range(start[row + kk], start[row + kk + 1]):
                            s = members[t]
                            dx, dy, dz = x - pts[s, 0], y - pts[s, 1], z - pts[s, 2]
                            d = dx * dx + dy * dy + dz * dz
                            if d < best or (d == best and sel[s] < sel[best_s]):
                                best, best_s = d, s
            if best_s >= 0 and best < r2 * (1.0 + 1e-9):
                d = np.sqrt(best)
                if d < reach:
                    dist[a, p] = d
                    near[a, p] = sel[best_s]
    return dist, near
