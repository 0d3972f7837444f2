"""Which query points have some point within a distance: an exact test, cheaper than a bounded
nearest query where many queries have none (such a query searches its whole ball).

A query first asks one point per cubic cell (its representative: every point of the cell lies
within the cell's diagonal D of it). A representative within the distance r settles the query;
none within r + D rules it out (the nearest point lies within D of its cell's representative);
only the queries in between ask every point. The answer is the bounded nearest query's of every
point (the same float64 distances, compared with r).

Units: metres. Arrays: (n, 3) float32 or float64 points.
"""
from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree


def first_per_cell(x: np.ndarray, cell_m: float) -> np.ndarray:
    """The index of the first row of x (n, 3) in each cubic cell of side cell_m, metres."""
    cell = np.floor(np.asarray(x) / cell_m).astype(np.int64)
    cell -= cell.min(0)
    span = cell.max(0) + 1
    if float(np.prod(span.astype(np.float64))) < 2.0**62:  # a 1-D key: np.unique(axis=0) is ~10x slower
        return np.unique((cell[:, 0] * span[1] + cell[:, 1]) * span[2] + cell[:, 2], return_index=True)[1]
    return np.unique(cell, axis=0, return_index=True)[1]


def within(points: np.ndarray, queries: np.ndarray, distance_m: float, cell_m: float, tree: cKDTree | None = None) -> np.ndarray:
    """(Q,) bool: some point lies nearer than ``distance_m`` to the query (module doc).

    points : (N, 3) ; queries : (Q, 3) ; cell_m : the representatives' cell, metres (smaller: more
    representatives, fewer queries left to ask every point) ; tree : a KD-tree of ``points``, if built
    """
    queries = np.asarray(queries)
    out = np.zeros(len(queries), bool)
    if not len(points) or not len(queries):
        return out
    representatives = np.asarray(points)[first_per_cell(points, cell_m)]
    bound = distance_m + cell_m * np.sqrt(3.0) + 1e-6
    d = cKDTree(representatives).query(queries, k=1, distance_upper_bound=bound)[0]
    out[:] = d < distance_m
    ask = np.flatnonzero(~out & (d <= bound))
    if len(ask):
        tree = tree if tree is not None else cKDTree(points)
        out[ask] = tree.query(queries[ask], k=1, distance_upper_bound=distance_m * (1 + 1e-6))[0] < distance_m
    return out
