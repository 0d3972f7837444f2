"""Collision guard: push garment vertices out of the posed body (and out of inner garments).

Thesis ch. 4.2.1 ("Collision postprocessing"): after skinning, cloth vertices that collide
with the body are pushed "outside their closest body primitive". Here the primitive is the
closest collider vertex with its area-weighted normal (its tangent plane), and the vertex is
pushed along that normal to a margin outside:

    c* = argmin_j |p - c_j|         over the candidates j of p           (closest primitive)
    s  = (p - c*) . n*               signed distance to the tangent plane at c*, metres
    p' = p + max(margin - s, 0) n*   (no-op for vertices already beyond the margin)

For a convex patch the tangent plane at c* supports the surface, so |p' - surface| >= margin;
in concave creases one pass can leave a vertex a little short of the margin (``iterations``
repeats the pass, with a fresh closest candidate each time).

Cost: the closest collider vertex is searched among ``k`` candidates per garment vertex, chosen
once per request by a KD-tree in the rest pose (``GuardPlan``); a frame then costs a few
gathers over (N, k) and normals for the plan's collider vertices only. Flat 1-D ``np.take``
on coordinate planes (structure of arrays) is several times faster than gathering (., 3) rows.
Points that another body part can reach when a joint bends (skin-aware plans) also get their
posed nearest collider vertices in every frame, from a KD-tree over the collider vertices near
them in the rest pose plus, thinned, the farther ones a limb can bring in (a forearm against
the back); this per-frame search is most of the guard's cost, the closest-triangle check
below the second largest part (measured for a 5k-vertex T-shirt: ~4 and 3-4 ms per frame).

Self-intersecting bodies. Under LBS the posed body intersects itself (an upper arm sunk into
the torso); a garment vertex squeezed there cannot be outside both parts. The guard does not
push it through the other part. ``GuardPlan.build`` marks, in the rest pose (where the body does
not intersect itself), the candidates c_j that lie on another surface across a gap: normal
opposing the point's own surface (n_j . n_0 < -0.5), the point on their outer side
((p - c_j) . n_j > 0) and ahead of it ((c_j - p) . n_0 > 0); it also adds candidates found
``ahead_m`` along the normal so that such a surface is seen. Per frame, each marked candidate
limits the push to the balanced position where p is equally far from (or equally deep in) both
planes,

    s*(delta) = s* + delta,  s_j(delta) = s_j + (n* . n_j) delta
    delta_j  = (s_j - s*) / (1 - n* . n_j)        (s*(delta_j) = s_j(delta_j))
    delta    = min(max(margin - s*, 0), max(min_j delta_j, 0)),

so a point in a gap narrower than two margins stops half-way, and a point inside both parts
stays where it is (the deeper of its two penetrations never grows). The far side of a thin part
(a finger) is not marked: in the rest pose the point is inside its plane. Parts that are
farther than ``ahead_m`` apart in the rest pose (the arm and the torso) are not seen; a garment
vertex there is pushed out of its own part only (it was inside the other already: the metric's
self-intersection exclusion covers it). ``frames=`` adds candidates from posed key frames.

Closest-triangle check (closed colliders: the body). The nearest vertex's tangent plane
misjudges points where the surface bends within a few millimetres of them (an elbow pit, an
armpit crease, the side of a concave fold): measured on 01_01, most of the garment vertices the
plane push left inside the body were of this kind. After the push, every point that the
screening kept is checked against the one-ring triangles of its ``REFINE_CANDIDATES`` nearest
candidates: q = the closest point on those triangles (``inference.triangles``), n_q = the
vertex normals interpolated at q (Phong), and a point with (p - q) . n_q < 0 moves to
q + margin n_q / |n_q|; a second pass re-checks the points the first one moved (one that lands
inside a neighbouring part). The plan therefore holds the candidates' one-rings
(``GuardPlan.ring``) and their corners. Measured on 01_01 (docs/evaluation.md): 1.2-4.4x fewer
vertices left inside after the guard; what remains lies mostly in the body's own folds and
overlaps, where no local push can be right.

Layers (``guard_layers``): garments in layer order, innermost first; layer i is pushed out of
the body with margin ``body_margin_m + i * layer_gap_m`` and then out of every inner garment
j < i (already guarded) with margin ``layer_gap_m``, along the inner garment's outward
vertex normals. Open collider meshes (garments) have borders: a vertex whose closest collider
vertex lies on the border and which lies beyond it (tangential offset > the collider's median
edge length) is not pushed (it does not project onto the collider surface).

Units: metres. Arrays: float32, batch axis first.
"""
from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
from scipy.spatial import cKDTree

from inference.errors import InputShapeError, InputValueError
from inference.mesh import face_normals, major_components, vertex_face_incidence, vertex_normals
from inference.triangles import closest_barycentrics

# Default clearance between the body and the innermost garment (DESIGN.md §3: 2–4 mm).
DEFAULT_MARGIN_M = 0.002
# Default clearance between consecutive garment layers (the pipeline's and the API's default too).
DEFAULT_LAYER_GAP_M = 0.003
# Candidates per garment vertex: the posed closest body vertex is among the 8 rest-pose
# nearest ones for ~96-99 % of vertices on random poses (0.3 rad per bone, measured).
DEFAULT_CANDIDATES = 8
# A candidate across a gap opposes the point's own surface by more than 120°.
_OPPOSING_COS = -0.5
# Skin-aware plans: points closer than this (rest pose) to a part skinned to another bone get
# per-frame nearest candidates, searched among the collider vertices within DYNAMIC_REGION_M.
DYNAMIC_RISK_M = 0.30
DYNAMIC_REGION_M = 0.05
# ... and among the farther collider vertices within DYNAMIC_REACH_M (a forearm that swings
# against the back, a hand against the thigh), thinned to one per DYNAMIC_VOXEL_M cell. Measured
# on 01_01 (learned default, v2 models, every 16th frame, clean inside % after the guard):
# neutral T-shirt 0.192 -> 0.060, heaviest adult 1.12 -> 0.61, for +1.4-2 ms per garment-frame
# (docs/benchmarks.md, Serving: 3 cm cells keep most of that for a third of the cost).
DYNAMIC_REACH_M = 0.30
DYNAMIC_VOXEL_M = 0.02
# Per-frame nearest candidates per dynamic point.
DYNAMIC_K = 3
# Passes of the body guard (each re-picks the closest candidate: concave creases converge).
GUARD_ITERATIONS = 2
# Rest-pose candidates of a skin-aware plan (its per-frame search finds the posed nearest ones).
SKIN_PLAN_K = 4
# An across-the-gap candidate limits the push only while it is this close to the point, metres.
_SQUEEZE_RADIUS_M = 0.02
# A point behind the plane of a candidate within this tangential offset is inside that part ...
_TANGENT_M = 0.012
# ... if that candidate is at most this much farther than the nearest one, metres.
_FARTHER_M = 0.02
# Closed colliders: the one-ring triangles of this many nearest candidates decide, after the push,
# whether a point is still inside (``_refine_block``; 0 turns the check off).
REFINE_CANDIDATES = 3
# Passes of that check; each later one revisits only the points the previous one moved.
REFINE_PASSES = 2
# Extra candidates are looked up this far along the rest normal (the other side of a crease).
DEFAULT_AHEAD_M = 0.015
# Skin-aware plans look for the nearest collider vertices of another bone among this many nearest
# ones first (a KD-tree per bone only for the points where fewer than k_skin are there).
_SKIN_SCAN = 32


# ------------------------------------------------------------------------------ push
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
    candidates is cheap (``_screen_planes``), and only the points it keeps (tolerance
    ``_screen_tolerance`` for its rounding) go through ``_push_block``: the result is the same
    as pushing every point.
    """
    if not margin_m >= 0:
        raise InputValueError("margin_m", f"expected >= 0, got {margin_m}")
    _, BT, N = P.shape
    k = candidates.shape[2]
    cand = np.moveaxis(candidates, 2, 0).astype(np.intp)  # (k, B|1, N)
    batch_of_frame = np.arange(BT) // T if cand.shape[1] > 1 else np.zeros(BT, np.intp)
    offset = C[0] * Nrm[0] + C[1] * Nrm[1] + C[2] * Nrm[2]  # o_j = c_j . n_j, (BT*M,)
    keep = margin_m + _screen_tolerance(P, C)
    dynamic = plan is not None and plan.dynamic_points is not None
    step = max(1, _BLOCK_ELEMENTS // max(N * (k + (DYNAMIC_K if dynamic else 0)), 1))
    out = np.empty((3, BT, N), np.float32)
    for f0 in range(0, BT, step):  # blocks of frames, not a loop per frame
        f1 = min(BT, f0 + step)
        Pb = P[:, f0:f1].reshape(3, -1)
        # flat[j, f, n] = (f0 + f) * M + candidates[b(f), n, j]: flat index into C and Nrm
        flat = ((np.arange(f0, f1, dtype=np.intp) * M)[None, :, None] + cand[:, batch_of_frame[f0:f1]]).reshape(k, -1)
        acr = None if across is None else np.moveaxis(across, 2, 0)[:, batch_of_frame[f0:f1] if across.shape[0] > 1 else np.zeros(f1 - f0, np.intp)].reshape(k, -1)
        s_min = _screen_planes(Pb, Nrm, offset, flat)
        if dynamic:
            extra = _dynamic_candidates(Pb, C, flat, plan, f0, f1)
            flat = np.concatenate([flat, extra], 0)
            s_min = np.minimum(s_min, _screen_planes(Pb, Nrm, offset, extra))
            if acr is not None:
                acr = np.concatenate([acr, np.zeros(extra.shape, bool)], 0)
        live = np.flatnonzero(s_min < keep)
        res = Pb.copy()
        if len(live):
            res[:, live] = _push_block(
                Pb[:, live], C, Nrm, flat[:, live], None if acr is None else acr[:, live],
                M, margin_m, max_push_m, boundary, reach_m, iterations,
            )
            if check and plan is not None and plan.ring is not None and REFINE_CANDIDATES > 0:
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


def _screen_planes(P: np.ndarray, Nrm: np.ndarray, offset: np.ndarray, flat: np.ndarray) -> np.ndarray:
    """min_j s_j = min_j (p . n_j - o_j) per point: P (3, L), flat (k, L) into Nrm (3, .) and
    offset (.,) = c . n; returns (L,) float32. In-place arithmetic: no (k, L) temporaries."""
    s = np.take(offset, flat)
    np.negative(s, out=s)
    t = np.empty_like(s)
    for c in range(3):
        np.take(Nrm[c], flat, out=t)
        t *= P[c]
        s += t
    return s.min(axis=0)


def _push_block(P, C, Nrm, flat, across, M, margin_m, max_push_m, boundary, reach_m, iterations):
    """Screened points: P (3, L), flat (k, L) candidate indices into C, Nrm (3, .), across (k, L).

    Each pass after the first revisits only the points the previous one moved (the others are
    where they were, so a pass would decide the same for them again). Returns (3, L) float32.
    """
    P = P.astype(np.float32, copy=True)
    live = np.arange(P.shape[1])
    for _ in range(max(int(iterations), 1)):
        if len(live) == 0:
            break
        delta, na, moved = _push_pass(P[:, live], C, Nrm, flat[:, live], None if across is None else across[:, live],
                                      M, margin_m, max_push_m, boundary, reach_m)
        live = live[moved]
        for c in range(3):
            P[c, live] += delta * na[c]  # p' = p + delta n*
    return P


def _push_pass(P, C, Nrm, flat, across, M, margin_m, max_push_m, boundary, reach_m):
    """One pass over points P (3, L): returns the push lengths delta (A,) != 0 and directions
    n* (3 x (A,)) of the A points it moves, and their positions ``moved`` (A,) in L."""
    L = P.shape[1]
    G = [np.take(C[c], flat) for c in range(3)]  # (k, L) candidate coordinates
    rows = np.arange(L, dtype=np.intp)
    Gn = [np.take(Nrm[c], flat) for c in range(3)]  # (k, L) candidate normals n_j
    D = [P[c] - G[c] for c in range(3)]  # p - c_j
    d2 = D[0] * D[0] + D[1] * D[1] + D[2] * D[2]
    s_all = D[0] * Gn[0] + D[1] * Gn[1] + D[2] * Gn[2]  # s_j = (p - c_j) . n_j
    j = np.argmin(d2, axis=0)  # closest candidate c*
    # ... unless p lies behind the plane of a candidate it projects onto (tangential offset <
    # _TANGENT_M) that is not much farther (< _FARTHER_M more): then p is inside that part,
    # and the nearest vertex (outside an arm, say) misjudges it; take the deepest such plane.
    s_near = np.take_along_axis(s_all, j[None], 0)[0]
    dmin = np.sqrt(np.take_along_axis(d2, j[None], 0)[0])
    behind = (s_all < 0) & (d2 - s_all * s_all < _TANGENT_M**2) & (np.sqrt(d2) <= dmin + _FARTHER_M)
    deep = np.argmin(np.where(behind, s_all, np.inf), axis=0)
    j = np.where(behind.any(axis=0) & (np.take_along_axis(s_all, deep[None], 0)[0] < s_near), deep, j)
    pick = j * L + rows
    sel = np.take(flat, pick)
    ns = [np.take(Gn[c], pick) for c in range(3)]  # n*
    s = np.take(s_all, pick)  # s = (p - c*) . n*
    delta = margin_m - s
    act = np.flatnonzero(delta > 0)  # only these need a push
    delta, s_a = delta[act], s[act]
    na = [ns[c][act] for c in range(3)]
    Gna = [Gn[c][:, act] for c in range(3)]
    a = na[0] * Gna[0] + na[1] * Gna[1] + na[2] * Gna[2]  # n* . n_j
    s_j = s_all[:, act]
    # a surface ahead of p (in the push direction), facing it and close in this frame squeezes:
    # balanced push delta_j = (s_j - s*) / (1 - n*.n_j) (the module docstring)
    ahead = -(D[0][:, act] * na[0] + D[1][:, act] * na[1] + D[2][:, act] * na[2]) > 0
    if across is not None:
        ahead = ahead | across[:, act]
    opposing = ahead & (a < _OPPOSING_COS) & (d2[:, act] < _SQUEEZE_RADIUS_M**2)
    bal = np.where(opposing, (s_j - s_a) / np.maximum(1.0 - a, 1.0), np.inf).min(axis=0)
    delta = np.minimum(delta, np.maximum(bal, 0.0))
    if max_push_m is not None:
        delta = np.minimum(delta, max_push_m)
    if boundary is not None:
        tangential2 = d2[j[act], act] - s_a * s_a
        delta = np.where(boundary[sel[act] % M] & (tangential2 > reach_m**2), 0.0, delta)
    moved = delta != 0
    return delta[moved], [n[moved] for n in na], act[moved]


def _ring_closest(ap, centre, C, other):
    """Closest points on ring triangles (centre, b, c): ap = p - centre and centre (3 x arrays
    broadcasting against other[..., 0]), other (..., 2) flat ids of b and c into C (3, .).
    Returns barycentrics v, w and p - q (3 x arrays) of other[..., 0]'s shape."""
    corner = [np.take(C[c], other) for c in range(3)]
    ab = [corner[c][..., 0] - centre[c] for c in range(3)]
    ac = [corner[c][..., 1] - centre[c] for c in range(3)]
    v, w = closest_barycentrics(ap, ab, ac)
    return v, w, [ap[c] - v * ab[c] - w * ac[c] for c in range(3)]


# Ring slots computed for every selected vertex; rings with more triangles (valence 7-8: ~13 % of
# anny's vertices, most have 6) get the rest computed for them alone.
_RING_SLOTS = 6


def _refine_block(P: np.ndarray, C: np.ndarray, Nrm: np.ndarray, flat: np.ndarray, ring: np.ndarray, valence: np.ndarray,
                  M: int, margin_m: float) -> np.ndarray:
    """Closest-triangle check of pushed points: P (3, L), flat (k, L) candidate indices into the
    frame-major planes C, Nrm (3, BT*M); ring (M, R, 2) one-ring triangles of the plan vertices
    and valence (M,) their counts (``GuardPlan.ring``, ``ring_valence``).

    The tangent plane of the nearest vertex misjudges points where the surface curves within a
    few millimetres (an elbow pit, the crease of an armpit). Among the one-ring triangles of the
    REFINE_CANDIDATES nearest candidates, the closest point q (``inference.triangles``) and the
    normal n_q interpolated from the corners' vertex normals (Phong) decide: a point with
    (p - q) . n_q < 0 is inside and moves to q + margin n_q; every other point stays.
    Returns (3, L) float32.
    """
    k = flat.shape[0]
    kr = int(min(REFINE_CANDIDATES, k))
    G = [np.take(C[c], flat) for c in range(3)]
    d2 = (P[0] - G[0]) ** 2 + (P[1] - G[1]) ** 2 + (P[2] - G[2]) ** 2
    L = flat.shape[1]
    near = np.argpartition(d2, kr - 1, axis=0)[:kr] if kr < k else np.arange(k)[:, None].repeat(L, 1)
    sel = np.take_along_axis(flat, near, 0)  # (kr, L) flat ids f * M + s
    # the ring triangles (centre, b, c) of each selected vertex, laid out (kr, R, L)
    other = np.moveaxis(ring[sel % M], 2, 1) + (sel - sel % M)[:, None, :, None]  # (kr, R, L, 2) flat ids
    centre = [np.take(C[c], sel)[:, None] for c in range(3)]  # (kr, 1, L)
    ap = [P[c] - centre[c] for c in range(3)]
    R = other.shape[1]
    R0 = min(R, _RING_SLOTS)
    v, w, r = _ring_closest(ap, centre, C, other[:, :R0])  # the first R0 triangles of every ring
    if R > R0:
        # slots past a ring's valence repeat its first triangle (``_one_rings``): their results are
        # slot 0's, so only the rings with more than R0 triangles are computed there
        v, w = (np.concatenate([a, np.repeat(a[:, :1], R - R0, axis=1)], axis=1) for a in (v, w))
        r = [np.concatenate([a, np.repeat(a[:, :1], R - R0, axis=1)], axis=1) for a in r]
        j, col = np.nonzero(valence[sel % M] > R0)
        if len(j):
            sub = other[j, R0:, col]  # (E, R - R0, 2)
            cj = [np.take(C[c], sel[j, col])[:, None] for c in range(3)]
            vx, wx, rx = _ring_closest([P[c][col][:, None] - cj[c] for c in range(3)], cj, C, sub)
            v[j, R0:, col], w[j, R0:, col] = vx, wx
            for c in range(3):
                r[c][j, R0:, col] = rx[c]
    best = np.argmin((r[0] * r[0] + r[1] * r[1] + r[2] * r[2]).reshape(-1, L), axis=0)[None]
    pick = lambda a: np.take_along_axis(np.broadcast_to(a, v.shape).reshape(-1, L), best, 0)[0]  # noqa: E731
    vb, wb = pick(v), pick(w)
    ub = 1 - vb - wb
    rb = [pick(r[c]) for c in range(3)]  # p - q
    ids = [pick(sel[:, None]), pick(other[..., 0]), pick(other[..., 1])]
    n = [ub * np.take(Nrm[c], ids[0]) + vb * np.take(Nrm[c], ids[1]) + wb * np.take(Nrm[c], ids[2]) for c in range(3)]
    norm = np.sqrt(n[0] * n[0] + n[1] * n[1] + n[2] * n[2])
    inside = (rb[0] * n[0] + rb[1] * n[1] + rb[2] * n[2] < 0) & (norm > 0)
    out = P.copy()
    if inside.any():
        scale = margin_m / norm[inside]
        for c in range(3):  # q + margin n_q, q = p - (p - q)
            out[c, inside] = P[c, inside] - rb[c][inside] + scale * n[c][inside]
    return out


# ------------------------------------------------------------------------------ plan
def _gather(a: np.ndarray, idx: np.ndarray) -> np.ndarray:
    """a (B, M, 3), idx (B, N) -> (B, N, 3)."""
    return np.take_along_axis(a, idx[..., None], axis=1)


def boundary_vertices(faces: np.ndarray, num_vertices: int) -> np.ndarray:
    """(V,) bool: vertices on an edge used by a single face (the border of an open mesh)."""
    faces = np.asarray(faces, np.int64)
    e = np.sort(faces[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1)
    # edge (a, b), a < b, as one int64 key a * V + b: a 1-D unique (np.unique(axis=0) is ~10x slower)
    uniq, count = np.unique(e[:, 0] * num_vertices + e[:, 1], return_counts=True)
    single = uniq[count == 1]
    out = np.zeros(num_vertices, bool)
    out[single // num_vertices] = True
    out[single % num_vertices] = True
    return out


def _one_rings(tris: np.ndarray, S: int) -> tuple[np.ndarray, np.ndarray]:
    """(S, R, 2): the triangles around each vertex s < S, from triangles (n, 3) of local vertex
    ids, each rotated to (s, b, c) (same orientation) and stored as (b, c); a row repeats its
    first triangle up to R (the largest valence); a vertex on no triangle gets (s, s) (such
    vertices are never candidates: they only close the rings). Also the valences (S,)."""
    tris = np.asarray(tris, np.int64)
    vert = tris.ravel()
    corner = np.tile(np.arange(3), len(tris))
    tri = np.repeat(np.arange(len(tris)), 3)
    rest = np.stack([tris[tri, (corner + 1) % 3], tris[tri, (corner + 2) % 3]], axis=1)  # (3n, 2)
    order = np.argsort(vert, kind="stable")
    vert, rest = vert[order], rest[order]
    count = np.bincount(vert, minlength=S)
    first = np.cumsum(count) - count
    col = np.arange(len(vert)) - first[vert]
    table = np.repeat(np.arange(S)[:, None, None], 2, axis=2).repeat(max(int(count.max()), 1), axis=1)
    has = count > 0
    table[has] = rest[first[has]][:, None, :]
    table[vert, col] = rest
    return table.astype(np.int32), count.astype(np.int32)


@dataclass(frozen=True)
class GuardPlan:
    """Per-request precomputation for ``guard``: candidates and normal data of one collider.

    collider_ids   : (S,) int, the collider vertices any point may touch (the union of candidates)
    candidates     : (B, N, k) int, indices into ``collider_ids``
    across         : (B, N, k) bool, candidates on another surface across a gap (module doc)
    face_ids       : (Fs,) int, collider faces touching ``collider_ids`` (for their normals)
    incidence      : (S, Fs) CSR 0/1, vertex-face incidence of those
    faces          : (F, 3) int, the collider's faces
    orientation    : +1.0, or -1.0 when the collider's faces wind inwards (normals are flipped)
    boundary       : (S,) bool or None, border vertices of an open collider
    reach_m        : median collider edge length, metres (border tolerance)
    dynamic_points : (Nd,) int or None, points that get per-frame nearest candidates (skin-aware
                     plans: points within DYNAMIC_RISK_M of a part skinned to another bone)
    dynamic_region : (R,) int or None, indices into ``collider_ids`` searched for them per frame
    ring           : (S, R, 2) int or None, closed colliders: the triangles around each collider
                     vertex s (its one-ring, padded by repetition) as (s, b, c) counter-clockwise,
                     b and c indices into ``collider_ids``, for the closest-triangle check
    ring_valence   : (S,) int or None, the number of distinct triangles in each ring
    """

    collider_ids: np.ndarray
    candidates: np.ndarray
    across: np.ndarray
    face_ids: np.ndarray
    incidence: sp.csr_matrix
    faces: np.ndarray
    orientation: float
    boundary: np.ndarray | None
    reach_m: float
    dynamic_points: np.ndarray | None = None
    dynamic_region: np.ndarray | None = None
    ring: np.ndarray | None = None
    ring_valence: np.ndarray | None = None

    @classmethod
    def build(
        cls,
        points_rest: np.ndarray,
        collider_rest: np.ndarray,
        collider_faces: np.ndarray,
        k: int = DEFAULT_CANDIDATES,
        *,
        k_ahead: int = 2,
        ahead_m: float = DEFAULT_AHEAD_M,
        frames: tuple[np.ndarray, np.ndarray] | None = None,
        k_frames: int = 4,
        skin: tuple[np.ndarray, np.ndarray] | None = None,
        k_skin: int = 4,
        rings: bool = True,
    ) -> "GuardPlan":
        """Candidates: the k collider vertices nearest to each point in the reference pose, plus
        the k_ahead nearest to p + ahead_m n_0 (n_0: normal of the nearest vertex), plus the
        k_skin nearest skinned mostly to another bone than the point (when ``skin`` is given).

        Where the rest pose puts two parts side by side (a sleeve's armpit against the torso in
        the A-pose), the plain nearest candidates may all lie on the part the point is skinned
        to; when a joint bends, the other part comes against it (measured on 01_01: T-shirt
        vertices skinned to the arm sank into the torso unseen). The skin-aware candidates are
        the nearest collider vertices whose dominant bone differs from the point's.

        points_rest    : (B, N, 3) float32, metres, garment vertices in the rest pose
        collider_rest  : (B, M, 3) float32, metres, collider vertices in the same pose
        collider_faces : (F, 3) int
        k              : candidates per point from the rest pose
        k_ahead        : candidates per point from ahead_m (metres) along the rest normal
        frames         : optional (points (B, T', N, 3), collider (B, T', M, 3)) posed key frames;
                         each adds its ``k_frames`` nearest collider vertices per point
        skin           : optional (point weights (N, J), collider weights (M, J)) LBS weights
        rings          : closed colliders: also keep the candidates' one-ring triangles and
                         their corners (``ring``, for the closest-triangle check)
        """
        points_rest = _check_frames("points_rest", points_rest, 3)
        collider_rest = _check_frames("collider_rest", collider_rest, 3)
        B, N = points_rest.shape[:2]
        M = collider_rest.shape[1]
        if collider_rest.shape[0] != B:
            raise InputShapeError("collider_rest", f"({B}, M, 3)", collider_rest.shape)
        faces = np.asarray(collider_faces, np.int64)
        if faces.ndim != 2 or faces.shape[1] != 3 or faces.min() < 0 or faces.max() >= M:
            raise InputShapeError("collider_faces", f"(F, 3) indices < {M}", faces.shape)
        bnd = boundary_vertices(faces, M)
        # closed collider: only its major components (anny's eyes and teeth sit in the head and
        # are never the surface a garment rests on)
        usable = np.flatnonzero(major_components(faces, M)) if not bnd.any() else np.arange(M)
        k = int(min(k, len(usable)))
        trees = [cKDTree(collider_rest[b][usable]) for b in range(B)]
        near = np.stack([usable[trees[b].query(points_rest[b], k=k)[1].reshape(N, k)] for b in range(B)])
        n_rest = vertex_normals(collider_rest, faces)
        if bnd.any():
            # open collider (a garment): the points lie on its outer side in the reference pose
            side = np.einsum("bnc,bnc->bn", points_rest - _gather(collider_rest, near[..., 0]), _gather(n_rest, near[..., 0]))
            orientation = -1.0 if np.median(side) < 0 else 1.0
        else:
            # closed collider: outward iff the signed volume sum_f v0 . (v1 x v2) / 6 is positive
            tri = collider_rest[0].astype(np.float64)[faces]
            orientation = -1.0 if np.einsum("fc,fc->", tri[:, 0], np.cross(tri[:, 1], tri[:, 2])) < 0 else 1.0
        n_rest = n_rest * np.float32(orientation)
        parts = [near]
        n0 = _gather(n_rest, near[..., 0])  # (B, N, 3) the point's own surface normal
        if k_ahead > 0:
            q = points_rest + ahead_m * n0
            kk = int(min(k_ahead, len(usable)))
            parts.append(np.stack([usable[trees[b].query(q[b], k=kk)[1].reshape(N, kk)] for b in range(B)]))
        if skin is not None and k_skin > 0:
            # the nearest collider vertices skinned mostly to another bone than the point: the
            # parts that a bending joint can bring against it (arm vs torso at the armpit)
            pw, cw = (np.asarray(w, np.float32) for w in skin)
            if pw.shape[0] != N or cw.shape[0] != M or pw.shape[1] != cw.shape[1]:
                raise InputShapeError("skin", f"((N={N}, J), (M={M}, J))", (pw.shape, cw.shape))
            point_bone = np.argmax(pw, 1)
            collider_bone = np.argmax(cw[usable], 1)
            skin_part = np.empty((B, N, k_skin), np.int64)
            # the nearest _SKIN_SCAN collider vertices, in order, hold the k_skin nearest of another
            # bone for most points; the rest get a KD-tree per dominant bone (the exact search)
            kk = int(min(_SKIN_SCAN, len(usable)))
            for b in range(B):
                scan = trees[b].query(points_rest[b], k=kk)[1].reshape(N, kk)  # (N, kk) into usable
                other = collider_bone[scan] != point_bone[:, None]
                enough = other.sum(1) >= k_skin
                # first k_skin "other" columns of each row (stable sort puts them first, in order)
                first = np.argsort(~other, axis=1, kind="stable")[:, :k_skin]
                skin_part[b] = usable[np.take_along_axis(scan, first, 1)]
                for bone in np.unique(point_bone[~enough]):  # one KD-tree per dominant bone (<= J)
                    rows = np.flatnonzero((point_bone == bone) & ~enough)
                    others = usable[collider_bone != bone]
                    kb = int(min(k_skin, len(others)))
                    got = others[cKDTree(collider_rest[b][others]).query(points_rest[b][rows], k=kb)[1].reshape(len(rows), kb)]
                    skin_part[b, rows] = np.pad(got, ((0, 0), (0, k_skin - kb)), mode="edge")
            parts.append(skin_part)
            # Points that another part can reach when a joint bends: their rest-pose candidates
            # cannot follow that part (it moves relative to the point), so the guard searches
            # the region around them in every posed frame.
            d_other = np.linalg.norm(points_rest[0] - collider_rest[0][skin_part[0, :, 0]], axis=-1)
            dynamic_points = np.flatnonzero(d_other < DYNAMIC_RISK_M)
            # the usable collider vertices within DYNAMIC_REGION_M of a dynamic point (one nearest
            # query per collider vertex: ~5x faster than query_ball_point's lists, same set)
            region = np.zeros(0, np.int64)
            if len(dynamic_points):
                d, _ = cKDTree(points_rest[0][dynamic_points]).query(collider_rest[0][usable], k=1, distance_upper_bound=DYNAMIC_REACH_M)
                region = np.flatnonzero(d <= DYNAMIC_REGION_M)
                # farther parts that a limb can bring in (a forearm against the back): within
                # DYNAMIC_REACH_M, thinned to one vertex per DYNAMIC_VOXEL_M cell (fingers, head)
                far = np.flatnonzero((d > DYNAMIC_REGION_M) & (d <= DYNAMIC_REACH_M))
                if len(far) and DYNAMIC_VOXEL_M > 0:
                    cell = np.floor(collider_rest[0][usable[far]] / DYNAMIC_VOXEL_M).astype(np.int64)
                    far = far[np.unique(cell, axis=0, return_index=True)[1]]
                region = np.union1d(region, far)
            dynamic_region_ids = usable[region]
        else:
            dynamic_points, dynamic_region_ids = None, None
        if frames is not None:
            fp, fc = (_check_frames("frames[0]", frames[0]), _check_frames("frames[1]", frames[1]))
            kk = int(min(k_frames, len(usable)))
            parts += [
                np.stack([usable[cKDTree(fc[b, t][usable]).query(fp[b, t], k=kk)[1].reshape(N, kk)] for b in range(B)])
                for t in range(fp.shape[1])
            ]
        cand = np.concatenate(parts, axis=-1)  # (B, N, k_total) collider vertex ids
        extra_ids = dynamic_region_ids if dynamic_region_ids is not None else np.zeros(0, np.int64)
        # across a gap in the reference pose: opposing normal, point outside its plane, ahead
        cj = np.stack([collider_rest[b][cand[b]] for b in range(B)])  # (B, N, k, 3)
        nj = np.stack([n_rest[b][cand[b]] for b in range(B)])
        rel = points_rest[:, :, None] - cj  # p - c_j
        across = (
            (np.einsum("bnc,bnkc->bnk", n0, nj) < _OPPOSING_COS)
            & (np.einsum("bnkc,bnkc->bnk", rel, nj) > 0)
            & (np.einsum("bnkc,bnc->bnk", rel, n0) < 0)
        )
        touched = np.unique(np.concatenate([cand.ravel(), extra_ids]))
        ring_faces = None
        if rings and not bnd.any():
            # closed collider: the candidates' one-ring triangles, so their corners join the plan
            ring_faces, _ = vertex_face_incidence(faces, M, touched)
            touched = np.union1d(touched, faces[ring_faces].ravel())
        collider_ids = touched
        local = np.searchsorted(collider_ids, cand)
        face_ids, inc = vertex_face_incidence(faces, M, collider_ids)
        rings_table = None if ring_faces is None else _one_rings(np.searchsorted(collider_ids, faces[ring_faces]), len(collider_ids))
        e = collider_rest[0][faces[:, [0, 1, 2]]] - collider_rest[0][faces[:, [1, 2, 0]]]
        reach = float(np.median(np.linalg.norm(e, axis=-1)))
        has_dynamic = dynamic_points is not None and len(dynamic_points) > 0
        return cls(
            collider_ids=collider_ids,
            candidates=local.astype(np.int32),
            across=across,
            face_ids=face_ids,
            incidence=inc,
            faces=faces,
            orientation=orientation,
            boundary=bnd[collider_ids] if bnd.any() else None,
            reach_m=reach,
            dynamic_points=dynamic_points if has_dynamic else None,
            dynamic_region=np.searchsorted(collider_ids, dynamic_region_ids) if has_dynamic else None,
            ring=rings_table[0] if rings_table else None,
            ring_valence=rings_table[1] if rings_table else None,
        )

    def collider_planes(self, collider: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The plan's collider vertices and unit outward normals as coordinate planes.

        collider : (B, T, M, 3) float32, metres
        returns  : points (3, B*T*S), normals (3, B*T*S) float32, frame-major
        """
        collider = _check_frames("collider", collider)
        B, T, M, _ = collider.shape
        if self.faces.max() >= M:
            raise InputShapeError("collider", f"(B, T, >{self.faces.max()}, 3)", collider.shape)
        BT = B * T
        C = _planes(collider)  # (3, BT*M)
        frame = (np.arange(BT, dtype=np.intp) * M)[None, :]
        # corner[i][c]: coordinate c of corner i of the plan's faces, (Fs, BT)
        f = self.faces[self.face_ids]
        corner = [[np.take(C[c], f[:, i, None] + frame) for c in range(3)] for i in range(3)]
        e1 = [corner[1][c] - corner[0][c] for c in range(3)]
        e2 = [corner[2][c] - corner[0][c] for c in range(3)]
        # area-weighted face normals (v1 - v0) x (v2 - v0), laid out (Fs, 3, BT)
        fn = np.stack([e1[1] * e2[2] - e1[2] * e2[1], e1[2] * e2[0] - e1[0] * e2[2], e1[0] * e2[1] - e1[1] * e2[0]], axis=1)
        # n[s, c, bt] = sum_f incidence[s, f] fn[f, c, bt]
        vn = (self.incidence @ fn.reshape(len(f), 3 * BT)).reshape(-1, 3, BT)
        vn *= self.orientation / np.maximum(np.sqrt(np.einsum("scb,scb->sb", vn, vn)), 1e-20)[:, None]
        S = len(self.collider_ids)
        normals = np.ascontiguousarray(vn.transpose(1, 2, 0)).reshape(3, BT * S)
        points = np.take(C, (frame.T + self.collider_ids[None]).reshape(-1), axis=1)
        return points, normals.astype(np.float32, copy=False)

    def collider_frames(self, collider: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The plan's collider vertices and their area-weighted unit outward normals per frame.

        collider : (B, T, M, 3) float32, metres, posed collider vertices
        returns  : points (B, T, S, 3), normals (B, T, S, 3) float32
        """
        B, T = np.shape(collider)[:2]
        pts, nrm = self.collider_planes(collider)
        S = len(self.collider_ids)
        return (np.moveaxis(pts.reshape(3, B, T, S), 0, -1), np.moveaxis(nrm.reshape(3, B, T, S), 0, -1))


def guard(
    points: np.ndarray,
    collider: np.ndarray,
    plan: GuardPlan,
    margin_m: float = DEFAULT_MARGIN_M,
    *,
    max_push_m: float | None = None,
    iterations: int = 1,
    check: bool = True,
) -> np.ndarray:
    """Collision guard, thesis ch. 4.2.1: no point inside or within ``margin_m`` of the collider.

    points   : (B, T, N, 3) float32, metres, posed garment vertices
    collider : (B, T, M, 3) float32, metres, posed body (or inner garment) vertices
    plan     : ``GuardPlan.build`` of these points and this collider
    check    : the closest-triangle check after the push (closed colliders; module docstring)
    returns  : (B, T, N, 3) float32, metres (``push_outside`` on the plan's collider vertices)
    """
    points = _check_frames("points", points)
    B, T, N, _ = points.shape
    if N != plan.candidates.shape[1] or plan.candidates.shape[0] not in (1, B):
        raise InputShapeError("points", f"({plan.candidates.shape[0]}, T, {plan.candidates.shape[1]}, 3)", points.shape)
    if np.shape(collider)[:2] != (B, T):
        raise InputShapeError("collider", f"({B}, {T}, M, 3)", np.shape(collider))
    cp, cn = plan.collider_planes(collider)
    out = _push_planes(
        _planes(points).reshape(3, B * T, N), cp, cn, plan.candidates, plan.across, T, len(plan.collider_ids), margin_m,
        max_push_m, plan.boundary, plan.reach_m, iterations, plan, check,
    )
    return np.moveaxis(out.reshape(3, B, T, N), 0, -1)


def _dynamic_candidates(Pb: np.ndarray, C: np.ndarray, flat: np.ndarray, plan: GuardPlan, f0: int, f1: int) -> np.ndarray:
    """Per-frame nearest candidates of frames f0..f1 (one block of ``_push_planes``): for the
    plan's dynamic points, the DYNAMIC_K nearest of its dynamic region in that frame (a KD-tree
    per frame, C code; the region is a few thousand vertices); every other point repeats its
    first plan candidate.

    Pb (3, L) the block's points (L = F * N), C (3, BT*S), flat (k, L) plan candidates;
    returns (DYNAMIC_K, L) flat indices into C.
    """
    S = len(plan.collider_ids)
    N = plan.candidates.shape[1]
    dyn, region = plan.dynamic_points, plan.dynamic_region
    k = int(min(DYNAMIC_K, len(region)))
    C3 = C.reshape(3, -1, S)
    extra = np.repeat(flat[:1], k, axis=0)
    for i, f in enumerate(range(f0, f1)):  # a KD-tree per frame: the search itself runs in C
        tree = cKDTree(C3[:, f, region].T)
        col = i * N + dyn
        extra[:, col] = f * S + region[tree.query(Pb[:, col].T, k=k)[1].reshape(len(dyn), k)].T
    return extra


# ------------------------------------------------------------------------------ layers
@dataclass(frozen=True)
class LayerPlans:
    """Plans for a stack of garments, innermost first.

    body  : one ``GuardPlan`` per layer against the body
    inner : inner[i][j] is the plan of layer i against inner layer j < i
    """

    body: list[GuardPlan]
    inner: list[list[GuardPlan]]
    skin: np.ndarray | None = None  # (Vb,) bool: the body's major components (``inference.repair``)

    @classmethod
    def build(
        cls,
        layers_rest: Sequence[np.ndarray],
        layer_faces: Sequence[np.ndarray],
        body_rest: np.ndarray,
        body_faces: np.ndarray,
        k: int = DEFAULT_CANDIDATES,
        layer_weights: Sequence[np.ndarray] | None = None,
        body_weights: np.ndarray | None = None,
        rings: bool = True,
    ) -> "LayerPlans":
        """layers_rest : each (B, N_i, 3) rest garment vertices; layer_faces : each (F_i, 3);
        layer_weights / body_weights : optional LBS weights (N_i, J) / (Vb, J) for
        skinning-aware body candidates (GuardPlan.build's ``skin``); rings : the body plans keep
        the triangles of the closest-triangle check (not needed with ``guard_layers(check=False)``)."""
        if len(layers_rest) != len(layer_faces):
            raise InputValueError("layer_faces", f"expected {len(layers_rest)} face arrays, got {len(layer_faces)}")
        body = [
            GuardPlan.build(g, body_rest, body_faces, k if layer_weights is None else SKIN_PLAN_K,
                            skin=None if layer_weights is None else (layer_weights[i], body_weights), k_skin=2, rings=rings)
            for i, g in enumerate(layers_rest)
        ]
        inner = [[GuardPlan.build(layers_rest[i], layers_rest[j], layer_faces[j], k) for j in range(i)] for i in range(len(layers_rest))]
        return cls(body=body, inner=inner, skin=major_components(body_faces, np.shape(body_rest)[-2]))


def guard_layers(
    layers: Sequence[np.ndarray],
    body: np.ndarray,
    plans: LayerPlans,
    body_margin_m: float = DEFAULT_MARGIN_M,
    layer_gap_m: float = DEFAULT_LAYER_GAP_M,
    check: bool = True,
) -> list[np.ndarray]:
    """Guard a stack of garments, innermost first (see the module docstring).

    layer i: p_i <- guard(p_i, body, margin = body_margin_m + i * layer_gap_m)
             p_i <- guard(p_i, p_j, margin = layer_gap_m) for j = 0 .. i-1 (guarded p_j)
    layers : each (B, T, N_i, 3) float32, metres ; body : (B, T, Vb, 3) float32, metres
    check  : the closest-triangle check against the body (module docstring; 3-4 ms per
             garment-frame for 5k vertices)
    returns: list of (B, T, N_i, 3) float32
    """
    if len(layers) != len(plans.body):
        raise InputValueError("layers", f"expected {len(plans.body)} layers, got {len(layers)}")
    out: list[np.ndarray] = []
    for i, p in enumerate(layers):
        p = guard(p, body, plans.body[i], body_margin_m + i * layer_gap_m, iterations=GUARD_ITERATIONS, check=check)
        for j in range(i):
            p = guard(p, out[j], plans.inner[i][j], layer_gap_m)
        out.append(p)
    return out
