"""The guard's kernels: the plane push out of the candidates' tangent planes (blocks of frames,
coordinate-major arrays), its screening, the closest-triangle check after it and the per-frame
candidate search of the plan's dynamic points (the algorithm: ``inference.guard``).

Units: metres. Arrays: float32, batch axis first.
"""
from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from inference.errors import InputShapeError, InputValueError
from inference.guard import nearest, push_kernels
from inference.guard.constants import (
    DEFAULT_MARGIN_M,
    DYNAMIC_K,
    REFINE_CANDIDATES,
    REFINE_PASSES,
    _FARTHER_M,
    _OPPOSING_COS,
    _SQUEEZE_RADIUS_M,
    _TANGENT_M,
)

if TYPE_CHECKING:
    from inference.guard.plan import GuardPlan


def _check_frames(name: str, a: np.ndarray, ndim: int = 4) -> np.ndarray:
    a = np.asarray(a)
    if a.ndim != ndim or a.shape[-1] != 3:
        raise InputShapeError(name, "(B, T, n, 3)" if ndim == 4 else "(B, n, 3)", a.shape)
    if not np.issubdtype(a.dtype, np.floating):
        raise InputValueError(name, f"expected floating point coordinates, got {a.dtype}")
    return a


def _planes(a: np.ndarray) -> np.ndarray:
    """(B, T, n, 3) -> (3, B*T*n) float32 coordinate planes for flat ``np.take``."""
    return np.ascontiguousarray(np.moveaxis(np.asarray(a, np.float32), -1, 0)).reshape(3, -1)


def push_outside(
    points: np.ndarray,
    collider_points: np.ndarray,
    collider_normals: np.ndarray,
    candidates: np.ndarray,
    margin_m: float = DEFAULT_MARGIN_M,
    *,
    across: np.ndarray | None = None,
    max_push_m: float | None = None,
    collider_boundary: np.ndarray | None = None,
    boundary_reach_m: float = 0.0,
    iterations: int = 1,
) -> np.ndarray:
    """Push points out of a collider to ``margin_m`` along its normal at the closest candidate.

    Thesis ch. 4.2.1 postprocess, with the squeeze limit of the module docstring:
        c* = argmin_j |p - c_j|, s = (p - c*).n*, p' = p + min(max(margin - s, 0), cap) n*

    points            : (B, T, N, 3) float32, metres
    collider_points   : (B, T, M, 3) float32, metres (body or inner-garment vertices)
    collider_normals  : (B, T, M, 3) float32, unit outward normals at collider_points
    candidates        : (N, k) or (B, N, k) int, collider vertex indices per point
    margin_m          : clearance to reach, metres (>= 0)
    across            : optional (N, k) or (B, N, k) bool, candidates on another surface across
                        a gap (``GuardPlan.build``); they limit the push (squeeze limit)
    max_push_m        : optional cap on the push length, metres
    collider_boundary : optional (M,) bool, border vertices of an open collider: a point whose
                        closest candidate is a border vertex and whose tangential offset from it
                        exceeds ``boundary_reach_m`` is left alone
    iterations        : passes; each re-selects the closest candidate from the pushed point
    returns           : (B, T, N, 3) float32, metres
    """
    points = _check_frames("points", points)
    collider_points = _check_frames("collider_points", collider_points)
    collider_normals = _check_frames("collider_normals", collider_normals)
    B, T, N, _ = points.shape
    M = collider_points.shape[2]
    if collider_points.shape[:2] != (B, T):
        raise InputShapeError("collider_points", f"({B}, {T}, M, 3)", collider_points.shape)
    if collider_normals.shape != collider_points.shape:
        raise InputShapeError("collider_normals", str(collider_points.shape), collider_normals.shape)
    candidates = _check_candidates(candidates, B, N, M)
    if across is not None:
        across = np.asarray(across, bool)
        across = across[None] if across.ndim == 2 else across
        if across.shape[1:] != candidates.shape[1:] or across.shape[0] not in (1, B):
            raise InputShapeError("across", str(candidates.shape), across.shape)
    if collider_boundary is not None and np.shape(collider_boundary) != (M,):
        raise InputShapeError("collider_boundary", f"({M},)", np.shape(collider_boundary))
    P = _planes(points).reshape(3, B * T, N)
    out = _push_planes(
        P, _planes(collider_points), _planes(collider_normals), candidates, across, T, M, margin_m,
        max_push_m, collider_boundary, boundary_reach_m, iterations,
    )
    return np.moveaxis(out.reshape(3, B, T, N), 0, -1)


def _check_candidates(candidates: np.ndarray, B: int, N: int, M: int) -> np.ndarray:
    candidates = np.asarray(candidates)
    if candidates.ndim == 2:
        candidates = candidates[None]
    if candidates.ndim != 3 or candidates.shape[0] not in (1, B) or candidates.shape[1] != N:
        raise InputShapeError("candidates", f"({N}, k) or ({B}, {N}, k)", candidates.shape)
    if not np.issubdtype(candidates.dtype, np.integer) or (candidates.size and (candidates.min() < 0 or candidates.max() >= M)):
        raise InputValueError("candidates", f"expected integer indices in [0, {M})")
    return candidates


def _push_planes(
    P: np.ndarray,
    C: np.ndarray,
    Nrm: np.ndarray,
    candidates: np.ndarray,
    across: np.ndarray | None,
    T: int,
    M: int,
    margin_m: float,
    max_push_m: float | None,
    boundary: np.ndarray | None,
    reach_m: float,
    iterations: int,
    plan: GuardPlan | None = None,
    check: bool = True,
) -> np.ndarray:
    """``push_outside`` on coordinate planes: P (3, BT, N); C, Nrm (3, BT*M) frame-major;
    candidates, across (B|1, N, k); ``plan`` with dynamic points: their per-frame nearest
    candidates are added (``_dynamic_candidates``; never across); ``check``: then the
    closest-triangle check (``_refine_block``) where the plan has rings. Returns (3, BT, N) float32.

    Frames go through in blocks of about ``_BLOCK_ELEMENTS`` candidate entries (cache blocking:
    one (k, BT*N) block of 16 frames is ~2.5x slower per frame than blocks of 4, measured).
    Screening: a push is at most margin - s* (the caps only shorten it), so a point with
    s_j >= margin for every candidate j is never pushed; s_j = p . n_j - c_j . n_j over all
    candidates is cheap, and only the points it keeps (tolerance ``_screen_tolerance`` for its
    rounding) are pushed: the result is the same as pushing every point. Both run compiled in
    one pass over the points (``_push_block``).
    """
    if not margin_m >= 0:
        raise InputValueError("margin_m", f"expected >= 0, got {margin_m}")
    _, BT, N = P.shape
    k = candidates.shape[2]
    cand = np.ascontiguousarray(np.moveaxis(candidates, 2, 0), np.intp)  # (k, B|1, N), C order: each block's ids come out C-contiguous
    batch_of_frame = np.arange(BT) // T if cand.shape[1] > 1 else np.zeros(BT, np.intp)
    offset = C[0] * Nrm[0] + C[1] * Nrm[1] + C[2] * Nrm[2]  # o_j = c_j . n_j, (BT*M,)
    keep = margin_m + _screen_tolerance(P, C)
    dynamic = plan is not None and plan.dynamic_points is not None
    step = max(1, _BLOCK_ELEMENTS // max(N * (k + (DYNAMIC_K if dynamic else 0)), 1))
    out = np.empty((3, BT, N), np.float32)
    # the dynamic points' nearest region vertices in the last frame done; before the first frame,
    # their rest-pose nearest (the bound of the first frame's search: ``_warm_start``)
    prev = _warm_start(plan, int(min(DYNAMIC_K, len(plan.dynamic_region)))) if dynamic else None
    for f0 in range(0, BT, step):  # blocks of frames, not a loop per frame
        f1 = min(BT, f0 + step)
        Pb = P[:, f0:f1].reshape(3, -1)
        # flat[j, f, n] = (f0 + f) * M + candidates[b(f), n, j]: flat index into C and Nrm
        flat = ((np.arange(f0, f1, dtype=np.intp) * M)[None, :, None] + cand[:, batch_of_frame[f0:f1]]).reshape(k, -1)
        acr = None if across is None else np.moveaxis(across, 2, 0)[:, batch_of_frame[f0:f1] if across.shape[0] > 1 else np.zeros(f1 - f0, np.intp)].reshape(k, -1)
        extra = _dynamic_candidates(Pb, C, flat, plan, f0, f1, prev) if dynamic else np.zeros((0, flat.shape[1]), np.intp)
        # the screen and the push of the points it keeps, compiled (``push_kernels``)
        res, live = _push_block(Pb, C, Nrm, flat, acr, M, margin_m, max_push_m, boundary, reach_m, iterations,
                                extra=extra, offset=offset, keep=keep)
        if check and plan is not None and plan.ring is not None and REFINE_CANDIDATES > 0 and len(live):
            flat = np.concatenate([flat, extra], 0) if len(extra) else flat
            todo = live
            for _ in range(REFINE_PASSES):  # later passes: only the points the last one moved
                new = _refine_block(res[:, todo], C, Nrm, flat[:, todo], plan.ring, plan.ring_valence, M, margin_m)
                moved = np.flatnonzero((new != res[:, todo]).any(0))
                res[:, todo] = new
                todo = todo[moved]
                if len(todo) == 0:
                    break
        out[:, f0:f1] = res.reshape(3, f1 - f0, N)
    return out


# Candidate entries (k * frames * N) per block in ``_push_planes``: keeps ~20 arrays in L2.
_BLOCK_ELEMENTS = 160_000


def _screen_tolerance(P: np.ndarray, C: np.ndarray) -> float:
    """Rounding bound, metres, of the screening s_j = p . n_j - c_j . n_j against (p - c_j) . n_j
    in float32: a few ulp of the largest coordinate (|n_j| = 1), with a factor 10 to spare."""
    r = max(float(np.abs(P).max(initial=0.0)), float(np.abs(C).max(initial=0.0)))
    return 10 * 8 * float(np.finfo(np.float32).eps) * (1.0 + r)


def _push_block(P, C, Nrm, flat, across, M, margin_m, max_push_m, boundary, reach_m, iterations, *, extra=None, offset=None,
                keep=None):
    """The plane push of ``push_outside``'s formula on P (3, L): candidates flat (k, L) and extra
    (k2, L, never across) into C, Nrm (3, .), across (k, L); ``iterations`` passes, each point
    passing again only while it moves. With ``offset`` (c . n of every collider vertex) and
    ``keep``, only the points the screen keeps (``_push_planes``) are pushed. Compiled:
    ``inference.guard.push_kernels``. Returns ((3, L) float32, the kept points' positions)."""
    P = np.array(P, np.float32, order="C", copy=True)
    L = P.shape[1]
    flat = np.ascontiguousarray(flat, np.int64)
    extra = np.zeros((0, L), np.int64) if extra is None else np.ascontiguousarray(extra, np.int64)
    if offset is None:
        offset, keep = np.zeros(np.shape(C)[1], np.float32), np.inf
    live = np.empty(L, bool)
    push_kernels.push_points(
        P, np.ascontiguousarray(C, np.float32), np.ascontiguousarray(Nrm, np.float32), np.ascontiguousarray(offset, np.float32), flat,
        extra, np.zeros((0, 0), bool) if across is None else np.ascontiguousarray(across, bool), np.float32(keep), live, int(M),
        np.float32(margin_m), np.float32(np.inf if max_push_m is None else max_push_m),
        np.zeros(0, bool) if boundary is None else np.ascontiguousarray(boundary, bool), np.float32(reach_m**2), max(int(iterations), 1),
        np.float32(_TANGENT_M**2), np.float32(_FARTHER_M), np.float32(_OPPOSING_COS), np.float32(_SQUEEZE_RADIUS_M**2))
    return P, np.flatnonzero(live)


def _refine_block(P: np.ndarray, C: np.ndarray, Nrm: np.ndarray, flat: np.ndarray, ring: np.ndarray, valence: np.ndarray,
                  M: int, margin_m: float) -> np.ndarray:
    """Closest-triangle check of pushed points: P (3, L), flat (k, L) candidate indices into the
    frame-major planes C, Nrm (3, BT*M); ring (M, R, 2) one-ring triangles of the plan vertices
    and valence (M,) their counts (``GuardPlan.ring``, ``ring_valence``).

    The tangent plane of the nearest vertex misjudges points where the surface curves within a
    few millimetres (an elbow pit, the crease of an armpit). Among the one-ring triangles of the
    REFINE_CANDIDATES nearest candidates, the closest point q (``inference.triangles``) and the
    normal n_q interpolated from the corners' vertex normals (Phong) decide: a point with
    (p - q) . n_q < 0 is inside and moves to q + margin n_q; every other point stays. Compiled,
    point by point (``push_kernels.refine_points``; the numpy form it replaced, kept in
    ``tests/test_guard_push_kernel.py``, made ~30 (kr, R, L) temporaries: ~10 ms a frame of
    leggings + shorts, whose shorts run the check).
    Returns (3, L) float32.
    """
    kr = int(min(REFINE_CANDIDATES, flat.shape[0]))
    out = np.empty(P.shape, np.float32)
    push_kernels.refine_points(np.ascontiguousarray(P, np.float32), C, Nrm, np.ascontiguousarray(flat, np.int64),
                               np.ascontiguousarray(ring, np.int32), np.ascontiguousarray(valence, np.int32), int(M), kr,
                               np.float32(margin_m), out)
    return out


def _warm_start(plan: GuardPlan, k: int) -> np.ndarray:
    """(Nd, k) int64: for each dynamic point, the positions in its region of its k rest-pose nearest
    candidates (the plan's first k), or -1 where one of them is not in the region. Any k region
    vertices bound a point's k nearest in a frame (``inference.guard.nearest``: rho, the farthest
    of them there), and the rest-pose nearest usually stay near (the point's own part): the first
    frame of a request searches a small ball instead of shells of cells from nothing (a 1-frame
    T-shirt + jacket: the search 5.9 -> 2.8 ms, the rate of a warm frame)."""
    slot = np.full(len(plan.collider_ids), -1, np.int64)
    slot[plan.dynamic_region] = np.arange(len(plan.dynamic_region))
    prev = slot[plan.candidates[0][plan.dynamic_points, :k]]
    prev[(prev < 0).any(1)] = -1
    return np.ascontiguousarray(prev, np.int64)


def _dynamic_candidates(Pb: np.ndarray, C: np.ndarray, flat: np.ndarray, plan: GuardPlan, f0: int, f1: int,
                        prev: np.ndarray) -> np.ndarray:
    """Per-frame nearest candidates of frames f0..f1 (one block of ``_push_planes``): for the
    plan's dynamic points, the DYNAMIC_K nearest of its dynamic region in that frame (exact, a
    grid per frame bounded by each point's answer in the frame before: ``inference.guard.nearest``);
    every other point repeats its first plan candidate.

    Pb (3, L) the block's points (L = F * N), C (3, BT*S), flat (k, L) plan candidates; prev
    (Nd, k) int64 the dynamic points' answers in the frame before f0 (positions in the region,
    -1: none), updated to frame f1 - 1's; returns (DYNAMIC_K, L) flat indices into C.
    """
    S = len(plan.collider_ids)
    N = plan.candidates.shape[1]
    dyn, region = plan.dynamic_points, plan.dynamic_region
    k = prev.shape[1]
    C3 = C.reshape(3, -1, S)
    extra = np.repeat(flat[:1], k, axis=0)
    region, dyn = np.ascontiguousarray(region, np.int64), np.ascontiguousarray(dyn, np.int64)
    found = nearest.frames_knn(C3, region, np.ascontiguousarray(Pb, np.float64), dyn, N, f0, f1, k, nearest.CELL_M, nearest.COLD_RHO_M, prev)
    nearest.flat_candidates(found, region, dyn, N, f0, S, extra)
    return extra
