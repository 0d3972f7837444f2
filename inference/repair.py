"""Exact repair after the guard: no garment vertex left inside the posed body (DESIGN.md §5).

The guard (``inference.guard``) pushes each point out of its closest skin, judged locally (tangent
planes, then the one-rings of the nearest candidates). Where the LBS body intersects itself (a
fold of the skin at the shoulder, the elbow crease, an arm sunk into the torso), a point outside
its closest skin can still be inside another part, and no local push sees it. This stage tests
every point with the metric's own exact test, the ray-crossing winding number of the posed body
(``inference.winding``), and moves each point w(p) >= 1 to the nearest outside one of its
candidate targets, the K nearest posed skin vertices c_j offset along their vertex normals n_j:

    t_j = c_j + margin n_j,      p' = argmin { |t_j - p| : w(t_j) = 0 }

(a point with no outside target among them tries FAR_FACTOR times more candidates; one with
none there either stays where it is and is counted). The targets lie
on the outer surface of the union of the overlapping parts, so a point squeezed between an arm
and the torso goes around the arm: measured on 01_01 (docs/evaluation.md) these moves are a
few centimetres for a handful of vertices per frame, all in folds and creases.

Cost per frame, one thread (bench/bench_guard.py): the winding grid of the body (~5 ms, once per
block of frames), the count at the garment's vertices (~3 ms for 5k), and, for the frames with
points inside, a KD-tree of the posed skin and the count at the targets.

Units: metres. Arrays: float32, batch axis first.
"""
from __future__ import annotations

import logging

import numpy as np
from scipy.spatial import cKDTree

from inference.errors import InputShapeError
from inference.mesh import major_components, vertex_normals
from inference.winding import FRAME_BLOCK, WindingGrid

log = logging.getLogger(__name__)

# Candidate targets per point inside: the nearest posed skin vertices.
REPAIR_CANDIDATES = 32
# Points with no outside target among those try this many times more.
FAR_FACTOR = 16


def exact_repair(
    points: np.ndarray,
    body: np.ndarray,
    body_faces: np.ndarray,
    margin_m: float,
    *,
    skin: np.ndarray | None = None,
    k: int = REPAIR_CANDIDATES,
) -> tuple[np.ndarray, int]:
    """Move every point inside the body (winding number >= 1) to its nearest outside target.

    points       : (B, T, N, 3) float32, metres, guarded garment vertices
    body         : (B, T, V, 3) float32, metres, posed closed body
    body_faces   : (F, 3) int, all faces of the body (the inside test's surface)
    margin_m     : offset of the targets along the normal, metres
    skin         : (V,) bool, the vertices that hold targets; default the major components
                   (anny's skin, not its eyes and teeth)
    returns      : repaired points (B, T, N, 3) float32, number of points left inside
    """
    points = np.asarray(points)
    if points.ndim != 4 or points.shape[-1] != 3:
        raise InputShapeError("points", "(B, T, N, 3)", points.shape)
    if np.shape(body)[:2] != points.shape[:2]:
        raise InputShapeError("body", f"({points.shape[0]}, {points.shape[1]}, V, 3)", np.shape(body))
    B, T, N, _ = points.shape
    P = points.reshape(B * T, N, 3).copy()
    Bv = np.asarray(body).reshape(B * T, -1, 3)
    if skin is None:
        skin = major_components(body_faces, Bv.shape[1])
    skin_ids = np.flatnonzero(skin)
    skin_faces = np.asarray(body_faces)[skin[body_faces].all(1)]
    k = int(min(k, len(skin_ids)))
    left = 0
    for f0 in range(0, B * T, FRAME_BLOCK):
        sl = slice(f0, f0 + FRAME_BLOCK)
        grid = WindingGrid(Bv[sl], body_faces)
        Pb = P[sl]  # a view: the moves write into P
        frame, idx = np.nonzero(grid.count(Pb) > 0)
        if len(frame):
            ok = _move_outside(Pb, Bv[sl], grid, frame, idx, skin_ids, skin_faces, margin_m, k)
            if not ok.all():  # deep in an overlap: every near target is inside too; look farther
                ok = _move_outside(Pb, Bv[sl], grid, frame[~ok], idx[~ok], skin_ids, skin_faces, margin_m, min(FAR_FACTOR * k, len(skin_ids)))
            left += int((~ok).sum())
    if left:
        log.warning("exact repair: %d of %d point-frames left inside the body (no outside target among %d candidates)",
                    left, B * T * N, min(FAR_FACTOR * k, len(skin_ids)))
    return P.reshape(B, T, N, 3), left


def _move_outside(Pb, Bb, grid, frame, idx, skin_ids, skin_faces, margin_m, k) -> np.ndarray:
    """Move points (frame, idx) of the block Pb (in place) to their nearest outside target;
    returns (n,) bool, True where one was found."""
    frames = np.unique(frame)
    normals = vertex_normals(Bb[frames], skin_faces)  # only the frames with points inside
    targets = np.empty((len(frame), k, 3), np.float32)
    for i, f in enumerate(frames):  # a KD-tree per frame with points inside (C code)
        sel = np.flatnonzero(frame == f)
        skin = Bb[f, skin_ids]
        j = cKDTree(skin).query(Pb[f, idx[sel]], k=k)[1].reshape(len(sel), k)
        targets[sel] = skin[j] + margin_m * normals[i, skin_ids][j]
    # count the targets frame by frame in the block's grid: pad every frame to the longest
    per_frame = np.bincount(frame, minlength=grid.B)
    slot = np.arange(len(frame)) - np.repeat(np.cumsum(per_frame) - per_frame, per_frame)  # frame is sorted
    cols = slot[:, None] * k + np.arange(k)
    padded = np.zeros((grid.B, per_frame.max() * k, 3), np.float32)
    padded[frame[:, None], cols] = targets
    outside = grid.count(padded)[frame[:, None], cols] == 0
    dist = np.where(outside, np.linalg.norm(targets - Pb[frame, idx][:, None], axis=-1), np.inf)
    best = dist.argmin(1)
    ok = np.isfinite(dist[np.arange(len(best)), best])
    Pb[frame[ok], idx[ok]] = targets[np.flatnonzero(ok), best[ok]]
    return ok
