"""Layered outfits in the posed space: every inner garment stays under the garments outside it.

Body anchors. Each garment vertex x is anchored to its nearest vertex a(x) of the shaped body in
the rest pose (once per request; for a garment whose canonical form moves per frame, its mean
form). In each posed frame the anchor a_t is that posed body vertex and the garment vertex p_t its
own skinning's position, so the segment a_t -> p_t runs from the skin out to the vertex through
whatever lies between; its height over the skin is h = (p_t - a_t) . n_t, n_t the body's normal
at the anchor.

Order test (thesis ch. 7 asks for one that handles the openings; this is the crossing count
from the body): an inner vertex p_t is beyond an outer layer when its anchor segment crosses the
outer layer's triangles (``inference.intersections``, exact orientation predicates). An opening
(neck, cuffs, hem, an open jacket's front) has no triangles to cross, so a vertex under it is
never counted; a vertex between the arm and the torso is judged against the layer between it and
its own skin, not against a sleeve that happens to be nearer. (The closest outer point's side,
``metrics.layer_violations``, calls 2-10 % of the T-shirt beyond the jacket on 02_02 whatever
is done: under the arm the nearest jacket surface is the sleeve's inner wall.)

Untangling: eq. 7.6's split along the anchor segments, with the outer layers held fixed, so that
the inner layer alone gives way. Layers are placed from the outside in (layer N - 2 under layer
N - 1, then N - 3 under both, ...); for inner layer i, per frame, a sink depth s(v) >= 0 per vertex:

  (a) an outer vertex o whose anchor ray, continued ``reach`` past o (RIM_REACH_M near the outer
      layer's rim, where a tucked-in layer blouses out over it), leaves layer i (crosses one of its
      faces from back to front: layer i lies just outside o) sinks that face's corners by the
      crossing's distance past o plus the gap;
  (b) an inner vertex whose anchor segment, continued past the vertex by e = gap / cos (cos: the
      segment's angle to the skin's normal at the anchor, at least MIN_SINK_COS: the gap is a
      height over the skin), crosses an outer layer at distance s from the anchor (segment length
      L) sinks by L + e - s: to the gap under it (beyond the outer layer, or under it by less
      than the gap);
  then s spreads SPREAD_RINGS rings over the inner mesh, times SPREAD_DECAY per ring (a dent's rim
  slopes instead of stepping), and each vertex moves by s against its anchor direction averaged
  over its one-ring (RAY_SMOOTHING times: neighbours anchored on different body parts, under the
  arm, sink in nearly one direction), but never below its floor height (its body margin):
      p <- p - min(s, (h - floor) / max(r . n, MIN_SINK_COS)) r
  (c) a moved vertex still beyond an outer layer goes back along its own anchor segment to the gap
      under it, or, where the outer layer lies within floor + gap of the skin, half-way to it (an
      outer layer that crosses at the anchor itself, inside the body there, puts the point on its
      skin vertex: the final stage moves it, ``inference.repair``).

Pushing outer vertices out instead (over an inner layer found within 3 cm past them) left 2-5x
fewer intersecting pairs away from the outer layer's self-intersections on 02_02, but stretched
the outer layer: the jacket's longest edge from 8.8x to 17.9x its rest length over a T-shirt, its
p99 from 1.48 to 1.62; (a) gets most of that gain from the inner side. Moving along the raw anchor
segments instead of the smoothed directions stretched 1.5 % of the T-shirt's edges past 1.5x
(smoothed: 0.19 %). Lifting, after (c), the outer vertices still under an inner layer held at its floor
(by at most 1 cm) made the 3-layer outfit worse on 02_02 (crop top beyond the shirt 0.29 -> 0.48 %,
shirt-jacket pairs 272 -> 456). After the stage, the body's exact repair (which runs last) moves the points
inside the body out, outer layers first; inner points whose segment an outer layer's moved faces then
cross go back under them by step (c) there, where they have room (``inference.repair``).

Units: metres. Arrays: float32 in, float32 out, frames (T, N, 3).
"""
from __future__ import annotations

import threading
from collections import OrderedDict
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
from scipy.spatial import cKDTree

from inference import layers_kernels, mesh_kernels
from inference.errors import InputShapeError
from inference.intersections import CELL_EDGES, _bin_faces, binned_crossings, first_crossings
from inference.mesh import content_key, faces_touching, per_array
from inference.nearness import near, nearest
from inference.winding import check_faces
from inference.winding_kernels import median_edge

# How far past an outer vertex, along its anchor ray, an inner layer is looked for (module doc, (a)).
SINK_REACH_M = 0.02
# A vertex's sink reaches SPREAD_RINGS rings of neighbours, times SPREAD_DECAY per ring.
SPREAD_RINGS = 2
SPREAD_DECAY = 0.5
# Sinking along a direction this oblique to the skin's normal or more counts as this cosine (floor test).
MIN_SINK_COS = 0.2
# Parts of two layers farther apart than this in their rest forms are not tested against each other.
CONTACT_M = 0.06
# ... widened by this where the rest forms are stand-ins: a learned canonical model's frames' mean
# form (the layers' true rest relation) lies up to 4.4 cm from its static canonical form shaped to
# the body (p50 1.2, p99 3.6 cm; tshirt, shirt, trousers, leggings in 24 outfit requests, three
# clips, random bodies), on which its contacts are kept per body (``inference.pipeline``).
STAND_IN_SLACK_M = 0.05
# One-ring averages of the sinking directions (``layers_kernels.sink_along_rays``).
RAY_SMOOTHING = 3
# Step (a) looks this far past the outer layer's vertices on its rim and RIM_RINGS rings in from it:
# an inner garment tucked under it (a shirt in trousers) blouses out over the waistband, 1-8 cm off
# the skin. On 02_02 (validation, neutral; step (b)'s gap then along the segment) the tucked shirt's
# intersecting pairs with the trousers fell from 108 to 46 a frame (2 cm everywhere: 108; 8 cm
# everywhere: 23, but the crop top under the shirt 274 -> 301); every other outfit the same or fewer.
RIM_REACH_M = 0.08
RIM_RINGS = 2
# A vertex nearer its anchor than this lies on the skin (step (c) with an outer layer crossing at
# the anchor): the final stage moves it out as if it were inside (``inference.repair``).
ON_SKIN_M = 1e-5


# KD-trees of rest bodies kept per process (``body_tree``): a shopper's body comes back with every
# outfit (~2 ms to build for the anny body, ~1 MB each).
BODY_TREE_ENTRIES = 4
_BODY_TREES: OrderedDict = OrderedDict()
_BODY_TREES_LOCK = threading.Lock()


def body_tree(rest_body: np.ndarray) -> cKDTree:
    """A KD-tree of a rest body's vertices (Vb, 3) in float64, for ``body_anchors``: kept (LRU,
    BODY_TREE_ENTRIES) under the contents of the vertices."""
    key = content_key(rest_body)
    with _BODY_TREES_LOCK:
        tree = _BODY_TREES.get(key)
        if tree is not None:
            _BODY_TREES.move_to_end(key)
            return tree
    tree = cKDTree(np.asarray(rest_body, np.float64))
    with _BODY_TREES_LOCK:
        _BODY_TREES[key] = tree
        while len(_BODY_TREES) > BODY_TREE_ENTRIES:
            _BODY_TREES.popitem(last=False)
    return tree


# Anchors and contacts of rest forms kept per process (``kept_anchors``, ``LayerContacts.kept``): a
# shopper's body comes back with every outfit and motion, and the rest forms are the garments'
# static ones for that body (~2.5 ms of anchors per garment, ~8 ms of contacts for T-shirt + jacket).
REST_ENTRIES = 16
_RESTS: OrderedDict = OrderedDict()
_RESTS_LOCK = threading.Lock()


def _kept(key: tuple, build):
    """build() kept under ``key`` (LRU, REST_ENTRIES; the values are read-only arrays)."""
    with _RESTS_LOCK:
        hit = _RESTS.get(key)
        if hit is not None:
            _RESTS.move_to_end(key)
            return hit
    value = build()
    with _RESTS_LOCK:
        _RESTS[key] = value
        while len(_RESTS) > REST_ENTRIES:
            _RESTS.popitem(last=False)
    return value


def kept_anchors(rest_garment: np.ndarray, rest_body: np.ndarray) -> np.ndarray:
    """``body_anchors`` (read-only) kept under the contents of both rest forms."""
    def build():
        a = body_anchors(rest_garment, rest_body, body_tree(rest_body))
        a.flags.writeable = False
        return a
    return _kept(("anchors", content_key(rest_garment), content_key(rest_body)), build)


def body_anchors(rest_garment: np.ndarray, rest_body: np.ndarray, tree: cKDTree | None = None) -> np.ndarray:
    """The nearest rest-body vertex of each rest garment vertex: (N,) int64.

    (Choosing instead, among the 8 nearest, the one whose skinning weights are closest to the
    garment vertex's left 1.2-1.5x more intersecting pairs on 02_02: the nearest it is.)
    rest_garment : (N, 3) ; rest_body : (Vb, 3) ; tree : a KD-tree of rest_body, if built already
    """
    rest_garment = np.asarray(rest_garment)
    if rest_garment.ndim != 2 or rest_garment.shape[1] != 3:
        raise InputShapeError("rest_garment", "(N, 3)", rest_garment.shape)
    rest_body = np.asarray(rest_body)
    tree = tree or cKDTree(np.asarray(rest_body, np.float64))
    return nearest(tree, rest_body, np.arange(len(rest_body)), rest_garment, 1)[:, 0]


class LayerFrames:
    """One layer's posed frames with its faces binned per frame, once, for every crossing query
    against it (``inference.intersections._bin_faces``; cell: CELL_EDGES median edge lengths of
    its first frame)."""

    def __init__(self, verts: np.ndarray, faces: np.ndarray):
        verts = np.asarray(verts)
        if verts.ndim != 3 or verts.shape[-1] != 3:
            raise InputShapeError("outer", "(T, V, 3)", verts.shape)
        faces = np.asarray(faces)
        self.faces = np.ascontiguousarray(check_faces(faces, verts.shape[1]) if len(faces) else np.zeros((0, 3), np.int64))
        self.verts = np.ascontiguousarray(verts, np.float64)
        edge = median_edge(self.verts[0], self.faces, 1) if len(self.faces) else 1.0  # compiled: numpy's median, bitwise
        self.cell = CELL_EDGES * max(float(edge), 1e-6)
        self._grids: dict[int, tuple] = {}

    def grid(self, t: int) -> tuple:
        if t not in self._grids:
            self._grids[t] = _bin_faces(self.verts[t], self.faces, self.cell)
        return self._grids[t]

    def crossings(self, t: int, starts: np.ndarray, ends: np.ndarray, exiting: bool = False,
                  any_only: bool = False) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Frame t: ``first_crossings`` of the segments starts -> ends (n, 3) against this layer
        (``any_only``: each segment's walk stops at its first crossing found, ``binned_crossings``)."""
        starts, ends = np.ascontiguousarray(starts, np.float64), np.ascontiguousarray(ends, np.float64)
        if not len(starts) or not len(self.faces):
            return np.zeros(len(starts), np.int32), np.full(len(starts), 2.0), np.full(len(starts), -1, np.int64)
        return binned_crossings(starts, ends, self.verts[t], self.faces, self.cell, self.grid(t), exiting, any_only)


def anchor_crossings(points: np.ndarray, anchors: np.ndarray, outer: np.ndarray | LayerFrames, outer_faces: np.ndarray | None = None,
                     exiting: bool = False) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per frame and point: how many outer triangles the segment anchor -> point crosses, the
    segment parameter of the crossing nearest the anchor (2.0 where none) and that triangle's row
    in outer_faces (-1); ``exiting``: only crossings out of the layer (from a face's back to its
    front).

    points, anchors : (T, N, 3) ; outer : (T, Vo, 3) with outer_faces (Fo, 3), or ``LayerFrames``
    returns (T, N) int32, (T, N) float64, (T, N) int64
    """
    points, anchors = np.asarray(points), np.asarray(anchors)
    if points.ndim != 3 or points.shape[-1] != 3:
        raise InputShapeError("points", "(T, N, 3)", points.shape)
    if anchors.shape != points.shape:
        raise InputShapeError("anchors", str(points.shape), anchors.shape)
    layer = outer if isinstance(outer, LayerFrames) else LayerFrames(outer, outer_faces)
    if layer.verts.shape[0] != points.shape[0]:
        raise InputShapeError("outer", f"({points.shape[0]}, Vo, 3)", layer.verts.shape)
    count = np.zeros(points.shape[:2], np.int32)
    first = np.full(points.shape[:2], 2.0)
    face = np.full(points.shape[:2], -1, np.int64)
    for t in range(points.shape[0]):  # one kernel call per frame, against that frame's grid
        count[t], first[t], face[t] = layer.crossings(t, anchors[t], points[t], exiting)
    return count, first, face


@dataclass(frozen=True)
class UntangleReport:
    """What ``untangle_layers`` did: per layer (innermost first; the outermost never moves) the
    vertex-frames it moved and, of those, the ones held half-way under an outer layer that lies
    within floor + gap of the skin; the largest move, metres."""

    moved: list[int]
    held: list[int]
    max_move_m: float


def _spread(sink: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """sink (T, N) spread over the mesh: each vertex takes at least SPREAD_DECAY^k times the sink of
    a vertex k edges away, k <= SPREAD_RINGS (a dent's rim slopes instead of stepping). Only the
    nonzero entries spread (a few % of the vertex-frames; compiled, ``layers_kernels.spread``)."""
    T, N = sink.shape
    src, dst = _neighbours(faces, N)
    start = np.searchsorted(src, np.arange(N + 1))
    flat = np.array(sink, np.float64).ravel()
    layers_kernels.spread(flat, N, start, dst, SPREAD_DECAY, SPREAD_RINGS)
    return flat.reshape(T, N)


@per_array
def _rim(faces: np.ndarray, n: int) -> np.ndarray:
    """(n,) bool: the vertices on the mesh's border (an edge of one face) and RIM_RINGS rings of
    neighbours in from it, once per faces array (read-only)."""
    e = np.sort(np.asarray(faces)[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1)
    keys, count = np.unique(e[:, 0].astype(np.int64) * n + e[:, 1], return_counts=True)
    out = np.zeros(n, bool)
    once = keys[count == 1]
    out[once // n] = out[once % n] = True
    src, dst = _neighbours(faces, n)
    for _ in range(RIM_RINGS):  # and the rings of vertices next to it
        grown = out.copy()
        grown[dst[out[src]]] = True
        out = grown
    out.flags.writeable = False
    return out


@per_array
def _neighbours(faces: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray]:
    """The mesh's directed edges (src, dst), sorted by src; once per faces array
    (``inference.mesh.per_array``), read-only."""
    e = np.asarray(faces)[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2)
    e = np.concatenate([e, e[:, ::-1]])
    order = np.argsort(e[:, 0], kind="stable")
    src, dst = e[order, 0], e[order, 1]
    src.flags.writeable = dst.flags.writeable = False
    return src, dst


@per_array
def _ring_matrix(faces: np.ndarray, n: int) -> sp.csr_matrix:
    """A + I: the mesh's (n, n) vertex adjacency with the diagonal, for one-ring sums; once per
    faces array (``inference.mesh.per_array``)."""
    e = np.asarray(faces)[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2)
    A = sp.coo_matrix((np.ones(len(e) * 2), (np.r_[e[:, 0], e[:, 1]], np.r_[e[:, 1], e[:, 0]])), shape=(n, n)).tocsr()
    return A + sp.identity(n, format="csr")


def anchor_normals(body: np.ndarray, body_faces: np.ndarray, anchors: np.ndarray) -> np.ndarray:
    """Unit area-weighted normals of the posed body at the anchor vertices: (T, N, 3) float64.

    body : (T, Vb, 3) ; body_faces : (F, 3) ; anchors : (N,) vertex ids (only their faces are used;
    compiled, ``inference.mesh_kernels.normals_at``: 0.08 ms per frame of 30 where the sparse sums of
    numpy face normals took 0.33, T-shirt under jacket)
    """
    body = np.ascontiguousarray(body)
    faces = np.ascontiguousarray(body_faces, np.int64)
    ids, inverse = np.unique(anchors, return_inverse=True)
    slot = np.full(body.shape[1], -1, np.int64)
    slot[ids] = np.arange(len(ids))
    face_ids = faces_touching(faces, slot)
    n = np.empty((body.shape[0], len(ids), 3))
    mesh_kernels.normals_at(body, faces, face_ids, slot, n)
    return n[:, inverse]


@dataclass(frozen=True)
class LayerContacts:
    """Where two layers can meet, from their rest forms (once per request): for each pair i < j,
    the outer layer's vertices and the inner layer's faces within CONTACT_M of the other layer's
    vertices. Only these take part in step (a) of
    ``untangle_layers`` (outer vertices under the inner layer: the intersecting pairs); step (b),
    the order, tests every vertex against every face: restricted too, it missed 0.03 % of the
    T-shirt's vertex-frames beyond the jacket on the dance clip (heavy body, both retargeted), which
    moves the layers farther from their rest relation than CONTACT_M. Nearness is judged at
    vertices: the radius must exceed the edges (CONTACT_M is 4x a garment's)."""

    outer_vertices: dict[tuple[int, int], np.ndarray]  # (i, j): layer j's vertices on its faces, near layer i
    inner_faces: dict[tuple[int, int], np.ndarray]  # (i, j): layer i's faces with a vertex near layer j

    @classmethod
    def build(cls, rest_layers: Sequence[np.ndarray], faces: Sequence[np.ndarray], radius_m: float | None = None) -> "LayerContacts":
        """rest_layers : each (N_i, 3) the layer's rest form ; faces : each (F_i, 3)."""
        radius_m = CONTACT_M if radius_m is None else radius_m
        rest = [np.asarray(x) for x in rest_layers]
        outer_vertices, inner_faces = {}, {}
        for i in range(len(rest)):
            for j in range(i + 1, len(rest)):
                near_j = near(rest[i], rest[j], radius_m)  # layer j near layer i (inference.nearness: a grid search)
                on_face = np.zeros(len(near_j), bool)
                on_face[np.asarray(faces[j]).ravel()] = True
                outer_vertices[i, j] = np.flatnonzero(near_j & on_face)
                near_i = near(rest[j], rest[i], radius_m)
                inner_faces[i, j] = np.flatnonzero(near_i[np.asarray(faces[i])].any(1))
        return cls(outer_vertices, inner_faces)

    @classmethod
    def kept(cls, rest_layers: Sequence[np.ndarray], faces: Sequence[np.ndarray], radius_m: float | None = None) -> "LayerContacts":
        """``build`` kept under the contents of the rest forms, the identities of the faces arrays
        (a garment's, never changed in place; the entry holds them, so their ids stay theirs) and
        the radius (default CONTACT_M)."""
        radius_m = CONTACT_M if radius_m is None else float(radius_m)

        def build():
            contacts = cls.build(rest_layers, faces, radius_m)
            for a in (*contacts.outer_vertices.values(), *contacts.inner_faces.values()):
                a.flags.writeable = False  # shared by the requests that hit the entry
            return tuple(faces), contacts

        return _kept(("contacts", tuple(content_key(x) for x in rest_layers), tuple(id(f) for f in faces), radius_m), build)[1]

    @classmethod
    def everywhere(cls, layers: Sequence[np.ndarray], faces: Sequence[np.ndarray]) -> "LayerContacts":
        """Every vertex on a face and every face of each pair (no rest forms: test everything)."""
        pairs = [(i, j) for i in range(len(layers)) for j in range(i + 1, len(layers))]
        return cls({(i, j): np.unique(np.asarray(faces[j])) for i, j in pairs}, {(i, j): np.arange(len(faces[i])) for i, j in pairs})


def untangle_layers(
    layers: Sequence[np.ndarray],
    faces: Sequence[np.ndarray],
    anchors: Sequence[np.ndarray],
    body: np.ndarray,
    body_faces: np.ndarray,
    gap_m: float,
    floors_m: Sequence[float],
    contacts: LayerContacts | None = None,
    reach_m: float = SINK_REACH_M,
) -> tuple[list[np.ndarray], UntangleReport]:
    """Sink each inner layer under the layers outside it (module doc).

    layers   : each (T, N_i, 3) float32 posed garment, innermost first ; faces : each (F_i, 3)
    anchors  : each (N_i,) int, ``body_anchors`` ; body : (T, Vb, 3) the posed body, body_faces (F, 3)
    gap_m    : clearance kept under an outer layer ; floors_m : each layer's least height over the
               skin at its anchors (its body margin)
    contacts : where each pair of layers can meet (``LayerContacts.build``); None: everywhere
    reach_m  : how far past an outer vertex an inner layer is looked for (step (a))
    returns the layers (the outermost unchanged) and an ``UntangleReport``
    """
    if not (len(layers) == len(faces) == len(anchors) == len(floors_m)):
        raise InputShapeError("layers", f"{len(layers)} layers with faces, anchors and floors", (len(faces), len(anchors), len(floors_m)))
    body = np.asarray(body)
    out = [np.asarray(p, np.float32) for p in layers]
    contacts = contacts or LayerContacts.everywhere(out, faces)
    moved, held, max_move = [0] * len(out), [0] * len(out), 0.0
    for i in range(len(out) - 2, -1, -1):  # outside in: each layer under those already placed
        p = np.ascontiguousarray(out[i], np.float64)  # C order, whatever the stage before left: the kernels' layout
        T, N = p.shape[:2]
        a, seg, L = np.empty_like(p), np.empty_like(p), np.empty((T, N))
        # the posed anchors a (T, N, 3), seg = p - a and L = |seg| (compiled)
        layers_kernels.anchor_segments(p, np.ascontiguousarray(body), np.ascontiguousarray(anchors[i], np.int64), a, seg, L)
        sink = np.zeros((T, N))
        t_hit = np.full((T, N), 2.0)
        # (b)'s segments reach the gap past the vertex: one under an outer layer by less than the
        # gap sinks too, to the gap under it (L_reach (1 - t) = L + ext - the crossing's distance)
        n = anchor_normals(body, body_faces, anchors[i])
        # the gap is a height over the skin, as the floors are: gap / cos along a segment at an
        # angle to the skin's normal (at least MIN_SINK_COS)
        ext = gap_m / np.maximum(np.einsum("tnc,tnc->tn", seg, n) / np.maximum(L, 1e-12), MIN_SINK_COS)
        L_reach = L + ext
        past = p + seg * (ext / np.maximum(L, 1e-12))[..., None]
        grids = {}
        for j in range(i + 1, len(out)):
            # (a) the outer layer's vertices with this layer just outside them: the corners of the
            # inner face their ray leaves through sink by its depth there plus the gap (none where
            # the two layers never come near each other)
            ov, rows = contacts.outer_vertices[i, j], contacts.inner_faces[i, j]
            if len(ov) and len(rows):
                o = np.ascontiguousarray(out[j][:, ov], np.float64)
                ahead = np.empty_like(o)  # o + reach along its unit anchor ray (compiled)
                ob = np.ascontiguousarray(body[:, anchors[j][ov]])
                layers_kernels.ray_starts(o, ob, float(reach_m), ahead)
                far = max(float(reach_m), RIM_REACH_M)
                rim = np.flatnonzero(_rim(faces[j], out[j].shape[1])[ov]) if far > reach_m else np.zeros(0, np.int64)
                if len(rim):  # near the outer layer's rim: an inner layer bloused out over it is looked for farther
                    ahead_rim = np.empty_like(o[:, rim])
                    layers_kernels.ray_starts(np.ascontiguousarray(o[:, rim]), np.ascontiguousarray(ob[:, rim]), far, ahead_rim)
                    ahead[:, rim] = ahead_rim
                length = np.full(len(ov), float(reach_m))
                length[rim] = far
                _, t_o, f_o = anchor_crossings(ahead, o, LayerFrames(p, faces[i][rows]), exiting=True)
                frame, idx = np.nonzero(t_o <= 1.0)
                corners = faces[i][rows[f_o[frame, idx]]]  # (H, 3)
                np.maximum.at(sink, (np.repeat(frame, 3), corners.ravel()), np.repeat(t_o[frame, idx] * length[idx] + gap_m, 3))
            # (b) this layer's vertices whose anchor segment crosses the outer layer: the gap under
            # it (every vertex against every face: this is the order the stage guarantees)
            grids[j] = LayerFrames(out[j], faces[j])
            t_hit = np.minimum(t_hit, anchor_crossings(past, a, grids[j])[1])
        sink = np.maximum(sink, np.where(t_hit <= 1.0, L_reach * (1.0 - t_hit), 0.0))
        if not sink.any():
            continue
        sink = _spread(sink, faces[i])
        hit = sink > 0
        # down the anchor rays averaged with their one-ring, RAY_SMOOTHING times, no deeper than the
        # floor: the height (p - a) . n over the skin drops by depth * (ray . n) (compiled)
        A = _ring_matrix(faces[i], N)
        layers_kernels.sink_along_rays(p, seg, L, sink, np.ascontiguousarray(n), A.indptr, A.indices, A.data, RAY_SMOOTHING,
                                       float(floors_m[i]), MIN_SINK_COS)
        # (c) a moved vertex still beyond an outer layer: back along its own anchor segment, to
        # the gap under it, or (an outer layer within floor + gap of the skin) half-way to it
        frame, idx = np.nonzero(hit)
        t_c = np.full(len(frame), 2.0)
        bounds = np.searchsorted(frame, np.arange(T + 1))
        for t in range(T):
            r = slice(bounds[t], bounds[t + 1])
            for grid in grids.values():
                t_c[r] = np.minimum(t_c[r], grid.crossings(t, a[t, idx[r]], p[t, idx[r]])[1])
        left = t_c <= 1.0
        if left.any():
            f, k = frame[left], idx[left]
            s = p[f, k] - a[f, k]
            Ls = np.linalg.norm(s, axis=-1)
            reach = t_c[left] * Ls
            up = np.maximum((s * n[f, k]).sum(-1), 1e-9) / np.maximum(Ls, 1e-12)  # height per metre along it
            d = np.maximum(reach - gap_m, np.minimum(floors_m[i] / up, 0.5 * reach))
            p[f, k] = a[f, k] + s * (d / np.maximum(Ls, 1e-12))[:, None]
            held[i] = int((reach - gap_m < floors_m[i] / up).sum())
        out[i] = p.astype(np.float32)
        count, longest = layers_kernels.moves(out[i], np.ascontiguousarray(layers[i]))
        moved[i] = int(count)
        max_move = max(max_move, float(longest))
    return out, UntangleReport(moved, held, max_move)


def warm_up() -> None:
    """Compile the crossing kernels (or load them from numba's cache) on a tetrahedron, through the
    same conversions as a request, so that no outfit pays the seconds of a first compilation."""
    tet = np.array([[[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]]], np.float32)
    faces = np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]])
    anchor_crossings(np.full((1, 1, 3), 0.1, np.float32), np.full((1, 1, 3), 2.0, np.float32), LayerFrames(tet, faces), exiting=True)
    anchor_normals(tet, faces.astype(np.int32), np.arange(4))
    # the sinking's kernels, with the layouts a request gives them (float64 frames, scipy's CSR)
    p = tet.astype(np.float64)
    seg, L = np.empty_like(p), np.empty(p.shape[:2])
    ids = np.arange(4, dtype=np.int64)
    layers_kernels.anchor_segments(p, tet, ids, np.empty_like(p), seg, L)
    ids.flags.writeable = False  # a static garment's anchors are kept per body, read-only (``kept_anchors``)
    layers_kernels.anchor_segments(p, tet, ids, np.empty_like(p), seg, L)
    layers_kernels.moves(tet, tet)
    layers_kernels.ray_starts(p, tet, 0.02, np.empty_like(p))  # the outer vertices' rays (float32 anchors)
    A = _ring_matrix(faces, 4)
    layers_kernels.sink_along_rays(p, seg, L, _spread(np.ones((1, 4)), faces), np.ascontiguousarray(seg), A.indptr, A.indices, A.data,
                                   RAY_SMOOTHING, 0.002, MIN_SINK_COS)
    _spread(np.ones((1, 4)), faces.astype(np.int32))  # a garment's faces are int32 (its neighbours too)
    # and the final stage's crossings of the faces it moved (``inference.repair._sink_under_moved``)
    first_crossings(np.full((1, 3), 0.1), np.full((1, 3), 2.0), tet[0].astype(np.float64), faces.astype(np.int64), 0.5, False)
