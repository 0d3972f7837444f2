"""Exact repair after the guard: no garment vertex left inside the posed body (DESIGN.md §5).

The guard (``inference.guard``) pushes each point out of its closest skin, judged locally (tangent
planes, then the one-rings of the nearest candidates). Where the LBS body intersects itself (a
fold of the skin at the shoulder, the elbow crease, an arm sunk into the torso), a point outside
its closest skin can still be inside another part, and no local push sees it. This stage tests
every point with the metric's own exact test, the ray-crossing winding number of the posed body
(``inference.winding``), and moves each point w(p) >= 1 to the nearest outside one of its
candidate targets, from the K nearest posed skin vertices c_j and their vertex normals n_j: the
point pushed along n_j to ``margin`` outside c_j's tangent plane, and c_j itself offset by it,

    t_j = p + ((c_j - p) . n_j + margin) n_j,   t'_j = c_j + margin n_j,
    p' = argmin { |t - p| : t in {t_j, t'_j}, w(t) = 0 }

The plane targets move neighbouring points to neighbouring places (a run of points inside a
hip or a flank stays a smooth sheet); the vertex targets alone snapped neighbours onto one
point (edges of zero length: the canonical jacket on a wide-hipped body lost 1.5 % of its edges
below half their rest length to it, 02_07 light-tall). The vertex targets stay for points whose
plane targets are all inside (a fold between two parts).

Clearance: a point on the skin, or a fraction of a millimetre off it, leaves the skin's bulges
free to cross the cloth's triangles between the points (under the chest and on the upper arm of a
heavy body, the renders show the skin through the cloth). So the outermost layer's test (a single
garment's; ``repair_layers`` says why not the layers under it) is against the body
inflated by CLEARANCE_M along its vertex normals (``inference.winding.inflated``), or the body
itself, whichever holds the point ("either": in a crease the inflated copy need not hold the
body), in one grid binned over both; the targets lie at least CLEARANCE_SLACK_M beyond the
clearance. A point outside the body whose nearest free target is more than BAND_MOVE_M beyond
its offset (in the gap between an arm and the torso) stays where it is: only points inside the
body must move, whatever the distance. On the validation walk (02_02, 20 frames; ``python
tools/skin_through.py``), the learned canonical T-shirt's crossing pairs on visible body faces
fall from 29 / 277 / 298 per frame (neutral / heaviest / light-tall) to 10 / 53 / 54, where the
retarget baseline has 31 / 39 / 46; 2-9 % of the vertices move, p99 1.6-3.4 mm.

Layers: in an outfit the layer stage (``inference.layers``) has put each inner layer under the
outer ones, along the segments from its vertices' body anchors; a point of an inner layer that is
inside the body and moves out can end beyond the outer layer again (where a sleeve is squeezed
onto the flank). With the layers' anchors and faces (``LayerOrder``), the layers are repaired from
the outside in, and an inner point takes its nearest outside target whose anchor segment crosses
no outer layer; where none of its candidates does, its nearest outside one (the body comes
first). On the validation walk (02_02) this takes the crop top beyond the shirt (crop top, shirt,
jacket) from 0.224 to 0.204 % of its vertex-frames on the neutral body, 0.079 to 0.059 % on the
heaviest. What was left came from the outer layers' own moves in this stage: an outer point inside
the body goes out to the skin, and its faces then cross the anchor segments of inner points that
the layer stage had put under them (every crop top vertex-frame beyond the shirt on the validation
walk and its bodies was of this kind). So before an inner layer's test, its points whose segment
now crosses a face that this stage moved go back along the segment under it, as the layer stage
does (``_sink_under_moved``), where that place is outside the body and no farther than the face
moved: the crop top beyond the shirt 0.07 -> 0.02 % (heaviest), 0.16 -> 0.02 % (val-near).

Over time: each frame's nearest way out is chosen alone, so deep in a limb a point can flip from
one side to the other between frames; a point keeps the side it had where that costs at most
HOLD_M more (``_hold_sides``; within a motion, across a long request's chunks).

Between neighbours: each point's nearest way out is chosen alone too, so where two body parts
overlap (an arm sunk into the flank, a heavy body's thighs) neighbouring points can leave on
opposite sides and the edge between them stretches across the part (4-9 cm on the validation
walk). Before the hold, a moved point at an edge stretched by more than KEEP_STRETCH_M takes the
free target (or neighbour's place) nearest to where its mesh neighbours would carry it, if that
costs at most KEEP_M more (``_keep_together``). On the validation walk (02_02, 75 frames, five
bodies, every garment and four outfits) the torn edge-frames (both ends moved, the edge 1 cm and
3x longer than it came) fall by 38 %, the frame-to-frame jumps by 11 % (docs/benchmarks.md,
session 45).

(a point with no outside target among them tries FAR_FACTOR times more candidates; one with
none there either stays where it is, is counted and logged). The targets lie on the outer surface
of the union of the overlapping parts, so a point squeezed between an arm and the torso goes
around the arm. On the validation clip CMU 02_02 (75 frames; `python tools/repair_validation.py`:
the T-shirt after the guard's check, neutral and heaviest adult) it moves 7.2-7.6 points per
frame, median 9.5-9.9 mm, at most 35.5 mm (vertex targets alone: median 12-15 mm), and leaves
none inside. The pipeline runs it
last, after the guard and the layers' pushes, on every layer with that layer's body margin.

Cost per frame, one thread (``python bench/bench_canonical.py``, the learned T-shirt on the heavy
body, ~400 points within the clearance per frame; session 37): the winding grid of the body over
the garments' region (REGION_M; ~0.8 ms, once per block of frames, shared by the layers, with the
inflated copy ~0.2 ms), the count at the garment's 5,148 vertices (~1.1 ms), and for the points
within the clearance their nearest skin vertices (a grid per frame, ~0.4 ms), their targets
(~0.5 ms) and the count at them (~0.7 ms): ~4.2 ms in all (bench tables in docs/benchmarks.md;
session 42's machine, ~1.5x slower: the grid 1.1, the count 1.1, ~4.0 ms in all; the targets are
one compiled pass since session 43, ``repair_kernels.skin_targets``, ~0.1 ms a frame).

Units: metres. Arrays: float32, batch axis first.
"""
from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
from scipy.spatial import cKDTree

from inference import mesh_kernels
from inference import repair_kernels as kernels
from inference.errors import InputShapeError
from inference.guard.constants import DEFAULT_LAYER_GAP_M
from inference.intersections import CELL_EDGES, first_crossings
from inference.layers import ON_SKIN_M, LayerFrames
from inference.mesh import _vertex_faces, faces_around, major_components, mesh_edges, per_array
from inference.winding import FRAME_BLOCK, WindingGrid, inflated, ray_down
from inference.winding_kernels import median_edge

log = logging.getLogger(__name__)

# Candidate targets per point inside: the nearest posed skin vertices. On 02_02 (above) every
# point found an outside target among its 8 nearest, and 8, 16, 32 or 64 gave the same moves at
# the same cost (the winding grid dominates: 10-15 ms per garment-frame); 32 is headroom for
# overlaps deeper than a walk makes.
REPAIR_CANDIDATES = 32
# The first pass asks only this many, the nearest (most points, and every one within the
# clearance, find theirs there); a point with no outside target among them asks REPAIR_CANDIDATES.
NEAR_CANDIDATES = 8
# Points with no outside target among those try this many times more (not needed on 02_02).
FAR_FACTOR = 16
# An inner layer's point with no target under the outer layers among its REPAIR_CANDIDATES looks
# among its far ones for one no farther than this, before it takes its nearest outside one of them:
# a farther one tore the cloth (in 48 random service requests, 6 of the 8 vertex-frames it changes
# have a shorter longest edge, 8-9 -> 3-4 cm, 2 a longer one, 3.5-4.9 -> 4.4-5.8 cm), and walking
# all 1,024 far targets in rounds was the slowest 1-frame T-shirt + jacket requests' costliest
# step (~4.4 ms of ~59; ~1 ms bounded). The validation layer metrics (tools/outfit_layers.py) do
# not change at 5 cm, nor with no far look at all, which changes 207 vertex-frames against 8.
FAR_ACCEPT_M = 0.05
# Half-width added around a frame's points inside for the skin vertices of their local grid
# (_posed_targets): the 32nd nearest skin vertex of a point inside the T-shirt's posed body lies
# 4.9 cm away (median; p99 8.5 cm, 30 frames of the heavy body on 02_02).
NEAR_BOX_M = 0.1
# ... and for the far look (more than REPAIR_CANDIDATES): the 512th nearest skin vertex of a point
# lies farther than NEAR_BOX_M (none of 304 far points of 120 1-frame crop top + shirt + jacket
# requests found its 512 there, each asking a KD-tree of its frame's whole skin, ~3.7 ms to
# build), within 0.2 m for 303 of them (0.8 ms a call).
FAR_BOX_M = 0.2
# ... in cells of this side (~25 skin vertices each), and a point's search stops at FAR_BOX_M: where
# a body folds onto itself (a light, tall body bending forward on CMU 02_06, its belly in its
# thighs), ~175 T-shirt points a frame ask their 512 nearest from deep in the overlap, and reading
# 2 cm cells out to the whole box cost ~0.4 ms a point (T-shirt + jacket: 195 -> 135 ms a frame,
# 0.04 and 0.1 m within 7 % of 0.06; ``repair_kernels.MANY_K`` then cut the search itself)
FAR_CELL_M = 0.06
# Cell side of the grid of a frame's nearby skin vertices (``repair_kernels.frame_knn``): about two
# vertex spacings of the anny body, so that a point's 8 nearest lie in its own and the next cells.
KNN_CELL_M = 0.02
# The points tested are those inside the body inflated by CLEARANCE_M (module doc): a point on the
# skin leaves the skin's bulges free to cross its triangles. They move at least CLEARANCE_SLACK_M
# beyond it, so that their targets are not on the inflated surface.
CLEARANCE_M = 0.002
CLEARANCE_SLACK_M = 0.001
# A point within the clearance but outside the body moves at most this much beyond its target
# offset; farther targets (around an arm that presses on the torso) leave it where it is.
BAND_MOVE_M = 0.003
# The winding grid bins only the body faces over the garments' points widened by this much (in
# the grid's x-z plane; ``inference.winding.WindingGrid``'s region): 45 % of the body's faces over a
# block of T-shirt frames (71 % at 10 cm).
# A target beyond it (a point at the garment's edge whose free skin lies farther out) is answered
# by a grid of the whole body in its frame. 3 against 10 cm: the block's grid 1.51 -> 1.08 ms a
# frame (T-shirt, `dance`); the whole body's grid was needed in 6 of ~2,000 frames of a BVH crouch
# sweep (1 at 10 cm), in none of 68 service requests (seven garments and outfits, random bodies).
REGION_M = 0.03
# Targets tested per point in the first round, nearest first, where an outer layer must accept
# them (an inner layer's points; the others take ``WindingGrid.first_outside``, one at a time,
# compiled); each further round tests twice as many as the one before, so that a point deep under
# both layers, with no accepted target among its 8 or 32 nearest, walks its 512 far candidates in at
# most 8 rounds of two calls each, not 128 (the slowest 1-frame T-shirt + jacket requests: ~30 ms in
# this stage, against 60-106 in rounds of 4; most take 10).
ROUND = 4
# A point this stage moves farther than HOLD_FROM_M in two consecutive frames of a motion, the
# second time against the first (to the other side of a limb), keeps the first side where a
# free target there is at most HOLD_M farther than its nearest (``_hold_sides``). Chosen on the
# validation walk against 0.5 and 2 cm (docs/benchmarks.md, session 41).
HOLD_FROM_M = 0.005
HOLD_M = 0.01
# ... and only where the flip would move it this much between the frames (smaller ones are no pop).
HOLD_JUMP_M = 0.02
# Two neighbouring points of a garment that this stage moves to opposite sides of a body part (moves
# against each other as ``_flips`` judges two frames' moves) tear the cloth between them; the
# smaller patch of agreeing moves takes the larger one's side where every one of its points has a
# free target there at most KEEP_M farther than the one it took (``_keep_together``).
KEEP_M = 0.02
KEEP_PASSES = 3
KEEP_STRETCH_M = 0.01
# ... where it lies this much from where its neighbours would carry it
KEEP_OFF_M = 0.01
# ... among the targets of its KEEP_CANDIDATES nearest skin vertices
KEEP_CANDIDATES = 32
# A point asked once is asked again only where its d_i moved this much since.
KEEP_ASKED_M = 0.001
# Refused choices an inner layer's point may strike off before it stays where it is.
KEEP_CONSENTS = 4


def exact_repair(
    points: np.ndarray,
    body: np.ndarray,
    body_faces: np.ndarray,
    margin_m: float,
    *,
    skin: np.ndarray | None = None,
    k: int = REPAIR_CANDIDATES,
    clearance_m: float | None = None,
) -> tuple[np.ndarray, int]:
    """Move every point inside the body (winding number >= 1), or within ``clearance_m`` of it
    (``repair_layers``), to its nearest outside target.

    points       : (B, T, N, 3) float32, metres, guarded garment vertices
    body         : (B, T, V, 3) float32, metres, posed closed body
    body_faces   : (F, 3) int, all faces of the body (the inside test's surface)
    margin_m     : offset of the targets along the normal, metres
    skin         : (V,) bool, the vertices that hold targets; default the major components
                   (anny's skin, not its eyes and teeth)
    returns      : repaired points (B, T, N, 3) float32, number of points left inside
    """
    out, left = repair_layers([points], body, body_faces, [margin_m], skin=skin, k=k, clearance_m=clearance_m)
    return out[0], left


def repair_layers(
    layers: Sequence[np.ndarray],
    body: np.ndarray,
    body_faces: np.ndarray,
    margins_m: Sequence[float],
    *,
    skin: np.ndarray | None = None,
    k: int = REPAIR_CANDIDATES,
    clearance_m: float | None = None,
    order: LayerOrder | None = None,
    faces: Sequence[np.ndarray] | None = None,
    segments: Sequence[int] | None = None,
    moves_before: Sequence[np.ndarray | None] | None = None,
) -> tuple[list[np.ndarray], int]:
    """``exact_repair`` of several garments on one body, sharing its winding grid per block of
    frames: layers each (B, T, N_i, 3), margins_m one per layer; returns the repaired layers and
    the number of point-frames left inside.

    order: the layers' body anchors and faces (``LayerOrder``), for an outfit whose layer stage
    has put each inner layer under the outer ones: the layers are then repaired from the outside
    in, and an inner point takes its nearest outside target whose anchor segment crosses no outer
    layer, if any of its candidates is one (of its far candidates, one within FAR_ACCEPT_M; else
    its nearest outside target: the body first).

    clearance_m: the outermost layer's test runs against the body inflated by this much along
    its vertex normals, so its points closer to the skin than it move too (default CLEARANCE_M; 0
    tests the body itself); its targets lie at least CLEARANCE_SLACK_M beyond it. The layers under
    it keep the body's own test: lifted by the clearance, an inner layer would cross an outer one
    that lies closer to the skin than that (T-shirt under jacket on the heavy body, dance clip:
    0.64 % of the T-shirt's vertices beyond the jacket against 0.23 %).

    faces: each layer's faces (F_i, 3), outward: a point's inside test then casts its ray along
    -y where its normal points down y (``inference.winding.ray_down``; the same answers, fewer
    faces to test); a target's ray follows its move.

    segments: frame counts of the motions concatenated along T (each batch item's; default one):
    a point keeps its side of a limb from one frame to the next of a motion (``_hold_sides``),
    never across two. moves_before: per layer, each point's move in this stage in the frame
    before the first (N_i, 3) (a motion draped in chunks: the chunk before's last frame; None:
    the first frame starts the motion)."""
    layers = [np.asarray(p) for p in layers]
    Bv = np.asarray(body)
    for p in layers:
        if p.ndim != 4 or p.shape[-1] != 3:
            raise InputShapeError("points", "(B, T, N, 3)", p.shape)
        if Bv.shape[:2] != p.shape[:2]:
            raise InputShapeError("body", f"({p.shape[0]}, {p.shape[1]}, V, 3)", Bv.shape)
    if len(margins_m) != len(layers):
        raise InputShapeError("margins_m", f"({len(layers)},)", (len(margins_m),))
    if not layers:
        return [], 0
    B, T = Bv.shape[:2]
    Bv = Bv.reshape(B * T, -1, 3)
    if skin is None:
        skin, skin_ids, skin_faces = _skin(body_faces, Bv.shape[1])
    else:
        skin_ids, skin_faces = _masked_skin(body_faces, np.asarray(skin, bool).tobytes())
    k = int(min(k, len(skin_ids)))
    if clearance_m is None:
        clearance_m = CLEARANCE_M
    cleared = [clearance_m > 0.0 and i == len(layers) - 1 for i in range(len(layers))]
    offsets = [max(m, clearance_m + CLEARANCE_SLACK_M) if c else m for m, c in zip(margins_m, cleared)]
    # the winding test per layer in the block's grid (below): the inflated copy or the body
    meshes = ["either" if c else ("second" if clearance_m > 0.0 else "first") for c in cleared]
    far = int(min(FAR_FACTOR * k, len(skin_ids)))
    out = [p.reshape(B * T, p.shape[2], 3).copy() for p in layers]
    if order is not None and (len(order.anchors) != len(layers) or len(order.faces) != len(layers)):
        raise InputShapeError("order", f"anchors and faces of {len(layers)} layers", (len(order.anchors), len(order.faces)))
    if faces is not None and len(faces) != len(layers):
        raise InputShapeError("faces", f"faces of {len(layers)} layers", (len(faces),))
    segments = [T] if segments is None else [int(n) for n in segments]
    if min(segments, default=0) < 1 or sum(segments) != T:
        raise InputShapeError("segments", f"positive frame counts summing to {T}", tuple(segments))
    starts = np.zeros((B, T), bool)  # the frames that start a motion
    starts[:, np.cumsum([0, *segments[:-1]])] = True
    starts = starts.ravel()
    if moves_before is not None:
        if len(moves_before) != len(layers):
            raise InputShapeError("moves_before", f"{len(layers)} layers", (len(moves_before),))
        starts[0] = False  # the motion goes on from the frame before
    # per layer: each point's move in the frame before the block (``_hold_sides``)
    carry = ([None] * len(out) if moves_before is None
             else [None if m is None else np.asarray(m, np.float32).reshape(o.shape[1], 3) for m, o in zip(moves_before, out)])
    left = 0
    for f0 in range(0, B * T, FRAME_BLOCK):
        sl = slice(f0, f0 + FRAME_BLOCK)
        # inside the body or its inflated copy ("either": where a crease of the skin folds the
        # copy's normals across each other, it need not hold the body); one grid for both
        region = _region([o[sl] for o in out])
        grid = (WindingGrid(inflated(Bv[sl], body_faces, clearance_m), body_faces, second=Bv[sl], region=region)
                if clearance_m > 0.0 else WindingGrid(Bv[sl], body_faces, region=region))
        before = [o[sl].copy() for o in out]  # the layers as they came to this stage
        trees: dict[int, cKDTree] = {}  # the posed skin's KD-tree per frame, built once for every layer
        for i in range(len(out) - 1, -1, -1):  # outside in: an inner layer's targets see the outer layers' final places
            Pb = out[i][sl]  # a view: the moves write into out[i]
            mesh = meshes[i]
            if order is not None:
                for j in range(i + 1, len(out)):  # under the outer layers' moves of this stage
                    _sink_under_moved(Pb, Bv[sl], body_faces, order, i, j, before[j], out[j][sl], margins_m[i],
                                      room=lambda t, q, mesh=meshes[i]: grid.count_at(q, np.full(len(q), t), mesh) == 0)
            down = None if faces is None else ray_down(Pb, faces[i])
            tested = grid.count(Pb, mesh, down) > 0
            if order is not None:
                # on its skin vertex (the layer stage's half-way under an outer layer that crosses
                # at the anchor): on the surface, where a ray's inside test is a tie, so it moves too
                Bb = np.ascontiguousarray(Bv[sl])  # compiled: |p - b_anchor|^2 in the arrays' precision, as numpy's einsum
                kernels.on_skin(np.ascontiguousarray(Pb), Bb, np.ascontiguousarray(order.anchors[i], np.int64),
                                np.result_type(Pb, Bb).type(ON_SKIN_M ** 2), tested)
            frame, idx = np.nonzero(tested)
            if not len(frame):
                continue
            ok = np.zeros(len(frame), bool)
            start = Pb[frame, idx]
            under = None
            if order is not None and i < len(out) - 1:
                under = _UnderOuter(Bv[sl, order.anchors[i]], [LayerFrames(out[j][sl], order.faces[j]) for j in range(i + 1, len(out))])
            for kk in (min(NEAR_CANDIDATES, k), k, far):  # deep in an overlap every near target is inside too: look farther
                rem = np.flatnonzero(~ok)
                targets = _posed_targets(Pb, Bv[sl], frame[rem], idx[rem], skin_ids, skin_faces, offsets[i], kk, trees)
                fallback = under is not None and kk == far
                known = np.full(targets.shape[:2], -1, np.int8) if fallback else None
                ok[rem] = _move_outside(Pb, grid, mesh, frame[rem], idx[rem], targets, under,
                                        reach_m=FAR_ACCEPT_M if fallback else None, known=known)
                if fallback and not ok.all():
                    # no candidate under the outer layers: the nearest outside one of the same targets
                    # (the points that found none have not moved), the ones counted above not again
                    miss = np.flatnonzero(~ok[rem])
                    ok[rem[miss]] = _move_outside(Pb, grid, mesh, frame[rem[miss]], idx[rem[miss]], targets[miss],
                                                  known=np.ascontiguousarray(known[miss]))
                if ok.all():
                    break
            held = ok.copy()
            in_body = None
            if cleared[i]:
                # a point that had to go far (or nowhere) but was only within the clearance, not
                # inside the body itself (between the arm and the torso), stays where it was
                went_far = np.flatnonzero(~ok | (np.linalg.norm(Pb[frame, idx] - start, axis=1) > offsets[i] + BAND_MOVE_M))
                if len(went_far):
                    band = went_far[grid.count_at(start[went_far], frame[went_far], "second") == 0]
                    Pb[frame[band], idx[band]] = start[band]
                    ok[band] = True
                    held[band] = False
                in_body = lambda rows: grid.count_at(start[rows], frame[rows], "second") > 0  # noqa: E731
            # the points inside the body itself keep their side of a limb from one frame to the next
            if faces is not None:  # and neighbours keep one side of it
                _keep_together(Pb, before[i], start, frame, idx, faces[i], grid, mesh, Bv[sl], skin_ids, skin_faces, offsets[i], min(KEEP_CANDIDATES, k), trees,
                               under)
            _hold_sides(Pb, before[i], starts[sl], carry[i], Bv[sl], start, frame, idx, held, in_body, grid, mesh, skin_ids, skin_faces,
                        offsets[i], k, trees, under)
            left += int((~ok).sum())
        carry = [o[sl][-1] - b[-1] for o, b in zip(out, before)]
    if left:
        log.warning("exact repair: %d point-frames left inside the body (no outside target among %d candidates)", left, far)
    return [P.reshape(B, T, -1, 3) for P in out], left


def _hold_sides(Pb, entering, starts, carry, Bb, start, frame, idx, ok, in_body, grid, mesh, skin_ids, skin_faces, margin_m, k, trees,
                accept=None) -> int:
    """Keep a point on its side of a limb from one frame to the next (Pb (T, N, 3), a block of one
    layer, in place; ``entering`` its points as they came to this stage; the points tested:
    frame (sorted), idx, from ``start``; ``ok`` the ones moved out; ``in_body(rows)`` (None: all
    of them are) which of those rows were inside the body itself, not only within a clearance).

    Each point takes its nearest outside target alone, frame by frame. Deep in a limb (a T-shirt's
    hem in a thigh when the body crouches, cloth between the arm and the flank) two ways out are
    about as near, and the choice can flip from one side to the other, and back, from one frame
    to the next: the cloth jumps by twice the depth. So, frame by frame in order, a point whose
    move m_t = p'_t - p_t (p' where this stage put it, p where it came) and the frame before's
    m_{t-1} are both longer than HOLD_FROM_M, with m_t . m_{t-1} < 0 and |m_t - m_{t-1}| >
    HOLD_JUMP_M (a jump worth holding), takes instead, of its free targets (outside the body, and
    where ``accept`` is given, under the outer layers) no more than HOLD_M farther from it than the
    one it had, the one nearest to p_t + m_{t-1}: it stays on its side unless that costs more than
    HOLD_M. A flip that still happens is then at most HOLD_M longer than it would have been.

    starts: (T,) bool, the frames that start a motion (no frame before them); carry: (N, 3) the
    moves of the frame before the block (None: none); k: the targets' nearest skin vertices (one
    search for every point that may need a hold in the block; the choice then goes frame by
    frame). Returns the points held."""
    T, N = Pb.shape[:2]
    moves = Pb - entering
    before = np.concatenate([np.zeros_like(moves[:1]) if carry is None else carry[None], moves[:-1]])  # the frame before's moves
    live = ~starts & ((np.arange(T) > 0) | (carry is not None))  # frames with a frame before them in the motion
    reach = _flips(moves[frame, idx], before[frame, idx]) & ok & live[frame]
    if not reach.any():
        return 0
    # a point held in a frame changes its move there, so its next frame may need a hold too (held
    # on one side, its nearest way out is on the other again): the rows reachable so, along runs of
    # consecutive frames the point is tested in
    row = np.full((T, N), -1, np.int64)
    row[frame, idx] = np.arange(len(frame))
    for t in range(1, T):
        r = row[t, idx[frame == t]]
        prev = row[t - 1, idx[r]]
        reach[r] |= (prev >= 0) & reach[np.maximum(prev, 0)] & ok[r] & live[t]
    rows = np.flatnonzero(reach)
    if in_body is not None:
        rows = rows[in_body(rows)]
    if not len(rows):
        return 0
    # every reachable point's targets at once (they depend on its place, not on the hold)
    f, v, p = frame[rows], idx[rows], start[rows]
    had = Pb[f, v].copy()
    Pb[f, v] = p  # the targets are p's
    targets = _posed_targets(Pb, Bb, f, v, skin_ids, skin_faces, margin_m, k, trees)  # (n, 2k, 3)
    Pb[f, v] = had
    free = np.linalg.norm(targets - p[:, None], axis=-1) <= (np.linalg.norm(had - p, axis=1) + HOLD_M)[:, None]
    at = np.nonzero(free)
    tried = targets[at]
    out = grid.count_at(tried, f[at[0]], mesh, tried[:, 1] < p[at[0], 1]) == 0
    if accept is not None and out.any():
        sel = np.flatnonzero(out)
        out[sel] = accept(f[at[0][sel]], v[at[0][sel]], tried[sel])
    free[at[0][~out], at[1][~out]] = False
    held_total = 0
    bounds = np.searchsorted(f, np.arange(T + 1))
    for t in np.unique(f):  # in order: a hold changes the next frame's move before
        r = np.arange(bounds[t], bounds[t + 1])
        vt = v[r]
        was = Pb[t - 1, vt] - entering[t - 1, vt] if t > 0 else carry[vt]
        flip = _flips(had[r] - entering[t, vt], was)
        r, vt, was = r[flip], vt[flip], was[flip]
        miss = np.where(free[r], np.linalg.norm(targets[r] - (entering[t, vt] + was)[:, None], axis=-1), np.inf)
        best = np.argmin(miss, axis=1)
        found = np.isfinite(miss[np.arange(len(r)), best])
        Pb[t, vt[found]] = targets[r[found], best[found]]
        held_total += int(found.sum())
    return held_total


def _keep_together(Pb, entering, start, frame, idx, faces, grid, mesh, Bb, skin_ids, skin_faces, margin_m, k, trees, accept=None) -> int:
    """Keep neighbouring points together (Pb (T, N, 3), a block of one layer, in place; ``entering``
    its points as they came to this stage; the points tested: frame, idx, from ``start``; faces:
    the layer's (F, 3)).

    Each point takes its nearest outside target alone. Where two body parts overlap (an arm sunk
    into the flank, the thighs of a heavy body), the ways out over either part are about as near,
    and neighbours can take different ones: the edge between them stretches across the part (4-9
    cm on the validation walk, 02_02). So a point this stage moved, at an edge it stretched by more
    than KEEP_STRETCH_M, takes instead, of its free targets (outside the body; under the outer
    layers where ``accept`` is given) at most KEEP_M farther from it than the one it took, and that
    one, the one nearest to where its neighbours would carry it,

        d_i = mean over the mesh neighbours j of (p'_j + e_i - e_j),   e: the points as they came;

    its free targets include each neighbour's place so carried, p'_j + e_i - e_j, so that a point
    can follow a neighbour to its side where none of its own skin vertices' targets lies there.
    In up to KEEP_PASSES rounds (a round's choices change the next one's d). It runs before
    ``_hold_sides``, which then keeps the points' sides from frame to frame. Returns the points moved."""
    T, N = Pb.shape[:2]
    E = mesh_edges(faces)
    adj = _adjacency(faces, N)
    incident = _incident_edges(faces, N)
    total = 0
    slot = np.full(len(frame), -1, np.int64)  # a row's place in the kept targets (found once)
    kept_t = np.zeros((0, 2 * k, 3), Pb.dtype)
    kept_near = np.zeros((0, 2 * k), bool)
    kept_known = np.zeros((0, 2 * k), np.int8)  # their verdicts so far: 0 outside, 1 inside, -1 not counted
    kept_reach = np.zeros(0)  # how far from p a row may go: its first move + KEEP_M
    asked = np.zeros((0, 3))  # the d_i each row was last tested for
    P32, E32 = np.ascontiguousarray(Pb), np.ascontiguousarray(entering)
    for _ in range(KEEP_PASSES):
        move = Pb[frame, idx] - start
        moved = np.flatnonzero((move != 0.0).any(1))
        if not len(moved):
            break
        row = np.full((T, N), -1, np.int64)
        row[frame[moved], idx[moved]] = moved
        # the edges at the points moved more than half the stretch (an edge stretched so has one)
        wide = moved[np.einsum("nc,nc->n", move[moved], move[moved]) > (0.5 * KEEP_STRETCH_M) ** 2]
        P32[...] = Pb
        mark = np.zeros(len(frame), bool)
        kernels.torn_ends(P32, E32, row, frame[wide], idx[wide], incident.indptr, incident.indices, E, KEEP_STRETCH_M, mark)
        rows = np.flatnonzero(mark)
        if not len(rows):
            break
        f, v = frame[rows], idx[rows]
        want = np.empty((len(rows), 3))
        kernels.carried_places(P32, E32, f, v, adj.indptr, adj.indices, want)
        off = np.linalg.norm(Pb[f, v] - want, axis=1)
        # the others are where their neighbours carry them already, or were asked for this d_i
        again = np.ones(len(rows), bool)
        seen = np.flatnonzero(slot[rows] >= 0)
        again[seen] = np.linalg.norm(want[seen] - asked[slot[rows[seen]]], axis=1) > KEEP_ASKED_M
        far = (off > KEEP_OFF_M) & again
        rows, f, v, want, off = rows[far], f[far], v[far], want[far], off[far]
        if not len(rows):
            break
        new = rows[slot[rows] < 0]
        if len(new):  # a row's targets and the farthest it may go, once
            fn, vn, p = frame[new], idx[new], start[new]
            had = Pb[fn, vn].copy()
            Pb[fn, vn] = p  # the targets are p's
            targets = _posed_targets(Pb, Bb, fn, vn, skin_ids, skin_faces, margin_m, k, trees)  # (n, 2k, 3)
            Pb[fn, vn] = had
            reach = np.linalg.norm(had - p, axis=1) + KEEP_M
            near = np.linalg.norm(targets - p[:, None], axis=-1) <= reach[:, None]
            slot[new] = len(kept_t) + np.arange(len(new))
            kept_t, kept_near = np.concatenate([kept_t, targets]), np.concatenate([kept_near, near])
            kept_known = np.concatenate([kept_known, np.full(near.shape, -1, np.int8)])
            kept_reach = np.concatenate([kept_reach, reach])
            asked = np.concatenate([asked, np.zeros((len(new), 3))])
        asked[slot[rows]] = want
        cur = Pb[f, v]
        # a target too far is replaced by the point's place, which is free: the nearest free one to d_i
        # of the others and the place itself
        options = np.where(kept_near[slot[rows]][..., None], kept_t[slot[rows]], cur[:, None])
        # and each neighbour's place carried by the offset between them (following it to its side),
        # within the same reach
        carried = _neighbour_places(Pb, entering, f, v, adj, cur)
        carried = np.where((np.linalg.norm(carried - start[rows][:, None], axis=-1) <= kept_reach[slot[rows], None])[..., None], carried,
                           cur[:, None])
        options = np.concatenate([options, carried.astype(options.dtype)], 1)
        # the kept targets' verdicts of the rounds before (d_i moves, the targets do not): each is
        # counted once; a target replaced by the point's place is not known
        mine = kept_near[slot[rows]]
        known = np.where(mine, kept_known[slot[rows]], np.int8(-1))
        # one compiled pass, nearest to d_i first; an inner layer's choice must lie under the outer
        # layers: a refused one is struck off and the pass asked again (a few times at most)
        best = grid.first_outside(want, options, f, mesh, known)
        kept_known[slot[rows]] = np.where(mine, known, np.int8(-1))
        ask = np.arange(len(rows))
        for _ in range(KEEP_CONSENTS if accept is not None else 0):
            ask = ask[(best[ask] >= 0) & ~(options[ask, np.maximum(best[ask], 0)] == cur[ask]).all(1)]
            if not len(ask):
                break
            yes = accept(f[ask], v[ask], options[ask, best[ask]])
            no = ask[~yes]
            if not len(no):
                break
            options[no, best[no]] = cur[no]
            struck = no[best[no] < mine.shape[1]]  # a kept target struck off: the place there is not known
            mine[struck, best[struck]] = False
            known[struck, best[struck]] = -1
            known_no = known[no]
            best[no] = grid.first_outside(want[no], options[no], f[no], mesh, known_no)
            kept_known[slot[rows[no]]] = np.where(mine[no], known_no, kept_known[slot[rows[no]]])
            known[no] = known_no
            ask = no
        else:
            if accept is not None and len(ask):  # still refused: the point stays
                best[ask] = -1
        took = options[np.arange(len(rows)), np.maximum(best, 0)]
        better = (best >= 0) & (np.linalg.norm(took - want, axis=1) < off)
        Pb[f[better], v[better]] = took[better]
        total += int(better.sum())
        if not better.any():
            break
    return total


def _neighbour_places(Pb, entering, f, v, adj: sp.csr_matrix, fill: np.ndarray) -> np.ndarray:
    """Each point's (frame f, vertex v) mesh neighbours' places carried by the offset between them as
    they came, p'_j + e_v - e_j: (n, most neighbours, 3), rows padded with ``fill`` (n, 3)."""
    deg = np.diff(adj.indptr)[v]
    out = np.repeat(fill[:, None], int(deg.max(initial=0)), 1)
    owner = np.repeat(np.arange(len(v)), deg)
    col = np.arange(deg.sum()) - np.repeat(np.cumsum(deg) - deg, deg)
    nb = adj.indices[np.repeat(adj.indptr[v], deg) + col]
    out[owner, col] = Pb[f[owner], nb] - entering[f[owner], nb] + entering[f[owner], v[owner]]
    return out


@per_array
def _incident_edges(faces: np.ndarray, num_vertices: int) -> sp.csr_matrix:
    """Vertex -> its edges (rows of ``mesh_edges``) as a CSR matrix, once per faces array."""
    E = mesh_edges(faces)
    ids = np.arange(len(E))
    m = sp.csr_matrix((np.ones(2 * len(E), np.int8), (np.r_[E[:, 0], E[:, 1]], np.r_[ids, ids])), shape=(num_vertices, len(E)))
    m.indptr, m.indices = m.indptr.astype(np.int64), m.indices.astype(np.int64)
    return m


@per_array
def _adjacency(faces: np.ndarray, num_vertices: int) -> sp.csr_matrix:
    """The vertex adjacency of a mesh (num_vertices x num_vertices CSR, no diagonal), once per faces array."""
    E = mesh_edges(faces)
    A = sp.coo_matrix((np.ones(2 * len(E), np.int8), (np.r_[E[:, 0], E[:, 1]], np.r_[E[:, 1], E[:, 0]])), shape=(num_vertices, num_vertices)).tocsr()
    A.indptr, A.indices = A.indptr.astype(np.int64), A.indices.astype(np.int64)
    return A


def _flips(cur: np.ndarray, was: np.ndarray) -> np.ndarray:
    """(n,) bool: moves cur and the frame before's was (n, 3) both longer than HOLD_FROM_M and
    against each other by more than HOLD_JUMP_M (``_hold_sides``)."""
    far2, jump = HOLD_FROM_M ** 2, cur - was
    return ((np.einsum("nc,nc->n", cur, cur) > far2) & (np.einsum("nc,nc->n", was, was) > far2) & (np.einsum("nc,nc->n", cur, was) < 0.0)
            & (np.einsum("nc,nc->n", jump, jump) > HOLD_JUMP_M ** 2))


def _region(layers: list[np.ndarray]) -> np.ndarray:
    """Per frame, the (x min, x max, z min, z max) of the layers' points (each (T, N_i, 3)) widened
    by REGION_M: the part of the winding grid's plane that the points and their targets ask."""
    lo = np.min([p[..., [0, 2]].min(1) for p in layers], 0) - REGION_M
    hi = np.max([p[..., [0, 2]].max(1) for p in layers], 0) + REGION_M
    return np.stack([lo[:, 0], hi[:, 0], lo[:, 1], hi[:, 1]], -1).astype(np.float64)


def _posed_targets(Pb, Bb, frame, idx, skin_ids, skin_faces, margin_m, k, trees: dict) -> np.ndarray:
    """Targets (n, k, 3) on the k posed skin vertices nearest to each point.

    Per frame, a grid of the skin vertices within NEAR_BOX_M (FAR_BOX_M for more than
    REPAIR_CANDIDATES) of the box of the frame's points
    answers every point whose k-th neighbour is nearer than the box's side
    (``inference.repair_kernels.frame_knn``: the same neighbours as the whole skin's). The others
    ask the whole skin's tree of their frame, built once per frame and kept in ``trees`` for the
    next pass."""
    q = Pb[frame, idx]
    order = np.argsort(frame, kind="stable")
    frames, counts = np.unique(frame[order], return_counts=True)
    starts = np.concatenate([[0], np.cumsum(counts)])
    # (the far look: each point's search stops where its cells cover the box's pad; a point whose
    # k-th nearest lies beyond asks the tree)
    pad, cell, radius = (NEAR_BOX_M, KNN_CELL_M, np.inf) if k <= REPAIR_CANDIDATES else (FAR_BOX_M, FAR_CELL_M, FAR_BOX_M)
    nn, found = kernels.frame_knn(np.ascontiguousarray(Bb, np.float32), frames.astype(np.int64), starts,
                                  np.ascontiguousarray(q[order], np.float64), skin_ids, k, pad, cell, radius)
    ids = np.empty((len(frame), k), np.int64)
    ids[order] = nn
    todo = order[~found]
    for f in np.unique(frame[todo]):  # C code
        sel = todo[frame[todo] == f]
        if f not in trees:
            trees[f] = cKDTree(Bb[f, skin_ids])
        ids[sel] = skin_ids[trees[f].query(q[sel], k=k)[1].reshape(len(sel), k)]
    return _targets(Bb, frame, ids, skin_faces, margin_m, q)


@per_array
def _skin(faces: np.ndarray, num_vertices: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``major_components`` of a body's faces (~5 ms a call), its vertex ids and the faces among
    them: once per faces array (``inference.mesh.per_array``)."""
    faces = np.asarray(faces)
    skin = major_components(faces, num_vertices)
    return skin, np.flatnonzero(skin), faces[skin[faces].all(1)]


@per_array
def _masked_skin(faces: np.ndarray, skin: bytes) -> tuple[np.ndarray, np.ndarray]:
    """The vertex ids of a skin mask (its (V,) bool bytes) and the faces among them: once per
    faces array and mask, so that the same faces array reaches ``faces_around`` (its table is
    kept per array) in every request."""
    mask = np.frombuffer(skin, bool)
    faces = np.asarray(faces)
    return np.flatnonzero(mask), faces[mask[faces].all(1)]


def _targets(Bb, frame, ids, skin_faces, margin_m, points) -> np.ndarray:
    """The targets (n, 2k, 3) of points (n, 3) (module docstring) from skin vertices ids (n, k) of
    frames frame (n,) of the block Bb: the plane targets, then the vertex targets, each from the
    vertex's area-weighted normal over its faces in its frame. Compiled
    (``repair_kernels.skin_targets``; bitwise the numpy form it replaced: the normals of the
    vertices used by ``mesh_kernels.normals_at`` over ``faces_around`` them, then the targets in
    float64; a 1-frame T-shirt request's 0.8 -> 0.15 ms)."""
    indptr, face_of = _vertex_faces(skin_faces, Bb.shape[1])
    out = np.empty((len(frame), 2 * ids.shape[1], 3), Bb.dtype)
    kernels.skin_targets(np.ascontiguousarray(Bb), np.ascontiguousarray(frame, np.int64), np.ascontiguousarray(ids, np.int64),
                         np.ascontiguousarray(skin_faces), indptr, face_of, float(margin_m), np.ascontiguousarray(points), out)
    return out


@dataclass(frozen=True)
class LayerOrder:
    """An outfit's layers for ``repair_layers``: per layer (innermost first) its vertices' body
    anchors (N_i,) int (``inference.layers.body_anchors``) and its faces (F_i, 3); gap_m the
    clearance an inner layer keeps under an outer one (the layer stage's)."""

    anchors: Sequence[np.ndarray]
    faces: Sequence[np.ndarray]
    gap_m: float = DEFAULT_LAYER_GAP_M


def _sink_under_moved(P: np.ndarray, body: np.ndarray, body_faces: np.ndarray, order: LayerOrder, i: int, j: int,
                      outer_before: np.ndarray, outer_after: np.ndarray, floor_m: float, room=None) -> int:
    """Inner layer i's points (P (T, N, 3), in place) under the faces of outer layer j that this
    stage moved (outer_before -> outer_after, (T, No, 3)): an outer point inside the body goes out
    to the skin, and its faces can then cross an inner point's body-anchor segment (the layer
    stage's order test, ``inference.layers``); such a point goes back along its segment to the
    gap under the crossing, or, where the outer layer lies within floor + gap of the skin, half-way
    to it (the layer stage's step (c)), if that place is outside the body (``room(t, points) ->
    bool``, where given) and no farther than the crossed face moved, plus the gap. On the
    validation walk every inner vertex-frame left beyond an outer layer after this stage was one
    such crossing (crop top under shirt, heavy body: 0.08 % beyond; after the layer stage 0.00 %).
    Returns the points moved."""
    faces = order.faces[j]
    moved_v = (outer_after != outer_before).any(-1)  # (T, No)
    frames = np.flatnonzero(moved_v.any(1))
    if not len(frames) or not len(faces):
        return 0
    anchors = order.anchors[i]
    h = None
    sunk = 0
    for t in frames:  # the frames where the outer layer moved: its moved faces, binned small
        near = faces_around(faces, np.flatnonzero(moved_v[t]), outer_after.shape[1])
        Fb = np.ascontiguousarray(faces[near], np.int64)
        B = np.ascontiguousarray(outer_after[t], np.float64)
        if h is None:
            h = CELL_EDGES * max(float(median_edge(B, np.ascontiguousarray(faces, np.int64), 1)), 1e-6)  # compiled: numpy's median, bitwise
        a = np.ascontiguousarray(body[t, anchors], np.float64)
        p = np.ascontiguousarray(P[t], np.float64)
        _, first, face = first_crossings(a, p, B, Fb, h, False)
        hit = np.flatnonzero(first <= 1.0)
        if not len(hit):
            continue
        ids, inverse = np.unique(anchors[hit], return_inverse=True)  # the anchors' normals (``layers.anchor_normals``)
        slot = np.full(body.shape[1], -1, np.int64)
        slot[ids] = np.arange(len(ids))
        n = np.empty((1, len(ids), 3))
        mesh_kernels.normals_at(body[t:t + 1], body_faces, faces_around(body_faces, ids, body.shape[1]), slot, n)
        n = n[0, inverse]
        s = p[hit] - a[hit]
        Ls = np.linalg.norm(s, axis=-1)
        reach = first[hit] * Ls
        up = np.maximum((s * n).sum(-1), 1e-9) / np.maximum(Ls, 1e-12)  # height per metre along the segment
        d = np.maximum(reach - order.gap_m, np.minimum(floor_m / up, 0.5 * reach))
        # no farther than the crossed face moved (plus the gap): a longer way back along the
        # segment is not this stage's doing (a garment far off the skin, its anchor segment long)
        bound = np.linalg.norm(outer_after[t][Fb[face[hit]]] - outer_before[t][Fb[face[hit]]], axis=-1).max(1) + order.gap_m
        go = (Ls - d) <= bound
        hit, s, d, Ls = hit[go], s[go], d[go], Ls[go]
        to = (a[hit] + s * (d / np.maximum(Ls, 1e-12))[:, None]).astype(P.dtype)
        if room is not None and len(hit):
            free = room(t, to)
            hit, to = hit[free], to[free]
        P[t, hit] = to
        sunk += len(hit)
    return sunk


class _UnderOuter:
    """Which targets of an inner layer's points keep it under the outer layers: the segment from
    the point's posed body anchor to the target crosses none of them (the layer stage's order,
    ``inference.layers``). anchors: (T, N, 3) the block's posed anchors of the layer's vertices."""

    def __init__(self, anchors: np.ndarray, outer: list[LayerFrames]):
        self.anchors, self.outer = anchors, outer

    def __call__(self, frame: np.ndarray, idx: np.ndarray, targets: np.ndarray) -> np.ndarray:
        """frame, idx (m,), targets (m, 3): (m,) bool, True where no outer layer is crossed."""
        ok = np.ones(len(frame), bool)
        order = np.argsort(frame, kind="stable")
        bounds = np.searchsorted(frame[order], np.arange(self.anchors.shape[0] + 1))
        for t in np.unique(frame):  # one kernel call per frame and outer layer, nearest layer first
            rows = order[bounds[t]:bounds[t + 1]]
            for layer in self.outer:
                ok[rows] = layer.crossings(t, self.anchors[t, idx[rows]], targets[rows], any_only=True)[0] == 0
                rows = rows[ok[rows]]  # a target refused by one layer is not asked of the next
                if not len(rows):
                    break
        return ok


def _move_outside(Pb, grid, mesh, frame, idx, targets, accept=None, reach_m=None, known=None) -> np.ndarray:
    """Move points (frame, idx) of the block Pb (in place) to their nearest outside target of
    ``targets`` (n, k, 3) that ``accept(frame, idx, targets) -> bool`` takes, if given, and no
    farther than ``reach_m`` from the point (with ``accept``; None: any distance); returns (n,)
    bool, True where one was found. known: (n, k) int8, C-contiguous, the targets' winding
    verdicts (0 outside, 1 inside, -1 not counted; ``WindingGrid.first_outside``'s): read without
    accept, and with it written for the targets counted (before accept's say), so that a second
    call on the same targets counts none of them again."""
    k = targets.shape[1]
    if accept is None:  # one compiled pass: each point's targets nearest first, to the first outside one
        best = grid.first_outside(Pb[frame, idx], targets, frame, mesh, known)
        ok = best >= 0
        Pb[frame[ok], idx[ok]] = targets[np.flatnonzero(ok), best[ok]]
        return ok
    # test the targets nearest first, ROUND per point at a time, then twice as many each round, in
    # the block's grid (each against its own frame): the first outside one is the nearest outside
    # one (equal distances in column order), whatever the rounds' sizes
    dist = np.linalg.norm(targets - Pb[frame, idx][:, None], axis=-1)
    order = np.argsort(dist, axis=1, kind="stable")
    within = np.full(len(frame), k)  # per point, how many of its nearest targets lie within reach
    if reach_m is not None:
        within = (dist <= reach_m).sum(1)
        k = int(within.max(initial=0))
    best = np.full(len(frame), -1)
    pending = np.flatnonzero(within > 0)
    r0, size = 0, ROUND
    while r0 < k and len(pending):
        cols = order[pending, r0:r0 + size]
        m = cols.shape[1]
        tried = targets[pending[:, None], cols].reshape(-1, 3)
        fr, at = np.repeat(frame[pending], m), np.flatnonzero((r0 + np.arange(m) < within[pending, None]).ravel())  # within reach
        # each target's ray along its move's side of y: it leaves the body at once
        down = tried[at, 1] < np.repeat(Pb[frame[pending], idx[pending], 1], m)[at]
        outside = np.zeros(len(tried), bool)
        outside[at] = grid.count_at(tried[at], fr[at], mesh, down) == 0
        if known is not None:
            rows, slots = np.divmod(at, m)
            known[pending[rows], cols[rows, slots]] = np.where(outside[at], 0, 1)
        if accept is not None and outside.any():
            at = np.flatnonzero(outside)
            outside[at] = accept(fr[at], np.repeat(idx[pending], m)[at], tried[at])
        outside = outside.reshape(cols.shape)
        hit = outside.any(1)
        best[pending[hit]] = cols[hit, outside[hit].argmax(1)]
        r0, size = r0 + size, 2 * size
        pending = pending[~hit & (within[pending] > r0)]
    ok = best >= 0
    Pb[frame[ok], idx[ok]] = targets[np.flatnonzero(ok), best[ok]]
    return ok


def warm_up() -> None:
    """Compile this stage's kernels (the winding grid's, ``inference.repair_kernels``,
    ``inference.mesh_kernels``) or load numba's cache, through one repair of a point inside a
    tetrahedron with int32 faces (the body model's), so that no request pays a first compilation."""
    tet = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], np.float32)[None, None]
    faces = np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]], np.int32)
    points = np.array([[0.1, 0.1, 0.1], [2.0, 2.0, 2.0]], np.float32)[None, None]
    exact_repair(points, tet, faces, 0.01)
    ray_down(tet[0], faces)  # a garment's rays (its kept topology: read-only int64 faces)
    # an outfit's anchor normals under an outer layer's moves (``_sink_under_moved``: the body's int32 faces)
    mesh_kernels.normals_at(tet[0], faces, np.arange(4, dtype=np.int64), np.arange(4, dtype=np.int64), np.empty((1, 4, 3)))
    # and its inner layers' points on their skin vertex (float32 frames; anchors built per request or
    # kept, read-only, per body: ``inference.layers.kept_anchors``)
    ids = np.arange(4, dtype=np.int64)
    kernels.on_skin(tet[0], tet[0], ids, np.float32(ON_SKIN_M ** 2), np.zeros((1, 4), bool))
    ids.flags.writeable = False
    kernels.on_skin(tet[0], tet[0], ids, np.float32(ON_SKIN_M ** 2), np.zeros((1, 4), bool))
    # the torn edges and the neighbours' places of ``_keep_together`` (a block's float32 frames)
    edges, one = mesh_edges(faces), np.zeros(1, np.int64)
    incident, adj = _incident_edges(faces, 4), _adjacency(faces, 4)
    kernels.torn_ends(tet[0], tet[0], np.zeros((1, 4), np.int64), one, one, incident.indptr, incident.indices, edges, KEEP_STRETCH_M,
                      np.zeros(1, bool))
    kernels.carried_places(tet[0], tet[0], one, one, adj.indptr, adj.indices, np.empty((1, 3)))
